"""Commands that render reports: ``report``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from pipescan.cli._app import DbOption, _db_url, _fail, app
from pipescan.core.errors import PipescanError


@app.command()
def report(
    inspection: Annotated[int, typer.Option("--inspection", help="Inspection id.")],
    output: Annotated[Path, typer.Option("-o", "--output", help="PDF file to write.")],
    db: DbOption = None,
) -> None:
    """Render the PDF condition report of a stored inspection."""
    from pipescan.reports.render import render_pdf
    from pipescan.tasks.reporting import load_report_input

    try:
        path = render_pdf(load_report_input(_db_url(db), inspection), output)
    except PipescanError as exc:
        _fail(exc)
    typer.echo(f"report written to {path}")
