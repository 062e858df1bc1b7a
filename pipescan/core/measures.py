"""Measures of one cross-section, with its coverage and an honest status.

DESIGN.md fixes the measures and their names. Ratios are fractions; percentages exist only in
reports.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from scipy.ndimage import median_filter

from pipescan.core.contour import (
    GridParams,
    PolarProfile,
    grid_contour,
    polar_profile,
    polygon_area,
    radii_of_polygon,
    remove_stray_points,
)
from pipescan.core.errors import GeometryError
from pipescan.core.model import SectionMeasures, SectionStatus

_BIN_CHOICES = (360, 180, 120, 90, 72)
# Fill lower than this is within the noise of a clean invert.
_DEPOSIT_FLOOR_M = 0.01


@dataclass(frozen=True)
class MeasureParams:
    """How sections are measured and when their figures are trusted.

    Attributes
    ----------
    method : {"polar", "grid"}
        Contour method (see ``pipescan.core.contour``).
    min_points : int
        Fewer points (after stray-point removal) gives ``too_few_points``.
    min_coverage_ratio : float
        Less of the perimeter seen, by angle, gives ``low_coverage``.
    max_gap_deg : float
        A single unseen arc longer than this also gives ``low_coverage``: interpolating across
        it would be a guess.
    wall_tolerance_ratio : float
        Contour radii within this share of the nominal radius count as wall when measuring
        ovality and deformation; anything further in is a deposit or an obstacle.
    stray_radius_m, stray_min_neighbours
        Stray-point removal (see ``remove_stray_points``).
    max_points : int
        A denser section is thinned to this many points, evenly spaced: the
        per-angle medians do not need more, and the cost stays bounded.
    grid : GridParams
        Parameters of the paper's grid method.
    max_wall_spread_m : float
        A section whose wall points spread around its contour by more than this (robust 1σ,
        pooled over the wall's angle bins) is ``smeared_wall``: the frames that saw it
        disagree. A forward-looking sensor sees the wall at grazing incidence, where range
        noise moves a point along the wall more than across it: with the true poses, the
        spread reads 1-3 mm under the simulator's default noise and at most 6.6 mm at the
        harsh end (20 mm range noise); frames that disagree by 10 mm (lateral) or 0.5°
        (tilt) read 8-20 mm, with errors of 1-10 pp (``docs/registration.md``).
    """

    method: Literal["polar", "grid"] = "polar"
    min_points: int = 200
    min_coverage_ratio: float = 0.9
    max_gap_deg: float = 20.0
    wall_tolerance_ratio: float = 0.12
    stray_radius_m: float = 0.02
    stray_min_neighbours: int = 3
    max_points: int = 40_000
    grid: GridParams = field(default_factory=GridParams)
    max_wall_spread_m: float = 0.008


def choose_bins(point_count: int, *, points_per_bin: int = 16) -> int:
    """Angular bins for a section: as fine as 1° when the points allow, never coarser than 5°."""
    for bins in _BIN_CHOICES:
        if point_count >= points_per_bin * bins:
            return bins
    return _BIN_CHOICES[-1]


def _wall_bins(
    radii_m: np.ndarray, seen: np.ndarray, nominal_diameter_m: float, wall_tolerance_ratio: float
) -> np.ndarray:
    """Seen bins whose contour lies at the wall: within ``wall_tolerance_ratio`` of the nominal
    radius. Anything further in is a deposit or an obstacle."""
    return seen & (radii_m >= nominal_diameter_m / 2.0 * (1.0 - wall_tolerance_ratio))


def _diameter_measures(
    radii_m: np.ndarray, seen: np.ndarray, nominal_diameter_m: float, wall_tolerance_ratio: float
) -> tuple[float | None, float | None]:
    """Ovality (ASTM F1216) and deformation (EN 13508-2 BAA) from wall diameters only."""
    bins = len(radii_m)
    half = bins // 2
    wall = _wall_bins(radii_m, seen, nominal_diameter_m, wall_tolerance_ratio)
    pair = wall[:half] & wall[half:]
    if pair.sum() < max(3, half // 6):
        return None, None
    d = radii_m[:half][pair] + radii_m[half:][pair]
    d_mean = float(d.mean())
    ovality = max((float(d.max()) - d_mean) / d_mean, (d_mean - float(d.min())) / d_mean)
    deformation = max(0.0, (nominal_diameter_m - float(d.min())) / nominal_diameter_m)
    return ovality, deformation


def _deposit_height_ratio(
    profile_radii_m: np.ndarray,
    seen: np.ndarray,
    angles_rad: np.ndarray,
    nominal_diameter_m: float,
    wall_tolerance_ratio: float,
) -> float | None:
    """Height of settled material above the invert, as a share of the pipe height.

    The invert is placed at the median wall radius below the centre; the fill's top is the
    median radius within ±5° of straight down.
    """
    wall = _wall_bins(profile_radii_m, seen, nominal_diameter_m, wall_tolerance_ratio)
    down = np.abs(np.angle(np.exp(1j * (angles_rad - 1.5 * np.pi)))) <= np.radians(5.0)
    bottom = down & seen
    if not bottom.any() or wall.sum() < 3:
        return None
    r_wall = float(np.median(profile_radii_m[wall]))
    r_bottom = float(np.median(profile_radii_m[bottom]))
    return max(0.0, (r_wall - r_bottom) / nominal_diameter_m)


def wall_spread_m(points_2d: np.ndarray, profile: PolarProfile, wall: np.ndarray) -> float | None:
    """Robust spread (1.4826 × MAD, metres) of the points of the wall's bins around their
    bin's radius: the sensor's noise where the frames agree, more where they do not. None
    without wall bins."""
    bins = len(profile.radii_m)
    rel = np.asarray(points_2d, dtype=np.float64)[:, :2]
    ang = np.mod(np.arctan2(rel[:, 1], rel[:, 0]), 2.0 * np.pi)
    b = np.minimum((ang * bins / (2.0 * np.pi)).astype(np.int64), bins - 1)
    on_wall = wall[b]
    if on_wall.sum() < 10:
        return None
    residual = np.hypot(rel[on_wall, 0], rel[on_wall, 1]) - profile.radii_m[b[on_wall]]
    return float(1.4826 * np.median(np.abs(residual - np.median(residual))))


def measure_section(
    points_2d: np.ndarray,
    *,
    chainage_start_m: float,
    chainage_end_m: float,
    nominal_diameter_m: float,
    params: MeasureParams = MeasureParams(),
    point_count: int | None = None,
    chainage_uncertainty_m: float | None = None,
    registration_weak: bool = False,
) -> SectionMeasures:
    """Measure one section from its projected points.

    Parameters
    ----------
    points_2d : (N, 2) or (N, 3) float
        The section's points projected onto the plane perpendicular to the axis, metres, the
        axis at the origin, column 0 across and column 1 up; column 2, when given, is the
        distance along the axis from the section's start (see ``polar_profile``).
    chainage_start_m, chainage_end_m : float
        The section's interval.
    nominal_diameter_m : float
        Design inner diameter.
    params : MeasureParams
    point_count : int, optional
        Points in the section before the caller thinned them (default: as given).
    chainage_uncertainty_m : float, optional
        How far the section's true place may be from its chainage (registration's).
    registration_weak : bool
        Most frames that saw the section slid along the axis, or one was extrapolated
        (``RegistrationEvidence``): the status is then ``weak_registration``.

    Returns
    -------
    SectionMeasures
        ``status`` is ``ok`` only when enough of the perimeter was seen with enough points,
        by frames that were registered and agree (the wall is not smeared). The first
        reason that applies is given: coverage and points, then registration, then smear.
        Figures that could be computed are kept for diagnostics even when the status is not
        ok; figures that could not are None.

    Examples
    --------
    >>> theta = np.linspace(0, 2 * np.pi, 2000, endpoint=False)
    >>> ring = 0.25 * np.column_stack((np.cos(theta), np.sin(theta)))
    >>> m = measure_section(ring, chainage_start_m=0.0, chainage_end_m=0.1,
    ...                     nominal_diameter_m=0.5)
    >>> m.status.value, round(m.blockage_ratio, 3)
    ('ok', 0.0)
    """
    nominal_area = math.pi * nominal_diameter_m**2 / 4.0
    raw = np.asarray(points_2d, dtype=np.float64)
    base: dict[str, Any] = dict(
        chainage_start_m=float(chainage_start_m),
        chainage_end_m=float(chainage_end_m),
        nominal_area_m2=nominal_area,
        point_count=len(raw) if point_count is None else point_count,
        chainage_uncertainty_m=chainage_uncertainty_m,
    )
    if len(raw) == 0:
        return SectionMeasures(status=SectionStatus.OUTSIDE_SCAN, coverage_ratio=0.0, **base)
    # Points arrive frame after frame, so evenly spaced picks thin every frame alike. (Not a
    # whole-number stride: a section just over the limit would lose half its points.)
    raw_used = raw
    if len(raw) > params.max_points:
        raw_used = raw[np.linspace(0, len(raw) - 1, params.max_points).astype(np.int64)]
    pts = remove_stray_points(
        raw_used, radius_m=params.stray_radius_m, min_neighbours=params.stray_min_neighbours
    )
    profile: PolarProfile = polar_profile(
        pts, bins=choose_bins(len(pts)), section_length_m=chainage_end_m - chainage_start_m
    )
    coverage = profile.coverage_ratio
    if len(pts) < params.min_points:
        return SectionMeasures(status=SectionStatus.TOO_FEW_POINTS, coverage_ratio=coverage, **base)
    if not profile.seen.any():
        return SectionMeasures(status=SectionStatus.LOW_COVERAGE, coverage_ratio=0.0, **base)

    status = SectionStatus.OK
    if coverage < params.min_coverage_ratio or profile.max_gap_deg > params.max_gap_deg:
        status = SectionStatus.LOW_COVERAGE
    elif registration_weak:
        status = SectionStatus.WEAK_REGISTRATION

    if params.method == "grid":
        try:
            polygon = grid_contour(pts[:, :2], params.grid).polygon
        except GeometryError:
            # Too little of the perimeter seen is the first reason, where it applies.
            if status == SectionStatus.OK:
                status = SectionStatus.NO_CONTOUR
            return SectionMeasures(status=status, coverage_ratio=coverage, **base)
        radii = radii_of_polygon(polygon, profile.angles_rad)
        open_area = polygon_area(polygon)
    else:
        polygon = profile.polygon()
        radii = profile.filled_radii()
        open_area = profile.area_m2()

    # A 5-bin running median keeps single noisy bins from setting D_min or D_max.
    radii_smooth = median_filter(radii, size=5, mode="wrap")
    deposit = _deposit_height_ratio(
        radii_smooth,
        profile.seen,
        profile.angles_rad,
        nominal_diameter_m,
        params.wall_tolerance_ratio,
    )
    # The deposit's flat top meets the wall at a shallow angle, so bins just above the wall
    # tolerance can still be fill: leave everything at or below the fill's top out of the
    # wall's diameters.
    wall_seen = profile.seen.copy()
    if deposit is not None and deposit * nominal_diameter_m > _DEPOSIT_FLOOR_M:
        y_top = -nominal_diameter_m / 2.0 + deposit * nominal_diameter_m
        y = radii_smooth * np.sin(profile.angles_rad)
        wall_seen &= y > y_top + _DEPOSIT_FLOOR_M
    ovality, deformation = _diameter_measures(
        radii_smooth, wall_seen, nominal_diameter_m, params.wall_tolerance_ratio
    )
    spread = wall_spread_m(
        pts,
        profile,
        _wall_bins(profile.radii_m, wall_seen, nominal_diameter_m, params.wall_tolerance_ratio),
    )
    if status == SectionStatus.OK and spread is not None and spread > params.max_wall_spread_m:
        status = SectionStatus.SMEARED_WALL
    return SectionMeasures(
        status=status,
        wall_spread_m=spread,
        coverage_ratio=coverage,
        open_area_m2=open_area,
        blockage_ratio=1.0 - open_area / nominal_area,
        ovality_ratio=ovality,
        deformation_ratio=deformation,
        deposit_height_ratio=deposit,
        contour_m=polygon,
        **base,
    )
