"""Commands that run over a whole network: ``inspect-network`` and ``deploy``."""

from __future__ import annotations

import dataclasses
import json
import logging
import os
from pathlib import Path
from typing import Annotated

import typer

from pipescan.cli._app import (
    ContourOption,
    DbOption,
    RegistrationOption,
    _db_url,
    _fail,
    _settings,
    app,
)
from pipescan.core.errors import PipescanError

DaskOption = Annotated[
    str | None,
    typer.Option(
        "--dask",
        help="Run each archive as a task on the Dask cluster whose scheduler is at this "
        "address, e.g. tcp://host:8786 (env PIPESCAN_DASK_ADDRESS; default: this machine).",
    ),
]
ConcurrencyOption = Annotated[
    int | None,
    typer.Option(
        min=1,
        help="Archives processed at the same time (env PIPESCAN_NETWORK_CONCURRENCY; "
        "default 2, or with --dask the cluster's worker threads).",
    ),
]


@app.command("inspect-network")
def inspect_network_command(
    store: Annotated[
        str,
        typer.Argument(
            help="Folder or fsspec URL (s3://...) holding the archives: folders with an "
            "inspection.toml, or .zip/.tar/.tar.gz files, at any depth."
        ),
    ],
    db: DbOption = None,
    dask: DaskOption = None,
    concurrency: ConcurrencyOption = None,
    workers: Annotated[
        int | None,
        typer.Option(min=1, help="Threads per archive for its chunk and window tasks (default 2)."),
    ] = None,
    reports: Annotated[
        Path | None, typer.Option(help="Also write each inspection's PDF report into this folder.")
    ] = None,
    network_report: Annotated[
        Path | None,
        typer.Option(help="Where to write the network report (default in reports/)."),
    ] = None,
    no_network_report: Annotated[
        bool, typer.Option("--no-network-report", help="Do not write the network report.")
    ] = False,
    force: Annotated[
        bool,
        typer.Option(
            "--force",
            help="Process every archive again, even those already stored with the same content "
            "and parameters (each inspection is still stored once).",
        ),
    ] = False,
    as_json: Annotated[
        bool, typer.Option("--json", help="Print a machine-readable summary.")
    ] = False,
    contour: ContourOption = None,
    registration: RegistrationOption = None,
) -> None:
    """Inspect every archive of a store: one sub-flow per archive, a few at a time.

    Archives already stored with the same content and parameters are reused, so a run that
    was interrupted can simply be started again: it finishes the rest.

    One bad archive fails alone. Exit code 1 when an archive failed, 2 when the run could not
    start.
    """
    from pipescan.cli.scan import _inspection_params
    from pipescan.flows.network import format_network_summary, inspect_network

    _keep_failed_runs_off_the_console()
    try:
        summary = inspect_network(
            store=store,
            database_url=_db_url(db),
            params=_inspection_params(contour, registration),
            concurrency=concurrency,
            dask_address=dask,
            workers=workers,
            reports_dir=str(reports) if reports else None,
            network_report_path=str(network_report) if network_report else None,
            write_network_report=not no_network_report,
            reuse_stored=not force,
        )
    except (PipescanError, ValueError) as exc:
        _fail(exc)
    if as_json:
        payload = dataclasses.asdict(summary)
        payload["failures"] = [dataclasses.asdict(o) for o in summary.failures]
        typer.echo(json.dumps(payload, indent=2, default=str))
    else:
        for line in format_network_summary(summary):
            typer.echo(line)
    if summary.failures:
        raise typer.Exit(code=1)


class _NoRunFailures(logging.Filter):
    """Drops Prefect's own run-failure records (with their tracebacks) from the console: the
    progress lines and the summary report each failed archive in one line. They still reach
    the Prefect API and its UI."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not record.name.startswith(("prefect.flow_runs", "prefect.task_runs"))


def _keep_failed_runs_off_the_console() -> None:
    if os.environ.get("PREFECT_LOGGING_LEVEL") == "INFO":  # --verbose: show everything
        return
    for handler in logging.getLogger().handlers:
        if type(handler).__name__ == "PrefectConsoleHandler":
            handler.addFilter(_NoRunFailures())


@app.command()
def deploy(
    store: Annotated[
        str, typer.Option(help="The store the scheduled runs inspect (folder or fsspec URL).")
    ],
    cron: Annotated[
        str, typer.Option(help='When to run, as a cron line, e.g. "0 2 * * *" (02:00 daily).')
    ],
    name: Annotated[str, typer.Option(help="The deployment's name.")] = "network-nightly",
    pool: Annotated[
        str, typer.Option(help="The Prefect work pool (a process pool; created if missing).")
    ] = "pipescan",
    timezone: Annotated[str, typer.Option(help="Time zone of the cron line (IANA).")] = "UTC",
    db: DbOption = None,
    dask: DaskOption = None,
    concurrency: ConcurrencyOption = None,
    network_report: Annotated[
        Path | None,
        typer.Option(help="Where each run writes the network report (default in reports/)."),
    ] = None,
    paused: Annotated[bool, typer.Option(help="Create the schedule paused.")] = False,
) -> None:
    """Create (or update) a Prefect deployment that runs inspect-network on a schedule.

    Needs a Prefect server: 'prefect server start', then PREFECT_API_URL=http://HOST:4200/api.

    A worker runs the scheduled runs: 'prefect worker start --pool pipescan'.
    """
    from pipescan.flows.deploy import deploy_network_inspection

    # The database and where files go are fixed now, as absolute paths: a process worker runs
    # each flow run in a temporary folder, where relative defaults would be lost.
    settings = _settings()
    parameters: dict = {
        "database_url": _db_url(db),
        "work_dir": str(settings.work_dir),
        "network_report_path": str(network_report or settings.reports_dir / "network-report.pdf"),
    }
    if dask:
        parameters["dask_address"] = dask
    if concurrency:
        parameters["concurrency"] = concurrency
    try:
        info = deploy_network_inspection(
            store,
            cron,
            name=name,
            work_pool=pool,
            timezone=timezone,
            parameters=parameters,
            paused=paused,
        )
    except (PipescanError, ValueError) as exc:
        _fail(exc)
    typer.echo(
        f"deployment {info.flow_name}/{info.name} ({info.deployment_id}) on {info.api_url}\n"
        f"  runs inspect-network over {info.parameters['store']}\n"
        f"  schedule: cron {info.cron!r} ({info.timezone}){' PAUSED' if paused else ''}\n"
        f"  work pool: {info.work_pool}; start a worker with:\n"
        f"    prefect worker start --pool {info.work_pool}\n"
        f"  run it now with:\n"
        f"    prefect deployment run '{info.flow_name}/{info.name}'"
    )
