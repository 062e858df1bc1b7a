"""Coding a section's displaced wall as an engineer would: which EN 13508-2 family, and where.

docs/coding.md states every rule. In short, from a section's inner contour:

1. **The wall.** The contour's radius at every degree around the axis is fitted, robustly and
   from outside in, by ``r(θ) = c0 + c1 cos θ + s1 sin θ + c2 cos 2θ + s2 sin 2θ``: a circle
   (``c0``), a small offset of the centre (``c1``, ``s1``) and an ellipse (``c2``, ``s2``,
   a smooth deformation), or about the axis as an exact ellipse. Deposits and obstacles only
   ever move the contour inwards, so bins further in than the noise allows are left out of
   the fit, and the fit is repeated.
2. **Displaced arcs.** Runs of bins that lie inside the wall by more than
   ``max(k σ, floor · r)`` (σ: the wall's own scatter) are the displaced wall.
3. **Each arc gets a family**, by its geometry alone:

   - **BBC settled deposits**: a straight, nearly level chord across the invert, meeting the
     wall at both ends, the wall under it unseen;
   - **BBB attached deposits**: a band along the wall, of even thickness, long against that
     thickness;
   - **BBE obstacle**: a body standing off the wall over a limited arc, rising steeply from a
     free wall (or from a deposit's top) at both ends;
   - **BAA deformation**: the wall itself, smoothly elliptical, its perimeter kept, its axes
     vertical and horizontal;
   - what fits none of these with confidence is **unclassified**, and keeps its figures.

   A deposit's chord is taken out first: whatever stands on it or beside it is coded on its
   own, so a combination gives one feature per family.

Angles are in the section plane of :class:`~pipescan.core.model.SectionMeasures` (column 0
is ``PipeAxis.right = up × direction``, column 1 up), counter-clockwise from column 0. Column 0
points to the *left* of someone looking in the survey's direction, so increasing angle runs
clockwise in their view, and clock positions (12 at the crown, 3 on their right) are
``((θ − 90°) / 30°) mod 12`` hours (:func:`clock_hours`).

Everything here is pure: arrays and small frozen dataclasses in, small dataclasses out.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from pipescan.core.contour.base import INVERT_ANGLE_RAD, angle_bins, polar_coordinates
from pipescan.core.model import SectionMeasures
from pipescan.core.summary import touches
from pipescan.core.uncertainty import MAD_TO_SIGMA, unseen_runs

__all__ = [
    "BAA",
    "BBB",
    "BBC",
    "BBE",
    "CODE_FAMILIES",
    "UNCLASSIFIED",
    "CodingParams",
    "FeatureRun",
    "SectionCoding",
    "WallFeature",
    "arcs_meet",
    "clock_angle_rad",
    "clock_hours",
    "code_contour",
    "code_section",
    "code_sections",
    "feature_runs",
    "radial_profile",
]

BBC = "BBC"
BBB = "BBB"
BBE = "BBE"
BAA = "BAA"
UNCLASSIFIED = "unclassified"
"""The code of a displaced wall that no rule fits with confidence: never an EN 13508-2 code."""

CODE_FAMILIES: dict[str, str] = {
    BBC: "settled deposits",
    BBB: "attached deposits",
    BBE: "obstacle",
    BAA: "deformation",
    UNCLASSIFIED: "unclassified",
}
"""Every code the coder gives, with the family's name in words."""

_TWO_PI = 2.0 * math.pi
_EDGE_TOL_DEG = 10.0  # a contour within this of the ray from the centre is an occluding edge


class _Interval(Protocol):
    @property
    def chainage_start_m(self) -> float: ...

    @property
    def chainage_end_m(self) -> float: ...


def clock_hours(angle_rad: float) -> float:
    """Clock position, in hours in (0, 12], of a section-plane angle (see the module).

    >>> [clock_hours(math.radians(a)) for a in (90, 180, 270, 0, 135)]
    [12.0, 3.0, 6.0, 9.0, 1.5]
    """
    hours = ((math.degrees(angle_rad) - 90.0) / 30.0) % 12.0
    hours = round(hours, 9) % 12.0
    return 12.0 if hours == 0.0 else hours


def clock_angle_rad(hours: float) -> float:
    """The section-plane angle (radians, in [0, 2π)) of a clock position in hours.

    >>> round(math.degrees(clock_angle_rad(3.0)))
    180
    """
    return math.radians(90.0 + 30.0 * hours) % _TWO_PI


@dataclass(frozen=True)
class CodingParams:
    """The coder's thresholds; docs/coding.md gives the reason for each.

    Attributes
    ----------
    bins : int
        Angle bins of the radial profile (1° at 360).
    noise_factor : float
        A bin is displaced when it lies inside the wall by more than ``noise_factor`` times
        the wall's scatter ...
    displacement_floor_ratio : float
        ... and by more than this share of the wall radius.
    gap_deg : float
        Displaced arcs closer than this merge (one body dipping towards the wall once).
    fade_ratio : float
        A displaced arc runs on, at both ends, while its displacement stays over this share of
        the threshold (and twice the wall's scatter): its edges are seen to where they fade.
    min_area_ratio : float
        A displaced arc whose lost area is under this share of the nominal cross-section is
        not a feature: below what sections measure reliably.
    min_deformation_ratio : float
        The smallest diameter reduction coded as a deformation: within the roundness
        tolerance of pipes and the noise of the fit below it.
    max_scatter_ratio : float
        A wall that scatters (1σ) by more than this share of the radius is too ragged to code
        anything against: the section is unclassified as a whole. Measured walls scatter by
        well under 1 % of the radius.
    ring_ratio : float
        A wall whose longest radius lies inside the nominal by more than this share is
        displaced all round (attached deposits all round, or a wrong nominal diameter):
        unclassified.
    chord_tol_ratio : float
        Distance from a deposit's chord (share of the nominal diameter) within which a bin lies
        on it.
    max_chord_tilt_deg : float
        Steepest chord still taken as a settled deposit's level top.
    min_chord_support_ratio, min_chord_seen_ratio, max_chord_contradiction_ratio : float
        Share of the fill's top in view (not under something standing on it) that must lie on
        the chord; share of the fill's whole arc that must be seen on it; share of the arc that
        may be more open than the fill allows.
    band_spread_ratio : float
        A band's thickness over the middle of its arc varies by at most this share of its
        median (10th to 90th percentile), and its face there follows the wall (a circle about
        the axis fits it better than a straight line).
    band_max_thickness_ratio : float
        Thickest band, as a share of the wall radius.
    band_min_length_ratio : float
        A band is at least this many times longer (along the wall) than it is thick.
    body_max_aspect : float
        A body whose face follows the wall is at most this many times longer (along the
        wall) than it stands off it; a flat face stands off the wall as a body at any length.
    body_min_steepness_deg : float
        At the invert, where settled material heaps, a body rises from its surroundings at both
        ends at least this steeply (from the horizontal); a heap's flank lies at its angle of
        repose, under 40°.
    max_body_arc_deg : float
        Widest arc a body standing off the wall may cover.
    deformation_axis_tol_deg : float
        An ellipse's axes within this of vertical and horizontal.
    symmetric_share : float
        Share of bins whose radius is within the displacement floor of the opposite bin's, for
        the contour to be taken as possibly a deformed wall from the start (an ellipse about
        the axis is point-symmetric; a band or an obstacle on one side is not).
    perimeter_tol_ratio : float
        "Perimeter roughly kept": the fitted wall's perimeter within this share of the
        nominal.
    """

    bins: int = 360
    noise_factor: float = 4.0
    displacement_floor_ratio: float = 0.03
    gap_deg: float = 4.0
    fade_ratio: float = 0.3
    min_area_ratio: float = 0.01
    min_deformation_ratio: float = 0.02
    ring_ratio: float = 0.03
    max_scatter_ratio: float = 0.02
    chord_tol_ratio: float = 0.015
    max_chord_tilt_deg: float = 12.0
    min_chord_support_ratio: float = 0.6
    min_chord_seen_ratio: float = 0.3
    max_chord_contradiction_ratio: float = 0.1
    band_spread_ratio: float = 0.3
    band_max_thickness_ratio: float = 0.25
    band_min_length_ratio: float = 6.0
    body_max_aspect: float = 5.0
    body_min_steepness_deg: float = 45.0
    max_body_arc_deg: float = 180.0
    deformation_axis_tol_deg: float = 20.0
    symmetric_share: float = 0.9
    perimeter_tol_ratio: float = 0.05


@dataclass(frozen=True)
class WallFeature:
    """One family found in one section.

    Attributes
    ----------
    code
        ``BBC``, ``BBB``, ``BBE``, ``BAA`` or ``unclassified``.
    arc_from_rad, arc_to_rad
        The displaced arc, section-plane angles in [0, 2π); it runs from ``arc_from_rad``
        with increasing angle (clockwise looking in the survey's direction) to
        ``arc_to_rad``. Both None for a deformation, which moves the whole ring.
    lost_area_m2
        Area between the wall and the contour over the arc (0 for a deformation).
    height_m
        The largest displacement from the wall (for a deposit, its chord's height above the
        wall's lowest point; for a deformation, the reduction of the smallest diameter).
    rule
        Which rule coded it, or why none did, in words.
    characterisation
        For a deformation, EN 13508-2's ``A`` (vertical) or ``B`` (horizontal); else None.
    measure
        The :class:`~pipescan.core.model.SectionMeasures` column that quantifies it, and that
        the threshold table grades it on: ``deposit_height_ratio`` for settled deposits,
        ``deformation_ratio`` for a deformation (or an unclassified ellipse),
        ``blockage_ratio`` for the rest.
    """

    code: str
    arc_from_rad: float | None
    arc_to_rad: float | None
    lost_area_m2: float
    height_m: float
    rule: str
    characterisation: str | None = None
    measure: str = "blockage_ratio"

    @property
    def clock_from_h(self) -> float | None:
        return None if self.arc_from_rad is None else clock_hours(self.arc_from_rad)

    @property
    def clock_to_h(self) -> float | None:
        return None if self.arc_to_rad is None else clock_hours(self.arc_to_rad)

    @property
    def arc_rad(self) -> float:
        """The arc's angular length, radians (2π for a deformation)."""
        if self.arc_from_rad is None or self.arc_to_rad is None:
            return _TWO_PI
        return (self.arc_to_rad - self.arc_from_rad) % _TWO_PI


@dataclass(frozen=True)
class SectionCoding:
    """What the coder found in one section.

    ``features`` are in order of their arcs' start; ``wall_radius_m`` is the fitted wall's
    mean radius and ``noise_m`` its scatter (1σ); ``displacement_m`` the threshold a bin had
    to pass to count as displaced.
    """

    features: tuple[WallFeature, ...]
    wall_radius_m: float
    noise_m: float
    displacement_m: float

    @property
    def codes(self) -> tuple[str, ...]:
        return tuple(f.code for f in self.features)


# --- the radial profile -----------------------------------------------------------------------


def radial_profile(contour_m: np.ndarray, bins: int = 360, *, step_m: float = 0.002) -> np.ndarray:
    """The nearest contour radius in each of ``bins`` equal angle bins around the origin.

    The closed polygon is sampled every ``step_m`` along its edges, so a long straight edge
    (a chord across a deposit) fills every bin it crosses; where the contour folds back (a
    pocket beside an obstacle), a bin takes the nearest surface. Bins that no edge crosses
    (only when the contour does not go round the origin) are interpolated around the circle.

    Parameters
    ----------
    contour_m : (M, 2) float
        Closed contour, metres, section-plane coordinates (origin on the axis).
    bins : int

    Returns
    -------
    (bins,) float
        Radius per bin, metres; bin ``k`` spans angles ``[k, k + 1) · 2π / bins``.

    Raises
    ------
    ValueError
        If the contour is not (M, 2) with M >= 3 finite points.

    Examples
    --------
    >>> t = np.linspace(0, 2 * np.pi, 100, endpoint=False)
    >>> r = radial_profile(np.column_stack((0.3 * np.cos(t), 0.3 * np.sin(t))))
    >>> bool(np.allclose(r, 0.3, atol=2e-4))
    True
    """
    poly = np.asarray(contour_m, dtype=np.float64)
    if poly.ndim != 2 or poly.shape[1] != 2 or len(poly) < 3 or not np.isfinite(poly).all():
        raise ValueError("contour_m must have shape (M, 2) with M >= 3 finite points.")
    start = poly
    end = np.roll(poly, -1, axis=0)
    length = np.hypot(*(end - start).T)
    pieces = np.maximum(1, np.ceil(length / step_m).astype(np.int64))
    owner = np.repeat(np.arange(len(poly)), pieces)
    offset = np.arange(len(owner)) - np.repeat(np.cumsum(pieces) - pieces, pieces)
    frac = offset / pieces[owner]
    pts = start[owner] + frac[:, None] * (end - start)[owner]
    angle, radius = polar_coordinates(pts)
    index = angle_bins(angle, bins)
    out = np.full(bins, np.inf)
    np.minimum.at(out, index, radius)
    seen = np.isfinite(out)
    if not seen.all():
        centres = (np.arange(bins) + 0.5) * _TWO_PI / bins
        out[~seen] = np.interp(centres[~seen], centres[seen], out[seen], period=_TWO_PI)
    return out


# --- the wall ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Wall:
    coef: np.ndarray  # c0, c1, s1, c2, s2 (an exact ellipse: its mean semi-axis in c0, and
    # half the difference of its semi-axes in c2, s2, along its long axis)
    noise_m: float
    inliers: np.ndarray  # bool per bin
    harmonics: int  # 0: circle about the axis, 1: with a centre offset, 2: with an ellipse
    inverse_square: np.ndarray | None = None
    """An exact ellipse about the axis, ``1/r² = A + B cos 2θ + C sin 2θ``: (A, B, C)."""

    def radius(self, angles: np.ndarray) -> np.ndarray:
        if self.inverse_square is not None:
            return _ellipse_radius(self.inverse_square, angles)
        return _design(angles, 2) @ self.coef


def _design(angles: np.ndarray, harmonics: int) -> np.ndarray:
    columns = [np.ones_like(angles)]
    if harmonics >= 1:
        columns += [np.cos(angles), np.sin(angles)]
    if harmonics >= 2:
        columns += [np.cos(2 * angles), np.sin(2 * angles)]
    return np.column_stack(columns)


def _largest_gap_rad(mask: np.ndarray) -> float:
    """Longest circular run of False in ``mask``, radians."""
    if mask.all():
        return 0.0
    if not mask.any():
        return _TWO_PI
    start = int(np.argmax(mask))
    rolled = np.roll(~mask, -start)
    longest = run = 0
    for off in rolled:
        run = run + 1 if off else 0
        longest = max(longest, run)
    return longest * _TWO_PI / len(mask)


def _fit_wall(radii: np.ndarray, angles: np.ndarray, floor_m: float, p: CodingParams) -> _Wall:
    """The wall by robust least squares (see the module).

    Two starts; the one that ends with more of the contour on it (within half the
    displacement floor) wins. One starts from the bins near the outer envelope (deposits and
    obstacles only pull the contour inwards). The other starts from every bin, as an ellipse
    centred on the axis: a deformed wall is far from any circle, so the first start would
    leave its flattened sides out and never fit them, and a deformation squeezes the pipe
    about its axis (the axis is fitted to the wall), where a band on one side would need the
    centre to move. The second start is tried only when the contour is point-symmetric about
    the axis (``symmetric_share`` of its bins within the floor of the opposite one), as an
    ellipse about it is. Where the winner's centre moved off the axis, a third fit, centred,
    may replace it (below). A centred ellipse is fitted exactly (``_ellipse_about_axis``).
    """
    reference = float(np.percentile(radii, 75))
    envelope = _robust_wall(
        radii, angles, floor_m, p, np.abs(radii - reference) <= max(0.03 * reference, floor_m)
    )
    # An ellipse about the axis is point-symmetric: r(θ) = r(θ + π). A contour that is not (a
    # band or an obstacle on one side) is no candidate for the second start.
    opposite = np.roll(radii, len(radii) // 2)
    wall = envelope
    if np.mean(np.abs(radii - opposite) <= floor_m) >= p.symmetric_share:
        ellipse = _robust_wall(
            radii, angles, floor_m, p, np.ones(len(radii), dtype=bool), centred=True
        )

        def on_wall(w: _Wall) -> int:
            return int((np.abs(radii - w.radius(angles)) <= 0.5 * floor_m).sum())

        wall = max((envelope, ellipse), key=on_wall)
    if wall.harmonics < 1 or not np.any(wall.coef[1:3]):
        return wall
    # The envelope's centre moved off the axis. A band of even thickness over one side of the
    # wall is concentric with it, yet the first harmonic can take up about two thirds of its
    # thickness as an offset, leaving it under the threshold: the wall then scatters well
    # beyond its noise. Refit about the axis, without the bins lower than their opposite by
    # more than the floor (an ellipse about the axis is point-symmetric; whatever stands on one
    # side is not); that wall is kept when it scatters significantly less.
    centred = _robust_wall(radii, angles, floor_m, p, radii >= opposite - floor_m, centred=True)
    if centred.harmonics < 2 or not _scatters_less(centred, wall):
        return wall
    return centred


def _scatters_less(a: _Wall, b: _Wall) -> bool:
    """Whether wall ``a`` scatters less than wall ``b`` by more than twice the standard error
    of the difference of their scatters (each a MAD-based σ from its inlier bins: relative
    variance 1.36 / n for Gaussian noise)."""
    n_a, n_b = max(int(a.inliers.sum()), 1), max(int(b.inliers.sum()), 1)
    return b.noise_m > a.noise_m * (1.0 + 2.0 * math.sqrt(1.36 / n_a + 1.36 / n_b))


def _robust_wall(
    radii: np.ndarray,
    angles: np.ndarray,
    floor_m: float,
    p: CodingParams,
    inliers: np.ndarray,
    *,
    centred: bool = False,
) -> _Wall:
    coef = np.array([float(np.median(radii[inliers])) if inliers.any() else 0.0, 0, 0, 0, 0])
    noise = floor_m
    harmonics = 0
    inverse = None
    for _ in range(10):
        if centred:
            folded = inliers | np.roll(inliers, len(inliers) // 2)
            harmonics = 2 if _largest_gap_rad(folded) <= math.radians(50) else 0
        else:
            gap = _largest_gap_rad(inliers)
            # Each harmonic needs the wall seen all round enough to be told from a feature.
            harmonics = 2 if gap <= math.radians(100) else 1 if gap <= math.radians(150) else 0
        if inliers.sum() < 8:
            break
        inverse = (
            _ellipse_about_axis(radii[inliers], angles[inliers])
            if (centred and harmonics == 2)
            else None
        )
        if inverse is not None:
            coef = _ellipse_coef(inverse)
            residual = radii - _ellipse_radius(inverse, angles)
        else:
            design = _design(angles[inliers], harmonics)
            if centred:
                design = design[:, :1]
            sol, *_ = np.linalg.lstsq(design, radii[inliers], rcond=None)
            coef = np.zeros(5)
            coef[: len(sol)] = sol
            residual = radii - _design(angles, 2) @ coef
        mad = float(np.median(np.abs(residual[inliers] - np.median(residual[inliers]))))
        noise = max(MAD_TO_SIGMA * mad, 1e-4)
        band = max(p.noise_factor * noise, floor_m)
        new = (residual > -band) & (residual < max(band, 3.0 * floor_m))
        if np.array_equal(new, inliers):
            break
        inliers = new
    return _Wall(coef, noise, inliers, harmonics, inverse)


def _ellipse_about_axis(radii: np.ndarray, angles: np.ndarray) -> np.ndarray | None:
    """The ellipse centred on the axis through the bins ``(angles, radii)``, by least squares
    on ``1/r² = A + B cos 2θ + C sin 2θ`` (linear in A, B, C; an ellipse about its centre is
    exactly that), each bin weighted by ``r³/2`` so that its residual counts in metres along
    the radius. (A, B, C), or None when the fit is no ellipse."""
    weight = 0.5 * radii**3
    design = _design(angles, 2)[:, [0, 3, 4]] * weight[:, None]
    sol, *_ = np.linalg.lstsq(design, 0.5 * radii, rcond=None)  # weight / r²
    return sol if sol[0] > math.hypot(sol[1], sol[2]) else None


def _ellipse_radius(inverse: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """The radius at ``angles`` of the ellipse ``1/r² = A + B cos 2θ + C sin 2θ``."""
    return 1.0 / np.sqrt(_design(angles, 2)[:, [0, 3, 4]] @ inverse)


def _ellipse_coef(inverse: np.ndarray) -> np.ndarray:
    """The wall's ``coef`` for an ellipse given as ``inverse_square``: its mean semi-axis, and
    half the difference of its semi-axes along its long axis (where ``1/r²`` is least)."""
    a_inv, b_inv, c_inv = (float(v) for v in inverse)
    swing = math.hypot(b_inv, c_inv)
    long_r, short_r = 1.0 / math.sqrt(a_inv - swing), 1.0 / math.sqrt(a_inv + swing)
    half = 0.5 * (long_r - short_r)
    cos2, sin2 = (-b_inv / swing, -c_inv / swing) if swing > 0 else (1.0, 0.0)
    return np.array([0.5 * (long_r + short_r), 0.0, 0.0, half * cos2, half * sin2])


# --- displaced arcs ---------------------------------------------------------------------------


def _circular_runs(mask: np.ndarray) -> list[np.ndarray]:
    """Circular runs of True in ``mask``, each as an array of bin indices in order."""
    return unseen_runs(~np.asarray(mask, dtype=bool))


def _close_gaps(mask: np.ndarray, gap_bins: int) -> np.ndarray:
    """``mask`` with circular runs of at most ``gap_bins`` False bins between True ones set."""
    if gap_bins <= 0 or mask.all() or not mask.any():
        return mask
    out = mask.copy()
    for run in _circular_runs(~mask):
        if len(run) <= gap_bins:
            out[run] = True
    return out


def _arc_area_m2(outer: np.ndarray, inner: np.ndarray, idx: np.ndarray, bins: int) -> float:
    """Area between two radial profiles over bins ``idx``: ``Σ ½ (outer² − inner²) Δθ``."""
    o, i = outer[idx], inner[idx]
    return float(np.sum(0.5 * np.clip(o * o - i * i, 0.0, None)) * _TWO_PI / bins)


def _arc_ends(idx: np.ndarray, bins: int) -> tuple[float, float]:
    """The angles where a run of bins starts and ends (bin edges), radians."""
    return (idx[0] * _TWO_PI / bins) % _TWO_PI, ((idx[-1] + 1) * _TWO_PI / bins) % _TWO_PI


# --- the families -----------------------------------------------------------------------------


@dataclass(frozen=True)
class _Chord:
    slope: float
    intercept_m: float  # the line y = intercept + slope x
    fill_r: np.ndarray  # the contour a fill below the line would leave, per bin
    fill: np.ndarray  # bins the fill displaces beyond the threshold
    support: float  # share of those bins whose contour lies on the line
    contradiction: float  # share of those bins whose contour is more open than the fill
    on: np.ndarray  # bins of the fill whose contour lies on the line


def _fill_profiles(
    wall_r: np.ndarray, angles: np.ndarray, slopes: np.ndarray, intercepts_m: np.ndarray
) -> np.ndarray:
    """(C, B) radius per bin of the contour a fill below each line ``y = b + m x`` leaves."""
    c, s = np.cos(angles)[None, :], np.sin(angles)[None, :]
    denom = s - slopes[:, None] * c
    with np.errstate(divide="ignore", invalid="ignore"):
        t = intercepts_m[:, None] / denom  # where the ray from the centre meets the line
    meets = (denom < 0) & (t > 0) & (intercepts_m[:, None] < 0)
    return np.where(meets, np.minimum(wall_r[None, :], np.where(meets, t, np.inf)), wall_r)


def _find_chord(
    radii: np.ndarray,
    angles: np.ndarray,
    wall_r: np.ndarray,
    arc: np.ndarray,
    threshold_m: float,
    tol_m: float,
    p: CodingParams,
) -> _Chord | None:
    """The line across the invert that best explains the bins ``arc`` as a fill (docs).

    Candidates are level lines at the height of every bin of the arc and lines through pairs
    of its bins, no steeper than ``max_chord_tilt_deg``. Each is scored by the bins its fill
    would displace: +1 for a bin whose contour lies on the line, -2 for one whose contour is
    more open than the fill allows (the fill is not there). Something standing on the fill
    (inside its top) neither helps nor hurts.
    """
    x = radii[arc] * np.cos(angles[arc])
    y = radii[arc] * np.sin(angles[arc])
    max_slope = math.tan(math.radians(p.max_chord_tilt_deg))
    levels = np.unique(np.round(y / (tol_m / 2.0)) * (tol_m / 2.0))
    slopes, intercepts = [np.zeros(len(levels))], [levels]
    if len(arc) >= 2:
        rng = np.random.default_rng(len(arc))
        i, j = rng.integers(0, len(arc), size=(2, min(300, len(arc) ** 2)))
        wide = np.abs(x[i] - x[j]) > 4.0 * tol_m
        m = (y[j][wide] - y[i][wide]) / (x[j][wide] - x[i][wide])
        level = np.abs(m) <= max_slope
        slopes.append(m[level])
        intercepts.append((y[i][wide] - m * x[i][wide])[level])
    m_all, b_all = np.concatenate(slopes), np.concatenate(intercepts)
    keep = b_all < 0
    if not keep.any():
        return None

    def evaluate(m: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, ...]:
        fill_r = _fill_profiles(wall_r, angles, m, b)
        fill = wall_r[None, :] - fill_r > threshold_m
        sin_abs = np.abs(np.sin(angles[None, :] - np.arctan(m)[:, None]))
        radial_tol = tol_m / np.maximum(sin_abs, 0.2)
        on = fill & (np.abs(radii[None, :] - fill_r) <= radial_tol)
        more_open = fill & (radii[None, :] > fill_r + radial_tol)
        inside = fill & (radii[None, :] < fill_r - radial_tol)
        return fill_r, fill, on, more_open, inside

    m_all, b_all = m_all[keep], b_all[keep]
    _, _, on, more_open, _ = evaluate(m_all, b_all)
    score = on.sum(axis=1) - 2.0 * more_open.sum(axis=1)
    k = int(np.argmax(score))
    m_best, b_best = float(m_all[k]), float(b_all[k])
    # Refine by least squares through the bins on the line (a level line stays level).
    on_k = on[k]
    if m_best != 0.0 and on_k.sum() >= 3:
        xs = radii[on_k] * np.cos(angles[on_k])
        ys = radii[on_k] * np.sin(angles[on_k])
        if np.ptp(xs) > 4.0 * tol_m:
            m_fit, b_fit = (float(v) for v in np.polyfit(xs, ys, 1))
            if abs(m_fit) <= max_slope and b_fit < 0:
                m_best, b_best = m_fit, b_fit
    elif on_k.sum() >= 1:
        b_best = float(np.median(radii[on_k] * np.sin(angles[on_k])))
    fill_r1, fill1, on1, open1, inside1 = (
        a[0] for a in evaluate(np.array([m_best]), np.array([b_best]))
    )
    n = float(fill1.sum())
    if n == 0:
        return None
    # Where the fill's top is in view (not under something standing on it), how much of it
    # lies on the line; and how much of the fill's arc is more open than a fill allows.
    visible = n - float(inside1.sum())
    support = float(on1.sum()) / visible if visible > 0 else 0.0
    if float(on1.sum()) < p.min_chord_seen_ratio * n:
        support = 0.0
    return _Chord(m_best, b_best, fill_r1, fill1, support, float(open1.sum()) / n, on1)


def _covers_invert(idx: np.ndarray, bins: int) -> bool:
    invert_bin = int(INVERT_ANGLE_RAD * bins / _TWO_PI)
    return bool(np.isin(invert_bin, idx) or np.isin(invert_bin - 1, idx))


def _flank_steepness_deg(
    radii: np.ndarray, angles: np.ndarray, idx: np.ndarray, min_rise_m: float
) -> float:
    """How steeply an arc's contour rises from its surroundings, at its gentler end, in
    degrees from the horizontal.

    At each end, the steepest secant from the contour just outside the arc to a point of the
    arc's first (or last) half that lies at least ``min_rise_m`` from it. A secant that runs
    along the ray from the centre (within ``_EDGE_TOL_DEG``) is an occluding edge: the side of
    a body hidden behind its top, which the contour crosses radially; it counts as upright.
    A body's side stands up steeply or hides behind such an edge; a heap of settled material
    slopes at its angle of repose, under 40°, facing the centre.
    """
    bins = len(radii)
    x, y = radii * np.cos(angles), radii * np.sin(angles)
    half = max(1, (len(idx) + 1) // 2)
    ends = []
    for outside, inner in ((idx[0] - 1, idx[:half]), ((idx[-1] + 1) % bins, idx[::-1][:half])):
        o = outside % bins
        dx, dy = x[inner] - x[o], y[inner] - y[o]
        far = np.hypot(dx, dy) >= min_rise_m
        if not far.any():
            ends.append(0.0)
            continue
        steep = np.degrees(np.arctan2(np.abs(dy[far]), np.abs(dx[far])))
        # The angle between the secant and the ray from the centre through the outside point.
        along_ray = np.degrees(
            np.abs(np.angle(np.exp(1j * (np.arctan2(-dy[far], -dx[far]) - angles[o]))))
        )
        steep = np.where(np.minimum(along_ray, 180.0 - along_ray) <= _EDGE_TOL_DEG, 90.0, steep)
        ends.append(float(steep.max()))
    return min(ends)


def _follows_the_wall(radii: np.ndarray, angles: np.ndarray, idx: np.ndarray) -> bool:
    """Whether the contour over bins ``idx`` follows the wall (a circle about the axis) more
    closely than a straight line: a band's face does, an obstacle's flat face does not."""
    if len(idx) < 5:
        return False
    r = radii[idx]
    x, y = r * np.cos(angles[idx]), r * np.sin(angles[idx])
    about_circle = float(np.sqrt(np.mean((r - np.median(r)) ** 2)))
    xy = np.column_stack((x - x.mean(), y - y.mean()))
    # The smallest singular value: the RMS distance to the best straight line (total least
    # squares), times the square root of the point count.
    about_line = float(np.linalg.svd(xy, compute_uv=False)[-1]) / math.sqrt(len(idx))
    return about_circle < about_line


def _classify_arc(
    disp: np.ndarray,
    idx: np.ndarray,
    reference: np.ndarray,
    radii: np.ndarray,
    angles: np.ndarray,
    threshold_m: float,
    on_fill: bool,
    p: CodingParams,
) -> tuple[str, str]:
    """BBB, BBE or unclassified for one displaced arc that is not a deposit's chord.

    ``disp`` is the displacement of every bin from ``reference``, the surface the arc stands
    on (the wall, or a deposit's top where there is one).
    """
    bins = len(radii)
    n = len(idx)
    arc_rad = n * _TWO_PI / bins
    radius = float(np.median(reference[idx]))
    own = disp[idx]
    middle = own[int(0.15 * n) : max(int(0.15 * n) + 1, n - int(0.15 * n))]
    thickness = float(np.median(middle))
    spread = float(np.percentile(middle, 90) - np.percentile(middle, 10)) / max(thickness, 1e-9)
    length_m = arc_rad * radius
    peak = float(own.max())
    aspect = length_m / max(peak, 1e-9)
    surface = "the deposit's top" if on_fill else "the wall"
    middle_idx = idx[int(0.15 * n) : max(int(0.15 * n) + 1, n - int(0.15 * n))]
    concentric = _follows_the_wall(radii, angles, middle_idx)
    if (
        not on_fill
        and spread <= p.band_spread_ratio
        and concentric
        and thickness <= p.band_max_thickness_ratio * radius
        and length_m >= p.band_min_length_ratio * thickness
    ):
        return BBB, (
            f"a band along the wall, {1000 * thickness:.0f} mm thick (varying by "
            f"{100 * spread:.0f} %) over {1000 * length_m:.0f} mm, its face following the wall"
        )
    at_invert = _covers_invert(idx, bins) or on_fill
    # A flat face that does not follow the wall is a body however long it is: a chord across
    # 60° of the wall stands off it by only an eighth of its length, so a board or a box
    # hanging from the crown would fail any length limit. The limit keeps apart only arcs
    # whose face follows the wall (an uneven band is not an obstacle).
    compact = (aspect <= p.body_max_aspect or not concentric) and arc_rad <= math.radians(
        p.max_body_arc_deg
    )
    steepness = _flank_steepness_deg(radii, angles, idx, 2.0 * threshold_m) if at_invert else 90.0
    steep = steepness >= p.body_min_steepness_deg
    if compact and steep and n < bins:
        return BBE, (
            f"a body standing {1000 * peak:.0f} mm off {surface} over {1000 * length_m:.0f} mm"
            f" ({math.degrees(arc_rad):.0f}°)"
            + (f", its sides rising at {steepness:.0f}° at the invert" if at_invert else "")
        )
    why = [
        f"its thickness varies by {100 * spread:.0f} % (not a band)"
        if concentric
        else "its face is straight, not following the wall (not a band)"
    ]
    if not compact:
        why.append(f"it is {aspect:.1f} times longer than high (not a body)")
    elif not steep:
        why.append(f"it rises at {steepness:.0f}° at the invert, as a heap would (not a body)")
    return UNCLASSIFIED, "no rule fits: " + "; ".join(why)


def code_section(
    contour_m: np.ndarray,
    nominal_diameter_m: float,
    params: CodingParams = CodingParams(),
) -> SectionCoding:
    """Code one section's displaced wall (see the module and docs/coding.md).

    Parameters
    ----------
    contour_m : (M, 2) float
        The section's inner contour, metres, in the section plane (origin on the axis,
        column 0 ``PipeAxis.right``, column 1 up), as ``SectionMeasures.contour_m``.
    nominal_diameter_m : float
        Design inner diameter.
    params : CodingParams

    Returns
    -------
    SectionCoding
        Its features, each over ``params.min_area_ratio`` of the nominal area (or a
        deformation over ``params.min_deformation_ratio``); none for a sound wall.

    Raises
    ------
    ValueError
        If the contour is not (M, 2) with M >= 3 finite points, or the diameter is not
        positive.

    Examples
    --------
    A 0.5 m pipe with a level fill 0.1 m deep at the invert:

    >>> t = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    >>> ring = 0.25 * np.column_stack((np.cos(t), np.sin(t)))
    >>> ring[:, 1] = np.maximum(ring[:, 1], -0.15)
    >>> f = code_section(ring, 0.5).features[0]
    >>> f.code, round(f.clock_from_h, 1), round(f.clock_to_h, 1), round(f.height_m, 3)
    ('BBC', 4.2, 7.8, 0.1)
    """
    if not nominal_diameter_m > 0:
        raise ValueError(f"nominal_diameter_m must be > 0, got {nominal_diameter_m!r}.")
    p = params
    bins = p.bins
    radii = radial_profile(contour_m, bins)
    angles = (np.arange(bins) + 0.5) * _TWO_PI / bins
    nominal_r = nominal_diameter_m / 2.0
    nominal_area = math.pi * nominal_r**2
    floor_m = p.displacement_floor_ratio * nominal_r
    wall = _fit_wall(radii, angles, floor_m, p)
    wall_r = wall.radius(angles)
    threshold = max(p.noise_factor * wall.noise_m, floor_m)
    if wall.noise_m > p.max_scatter_ratio * nominal_r:
        return _too_ragged(radii, wall, nominal_area, threshold)
    ring = _ring_feature(wall, wall_r, radii, nominal_r, nominal_area, bins, p)
    if ring is not None:
        return SectionCoding((ring,), float(wall.coef[0]), wall.noise_m, threshold)
    deposits, reference = _deposits(radii, angles, wall, wall_r, threshold, nominal_diameter_m, p)
    standing = _standing_arcs(radii, angles, wall, wall_r, reference, threshold, nominal_area, p)
    features = [f for f in deposits + standing if f.lost_area_m2 >= p.min_area_ratio * nominal_area]
    deformation = _deformation_feature(wall, wall_r, nominal_r, bins, p)
    if deformation is not None:
        features.append(deformation)
    features.sort(key=lambda f: (f.arc_from_rad is None, f.arc_from_rad or 0.0))
    return SectionCoding(tuple(features), float(wall.coef[0]), wall.noise_m, threshold)


def _too_ragged(
    radii: np.ndarray, wall: _Wall, nominal_area: float, threshold: float
) -> SectionCoding:
    """A wall this ragged (a face across the section, points from elsewhere) is no wall to
    code anything against: one unclassified feature says so."""
    bins = len(radii)
    lost = float(nominal_area - np.sum(0.5 * radii * radii) * _TWO_PI / bins)
    ragged = WallFeature(
        UNCLASSIFIED,
        None,
        None,
        max(lost, 0.0),
        0.0,
        rule=(
            f"the contour is too ragged to code: the wall scatters by {1000 * wall.noise_m:.0f} mm"
        ),
    )
    return SectionCoding((ragged,), float(wall.coef[0]), wall.noise_m, threshold)


def _deposits(
    radii: np.ndarray,
    angles: np.ndarray,
    wall: _Wall,
    wall_r: np.ndarray,
    threshold: float,
    nominal_diameter_m: float,
    p: CodingParams,
) -> tuple[list[WallFeature], np.ndarray]:
    """Settled deposits (BBC): displaced arcs over the invert whose top is a straight chord.
    Returns them, and the surface each remaining arc stands off (the wall, or a fill's top)."""
    bins = len(radii)
    displaced = _close_gaps(wall_r - radii > threshold, round(p.gap_deg * bins / 360.0))
    tol_m = max(p.chord_tol_ratio * nominal_diameter_m, 2.5 * wall.noise_m)
    reference = wall_r.copy()
    features = []
    for arc in _circular_runs(displaced):
        if not _covers_invert(arc, bins):
            continue
        chord = _find_chord(radii, angles, wall_r, arc, threshold, tol_m, p)
        if chord is None:
            continue
        ok = (
            chord.support >= p.min_chord_support_ratio
            and chord.contradiction <= p.max_chord_contradiction_ratio
            and _covers_invert(np.flatnonzero(chord.fill), bins)
            # A settled top is straight; a band's face reaching the invert follows the wall.
            and not _follows_the_wall(radii, angles, _ordered(np.flatnonzero(chord.on), bins))
        )
        if not ok:
            continue
        # The fill's arc runs to where its top meets the wall.
        fill_idx = _ordered(np.flatnonzero(chord.fill_r < wall_r - 1e-9), bins)
        area = _arc_area_m2(wall_r, chord.fill_r, fill_idx, bins)
        lowest = float(np.min(wall_r * np.sin(angles)))
        height = max(0.0, chord.intercept_m - lowest)
        tilt = math.degrees(math.atan(chord.slope))
        features.append(
            WallFeature(
                BBC,
                *_arc_ends(fill_idx, bins),
                lost_area_m2=area,
                height_m=height,
                measure="deposit_height_ratio",
                rule=(
                    f"a chord across the invert, {1000 * height:.0f} mm high, tilted "
                    f"{tilt:.0f}°: {100 * chord.support:.0f} % of its top in view on it"
                ),
            )
        )
        reference = np.minimum(reference, chord.fill_r)
    return features, reference


def _standing_arcs(
    radii: np.ndarray,
    angles: np.ndarray,
    wall: _Wall,
    wall_r: np.ndarray,
    reference: np.ndarray,
    threshold: float,
    nominal_area: float,
    p: CodingParams,
) -> list[WallFeature]:
    """Whatever stands inside the wall, or inside a deposit's top, beyond the threshold,
    classified (:func:`_classify_arc`).

    Each arc runs on to where its displacement fades into the wall's scatter, so that a
    tapering edge is seen whole (an even band has square edges; a thin chord tapers).
    """
    bins = len(radii)
    disp = _smooth3(reference - radii)
    rest = _close_gaps(disp > threshold, round(p.gap_deg * bins / 360.0))
    runs = _circular_runs(rest)
    fade = max(2.0 * wall.noise_m, p.fade_ratio * threshold)
    taken = rest.copy()
    for k, arc in enumerate(runs):
        runs[k] = arc = _grow(arc, disp > fade, taken)
        taken[arc] = True
    features = []
    for arc in runs:
        area = _arc_area_m2(reference, radii, arc, bins)
        if area < p.min_area_ratio * nominal_area:
            continue
        on_fill = bool(np.any(reference[arc] < wall_r[arc] - 1e-9))
        code, rule = _classify_arc(disp, arc, reference, radii, angles, threshold, on_fill, p)
        features.append(
            WallFeature(code, *_arc_ends(arc, bins), area, float(disp[arc].max()), rule)
        )
    return features


def _grow(arc: np.ndarray, above: np.ndarray, taken: np.ndarray) -> np.ndarray:
    """``arc`` (bins in order) extended at both ends over bins that are ``above`` and not
    ``taken`` by another arc."""
    bins = len(above)
    if len(arc) >= bins:
        return arc
    before: list[int] = []
    after: list[int] = []
    k = (arc[0] - 1) % bins
    while above[k] and not taken[k] and len(arc) + len(before) < bins:
        before.append(k)
        k = (k - 1) % bins
    k = (arc[-1] + 1) % bins
    while (
        above[k] and not taken[k] and k not in before and len(arc) + len(before) + len(after) < bins
    ):
        after.append(k)
        k = (k + 1) % bins
    return np.concatenate(
        (np.array(before[::-1], dtype=np.int64), arc, np.array(after, dtype=np.int64))
    )


def _smooth3(values: np.ndarray) -> np.ndarray:
    """Circular running median of three bins: one noisy bin cannot make or break an arc."""
    stacked = np.stack((np.roll(values, 1), values, np.roll(values, -1)))
    return np.median(stacked, axis=0)


def _ordered(idx: np.ndarray, bins: int) -> np.ndarray:
    """Bin indices of one circular run, in order from its first bin (it may wrap past 0)."""
    idx = np.sort(idx)
    if len(idx) and len(idx) < bins:
        jumps = np.flatnonzero(np.diff(idx) > 1)
        if len(jumps):
            idx = np.roll(idx, -(jumps[0] + 1))
    return idx


def _ring_feature(
    wall: _Wall,
    wall_r: np.ndarray,
    radii: np.ndarray,
    nominal_r: float,
    nominal_area: float,
    bins: int,
    p: CodingParams,
) -> WallFeature | None:
    """The wall displaced all round: even its longest radius well inside the nominal (a
    deformation brings one diameter in, not both)."""
    shrink = 1.0 - float(wall_r.max()) / nominal_r
    if shrink <= p.ring_ratio:
        return None
    area = float(nominal_area - np.sum(0.5 * radii * radii) * _TWO_PI / bins)
    return WallFeature(
        UNCLASSIFIED,
        None,
        None,
        lost_area_m2=max(area, 0.0),
        height_m=nominal_r - float(wall.coef[0]),
        rule=(
            f"the wall lies {100 * shrink:.1f} % inside the nominal radius all round: attached "
            "deposits all round, or a wrong nominal diameter"
        ),
    )


def _deformation_feature(
    wall: _Wall, wall_r: np.ndarray, nominal_r: float, bins: int, p: CodingParams
) -> WallFeature | None:
    """BAA when the fitted wall is a significant ellipse with vertical and horizontal axes and
    its perimeter kept (see the module)."""
    if wall.harmonics < 2:
        return None
    c0, _, _, c2, s2 = (float(v) for v in wall.coef)
    amplitude = math.hypot(c2, s2)
    # The standard error of one harmonic's amplitude from n inlier bins of scatter σ.
    sigma = wall.noise_m * math.sqrt(2.0 / max(int(wall.inliers.sum()), 1))
    reduction = (2.0 * nominal_r - 2.0 * (c0 - amplitude)) / (2.0 * nominal_r)
    if amplitude < 5.0 * sigma or reduction < p.min_deformation_ratio:
        return None
    if 2.0 * amplitude / (2.0 * nominal_r) < p.min_deformation_ratio:
        return None  # a round pipe a little smaller than nominal is not deformed
    major_deg = math.degrees(0.5 * math.atan2(s2, c2)) % 180.0  # direction of the long axis
    a, b = c0 + amplitude, c0 - amplitude
    h = ((a - b) / (a + b)) ** 2
    perimeter = math.pi * (a + b) * (1 + 3 * h / (10 + math.sqrt(4 - 3 * h)))
    kept = abs(perimeter / (2 * math.pi * nominal_r) - 1.0)
    tol = p.deformation_axis_tol_deg

    def unclassified(rule: str) -> WallFeature:
        return WallFeature(
            UNCLASSIFIED, None, None, 0.0, 2.0 * amplitude, measure="deformation_ratio", rule=rule
        )

    if min(major_deg, 180.0 - major_deg) <= tol:
        characterisation, words = "A", "vertical"  # long axis across: squeezed from above
    elif abs(major_deg - 90.0) <= tol:
        characterisation, words = "B", "horizontal"
    else:
        return unclassified(
            f"the wall is elliptical with its long axis at {major_deg:.0f}°: not vertical "
            "or horizontal"
        )
    if kept > p.perimeter_tol_ratio:
        return unclassified(
            f"the wall is elliptical but its perimeter is {100 * kept:.0f} % off the nominal"
        )
    return WallFeature(
        BAA,
        None,
        None,
        0.0,
        2.0 * nominal_r - 2.0 * b,
        measure="deformation_ratio",
        rule=(
            f"the wall smoothly elliptical, {words}: diameters {2000 * b:.0f} to {2000 * a:.0f} mm,"
            f" perimeter within {100 * kept:.1f} % of the nominal"
        ),
        characterisation=characterisation,
    )


def code_sections(
    sections: Sequence[SectionMeasures], params: CodingParams = CodingParams()
) -> list[SectionCoding | None]:
    """:func:`code_section` for every measured section that has a contour; None for the rest
    (a section that is not ``ok`` is never coded, and one without a contour cannot be).

    A section with water in its invert whose figures are lower bounds
    (:attr:`~pipescan.core.model.SectionMeasures.is_lower_bound`) is coded too, keeping only
    the features graded on their blockage (:func:`lower_bound_coding`)."""
    return [
        code_contour(s, params)
        if s.is_ok
        else lower_bound_coding(code_contour(s, params))
        if s.is_lower_bound
        else None
        for s in sections
    ]


def lower_bound_coding(coding: SectionCoding | None) -> SectionCoding | None:
    """What a section with water in its invert can tell of its features: those graded on
    their blockage (an obstacle, an attached deposit, an unclassified blockage), each at
    least as large as its figure, since the contour runs along the nominal wall under the
    water. A settled deposit's height and a deformation are read at the invert or across the
    whole ring, where the water hides the wall: they are left out. None when none is left."""
    if coding is None:
        return None
    kept = tuple(f for f in coding.features if f.measure == "blockage_ratio")
    return dataclasses.replace(coding, features=kept) if kept else None


def code_contour(
    section: SectionMeasures, params: CodingParams = CodingParams()
) -> SectionCoding | None:
    """:func:`code_section` of a section's contour at its nominal diameter, whatever its
    status; None when it has no contour or no nominal size."""
    if section.contour_m is None or not section.nominal_area_m2 > 0:
        return None
    return code_section(section.contour_m, section.nominal_diameter_m, params)


# --- along the chainage -----------------------------------------------------------------------


@dataclass(frozen=True)
class FeatureRun:
    """One physical feature along the chainage: the sections that show it, in order.

    ``sections`` index the sequence given to :func:`feature_runs`; ``features`` holds the
    feature each of them shows (the same length). ``absorbed`` lists the sections among them
    whose feature was unclassified and joined this run as its ramp or its shadowed rear.
    """

    code: str
    sections: tuple[int, ...]
    features: tuple[WallFeature, ...]
    absorbed: tuple[int, ...] = ()

    def arc(self, bins: int = 360) -> tuple[float | None, float | None]:
        """The union of the run's arcs: ``(from, to)`` section-plane angles in radians, or
        ``(None, None)`` when its features have no arc (a deformation)."""
        mask = np.zeros(bins, dtype=bool)
        for f in self.features:
            if f.arc_from_rad is None or f.arc_to_rad is None:
                continue
            first = round(f.arc_from_rad * bins / _TWO_PI) % bins
            n = max(1, round(f.arc_rad * bins / _TWO_PI))
            mask[(first + np.arange(n)) % bins] = True
        if not mask.any():
            return None, None
        if mask.all():
            return 0.0, 0.0
        longest = max(_circular_runs(mask), key=len)
        return _arc_ends(longest, bins)


def arcs_meet(f: WallFeature, g: WallFeature, slack_rad: float) -> bool:
    """Whether two features' arcs overlap (within ``slack_rad``); features without an arc
    (deformations) meet each other."""
    if f.arc_from_rad is None or g.arc_from_rad is None:
        return f.arc_from_rad is None and g.arc_from_rad is None

    # Two circular arcs overlap when either one's start lies on the other (slack added).
    def on(angle: float, arc: WallFeature) -> bool:
        assert arc.arc_from_rad is not None
        return (angle - arc.arc_from_rad + slack_rad) % _TWO_PI <= arc.arc_rad + 2 * slack_rad

    assert f.arc_from_rad is not None and g.arc_from_rad is not None
    return on(f.arc_from_rad, g) or on(g.arc_from_rad, f)


def feature_runs(
    sections: Sequence[_Interval],
    codings: Sequence[SectionCoding | None],
    *,
    bridge_m: float = 0.2,
    absorb_m: float = 0.5,
    slack_deg: float = 5.0,
) -> list[FeatureRun]:
    """Follow each section's features along the chainage into one run per physical feature.

    (Over 80 lines for its rules' docstring: the body is one pass along the chainage.)

    Rules (docs/coding.md):

    - A feature continues a run when the run's last section touches this one
      (:func:`pipescan.core.summary.touches`), both show the same code, and their arcs overlap
      (within ``slack_deg``). A section that shows another code, or nothing, ends the run:
      the feature changes there.
    - A run also continues across unmeasured sections (``codings`` None), over at most
      ``bridge_m`` of chainage, when the feature on the far side is the same: a section lost to
      a shadow does not cut one feature in two.
    - An unclassified run of at most ``absorb_m`` that touches a coded run at an overlapping
      arc joins it: a deposit's ramp, or an obstacle's shadowed rear, belongs to its feature.
    - A one-section run graded on the blockage that touches a run of another code, lies
      within the arc of the run's section beside it and takes less area there joins it: the
      section holds only the run's end, read diluted (:func:`_absorb_diluted_ends`).

    Parameters
    ----------
    sections
        In chainage order (anything with ``chainage_start_m`` and ``chainage_end_m``).
    codings
        One per section: its :class:`SectionCoding`, or None when it was not measured.

    Returns
    -------
    list of FeatureRun
        In order of their first section.
    """
    if len(sections) != len(codings):
        raise ValueError(f"{len(codings)} codings for {len(sections)} sections")
    slack = math.radians(slack_deg)
    runs: list[dict[str, Any]] = []

    def continues(run: dict[str, Any], i: int, f: WallFeature) -> bool:
        last = run["sections"][-1]
        if run["code"] != f.code or last >= i:
            return False
        return bridges(last, i) and arcs_meet(run["features"][-1], f, slack)

    def bridges(last: int, i: int) -> bool:
        """Section ``i`` follows ``last`` directly, or across at most ``bridge_m`` of
        unmeasured sections (a measured one without the feature ends it; so does a gap in
        chainage)."""
        gap_ok = touches(
            sections[last].chainage_end_m, sections[i].chainage_start_m, gap_m=bridge_m
        )
        if not gap_ok or any(codings[k] is not None for k in range(last + 1, i)):
            return False
        return all(
            touches(sections[k].chainage_end_m, sections[k + 1].chainage_start_m)
            for k in range(last, i)
        )

    for i, coding in enumerate(codings):
        if coding is None:
            continue
        taken: set[int] = set()
        for f in coding.features:
            options = [k for k, run in enumerate(runs) if k not in taken and continues(run, i, f)]
            if options:
                k = max(options, key=lambda k: runs[k]["sections"][-1])
                runs[k]["sections"].append(i)
                runs[k]["features"].append(f)
                taken.add(k)
            else:
                runs.append({"code": f.code, "sections": [i], "features": [f], "absorbed": []})
                taken.add(len(runs) - 1)

    _absorb_unclassified(runs, sections, absorb_m, bridges, slack)
    _absorb_diluted_ends(runs, bridges, slack)
    out = [
        FeatureRun(r["code"], tuple(r["sections"]), tuple(r["features"]), tuple(r["absorbed"]))
        for r in runs
        if r["sections"]
    ]
    return sorted(out, key=lambda r: (r.sections[0], r.code))


def _absorb_unclassified(
    runs: list[dict[str, Any]],
    sections: Sequence[_Interval],
    absorb_m: float,
    bridges: Any,
    slack: float,
) -> None:
    """Join short unclassified runs to the coded run they touch at an overlapping arc."""
    for u in runs:
        if u["code"] != UNCLASSIFIED or not u["sections"]:
            continue
        first, last = u["sections"][0], u["sections"][-1]
        if sections[last].chainage_end_m - sections[first].chainage_start_m > absorb_m + 1e-9:
            continue
        best, best_overlap = None, -1
        for r in runs:
            if r is u or r["code"] == UNCLASSIFIED or not r["sections"]:
                continue
            ends = []
            if r["sections"][-1] < first and bridges(r["sections"][-1], first):
                ends.append((r["features"][-1], u["features"][0]))
            if last < r["sections"][0] and bridges(last, r["sections"][0]):
                ends.append((r["features"][0], u["features"][-1]))
            meeting = [a for a, b in ends if arcs_meet(a, b, slack) or a.arc_from_rad is None]
            if meeting and len(r["sections"]) > best_overlap:
                best, best_overlap = r, len(r["sections"])
        if best is not None:
            _join(best, u)


def _join(run: dict[str, Any], part: dict[str, Any]) -> None:
    """Move ``part``'s sections and features into ``run``, in section order, as absorbed."""
    merged = sorted(
        zip(run["sections"] + part["sections"], run["features"] + part["features"], strict=True),
        key=lambda pair: pair[0],
    )
    run["sections"] = [k for k, _ in merged]
    run["features"] = [f for _, f in merged]
    run["absorbed"] = sorted(run["absorbed"] + part["sections"])
    part["sections"], part["features"] = [], []


def _arc_within(f: WallFeature, g: WallFeature, slack_rad: float) -> bool:
    """Whether ``f``'s arc lies within ``g``'s, widened by ``slack_rad`` at both ends."""
    if f.arc_from_rad is None or g.arc_from_rad is None:
        return False
    start = (f.arc_from_rad - g.arc_from_rad + slack_rad) % _TWO_PI
    return start + f.arc_rad <= g.arc_rad + 2 * slack_rad


def _absorb_diluted_ends(runs: list[dict[str, Any]], bridges: Any, slack: float) -> None:
    """Join a one-section run to the run whose end it holds, read diluted.

    A section's radius in each bin is the median of its sub-slices along the axis
    (``contour.polar.polar_profile``). Where a feature ends a few centimetres into a section,
    only one or two sub-slices see it, and the section reads a layer between the wall and the
    feature's face: thinner than the feature, and of a shape (a thin layer following the wall)
    that says nothing of its family. So a one-section run whose feature is graded on the
    blockage (the thin layer reads as attached deposits or a body), lies within the arc of
    the feature in the touching section of another run (``slack`` at both ends), and takes
    less area than that feature, is that run's end: an obstacle's, or a deposit's (whose
    figure, its height, the joined section does not compete for: ``grading.merge_defects``).
    A feature of its own beside another keeps its run: its arc differs (a band beside an
    obstacle), or it takes more area than the section next to it.
    """
    for u in runs:
        if len(u["sections"]) != 1 or u["code"] == UNCLASSIFIED:
            continue
        (i,), (f,) = u["sections"], u["features"]
        if f.measure != "blockage_ratio":
            continue
        best = None
        for r in runs:
            if r is u or r["code"] in (u["code"], UNCLASSIFIED) or not r["sections"]:
                continue
            if r["sections"][-1] < i and bridges(r["sections"][-1], i):
                beside = r["features"][-1]
            elif i < r["sections"][0] and bridges(i, r["sections"][0]):
                beside = r["features"][0]
            else:
                continue
            if not (_arc_within(f, beside, slack) and f.lost_area_m2 < beside.lost_area_m2):
                continue
            if best is None or len(r["sections"]) > len(best["sections"]):
                best = r
        if best is not None:
            _join(best, u)
