"""Read-only queries for the web view (``pipescan serve``): a read-only database URL, the
network's pipes with their latest figures, and pages of sections and inspections.

Every figure comes from the function that defines it elsewhere: the latest inspection of each
asset from :func:`pipescan.storage.database.queries.latest_per_asset_statement`, the stored
blockage summary written with the sections, the pipe's growth from
:func:`pipescan.storage.database.trends.worst_assets` (the growth of ``worst`` and the network
report), the line from :func:`pipescan.storage.database.network.asset_geometries`. The one
figure computed in SQL here is the worst condition class, with the rule of
:func:`pipescan.core.summary.worst_grade` (the lowest grade of the ``ok`` sections), so that the
network page does not read a million sections into Python; ``tests/test_web_api.py`` checks
that both agree. Nothing here writes.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any
from urllib.parse import quote

import numpy as np
import sqlalchemy as sa
from sqlalchemy.engine import Engine

from pipescan.core.model import SectionStatus
from pipescan.storage.database.db import StorageError, parse_database_url, session_scope
from pipescan.storage.database.models import Asset, Inspection, NetworkPipe, Section
from pipescan.storage.database.network import asset_geometries
from pipescan.storage.database.queries import defect_counts, latest_per_asset_statement
from pipescan.storage.database.repository import (
    InspectionRecord,
    inspection_records,
    mm_to_m,
    record_statement,
    section_from_row,
)
from pipescan.storage.database.trends import worst_assets

__all__ = [
    "MAX_PAGE_SIZE",
    "PipeRow",
    "database_version",
    "inspection_page",
    "network_pipes",
    "read_only_url",
    "section_page",
    "worst_grades",
]

MAX_PAGE_SIZE = 1000
"""The most rows one page of sections or inspections holds: a request cannot ask the
database for a whole network at once."""

_OK = SectionStatus.OK.value


def read_only_url(url: str) -> str:
    """The same database, opened so that no statement can write.

    SQLite: the file opened as a URI with ``mode=ro`` (SQLite refuses every write on the
    connection). PostgreSQL: every transaction starts read-only
    (``default_transaction_read_only``, set by the connection's options). Other databases are
    refused.

    Raises
    ------
    StorageError
        The URL names an in-memory SQLite database, a SQLite file that does not exist, or a
        database that is neither SQLite nor PostgreSQL.
    """
    parsed = parse_database_url(url)
    backend = parsed.get_backend_name()
    if backend == "sqlite":
        database = parsed.database or ""
        if database in ("", ":memory:") or database.startswith("file:"):
            raise StorageError(
                f"cannot serve the SQLite database {database or ':memory:'!r} read-only",
                hint="give the database file's path, e.g. --db surveys/pipescan.db",
            )
        path = Path(database).expanduser().resolve()
        if not path.is_file():
            raise StorageError(
                f"no database at {path}",
                hint="give the database `pipescan inspect` wrote with --db or "
                "PIPESCAN_DATABASE_URL",
            )
        return f"sqlite:///file:{quote(str(path))}?mode=ro&uri=true"
    if backend == "postgresql":
        options = parsed.query.get("options", "")
        if isinstance(options, tuple):
            options = " ".join(options)
        options = f"{options} -c default_transaction_read_only=on".strip()
        return parsed.update_query_dict({"options": options}).render_as_string(hide_password=False)
    raise StorageError(
        f"pipescan serve reads SQLite or PostgreSQL, not {backend}",
        hint="give a sqlite:/// or postgresql+psycopg:// URL",
    )


def is_read_only_error(exc: BaseException) -> bool:
    """Whether a database error is the refusal of a write on a read-only connection."""
    orig = getattr(exc, "orig", exc)
    if isinstance(orig, sqlite3.OperationalError):
        return "readonly" in str(orig)
    return "read-only transaction" in str(orig)


@dataclass(frozen=True)
class PipeRow:
    """One pipe on the network page: the asset, its latest inspection's figures and its line.

    ``worst_grade`` is the latest inspection's worst condition class (0 worst ... 4 best; None
    when no measured section was graded). ``peak_change_per_year`` is the pipe's growth (ratio
    per year; None without two measured scans far enough apart). ``line_xy`` is the pipe's
    line, upstream first, in ``crs`` (None without a geometry).
    """

    asset_id: str
    gis_id: str | None
    upstream_node: str | None
    downstream_node: str | None
    nominal_diameter_m: float | None
    material: str | None
    inspection_count: int
    last_inspection_id: int
    last_inspected_at: datetime
    measured_section_count: int
    worst_grade: int | None
    peak_blockage_ratio: float | None
    peak_chainage_m: float | None
    peak_change_per_year: float | None
    defect_count: int
    line_xy: tuple[tuple[float, float], ...] | None
    crs: str | None


def worst_grades(engine: Engine, ids_statement: Any) -> dict[int, int | None]:
    """The worst condition class of each inspection that ``ids_statement`` selects: the
    lowest grade of its ``ok`` sections (the rule of :func:`pipescan.core.summary.worst_grade`),
    one grouped query."""
    statement = (
        sa.select(Section.inspection_id, sa.func.min(Section.grade))
        .where(
            Section.inspection_id.in_(ids_statement),
            Section.status == _OK,
            Section.grade.is_not(None),
        )
        .group_by(Section.inspection_id)
    )
    with session_scope(engine) as session:
        return dict(session.connection().execute(statement).all())  # type: ignore[arg-type]


def _inspection_counts(engine: Engine) -> dict[str, int]:
    statement = sa.select(Inspection.asset_id, sa.func.count()).group_by(Inspection.asset_id)
    with session_scope(engine) as session:
        return dict(session.connection().execute(statement).all())  # type: ignore[arg-type]


def _latest_statement() -> sa.Select[Any]:
    """The latest inspection of each asset with the figures the network page shows: plain
    columns (no ORM objects, no JSON parsed), by asset id."""
    latest = latest_per_asset_statement()
    return (
        sa.select(
            Inspection.id,
            Inspection.asset_id,
            Inspection.inspected_at,
            Inspection.measured_section_count,
            Inspection.peak_blockage_ratio,
            Inspection.peak_chainage_start_mm,
            Asset.upstream_node,
            Asset.downstream_node,
            Asset.nominal_diameter_m,
            Asset.material,
        )
        .join(Asset, Asset.asset_id == Inspection.asset_id)
        .where(Inspection.id.in_(latest))
        .order_by(Inspection.asset_id)
    )


def network_pipes(engine: Engine) -> list[PipeRow]:
    """Every asset with an inspection, with its latest inspection's figures, by asset id."""
    with session_scope(engine) as session:
        records = session.connection().execute(_latest_statement()).all()
    grades = worst_grades(engine, latest_per_asset_statement())
    growth = {
        r.asset_id: r.peak_change_per_year
        for r in worst_assets(engine, by="current", limit=len(records) + 1)
    }
    counts = defect_counts(engine, [r.id for r in records])
    scans = _inspection_counts(engine)
    geometries = asset_geometries(engine, [r.asset_id for r in records])
    rows = []
    for r in records:
        geometry = geometries.get(r.asset_id)
        line = None
        if geometry is not None:
            xy = np.asarray(geometry.line.coords)[:, :2]
            line = tuple((float(x), float(y)) for x, y in xy)
        rows.append(
            PipeRow(
                asset_id=r.asset_id,
                gis_id=None if geometry is None else geometry.gis_id,
                upstream_node=r.upstream_node,
                downstream_node=r.downstream_node,
                nominal_diameter_m=r.nominal_diameter_m,
                material=r.material,
                inspection_count=scans.get(r.asset_id, 1),
                last_inspection_id=r.id,
                last_inspected_at=r.inspected_at,
                measured_section_count=r.measured_section_count,
                worst_grade=grades.get(r.id),
                peak_blockage_ratio=r.peak_blockage_ratio,
                peak_chainage_m=(
                    None if r.peak_chainage_start_mm is None else mm_to_m(r.peak_chainage_start_mm)
                ),
                peak_change_per_year=growth.get(r.asset_id),
                defect_count=counts.get(r.id, 0),
                line_xy=line,
                crs=None if geometry is None else geometry.crs,
            )
        )
    return rows


def database_version(engine: Engine) -> tuple[Any, ...]:
    """A cheap fingerprint of what the network page shows: it changes when an inspection is
    saved or replaced, or a GIS layer imported (so a cached page is rebuilt)."""
    with session_scope(engine) as session:
        inspections = session.execute(
            sa.select(sa.func.count(Inspection.id), sa.func.max(Inspection.id))
        ).one()
        layer = session.execute(
            sa.select(sa.func.count(NetworkPipe.gis_id), sa.func.max(NetworkPipe.imported_at))
        ).one()
    return (*inspections, *layer)


def section_page(
    engine: Engine, inspection_id: int, *, offset: int = 0, limit: int = 100
) -> list[Any]:
    """Sections of an inspection by chainage, without contours: rows ``offset`` to
    ``offset + limit`` (``limit`` at most :data:`MAX_PAGE_SIZE`).

    Raises
    ------
    StorageError
        ``limit`` or ``offset`` out of range.
    """
    _check_page(offset, limit)
    columns = [c for c in Section.__table__.c if c.name != "contour_json"]
    statement = (
        sa.select(*columns, sa.null().label("contour_json"))
        .where(Section.inspection_id == inspection_id)
        .order_by(Section.chainage_start_mm)
        .offset(offset)
        .limit(limit)
    )
    with session_scope(engine) as session:
        return [section_from_row(row) for row in session.connection().execute(statement)]


def inspection_page(
    engine: Engine,
    *,
    asset_id: str | None = None,
    ids: Sequence[int] | None = None,
    offset: int = 0,
    limit: int = 100,
) -> list[InspectionRecord]:
    """Stored inspections (of one asset, or these ids, or all) by asset, date and id: rows
    ``offset`` to ``offset + limit`` (``limit`` at most :data:`MAX_PAGE_SIZE`)."""
    _check_page(offset, limit)
    page = sa.select(Inspection.id)
    if asset_id is not None:
        page = page.where(Inspection.asset_id == asset_id)
    if ids is not None:
        page = page.where(Inspection.id.in_(list(ids)))
    page = (
        page.order_by(Inspection.asset_id, Inspection.inspected_at, Inspection.id)
        .offset(offset)
        .limit(limit)
    )
    with session_scope(engine) as session:
        wanted = list(session.scalars(page))
        if not wanted:
            return []
        statement = record_statement(wanted).order_by(
            Inspection.asset_id, Inspection.inspected_at, Inspection.id
        )
        return inspection_records(session, statement)


def _check_page(offset: int, limit: int) -> None:
    if not 1 <= limit <= MAX_PAGE_SIZE:
        raise StorageError(
            f"page size {limit} is out of range", field="limit", hint=f"give 1-{MAX_PAGE_SIZE}"
        )
    if offset < 0:
        raise StorageError(f"offset {offset} is negative", field="offset", hint="give 0 or more")
