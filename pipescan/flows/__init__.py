"""Prefect flows. Importing the package guards the Prefect API server a flow may start: it
stops with this process, and servers that killed runs left are stopped
(:func:`pipescan.flows.housekeeping.guard_ephemeral_server`)."""

from pipescan.flows.housekeeping import guard_ephemeral_server

guard_ephemeral_server()
