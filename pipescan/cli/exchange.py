"""Commands that hand results to asset systems and GIS: ``export isybau``, ``export gis`` and
``network import`` (docs/exports.md)."""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path
from typing import Annotated

import typer

from pipescan.cli._app import (
    HELP_MARKUP,
    DbOption,
    _db_url,
    _fail,
    _settings,
    _WholeHelpGroup,
    app,
    export_app,
    make_output_folder,
)
from pipescan.core.errors import PipescanError
from pipescan.core.sanitize import escape_control

network_app = typer.Typer(
    cls=_WholeHelpGroup,
    help="The network's geometry: import the GIS layer of its pipes.",
    no_args_is_help=True,
    rich_markup_mode=HELP_MARKUP,
)
app.add_typer(network_app, name="network")

AssetOption = Annotated[
    str | None, typer.Option(help="The pipe: its asset id (or, after an import, its GIS id).")
]
InspectionOption = Annotated[int | None, typer.Option(help="The inspection id.")]


def gis_names(engine, asset_ids=None) -> dict[str, str]:
    """Asset id to the pipe's GIS id, for the assets an imported network layer names."""
    from pipescan.storage.database.network import gis_ids

    return gis_ids(engine, asset_ids)


def pipe_label(asset_id: str, names: dict[str, str]) -> str:
    """How the CLI names a pipe: by its GIS id when a layer was imported, with the asset id
    beside it when they differ.

    >>> pipe_label("MH1-MH2", {"MH1-MH2": "SW-0042"}), pipe_label("MH1-MH2", {})
    ('SW-0042 (asset MH1-MH2)', 'MH1-MH2')
    """
    gis_id = names.get(asset_id)
    if gis_id is None or gis_id == asset_id:
        return asset_id
    return f"{gis_id} (asset {asset_id})"


class GisFormat(StrEnum):
    gpkg = "gpkg"
    geojson = "geojson"


@export_app.command("isybau")
def export_isybau_command(
    output: Annotated[Path, typer.Option("-o", "--output", help="The XML file to write.")],
    inspection: InspectionOption = None,
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
    from pipescan.storage.database.db import connect
    from pipescan.storage.database.isybau import (
        IsybauError,
        IsybauHeader,
        created_today,
        export_isybau,
    )

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
    asset: AssetOption = None,
    inspection: InspectionOption = None,
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
    from pipescan.storage.database.db import connect
    from pipescan.storage.database.gis import export_gis

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


@network_app.command("import")
def network_import(
    layer_file: Annotated[
        Path, typer.Argument(help="The pipe layer: GeoPackage, Shapefile, GeoJSON, ...")
    ],
    id_field: Annotated[str, typer.Option(help="The field with each pipe's GIS id.")],
    asset_field: Annotated[
        str | None,
        typer.Option(help="A field with pipescan's asset id of each pipe (default: the GIS id)."),
    ] = None,
    from_node_field: Annotated[
        str | None,
        typer.Option(help="The field naming the node at each line's first vertex."),
    ] = None,
    to_node_field: Annotated[
        str | None, typer.Option(help="The field naming the node at each line's last vertex.")
    ] = None,
    layer: Annotated[str | None, typer.Option(help="The layer, for a file with several.")] = None,
    db: DbOption = None,
) -> None:
    """Store the line, length and nodes of each pipe of a GIS layer.

    Imported once: later exports place defects along the lines, and reports name pipes by
    the layer's ids. A pipe stands for the asset whose id its --asset-field (or its GIS id)
    holds or, with the node fields, for the asset between its two nodes.
    """
    from pipescan.storage.database.db import connect
    from pipescan.storage.database.network import import_network_layer
    from pipescan.storage.input.network_layer import LayerLimits, read_network_layer

    try:
        network = read_network_layer(
            layer_file,
            id_field=id_field,
            asset_field=asset_field,
            from_field=from_node_field,
            to_field=to_node_field,
            layer=layer,
            limits=LayerLimits.from_settings(_settings()),
        )
        engine = connect(_db_url(db))
        try:
            result = import_network_layer(engine, network)
        finally:
            engine.dispose()
    except PipescanError as exc:
        _fail(exc)
        return
    typer.echo(
        f"imported {result.stored} pipes from {network.source} ({network.crs}); "
        f"{len(result.matched)} stored asset(s) matched"
        + (f", {result.replaced} pipe(s) replaced" if result.replaced else "")
    )
    if result.unmatched_assets:
        shown = ", ".join(escape_control(a) for a in result.unmatched_assets[:10])
        more = len(result.unmatched_assets) - 10
        typer.echo(
            f"  stored assets without a pipe in any imported layer: {shown}"
            + (f" and {more} more" if more > 0 else "")
        )
