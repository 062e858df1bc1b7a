"""Read-only queries the reports need beyond ``repository.py``: earlier inspections of an
asset, light blockage profiles (no contours) and the inspections of a network run.

Like the repository, every function opens and closes its own session and returns core
dataclasses or the repository's records; nothing here writes.
"""

from __future__ import annotations

from collections.abc import Sequence
from datetime import UTC, datetime

import sqlalchemy as sa
from sqlalchemy.engine import Engine

from pipescan.core.model import SectionMeasures
from pipescan.storage.database.db import StorageError, session_scope
from pipescan.storage.database.models import DefectRow, Section
from pipescan.storage.database.repository import (
    InspectionRecord,
    get_inspection,
    list_inspections,
    section_from_row,
)

__all__ = [
    "defect_counts",
    "earlier_inspections",
    "network_inspections",
    "previous_inspections",
    "section_profiles",
]


def _aware(value: datetime) -> datetime:
    return value if value.tzinfo is not None else value.replace(tzinfo=UTC)


def earlier_inspections(
    engine: Engine, inspection_id: int, *, limit: int | None = None
) -> list[InspectionRecord]:
    """The inspections of the same asset taken before this one, most recent first.

    "Before" orders by ``inspected_at``, then by id (an inspection saved earlier on the same
    date counts as earlier). Re-processings of the same archive under other parameters are
    excluded: they are the same scan, not an earlier state of the pipe.

    Raises
    ------
    StorageError
        If there is no inspection with that id.
    """
    current = get_inspection(engine, inspection_id)
    earlier = [
        r
        for r in list_inspections(engine, current.asset_id)
        if (r.inspected_at, r.id) < (current.inspected_at, current.id)
        and r.content_hash != current.content_hash
    ]
    earlier.sort(key=lambda r: (r.inspected_at, r.id), reverse=True)
    return earlier[:limit] if limit is not None else earlier


def section_profiles(
    engine: Engine, inspection_ids: Sequence[int]
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
    )
    statement = (
        sa.select(*columns)
        .where(Section.inspection_id.in_(list(inspection_ids)))
        .order_by(Section.inspection_id, Section.chainage_start_mm)
    )
    with session_scope(engine) as session:
        for row in session.execute(statement):
            profiles[row.inspection_id].append(section_from_row(row))
    return profiles


def defect_counts(engine: Engine, inspection_ids: Sequence[int]) -> dict[int, int]:
    """The number of defects of each inspection (0 for one without defects)."""
    counts = dict.fromkeys(inspection_ids, 0)
    if not inspection_ids:
        return counts
    statement = (
        sa.select(DefectRow.inspection_id, sa.func.count())
        .where(DefectRow.inspection_id.in_(list(inspection_ids)))
        .group_by(DefectRow.inspection_id)
    )
    with session_scope(engine) as session:
        for inspection_id, count in session.execute(statement):
            counts[inspection_id] = count
    return counts


def network_inspections(
    engine: Engine,
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
    records = list_inspections(engine)
    if inspection_ids is not None:
        wanted = set(inspection_ids)
        known = {r.id for r in records}
        missing = sorted(wanted - known)
        if missing:
            raise StorageError(
                f"no inspection with id {', '.join(map(str, missing))}",
                field="inspection_ids",
                hint="list the stored inspections with `pipescan inspections`",
            )
        records = [r for r in records if r.id in wanted]
    if since is not None:
        since = _aware(since)
        records = [r for r in records if r.inspected_at >= since]
    latest: dict[str, InspectionRecord] = {}
    for r in records:
        best = latest.get(r.asset_id)
        if best is None or (r.inspected_at, r.id) > (best.inspected_at, best.id):
            latest[r.asset_id] = r
    return [latest[a] for a in sorted(latest)]


def previous_inspections(
    engine: Engine, records: Sequence[InspectionRecord]
) -> dict[int, InspectionRecord]:
    """For each inspection, the asset's latest earlier inspection of another scan, if any.

    Returns
    -------
    dict
        Inspection id to its previous inspection; ids without one are left out.
    """
    assets = {r.asset_id for r in records}
    by_asset: dict[str, list[InspectionRecord]] = {a: [] for a in assets}
    for r in list_inspections(engine):
        if r.asset_id in assets:
            by_asset[r.asset_id].append(r)
    previous: dict[int, InspectionRecord] = {}
    for r in records:
        earlier = [
            e
            for e in by_asset[r.asset_id]
            if (e.inspected_at, e.id) < (r.inspected_at, r.id) and e.content_hash != r.content_hash
        ]
        if earlier:
            previous[r.id] = max(earlier, key=lambda e: (e.inspected_at, e.id))
    return previous
