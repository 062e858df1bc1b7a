"""Commands over the database: ``assets``, ``inspections``, ``db`` (the exports are in
:mod:`pipescan.cli.export`)."""

from __future__ import annotations

from typing import Annotated

import typer

from pipescan.cli._app import (
    DbOption,
    _db_url,
    _fail,
    _stored_db_url,
    app,
    db_app,
)
from pipescan.core.errors import PipescanError
from pipescan.core.sanitize import escape_control, strip_credentials
from pipescan.core.wording import plural

AssetOption = Annotated[str | None, typer.Option(help="Only this asset.")]


@app.command()
def assets(db: DbOption = None) -> None:
    """List the pipe assets in the database."""
    from pipescan.cli.exchange import gis_names, pipe_label
    from pipescan.storage.database.db import connect
    from pipescan.storage.database.repository import list_assets

    try:
        engine = connect(_stored_db_url(db))
        try:
            rows = list_assets(engine)
            names = gis_names(engine)
        finally:
            engine.dispose()
    except PipescanError as exc:
        _fail(exc)
    if not rows:
        typer.echo("no assets yet: run `pipescan inspect ARCHIVE` first")
        return
    typer.echo(
        f"{'asset':24} {'upstream':>10}    {'downstream':10} {'size':8} {'shape':10} "
        f"{'material':10} inspections"
    )
    for a in rows:
        last = a.last_inspected_at.date().isoformat() if a.last_inspected_at else "-"
        size = f"DN {1000 * a.nominal_diameter_m:.0f}" if a.nominal_diameter_m else "DN ?"
        typer.echo(
            f"{escape_control(pipe_label(a.asset_id, names)):24} "
            f"{escape_control(a.upstream_node or '-'):>10} -> "
            f"{escape_control(a.downstream_node or '-'):10} "
            f"{size:8} {a.pipe_shape:10} {escape_control(a.material or '-'):10} "
            f"{plural(a.inspection_count, 'inspection')}, last {last}"
        )


@app.command()
def inspections(
    asset: AssetOption = None,
    db: DbOption = None,
) -> None:
    """List stored inspections: measured sections of all, peak blockage, status, archive."""
    from pipescan.cli.exchange import gis_names, pipe_label
    from pipescan.storage.database.db import connect
    from pipescan.storage.database.repository import get_asset, list_inspections

    try:
        engine = connect(_stored_db_url(db))
        try:
            if asset is not None:
                get_asset(engine, asset)
            rows = list_inspections(engine, asset_id=asset)
            names = gis_names(engine, sorted({r.asset_id for r in rows}))
        finally:
            engine.dispose()
    except PipescanError as exc:
        _fail(exc)
    if not rows:
        typer.echo("no inspections yet: run `pipescan inspect ARCHIVE` first")
        return
    typer.echo(
        f"{'id':>6}  {'asset':24} {'inspected':26} {'measured':>11}  {'peak':>7}  "
        f"{'status':10} archive"
    )
    for r in rows:
        peak = "-" if r.peak_blockage_ratio is None else f"{100 * r.peak_blockage_ratio:.1f} %"
        # Rows stored before credentials were stripped, or ids with control characters,
        # still print safely.
        typer.echo(
            f"{r.id:6}  {escape_control(pipe_label(r.asset_id, names)):24} "
            f"{r.inspected_at.isoformat():26} "
            f"{f'{r.measured_section_count}/{r.section_count}':>11}  {peak:>7}  "
            f"{r.status:10} {escape_control(strip_credentials(r.archive_uri))}"
        )


@db_app.command("upgrade")
def db_upgrade(
    db: DbOption = None,
    revision: Annotated[
        str, typer.Option(help="Target revision: head, a revision id, or a step such as +1.")
    ] = "head",
) -> None:
    """Migrate the database schema (SQLite files are migrated automatically on first use)."""
    from pipescan.storage.database.db import create_engine_for, current_revision, upgrade

    try:
        engine = create_engine_for(_db_url(db))
        try:
            before = current_revision(engine)
            upgrade(engine, revision)
            after = current_revision(engine)
        finally:
            engine.dispose()
    except PipescanError as exc:
        _fail(exc)
        return
    if before == after:
        typer.echo(f"database already at revision {after}")
    else:
        from pipescan.flows.database import migration_steps

        typer.echo(f"database migrated from {before or 'empty'} to revision {after}:")
        for step in migration_steps(before, after):
            typer.echo(f"  {step}")


@db_app.command("current")
def db_current(db: DbOption = None) -> None:
    """Show the database's schema revision and the newest one this pipescan knows."""
    from pipescan.storage.database.db import create_engine_for, current_revision, head_revision

    try:
        engine = create_engine_for(_db_url(db))
        try:
            current = current_revision(engine)
        finally:
            engine.dispose()
    except PipescanError as exc:
        _fail(exc)
        return
    head = head_revision()
    state = "up to date" if current == head else "run `pipescan db upgrade`"
    typer.echo(f"revision {current or 'none (empty database)'}; newest {head}: {state}")
