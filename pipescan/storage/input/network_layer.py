"""Read a network's pipe layer (GeoPackage, Shapefile, GeoJSON, any vector format GDAL reads)
for ``pipescan network import``.

Every pipe is one line feature with a unique id. The reader checks what the import relies on
and refuses anything else with a :class:`~pipescan.core.errors.LayerError` naming the file,
the field and the feature:

- the named fields exist (the id field, and the asset and node fields when asked for);
- every id is present, printable, at most 64 characters, and unique;
- every geometry is one line (a LineString, or a MultiLineString of one part) of finite
  coordinates and non-zero length;
- the layer has a CRS, a projected one in metres (not degrees, not feet: lengths are
  stored as metres), looked up in the PROJ database that pyogrio ships;
- the layer stays within :class:`LayerLimits`: its bytes (on disk, declared in a zip, and
  the geometries a GeoPackage table holds, counted by SQLite before GDAL reads a row), its
  features and each line's vertices. A GeoPackage layer must be a plain table: a view or a
  generated column makes its bytes from nothing. A zip is unpacked under the byte cap first,
  into a private temporary folder, and checked the same way.
"""

from __future__ import annotations

import math
import re
import shutil
import sqlite3
import tempfile
import zipfile
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from pipescan.core.errors import LayerError
from pipescan.core.network import LayerPipe, NetworkLayer, PipeLine

__all__ = ["MAX_COORDINATE", "MAX_ID_CHARS", "LayerLimits", "read_network_layer"]

MAX_ID_CHARS = 64
"""Longest pipe id or node name (the limit on names in ``inspection.toml``)."""

MAX_COORDINATE = 1.0e8
"""Largest coordinate accepted, in the CRS's units (as for node positions in the metadata)."""


@dataclass(frozen=True)
class LayerLimits:
    """Caps on a network layer (each field is the setting of that name, ``PIPESCAN_<NAME>``).

    Attributes
    ----------
    layer_max_bytes
        Bytes of the layer: its file(s), what a zip declares it unpacks to, and the
        geometries a GeoPackage table holds.
    layer_max_features
        Features (pipes) of the layer; a city's network has tens of thousands.
    layer_max_vertices
        Vertices of one pipe's line (a pipe from manhole to manhole has a handful).
    """

    layer_max_bytes: int = 2 << 30
    layer_max_features: int = 1_000_000
    layer_max_vertices: int = 10_000

    def __post_init__(self) -> None:
        for f in fields(self):
            if not getattr(self, f.name) > 0:
                raise ValueError(f"{f.name} must be positive, got {getattr(self, f.name)!r}")

    @classmethod
    def from_settings(cls, settings: Any) -> LayerLimits:
        return cls(**{f.name: getattr(settings, f.name) for f in fields(cls)})


def _over(cap: str, limits: LayerLimits, what: str, where: str, field: str) -> LayerError:
    return LayerError(
        f"{what}, over the limit of {getattr(limits, cap):,} ({cap})",
        file=where,
        field=field,
        hint=f"if the layer is genuine, raise the limit: set PIPESCAN_{cap.upper()}",
    )


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
    limits: LayerLimits | None = None,
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
    limits
        The caps on the layer's bytes, features and vertices (default :class:`LayerLimits`).

    Returns
    -------
    NetworkLayer
        The pipes in the layer's order, with their lines as digitised.

    Raises
    ------
    LayerError
        Anything listed in the module's docstring.
    """
    limits = limits or LayerLimits()
    where = str(path)
    with _unpacked(Path(path), where, limits) as local:
        return _read(
            local,
            where,
            limits,
            id_field=id_field,
            asset_field=asset_field,
            from_field=from_field,
            to_field=to_field,
            layer=layer,
        )


def _read(
    path: Path,
    where: str,
    limits: LayerLimits,
    *,
    id_field: str,
    asset_field: str | None,
    from_field: str | None,
    to_field: str | None,
    layer: str | None,
) -> NetworkLayer:
    import pyogrio
    import shapely
    from pyogrio.errors import DataLayerError, DataSourceError

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
    layer_name = str(info.get("layer_name") or layer or path.stem)
    source = f"{Path(where).name}, layer {layer_name}"
    declared = int(info.get("features", -1))
    if declared > limits.layer_max_features:
        what = f"the layer declares {declared:,} features"
        raise _over("layer_max_features", limits, what, where, "features")
    if _is_sqlite(path):
        _check_geopackage(path, layer_name, where, limits)
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
    if (units := _not_metres(str(crs))) is not None:
        raise LayerError(
            f"the layer's CRS ({_short(str(crs))}) is {units}: its lengths would not be metres",
            file=where,
            field="crs",
            hint="reproject the layer to the network's projected CRS in metres first",
        )
    columns = list(dict.fromkeys(wanted))
    _, _, geometry, values = pyogrio.raw.read(
        path, layer=layer, columns=columns, max_features=limits.layer_max_features + 1
    )
    if len(geometry) > limits.layer_max_features:
        what = f"the layer has more than {limits.layer_max_features:,} features"
        raise _over("layer_max_features", limits, what, where, "features")
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
        line = _line(shapely, wkb, i, where, str(ids[i]), limits)
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


def _line(
    shapely: Any, wkb: Any, index: int, where: str, gis_id: str, limits: LayerLimits
) -> PipeLine:
    def refuse(reason: str) -> LayerError:
        return LayerError(
            f"feature {index} ({gis_id}): {reason}",
            file=where,
            field="geometry",
            hint="each pipe must be one line from node to node",
        )

    if wkb is None:
        raise refuse("has no geometry")
    if len(wkb) > _wkb_max_bytes(limits):
        what = f"feature {index} ({gis_id}) holds {len(wkb):,} bytes of geometry"
        raise _over("layer_max_vertices", limits, what, where, "geometry")
    geom = shapely.from_wkb(wkb)
    if geom.geom_type == "MultiLineString" and len(geom.geoms) == 1:
        geom = geom.geoms[0]
    if geom.geom_type != "LineString":
        parts = f" of {len(geom.geoms)} parts" if hasattr(geom, "geoms") else ""
        raise refuse(f"is a {geom.geom_type}{parts}, not one line")
    if (vertices := int(shapely.get_num_coordinates(geom))) > limits.layer_max_vertices:
        what = f"feature {index} ({gis_id}) has {vertices:,} vertices"
        raise _over("layer_max_vertices", limits, what, where, "geometry")
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


# --- bytes: a zip unpacked under the cap, a GeoPackage's table counted before GDAL reads it -----


def _is_sqlite(path: Path) -> bool:
    try:
        with path.open("rb") as fh:
            return fh.read(16) == b"SQLite format 3\0"
    except OSError:
        return False


def _size(path: Path) -> int:
    if path.is_dir():
        return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
    return path.stat().st_size


@contextmanager
def _unpacked(path: Path, where: str, limits: LayerLimits) -> Iterator[Path]:
    """``path`` itself, its size checked; a zip unpacked (its declared sizes checked, then
    streamed under the cap) into a private temporary folder, removed afterwards: the one
    file it holds, or the folder (a Shapefile's parts)."""
    try:
        size = _size(path)
    except OSError as exc:
        raise LayerError(f"cannot read the layer: {exc}", file=where) from exc
    if size > limits.layer_max_bytes:
        raise _over("layer_max_bytes", limits, f"the layer is {size:,} bytes", where, "size")
    if not (path.is_file() and zipfile.is_zipfile(path)):
        yield path
        return
    folder = Path(tempfile.mkdtemp(prefix="pipescan-layer-"))
    try:
        with zipfile.ZipFile(path) as zf:
            members = [m for m in zf.infolist() if not m.is_dir()]
            declared = sum(m.file_size for m in members)
            if declared > limits.layer_max_bytes:
                what = f"the zip declares {declared:,} bytes unpacked"
                raise _over("layer_max_bytes", limits, what, where, "size")
            written = 0
            for m in members:
                name = Path(m.filename).name
                if not name or name.startswith(".") or (folder / name).exists():
                    continue  # folders flattened; hidden files and repeats left out
                with zf.open(m) as src, (folder / name).open("xb") as dst:
                    while block := src.read(1 << 20):
                        written += len(block)
                        if written > limits.layer_max_bytes:
                            what = f"the zip unpacks to more than {written:,} bytes"
                            raise _over("layer_max_bytes", limits, what, where, "size")
                        dst.write(block)
        files = list(folder.iterdir())
        yield files[0] if len(files) == 1 else folder
    except (zipfile.BadZipFile, OSError) as exc:
        raise LayerError(f"cannot unpack the zip: {exc}", file=where) from exc
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def _wkb_max_bytes(limits: LayerLimits) -> int:
    """The most bytes a line within ``layer_max_vertices`` takes: a vertex is 16 to 32 bytes
    of WKB (x y, up to x y z m), plus a header (a GeoPackage's may hold an envelope)."""
    return 128 + 32 * limits.layer_max_vertices


def _check_geopackage(path: Path, layer: str, where: str, limits: LayerLimits) -> None:
    """The layer's table must be a plain table of stored columns, its features and geometry
    bytes within the caps: counted by SQLite (``length()`` does not read a blob) before GDAL
    reads a row."""
    try:
        conn = sqlite3.connect(f"file:{path}?mode=ro&immutable=1", uri=True)
    except sqlite3.Error as exc:
        raise LayerError(f"cannot read the GeoPackage: {exc}", file=where) from exc
    try:
        row = conn.execute(
            "SELECT table_name, column_name FROM gpkg_geometry_columns WHERE table_name = ?",
            (layer,),
        ).fetchone()
        if row is None:
            return  # not a GeoPackage layer GDAL reads as a table: GDAL refuses or reads it
        table, column = row
        kinds = [k for (k,) in conn.execute("SELECT type FROM sqlite_master WHERE name = ?",
                                            (table,))]  # fmt: skip
        if kinds != ["table"]:
            raise LayerError(
                f"layer {layer!r} is a {kinds[0] if kinds else 'missing table'}, not a table",
                file=where,
                field="layer",
                hint="export the layer as a table (a view can make its rows from nothing)",
            )
        quoted = '"' + table.replace('"', '""') + '"'
        for info in conn.execute(f"PRAGMA table_xinfo({quoted})"):
            if info[6]:
                raise LayerError(
                    f"layer {layer!r}'s column {info[1]!r} is generated, not stored",
                    file=where,
                    field=str(info[1]),
                    hint="export the layer again as plain columns",
                )
        geom = '"' + column.replace('"', '""') + '"'
        count, total, longest = conn.execute(
            f"SELECT count(*), coalesce(sum(length({geom})), 0), coalesce(max(length({geom})), 0) "
            f"FROM {quoted}"
        ).fetchone()
    except sqlite3.Error as exc:
        raise LayerError(f"cannot read the GeoPackage: {exc}", file=where) from exc
    finally:
        conn.close()
    if count > limits.layer_max_features:
        what = f"the layer has {count:,} features"
        raise _over("layer_max_features", limits, what, where, "features")
    if total > limits.layer_max_bytes:
        what = f"the layer's geometries take {total:,} bytes"
        raise _over("layer_max_bytes", limits, what, where, "geometry")
    if longest > _wkb_max_bytes(limits):
        what = f"a feature holds {longest:,} bytes of geometry"
        raise _over("layer_max_vertices", limits, what, where, "geometry")


# --- units of the CRS ---------------------------------------------------------------------------

_WKT_UNIT = re.compile(r'(?:LENGTHUNIT|UNIT)\[\s*"([^"]+)"\s*,\s*([0-9.eE+-]+)', re.IGNORECASE)


def _proj_db() -> Path | None:
    import pyogrio

    found = Path(pyogrio.__file__).parent / "proj_data" / "proj.db"
    return found if found.is_file() else None


def _not_metres(crs: str) -> str | None:
    """What the CRS's units are when they are not metres (``"in degrees"``, ``"in US survey
    foot"``), or None for a projected CRS in metres. An ``AUTH:CODE`` is looked up in the PROJ
    database pyogrio ships; WKT is read for its kind and its last unit."""
    text = crs.strip()
    head = text.upper()
    if head in _GEOGRAPHIC_CODES or head.startswith(("GEOGCS", "GEOGCRS", "GEODCRS")):
        return "a geographic CRS (degrees)"
    if head.startswith(("PROJCS", "PROJCRS")):
        units = _WKT_UNIT.findall(text)
        if not units:
            return "of unknown units"
        name, factor = units[-1]
        return None if abs(float(factor) - 1.0) < 1e-9 else f"in {name}"
    auth, _, code = text.partition(":")
    db = _proj_db()
    if not code or db is None:
        return "of unknown units (neither WKT nor an AUTHORITY:CODE PROJ knows)"
    conn = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    try:
        if conn.execute("SELECT 1 FROM geodetic_crs WHERE auth_name = ? AND code = ?",
                        (auth, code)).fetchone():  # fmt: skip
            return "a geographic CRS (degrees)"
        units = conn.execute(
            "SELECT u.name, u.conv_factor FROM projected_crs p "
            "JOIN axis a ON a.coordinate_system_auth_name = p.coordinate_system_auth_name "
            "AND a.coordinate_system_code = p.coordinate_system_code "
            "JOIN unit_of_measure u ON u.auth_name = a.uom_auth_name AND u.code = a.uom_code "
            "WHERE p.auth_name = ? AND p.code = ?",
            (auth, code),
        ).fetchall()
    finally:
        conn.close()
    if not units:
        return "not a projected CRS PROJ knows"
    odd = [name for name, factor in units if abs(float(factor) - 1.0) > 1e-9]
    return f"in {odd[0]}" if odd else None
