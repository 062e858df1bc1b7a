"""The ``pipescan`` app object, shared options and helpers of the command modules."""

from __future__ import annotations

import logging
import os
import sys
from enum import StrEnum
from typing import Annotated

import typer

from pipescan.core.contour import CONTOUR_METHODS, DEFAULT_CONTOUR_METHOD

# Prefect reads its settings at import: set ours before any import of it.
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("PREFECT_LOGGING_EXTRA_LOGGERS", "pipescan")
os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
# The CLI logs its own stage lines outside flow runs too; those are not for the API.
os.environ.setdefault("PREFECT_LOGGING_TO_API_WHEN_MISSING_FLOW", "ignore")
# A bad archive is one line ("error: ..."), exit code 2; Prefect's run loggers would print the
# same error again with a traceback. The run's state in the API keeps it; --verbose shows it.
_RUN_LOGGERS = (
    "PREFECT_LOGGING_LOGGERS_PREFECT_FLOW_RUNS_LEVEL",
    "PREFECT_LOGGING_LOGGERS_PREFECT_TASK_RUNS_LEVEL",
)
for _name in _RUN_LOGGERS:
    os.environ.setdefault(_name, "CRITICAL")

app = typer.Typer(
    help="Measure the inside of underground pipes from LiDAR scans.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
export_app = typer.Typer(help="Export stored results (CSV or JSON lines).", no_args_is_help=True)
db_app = typer.Typer(help="Database schema management.", no_args_is_help=True)
app.add_typer(export_app, name="export")
app.add_typer(db_app, name="db")

DbOption = Annotated[
    str | None,
    typer.Option(
        "--db", help="Database URL [env PIPESCAN_DATABASE_URL; default sqlite:///pipescan.db]"
    ),
]

ContourOption = Annotated[
    str | None,
    typer.Option(
        help=f"Contour method: {' or '.join(CONTOUR_METHODS)} "
        f"(env PIPESCAN_CONTOUR_METHOD; default {DEFAULT_CONTOUR_METHOD})."
    ),
]


class Scenario(StrEnum):
    paper = "paper"
    clean = "clean"
    long = "long"
    ring = "ring"
    static = "static"


class ExportFormat(StrEnum):
    csv = "csv"
    jsonl = "jsonl"


def _settings():
    from pipescan.settings import get_settings

    return get_settings()


def _db_url(db: str | None) -> str:
    return db or _settings().database_url


def _setup_logging(verbose: bool) -> None:
    if verbose:
        os.environ["PREFECT_LOGGING_LEVEL"] = "INFO"
        for name in _RUN_LOGGERS:
            os.environ[name] = "INFO"
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(asctime)s  %(message)s", datefmt="%H:%M:%S"))
    logger = logging.getLogger("pipescan")
    logger.handlers[:] = [handler]
    logger.setLevel(logging.INFO)
    logger.propagate = False


def _fail(exc: Exception) -> None:
    typer.secho(f"error: {exc}", fg=typer.colors.RED, err=True)
    raise typer.Exit(code=2)


@app.callback()
def main(
    verbose: Annotated[
        bool, typer.Option("--verbose", "-v", help="Show Prefect's own logs.")
    ] = False,
) -> None:
    _setup_logging(verbose)
