"""Read a network's pipe layer (GeoPackage, Shapefile, GeoJSON, any vector format GDAL reads)
for ``pipescan network import``.

Every pipe is one line feature with a unique id. The reader checks what the import relies on
and refuses anything else with a :class:`~pipescan.core.errors.LayerError` naming the file,
the field and the feature:

- the named fields exist (the id field, and the asset and node fields when asked for);
- every id is present, printable, at most 64 characters, and unique;
- every geometry is one line (a LineString, or a MultiLineString of one part) of finite
  coordinates and non-zero length;
- the layer has a CRS, and not a geographic one (lengths must be metres, not degrees).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pipescan.core.errors import LayerError
from pipescan.core.network import LayerPipe, NetworkLayer, PipeLine

__all__ = ["MAX_COORDINATE", "MAX_ID_CHARS", "read_network_layer"]

MAX_ID_CHARS = 64
"""Longest pipe id or node name (the limit on names in ``inspection.toml``)."""

MAX_COORDINATE = 1.0e8
"""Largest coordinate accepted, in the CRS's units (as for node positions in the metadata)."""

# Geographic CRSs (degrees) that pipe layers are most often found in by mistake; WKT of any
# geographic CRS is recognised by its first keyword.
_GEOGRAPHIC_CODES = {"EPSG:4326", "EPSG:4258", "EPSG:4269", "EPSG:4283", "EPSG:4167", "OGC:CRS84"}


def read_network_layer(
    path: Path,
    *,
    id_field: str,
    asset_field: str | None = None,
    from_field: str | None = None,
    to_field: str | None = None,
    layer: str | None = None,
) -> NetworkLayer:
    """Read and check a network's pipe layer.

    Parameters
    ----------
    path
        The file (any vector format GDAL reads).
    id_field
        The field holding each pipe's GIS id.
    asset_field
        A field holding the pipescan asset id of each pipe; by default the GIS id is the
        asset id.
    from_field, to_field
        Fields holding the names of the nodes at the line's first and last vertex; they
        match pipes to assets by their nodes and orient the lines. Given together or not at all.
    layer
        The layer's name, for a file with several layers.

    Returns
    -------
    NetworkLayer
        The pipes in the layer's order, with their lines as digitised.

    Raises
    ------
    LayerError
        Anything listed in the module's docstring.
    """
    import pyogrio
    import shapely
    from pyogrio.errors import DataLayerError, DataSourceError

    where = str(path)
    if (from_field is None) != (to_field is None):
        raise LayerError(
            "node fields are given as a pair",
            file=where,
            field="--from-node-field" if from_field is None else "--to-node-field",
            hint="give both --from-node-field and --to-node-field, or neither",
        )
    try:
        layer = layer if layer is not None else _only_line_layer(pyogrio.list_layers(path), where)
        info = pyogrio.read_info(path, layer=layer)
    except (DataSourceError, DataLayerError, OSError) as exc:
        raise LayerError(
            f"cannot read the layer: {_first_line(exc)}",
            file=where,
            hint="give a GeoPackage, Shapefile or GeoJSON file (and --layer for one of several)",
        ) from exc
    source = f"{path.name}, layer {info.get('layer_name') or layer or path.stem}"
    fields = [str(f) for f in info["fields"]]
    wanted = [f for f in (id_field, asset_field, from_field, to_field) if f is not None]
    for name in wanted:
        if name not in fields:
            raise LayerError(
                f"the layer has no field {name!r}",
                file=where,
                field=name,
                hint=f"its fields are: {', '.join(fields) or 'none'}",
            )
    crs = info.get("crs")
    if not crs:
        raise LayerError(
            "the layer has no coordinate reference system",
            file=where,
            field="crs",
            hint="assign the network's CRS in your GIS and export the layer again",
        )
    if _is_geographic(crs):
        raise LayerError(
            f"the layer is in a geographic CRS ({_short(crs)}): its lengths would be degrees",
            file=where,
            field="crs",
            hint="reproject the layer to the network's projected CRS (metres) first",
        )
    columns = list(dict.fromkeys(wanted))
    _, _, geometry, values = pyogrio.raw.read(path, layer=layer, columns=columns)
    by_name = dict(zip(columns, values, strict=True))

    ids = [_text(v, i, id_field, where, required=True) for i, v in enumerate(by_name[id_field])]
    if (twice := _first_repeat(ids)) is not None:
        gis_id, first, again = twice
        raise LayerError(
            f"id {gis_id!r} is on feature {first} and on feature {again}",
            file=where,
            field=id_field,
            hint="every pipe needs its own id: choose the layer's unique id field",
        )
    refs = (
        ids
        if asset_field is None
        else [
            _text(v, i, asset_field, where, required=True)
            for i, v in enumerate(by_name[asset_field])
        ]
    )
    if (twice := _first_repeat(refs)) is not None:
        ref, first, again = twice
        raise LayerError(
            f"asset id {ref!r} is on feature {first} and on feature {again}",
            file=where,
            field=asset_field,
            hint="each asset can be one pipe of the layer only",
        )
    froms = _optional_texts(by_name, from_field, where, len(ids))
    tos = _optional_texts(by_name, to_field, where, len(ids))

    pipes = []
    for i, wkb in enumerate(geometry):
        line = _line(shapely, wkb, i, where, str(ids[i]))
        pipes.append(
            LayerPipe(
                gis_id=str(ids[i]),
                asset_ref=str(refs[i]),
                from_node=froms[i],
                to_node=tos[i],
                line=line,
            )
        )
    if not pipes:
        raise LayerError("the layer has no features", file=where, hint="export the pipes again")
    if _looks_like_degrees([p.line for p in pipes]):
        raise LayerError(
            "every coordinate is within ±180/±90 and every pipe is shorter than 0.1 units: "
            "the layer looks like degrees",
            file=where,
            field="crs",
            hint="reproject the layer to the network's projected CRS (metres) first",
        )
    return NetworkLayer(pipes=tuple(pipes), crs=str(crs), source=source)


def _only_line_layer(layers: Any, where: str) -> str:
    names = [str(name) for name, _ in layers]
    lines = [str(name) for name, kind in layers if kind and "LineString" in str(kind)]
    if len(names) == 1:
        return names[0]
    if len(lines) == 1:
        return lines[0]
    raise LayerError(
        f"the file has {len(names)} layers" + (f", {len(lines)} of lines" if lines else ""),
        file=where,
        field="layer",
        hint=f"choose one with --layer: {', '.join(names) or 'none'}",
    )


def _first_line(exc: Exception) -> str:
    return str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__


def _short(text: str, limit: int = 60) -> str:
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _is_geographic(crs: str) -> bool:
    head = crs.strip().upper()
    return head in _GEOGRAPHIC_CODES or head.startswith(("GEOGCS", "GEOGCRS", "GEODCRS"))


def _text(value: Any, index: int, field: str | None, where: str, *, required: bool) -> str | None:
    """A text cell: an integer-valued number becomes its digits; blank is None."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        text = ""
    elif isinstance(value, float) and value.is_integer():
        text = str(int(value))
    else:
        text = str(value).strip()
    if not text:
        if required:
            raise LayerError(
                f"feature {index} has no value",
                file=where,
                field=field,
                hint="every pipe needs one; fill it in the GIS",
            )
        return None
    if len(text) > MAX_ID_CHARS or not text.isprintable():
        raise LayerError(
            f"feature {index}: {_short(repr(text))} is not 1-{MAX_ID_CHARS} printable characters",
            file=where,
            field=field,
        )
    return text


def _first_repeat(values: list[Any]) -> tuple[Any, int, int] | None:
    """The first value that stands on two features, with both feature indices; None when
    every value is unique."""
    first_seen: dict[Any, int] = {}
    for i, value in enumerate(values):
        if value in first_seen:
            return value, first_seen[value], i
        first_seen[value] = i
    return None


def _optional_texts(
    values: dict[str, Any], field: str | None, where: str, count: int
) -> list[str | None]:
    if field is None:
        return [None] * count
    return [_text(v, i, field, where, required=False) for i, v in enumerate(values[field])]


def _line(shapely: Any, wkb: Any, index: int, where: str, gis_id: str) -> PipeLine:
    def refuse(reason: str) -> LayerError:
        return LayerError(
            f"feature {index} ({gis_id}): {reason}",
            file=where,
            field="geometry",
            hint="each pipe must be one line from node to node",
        )

    if wkb is None:
        raise refuse("has no geometry")
    geom = shapely.from_wkb(wkb)
    if geom.geom_type == "MultiLineString" and len(geom.geoms) == 1:
        geom = geom.geoms[0]
    if geom.geom_type != "LineString":
        parts = f" of {len(geom.geoms)} parts" if hasattr(geom, "geoms") else ""
        raise refuse(f"is a {geom.geom_type}{parts}, not one line")
    coords = np.asarray(shapely.get_coordinates(geom, include_z=geom.has_z), dtype=np.float64)
    if not np.isfinite(coords).all() or (np.abs(coords) > MAX_COORDINATE).any():
        raise refuse(f"has coordinates that are not finite or beyond {MAX_COORDINATE:g}")
    try:
        return PipeLine(coords)
    except ValueError as exc:
        raise refuse(str(exc)) from exc


def _looks_like_degrees(lines: Sequence[PipeLine]) -> bool:
    for line in lines:
        xy = line.coords[:, :2]
        if (np.abs(xy[:, 0]) > 180).any() or (np.abs(xy[:, 1]) > 90).any():
            return False
        if np.linalg.norm(np.diff(xy, axis=0), axis=1).sum() >= 0.1:
            return False
    return True
