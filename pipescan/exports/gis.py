"""Stored inspections as GIS layers: pipes, defects along them, and (optionally) sections.

Written with pyogrio (GDAL) as a GeoPackage (one file, three layers) or as GeoJSON (one file
per layer), in the network's CRS: the CRS of the pipes' geometry, which must be one for all of
them. A pipe's geometry is its imported layer's line or the straight line between the node
positions of its metadata (:func:`pipescan.storage.database.network.asset_geometries`).

- ``pipes``: one line per pipe, from its latest selected inspection: the pipe's condition
  class (:func:`pipescan.core.summary.worst_grade`), peak blockage
  (:func:`pipescan.core.summary.peak_blockage`) and its growth per year over the pipe's scans
  (:func:`pipescan.core.trends.growth_per_year`), the scan's reach against the line's length.
- ``defects``: one line event per defect, placed along the pipe from its start to its end
  chainage by linear referencing, never stretched (:mod:`pipescan.core.network`).
- ``sections``: one point per section, at its middle (``--sections``).

Field names are pipescan's column names (docs/measures.md); ratios are fractions; a figure
that was not measured is null, never 0.
"""

from __future__ import annotations

from collections.abc import Sequence
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from sqlalchemy.engine import Engine

from pipescan.core.errors import PipescanError
from pipescan.core.model import SectionMeasures
from pipescan.core.network import (
    PipeGeometry,
    length_difference_ratio,
    length_note,
)
from pipescan.core.summary import peak_blockage, worst_grade
from pipescan.core.trends import growth_per_year
from pipescan.storage.atomic import atomic_path
from pipescan.storage.database.db import StorageError, session_scope
from pipescan.storage.database.models import Inspection
from pipescan.storage.database.network import asset_geometries, resolve_asset
from pipescan.storage.database.queries import (
    defect_counts,
    latest_per_asset_statement,
    list_earlier_scans,
    list_network_inspections,
    section_profiles,
)
from pipescan.storage.database.repository import (
    InspectionRecord,
    get_inspection,
    inspection_records,
    list_defects,
    record_statement,
)

__all__ = ["LAYERS", "GisError", "GisExport", "export_gis", "select_inspections"]

LAYERS = ("pipes", "defects", "sections")
"""The layers, in the order they are written."""

GisFormat = Literal["gpkg", "geojson"]

_CHUNK = 200


class GisError(PipescanError):
    """A GIS export cannot be made: no geometry for the pipes asked for, or pipes in
    different CRSs."""


@dataclass(frozen=True)
class GisExport:
    """What :func:`export_gis` wrote.

    ``paths`` are the files (one GeoPackage, or a GeoJSON file per layer); ``counts`` the
    features per layer; ``without_geometry`` the asset ids left out for want of a line;
    ``length_notes`` the pipes whose scan and line lengths disagree, with the words written.
    """

    paths: tuple[Path, ...]
    crs: str
    counts: dict[str, int]
    without_geometry: tuple[str, ...]
    length_notes: dict[str, str]


def select_inspections(
    engine: Engine, *, inspection_id: int | None = None, asset_id: str | None = None
) -> list[InspectionRecord]:
    """The inspections a GIS export shows: the one given; else the latest of the asset given
    (its id or its GIS id); else the latest of every asset.

    Raises
    ------
    StorageError
        Unknown ids, or an inspection of another asset than the one given.
    """
    if asset_id is not None:
        asset_id = resolve_asset(engine, asset_id)
    if inspection_id is not None:
        record = get_inspection(engine, inspection_id)
        if asset_id is not None and record.asset_id != asset_id:
            raise StorageError(
                f"inspection {inspection_id} is of asset {record.asset_id}, not {asset_id}",
                field="asset",
                hint="give --inspection or --asset, or both of the same pipe",
            )
        return [record]
    if asset_id is not None:
        latest = latest_per_asset_statement(Inspection.asset_id == asset_id)
        with session_scope(engine) as session:
            return inspection_records(session, record_statement(latest))
    return list_network_inspections(engine)


# --------------------------------------------------------------------------------------------
# Features


@dataclass
class _Layer:
    """Features of one layer as columns: WKB geometries and one list per field."""

    name: str
    geometry_type: str
    fields: dict[str, str]  # name -> "str" | "int" | "float"
    geometries: list[Any]
    values: dict[str, list[Any]]

    @classmethod
    def empty(cls, name: str, geometry_type: str, fields: dict[str, str]) -> _Layer:
        return cls(name, geometry_type, fields, [], {f: [] for f in fields})

    def add(self, geometry: Any, **values: Any) -> None:
        self.geometries.append(geometry)
        for name in self.fields:
            self.values[name].append(values.get(name))

    def __len__(self) -> int:
        return len(self.geometries)


_PIPE_FIELDS = {
    "asset_id": "str",
    "gis_id": "str",
    "inspection_id": "int",
    "inspected_at": "str",
    "inspection_count": "int",
    "condition_class": "int",
    "peak_blockage_ratio": "float",
    "peak_chainage_m": "float",
    "measured_inner_diameter_m": "float",
    "growth_per_year_ratio": "float",
    "defect_count": "int",
    "scan_end_chainage_m": "float",
    "gis_length_m": "float",
    "length_difference_ratio": "float",
    "length_note": "str",
    "geometry_source": "str",
    "oriented_by": "str",
}
_DEFECT_FIELDS = {
    "asset_id": "str",
    "gis_id": "str",
    "inspection_id": "int",
    "code": "str",
    "measure": "str",
    "condition_class": "int",
    "chainage_start_m": "float",
    "chainage_end_m": "float",
    "peak_chainage_m": "float",
    "peak_value": "float",
    "peak_blockage_ratio": "float",
    "clock_from_h": "float",
    "clock_to_h": "float",
    "lower_bound": "int",
    "beyond_line_m": "float",
    "position_note": "str",
}
_SECTION_FIELDS = {
    "asset_id": "str",
    "gis_id": "str",
    "inspection_id": "int",
    "chainage_start_m": "float",
    "chainage_end_m": "float",
    "status": "str",
    "blockage_ratio": "float",
    "deposit_height_ratio": "float",
    "deformation_ratio": "float",
    "coverage_ratio": "float",
    "condition_class": "int",
    "beyond_line_m": "float",
}


def _linestring(shapely: Any, coords: np.ndarray, dims: int) -> Any:
    return shapely.to_wkb(shapely.LineString(coords[:, :dims]))


def _measured(section: SectionMeasures, value: float | None) -> float | None:
    # Figures of a section that is not ok are not measured: null, as in the CSV export.
    return value if section.is_ok else None


def _beyond_words(beyond_m: float) -> str | None:
    if beyond_m <= 0:
        return None
    return f"{beyond_m:.2f} m of it lies past the end of the GIS line and is cut there"


def _features(
    engine: Engine,
    records: Sequence[InspectionRecord],
    geometries: dict[str, PipeGeometry],
    *,
    dims: int,
    with_sections: bool,
) -> tuple[_Layer, _Layer, _Layer, dict[str, str]]:
    import shapely

    line_type = "LineString Z" if dims == 3 else "LineString"
    pipes = _Layer.empty("pipes", line_type, _PIPE_FIELDS)
    defects = _Layer.empty("defects", line_type, _DEFECT_FIELDS)
    sections = _Layer.empty("sections", "Point Z" if dims == 3 else "Point", _SECTION_FIELDS)
    notes: dict[str, str] = {}
    for start in range(0, len(records), _CHUNK):
        chunk = records[start : start + _CHUNK]
        ids = [r.id for r in chunk]
        with session_scope(engine) as session:
            history = list_earlier_scans(session, ids)
            profiles = section_profiles(session, ids)
            counts = defect_counts(session, ids)
            chunk_defects = {r.id: list_defects(session, r.id) for r in chunk}
        for record in chunk:
            geometry = geometries[record.asset_id]
            line = geometry.line
            profile = profiles[record.id]
            peak = peak_blockage(profile)
            peak_ratio = None if peak is None else peak.blockage_ratio
            earlier = list(reversed(history[record.id]))
            growth = growth_per_year(
                [e.inspected_at for e in earlier] + [record.inspected_at],
                [e.peak_blockage_ratio for e in earlier] + [peak_ratio],
            )
            reach = max((s.chainage_end_m for s in profile), default=None)
            note = None if reach is None else length_note(reach, line.length_m)
            if note is not None:
                notes[record.asset_id] = note
            pipes.add(
                _linestring(shapely, line.coords, dims),
                asset_id=record.asset_id,
                gis_id=geometry.gis_id,
                inspection_id=record.id,
                inspected_at=record.inspected_at.isoformat(),
                inspection_count=len(earlier) + 1,
                condition_class=worst_grade(profile),
                peak_blockage_ratio=peak_ratio,
                peak_chainage_m=None if peak is None else peak.chainage_start_m,
                # The wall's inner diameter as the run measured it (docs/instrument.md).
                measured_inner_diameter_m=(record.registration or {}).get(
                    "measured_inner_diameter_m"
                ),
                growth_per_year_ratio=growth,
                defect_count=counts[record.id],
                scan_end_chainage_m=reach,
                gis_length_m=line.length_m,
                length_difference_ratio=(
                    None if reach is None else length_difference_ratio(reach, line.length_m)
                ),
                length_note=note,
                geometry_source=geometry.source,
                oriented_by=geometry.oriented_by,
            )
            common = {
                "asset_id": record.asset_id,
                "gis_id": geometry.gis_id,
                "inspection_id": record.id,
            }
            for defect in chunk_defects[record.id]:
                cut = line.cut(defect.chainage_start_m, defect.chainage_end_m)
                defects.add(
                    _linestring(shapely, cut.coords, dims),
                    **common,
                    code=defect.code,
                    measure=defect.measure,
                    condition_class=defect.grade,
                    chainage_start_m=defect.chainage_start_m,
                    chainage_end_m=defect.chainage_end_m,
                    peak_chainage_m=defect.peak_chainage_m,
                    peak_value=defect.peak_value,
                    peak_blockage_ratio=defect.peak_blockage_ratio,
                    clock_from_h=defect.clock_from_h,
                    clock_to_h=defect.clock_to_h,
                    lower_bound=int(defect.lower_bound),
                    beyond_line_m=cut.beyond_m,
                    position_note=_beyond_words(cut.beyond_m),
                )
            if not with_sections:
                continue
            for s in profile:
                middle = (s.chainage_start_m + s.chainage_end_m) / 2
                beyond = max(0.0, middle - line.length_m, -middle)
                sections.add(
                    shapely.to_wkb(shapely.Point(line.point_at(middle)[:dims])),
                    **common,
                    chainage_start_m=s.chainage_start_m,
                    chainage_end_m=s.chainage_end_m,
                    status=s.status.value,
                    blockage_ratio=_measured(s, s.blockage_ratio),
                    deposit_height_ratio=_measured(s, s.deposit_height_ratio),
                    deformation_ratio=_measured(s, s.deformation_ratio),
                    coverage_ratio=s.coverage_ratio,
                    condition_class=s.grade if s.is_ok else None,
                    beyond_line_m=beyond,
                )
    return pipes, defects, sections, notes


# --------------------------------------------------------------------------------------------
# Writing


def _columns(layer: _Layer) -> tuple[list[np.ndarray], list[np.ndarray | None]]:
    arrays: list[np.ndarray] = []
    masks: list[np.ndarray | None] = []
    for name, kind in layer.fields.items():
        values = layer.values[name]
        missing = np.array([v is None for v in values], dtype=bool)
        if kind == "str":
            arrays.append(np.array(values, dtype=object))
            masks.append(None)
        elif kind == "int":
            arrays.append(np.array([0 if v is None else int(v) for v in values], dtype=np.int64))
            masks.append(missing if missing.any() else None)
        else:
            arrays.append(
                np.array([np.nan if v is None else float(v) for v in values], dtype=np.float64)
            )
            masks.append(None)  # NaN is written as null
    return arrays, masks


def _write_layer(path: Path, layer: _Layer, *, driver: str, crs: str, append: bool) -> None:
    from pyogrio.raw import write

    arrays, masks = _columns(layer)
    write(
        str(path),
        np.array(layer.geometries, dtype=object),
        arrays,
        list(layer.fields),
        field_mask=masks if any(m is not None for m in masks) else None,
        layer=layer.name,
        driver=driver,
        geometry_type=layer.geometry_type,
        crs=crs,
        append=append,
    )


def export_gis(
    engine: Engine,
    out: Path,
    *,
    fmt: GisFormat = "gpkg",
    inspection_id: int | None = None,
    asset_id: str | None = None,
    with_sections: bool = False,
) -> GisExport:
    """Write the pipes, their defects and optionally their sections as GIS layers.

    Parameters
    ----------
    out
        The GeoPackage file (``gpkg``), or for ``geojson`` a folder that receives
        ``pipes.geojson``, ``defects.geojson`` (and ``sections.geojson``).
    fmt
        ``gpkg`` or ``geojson``.
    inspection_id, asset_id
        What to export (see :func:`select_inspections`).
    with_sections
        Also write the ``sections`` layer.

    Raises
    ------
    GisError
        No pipe asked for has a geometry, a pipe asked for by id has none, or the pipes are
        in different CRSs. Nothing is written then.
    StorageError
        Unknown ids.
    """
    records = select_inspections(engine, inspection_id=inspection_id, asset_id=asset_id)
    geometries = asset_geometries(engine, sorted({r.asset_id for r in records}))
    without = tuple(sorted({r.asset_id for r in records if r.asset_id not in geometries}))
    hint = (
        "give upstream_node_xyz, downstream_node_xyz and crs in inspection.toml "
        "(docs/archive.md), or import the network's pipe layer with `pipescan network import`"
    )
    if without and (inspection_id is not None or asset_id is not None):
        raise GisError(f"asset {without[0]} has no geometry", field="geometry", hint=hint)
    kept = [r for r in records if r.asset_id in geometries]
    if not kept:
        raise GisError(
            "no stored pipe has a geometry" if records else "no inspection is stored",
            field="geometry",
            hint=hint,
        )
    crs_of: dict[str, list[str]] = {}
    for r in kept:
        crs_of.setdefault(geometries[r.asset_id].crs.upper(), []).append(r.asset_id)
    if len(crs_of) > 1:
        listed = "; ".join(f"{crs}: {', '.join(ids[:3])}" for crs, ids in crs_of.items())
        raise GisError(
            f"the pipes are in {len(crs_of)} coordinate reference systems ({listed})",
            field="crs",
            hint="export the pipes of one CRS at a time with --asset or --inspection",
        )
    crs = geometries[kept[0].asset_id].crs
    dims = 3 if all(geometries[r.asset_id].line.coords.shape[1] == 3 for r in kept) else 2
    layers = _features(engine, kept, geometries, dims=dims, with_sections=with_sections)
    pipes, defects, sections, notes = layers
    written = [pipes, defects] + ([sections] if with_sections else [])
    paths = _write(out, written, fmt=fmt, crs=crs)
    return GisExport(
        paths=paths,
        crs=crs,
        counts={layer.name: len(layer) for layer in written},
        without_geometry=without,
        length_notes=notes,
    )


def _check_target(out: Path, fmt: GisFormat) -> None:
    where = str(out)
    if fmt == "gpkg" and (out.is_dir() or not out.parent.is_dir()):
        raise GisError(
            "is a folder" if out.is_dir() else "its folder does not exist",
            file=where,
            hint="give the GeoPackage file to write, in an existing folder",
        )
    if fmt == "geojson" and out.exists() and not out.is_dir():
        raise GisError(
            "is a file; GeoJSON is written as a folder of one file per layer",
            file=where,
            hint="give a folder (it is created if missing)",
        )


def _write(out: Path, layers: Sequence[_Layer], *, fmt: GisFormat, crs: str) -> tuple[Path, ...]:
    from pyogrio.errors import DataSourceError

    _check_target(out, fmt)
    try:
        return _write_files(out, layers, fmt=fmt, crs=crs)
    except (OSError, DataSourceError) as exc:
        raise GisError(f"cannot write: {exc}", file=str(out), hint="nothing was written") from exc


def _write_files(
    out: Path, layers: Sequence[_Layer], *, fmt: GisFormat, crs: str
) -> tuple[Path, ...]:
    # Everything is written in new private folders next to the target (GDAL adds journal
    # files of its own), and renamed onto it at the end: a failed export leaves nothing
    # half-written, and a link planted at a predictable name is never written through.
    if fmt == "gpkg":
        with atomic_path(out) as tmp:
            for i, layer in enumerate(layers):
                _write_layer(tmp, layer, driver="GPKG", crs=crs, append=i > 0)
        return (out,)
    out.mkdir(parents=True, exist_ok=True)
    targets = [out / f"{layer.name}.geojson" for layer in layers]
    with ExitStack() as stack:
        for layer, target in zip(layers, targets, strict=True):
            tmp = stack.enter_context(atomic_path(target))
            _write_layer(tmp, layer, driver="GeoJSON", crs=crs, append=False)
    return tuple(targets)
