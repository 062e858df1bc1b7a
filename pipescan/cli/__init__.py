"""The ``pipescan`` command line. It reads settings and calls flows; nothing below it does.

The verbs ``simulate``, ``inspect``, ``export``, ``report`` and ``demo`` are a contract used by
other tools: their names, options and ``--json`` output stay stable. Each command module
registers its commands on the shared ``app`` when imported.
"""

from pipescan.cli import scan  # noqa: I001  (scan commands list first in --help)
from pipescan.cli import data, exchange, export, network, reports, serve, trends
from pipescan.cli._app import app

__all__ = ["app", "data", "exchange", "export", "network", "reports", "scan", "serve", "trends"]
