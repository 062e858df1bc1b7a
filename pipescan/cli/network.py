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
    _fail,
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
        Path | None,
        typer.Option(
            help="Write each inspection's PDF report, and the network report, into this folder."
        ),
    ] = None,
    network_report: Annotated[
        Path | None,
        typer.Option(
            help="Where to write the network report (default: network-<date>-<run>.pdf in the "
            "--reports folder, else in PIPESCAN_REPORTS_DIR, reports/)."
        ),
    ] = None,
    database_wait_s: Annotated[
        float,
        typer.Option(
            "--wait-for-database",
            min=0,
            metavar="SECONDS",
            help="While the database does not answer at the start, try again (5, 10, 20, 40, "
            "60 s apart) for up to this long, as a scheduled run does for 300 s; for cron.",
        ),
    ] = 0,
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

    One bad archive fails alone. An archive that fails for a transient cause (the database or
    Prefect's API not answering) is tried again, with backoff, for up to 15 minutes. Exit code
    1 when an archive was not stored, 2 when the run could not start.
    """
    from pipescan.cli.scan import _inspection_params
    from pipescan.flows.network import (
        NetworkIncomplete,
        format_network_summary,
        inspect_network,
        refuse_password_in_url,
        wait_for_database,
    )
    from pipescan.settings import get_settings, use_settings

    _keep_failed_runs_off_the_console()
    try:
        refuse_password_in_url(store)
        params = _inspection_params(contour, registration)  # options first: they cost nothing
        # The database is a setting of this process, not a flow parameter (Prefect would keep
        # it, password and all, with the run). Checked here too, before a temporary Prefect
        # server is started for the run: a bad database is an error in a second or two.
        with use_settings(database_url=db):
            wait_for_database(get_settings(), database_wait_s, logging.getLogger("pipescan"))
            summary = inspect_network(
                store=store,
                params=params,
                concurrency=concurrency,
                dask_address=dask,
                workers=workers,
                reports_dir=str(reports) if reports else None,
                network_report_path=str(network_report) if network_report else None,
                write_network_report=not no_network_report,
                reuse_stored=not force,
                startup_wait_s=database_wait_s,
            )
    except NetworkIncomplete as exc:  # archives not stored: the summary says which, exit 1
        if exc.summary is None:
            _fail(exc)
        summary = exc.summary
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
    db: Annotated[
        str | None,
        typer.Option(
            "--db",
            help="The database the workers use, to check it now; it is not stored in the "
            "deployment (env PIPESCAN_DATABASE_URL; required, one way or the other).",
        ),
    ] = None,
    dask: DaskOption = None,
    concurrency: ConcurrencyOption = None,
    paused: Annotated[bool, typer.Option(help="Create the schedule paused.")] = False,
    notify: Annotated[
        str | None,
        typer.Option(
            help="A Prefect notification block, TYPE/NAME (e.g. custom-webhook/pipescan-alerts): "
            "a run that ends Failed (archives missing or failed) sends a notification."
        ),
    ] = None,
) -> None:
    """Create (or update) a Prefect deployment that runs inspect-network on a schedule, with the
    automations that recover its runs after a crash (docs/operations.md).

    Checks first that the Prefect server answers, that the store exists, and that the database
    is reachable, migrated and writable. The deployment holds neither the database URL nor any
    password: each worker reads PIPESCAN_DATABASE_URL (and PIPESCAN_REPORTS_DIR...) from its own
    environment.
    """
    from pipescan.flows.deploy import (
        CANCELLING_AFTER_S,
        MAX_ATTEMPTS,
        PLACEHOLDER_NOTE,
        RETRY_AFTER_S,
        RETRY_PARAMETER,
        SILENT_AFTER_S,
        deploy_network_inspection,
    )
    from pipescan.flows.network import absolute_location, refuse_password_in_url
    from pipescan.tasks.network import EmptyStoreError, find_archives

    parameters: dict = {}
    if dask:
        parameters["dask_address"] = dask
    if concurrency:
        parameters["concurrency"] = concurrency
    try:
        refuse_password_in_url(store)
        _deploy_database_check(db)
        try:
            found = len(find_archives(absolute_location(store)))
        except EmptyStoreError:
            found = 0
        info = deploy_network_inspection(
            store,
            cron,
            name=name,
            work_pool=pool,
            timezone=timezone,
            parameters=parameters,
            paused=paused,
            notify=notify,
        )
    except (PipescanError, ValueError, OSError) as exc:
        _fail(exc)
    full = f"{info.flow_name}/{info.name}"
    typer.echo(
        f"deployment {full} ({info.deployment_id}) on {info.api_url}\n"
        f"  runs inspect-network over {info.parameters['store']} "
        f"({found} archives there now)\n"
        f"  schedule: cron {info.cron!r} ({info.timezone}){' PAUSED' if paused else ''}\n"
        f"  recovery: a run silent for {SILENT_AFTER_S} s is marked Crashed, a crashed run is "
        f"retried after {RETRY_AFTER_S} s ({MAX_ATTEMPTS} attempts in all), a run Cancelling "
        f"for {CANCELLING_AFTER_S} s is marked Cancelled\n"
        f"    (automations {', '.join(repr(a) for a in info.automations)})\n"
        f"  alerts: {_alerts(notify)}\n"
        f"  start workers, under systemd or another supervisor, with this environment "
        f"(docs/operations.md; {PLACEHOLDER_NOTE}):\n"
        + "".join(f"    {line}\n" for line in _worker_environment(info.api_url, store, db))
        + f"    prefect worker start --pool {info.work_pool}\n"
        f"  run now:               prefect deployment run '{full}'\n"
        f"  re-inspect everything: prefect deployment run '{full}' "
        f"--param {RETRY_PARAMETER}=false"
    )
    if not found:
        typer.secho(
            f"warning: the store holds no archive yet: {info.parameters['store']}",
            fg=typer.colors.YELLOW,
            err=True,
        )


def _alerts(notify: str | None) -> str:
    """Who hears of a run that ends Failed, as far as this shell knows the workers' settings."""
    from pipescan.settings import get_settings

    ways = []
    to = get_settings().smtp_alert_to
    if to:
        ways.append(f"e-mail to {to} (PIPESCAN_SMTP_ALERT_TO, sent by the run on its worker)")
    if notify:
        ways.append(f"the notification block {notify}")
    if not ways:
        return (
            "none for a run that ends Failed (PIPESCAN_SMTP_ALERT_TO on the workers for "
            "e-mail; --notify TYPE/NAME for a webhook or Slack block)"
        )
    return "a run that ends Failed (archives missing or failed) sends " + " and ".join(ways)


def _worker_environment(api_url: str, store: str, db: str | None) -> list[str]:
    """What a worker's environment must hold, as far as this shell (and ``--db``) knows it."""
    from prefect.settings import PREFECT_API_AUTH_STRING

    from pipescan.flows.deploy import worker_environment
    from pipescan.settings import get_settings, use_settings

    auth = PREFECT_API_AUTH_STRING.value()
    if hasattr(auth, "get_secret_value"):
        auth = auth.get_secret_value()
    with use_settings(database_url=db):
        settings = get_settings()
    return worker_environment(api_url, settings, store=store, auth_string=auth or None)


def _deploy_database_check(db: str | None) -> str:
    """Check the database the workers are to use; its URL as shown (password hidden).

    Raises
    ------
    StorageError
        No database named (the implicit ./pipescan.db would be the worker's temporary
        folder), a relative SQLite path, or a database that is unreachable, not migrated or
        read-only.
    """
    from sqlalchemy.engine import make_url

    from pipescan.flows.database import is_relative_sqlite, refuse_unencoded_password
    from pipescan.settings import database_url, get_settings, use_settings
    from pipescan.storage.database.db import StorageError, check_database

    with use_settings(database_url=db):
        settings = get_settings()
        refuse_unencoded_password(settings.database_url)
        if "database_url" not in settings.model_fields_set:
            raise StorageError(
                "no database named: scheduled runs would write to a pipescan.db in the "
                "worker's temporary folder",
                field="PIPESCAN_DATABASE_URL",
                hint="pass --db URL or set PIPESCAN_DATABASE_URL: the database the workers will "
                "use is checked now, not stored; they need it in their own environment "
                "(docs/operations.md)",
            )
        url = database_url(settings)
    if is_relative_sqlite(url):
        raise StorageError(
            f"{url} is a relative SQLite path, which each worker would resolve in its own "
            "temporary folder",
            field="PIPESCAN_DATABASE_URL",
            hint="give an absolute path: sqlite:////srv/pipescan/pipescan.db",
        )
    check_database(url)
    return make_url(url).render_as_string(hide_password=True)


from pipescan.cli import runs as _runs  # noqa: E402,F401  (registers `pipescan runs` after these)
