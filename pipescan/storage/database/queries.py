"""Read-only queries beyond ``repository.py``: which inspections (the latest of each asset, the
earlier scans of a pipe, one row per scan), light blockage profiles (no contours) and defect
counts, for the reports and the trends.

"Latest" and "earlier" are chosen by the database, with window functions (``row_number()``,
on SQLite and PostgreSQL alike), and come back as records: no inspection list is filtered in
Python, and no count runs once per row. Like the repository, every function opens and closes
its own session and returns core dataclasses or the repository's records; nothing here writes.

Two rules hold throughout:

- **Order in time** is ``inspected_at``, then the id (an inspection saved earlier on the same
  date counts as earlier).
- **One scan counts once.** An earlier scan of a pipe is an archive with another content hash
  than the inspection at hand; when it was processed more than once (other parameters), its
  latest save before that inspection stands for it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

import sqlalchemy as sa
from sqlalchemy.orm import Session

from pipescan.core.model import Defect, SectionMeasures
from pipescan.storage.database.db import Reader, StorageError, reading
from pipescan.storage.database.models import DefectRow, Inspection, Section
from pipescan.storage.database.repository import (
    InspectionRecord,
    defect_from_row,
    get_inspection_row,
    inspection_records,
    record_statement,
    section_from_row,
)

__all__ = [
    "ScanRecord",
    "defect_counts",
    "defects_by_inspection",
    "earlier_scans_statement",
    "find_previous_scans",
    "latest_per_asset_statement",
    "list_earlier_inspections",
    "list_earlier_scans",
    "list_network_inspections",
    "scans_statement",
    "section_profiles",
]


def _aware(value: datetime) -> datetime:
    return value if value.tzinfo is not None else value.replace(tzinfo=UTC)


def latest_per_asset_statement(*where: Any) -> sa.Select[Any]:
    """The id of each asset's latest inspection among those ``where`` selects.

    ``row_number()`` over each asset's inspections, newest first (date, then id); the first
    row of each asset is kept. One column, ``id``.
    """
    ranked = (
        sa.select(
            Inspection.id,
            sa.func.row_number()
            .over(
                partition_by=Inspection.asset_id,
                order_by=(Inspection.inspected_at.desc(), Inspection.id.desc()),
            )
            .label("recency"),
        )
        .where(*where)
        .subquery("ranked")
    )
    return sa.select(ranked.c.id).where(ranked.c.recency == 1)


def earlier_scans_statement(
    inspection_ids: Sequence[int], *, limit: int | None = None
) -> sa.Select[Any]:
    """For each given inspection, its asset's earlier scans (see the module's rules).

    Each inspection is joined to its asset's inspections that come before it and hold another
    archive; ``row_number()`` keeps each archive's latest save, then numbers the scans newest
    first, and ``limit`` keeps that many per inspection. Named columns: ``of_id`` (the given
    inspection), ``recency`` (1 for the previous scan) and the fields of :class:`ScanRecord`,
    ordered by ``of_id`` and ``recency``.
    """
    target = Inspection.__table__.alias("target")
    earlier = Inspection.__table__.alias("earlier")
    before = sa.or_(
        earlier.c.inspected_at < target.c.inspected_at,
        sa.and_(earlier.c.inspected_at == target.c.inspected_at, earlier.c.id < target.c.id),
    )
    pairs = (
        sa.select(
            target.c.id.label("of_id"),
            earlier.c.id.label("earlier_id"),
            earlier.c.inspected_at,
            earlier.c.content_hash,
            earlier.c.measured_section_count,
            earlier.c.mean_blockage_ratio,
            earlier.c.peak_blockage_ratio,
            sa.func.row_number()
            .over(partition_by=(target.c.id, earlier.c.content_hash), order_by=earlier.c.id.desc())
            .label("save_rank"),
        )
        .select_from(
            target.join(
                earlier,
                sa.and_(
                    earlier.c.asset_id == target.c.asset_id,
                    earlier.c.content_hash != target.c.content_hash,
                    before,
                ),
            )
        )
        .where(target.c.id.in_(list(inspection_ids)))
        .subquery("pairs")
    )
    scans = (
        sa.select(
            pairs.c.of_id,
            pairs.c.earlier_id.label("id"),
            pairs.c.inspected_at,
            pairs.c.content_hash,
            pairs.c.measured_section_count,
            pairs.c.mean_blockage_ratio,
            pairs.c.peak_blockage_ratio,
            sa.func.row_number()
            .over(
                partition_by=pairs.c.of_id,
                order_by=(pairs.c.inspected_at.desc(), pairs.c.earlier_id.desc()),
            )
            .label("recency"),
        )
        .where(pairs.c.save_rank == 1)
        .subquery("scans")
    )
    statement = sa.select(*scans.c)
    if limit is not None:
        statement = statement.where(scans.c.recency <= limit)
    return statement.order_by(scans.c.of_id, scans.c.recency)


@dataclass(frozen=True)
class ScanRecord:
    """An earlier scan of a pipe, as its history needs it: when, and its stored blockage
    summary (see :class:`~pipescan.storage.database.repository.InspectionRecord`)."""

    id: int
    inspected_at: datetime
    content_hash: str
    measured_section_count: int
    mean_blockage_ratio: float | None
    peak_blockage_ratio: float | None


def list_earlier_scans(
    source: Reader, inspection_ids: Sequence[int], *, limit: int | None = None
) -> dict[int, list[ScanRecord]]:
    """The earlier scans of each inspection's pipe, most recent first (see the module's rules).

    Parameters
    ----------
    inspection_ids
        The inspections; an unknown id maps to ``[]``.
    limit
        At most this many per inspection (the most recent).

    Returns
    -------
    dict
        Inspection id to its pipe's earlier scans, newest first.
    """
    if not inspection_ids:
        return {}
    with reading(source) as session:
        return _earlier_scans(session, inspection_ids, limit)


def _earlier_scans(
    session: Session, inspection_ids: Sequence[int], limit: int | None
) -> dict[int, list[ScanRecord]]:
    found: dict[int, list[ScanRecord]] = {i: [] for i in inspection_ids}
    fields = [f.name for f in dataclasses.fields(ScanRecord)]
    for row in session.connection().execute(earlier_scans_statement(inspection_ids, limit=limit)):
        found[row.of_id].append(ScanRecord(*(getattr(row, f) for f in fields)))
    return found


def list_earlier_inspections(
    source: Reader, inspection_id: int, *, limit: int | None = None
) -> list[ScanRecord]:
    """The earlier scans of the same asset as this inspection, most recent first (see the
    module's rules): its trend history.

    Raises
    ------
    StorageError
        If there is no inspection with that id.
    """
    with reading(source) as session:  # one session for the check and the read
        get_inspection_row(session, inspection_id)
        return _earlier_scans(session, [inspection_id], limit)[inspection_id]


def find_previous_scans(
    source: Reader, records: Sequence[InspectionRecord]
) -> dict[int, ScanRecord]:
    """For each inspection, its pipe's previous scan, if any (see the module's rules).

    Returns
    -------
    dict
        Inspection id to its previous scan; ids without one are left out.
    """
    earlier = list_earlier_scans(source, [r.id for r in records], limit=1)
    return {i: scans[0] for i, scans in earlier.items() if scans}


def scans_statement(*where: Any) -> sa.Select:  # type: ignore[type-arg]
    """One row per scan of an asset (its latest save), among the inspections ``where`` selects.

    A window function ranks the saves of each (asset, content hash) by id; the first stands for
    the scan. Rows have the named columns ``id, asset_id, inspected_at,
    measured_section_count, mean_blockage_ratio, peak_blockage_ratio,
    peak_chainage_start_mm``, ordered by asset, date and id.
    """
    ranked = (
        sa.select(
            Inspection.id,
            Inspection.asset_id,
            Inspection.inspected_at,
            Inspection.measured_section_count,
            Inspection.mean_blockage_ratio,
            Inspection.peak_blockage_ratio,
            Inspection.peak_chainage_start_mm,
            sa.func.row_number()
            .over(
                partition_by=(Inspection.asset_id, Inspection.content_hash),
                order_by=Inspection.id.desc(),
            )
            .label("save_rank"),
        )
        .where(*where)
        .subquery("ranked")
    )
    columns = [c for c in ranked.c if c.name != "save_rank"]
    return (
        sa.select(*columns)
        .where(ranked.c.save_rank == 1)
        .order_by(ranked.c.asset_id, ranked.c.inspected_at, ranked.c.id)
    )


def section_profiles(
    source: Reader, inspection_ids: Sequence[int]
) -> dict[int, list[SectionMeasures]]:
    """The sections of several inspections without their contours, by chainage.

    Only the columns a blockage profile needs are read (no contour JSON), so loading the
    history of a long pipe stays cheap.

    Returns
    -------
    dict
        Inspection id to its sections; an id with no sections (or unknown) maps to ``[]``.
    """
    profiles: dict[int, list[SectionMeasures]] = {i: [] for i in inspection_ids}
    if not inspection_ids:
        return profiles
    columns = (
        Section.inspection_id,
        Section.chainage_start_mm,
        Section.chainage_end_mm,
        Section.nominal_area_m2,
        Section.status,
        Section.point_count,
        Section.coverage_ratio,
        Section.open_area_m2,
        Section.blockage_ratio,
        Section.ovality_ratio,
        Section.deformation_ratio,
        Section.deposit_height_ratio,
        Section.grade,
        Section.blockage_uncertainty_ratio,
        Section.ovality_uncertainty_ratio,
        Section.deformation_uncertainty_ratio,
        Section.deposit_height_uncertainty_ratio,
        Section.water_depth_ratio,
        Section.water_depth_uncertainty_ratio,
        # Named, so that section_from_row finds it (None) without a failed lookup per row.
        sa.null().label("contour_json"),
    )
    statement = (
        sa.select(*columns)
        .where(Section.inspection_id.in_(list(inspection_ids)))
        .order_by(Section.inspection_id, Section.chainage_start_mm)
    )
    with reading(source) as session:
        for row in session.connection().execute(statement):
            profiles[row.inspection_id].append(section_from_row(row))
    return profiles


def defect_counts(source: Reader, inspection_ids: Sequence[int]) -> dict[int, int]:
    """The number of defects of each inspection (0 for one without defects)."""
    counts = dict.fromkeys(inspection_ids, 0)
    if not inspection_ids:
        return counts
    statement = (
        sa.select(DefectRow.inspection_id, sa.func.count())
        .where(DefectRow.inspection_id.in_(list(inspection_ids)))
        .group_by(DefectRow.inspection_id)
    )
    with reading(source) as session:
        for inspection_id, count in session.execute(statement):
            counts[inspection_id] = count
    return counts


def defects_by_inspection(source: Reader, inspection_ids: Sequence[int]) -> dict[int, list[Defect]]:
    """The defects of each inspection, by start chainage (an empty list for one without)."""
    out: dict[int, list[Defect]] = {i: [] for i in inspection_ids}
    if not inspection_ids:
        return out
    statement = (
        sa.select(DefectRow)
        .where(DefectRow.inspection_id.in_(list(inspection_ids)))
        .order_by(DefectRow.inspection_id, DefectRow.chainage_start_m, DefectRow.id)
    )
    with reading(source) as session:
        for row in session.scalars(statement):
            out[row.inspection_id].append(defect_from_row(row))
    return out


def list_network_inspections(
    source: Reader,
    *,
    since: datetime | None = None,
    inspection_ids: Sequence[int] | None = None,
) -> list[InspectionRecord]:
    """The inspections a network summary covers: the latest one of each asset.

    Parameters
    ----------
    since
        Only inspections taken at or after this time (a naive datetime is taken as UTC).
    inspection_ids
        Only these inspections (e.g. those of one scheduled run). Combined with ``since``
        when both are given.

    Returns
    -------
    list of InspectionRecord
        One per asset (its most recent qualifying inspection), by asset id.

    Raises
    ------
    StorageError
        If an id in ``inspection_ids`` is not stored.
    """
    where: list[Any] = []
    if inspection_ids is not None:
        where.append(Inspection.id.in_(list(inspection_ids)))
    if since is not None:
        where.append(Inspection.inspected_at >= _aware(since))
    latest = latest_per_asset_statement(*where)
    with reading(source) as session:
        if inspection_ids is not None:
            known = set(
                session.scalars(
                    sa.select(Inspection.id).where(Inspection.id.in_(list(inspection_ids)))
                )
            )
            missing = sorted(set(inspection_ids) - known)
            if missing:
                raise StorageError(
                    f"no inspection with id {', '.join(map(str, missing))}",
                    field="inspection_ids",
                    hint="list the stored inspections with `pipescan inspections`",
                )
        return inspection_records(session, record_statement(latest).order_by(Inspection.asset_id))
