"""Commands over stored results: ``export``, ``assets``, ``inspections``, ``db``."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import typer

from pipescan.cli._app import DbOption, ExportFormat, _db_url, _fail, app, db_app, export_app
from pipescan.core.errors import PipescanError


@export_app.command("sections")
def export_sections(
    asset: Annotated[str | None, typer.Option(help="Only this asset.")] = None,
    inspection: Annotated[int | None, typer.Option(help="Only this inspection id.")] = None,
    fmt: Annotated[
        ExportFormat, typer.Option("--format", help="Output format.")
    ] = ExportFormat.csv,
    output: Annotated[
        Path | None, typer.Option("-o", "--output", help="File (default stdout).")
    ] = None,
    db: DbOption = None,
) -> None:
    """One row per section, with the DESIGN.md column names."""
    from pipescan.storage import export

    fn = export.export_sections_csv if fmt == ExportFormat.csv else export.export_sections_jsonl
    _export(fn, asset, inspection, output, db)


@export_app.command("defects")
def export_defects(
    asset: Annotated[str | None, typer.Option(help="Only this asset.")] = None,
    inspection: Annotated[int | None, typer.Option(help="Only this inspection id.")] = None,
    output: Annotated[
        Path | None, typer.Option("-o", "--output", help="File (default stdout).")
    ] = None,
    db: DbOption = None,
) -> None:
    """One row per merged defect (CSV)."""
    from pipescan.storage import export

    _export(export.export_defects_csv, asset, inspection, output, db)


def _export(fn, asset, inspection, output, db) -> None:
    from pipescan.storage.db import connect

    try:
        engine = connect(_db_url(db))
        if output is None:
            n = fn(engine, sys.stdout, asset_id=asset, inspection_id=inspection)
        else:
            tmp = output.with_name(output.name + ".tmp")
            with tmp.open("w", newline="", encoding="utf-8") as fh:
                n = fn(engine, fh, asset_id=asset, inspection_id=inspection)
            tmp.replace(output)
            typer.echo(f"wrote {n} rows to {output}", err=True)
    except PipescanError as exc:
        _fail(exc)


@app.command()
def assets(db: DbOption = None) -> None:
    """List the pipe assets in the database."""
    from pipescan.storage.db import connect
    from pipescan.storage.repository import list_assets

    rows = list_assets(connect(_db_url(db)))
    if not rows:
        typer.echo("no assets yet: run `pipescan inspect ARCHIVE` first")
    for a in rows:
        last = a.last_inspected_at.date().isoformat() if a.last_inspected_at else "-"
        size = f"DN {1000 * a.nominal_diameter_m:.0f}" if a.nominal_diameter_m else "DN ?"
        typer.echo(
            f"{a.asset_id:24} {a.upstream_node or '-':>10} -> {a.downstream_node or '-':10} "
            f"{size:8} {a.inspection_count} inspections, last {last}"
        )


@app.command()
def inspections(
    asset: Annotated[str | None, typer.Option(help="Only this asset.")] = None,
    db: DbOption = None,
) -> None:
    """List stored inspections."""
    from pipescan.storage.db import connect
    from pipescan.storage.repository import list_inspections

    rows = list_inspections(connect(_db_url(db)), asset_id=asset)
    if not rows:
        typer.echo("no inspections yet")
    for r in rows:
        typer.echo(
            f"{r.id:6}  {r.asset_id:24} {r.inspected_at.isoformat():26} "
            f"{r.section_count:5} sections  {r.status:10} {r.archive_uri}"
        )


@db_app.command("upgrade")
def db_upgrade(db: DbOption = None, revision: str = "head") -> None:
    """Migrate the database schema (SQLite files are migrated automatically on first use)."""
    from pipescan.storage.db import upgrade

    upgrade(_db_url(db), revision)
    typer.echo(f"database at {revision}")
