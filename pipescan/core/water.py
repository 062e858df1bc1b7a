"""Water standing in the invert of a section: a flat chord and missing wall below it.

A LiDAR gets no return from under water and few from its surface, so water leaves the invert
unseen, from one side's wall to the other's at the same height, with at most a sparse line of
points along that chord. A deposit is the opposite: its flat top is seen as densely as the
wall. :func:`detect_water` tells them apart; docs/measures.md says how the figures use it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipescan.core.uncertainty import unseen_runs

SPARSE_BIN_SHARE = 0.1
"""A bin holding under this share of the section's median bin count holds only stray returns
(a water surface returns a few per cent of the rays that reach it)."""


@dataclass(frozen=True)
class WaterLevel:
    """Water found in a section.

    Attributes
    ----------
    level_m : float
        Height of the surface above the axis (negative: below it), section-plane metres.
    depth_ratio : float
        Depth above the invert over the nominal diameter.
    bins : (K,) int
        The angle bins under water (unseen wall, or a sparse chord), to be left out of the
        contour.
    from_surface : bool
        The level was read from points on the surface (else from where the wall stops).
    """

    level_m: float
    depth_ratio: float
    bins: np.ndarray
    from_surface: bool


def detect_water(
    points: np.ndarray,
    angles_rad: np.ndarray,
    seen: np.ndarray,
    counts: np.ndarray,
    wall_radius_m: float,
    nominal_diameter_m: float,
    sigma_m: float,
) -> WaterLevel | None:
    """Find water in a section's invert.

    The candidate is the run of bins around straight down that hold no points or only a
    sparse line of them (:data:`SPARSE_BIN_SHARE` of the seen bins' median count). It is
    water when the wall on both sides of it stops at the same height (within
    ``max(3 σ, 2 cm)`` plus one bin's rise), below the axis; the level is the median
    height of the points found on the chord when there are at least three, lying flat, or
    else the mean height where the wall stops.

    Parameters
    ----------
    points : (N, 2+) float
        The section's points, section plane (0 across, 1 up), axis at the origin.
    angles_rad, seen, counts : (B,) arrays
        The section profile's bins (centres, seen, points per bin).
    wall_radius_m : float
        The wall's radius (median of the seen bins at the wall).
    nominal_diameter_m : float
    sigma_m : float
        The section's residual spread (1σ).

    Returns
    -------
    WaterLevel or None
        None when the invert is seen (dry), or the gap there is not level water.
    """
    bins = len(angles_rad)
    dtheta = 2.0 * math.pi / bins
    down = int(np.argmin(np.abs(np.angle(np.exp(1j * (angles_rad - 1.5 * math.pi))))))
    typical = float(np.median(counts[seen])) if seen.any() else 0.0
    # Water leaves (almost) no points: bins that hold many points but failed the sub-slice
    # vote (a deposit's top seen along part of the section) are a shadow, not water.
    candidate = counts < SPARSE_BIN_SHARE * typical
    if not candidate[down] or candidate.all():
        return None
    run = next(r for r in unseen_runs(~candidate) if down in set(r.tolist()))
    if len(run) < 2 or len(run) > bins // 2:
        return None
    left, right = (run[0] - 1) % bins, (run[-1] + 1) % bins
    xy = np.asarray(points, dtype=np.float64)[:, :2]
    ang = np.mod(np.arctan2(xy[:, 1], xy[:, 0]), 2.0 * math.pi)
    b_idx = np.minimum((ang / dtheta).astype(np.int64), bins - 1)
    rad = np.hypot(xy[:, 0], xy[:, 1])
    at_wall = np.abs(rad - wall_radius_m) <= max(3.0 * sigma_m, 0.01)
    edges = []
    for b in (left, right):
        near = at_wall & (b_idx == b)
        if not near.any():
            return None
        edges.append(float(xy[near, 1].min()))
    tolerance = max(3.0 * sigma_m, 0.02) + wall_radius_m * math.sin(dtheta)
    if abs(edges[0] - edges[1]) > tolerance or max(edges) >= 0.0:
        return None
    in_run = np.isin(b_idx, run) & (rad < wall_radius_m - max(3.0 * sigma_m, 0.01))
    surface_y = xy[in_run, 1]
    from_surface = False
    level = 0.5 * (edges[0] + edges[1])
    if len(surface_y) >= 3:
        centre = float(np.median(surface_y))
        flat = 1.4826 * float(np.median(np.abs(surface_y - centre)))
        if flat <= max(3.0 * sigma_m, 0.01) and abs(centre - level) <= tolerance:
            level, from_surface = centre, True
    depth = (level + wall_radius_m) / nominal_diameter_m
    if depth <= 0:
        return None
    return WaterLevel(level_m=level, depth_ratio=depth, bins=run, from_surface=from_surface)
