"""Cleaning up after runs that were killed: stale scratch directories and the Prefect API
server a killed run had started.

A run killed with ``kill -9`` leaves its scratch directory, and, when it ran on Prefect's
ephemeral API, the API server process that Prefect started for it (a child of the run's
process, which outlives it). The next run sweeps both, safely: only directories that carry
pipescan's run marker, and only server processes that the marker recorded, checked again by
id, start time and command line before they are stopped.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import psutil

from pipescan.storage.scratch import ProcessRef, create_run_dir, sweep_stale_runs

log = logging.getLogger("pipescan")

PREFECT_SERVER_APP = "prefect.server.api.server:create_app"
"""What the command line of the API server Prefect starts for an ephemeral run holds."""

_STOP_TIMEOUT_S = 5.0


def _is_prefect_server(proc: psutil.Process) -> bool:
    try:
        return PREFECT_SERVER_APP in proc.cmdline()
    except psutil.Error:
        return False


def prefect_servers_started_here() -> list[ProcessRef]:
    """The Prefect API servers this process started (its children running one)."""
    try:
        children = psutil.Process(os.getpid()).children()
    except psutil.Error:
        return []
    refs = []
    for child in children:
        if _is_prefect_server(child):
            try:
                refs.append(ProcessRef(child.pid, child.create_time()))
            except psutil.Error:
                continue
    return refs


def stop_orphaned_server(ref: ProcessRef) -> bool:
    """Stop a Prefect API server that a killed run had started; True if one was stopped.

    The process must still be that very process (id and start time) and still run a Prefect
    server; anything else is left alone.
    """
    if not ref.is_running():
        return False
    try:
        proc = psutil.Process(ref.pid)
        if not _is_prefect_server(proc):
            return False
        proc.terminate()
        try:
            proc.wait(_STOP_TIMEOUT_S)
        except psutil.TimeoutExpired:
            proc.kill()
            proc.wait(_STOP_TIMEOUT_S)
    except psutil.Error:
        return False
    log.info("stopped the Prefect API server (process %d) of a run that was killed", ref.pid)
    return True


def start_run_dir(work_dir: Path) -> Path:
    """Sweep what killed runs left in ``work_dir``, then create this run's scratch
    directory, recording the Prefect API server this process started (if any)."""
    swept = sweep_stale_runs(work_dir)
    for orphan in swept.orphans:
        stop_orphaned_server(orphan)
    return create_run_dir(work_dir, helpers=prefect_servers_started_here())
