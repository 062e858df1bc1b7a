"""Blockage over time from the database: one asset's trend, and the network's worst pipes.

Two questions from asset teams drive this module: "how has blockage at 37 m along pipe
MH1042-MH1043 changed since 2022?" (:func:`asset_trend`) and "which pipes got worse fastest?"
(:func:`worst_assets`). The figures follow the rules of :mod:`pipescan.core.trends` (growth
per year, the alignment of surveys) and :mod:`pipescan.core.summary` (measured sections, the
peak blockage); this module only reads the rows they need:

- Only **measured** sections count: status ``ok`` with a blockage ratio. An unmeasured section
  is a gap (NaN in arrays, None in records), never a blockage of 0.
- **One scan counts once.** When the same archive (content hash) of an asset was processed more
  than once with different parameters, the latest save stands for it; the database picks it
  (:func:`pipescan.storage.database.queries.scans_statement`, a window function), not
  Python.
- Chainages in a trend are those of the reference survey (the latest measured one).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from typing import Any, Literal

import numpy as np
import sqlalchemy as sa
from sqlalchemy.engine import Engine

from pipescan.core.model import SectionStatus
from pipescan.core.trends import (
    DEFAULT_MAX_OFFSET_M,
    estimate_offset,
    growth_per_year,
    rasterise,
    robust_slopes,
    shift,
    years,
)
from pipescan.storage.database.db import StorageError, session_scope
from pipescan.storage.database.models import Asset, Inspection, Section
from pipescan.storage.database.queries import scans_statement
from pipescan.storage.database.repository import mm_to_m

__all__ = [
    "AssetRanking",
    "AssetTrend",
    "SurveyAlignment",
    "asset_trend",
    "trend_statement",
    "worst_assets",
]

_OK = SectionStatus.OK.value


# ---------------------------------------------------------------------------------------------
# Records


@dataclass(frozen=True)
class SurveyAlignment:
    """One inspection in a trend: when, how well measured, and how it was aligned.

    ``offset_m`` was added to the inspection's stored chainages to line it up with the
    reference survey; ``correlation`` is the profile correlation at that offset (None when
    it could not be estimated, e.g. a featureless profile). The blockage figures cover the
    measured sections; None when there were none.
    """

    inspection_id: int
    inspected_at: datetime
    offset_m: float
    correlation: float | None
    is_reference: bool
    measured_section_count: int
    mean_blockage_ratio: float | None
    peak_blockage_ratio: float | None
    peak_chainage_m: float | None


@dataclass(frozen=True)
class AssetTrend:
    """Blockage along one asset across its inspections, aligned by chainage.

    Attributes
    ----------
    chainage_start_m : (K,) float64 array
        Start of each chainage cell, in the reference survey's chainage, metres.
    blockage_ratio : (N, K) float64 array
        Per inspection (in date order, as in ``surveys``) and cell; NaN where unmeasured.
    section_status : (N, K) object array
        The status of the section at each cell (``"ok"``, ``"low_coverage"``, ...); None
        where the inspection has no section there.
    change_per_year : (K,) float64 array
        Growth per year of each cell's blockage (Theil–Sen, as
        :func:`pipescan.core.trends.growth_per_year`), ratio per year; NaN where no two
        inspections far enough apart measured the cell.
    measured_count : (K,) int array
        How many inspections measured each cell.
    mean_change_per_year, peak_change_per_year
        Growth per year of the inspections' mean and peak blockage
        (:func:`pipescan.core.trends.growth_per_year`); the peak's is the pipe's growth, as
        ``worst --by growth`` and the network report give it. None without two measured
        inspections far enough apart.
    """

    asset_id: str
    upstream_node: str | None
    downstream_node: str | None
    nominal_diameter_m: float | None
    pipe_shape: str
    material: str | None
    step_m: float
    surveys: tuple[SurveyAlignment, ...]
    chainage_start_m: np.ndarray
    blockage_ratio: np.ndarray
    section_status: np.ndarray
    change_per_year: np.ndarray
    measured_count: np.ndarray
    mean_change_per_year: float | None
    peak_change_per_year: float | None

    def cell_at(self, chainage_m: float) -> int:
        """The index of the cell holding ``chainage_m`` (reference survey's chainage).

        Raises
        ------
        StorageError
            If the chainage is outside the inspected length.
        """
        if self.chainage_start_m.size == 0:
            raise StorageError(f"asset {self.asset_id} has no stored sections")
        first = float(self.chainage_start_m[0])
        index = math.floor(round((chainage_m - first) / self.step_m, 9))
        if not 0 <= index < self.chainage_start_m.size:
            last = first + self.step_m * self.chainage_start_m.size
            raise StorageError(
                f"chainage {chainage_m:g} m is outside asset {self.asset_id}'s inspected "
                f"length {first:g}-{last:g} m",
                field="chainage_m",
                hint="give a chainage inside that range",
            )
        return index

    def fastest_growth(self) -> tuple[float, float] | None:
        """``(chainage_start_m, change_per_year)`` of the fastest-growing cell, or None.

        Only cells measured by at least half the inspections (and two) compete: a slope
        between two noisy readings at the edge of one survey is not a finding.
        """
        needed = max(2, math.ceil(len(self.surveys) / 2))
        finite = np.isfinite(self.change_per_year) & (self.measured_count >= needed)
        if not finite.any():
            return None
        index = int(np.flatnonzero(finite)[np.argmax(self.change_per_year[finite])])
        return float(self.chainage_start_m[index]), float(self.change_per_year[index])


@dataclass(frozen=True)
class AssetRanking:
    """One asset in the network ranking of :func:`worst_assets`.

    ``current_*`` come from the latest measured inspection; the ``*_change_per_year`` are the
    growth per year of the measured inspections' peak and mean blockage
    (:func:`pipescan.core.trends.growth_per_year`), None without two far enough apart.
    """

    asset_id: str
    upstream_node: str | None
    downstream_node: str | None
    nominal_diameter_m: float | None
    inspection_count: int
    first_inspected_at: datetime
    last_inspected_at: datetime
    last_inspection_id: int
    current_peak_blockage_ratio: float
    current_peak_chainage_m: float | None
    current_mean_blockage_ratio: float
    peak_change_per_year: float | None
    mean_change_per_year: float | None


# ---------------------------------------------------------------------------------------------
# Queries


def trend_statement(inspection_ids: Sequence[int]) -> sa.Select:  # type: ignore[type-arg]
    """The sections query behind :func:`asset_trend` (exposed for ``EXPLAIN``).

    Selects ``inspection_id, chainage_start_mm, chainage_end_mm, blockage_ratio, status`` of
    the given inspections, ordered by inspection and chainage: a range scan of the sections'
    primary key per inspection.
    """
    return (
        sa.select(
            Section.inspection_id,
            Section.chainage_start_mm,
            Section.chainage_end_mm,
            Section.blockage_ratio,
            Section.status,
        )
        .where(Section.inspection_id.in_(list(inspection_ids)))
        .order_by(Section.inspection_id, Section.chainage_start_mm)
    )


def _aware(since: datetime | None) -> datetime | None:
    return since if since is None or since.tzinfo is not None else since.replace(tzinfo=UTC)


def asset_trend(
    engine: Engine,
    asset_id: str,
    *,
    max_offset_m: float = DEFAULT_MAX_OFFSET_M,
    since: datetime | None = None,
) -> AssetTrend:
    """Blockage along one asset across its inspections, aligned, with the change per year.

    Parameters
    ----------
    engine
        From ``pipescan.storage.database.db.connect``.
    asset_id
        The pipe asset.
    max_offset_m
        Largest chainage shift between a survey and the reference that alignment looks for,
        in metres; 0 turns alignment off.
    since
        Only inspections at or after this time (timezone-aware; a naive one is taken as UTC).

    Returns
    -------
    AssetTrend
        On a grid of the reference survey's section length (the latest measured inspection;
        with none measured, the latest).

    Raises
    ------
    StorageError
        If the asset is unknown, has no inspections (since ``since``), or ``max_offset_m`` is
        negative or not finite.
    """
    if not math.isfinite(max_offset_m) or max_offset_m < 0:
        raise StorageError(
            f"max_offset_m is {max_offset_m}, expected a finite number >= 0",
            field="max_offset_m",
        )
    since = _aware(since)
    where = [Inspection.asset_id == asset_id]
    if since is not None:
        where.append(Inspection.inspected_at >= since)
    with session_scope(engine) as session:
        asset = session.get(Asset, asset_id)
        if asset is None:
            raise StorageError(
                f"no asset {asset_id!r} in the database",
                field="asset_id",
                hint="list the stored assets with `pipescan assets`",
            )
        rows = session.connection().execute(scans_statement(*where)).all()
        if not rows:
            after = f" since {since.date().isoformat()}" if since is not None else ""
            raise StorageError(f"asset {asset_id} has no inspections{after}")
        sections = session.connection().execute(trend_statement([r.id for r in rows])).all()
        asset_attributes = (
            asset.upstream_node,
            asset.downstream_node,
            asset.nominal_diameter_m,
            asset.pipe_shape,
            asset.material,
        )
    return _build_trend(asset_id, asset_attributes, rows, sections, max_offset_m)


def _build_trend(
    asset_id: str,
    asset_attributes: tuple[str | None, str | None, float | None, str, str | None],
    rows: Sequence[Any],
    sections: Sequence[Any],
    max_offset_m: float,
) -> AssetTrend:
    # Per inspection: sorted starts, ends, measured blockage (NaN where not measured) and
    # the status, as a code into status_names.
    status_names: list[str] = []
    status_codes: dict[str, int] = {}
    by_inspection: dict[int, list[tuple[int, int, float, int]]] = {r.id: [] for r in rows}
    for inspection_id, start_mm, end_mm, blockage, status in sections:
        value = blockage if status == _OK and blockage is not None else math.nan
        if status not in status_codes:
            status_codes[status] = len(status_names)
            status_names.append(status)
        by_inspection[inspection_id].append((start_mm, end_mm, value, status_codes[status]))
    arrays = {
        i: (
            np.array([s[0] for s in items], dtype=np.int64),
            np.array([s[1] for s in items], dtype=np.int64),
            np.array([s[2] for s in items], dtype=np.float64),
            np.array([s[3] for s in items], dtype=np.float64),
        )
        for i, items in by_inspection.items()
    }
    measured_rows = [r for r in rows if np.isfinite(arrays[r.id][2]).any()]
    reference_id = (measured_rows or rows)[-1].id
    ref_start, ref_end = arrays[reference_id][:2]
    lengths = ref_end - ref_start
    step_mm = int(np.median(lengths)) if lengths.size else 100
    step_mm = max(step_mm, 1)
    max_lag = math.floor(max_offset_m * 1000.0 / step_mm + 1e-9)

    all_starts = [a[0] for a in arrays.values() if a[0].size]
    all_ends = [a[1] for a in arrays.values() if a[1].size]
    if all_starts:
        first_cell = math.floor(min(int(s.min()) for s in all_starts) / step_mm) - max_lag
        last_cell = math.ceil(max(int(e.max()) for e in all_ends) / step_mm) + max_lag
    else:
        first_cell, last_cell = 0, 0
    cell_count = last_cell - first_cell
    cells_of = {"first_cell": first_cell, "cell_count": cell_count, "step_mm": step_mm}
    grid = {i: rasterise(s, e, v, **cells_of) for i, (s, e, v, _) in arrays.items()}

    reference = grid[reference_id]
    profiles, codes, lags, correlations = [], [], [], []
    for row in rows:
        if row.id == reference_id:
            lag, correlation = 0, None
        else:
            lag, correlation = estimate_offset(reference, grid[row.id], max_lag)
        lags.append(lag)
        correlations.append(correlation)
        profiles.append(shift(grid[row.id], lag))
        start, end, _, code = arrays[row.id]
        codes.append(shift(rasterise(start, end, code, **cells_of), lag))
    matrix = np.vstack(profiles) if profiles else np.empty((0, cell_count))
    code_matrix = np.vstack(codes) if codes else np.empty((0, cell_count))

    # Trim to the cells some inspection has a section at, measured or not.
    covered = np.flatnonzero(np.isfinite(code_matrix).any(axis=0))
    keep = slice(int(covered[0]), int(covered[-1]) + 1) if covered.size else slice(0, 0)
    matrix = matrix[:, keep]
    code_matrix = code_matrix[:, keep]
    names = np.array([*status_names, None], dtype=object)
    status = names[np.where(np.isfinite(code_matrix), code_matrix, len(status_names)).astype(int)]
    cells = np.arange(cell_count)[keep] + first_cell
    dates = [r.inspected_at for r in rows]

    surveys = tuple(
        SurveyAlignment(
            inspection_id=r.id,
            inspected_at=r.inspected_at,
            offset_m=lag * step_mm / 1000.0,
            correlation=correlation,
            is_reference=r.id == reference_id,
            measured_section_count=r.measured_section_count,
            mean_blockage_ratio=r.mean_blockage_ratio,
            peak_blockage_ratio=r.peak_blockage_ratio,
            peak_chainage_m=(
                None if r.peak_chainage_start_mm is None else mm_to_m(r.peak_chainage_start_mm)
            ),
        )
        for r, lag, correlation in zip(rows, lags, correlations, strict=True)
    )
    upstream, downstream, diameter, shape, material = asset_attributes
    return AssetTrend(
        asset_id=asset_id,
        upstream_node=upstream,
        downstream_node=downstream,
        nominal_diameter_m=diameter,
        pipe_shape=shape,
        material=material,
        step_m=step_mm / 1000.0,
        surveys=surveys,
        chainage_start_m=cells * step_mm / 1000.0,
        blockage_ratio=matrix,
        section_status=status,
        change_per_year=robust_slopes(np.array([years(t) for t in dates]), matrix),
        measured_count=np.isfinite(matrix).sum(axis=0),
        mean_change_per_year=growth_per_year(dates, [r.mean_blockage_ratio for r in rows]),
        peak_change_per_year=growth_per_year(dates, [r.peak_blockage_ratio for r in rows]),
    )


def worst_assets(
    engine: Engine,
    *,
    by: Literal["growth", "current"] = "growth",
    limit: int = 10,
    since: datetime | None = None,
) -> list[AssetRanking]:
    """The network's worst pipes, from the inspections' stored blockage summaries.

    Parameters
    ----------
    engine
        From ``pipescan.storage.database.db.connect``.
    by
        ``"growth"``: fastest-growing pipes, by the growth per year of their peak blockage
        (:func:`pipescan.core.trends.growth_per_year` over each measured scan's peak; assets
        need two measured inspections far enough apart). ``"current"``: highest peak blockage
        in the latest measured inspection.
    limit
        How many assets to return (at least 1).
    since
        Only inspections at or after this time (a naive one is taken as UTC).

    Returns
    -------
    list of AssetRanking
        Worst first; ties by asset id. Assets without a measured inspection are left out.

    Raises
    ------
    StorageError
        If ``by`` or ``limit`` is invalid.
    """
    if by not in ("growth", "current"):
        raise StorageError(f"unknown ranking {by!r}", field="by", hint="use growth or current")
    if limit < 1:
        raise StorageError(f"limit is {limit}, expected at least 1", field="limit")
    since = _aware(since)
    where = [Inspection.measured_section_count > 0]
    if since is not None:
        where.append(Inspection.inspected_at >= since)
    with session_scope(engine) as session:
        # On the Connection: plain rows, without the ORM's per-row bookkeeping.
        rows = session.connection().execute(scans_statement(*where)).all()
        rankings = []
        for asset_id, scans in itertools.groupby(rows, key=lambda r: r.asset_id):
            inspections = list(scans)
            dates = [r.inspected_at for r in inspections]
            last = inspections[-1]
            peak_growth = growth_per_year(dates, [r.peak_blockage_ratio for r in inspections])
            if by == "growth" and peak_growth is None:
                continue
            rankings.append(
                AssetRanking(
                    asset_id=asset_id,
                    upstream_node=None,
                    downstream_node=None,
                    nominal_diameter_m=None,
                    inspection_count=len(inspections),
                    first_inspected_at=dates[0],
                    last_inspected_at=last.inspected_at,
                    last_inspection_id=last.id,
                    current_peak_blockage_ratio=float(last.peak_blockage_ratio),
                    current_peak_chainage_m=(
                        None
                        if last.peak_chainage_start_mm is None
                        else mm_to_m(last.peak_chainage_start_mm)
                    ),
                    current_mean_blockage_ratio=float(last.mean_blockage_ratio),
                    peak_change_per_year=peak_growth,
                    mean_change_per_year=growth_per_year(
                        dates, [r.mean_blockage_ratio for r in inspections]
                    ),
                )
            )

        def key(r: AssetRanking) -> tuple[float, str]:
            figure = r.peak_change_per_year if by == "growth" else r.current_peak_blockage_ratio
            return (-(figure or 0.0), r.asset_id)

        top = sorted(rankings, key=key)[:limit]
        assets = {
            a.asset_id: a
            for a in session.scalars(
                sa.select(Asset).where(Asset.asset_id.in_([r.asset_id for r in top]))
            )
        }
        return [_with_asset(r, assets[r.asset_id]) if r.asset_id in assets else r for r in top]


def _with_asset(ranking: AssetRanking, asset: Asset) -> AssetRanking:
    return replace(
        ranking,
        upstream_node=asset.upstream_node,
        downstream_node=asset.downstream_node,
        nominal_diameter_m=asset.nominal_diameter_m,
    )
