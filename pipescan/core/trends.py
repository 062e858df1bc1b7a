"""Change over time: the one definition of growth per year, and the alignment of surveys.

Rules that hold for every figure of change pipescan gives (the ``trend`` and ``worst``
commands, the per-inspection report's trend page, the network report):

- **A year** is :data:`SECONDS_PER_YEAR` (365.25 days).
- **Growth per year** of a figure (a blockage ratio: of a pipe's peak, of a chainage, of a
  defect's span) is a **Theil–Sen** slope: the median of the slopes between every pair of
  inspections at least :data:`MIN_YEARS_APART` apart. One wild value among five inspections
  moves it little, where a least-squares slope would follow it; two inspections days apart say
  nothing about a rate (their difference is measurement noise divided by a tiny interval). With
  two inspections it is their difference over the years between them. Its unit is ratio per
  year: 0.05 is 5 percentage points of blockage a year. See :func:`growth_per_year`.
- **A pipe's growth** is the growth per year of the peak blockage of each of its inspections
  (:func:`pipescan.core.summary.peak_blockage`). The peak is taken wherever it is, so it needs
  no chainage alignment, and it does not pick the largest of many noisy differences (the
  largest change at any one chainage grows with the noise and the pipe's length, even between
  two identical surveys).
- **A change is significant** only when it is larger than what two surveys of an unchanged
  pipe disagree by: the growth per year times the years between the first and the last
  survey that measured the figure must exceed :data:`SIGNIFICANT_CHANGE_RATIO` (at one
  chainage, plus what the chainage repeatability gives on a steep profile:
  :func:`change_thresholds`). Anything smaller is "no significant change", in words and in
  plots. See :func:`is_significant`.
- **Chainages of different surveys are aligned** before they are compared chainage by
  chainage. A crawler's cable counter and the chainage origin differ a little between surveys,
  so the same deposit can sit at 37.2 m in one and 37.5 m in the next. Each profile is
  cross-correlated with the reference survey's over shifts of up to a maximum; the shift with
  the highest correlation is applied, in whole cells, if that correlation is convincing
  (:data:`MIN_CORRELATION`). See :func:`estimate_offset`, :func:`rasterise` and :func:`shift`.

Everything here is pure: arrays and small values in and out.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Sequence
from datetime import UTC, datetime

import numpy as np

__all__ = [
    "CHAINAGE_REPEATABILITY_M",
    "DEFAULT_MAX_OFFSET_M",
    "MIN_CORRELATION",
    "MIN_OVERLAP_SECTIONS",
    "MIN_YEARS_APART",
    "NO_SIGNIFICANT_CHANGE",
    "SECONDS_PER_YEAR",
    "SIGNIFICANT_CHANGE_RATIO",
    "change_thresholds",
    "estimate_offset",
    "growth_per_year",
    "is_significant",
    "measured_span_years",
    "rasterise",
    "robust_slope",
    "robust_slopes",
    "shift",
    "years",
    "years_between",
]

SECONDS_PER_YEAR = 365.25 * 86400.0
"""The year of every rate pipescan gives."""

MIN_YEARS_APART = 0.05
"""Inspections closer in time than this (about 18 days) are not used as a pair for a rate."""

DEFAULT_MAX_OFFSET_M = 1.0
"""Largest chainage shift between two surveys that alignment looks for, in metres."""

MIN_CORRELATION = 0.5
"""Correlation (Pearson) a shift must reach to be applied; below it the survey stays put."""

MIN_OVERLAP_SECTIONS = 10
"""Measured sections two profiles must share at a shift for it to be considered."""

SIGNIFICANT_CHANGE_RATIO = 0.02
"""The smallest change of a blockage ratio between surveys that is a change and not noise:
2 percentage points over the years the surveys span.

A measured section's blockage is within 1 pp of the truth, so two surveys of an unchanged
pipe can read it up to 2 pp apart whatever their errors (docs/measures.md, *Where the 2 points
and 3 cm come from*, with the repeatability sweep that checks it).
"""

CHAINAGE_REPEATABILITY_M = 0.03
"""How far apart two aligned surveys of one pipe can still place the same section: 3 cm.

Where the blockage profile is steep (a deposit's ramp, an obstacle's face), that shift alone
changes the reading at a chainage by the profile's slope times it; :func:`change_thresholds`
adds that to :data:`SIGNIFICANT_CHANGE_RATIO` (docs/measures.md, *Where the 2 points and 3 cm
come from*).
"""

NO_SIGNIFICANT_CHANGE = "no significant change"
"""How every output words a change that :func:`is_significant` finds to be noise."""

_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)


def _aware(when: datetime) -> datetime:
    return when if when.tzinfo is not None else when.replace(tzinfo=UTC)


def years(when: datetime) -> float:
    """A time as years since 1970 (a naive datetime is taken as UTC)."""
    return (_aware(when) - _EPOCH).total_seconds() / SECONDS_PER_YEAR


def years_between(later: datetime, earlier: datetime) -> float:
    """Years from ``earlier`` to ``later`` (negative if ``later`` is earlier).

    >>> round(years_between(datetime(2025, 6, 1), datetime(2023, 6, 1)), 4)
    2.0014
    """
    return years(later) - years(earlier)


def growth_per_year(
    inspected_at: Sequence[datetime], values: Sequence[float | None]
) -> float | None:
    """Growth per year of a figure across inspections: the one definition (see the module).

    Parameters
    ----------
    inspected_at
        When each inspection was taken (any order).
    values
        The figure in each inspection, a ratio; None (or NaN) where it was not measured.

    Returns
    -------
    float or None
        Ratio per year; None without two measured inspections at least
        :data:`MIN_YEARS_APART` apart.

    Examples
    --------
    >>> round(growth_per_year([datetime(2023, 6, 1), datetime(2025, 6, 1)], [0.10, 0.14]), 4)
    0.02
    >>> growth_per_year([datetime(2025, 6, 1), datetime(2025, 6, 2)], [0.10, 0.30]) is None
    True
    """
    return robust_slope([years(t) for t in inspected_at], values)


def robust_slopes(
    times_yr: np.ndarray, values: np.ndarray, *, min_years_apart: float = MIN_YEARS_APART
) -> np.ndarray:
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
        ``i < j`` where both samples are present and at least ``min_years_apart`` apart, in
        value units per year; NaN where there is no such pair.

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
    keep = np.abs(dt) >= min_years_apart
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
    times_yr: Sequence[float] | np.ndarray,
    values: Sequence[float | None],
    *,
    min_years_apart: float = MIN_YEARS_APART,
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
        if abs(t2 - t1) >= min_years_apart
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


def shift(profile: np.ndarray, lag: int) -> np.ndarray:
    """A profile moved by ``lag`` cells: ``out[k + lag] = profile[k]``, NaN where nothing
    moved in (the lag :func:`estimate_offset` returns lines it up with the reference)."""
    out = np.full_like(profile, np.nan)
    if lag >= 0:
        out[lag:] = profile[: profile.size - lag]
    else:
        out[:lag] = profile[-lag:]
    return out


def measured_span_years(times_yr: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Years between the first and the last sample of each series that is present.

    Parameters
    ----------
    times_yr : (N,) float array
        Sample times, in years.
    values : (N, K) float array
        ``K`` series; NaN marks a missing sample.

    Returns
    -------
    (K,) float64 array
        ``max(t) - min(t)`` over each series' present samples; 0 where fewer than two.

    Examples
    --------
    >>> measured_span_years(np.array([0.0, 1.0, 3.0]), np.array([[1.0], [np.nan], [2.0]]))
    array([3.])
    """
    times_yr = np.asarray(times_yr, dtype=np.float64)
    present = np.isfinite(np.asarray(values, dtype=np.float64))
    if present.size == 0:
        return np.zeros(present.shape[1] if present.ndim == 2 else 0)
    t = times_yr[:, None]
    latest = np.where(present, t, -np.inf).max(axis=0)
    earliest = np.where(present, t, np.inf).min(axis=0)
    return np.where(present.sum(axis=0) >= 2, latest - earliest, 0.0)


def is_significant(
    change_per_year: float | None,
    span_years: float,
    *,
    threshold_ratio: float = SIGNIFICANT_CHANGE_RATIO,
) -> bool | None:
    """Whether a growth per year is a change rather than noise: over the years the surveys
    span, it must add up to more than ``threshold_ratio`` (:data:`SIGNIFICANT_CHANGE_RATIO`).

    Parameters
    ----------
    change_per_year
        Growth per year (:func:`growth_per_year`), ratio per year; None when there is none.
    span_years
        Years between the first and the last survey that measured the figure.

    Returns
    -------
    bool or None
        None when there is no growth figure.

    Examples
    --------
    >>> is_significant(0.0011, 2.0)  # +0.11 points a year over two years: noise
    False
    >>> is_significant(0.03, 2.0), is_significant(-0.015, 2.0), is_significant(None, 2.0)
    (True, True, None)
    """
    if change_per_year is None or not math.isfinite(change_per_year):
        return None
    return abs(change_per_year) * span_years > threshold_ratio


def change_thresholds(values: np.ndarray, step_m: float) -> np.ndarray:
    """The change at each chainage cell below which it is no significant change: the
    :data:`SIGNIFICANT_CHANGE_RATIO`, plus the steepest slope of any survey's profile there
    times :data:`CHAINAGE_REPEATABILITY_M` (on a ramp, a centimetre of chainage is a change
    of reading).

    Parameters
    ----------
    values : (N, K) float array
        The surveys' aligned blockage ratios on one chainage grid; NaN where unmeasured.
    step_m
        The grid's cell length, metres.

    Returns
    -------
    (K,) float64 array
        Ratios; pass each as ``threshold_ratio`` to :func:`is_significant`.

    Examples
    --------
    >>> flat_then_ramp = np.array([[0.0, 0.0, 0.0, 0.1, 0.2]])
    >>> change_thresholds(flat_then_ramp, 0.1).round(3)
    array([0.02 , 0.02 , 0.035, 0.05 , 0.05 ])
    """
    values = np.asarray(values, dtype=np.float64)
    if values.ndim != 2 or values.shape[1] == 0:
        return np.full(values.shape[-1] if values.ndim else 0, SIGNIFICANT_CHANGE_RATIO)
    if values.shape[1] == 1:
        slope = np.zeros(values.shape)
    else:
        slope = np.abs(np.gradient(values, step_m, axis=1))  # NaN next to a gap: ignored
    with np.errstate(all="ignore"):
        steepest = np.nanmax(np.where(np.isfinite(slope), slope, -np.inf), axis=0)
    steepest = np.where(np.isfinite(steepest), steepest, 0.0)
    return SIGNIFICANT_CHANGE_RATIO + steepest * CHAINAGE_REPEATABILITY_M
