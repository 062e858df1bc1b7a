"""The network's GIS layer: ``network import``, and how the CLI names a pipe once it is
imported (docs/exports.md). The exports are in :mod:`pipescan.cli.export`."""

from __future__ import annotations

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
