"""``pipescan runs``: what became of the recent network runs, at a glance."""

from __future__ import annotations

import dataclasses
import json
from typing import Annotated

import typer

from pipescan.cli._app import DbOption, _fail, app
from pipescan.core.errors import PipescanError
from pipescan.core.sanitize import escape_control


def _when(value) -> str:
    return "-" if value is None else value.strftime("%Y-%m-%d %H:%M:%S")


def _took(run) -> str:
    if run.started is None or run.finished is None:
        return ""
    minutes, seconds = divmod(int((run.finished - run.started).total_seconds()), 60)
    return f"{minutes} min {seconds:02d} s" if minutes else f"{seconds} s"


def _note(note) -> str:
    since = {True: " [stored since]", False: " [still not stored]", None: ""}[note.stored_since]
    return escape_control(f"{note.archive}{since}: {note.why}")


def run_lines(runs) -> list[str]:
    """The runs as a table, each followed by the archives it did not store and why."""
    header = (
        f"{'started (UTC)':19}  {'finished (UTC)':19}  {'state':9}  "
        f"{'inspected':>9} {'reused':>6} {'same':>4} {'failed':>6} {'missing':>7}  run"
    )
    lines = [header]
    for run in runs:
        c = run.counts
        state = run.state_name
        lines.append(
            f"{_when(run.started):19}  {_when(run.finished):19}  {state:9}  "
            f"{c.get('inspected', 0):>9} {c.get('reused', 0):>6} {c.get('duplicate', 0):>4} "
            f"{c.get('failed', 0):>6} {c.get('missing', 0):>7}  {run.name}"
            + (f" (attempt {run.run_count})" if run.run_count > 1 else "")
        )
        if run.source != "outcomes":
            lines.append(
                "    (did not finish: counted from its sub-flow runs, the archives it did not "
                "reach left out; "
                + (f"state: {escape_control(run.message)})" if run.message else "no message)")
            )
        elif run.state != "COMPLETED" and not (run.failed or run.missing) and run.message:
            lines.append(f"    {escape_control(run.message)}")
        lines += [f"    missing {_note(n)}" for n in run.missing]
        lines += [f"    failed  {_note(n)}" for n in run.failed]
    return lines


@app.command("runs")
def runs_command(
    limit: Annotated[int, typer.Option(min=1, help="How many recent runs to show.")] = 10,
    db: DbOption = None,
    as_json: Annotated[
        bool, typer.Option("--json", help="Print the runs as JSON (one object each).")
    ] = False,
) -> None:
    """List recent network runs: state, archives inspected, reused, failed, missing.

    Newest first, each with its start and end, and under it the archives it did not store and
    why (and whether a later run has stored them since).

    Reads Prefect's API (PREFECT_API_URL) for the runs and the database for whether an archive
    a run left out has been stored since.
    """
    import httpx

    from pipescan.flows.runs import recent_network_runs
    from pipescan.settings import database_url, get_settings, use_settings

    try:
        with use_settings(database_url=db):
            url = database_url(get_settings())
        runs = recent_network_runs(limit, database_url=url)
    except httpx.HTTPError as exc:
        _fail(
            PipescanError(
                f"Prefect's API does not answer ({type(exc).__name__}: {exc})",
                hint="set PREFECT_API_URL (and PREFECT_API_AUTH_STRING) to the server the "
                "runs ran on",
            )
        )
    except PipescanError as exc:
        _fail(exc)
    if as_json:
        typer.echo(json.dumps([dataclasses.asdict(r) for r in runs], indent=2, default=str))
        return
    if not runs:
        typer.echo("no network run on this Prefect server yet")
        return
    for line in run_lines(runs):
        typer.echo(line)
