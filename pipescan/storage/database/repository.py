"""Reading and writing inspections: plain functions over an Engine.

Every function opens and closes its own session and returns core dataclasses
(``pipescan.core.model``) or the small frozen records defined here; ORM objects never leave a
session. Writes are idempotent: saving the same archive with the same processing parameters
again replaces the earlier inspection, so a retried or re-run task is safe.

A reader's verb says what it does when nothing is stored: ``get_`` raises
:class:`StorageError`, ``find_`` returns None, ``list_`` returns a list (maybe empty).
"""

from __future__ import annotations

import dataclasses
import enum
import hashlib
import json
import logging
import math
import operator
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, date, datetime
from pathlib import PurePath
from typing import Any, TypeVar

import numpy as np
import sqlalchemy as sa
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.engine import Engine
from sqlalchemy.orm import Session

from pipescan.core.model import Defect, FrameQuality, InspectionMeta, SectionMeasures, SectionStatus
from pipescan.core.sanitize import strip_credentials
from pipescan.core.summary import blockage_summary
from pipescan.storage.database.db import Reader, StorageError, reading, session_scope
from pipescan.storage.database.models import (
    Asset,
    DefectRow,
    FrameQualityRow,
    Inspection,
    Section,
    utc_now,
)
from pipescan.storage.lookalike import skeleton

__all__ = [
    "AssetRecord",
    "InspectionRecord",
    "InspectionToSave",
    "Reader",
    "TrendPoint",
    "canonical_params_json",
    "defect_from_row",
    "find_inspection",
    "find_latest_inspection_id",
    "get_asset",
    "get_inspection",
    "inspection_records",
    "list_assets",
    "list_defects",
    "list_frame_quality",
    "list_inspections",
    "list_section_trend",
    "list_sections",
    "m_to_mm",
    "mm_to_m",
    "params_hash",
    "record_statement",
    "save_inspection",
    "save_inspections",
]


@dataclass(frozen=True)
class InspectionRecord:
    """One stored inspection, with its asset's attributes and its number of sections.

    ``inspected_at`` and ``created_at`` are timezone-aware, in UTC. ``nominal_diameter_m`` is
    None for a non-circular pipe whose metadata gives none. ``params`` are the
    processing parameters as hashed into ``params_hash``; ``registration`` is the registration
    summary (empty when none was saved).

    The blockage summary covers the *measured* sections only (status ``ok`` with a blockage
    ratio): how many there are, their mean and peak ``blockage_ratio`` and the start chainage
    of the (first) peak section. The three figures are None when no section was measured.

    ``direction`` (``"downstream"`` or ``"upstream"``) and ``chainage_offset_m`` are the
    survey's, from its metadata; None for an inspection stored before pipescan kept them.
    """

    id: int
    asset_id: str
    inspected_at: datetime
    archive_uri: str
    content_hash: str
    params_hash: str
    params: dict[str, Any]
    software_version: str
    status: str
    created_at: datetime
    point_count: int
    frame_count: int
    scanned_length_m: float
    registration: dict[str, Any]
    threshold_table: str
    upstream_node: str | None
    downstream_node: str | None
    nominal_diameter_m: float | None
    pipe_shape: str
    material: str | None
    section_count: int
    measured_section_count: int = 0
    mean_blockage_ratio: float | None = None
    peak_blockage_ratio: float | None = None
    peak_chainage_m: float | None = None
    direction: str | None = None
    chainage_offset_m: float | None = None
    start_source: str | None = None


@dataclass(frozen=True)
class AssetRecord:
    """One pipe asset, with how many inspections are stored and the date of the latest.

    ``nominal_diameter_m`` is None for a non-circular pipe whose metadata gives none.
    """

    asset_id: str
    upstream_node: str | None
    downstream_node: str | None
    nominal_diameter_m: float | None
    pipe_shape: str
    material: str | None
    inspection_count: int
    last_inspected_at: datetime | None


@dataclass(frozen=True)
class TrendPoint:
    """The section covering one chainage in one inspection of an asset."""

    inspection_id: int
    inspected_at: datetime
    section: SectionMeasures


# ---------------------------------------------------------------------------------------------
# Conversions


def m_to_mm(value_m: float) -> int:
    """A length in metres as whole millimetres (the sections' key representation)."""
    return round(value_m * 1000.0)


def mm_to_m(value_mm: int) -> float:
    """Whole millimetres back to metres."""
    return value_mm / 1000.0


def _json_default(value: Any) -> Any:
    if isinstance(value, enum.Enum):
        return value.value
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, datetime | date):
        return value.isoformat()
    if isinstance(value, PurePath):
        return value.as_posix()
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return dataclasses.asdict(value)
    if isinstance(value, set | frozenset):
        return sorted(value)
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def canonical_params_json(params: Mapping[str, Any]) -> str:
    """The canonical JSON text of processing parameters: sorted keys, no whitespace.

    Tuples become lists, enums their values, numpy scalars Python numbers, paths POSIX
    strings, dates ISO 8601 text; so equal parameters give equal text whatever their Python
    types.

    Raises
    ------
    StorageError
        If a value has no JSON form or is not finite (NaN, inf).
    """
    try:
        return json.dumps(
            dict(params),
            sort_keys=True,
            separators=(",", ":"),
            ensure_ascii=False,
            allow_nan=False,
            default=_json_default,
        )
    except (TypeError, ValueError) as exc:
        raise StorageError(
            f"processing parameters cannot be stored as JSON: {exc}",
            field="params",
            hint="use numbers, strings, booleans, lists and dicts, with finite numbers",
        ) from exc


def params_hash(params: Mapping[str, Any]) -> str:
    """SHA-256 (hex) of :func:`canonical_params_json`: the identity of a parameter set."""
    return hashlib.sha256(canonical_params_json(params).encode("utf-8")).hexdigest()


def _finite_or_none(value: float | None) -> float | None:
    # NaN means "not computed" upstream; it is stored as NULL, never as a number.
    if value is None:
        return None
    value = float(value)
    return value if math.isfinite(value) else None


def _require_finite(value: float, what: str, where: str) -> float:
    value = float(value)
    if not math.isfinite(value):
        raise StorageError(f"{where}: {what} is {value}, expected a finite number", field=what)
    return value


def _contour_to_json(contour_m: np.ndarray | None, where: str) -> str | None:
    if contour_m is None:
        return None
    contour = np.asarray(contour_m, dtype=np.float64)
    if contour.ndim != 2 or contour.shape[1] != 2:
        raise StorageError(
            f"{where}: contour_m has shape {contour.shape}, expected (M, 2)", field="contour_m"
        )
    if not np.isfinite(contour).all():
        raise StorageError(f"{where}: contour_m holds non-finite values", field="contour_m")
    contour_mm = np.rint(contour * 1000.0).astype(np.int64)
    return json.dumps(contour_mm.tolist(), separators=(",", ":"))


def _contour_from_json(text: str | None) -> np.ndarray | None:
    if text is None:
        return None
    return np.asarray(json.loads(text), dtype=np.float64).reshape(-1, 2) / 1000.0


def _section_where(section: SectionMeasures) -> str:
    return f"section at chainage {section.chainage_start_m:.3f} m"


# Status members and their plain string values alike map to the plain string.
_STATUS_VALUES: dict[str, str] = {status: status.value for status in SectionStatus}
_isfinite = math.isfinite


def _section_row(section: SectionMeasures) -> dict[str, Any]:
    # Called for every section of every save, so written for speed: conversions inline, and
    # error messages formatted only on error.
    start_mm = round(section.chainage_start_m * 1000.0)
    end_mm = round(section.chainage_end_m * 1000.0)
    if end_mm <= start_mm:
        raise StorageError(
            f"{_section_where(section)}: chainage_end_m {section.chainage_end_m} is not after "
            "chainage_start_m (to the millimetre)",
            field="chainage_end_m",
        )
    status = _STATUS_VALUES.get(section.status)
    if status is None:
        raise StorageError(
            f"{_section_where(section)}: unknown status {section.status!r}",
            field="status",
            hint=f"use one of {', '.join(s.value for s in SectionStatus)}",
        )
    coverage_ratio = float(section.coverage_ratio)
    if not 0.0 <= coverage_ratio <= 1.0:  # also refuses NaN
        raise StorageError(
            f"{_section_where(section)}: coverage_ratio {coverage_ratio} is outside [0, 1]",
            field="coverage_ratio",
        )
    if section.point_count < 0:
        raise StorageError(
            f"{_section_where(section)}: point_count {section.point_count} < 0",
            field="point_count",
        )
    # NaN means "not computed" upstream: stored as NULL, never as a number.
    open_area, nominal_area, blockage, ovality, deformation, deposit = (
        None if v is None or not _isfinite(f := float(v)) else f
        for v in (
            section.open_area_m2,
            section.nominal_area_m2,
            section.blockage_ratio,
            section.ovality_ratio,
            section.deformation_ratio,
            section.deposit_height_ratio,
        )
    )
    return {
        "chainage_start_mm": start_mm,
        "chainage_end_mm": end_mm,
        "open_area_m2": open_area,
        "nominal_area_m2": nominal_area,
        "blockage_ratio": blockage,
        "ovality_ratio": ovality,
        "deformation_ratio": deformation,
        "deposit_height_ratio": deposit,
        "coverage_ratio": coverage_ratio,
        "point_count": int(section.point_count),
        "status": status,
        "grade": None if section.grade is None else int(section.grade),
        "contour_json": (
            None
            if section.contour_m is None
            else _contour_to_json(section.contour_m, _section_where(section))
        ),
        **{
            name: None if v is None or not _isfinite(f := float(v)) else f
            for name, v in (
                ("blockage_uncertainty_ratio", section.blockage_uncertainty_ratio),
                ("ovality_uncertainty_ratio", section.ovality_uncertainty_ratio),
                ("deformation_uncertainty_ratio", section.deformation_uncertainty_ratio),
                ("deposit_height_uncertainty_ratio", section.deposit_height_uncertainty_ratio),
                ("water_depth_ratio", section.water_depth_ratio),
                ("water_depth_uncertainty_ratio", section.water_depth_uncertainty_ratio),
                ("chainage_uncertainty_m", section.chainage_uncertainty_m),
            )
        },
    }


def section_from_row(row: Any) -> SectionMeasures:
    """A stored section as the core's ``SectionMeasures``.

    ``row`` is a ``Section`` or any result row with its columns; without ``contour_json``
    (a query that left the contours out), ``contour_m`` is None.
    """
    try:
        status = SectionStatus(row.status)
    except ValueError as exc:
        raise StorageError(
            f"inspection {row.inspection_id}, section at {mm_to_m(row.chainage_start_mm):.3f} m:"
            f" unknown status {row.status!r}",
            field="status",
            hint="it was written by a newer pipescan; upgrade pipescan",
        ) from exc
    return SectionMeasures(
        chainage_start_m=mm_to_m(row.chainage_start_mm),
        chainage_end_m=mm_to_m(row.chainage_end_mm),
        # The core's type is float: an unknown nominal area is NaN there, NULL here.
        nominal_area_m2=math.nan if row.nominal_area_m2 is None else row.nominal_area_m2,
        status=status,
        point_count=row.point_count,
        coverage_ratio=row.coverage_ratio,
        open_area_m2=row.open_area_m2,
        blockage_ratio=row.blockage_ratio,
        ovality_ratio=row.ovality_ratio,
        deformation_ratio=row.deformation_ratio,
        deposit_height_ratio=row.deposit_height_ratio,
        grade=row.grade,
        # Queries that predate them, or leave them out, give None.
        blockage_uncertainty_ratio=getattr(row, "blockage_uncertainty_ratio", None),
        ovality_uncertainty_ratio=getattr(row, "ovality_uncertainty_ratio", None),
        deformation_uncertainty_ratio=getattr(row, "deformation_uncertainty_ratio", None),
        deposit_height_uncertainty_ratio=getattr(row, "deposit_height_uncertainty_ratio", None),
        water_depth_ratio=getattr(row, "water_depth_ratio", None),
        water_depth_uncertainty_ratio=getattr(row, "water_depth_uncertainty_ratio", None),
        contour_m=_contour_from_json(getattr(row, "contour_json", None)),
        chainage_uncertainty_m=getattr(row, "chainage_uncertainty_m", None),
    )


def _defect_row(defect: Defect) -> dict[str, Any]:
    where = f"defect {defect.code} at chainage {defect.chainage_start_m:.3f} m"
    return {
        "code": defect.code,
        "measure": defect.measure,
        "chainage_start_m": _require_finite(defect.chainage_start_m, "chainage_start_m", where),
        "chainage_end_m": _require_finite(defect.chainage_end_m, "chainage_end_m", where),
        "peak_chainage_m": _require_finite(defect.peak_chainage_m, "peak_chainage_m", where),
        "peak_value": _require_finite(defect.peak_value, "peak_value", where),
        "peak_blockage_ratio": _finite_or_none(defect.peak_blockage_ratio),
        "grade": None if defect.grade is None else int(defect.grade),
        "clock_from_h": _finite_or_none(defect.clock_from_h),
        "clock_to_h": _finite_or_none(defect.clock_to_h),
        "characterisation": defect.characterisation,
        "lower_bound": bool(defect.lower_bound),
    }


def _frame_quality_row(quality: FrameQuality) -> dict[str, Any]:
    # Registration must turn a failed frame into finite figures (fitness 0) or an error; a
    # NaN here would be a bug upstream, so it is refused with the frame's index.
    where = f"frame {quality.index}"
    return {
        "frame_index": int(quality.index),
        "fitness": _require_finite(quality.fitness, "fitness", where),
        "rmse_m": _require_finite(quality.rmse_m, "rmse_m", where),
        "degenerate": bool(quality.degenerate),
    }


def _inspection_record(
    inspection: Inspection, asset: Asset, section_count: int
) -> InspectionRecord:
    return InspectionRecord(
        id=inspection.id,
        asset_id=inspection.asset_id,
        inspected_at=inspection.inspected_at,
        archive_uri=inspection.archive_uri,
        content_hash=inspection.content_hash,
        params_hash=inspection.params_hash,
        params=dict(inspection.params_json),
        software_version=inspection.software_version,
        status=inspection.status,
        created_at=inspection.created_at,
        point_count=inspection.point_count,
        frame_count=inspection.frame_count,
        scanned_length_m=inspection.scanned_length_m,
        registration=dict(inspection.registration_json or {}),
        threshold_table=inspection.threshold_table,
        start_source=inspection.start_source,
        upstream_node=asset.upstream_node,
        downstream_node=asset.downstream_node,
        nominal_diameter_m=asset.nominal_diameter_m,
        pipe_shape=asset.pipe_shape,
        material=asset.material,
        section_count=section_count,
        measured_section_count=inspection.measured_section_count,
        mean_blockage_ratio=inspection.mean_blockage_ratio,
        peak_blockage_ratio=inspection.peak_blockage_ratio,
        peak_chainage_m=(
            None
            if inspection.peak_chainage_start_mm is None
            else mm_to_m(inspection.peak_chainage_start_mm)
        ),
        direction=inspection.direction,
        chainage_offset_m=inspection.chainage_offset_m,
    )


# ---------------------------------------------------------------------------------------------
# Writing


def _asset_values(metas: Iterable[InspectionMeta]) -> list[dict[str, Any]]:
    # One row per asset, by asset id; a later meta's known values override an earlier one's,
    # its unknown (None) values do not, as consecutive saves would have it.
    merged: dict[str, dict[str, Any]] = {}
    for meta in metas:
        values = {
            "asset_id": meta.asset_id,
            "upstream_node": meta.upstream_node,
            "downstream_node": meta.downstream_node,
            "nominal_diameter_m": _finite_or_none(meta.nominal_diameter_m),
            "pipe_shape": meta.pipe_shape,
            "material": meta.material,
            "upstream_node_xyz": _position(meta.upstream_node_xyz),
            "downstream_node_xyz": _position(meta.downstream_node_xyz),
            "crs": meta.crs,
        }
        known = merged.setdefault(meta.asset_id, values)
        known.update((k, v) for k, v in values.items() if v is not None)
    return [merged[a] for a in sorted(merged)]


def _position(xyz: Sequence[float] | None) -> list[float] | None:
    # A node position as stored (a JSON list); the metadata parser checked it is finite.
    return None if xyz is None else [float(v) for v in xyz]


def _warn_of_twins(session: Session, asset_ids: Sequence[str]) -> None:
    """Warn of a new asset whose id looks like a stored one's (Cyrillic "МН1" against Latin
    "MH1"): different characters, so another asset, which is most likely a typing slip."""
    stored = set(session.scalars(sa.select(Asset.asset_id).where(Asset.asset_id.in_(asset_ids))))
    fresh = [a for a in asset_ids if a not in stored]
    if not fresh:
        return
    looks = {skeleton(a): a for a in session.scalars(sa.select(Asset.asset_id))}
    for asset_id in fresh:
        twin = looks.get(skeleton(asset_id))
        if twin is not None and twin != asset_id:
            logging.getLogger("pipescan").warning(
                f"warning: new asset {asset_id!r} looks like stored asset {twin!r} but is "
                "spelt with other letters; it is stored as another asset"
            )


def _upsert_assets(session: Session, metas: Iterable[InspectionMeta]) -> None:
    rows = _asset_values(metas)
    _warn_of_twins(session, [r["asset_id"] for r in rows])
    dialect = session.get_bind().dialect.name
    if dialect in ("sqlite", "postgresql"):
        insert = sqlite.insert if dialect == "sqlite" else postgresql.insert
        # Atomic statements, in asset id order: on PostgreSQL they also lock the assets' rows
        # until commit, so concurrent saves of one asset run their delete-then-insert one
        # after the other, and two batches lock shared assets in the same order (no deadlock).
        for chunk in _chunks(rows, 500):
            statement = insert(Asset).values(chunk)
            new = statement.excluded
            statement = statement.on_conflict_do_update(
                index_elements=[Asset.asset_id],
                set_={
                    "upstream_node": sa.func.coalesce(new.upstream_node, Asset.upstream_node),
                    "downstream_node": sa.func.coalesce(new.downstream_node, Asset.downstream_node),
                    "nominal_diameter_m": sa.func.coalesce(
                        new.nominal_diameter_m, Asset.nominal_diameter_m
                    ),
                    "pipe_shape": new.pipe_shape,
                    "material": sa.func.coalesce(new.material, Asset.material),
                    # The positions and their CRS go together: a metadata without them
                    # keeps the known ones, one with them replaces all three.
                    **{
                        name: sa.case(
                            (new.crs.is_(None), getattr(Asset, name)),
                            else_=getattr(new, name),
                        )
                        for name in ("upstream_node_xyz", "downstream_node_xyz", "crs")
                    },
                },
            )
            session.execute(statement)
        return
    for values in rows:
        asset = session.get(Asset, values["asset_id"], with_for_update=True)
        if asset is None:
            session.add(Asset(**values))
            session.flush()
            continue
        for name, value in values.items():
            if value is not None:
                setattr(asset, name, value)
    session.flush()


def _chunks(items: Sequence[Any], size: int) -> Iterable[Sequence[Any]]:
    for start in range(0, len(items), size):
        yield items[start : start + size]


# Section columns in the order of _section_row, with their PostgreSQL types for binary COPY.
_SECTION_COPY_TYPES: dict[str, str] = {
    "inspection_id": "int4",
    "chainage_start_mm": "int4",
    "chainage_end_mm": "int4",
    "open_area_m2": "float8",
    "nominal_area_m2": "float8",
    "blockage_ratio": "float8",
    "ovality_ratio": "float8",
    "deformation_ratio": "float8",
    "deposit_height_ratio": "float8",
    "coverage_ratio": "float8",
    "point_count": "int4",
    "status": "varchar",
    "grade": "int4",
    "contour_json": "text",
    "blockage_uncertainty_ratio": "float8",
    "ovality_uncertainty_ratio": "float8",
    "deformation_uncertainty_ratio": "float8",
    "deposit_height_uncertainty_ratio": "float8",
    "water_depth_ratio": "float8",
    "water_depth_uncertainty_ratio": "float8",
    "chainage_uncertainty_m": "float8",
}


def _summary_columns(sections: Sequence[SectionMeasures]) -> dict[str, Any]:
    # The inspection's blockage summary columns, by the core's one definition.
    summary = blockage_summary(sections)
    peak_m = summary.peak_chainage_m
    return {
        "measured_section_count": summary.measured_section_count,
        "mean_blockage_ratio": summary.mean_blockage_ratio,
        "peak_blockage_ratio": summary.peak_blockage_ratio,
        "peak_chainage_start_mm": None if peak_m is None else m_to_mm(peak_m),
    }


# Rows to insert, each with the id of the inspection it belongs to.
_Owned = list[tuple[int, list[dict[str, Any]]]]


def _insert_sections(session: Session, owned: _Owned) -> None:
    if not any(rows for _, rows in owned):
        return
    connection = session.connection()
    if connection.dialect.name == "postgresql" and connection.dialect.driver == "psycopg":
        _copy_sections(connection, owned)
        return
    if connection.dialect.name == "sqlite":
        # The driver's executemany over plain tuples: three times the rows per second of
        # SQLAlchemy's per-row parameter processing, which these plain types do not need.
        names = list(_SECTION_COPY_TYPES)
        values = operator.itemgetter(*names[1:])
        connection.exec_driver_sql(
            f"INSERT INTO sections ({', '.join(names)}) VALUES ({', '.join('?' * len(names))})",
            [(inspection_id, *values(r)) for inspection_id, rows in owned for r in rows],
        )
        return
    # Core's executemany on the session's connection: one statement for every row. (The ORM's
    # bulk insert would split the rows into a statement per run of rows with the same NULLs.)
    connection.execute(
        sa.insert(Section),
        [{"inspection_id": inspection_id, **r} for inspection_id, rows in owned for r in rows],
    )


def _copy_sections(connection: sa.Connection, owned: _Owned) -> None:
    # PostgreSQL's binary COPY, on the session's own connection and so inside its transaction,
    # one for the whole batch: four to five times the rows per second of a batched INSERT.
    import psycopg

    driver_connection = connection.connection.driver_connection
    names = list(_SECTION_COPY_TYPES)
    columns = ", ".join(names)
    try:
        with (
            driver_connection.cursor() as cursor,  # type: ignore[union-attr]
            cursor.copy(f"COPY sections ({columns}) FROM STDIN (FORMAT BINARY)") as copy,
        ):
            copy.set_types(list(_SECTION_COPY_TYPES.values()))
            values = operator.itemgetter(*names[1:])
            for inspection_id, rows in owned:
                for row in rows:
                    copy.write_row((inspection_id, *values(row)))
    except psycopg.Error as exc:
        ids = sorted({inspection_id for inspection_id, _ in owned})
        raise StorageError(
            f"PostgreSQL refused the sections of inspection(s) {', '.join(map(str, ids))}: {exc}",
            hint="nothing was written",
        ) from exc


def _insert_defects(session: Session, owned: _Owned) -> None:
    rows = [{"inspection_id": i, **r} for i, defect_rows in owned for r in defect_rows]
    if rows:
        session.connection().execute(sa.insert(DefectRow), rows)


def _insert_frame_quality(session: Session, owned: _Owned) -> None:
    rows = [{"inspection_id": i, **r} for i, quality_rows in owned for r in quality_rows]
    if rows:
        session.connection().execute(sa.insert(FrameQualityRow), rows)


def _check_unique(keys: list[int], what: str, unit: str) -> None:
    seen: set[int] = set()
    for key in keys:
        if key in seen:
            raise StorageError(f"two {what} share the key {key}{unit}", hint="they must be unique")
        seen.add(key)


@dataclass(frozen=True)
class InspectionToSave:
    """One processed inspection to store: what a flow hands to :func:`save_inspection`.

    Attributes
    ----------
    meta
        The archive's metadata. A naive ``inspected_at`` is taken as UTC. A NaN
        ``nominal_diameter_m`` (non-circular pipe) is stored as NULL.
    archive_uri
        Where the archive was read from (path or URL), for the record.
    content_hash
        Hash of the archive's content, identifying the scan independent of its location.
    params
        The processing parameters, JSON-serialisable (see :func:`canonical_params_json`);
        their hash is the second half of the inspection's identity.
    software_version
        pipescan's version that produced the figures.
    sections
        One per section; chainages are stored to the millimetre and must be distinct at that
        resolution. NaN figures are stored as NULL (unmeasured).
    defects, frame_quality
        The merged defects and the per-frame registration quality.
    registration
        JSON summary of the registration (mean fitness, RMSE, degenerate frames, engine).
    status
        The inspection's status: ``"ok"``, ``"partial"``, ``"failed"``, ...
    threshold_table
        Name of the grading table the grades come from.
    point_count, frame_count, scanned_length_m
        Size of the scan: points and frames read, and the chainage length covered, in metres.
    start_source
        Where the scan's start came from (a key of ``pipescan.core.start.START_SOURCES``).
    """

    meta: InspectionMeta
    archive_uri: str
    content_hash: str
    params: Mapping[str, Any]
    software_version: str
    sections: Sequence[SectionMeasures]
    defects: Sequence[Defect]
    frame_quality: Sequence[FrameQuality] = ()
    registration: Mapping[str, Any] | None = None
    status: str = "ok"
    threshold_table: str = ""
    point_count: int = 0
    frame_count: int = 0
    scanned_length_m: float = 0.0
    start_source: str | None = None


def save_inspection(engine: Engine, inspection: InspectionToSave) -> int:
    """Store one processed inspection, replacing an earlier save of the same work.

    In one transaction: the asset is inserted or updated from ``inspection.meta``; any
    inspection of the same asset with the same ``content_hash`` and parameter hash is deleted
    (with its sections, defects and frame quality); the inspection and all its rows are
    inserted, under the replaced inspection's id if there was one. If anything fails, the
    database is left as it was.

    Parameters
    ----------
    engine
        From ``pipescan.storage.database.db.connect``.
    inspection
        What to store (see :class:`InspectionToSave`).

    Returns
    -------
    int
        The inspection's id: the id of the earlier save when it replaced one (the same
        archive and parameters keep their id), a new one otherwise.

    Raises
    ------
    StorageError
        If a value cannot be stored (non-finite chainages or coverage, duplicate chainages,
        unknown status, parameters without a JSON form) or the database refuses the write;
        nothing is written then.
    """
    return save_inspections(engine, [inspection])[0]


@dataclass(frozen=True)
class _Prepared:
    # An inspection validated and converted to rows, ready to write.
    where: str
    meta: InspectionMeta
    identity: dict[str, str]
    values: dict[str, Any]
    section_rows: list[dict[str, Any]]
    defect_rows: list[dict[str, Any]]
    quality_rows: list[dict[str, Any]]


def _prepare(item: InspectionToSave) -> _Prepared:
    meta = item.meta
    inspected_at = meta.inspected_at
    if inspected_at.tzinfo is None or inspected_at.utcoffset() is None:
        # inspection.toml without an offset (or a bare date) gives a naive datetime: UTC is
        # the only reading that does not depend on the machine that processed the scan.
        inspected_at = inspected_at.replace(tzinfo=UTC)
    # Never store credentials, whoever calls: the URL is printed and rendered from here on.
    archive_uri = strip_credentials(item.archive_uri)
    where = f"inspection of asset {meta.asset_id} from {archive_uri}"
    canonical = canonical_params_json(item.params)
    registration_json = (
        None if item.registration is None else json.loads(canonical_params_json(item.registration))
    )
    section_rows = [_section_row(s) for s in item.sections]
    _check_unique([r["chainage_start_mm"] for r in section_rows], "sections", " mm of chainage")
    defect_rows = [_defect_row(d) for d in item.defects]
    quality_rows = [_frame_quality_row(q) for q in item.frame_quality]
    _check_unique([r["frame_index"] for r in quality_rows], "frame quality rows", " (frame)")
    values = {
        "inspected_at": inspected_at,
        "archive_uri": archive_uri,
        "params_json": json.loads(canonical),
        "software_version": item.software_version,
        "status": item.status,
        "point_count": int(item.point_count),
        "frame_count": int(item.frame_count),
        "scanned_length_m": _require_finite(item.scanned_length_m, "scanned_length_m", where),
        "registration_json": registration_json,
        "threshold_table": item.threshold_table,
        "direction": meta.direction,
        "chainage_offset_m": _require_finite(meta.chainage_offset_m, "chainage_offset_m", where),
        "start_source": item.start_source,
        **_summary_columns(item.sections),
    }
    return _Prepared(
        where=where,
        meta=meta,
        identity={
            "asset_id": meta.asset_id,
            "content_hash": item.content_hash,
            "params_hash": hashlib.sha256(canonical.encode("utf-8")).hexdigest(),
        },
        values=values,
        section_rows=section_rows,
        defect_rows=defect_rows,
        quality_rows=quality_rows,
    )


def _write(session: Session, prepared: Sequence[_Prepared]) -> list[int]:
    # Set-based, whatever the batch's size: one upsert of the assets, one delete of the
    # inspections being replaced, one insert of the inspections, then one bulk insert each of
    # sections, defects and frame quality. A handful of round trips per batch, not per row.
    _upsert_assets(session, (p.meta for p in prepared))
    # A later item with the same identity replaces an earlier one of the batch.
    last = {tuple(p.identity.values()): index for index, p in enumerate(prepared)}
    kept = sorted(last.values())
    keys = sa.tuple_(Inspection.asset_id, Inspection.content_hash, Inspection.params_hash)
    # A re-save of the same work keeps the id it was stored under: reports, exports and
    # e-mails quote it, and it still names the same archive processed the same way.
    stored_ids: dict[tuple[str, ...], int] = {}
    for chunk in _chunks(list(last), 300):
        found = session.execute(
            sa.select(
                Inspection.asset_id, Inspection.content_hash, Inspection.params_hash, Inspection.id
            ).where(keys.in_(chunk))
        ).all()
        stored_ids.update({(a, c, p): i for a, c, p, i in found})
        session.execute(
            sa.delete(Inspection).where(keys.in_(chunk)),
            execution_options={"synchronize_session": False},
        )
    now = utc_now()

    def row(k: int) -> dict[str, Any]:
        return {**prepared[k].identity, **prepared[k].values, "created_at": now}

    def stored_id(k: int) -> int | None:
        return stored_ids.get(tuple(prepared[k].identity.values()))

    new_ids = {k: i for k in kept if (i := stored_id(k)) is not None}
    if new_ids:
        session.connection().execute(
            sa.insert(Inspection), [{**row(k), "id": i} for k, i in new_ids.items()]
        )
    fresh = [k for k in kept if k not in new_ids]
    if fresh:
        inserted = session.connection().execute(
            sa.insert(Inspection).returning(Inspection.id, sort_by_parameter_order=True),
            [row(k) for k in fresh],
        )
        new_ids.update(zip(fresh, inserted.scalars().all(), strict=True))
    _insert_sections(session, [(new_ids[k], prepared[k].section_rows) for k in kept])
    _insert_defects(session, [(new_ids[k], prepared[k].defect_rows) for k in kept])
    _insert_frame_quality(session, [(new_ids[k], prepared[k].quality_rows) for k in kept])
    return [new_ids[last[tuple(p.identity.values())]] for p in prepared]


def save_inspections(engine: Engine, inspections: Iterable[InspectionToSave]) -> list[int]:
    """Store several processed inspections in one transaction: a bulk import.

    Each is saved as by :func:`save_inspection` (replacing an earlier save of the same
    archive and parameters; a later item of the batch replaces an earlier one the same way),
    but they all commit together, or not at all. On PostgreSQL one commit for many inspections
    saves a disk flush per inspection; choose batches that are cheap to redo (a few hundred
    inspections).

    Parameters
    ----------
    engine
        From ``pipescan.storage.database.db.connect``.
    inspections
        What to store, in order.

    Returns
    -------
    list of int
        The inspections' ids, in order (a replaced save keeps its id).

    Raises
    ------
    StorageError
        As :func:`save_inspection`, naming the inspection at fault; nothing is written then.
        Every inspection is validated before anything is written.
    """
    # Validate and convert everything before touching the database.
    prepared = [_prepare(item) for item in inspections]
    if not prepared:
        return []
    what = (
        f"the {prepared[0].where}"
        if len(prepared) == 1
        else f"a batch of {len(prepared)} inspections, from the {prepared[0].where} on"
    )
    try:
        with session_scope(engine, write=True) as session:
            return _write(session, prepared)
    except sa.exc.DBAPIError as exc:
        raise StorageError(
            f"could not save {what}: {exc.orig}",
            hint="nothing was written; if the database was locked, retry",
        ) from exc


# ---------------------------------------------------------------------------------------------
# Reading


def record_statement(ids: Any = None) -> sa.Select[Any]:
    """Inspection, asset and section count of the inspections ``ids`` selects (a select of
    inspection ids, or a list; None for all), for :func:`inspection_records`.

    The section counts come from one grouped count over those inspections' sections (a range
    of the sections' primary key each), joined in: not a subquery run again for every row.
    """
    counted = sa.select(Section.inspection_id, sa.func.count().label("section_count"))
    statement = sa.select(Inspection, Asset).join(Asset, Inspection.asset_id == Asset.asset_id)
    if ids is not None:
        counted = counted.where(Section.inspection_id.in_(ids))
        statement = statement.where(Inspection.id.in_(ids))
    counts = counted.group_by(Section.inspection_id).subquery("section_counts")
    return statement.add_columns(sa.func.coalesce(counts.c.section_count, 0)).outerjoin(
        counts, counts.c.inspection_id == Inspection.id
    )


def inspection_records(session: Session, statement: sa.Select[Any]) -> list[InspectionRecord]:
    """The records of a :func:`record_statement`, in its order."""
    return [_inspection_record(i, a, n) for i, a, n in session.execute(statement).all()]


def _no_inspection(inspection_id: int) -> StorageError:
    return StorageError(
        f"no inspection with id {inspection_id}",
        hint="list the stored inspections and their ids with `pipescan inspections`",
    )


def get_inspection_row(session: Session, inspection_id: int) -> Inspection:
    """The stored inspection's row, in a session the caller holds.

    Raises
    ------
    StorageError
        The one "no inspection with id" error, when the inspection is not stored.
    """
    row = session.get(Inspection, inspection_id)
    if row is None:
        raise _no_inspection(inspection_id)
    return row


def get_asset(engine: Engine, asset_id: str) -> AssetRecord:
    """One stored asset, with its number of inspections and latest inspection date.

    Raises
    ------
    StorageError
        If there is no asset with that id.
    """
    found = _asset_records(engine, Asset.asset_id == asset_id)
    if not found:
        raise StorageError(
            f"no asset {asset_id!r} in the database",
            field="asset_id",
            hint="list the stored assets with `pipescan assets`",
        )
    return found[0]


def list_assets(engine: Engine) -> list[AssetRecord]:
    """Every asset, by asset id, with its number of inspections and latest inspection date."""
    return _asset_records(engine)


def _asset_records(engine: Engine, *where: Any) -> list[AssetRecord]:
    statement = (
        sa.select(
            Asset,
            sa.func.count(Inspection.id),
            sa.func.max(Inspection.inspected_at),
        )
        .where(*where)
        .outerjoin(Inspection, Inspection.asset_id == Asset.asset_id)
        .group_by(Asset.asset_id)
        .order_by(Asset.asset_id)
    )
    with session_scope(engine) as session:
        records = []
        # max() keeps the column's type, so the date comes back aware, in UTC.
        for asset, count, last in session.execute(statement).all():
            records.append(
                AssetRecord(
                    asset_id=asset.asset_id,
                    upstream_node=asset.upstream_node,
                    downstream_node=asset.downstream_node,
                    nominal_diameter_m=asset.nominal_diameter_m,
                    pipe_shape=asset.pipe_shape,
                    material=asset.material,
                    inspection_count=count,
                    last_inspected_at=last,
                )
            )
        return records


def list_inspections(source: Reader, asset_id: str | None = None) -> list[InspectionRecord]:
    """The stored inspections, of one asset or of all, by asset, date and id."""
    ids = None
    if asset_id is not None:
        ids = sa.select(Inspection.id).where(Inspection.asset_id == asset_id)
    statement = record_statement(ids).order_by(
        Inspection.asset_id, Inspection.inspected_at, Inspection.id
    )
    with reading(source) as session:
        return inspection_records(session, statement)


def get_inspection(source: Reader, inspection_id: int) -> InspectionRecord:
    """One inspection by id.

    Raises
    ------
    StorageError
        If there is no inspection with that id.
    """
    with reading(source) as session:
        found = inspection_records(session, record_statement([inspection_id]))
        if not found:
            raise _no_inspection(inspection_id)
        return found[0]


def find_inspection(
    source: Reader, asset_id: str, content_hash: str, params_hash: str
) -> int | None:
    """The id of the inspection with this identity (asset, archive content, parameters), or
    None. Saving an identity again replaces the earlier inspection, so there is at most one."""
    statement = sa.select(sa.func.max(Inspection.id)).where(
        Inspection.asset_id == asset_id,
        Inspection.content_hash == content_hash,
        Inspection.params_hash == params_hash,
    )
    with reading(source) as session:
        return session.scalar(statement)


def list_sections(source: Reader, inspection_id: int) -> list[SectionMeasures]:
    """An inspection's sections by chainage, with ``contour_m`` as (M, 2) float64 metres.

    Raises
    ------
    StorageError
        If there is no inspection with that id.
    """
    return _inspection_rows(
        source, inspection_id, Section, section_from_row, Section.chainage_start_mm
    )


def list_defects(source: Reader, inspection_id: int) -> list[Defect]:
    """An inspection's defects by start chainage.

    Raises
    ------
    StorageError
        If there is no inspection with that id.
    """
    return _inspection_rows(
        source, inspection_id, DefectRow, defect_from_row, DefectRow.chainage_start_m, DefectRow.id
    )


_Row = TypeVar("_Row")


def _inspection_rows(
    source: Reader,
    inspection_id: int,
    model: type[Section] | type[DefectRow] | type[FrameQualityRow],
    convert: Callable[[Any], _Row],
    *order_by: Any,
) -> list[_Row]:
    """One inspection's rows of ``model``, in ``order_by`` order, each ``convert``-ed.

    Raises
    ------
    StorageError
        If there is no inspection with that id.
    """
    statement = sa.select(model).where(model.inspection_id == inspection_id).order_by(*order_by)
    with reading(source) as session:
        get_inspection_row(session, inspection_id)
        return [convert(row) for row in session.scalars(statement)]


def defect_from_row(row: DefectRow) -> Defect:
    """The :class:`Defect` a stored defect row holds."""
    return Defect(
        code=row.code,
        measure=row.measure,
        chainage_start_m=row.chainage_start_m,
        chainage_end_m=row.chainage_end_m,
        peak_chainage_m=row.peak_chainage_m,
        peak_value=row.peak_value,
        peak_blockage_ratio=row.peak_blockage_ratio,
        grade=row.grade,
        clock_from_h=row.clock_from_h,
        clock_to_h=row.clock_to_h,
        characterisation=row.characterisation,
        lower_bound=bool(row.lower_bound),
    )


def list_frame_quality(source: Reader, inspection_id: int) -> list[FrameQuality]:
    """An inspection's per-frame registration quality by frame index.

    Raises
    ------
    StorageError
        If there is no inspection with that id.
    """
    return _inspection_rows(
        source, inspection_id, FrameQualityRow, _frame_quality_from_row, FrameQualityRow.frame_index
    )


def _frame_quality_from_row(row: FrameQualityRow) -> FrameQuality:
    return FrameQuality(
        index=row.frame_index, fitness=row.fitness, rmse_m=row.rmse_m, degenerate=row.degenerate
    )


def find_latest_inspection_id(source: Reader, asset_id: str | None = None) -> int | None:
    """The id of the most recent inspection (by ``inspected_at``, then the last saved), of
    one asset or of all; None if there is none."""
    statement = sa.select(Inspection.id).order_by(
        Inspection.inspected_at.desc(), Inspection.id.desc()
    )
    if asset_id is not None:
        statement = statement.where(Inspection.asset_id == asset_id)
    with reading(source) as session:
        return session.scalars(statement.limit(1)).first()


def list_section_trend(source: Reader, asset_id: str, chainage_m: float) -> list[TrendPoint]:
    """How the section at one chainage of an asset changed across its inspections.

    Parameters
    ----------
    asset_id
        The pipe asset.
    chainage_m
        A chainage from the upstream node, in metres; each inspection contributes the section
        whose interval ``[start, end)`` contains it (to the millimetre), if it has one.

    Returns
    -------
    list of TrendPoint
        In inspection date order (then save order).
    """
    chainage_mm = m_to_mm(chainage_m)
    statement = (
        sa.select(Inspection.id, Inspection.inspected_at, Section)
        .join(Section, Section.inspection_id == Inspection.id)
        .where(
            Inspection.asset_id == asset_id,
            Section.chainage_start_mm <= chainage_mm,
            Section.chainage_end_mm > chainage_mm,
        )
        .order_by(Inspection.inspected_at, Inspection.id)
    )
    with reading(source) as session:
        return [
            TrendPoint(inspection_id=i, inspected_at=t, section=section_from_row(s))
            for i, t, s in session.execute(statement).all()
        ]
