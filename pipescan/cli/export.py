"""``pipescan export``: stored results as files for asset systems and GIS (docs/exports.md).

- ``export sections``, ``export defects``: CSV or JSON Lines (:mod:`pipescan.exports.tables`);
- ``export isybau``: ISYBAU XML 2013, validated (:mod:`pipescan.exports.isybau`);
- ``export gis``: GeoPackage or GeoJSON layers (:mod:`pipescan.exports.gis`).

Every export checks its selection first: an unknown inspection or asset is an error, not an
empty file.
"""

from __future__ import annotations

import sys
from enum import StrEnum
from pathlib import Path
from typing import Annotated

import typer

from pipescan.cli._app import (
    DbOption,
    ExportFormat,
    _db_url,
    _fail,
    _stored_db_url,
    export_app,
    make_output_folder,
)
from pipescan.cli.exchange import gis_names, pipe_label
from pipescan.core.errors import OptionError, PipescanError
from pipescan.core.sanitize import escape_control
from pipescan.core.wording import plural

AssetOption = Annotated[str | None, typer.Option(help="Only this asset.")]
InspectionOption = Annotated[int | None, typer.Option(help="Only this inspection id.")]
FormatOption = Annotated[ExportFormat, typer.Option("--format", help="Output format.")]
OutputOption = Annotated[
    Path | None, typer.Option("-o", "--output", help="File (default, or -: stdout).")
]
PipeOption = Annotated[
    str | None, typer.Option(help="The pipe: its asset id (or, after an import, its GIS id).")
]
OneInspectionOption = Annotated[int | None, typer.Option(help="The inspection id.")]


def _table_command(rows: str, doc: str) -> None:
    """Register ``export <rows>``: one table of the stored results, CSV or JSON Lines
    (:func:`pipescan.exports.tables.export_sections_csv` and its siblings)."""

    def command(
        asset: AssetOption = None,
        inspection: InspectionOption = None,
        fmt: FormatOption = ExportFormat.csv,
        output: OutputOption = None,
        db: DbOption = None,
    ) -> None:
        from pipescan.exports import tables

        _export(getattr(tables, f"export_{rows}_{fmt.value}"), asset, inspection, output, db)

    command.__doc__ = doc
    command.__name__ = f"export_{rows}"
    export_app.command(rows)(command)


_table_command("sections", "One row per section, with the column names of docs/measures.md.")
_table_command("defects", "One row per merged defect.")


def _export(fn, asset, inspection, output, db) -> None:
    from pipescan.storage.database.db import connect

    if output == Path("-"):  # the usual name for stdout, not a file called "-"
        output = None
    try:
        engine = connect(_stored_db_url(db))
        try:
            _check_selection(engine, asset, inspection)
            if output is None:
                n = fn(engine, sys.stdout, asset_id=asset, inspection_id=inspection)
            else:
                n = _write_atomically(
                    output, lambda fh: fn(engine, fh, asset_id=asset, inspection_id=inspection)
                )
        finally:
            engine.dispose()
    except PipescanError as exc:
        _fail(exc)
    if output is not None:
        typer.echo(f"wrote {plural(n, 'row')} to {output}", err=True)
    elif n == 0:
        typer.echo("no rows: the database holds no inspections yet", err=True)


def _check_selection(engine, asset: str | None, inspection: int | None) -> None:
    """An unknown inspection or asset is an error, not an empty export."""
    from pipescan.storage.database.repository import get_asset, get_inspection

    if inspection is not None:
        record = get_inspection(engine, inspection)
        if asset is not None and record.asset_id != asset:
            raise OptionError(
                f"inspection {inspection} is of asset {record.asset_id!r}, not {asset!r}",
                hint="give one of --asset and --inspection, or both of one inspection",
            )
    elif asset is not None:
        get_asset(engine, asset)


def _write_atomically(output: Path, write) -> int:
    """Write through a temporary file beside ``output`` (its folder created), renamed into
    place at the end: an interrupted export leaves no half-written file under the name."""
    from pipescan.storage.atomic import atomic_file

    try:
        output.parent.mkdir(parents=True, exist_ok=True)
        # A new file of a random name (O_EXCL, no link followed), renamed onto ``output``.
        with atomic_file(output, "w", newline="", encoding="utf-8") as fh:
            n = write(fh)
    except OSError as exc:
        raise OptionError(f"cannot write {output}: {exc.strerror or exc}") from exc
    return n


class GisFormat(StrEnum):
    gpkg = "gpkg"
    geojson = "geojson"


@export_app.command("isybau")
def export_isybau_command(
    output: Annotated[Path, typer.Option("-o", "--output", help="The XML file to write.")],
    inspection: OneInspectionOption = None,
    asset: Annotated[
        str | None, typer.Option(help="Every inspection of this asset (one pipe each).")
    ] = None,
    property_number: Annotated[
        str, typer.Option(help="ISYBAU Liegenschaftsnummer (at most 20 characters).")
    ] = "",
    property_name: Annotated[
        str, typer.Option(help="ISYBAU Liegenschaftsbezeichnung (at most 255 characters).")
    ] = "",
    db: DbOption = None,
) -> None:
    """ISYBAU XML 2013 condition data, validated against the schema before writing.

    One inspected pipe per inspection, one observation per defect whose code's use in ISYBAU
    was checked (docs/exports.md); anything else goes to the pipe's remarks, in words.
    """
    from pipescan.exports.isybau import (
        IsybauError,
        IsybauHeader,
        created_today,
        export_isybau,
    )
    from pipescan.storage.database.db import connect

    for value, limit, name in (
        (property_number, 20, "--property-number"),
        (property_name, 255, "--property-name"),
    ):
        if len(value) > limit or not value.isprintable():
            _fail(IsybauError(f"give at most {limit} printable characters", field=name))
    try:
        make_output_folder(output, "ISYBAU file", "XML")
        engine = connect(_db_url(db))
        try:
            result = export_isybau(
                engine,
                output,
                IsybauHeader(
                    created_on=created_today(),
                    property_number=property_number,
                    property_name=property_name,
                ),
                inspection_id=inspection,
                asset_id=asset,
            )
        finally:
            engine.dispose()
    except PipescanError as exc:
        _fail(exc)
        return
    ids = ", ".join(map(str, result.inspection_ids))
    typer.echo(
        f"wrote {output}: inspection {ids}, {result.observations} observations, validated "
        "against the ISYBAU XML 2013 schema",
        err=True,
    )
    if result.defects_in_remarks:
        typer.echo(
            f"  {result.defects_in_remarks} defect(s) with a code not used in ISYBAU's published "
            "example are described in the remarks (Bemerkung), not coded",
            err=True,
        )


@export_app.command("gis")
def export_gis_command(
    output: Annotated[
        Path,
        typer.Option(
            "-o",
            "--output",
            help="The GeoPackage file; for geojson a folder, which receives one file per layer.",
        ),
    ],
    fmt: Annotated[GisFormat, typer.Option("--format", help="Output format.")] = GisFormat.gpkg,
    asset: PipeOption = None,
    inspection: OneInspectionOption = None,
    sections: Annotated[
        bool, typer.Option("--sections", help="Also write a point per section.")
    ] = False,
    db: DbOption = None,
) -> None:
    """GIS layers in the network's CRS: pipes, and defects along them.

    The pipes carry their latest condition class, peak blockage and growth per year; the
    defects are line events placed by their chainage, never stretched. Without --asset or
    --inspection: the latest inspection of every pipe with a geometry.
    """
    from pipescan.exports.gis import export_gis
    from pipescan.storage.database.db import connect

    try:
        if fmt == GisFormat.gpkg:  # a geojson folder is made by the export itself
            make_output_folder(output, "GeoPackage", "GeoPackage")
        engine = connect(_db_url(db))
        try:
            result = export_gis(
                engine,
                output,
                fmt=fmt.value,  # type: ignore[arg-type]
                inspection_id=inspection,
                asset_id=asset,
                with_sections=sections,
            )
            names = gis_names(engine, sorted(result.length_notes))
        finally:
            engine.dispose()
    except PipescanError as exc:
        _fail(exc)
        return
    counts = ", ".join(f"{n} {layer}" for layer, n in result.counts.items())
    paths = ", ".join(str(p) for p in result.paths)
    typer.echo(f"wrote {paths} ({result.crs}): {counts}", err=True)
    for asset_id, note in sorted(result.length_notes.items()):
        typer.echo(f"  {escape_control(pipe_label(asset_id, names))}: {note}", err=True)
    if result.without_geometry:
        shown = ", ".join(escape_control(a) for a in result.without_geometry[:10])
        more = len(result.without_geometry) - 10
        typer.echo(
            f"  left out, without a geometry: {shown}" + (f" and {more} more" if more > 0 else ""),
            err=True,
        )
