"""Water standing in the invert of a section: a flat chord and missing wall below it.

A LiDAR gets no return from under water and few from its surface, so water leaves the invert
unseen, from one side's wall to the other's at the same height, with at most a sparse line of
points along that chord. A deposit is the opposite: its flat top is seen as densely as the
wall. :func:`detect_water` tells them apart; docs/measures.md says how the figures use it.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from pipescan.core.axis import PipeAxis
from pipescan.core.contour.base import angle_from_invert_rad, polar_coordinates
from pipescan.core.model import SectionMeasures, SectionStatus
from pipescan.core.summary import adjacent_runs
from pipescan.core.uncertainty import MAD_TO_SIGMA, MEDIAN_EFFICIENCY, Z95, unseen_runs

MIN_SURFACE_POINTS = 3
"""Points on the chord that make it a seen water surface."""

SPARSE_BIN_SHARE = 0.1
"""A bin holding under this share of the section's median bin count holds only a sparse line
of returns, even where the sub-slice vote saw it (a water surface returns a share of the rays
that reach it, fewer the more grazing); a surface seen as densely as the wall is a deposit's
top, and counts as one."""


@dataclass(frozen=True)
class WaterLevel:
    """Water found in a section.

    Attributes
    ----------
    level_m : float
        Height of the surface above the axis (negative: below it), section-plane metres.
    depth_ratio : float
        Depth above the invert over the nominal diameter. The invert is the bottom of the
        section's own wall circle (:func:`_wall_circle`), not the axis less the radius.
    bins : (K,) int
        The angle bins under water (unseen wall, or a sparse chord), to be left out of the
        contour.
    from_surface : bool
        The level was read from points on the surface (else from where the wall stops: water
        only once the sections along the pipe agree, :func:`confirm_surfaceless_water`).
    """

    level_m: float
    depth_ratio: float
    bins: np.ndarray
    from_surface: bool
    uncertainty_ratio: float | None = None
    """The depth's 95 % uncertainty (half-width) over the nominal diameter: where the level
    was read from where the wall stops, :func:`_edge_uncertainty_m`; from the surface, its
    median's noise and how far it lies from where the wall stops."""


def detect_water(
    points: np.ndarray,
    angles_rad: np.ndarray,
    seen: np.ndarray,
    counts: np.ndarray,
    radii_m: np.ndarray,
    wall_radius_m: float,
    nominal_diameter_m: float,
    sigma_m: float,
    *,
    min_coverage_ratio: float = 0.9,
    max_gap_deg: float = 20.0,
    surface_points: np.ndarray | None = None,
) -> WaterLevel | None:
    """Find water in a section's invert.

    The candidate is the run of bins around straight down that hold no points or only a
    sparse line of them (:data:`SPARSE_BIN_SHARE` of the seen bins' median count). It is
    water when the wall on both sides of it stops at the same height (within
    ``max(3 σ, 2 cm)`` plus one bin's rise), below the axis, and at least
    :data:`MIN_SURFACE_POINTS` points lie on the chord at that height (within the same
    tolerance): the level is their median height.

    Parameters
    ----------
    points : (N, 2+) float
        The section's points, section plane (0 across, 1 up), axis at the origin.
    angles_rad, seen, counts, radii_m : (B,) arrays
        The section profile's bins (centres, seen, points per bin, radius or NaN).
    wall_radius_m : float
        The wall's radius (median of the seen bins at the wall).
    nominal_diameter_m : float
    sigma_m : float
        The section's residual spread (1σ).
    min_coverage_ratio, max_gap_deg : float
        The rest of the wall must be seen as a measured section's is: at least this share,
        with no other unseen arc longer than this.
    surface_points : (M, 2+) float, optional
        Where to look for the surface's returns: the section's points before stray-point
        removal (default ``points``).

    Returns
    -------
    WaterLevel or None
        None when the invert is seen (dry), or the gap there is not level water.
    """
    typical = float(np.median(counts[seen])) if seen.any() else 0.0
    run = _invert_gap(angles_rad, seen, counts, radii_m, wall_radius_m, typical, max_gap_deg)
    if run is None:
        return None
    xy = np.asarray(points, dtype=np.float64)[:, :2]
    # Rule: the depth is counted from the bottom of the section's own wall circle, not from
    # the axis less the radius. Why: the registered cloud's wall may lie off the fitted axis
    # by more than a centimetre where the frames were seen from afar (docs/measures.md).
    centre_m, radius_m, oval_m = _wall_circle(angles_rad, radii_m, seen, run)
    # Rule: under an oval wall the hidden invert is taken halfway between the circle's bottom
    # and the oval's (higher by its amplitude where the crown is flattened), and the depth's
    # ± holds both. Why: a flexible pipe deflects as an ellipse, its invert rising as its
    # crown falls, but a dented crown leaves the invert round; the water hides which.
    invert_m = centre_m[1] - radius_m + 0.5 * oval_m
    hidden_m = 0.5 * abs(oval_m)
    sides = _wall_edges(xy, run, len(angles_rad), centre_m, radius_m, sigma_m)
    if sides is None:
        return None  # no wall on a side
    # Whether this is water is told from the edge bins' medians, as it was tuned; the depth
    # from where the wall stops below them.
    medians = [e.level_m + e.rise_m for e in sides]
    tolerance = max(3.0 * sigma_m, 0.02) + wall_radius_m * math.sin(2.0 * math.pi / len(seen))
    if abs(medians[0] - medians[1]) > tolerance or max(medians) >= 0.0:
        return None  # the sides at different heights, or above the axis
    raw = xy if surface_points is None else np.asarray(surface_points, dtype=np.float64)[:, :2]
    window = 0.5 * (medians[0] + medians[1])
    surface_y = _surface_returns(raw, run, len(seen), window, tolerance, wall_radius_m, sigma_m)
    if len(surface_y) > typical / 3.0 * len(run):
        # As dense as a wall: a deposit's top seen along part of the section (its shadow).
        return None
    edge_level = 0.5 * (sides[0].level_m + sides[1].level_m)
    if len(surface_y) < MIN_SURFACE_POINTS:
        # No surface seen: water whose surface returns nothing, or a view that stops short of
        # the invert. One section cannot tell; the sections along the pipe can
        # (:func:`confirm_surfaceless_water`).
        depth = (edge_level - invert_m) / nominal_diameter_m
        if depth <= 0:
            return None
        u = (_edge_uncertainty_m(sides, sigma_m) + hidden_m) / nominal_diameter_m
        return WaterLevel(edge_level, depth, run, from_surface=False, uncertainty_ratio=u)
    # Then only the points close to their median: stray returns in the window do not count.
    level = float(np.median(surface_y))
    surface_y = surface_y[np.abs(surface_y - level) <= max(3.0 * sigma_m, 0.02)]
    if len(surface_y) < MIN_SURFACE_POINTS:
        return None
    level = float(np.median(surface_y))
    depth = (level - invert_m) / nominal_diameter_m
    if depth <= 0:
        return None
    # The surface and the wall's edge are two readings of one level: either may be the one
    # off (a few stray returns taken for a surface read up to 1.8 pp deep on ``hap 8``).
    spread = MAD_TO_SIGMA * float(np.median(np.abs(surface_y - level)))
    noise = Z95 * MEDIAN_EFFICIENCY * spread / math.sqrt(len(surface_y))
    u = (noise + abs(level - edge_level) + hidden_m) / nominal_diameter_m
    return WaterLevel(level, depth, run, from_surface=True, uncertainty_ratio=u)


def _invert_gap(
    angles_rad: np.ndarray,
    seen: np.ndarray,
    counts: np.ndarray,
    radii_m: np.ndarray,
    wall_radius_m: float,
    typical: float,
    max_gap_deg: float,
) -> np.ndarray | None:
    """The run of bins at the invert that water could hide (its bin indices, in order), or
    None when the invert is seen, the run is too narrow or too wide, or the wall elsewhere is
    not seen as a measured section's is. ``typical``: the seen bins' median count."""
    bins = len(angles_rad)
    down = int(np.argmin(angle_from_invert_rad(angles_rad)))
    # Water leaves the invert unseen, or holding only a sparse line of points: very few, or
    # few and well inside the wall (not a flattened invert, which a dense scan sees sparsely).
    inside = np.nan_to_num(radii_m, nan=wall_radius_m) < wall_radius_m * (1.0 - 0.12)
    candidate = ~seen | (counts < SPARSE_BIN_SHARE * typical) | ((counts < typical / 3.0) & inside)
    if not candidate[down] or candidate.all():
        return None
    run = next(r for r in unseen_runs(~candidate) if down in set(r.tolist()))
    # Narrower than the longest gap a measured section may bridge, it is not worth calling
    # water (under 1 % of the diameter deep); wider than half the section, it is no level.
    if len(run) * 360.0 / bins <= max_gap_deg or len(run) > bins // 2:
        return None
    # Only the invert is missing: the rest of the wall is seen as a measured section's is (a
    # forward-looking sensor's first metre misses the crown too, and is no water).
    rest = np.ones(bins, dtype=bool)
    rest[run] = False
    other_gaps = [len(r) for r in unseen_runs(seen | ~rest)]
    if other_gaps and max(other_gaps) * 360.0 / bins > max(max_gap_deg, 2 * 360.0 / bins):
        return None
    return run


@dataclass(frozen=True)
class _Edge:
    """Where the wall stops on one side of the water (:func:`_wall_edges`)."""

    level_m: float
    """Its height, section-plane metres."""
    noise_m: float
    """The standard error of the median height it was read from."""
    rise_m: float
    """How far below that median it was placed: the wall's rise over half the points' span."""


def _wall_edges(
    xy: np.ndarray,
    run: np.ndarray,
    bins: int,
    centre_m: tuple[float, float],
    wall_radius_m: float,
    sigma_m: float,
) -> list[_Edge] | None:
    """Where the wall stops on each side of ``run``, from its points at the wall in the
    nearest bin (or the next one when that holds nothing); None when a side has none.

    The median height of those points, not the lowest: the lowest takes the extreme of the
    noise and of the frames' pose errors, and read surfaceless water 1.3 pp shallow
    (docs/measures.md). Less the wall's rise over half their span: they run from where the
    wall stops to the bin's far side, so their median lies halfway up, and read the water
    deeper by half a bin (0.2 pp at 1°, 1.3 pp at 6°: docs/measures.md).
    """
    dtheta = 2.0 * math.pi / bins
    ang, _ = polar_coordinates(xy)
    b_idx = np.minimum((ang / dtheta).astype(np.int64), bins - 1)
    # At the wall: around its own circle, not the axis (off it, the axis would cut the
    # scatter on one side and lift the median height: 3 mm with the wall 12 mm low).
    rad = np.hypot(xy[:, 0] - centre_m[0], xy[:, 1] - centre_m[1])
    at_wall = np.abs(rad - wall_radius_m) <= max(3.0 * sigma_m, 0.01)
    edges = []
    for b, away in (((run[0] - 1) % bins, -1), ((run[-1] + 1) % bins, 1)):
        near = at_wall & (b_idx == b)
        if not near.any():
            b = (b + away) % bins
            near = at_wall & (b_idx == b)
        if not near.any():
            return None
        far_rad = (b + (away > 0)) * dtheta  # the bin's side away from the water
        middle_rad = float(np.median(ang[near]))
        span = abs(math.remainder(far_rad - middle_rad, 2.0 * math.pi))
        heights = xy[near, 1]
        median = float(np.median(heights))
        spread = MAD_TO_SIGMA * float(np.median(np.abs(heights - median)))
        rise = wall_radius_m * abs(math.cos(middle_rad)) * span
        noise = MEDIAN_EFFICIENCY * spread / math.sqrt(len(heights))
        edges.append(_Edge(level_m=median - rise, noise_m=noise, rise_m=rise))
    return edges


def _edge_uncertainty_m(sides: list[_Edge], sigma_m: float) -> float:
    """The 95 % uncertainty of the level read where the wall stops, metres. Its parts,
    added (all but the first are bounds, as the blockage's are: ``core.uncertainty``):

    - the noise of the two sides' medians (1.96 standard errors of their mean);
    - half their difference: either side may be the one off;
    - half the rise taken off them: the points need not spread evenly over the bin;
    - the wall's scatter ``sigma_m`` (1σ): frames placed at slightly different heights
      each stop at their own level, and the first bin dense enough to count as seen lies
      among the lowest of them (on ``hap 12``, 2-3 mm low where the frames were seen from
      1-2 m off, with a wall scatter of 2-3 mm).
    """
    a, b = sides
    noise = Z95 * 0.5 * math.hypot(a.noise_m, b.noise_m)
    return noise + 0.5 * abs(a.level_m - b.level_m) + 0.25 * (a.rise_m + b.rise_m) + sigma_m


def _wall_circle(
    angles_rad: np.ndarray, radii_m: np.ndarray, seen: np.ndarray, run: np.ndarray
) -> tuple[tuple[float, float], float, float]:
    """The centre of the section's own wall (across, up from the axis), its radius and its
    oval's amplitude ``a`` (the ``cos 2θ`` term: wider across than high by ``2a``; 0 unless
    the bins show it over twice its standard error), metres: the seen bins' radii outside
    ``run`` fitted by ``R + x cos θ + y sin θ``
    (a circle off the axis by ``(x, y)``, for offsets small against ``R``) plus
    ``a cos 2θ + b sin 2θ`` (an oval: a deformation that flattens the crown would otherwise
    pull the centre down, 9 mm on ``hap 16``), bins further off than three times their
    robust spread (an obstacle's face, a deposit) left out. The axis and the median radius
    where the bins kept do not ring the pipe (:func:`_rings_the_pipe`), or where the offset
    up is within twice its standard error."""
    use = seen & np.isfinite(radii_m)
    use[run] = False
    fallback = (0.0, 0.0), float(np.median(radii_m[use])) if use.any() else 0.0, 0.0
    if use.sum() < 12:
        return fallback
    theta, radii = angles_rad[use], radii_m[use]
    design = np.column_stack(
        (np.ones_like(theta), np.cos(theta), np.sin(theta), np.cos(2 * theta), np.sin(2 * theta))
    )
    # Start from the bins near the median radius: an obstacle's face over a third of the
    # wall would otherwise pull the first fit, and stay in it (on ``hap 12``, 40 mm low).
    off = np.abs(radii - np.median(radii))
    keep = off <= max(3.0 * MAD_TO_SIGMA * float(np.median(off)), 1e-4)
    for _ in range(5):
        fit, *_ = np.linalg.lstsq(design[keep], radii[keep], rcond=None)
        residual = radii - design @ fit
        spread = MAD_TO_SIGMA * float(np.median(np.abs(residual[keep])))
        keep = np.abs(residual) <= max(3.0 * spread, 1e-4)
        if keep.sum() < 12:
            return fallback
    if not _rings_the_pipe(theta[keep], len(angles_rad)):
        return fallback
    # Only an offset the bins show clearly (over twice its standard error): a sparse ring's
    # few noisy bins would move the invert by more than they correct (on a ring profiler's
    # 18-24 bins at 15 mm of noise, 5-12 mm where the axis was true).
    cov = spread**2 * np.linalg.pinv(design[keep].T @ design[keep])
    oval = float(fit[3]) if abs(fit[3]) > 2.0 * math.sqrt(max(float(cov[3, 3]), 0.0)) else 0.0
    if abs(fit[2]) <= 2.0 * math.sqrt(max(float(cov[2, 2]), 0.0)):
        return fallback[0], fallback[1], oval
    # The radius: the median distance of the wall from that centre, as the axis's is, so an
    # oval's flattened crown does not shrink it.
    x, y = radii * np.cos(theta) - fit[1], radii * np.sin(theta) - fit[2]
    return (float(fit[1]), float(fit[2])), float(np.median(np.hypot(x, y)[keep])), oval


def _rings_the_pipe(angles_rad: np.ndarray, bins: int) -> bool:
    """Whether the wall bins a circle was fitted to hold a third of each quadrant above the
    water (right, crown, left): the arcs left beside a hidden quarter let the centre slide
    along them (on ``hap 12`` at 2.6-2.8 m, the obstacle hanging from the crown hides it, and
    the axis stands there)."""
    quadrant = np.round(np.mod(angles_rad, 2.0 * math.pi) / (0.5 * math.pi)).astype(np.int64) % 4
    held = np.bincount(quadrant, minlength=4)
    return bool(np.all(held[:3] >= bins / 12.0))


def _surface_returns(
    raw: np.ndarray,
    run: np.ndarray,
    bins: int,
    edge_level: float,
    tolerance: float,
    wall_radius_m: float,
    sigma_m: float,
) -> np.ndarray:
    """Heights of the returns on the water's chord: in ``run``'s bins, inside the wall, within
    ``tolerance`` of the level where the wall stops.

    The chord must be seen: a few points lying flat on the water's surface. A view that merely
    stops short of the invert (a forward-looking sensor's first metre, a shadow) leaves no
    such line. Its returns are sparse, so they are looked for among all the section's points
    (``raw``: stray removal drops most of them).
    """
    dtheta = 2.0 * math.pi / bins
    raw_ang, raw_rad = polar_coordinates(raw)
    raw_bin = np.minimum((raw_ang / dtheta).astype(np.int64), bins - 1)
    on_chord = (
        np.isin(raw_bin, run)
        & (raw_rad < wall_radius_m - max(3.0 * sigma_m, 0.01))
        & (np.abs(raw[:, 1] - edge_level) <= tolerance)
    )
    # A surface returns more than free space does: the chord's count must stand out of what
    # the stray returns in the open pipe above it would put there by chance (early returns
    # from dust or spray at 1-2 % of a frame made a "surface" where the view stopped short).
    expected = _stray_density(raw, raw_rad, edge_level + tolerance, wall_radius_m) * (
        2.0 * math.sqrt(max(wall_radius_m**2 - edge_level**2, 0.0)) * 2.0 * tolerance
    )
    if on_chord.sum() <= expected + 3.0 * math.sqrt(expected):
        return raw[:0, 1]
    return raw[on_chord, 1]


_OPEN_RADIUS_SHARE = 0.6
"""The open middle of the pipe, where no wall is, as a share of its radius: where stray
returns in free space are counted."""


def _stray_density(
    raw: np.ndarray, raw_rad: np.ndarray, above_m: float, wall_radius_m: float
) -> float:
    """Returns per square metre of the section plane in the open middle of the pipe above
    ``above_m`` (none where that region is empty)."""
    a = _OPEN_RADIUS_SHARE * wall_radius_m
    y0 = min(max(above_m, -a), a)
    area = a * a * math.acos(y0 / a) - y0 * math.sqrt(a * a - y0 * y0)
    if area <= 0.0:
        return 0.0
    return float(np.count_nonzero((raw_rad < a) & (raw[:, 1] > above_m))) / area


SHADOW_LEVEL_MARGIN_RATIO = 0.01
"""A deposit or obstacle whose top stands within this share of the diameter below a water
level, or higher, explains a missing invert by its shadow (the line of sight over its top
descends behind it, so a shadow's edge always lies below the top that casts it)."""


@dataclass(frozen=True)
class SensorSight:
    """Where a forward-looking sensor looked from, and how steeply it could look down: what
    bounds the reach of a shadow (:func:`explain_invert_shadows`).

    Attributes
    ----------
    chainage_m : (P,) float
        Chainage of the sensor's positions (the registered frames').
    height_m : (P,) float
        The sensor's height above the axis at each position (section plane, metres).
    descent_ratio : float
        How steeply down, straight ahead in the pipe's vertical plane, every frame could
        look (the least steep of the frames' steepest sights: a frame whose attitude swung
        nose up saw less far down): the tangent of the angle below the axis, descent per
        metre of chainage. 0 when the sensor never looked down.
    forward_sign : float
        +1 when the sensor looked towards growing chainage, -1 towards falling chainage.
    max_range_m : float
        Returns further from the sensor than this were not measured.
    """

    chainage_m: np.ndarray
    height_m: np.ndarray
    descent_ratio: float
    forward_sign: float = 1.0
    max_range_m: float = float("inf")


def steepest_descent_ratio(points_sensor_m: np.ndarray, R_pipe_sensor: np.ndarray) -> float:
    """How steeply one frame looked down straight ahead: the tangent of the angle below the
    axis of its lowest line of sight in the pipe's vertical plane.

    The field of view's lower edge is the lowest elevation of the frame's returns in the
    sensor's own frame (x forward, z up), taken as flat across the azimuths the returns span
    (a rectangular field of view, as a forward-looking scanner's); that edge is turned into
    the pipe frame by the frame's attitude, and its ray with no sideways component is the one
    read. Rays that hit water return nothing, but the same lower edge reaches the wall beside
    it, so the edge is found with water in the invert too.

    Parameters
    ----------
    points_sensor_m : (N, 3) float
        One frame's returns in the sensor frame.
    R_pipe_sensor : (3, 3) float
        The frame's attitude: columns are the sensor's axes in the pipe frame (rows: along
        the sensor's travel, across, up).

    Returns
    -------
    float
        The tangent (0 when the frame holds no return below the sensor, or none ahead).
    """
    p = np.asarray(points_sensor_m, dtype=np.float64)
    r = np.linalg.norm(p, axis=1)
    p, r = p[r > 0], r[r > 0]
    if not len(p):
        return 0.0
    lowest = float(np.arcsin(np.clip(p[:, 2] / r, -1.0, 1.0)).min())
    az = np.arctan2(p[:, 1], p[:, 0])
    grid = np.linspace(float(az.min()), float(az.max()), 721)
    edge = (
        np.column_stack(
            (
                math.cos(lowest) * np.cos(grid),
                math.cos(lowest) * np.sin(grid),
                np.full_like(grid, math.sin(lowest)),
            )
        )
        @ np.asarray(R_pipe_sensor, dtype=np.float64).T
    )
    ahead = edge[:, 0] > 0
    if not ahead.any():
        return 0.0
    edge = edge[ahead]
    straight = int(np.argmin(np.abs(edge[:, 1]) / edge[:, 0]))
    return max(0.0, float(-edge[straight, 2] / edge[straight, 0]))


def sensor_sight(
    axis: PipeAxis,
    T_world_sensor: np.ndarray,
    frames: Iterable[tuple[int, np.ndarray]],
    *,
    max_range_m: float,
) -> SensorSight | None:
    """The sensor's positions along the pipe and how steeply it looked down.

    Parameters
    ----------
    axis : PipeAxis
    T_world_sensor : (P, 4, 4) float
        The sensor's poses (the registered frames').
    frames : iterable of (int, (N, 3) float)
        The frames to read the sight from (every registered one, or frames spread over the
        run), read one at a time: the row of their pose in ``T_world_sensor``, and their
        returns in the sensor frame (x forward, z up).
    max_range_m : float
        Returns further from the sensor were not measured.

    Returns
    -------
    SensorSight or None
        None when no frame was read, or the sensor did not look only the way it travelled
        (its x axis pointing back, or more than 1 % of a frame's returns behind it): a shadow
        may then fall on either side of what casts it.
    """
    T = np.asarray(T_world_sensor, dtype=np.float64)
    chainage, plane = axis.section_coordinates(T[:, :3, 3])
    forward = 1.0 if chainage[-1] >= chainage[0] else -1.0  # the way the sensor travelled
    descents = []
    for row, points in frames:
        origin = T[row, :3, 3]
        ends = origin + 0.1 * T[row, :3, :3].T  # a decimetre along each of the sensor's axes
        c, pl = axis.section_coordinates(np.vstack((origin, ends)))
        local = np.column_stack((c, pl))
        # Columns: the sensor's axes in (ahead, across, up).
        R = np.diag([forward, 1.0, 1.0]) @ ((local[1:] - local[0]) / 0.1).T
        p = np.asarray(points, dtype=np.float64)
        if R[0, 0] <= 0 or np.mean(p @ R[0] < 0) > 0.01:
            return None
        descents.append(steepest_descent_ratio(p, R))
    if not descents:
        return None
    return SensorSight(
        chainage_m=chainage,
        height_m=plane[:, 1],
        descent_ratio=min(descents),
        forward_sign=forward,
        max_range_m=max_range_m,
    )


def explain_invert_shadows(
    sections: Sequence[SectionMeasures], sight: SensorSight | None = None
) -> list[SectionMeasures]:
    """Take water back where a deposit or an obstacle beside it explains the missing invert.

    A section reads as water (``invert_under_water``) when its invert is unseen below a level
    chord with a few points on it. The shadow a deposit's or an obstacle's end casts on the
    invert looks the same to one section: the wall stops at the same height on both sides,
    and spurious returns or the ramp's grazing points lie on the chord. Along the pipe they
    differ: a shadow begins where something stands at least as high as its edge, and ends
    where the sensor's line of sight over that top reaches the invert.

    With ``sight``, a water section is the shadow's when a section before it (in the
    direction the sensor looked) has a deposit height (ok or not: a smeared deposit casts a
    shadow too) within :data:`SHADOW_LEVEL_MARGIN_RATIO` of its depth, or higher, and no
    position of the sensor saw the invert past that top before the section's start: from a
    position before the top, over it, at most as steeply as ``sight`` looked down; from a
    position past it, with nothing in between. The top reaches on through the sections after
    it read as water at its own height (its far side, seen only from above). Without
    ``sight`` (a registered cloud: the positions are not known), a stretch of sections that
    are water or too little seen is the shadow's all along when a section just before or
    after it has such a height. Such sections become ``low_coverage`` without a water depth:
    water that really ponds against a deposit is then not reported either (no figure, rather
    than a wrong one).

    Parameters
    ----------
    sections
        One scan's sections, in any order.
    sight : SensorSight, optional
        Where the sensor looked from, and how steeply (:func:`sensor_sight`).

    Returns
    -------
    list of SectionMeasures
        The same sections, in chainage order, with shadowed "water" taken back.
    """
    ordered = sorted(sections, key=lambda s: s.chainage_start_m)
    out = list(ordered)
    if sight is None:
        shadowed = _shadowed_stretches(ordered)
    else:
        shadowed = _shadowed_within_reach(ordered, sight)
    for k in shadowed:
        out[k] = dataclasses.replace(
            ordered[k],
            status=SectionStatus.LOW_COVERAGE,
            water_depth_ratio=None,
            water_depth_uncertainty_ratio=None,
        )
    return out


def _shadow_end(
    sight: SensorSight, top_u: float, top_y: float, invert_y: float, end_u: float
) -> float:
    """Where, beyond a top at ``top_u`` (``sight``'s forward coordinate) standing ``top_y``
    above the axis, some position of the sensor saw the invert (at ``invert_y``) past it, with
    ``end_u`` within its range: the shadow's far end (inf where none did)."""
    u = sight.forward_sign * np.asarray(sight.chainage_m, dtype=np.float64)
    y = np.asarray(sight.height_m, dtype=np.float64)
    t = sight.descent_ratio
    if t <= 0 or not len(u):
        return math.inf
    with np.errstate(divide="ignore", invalid="ignore"):
        near = u + (y - invert_y) / t  # the field of view's lower edge reaches the invert
        over = top_u + (top_u - u) * (top_y - invert_y) / (y - top_y)  # the sight over the top
    before = u < top_u
    near = np.where(before & (y <= top_y), math.inf, near)
    near = np.where(before & (y > top_y), np.maximum(near, over), near)
    near = np.where(end_u <= u + sight.max_range_m, near, math.inf)
    return float(near.min())


def _casts(height: float | None, depth: float) -> bool:
    return height is not None and height >= depth - SHADOW_LEVEL_MARGIN_RATIO


def _is_water(s: SectionMeasures) -> bool:
    """Read as water, with its depth: what a shadow may take back."""
    return s.status == SectionStatus.INVERT_UNDER_WATER and s.water_depth_ratio is not None


def _shadowed_within_reach(ordered: list[SectionMeasures], sight: SensorSight) -> list[int]:
    """The water sections within the reach of a shadow (:func:`explain_invert_shadows`)."""
    sign = sight.forward_sign
    along = ordered if sign > 0 else ordered[::-1]  # in the direction the sensor looked
    index = list(range(len(ordered))) if sign > 0 else list(range(len(ordered)))[::-1]

    shadowed: set[int] = set()
    for j, top in enumerate(along):
        height = top.deposit_height_ratio
        if height is None:
            continue
        # Sections read as water at the top's own height may hold the rest of the top, seen
        # only from above: the top reaches to the end of the last of them.
        last = j
        while last + 1 < len(along) and _is_water(along[last + 1]):
            if (along[last + 1].water_depth_ratio or 0.0) < height - SHADOW_LEVEL_MARGIN_RATIO:
                break
            last += 1
        top_u = max(sign * along[last].chainage_start_m, sign * along[last].chainage_end_m)
        diameter = top.nominal_diameter_m
        top_y = (height + SHADOW_LEVEL_MARGIN_RATIO - 0.5) * diameter
        for k in range(j + 1, len(along)):
            s = along[k]
            if not _is_water(s) or not _casts(height, s.water_depth_ratio or 0.0):
                continue
            start_u, end_u = sorted((sign * s.chainage_start_m, sign * s.chainage_end_m))
            if _shadow_end(sight, top_u, top_y, -0.5 * diameter, end_u) > start_u:
                shadowed.add(index[k])
    return sorted(shadowed)


def _shadowed_stretches(ordered: list[SectionMeasures]) -> list[int]:
    """The water sections of stretches beside a shadow's top, all along them (no sight)."""

    def is_gap(s: SectionMeasures) -> bool:
        return s.status in (SectionStatus.INVERT_UNDER_WATER, SectionStatus.LOW_COVERAGE)

    shadowed = []
    i = 0
    while i < len(ordered):
        if not is_gap(ordered[i]):
            i += 1
            continue
        j = i
        while j < len(ordered) and is_gap(ordered[j]):
            j += 1
        beside = [ordered[k].deposit_height_ratio for k in (i - 1, j) if 0 <= k < len(ordered)]
        for k in range(i, j):
            s = ordered[k]
            if _is_water(s) and any(_casts(h, s.water_depth_ratio or 0.0) for h in beside):
                shadowed.append(k)
        i = j
    return shadowed


LEVEL_RUN_SECTIONS = 5
"""Water whose surface returns nothing is read only where at least this many touching sections
(half a metre) show the invert unseen under a level chord at one height: water stands over
metres, level; a view that stops short of the invert, or the shadow of something on it,
changes height from section to section or lasts a few decimetres."""

LEVEL_TOLERANCE_M = 0.02
"""The heights where the wall stops, along such a run, agree within this, or within three
times the wall's spread where that is more: 3σ of where the wall's lowest points lie, and a
1 % gradient over the run."""


def confirm_surfaceless_water(sections: Sequence[SectionMeasures]) -> list[SectionMeasures]:
    """Read water where its surface returned nothing, once the pipe confirms it.

    A section whose invert is unseen under a level chord with no return on it is measured as
    ``low_coverage`` with the level as a candidate (``water_depth_ratio``, with
    ``water_from_surface`` False): one section cannot tell water from a view that stops short
    of the invert. It becomes water (``invert_under_water``, that depth) when it lies among
    :data:`LEVEL_RUN_SECTIONS` touching candidates or water sections whose levels agree within
    :data:`LEVEL_TOLERANCE_M` (or three times the run's median wall spread, where more);
    otherwise it stays ``low_coverage`` and its candidate depth is dropped. Water read from
    its surface's returns is kept as it is.

    Parameters
    ----------
    sections
        One scan's sections, in any order.

    Returns
    -------
    list of SectionMeasures
        In chainage order.
    """
    ordered = sorted(sections, key=lambda s: s.chainage_start_m)
    out = list(ordered)

    def candidate(k: int) -> bool:
        s = ordered[k]
        return s.water_from_surface is False and s.water_depth_ratio is not None

    def wet(k: int) -> bool:
        return ordered[k].status == SectionStatus.INVERT_UNDER_WATER or candidate(k)

    def level_m(k: int) -> float:
        s = ordered[k]
        return (s.water_depth_ratio or 0.0) * s.nominal_diameter_m

    for run in adjacent_runs(ordered, [wet(k) for k in range(len(ordered))]):
        i, j = run.start, run.stop
        levels = np.array([level_m(k) for k in run])
        spreads = [ordered[k].wall_spread_m or 0.0 for k in run]
        tolerance = max(LEVEL_TOLERANCE_M, 3.0 * float(np.median(spreads)))
        # Each section needs LEVEL_RUN_SECTIONS touching ones around it, itself among them,
        # whose levels agree (a long run may follow a gentle change of level).
        confirmed = np.zeros(j - i, dtype=bool)
        for a in range(0, j - i - LEVEL_RUN_SECTIONS + 1):
            window = levels[a : a + LEVEL_RUN_SECTIONS]
            if window.max() - window.min() <= tolerance:
                confirmed[a : a + LEVEL_RUN_SECTIONS] = True
        for k in run:
            if not candidate(k):
                continue
            if confirmed[k - i]:
                out[k] = dataclasses.replace(ordered[k], status=SectionStatus.INVERT_UNDER_WATER)
            else:
                out[k] = dataclasses.replace(
                    ordered[k], water_depth_ratio=None, water_depth_uncertainty_ratio=None
                )
    return out
