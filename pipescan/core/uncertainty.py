"""The 95 % uncertainty of a section's figures, from its points, its residual spread and its
unseen arcs.

One definition, used by :func:`pipescan.core.measures.measure_section` to attach a ``±`` to
every figure and to decide whether the figures can be trusted (docs/measures.md,
"Uncertainty"). Its parts are added (all but the first are bounds, not random errors):

- **noise**: each angle bin's radius is a median of ``n`` points whose radii scatter by
  ``σ`` (the section's robust residual spread); a median's standard error is
  ``sqrt(π / 2) σ / sqrt(n)``. Propagated through the polar area ``½ Σ r² Δθ``, with 1.96
  standard errors for 95 % (Student's t over the seen bins, :func:`coverage_factor`).
- **unseen arcs**: an unseen arc of angle ``g`` is interpolated between the radii at its
  ends; whatever hides there and does not reach in past the chord between those ends changes
  the area by at most the circular segment ``R² (g − sin g) / 2``.
- **along the section**: where the sub-slices' radii of a bin differ by more than their noise
  (a deformation's ramp, an obstacle's end), the bin's one radius may be off by half that.
- **smear**: frames that disagree lay shifted copies of the wall, whose polar median reads
  more open by up to ``2 median(s²) / R²`` of the area (``s``, the wall bins' scatter;
  :func:`smear_bias_m2`). Dense sections only: a sparse one sees each bin once.
- **hidden beside an obstacle**: free space beside an overhanging obstacle's edge that no ray
  reached; the figure counts half of it as free and the ± carries the other half
  (``PolarProfile.hidden_polygons``: the obstacle's side at right angles to its face, or
  along the line of sight).
- **resolution**: where the contour steps between two neighbouring bins by more than their
  noise and by more than twice the steps beside it (an obstacle's edge), the edge may lie
  anywhere within the half bins on either side: at most ``½ |r₁² − r₂²| Δθ / 2`` of area;
  where it bends (a deposit's chord meeting the wall), a quarter of the second difference
  of ``r²`` times ``Δθ``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

Z95 = 1.959963984540054
"""Standard normal quantile of a two-sided 95 % interval."""

MEDIAN_EFFICIENCY = math.sqrt(math.pi / 2.0)
"""Standard error of a median over that of a mean, for normal scatter."""

MAD_TO_SIGMA = 1.4826
"""σ of normal scatter over its median absolute deviation (1 / Φ⁻¹(3/4)): a robust σ is
``MAD_TO_SIGMA * median(|r - median(r)|)``."""


def coverage_factor(seen_bins: int) -> float:
    """The 95 % coverage factor for a standard error estimated from the section itself:
    Student's t with one degree of freedom fewer than the seen bins (the scatter is pooled
    over them), so a sparse section's ± is not overconfident; 1.96 in the limit.

    >>> round(coverage_factor(36), 3), round(coverage_factor(360), 3)
    (2.03, 1.967)
    """
    from scipy.stats import t

    return float(t.ppf(0.975, max(seen_bins - 1, 1)))


@dataclass(frozen=True)
class AreaUncertainty:
    """The parts of the 95 % uncertainty of a section's open area, m²."""

    noise_m2: float
    unseen_m2: float
    resolution_m2: float
    along_m2: float = 0.0
    smear_m2: float = 0.0
    hidden_m2: float = 0.0

    @property
    def total_m2(self) -> float:
        return (
            self.noise_m2
            + self.unseen_m2
            + self.resolution_m2
            + self.along_m2
            + self.smear_m2
            + self.hidden_m2
        )


def smear_bias_m2(open_area_m2: float, wall_sigma_m: np.ndarray, radius_m: float) -> float:
    """How much more open a section may read because the frames that saw it disagree, m².

    Frames registered a little apart lay copies of the wall shifted against each other. At
    each angle the polar contour takes the median radius over the copies, and a copy
    shifted outwards there puts more of its points in that angle bin (its wall is further
    away, so a bin's angle spans more of it): the median moves outwards, and the section
    reads more open. The outward part grows with the shifts' variance across the wall,
    ``s²``, which adds to the bin's radial scatter; the shifts along the wall pull the
    other way. Ignoring that pull, the area grows by at most ``2 median(s²) / R²`` of itself,
    with ``s`` the wall bins' scatter (the sensor's own noise is in it, so this is an upper
    bound). Checked on synthetic rings of 200 shifted copies (0.15 m radius; shifts 4 mm
    in every direction, 6 mm one way, 1 cm along a line, 8 mm diagonal; 8 rings each): the
    area grew by 0.07-0.27 %, within the bound or within the rings' own noise of it
    (0.066 % against 0.060 % for the line).

    Parameters
    ----------
    open_area_m2 : float
        The section's open area.
    wall_sigma_m : (K,) float
        The radial scatter (1σ) of the wall's angle bins (``residual_sigma_m`` over the
        bins that are wall, not a feature).
    radius_m : float
        The wall's radius.

    Examples
    --------
    >>> round(smear_bias_m2(0.0707, np.full(300, 0.004), 0.15) / 0.0707 * 100, 3)  # % of area
    0.142
    """
    sigma = np.asarray(wall_sigma_m, dtype=np.float64)
    if len(sigma) == 0 or not radius_m > 0:
        return 0.0
    # The median over the bins, not the mean: a few bins of stray scatter (an end wall, a
    # pipe's joint) would otherwise set it. For shifts one way, s² = σ² cos² θ, whose median
    # over the angles is its mean, σ² / 2.
    return float(open_area_m2 * 2.0 * np.median(sigma**2) / radius_m**2)


def residual_sigma_m(
    radii_of_points_m: np.ndarray,
    bin_of_points: np.ndarray,
    bin_radii_m: np.ndarray,
    *,
    window_bins: int = 5,
) -> np.ndarray:
    """Robust spread (1σ, metres) of the points' radii about their bins' radii, per bin.

    A sensor's noise grows towards grazing incidence and with range, so the wall's scatter
    differs round the section: each bin gets the median absolute residual of the points in
    the ``window_bins`` bins around it, times :data:`MAD_TO_SIGMA`.

    Parameters
    ----------
    radii_of_points_m : (N,) float
        Each point's distance from the axis.
    bin_of_points : (N,) int
        Each point's angle bin.
    bin_radii_m : (B,) float
        The bins' radii (NaN where unseen: those points do not count).

    Returns
    -------
    (B,) float
        The scatter per bin; the section's median where a window has no points; zeros when
        no point lies in a seen bin.
    """
    bins = len(bin_radii_m)
    res = np.abs(radii_of_points_m - bin_radii_m[bin_of_points])
    finite = np.isfinite(res)
    if not finite.any():
        return np.zeros(bins)
    res, which = res[finite], bin_of_points[finite]
    # Each bin's median sits closer to its own points than the truth does, the more so the
    # fewer they are: the median absolute residual of n normal points about their median is
    # (1 - 1.2 / n) of σ / 1.4826 or a little more (a property of normal samples, not of the
    # scanner: 0.73 / 0.89 / 0.95 for n = 4 / 8 / 16, against 0.70 / 0.85 / 0.925), so σ is
    # read up to 5 % high, the safe side (tests/test_instrument.py, the MAD's factor).
    per_bin = np.bincount(which, minlength=bins)
    n = float(np.median(per_bin[per_bin > 0]))
    scale = MAD_TO_SIGMA / (1.0 - 1.2 / max(n, 3.0))
    # Every residual counts in the windows of the ``window_bins`` bins around its own. List
    # each once per window, in ascending order of residual, then sort stably by window: each
    # window's residuals come out sorted, and its median is read at its middle.
    half = window_bins // 2
    order = np.argsort(res)
    res = res[order]
    # (A circle holds far fewer than 32,768 bins: as int16, NumPy sorts by radix.)
    dtype = np.int16 if bins < 2**15 else np.int64
    key = which[order].astype(dtype)[:, None] + np.arange(-half, half + 1, dtype=dtype)
    key[key < 0] += bins
    key[key >= bins] -= bins
    key = key.ravel()
    values = np.repeat(res, window_bins)[np.argsort(key, kind="stable")]
    counts = np.bincount(key, minlength=bins)
    starts = np.concatenate(([0], np.cumsum(counts)[:-1]))
    low = starts + np.maximum(counts - 1, 0) // 2
    high = starts + counts // 2
    seen = counts > 0
    # ``res`` is sorted: the section's median is read at its middle.
    medians = np.full(bins, 0.5 * (float(res[(len(res) - 1) // 2]) + float(res[len(res) // 2])))
    medians[seen] = (values[low[seen]] + values[high[seen]]) / 2.0
    return scale * medians


def unseen_runs(seen: np.ndarray) -> list[np.ndarray]:
    """The runs of unseen bins around the circle, each as its bin indices in order."""
    bins = len(seen)
    if seen.all():
        return []
    if not seen.any():
        return [np.arange(bins)]
    start = int(np.argmax(seen))  # a seen bin: runs never wrap past it
    idx = np.roll(np.arange(bins), -start)
    runs, current = [], []
    for i in idx:
        if not seen[i]:
            current.append(i)
        elif current:
            runs.append(np.array(current))
            current = []
    if current:
        runs.append(np.array(current))
    return runs


def area_uncertainty(
    radii_m: np.ndarray,
    seen: np.ndarray,
    counts: np.ndarray,
    sigma_m: np.ndarray | float,
    radius_m: float,
    slice_radii_m: np.ndarray | None = None,
) -> AreaUncertainty:
    """The 95 % uncertainty of the polar area ``½ Σ r² Δθ`` of a section profile.

    (Over 80 lines for its reference docstring: the body sums its parts, noise, unseen bins,
    edges and kinks, and the change along the section.)

    Parameters
    ----------
    radii_m : (B,) float
        The contour's radius per bin, unseen bins filled (as the area used them).
    seen : (B,) bool
        Which bins were seen.
    counts : (B,) int
        Points per bin.
    sigma_m : (B,) float, or float
        The residual spread of the points about the bins' radii (1σ), per bin or for all.
    radius_m : float
        The wall's radius, for the unseen arcs' segments.
    slice_radii_m : (B, S) float, optional
        Each sub-slice's radius per bin: where they differ beyond their noise, the section
        changes along its length (a deformation's ramp, an obstacle's end) and its one
        radius per bin may be off by half that change.

    Returns
    -------
    AreaUncertainty

    Examples
    --------
    >>> r = np.full(36, 0.4)
    >>> u = area_uncertainty(r, np.ones(36, bool), np.full(36, 8), 0.015, 0.4)
    >>> round(u.noise_m2 / (np.pi * 0.4**2), 4), u.unseen_m2, u.resolution_m2
    (0.0112, 0.0, 0.0)
    """
    bins = len(radii_m)
    dtheta = 2.0 * math.pi / bins
    n = np.maximum(counts, 1).astype(np.float64)
    bin_sd = MEDIAN_EFFICIENCY * sigma_m / np.sqrt(n)
    # An unseen bin's radius is interpolated from seen ones: count it with their scatter.
    if seen.any():
        typical = float(np.median(bin_sd[seen]))
        bin_sd = np.where(seen, bin_sd, typical)
    var = float(np.sum((radii_m * dtheta * bin_sd) ** 2))
    noise = coverage_factor(int(seen.sum())) * math.sqrt(var)

    unseen = unseen_area_m2(seen, radius_m)

    # Steps between neighbouring bins beyond three of their standard errors, and twice the
    # steps beside them: an edge, not a steep but smooth stretch (a deposit's chord, whose
    # radius changes fast near the wall, is followed well by its bins' medians).
    nxt = np.roll(radii_m, -1)
    step = np.abs(nxt - radii_m)
    step_sd = np.hypot(bin_sd, np.roll(bin_sd, -1))
    beside = np.maximum(np.roll(step, 1), np.roll(step, -1))
    jump = (step > 3.0 * step_sd) & (step > 2.0 * beside)
    resolution = float(np.sum(np.abs(nxt**2 - radii_m**2)[jump]) * 0.25 * dtheta)
    # Kinks (where a deposit's chord meets the wall): a bin's median stands for a radius that
    # bends inside the bin; the midpoint rule is off by about an eighth of the second
    # difference of r² there (a quarter, to bound it). Only kinks beyond the noise count.
    prv = np.roll(radii_m, 1)
    second = np.abs(nxt**2 - 2.0 * radii_m**2 + prv**2)
    second_sd = math.sqrt(6.0) * 2.0 * radii_m * bin_sd
    kink = (second > 3.0 * second_sd) & ~jump & ~np.roll(jump, 1)
    resolution += float(np.sum(second[kink]) * 0.25 * dtheta)
    along = 0.0
    if slice_radii_m is not None and slice_radii_m.shape[1] > 1:
        cells = slice_radii_m.shape[1]
        seen_cells = np.isfinite(slice_radii_m)
        high = np.where(seen_cells, slice_radii_m, -np.inf).max(axis=1)
        low = np.where(seen_cells, slice_radii_m, np.inf).min(axis=1)
        spread = np.where(seen_cells.sum(axis=1) >= 2, high - low, np.nan)
        cell_sd = bin_sd * math.sqrt(cells)  # a sub-slice holds 1/S of the bin's points
        excess = np.nan_to_num(spread - 3.0 * math.sqrt(2.0) * cell_sd, nan=0.0)
        along = float(np.sum(radii_m * dtheta * np.clip(excess, 0.0, None)) * 0.5)
    return AreaUncertainty(
        noise_m2=noise, unseen_m2=unseen, resolution_m2=resolution, along_m2=along
    )


def longest_unseen_deg(seen: np.ndarray) -> float:
    """The longest run of unseen bins around the circle, in degrees (wrapping around).

    >>> longest_unseen_deg(np.arange(360) % 90 >= 20)
    20.0
    """
    return float(max(map(len, unseen_runs(seen)), default=0)) * 360.0 / len(seen)


def unseen_area_m2(seen: np.ndarray, radius_m: float) -> float:
    """What the unseen arcs of a section may hide, m²: for each run of unseen bins, the
    segment of a circle of ``radius_m`` behind the chord across it (``r²/2 (g − sin g)``
    for an arc of ``g`` radians).

    >>> half = np.arange(360) < 180
    >>> round(unseen_area_m2(half, 1.0) / (np.pi / 2), 6)
    1.0
    """
    dtheta = 2.0 * math.pi / len(seen)
    unseen = 0.0
    for run in unseen_runs(seen):
        g = min(len(run) * dtheta, 2.0 * math.pi)
        unseen += 0.5 * radius_m**2 * (g - math.sin(g))
    return unseen


def diameter_uncertainty_m(sigma_m: float, points_per_bin: float, pairs: int) -> float:
    """95 % uncertainty of the smallest (or largest) of ``pairs`` wall diameters, metres.

    Each diameter is the sum of two bin radii after the 5-bin running median; the extreme of
    ``pairs`` noisy diameters also strays by about ``sqrt(2 ln pairs)`` of their scatter, so
    that is added to the 1.96.
    """
    bin_sd = MEDIAN_EFFICIENCY * sigma_m / math.sqrt(max(points_per_bin, 1.0))
    smoothed_sd = MEDIAN_EFFICIENCY * bin_sd / math.sqrt(5.0)
    diameter_sd = math.sqrt(2.0) * smoothed_sd
    return (Z95 + math.sqrt(2.0 * math.log(max(pairs, 2)))) * diameter_sd


def height_uncertainty_m(sigma_m: float, points_low: float, points_wall: float) -> float:
    """95 % uncertainty of a deposit's height: the difference of two medians (the radius
    straight down over ``points_low`` points, the wall's over ``points_wall``)."""
    sd = (
        MEDIAN_EFFICIENCY
        * sigma_m
        * math.sqrt(1.0 / max(points_low, 1.0) + 1.0 / max(points_wall, 1.0))
    )
    return Z95 * sd
