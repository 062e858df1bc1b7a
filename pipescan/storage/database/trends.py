"""Blockage over time: sections aligned between inspections, change per year, worst pipes.

Two questions from asset teams drive this module: "how has blockage at 37 m along pipe
MH1042-MH1043 changed since 2022?" (:func:`asset_trend`) and "which pipes got worse fastest?"
(:func:`worst_assets`).

Rules that hold throughout:

- Only **measured** sections count: status ``ok`` with a blockage ratio. An unmeasured section
  is a gap (NaN in arrays, None in records), never a blockage of 0.
- One scan counts once. When the same archive (content hash) of an asset was processed more
  than once with different parameters, the latest save stands for it.
- Change per year is a **Theil–Sen** slope: the median of the slopes between every pair of
  inspections made at different times. One wild value among five inspections moves it little,
  where a least-squares slope would follow it. Its unit is ratio per year (0.05 is 5
  percentage points of blockage a year).
- Chainages of different surveys are aligned before they are compared. A crawler's cable
  counter and the chainage origin differ a little between surveys, so the same deposit can
  sit at 37.2 m in one and 37.5 m in the next. Each inspection's blockage profile is
  cross-correlated with the reference survey's (the latest measured one) over shifts of up to
  ``max_offset_m``; the shift with the highest correlation is applied, in whole sections, if
  that correlation is convincing (:data:`MIN_CORRELATION`). Chainages in a trend are those of
  the reference survey.

The numeric core (:func:`robust_slopes`, :func:`estimate_offset`, :func:`rasterise`) takes and
returns arrays; the rest reads the database.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Sequence
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from typing import Any, Literal

import numpy as np
import sqlalchemy as sa
from sqlalchemy.engine import Engine

from pipescan.core.model import SectionStatus
from pipescan.storage.database.db import StorageError, session_scope
from pipescan.storage.database.models import Asset, Inspection, Section
from pipescan.storage.database.repository import mm_to_m

__all__ = [
    "DEFAULT_MAX_OFFSET_M",
    "MIN_CORRELATION",
    "MIN_OVERLAP_SECTIONS",
    "AssetRanking",
    "AssetTrend",
    "SurveyAlignment",
    "asset_trend",
    "estimate_offset",
    "rasterise",
    "robust_slope",
    "robust_slopes",
    "trend_statement",
    "worst_assets",
]

DEFAULT_MAX_OFFSET_M = 1.0
"""Largest chainage shift between two surveys that alignment looks for, in metres."""

MIN_CORRELATION = 0.5
"""Correlation (Pearson) a shift must reach to be applied; below it the survey stays put."""

MIN_OVERLAP_SECTIONS = 10
"""Measured sections two profiles must share at a shift for it to be considered."""

_SECONDS_PER_YEAR = 365.25 * 86400.0
_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)
_OK = SectionStatus.OK.value


# ---------------------------------------------------------------------------------------------
# Numeric core: arrays in, arrays out


def robust_slopes(times_yr: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Theil–Sen slopes of several series sampled at the same times.

    Parameters
    ----------
    times_yr : (N,) float array
        Sample times, in years (any origin).
    values : (N, K) float array
        ``K`` series; NaN marks a missing sample.

    Returns
    -------
    (K,) float64 array
        For each series, the median of ``(v_j - v_i) / (t_j - t_i)`` over the pairs
        ``i < j`` where both samples are present and ``t_j != t_i``, in value units per year;
        NaN where there is no such pair.

    Raises
    ------
    ValueError
        If the shapes do not match.

    Examples
    --------
    >>> robust_slopes(np.array([0.0, 1.0, 2.0, 3.0]), np.array([[0.0], [1.0], [9.0], [3.0]]))
    array([1.])
    """
    times_yr = np.asarray(times_yr, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64)
    if values.ndim != 2 or times_yr.ndim != 1 or values.shape[0] != times_yr.shape[0]:
        raise ValueError(
            f"values must have shape (N, K) and times_yr (N,); got {values.shape} and "
            f"{times_yr.shape}"
        )
    n, k = values.shape
    i, j = np.triu_indices(n, 1)
    dt = times_yr[j] - times_yr[i]
    keep = dt != 0
    i, j, dt = i[keep], j[keep], dt[keep]
    out = np.full(k, np.nan)
    if i.size == 0 or k == 0:
        return out
    slopes = (values[j] - values[i]) / dt[:, None]  # (pairs, K), NaN where a sample is missing
    has_pair = np.isfinite(slopes).any(axis=0)
    if has_pair.any():
        out[has_pair] = np.nanmedian(slopes[:, has_pair], axis=0)
    return out


def robust_slope(
    times_yr: Sequence[float] | np.ndarray, values: Sequence[float | None]
) -> float | None:
    """The Theil–Sen slope of one series (see :func:`robust_slopes`); None if it has none.

    ``values`` may hold None (or NaN) for missing samples. Plain Python: for the few samples
    of one asset it is a hundred times quicker than numpy's NaN-aware median.
    """
    samples = [
        (float(t), float(v))
        for t, v in zip(times_yr, values, strict=True)
        if v is not None and math.isfinite(v)
    ]
    slopes = [
        (v2 - v1) / (t2 - t1)
        for i, (t1, v1) in enumerate(samples)
        for t2, v2 in samples[i + 1 :]
        if t2 != t1
    ]
    return statistics.median(slopes) if slopes else None


def estimate_offset(
    reference: np.ndarray,
    profile: np.ndarray,
    max_lag: int,
    *,
    min_overlap: int = MIN_OVERLAP_SECTIONS,
) -> tuple[int, float | None]:
    """The shift that best lines a profile up with a reference, by cross-correlation.

    Parameters
    ----------
    reference, profile : (K,) float arrays
        Blockage ratios on the same chainage grid; NaN where unmeasured.
    max_lag
        Largest shift tried, in grid cells, both ways.
    min_overlap
        Measured cells the two must share at a shift for it to count.

    Returns
    -------
    lag : int
        Cells to add to the profile's indices: ``profile[k]`` lines up with
        ``reference[k + lag]``. 0 when no shift correlates at least :data:`MIN_CORRELATION`.
    correlation : float or None
        The Pearson correlation at the chosen shift (at 0 if no shift was convincing); None
        when no shift had enough overlap with variation in both profiles.

    Notes
    -----
    Pearson correlation ignores scale and level, so deposits that grew between the surveys
    still line up. On equal correlations the smaller shift wins.
    """
    reference = np.asarray(reference, dtype=np.float64)
    profile = np.asarray(profile, dtype=np.float64)
    if reference.shape != profile.shape or reference.ndim != 1:
        raise ValueError(
            f"reference and profile must be 1-D of one length; got {reference.shape} and "
            f"{profile.shape}"
        )
    size = reference.size
    by_lag: dict[int, float] = {}
    for lag in range(-max_lag, max_lag + 1):
        # profile[k] against reference[k + lag], over the indices both exist at.
        lo, hi = max(0, -lag), min(size, size - lag)
        if hi - lo < min_overlap:
            continue
        a = profile[lo:hi]
        b = reference[lo + lag : hi + lag]
        both = np.isfinite(a) & np.isfinite(b)
        if both.sum() < min_overlap:
            continue
        a, b = a[both] - a[both].mean(), b[both] - b[both].mean()
        denominator = math.sqrt(float(a @ a) * float(b @ b))
        if denominator <= 1e-12:
            continue  # a flat profile: no shape to line up
        by_lag[lag] = float(a @ b) / denominator
    if not by_lag:
        return 0, None
    best = max(by_lag, key=lambda lag: (round(by_lag[lag], 9), -abs(lag)))
    if by_lag[best] < MIN_CORRELATION:
        return 0, by_lag.get(0)
    return best, by_lag[best]


def rasterise(
    start_mm: np.ndarray,
    end_mm: np.ndarray,
    values: np.ndarray,
    *,
    first_cell: int,
    cell_count: int,
    step_mm: int,
) -> np.ndarray:
    """Put one inspection's sections on a regular chainage grid.

    Parameters
    ----------
    start_mm, end_mm : (S,) int arrays
        The sections' intervals ``[start, end)``, in millimetres, sorted by start and not
        overlapping.
    values : (S,) float array
        A figure per section; NaN where unmeasured.
    first_cell, cell_count, step_mm
        The grid: cell ``c`` covers ``[(first_cell + c) * step_mm, ... + step_mm)``.

    Returns
    -------
    (cell_count,) float64 array
        The value of the section that holds each cell's centre; NaN where no section does.
    """
    centres_mm = (np.arange(cell_count) + first_cell) * step_mm + step_mm / 2.0
    out = np.full(cell_count, np.nan)
    if start_mm.size == 0:
        return out
    index = np.searchsorted(start_mm, centres_mm, side="right") - 1
    inside = index >= 0
    inside[inside] &= centres_mm[inside] < end_mm[index[inside]]
    out[inside] = values[index[inside]]
    return out


def _years(when: datetime) -> float:
    return (when - _EPOCH).total_seconds() / _SECONDS_PER_YEAR


def _shift(profile: np.ndarray, lag: int) -> np.ndarray:
    # out[k + lag] = profile[k], NaN where nothing moved in.
    out = np.full_like(profile, np.nan)
    if lag >= 0:
        out[lag:] = profile[: profile.size - lag]
    else:
        out[:lag] = profile[-lag:]
    return out


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
        Theil–Sen slope of each cell's blockage, ratio per year; NaN where fewer than two
        inspections at different times measured the cell.
    measured_count : (K,) int array
        How many inspections measured each cell.
    mean_change_per_year, peak_change_per_year
        Theil–Sen slopes of the inspections' mean and peak blockage, ratio per year; None
        with fewer than two measured inspections at different times.
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

    ``current_*`` come from the latest measured inspection; the ``*_change_per_year`` are
    Theil–Sen slopes over the measured inspections (ratio per year), None with fewer than two
    at different times.
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

_InspectionRow = tuple[int, str, datetime, str, int, float | None, float | None, int | None]


def _latest_per_scan(rows: Sequence[_InspectionRow]) -> list[_InspectionRow]:
    # rows: (id, asset_id, inspected_at, content_hash, ...); one per (asset, scan), the
    # highest id (latest save) winning; returned in (asset, date, id) order.
    best: dict[tuple[str, str], _InspectionRow] = {}
    for row in rows:
        key = (row[1], row[3])
        if key not in best or row[0] > best[key][0]:
            best[key] = row
    return sorted(best.values(), key=lambda r: (r[1], r[2], r[0]))


def _inspection_columns() -> tuple[Any, ...]:
    return (
        Inspection.id,
        Inspection.asset_id,
        Inspection.inspected_at,
        Inspection.content_hash,
        Inspection.measured_section_count,
        Inspection.mean_blockage_ratio,
        Inspection.peak_blockage_ratio,
        Inspection.peak_chainage_start_mm,
    )


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
    if since is not None and since.tzinfo is None:
        since = since.replace(tzinfo=UTC)
    inspections = sa.select(*_inspection_columns()).where(Inspection.asset_id == asset_id)
    if since is not None:
        inspections = inspections.where(Inspection.inspected_at >= since)
    with session_scope(engine) as session:
        asset = session.get(Asset, asset_id)
        if asset is None:
            raise StorageError(
                f"no asset {asset_id!r} in the database",
                field="asset_id",
                hint="list the stored assets with `pipescan assets`",
            )
        found = session.connection().execute(inspections).all()
        rows = _latest_per_scan([tuple(r) for r in found])  # type: ignore[misc]
        if not rows:
            after = f" since {since.date().isoformat()}" if since is not None else ""
            raise StorageError(f"asset {asset_id} has no inspections{after}")
        sections = session.connection().execute(trend_statement([r[0] for r in rows])).all()
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
    rows: Sequence[_InspectionRow],
    sections: Sequence[Any],
    max_offset_m: float,
) -> AssetTrend:
    # Per inspection: sorted starts, ends, measured blockage (NaN where not measured) and
    # the status, as a code into status_names.
    status_names: list[str] = []
    status_codes: dict[str, int] = {}
    by_inspection: dict[int, list[tuple[int, int, float, int]]] = {r[0]: [] for r in rows}
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
    measured_rows = [r for r in rows if np.isfinite(arrays[r[0]][2]).any()]
    reference_id = (measured_rows or rows)[-1][0]
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
        if row[0] == reference_id:
            lag, correlation = 0, None
        else:
            lag, correlation = estimate_offset(reference, grid[row[0]], max_lag)
        lags.append(lag)
        correlations.append(correlation)
        profiles.append(_shift(grid[row[0]], lag))
        start, end, _, code = arrays[row[0]]
        codes.append(_shift(rasterise(start, end, code, **cells_of), lag))
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
    times_yr = np.array([_years(r[2]) for r in rows])

    surveys = tuple(
        SurveyAlignment(
            inspection_id=r[0],
            inspected_at=r[2],
            offset_m=lag * step_mm / 1000.0,
            correlation=correlation,
            is_reference=r[0] == reference_id,
            measured_section_count=r[4],
            mean_blockage_ratio=r[5],
            peak_blockage_ratio=r[6],
            peak_chainage_m=None if r[7] is None else mm_to_m(r[7]),
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
        change_per_year=robust_slopes(times_yr, matrix),
        measured_count=np.isfinite(matrix).sum(axis=0),
        mean_change_per_year=robust_slope(times_yr, [r[5] for r in rows]),
        peak_change_per_year=robust_slope(times_yr, [r[6] for r in rows]),
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
        ``"growth"``: fastest-growing peak blockage (Theil–Sen slope of each measured
        inspection's peak, ratio per year; assets need two measured inspections at different
        times). ``"current"``: highest peak blockage in the latest measured inspection.
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
    if since is not None and since.tzinfo is None:
        since = since.replace(tzinfo=UTC)
    statement = sa.select(*_inspection_columns()).where(Inspection.measured_section_count > 0)
    if since is not None:
        statement = statement.where(Inspection.inspected_at >= since)
    with session_scope(engine) as session:
        # On the Connection: plain rows, without the ORM's per-row bookkeeping.
        found = session.connection().execute(statement).all()
        rows = _latest_per_scan([tuple(r) for r in found])  # type: ignore[misc]
        by_asset: dict[str, list[_InspectionRow]] = {}
        for row in rows:
            by_asset.setdefault(row[1], []).append(row)
        rankings = []
        for asset_id, inspections in by_asset.items():
            times_yr = [_years(r[2]) for r in inspections]
            last = inspections[-1]
            peak_growth = robust_slope(times_yr, [r[6] for r in inspections])
            if by == "growth" and peak_growth is None:
                continue
            rankings.append(
                AssetRanking(
                    asset_id=asset_id,
                    upstream_node=None,
                    downstream_node=None,
                    nominal_diameter_m=None,
                    inspection_count=len(inspections),
                    first_inspected_at=inspections[0][2],
                    last_inspected_at=last[2],
                    last_inspection_id=last[0],
                    current_peak_blockage_ratio=float(last[6]),  # type: ignore[arg-type]
                    current_peak_chainage_m=None if last[7] is None else mm_to_m(last[7]),
                    current_mean_blockage_ratio=float(last[5]),  # type: ignore[arg-type]
                    peak_change_per_year=peak_growth,
                    mean_change_per_year=robust_slope(times_yr, [r[5] for r in inspections]),
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
