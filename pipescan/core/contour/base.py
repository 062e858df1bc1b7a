"""What every contour method shares: the result type, stray-point removal and polygon helpers.

A contour method takes a section's points projected onto the section plane, metres, with the
pipe axis at the origin, column 0 across and column 1 up (column 2, when given, the distance
along the axis from the section's start), and returns a :class:`ContourResult` in the same
frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

INVERT_ANGLE_RAD = 1.5 * math.pi
"""The section-plane angle of the invert: straight down, 6 o'clock."""


def angle_from_invert_rad(angles_rad: np.ndarray | float) -> np.ndarray:
    """The absolute angle (radians, in [0, π]) between section-plane angles and the invert.

    >>> [round(float(angle_from_invert_rad(math.radians(a))), 4) for a in (270, 90, 300)]
    [0.0, 3.1416, 0.5236]
    """
    return np.abs(np.angle(np.exp(1j * (np.asarray(angles_rad) - INVERT_ANGLE_RAD))))


@dataclass(frozen=True)
class ContourResult:
    """The inner contour of one section, as every contour method returns it.

    Attributes
    ----------
    polygon_m : (M, 2) float
        The contour, ordered, closed implicitly (the last point joins the first), metres, in
        the section plane with the pipe axis at the origin.
    area_m2 : float
        The open area the contour encloses.
    radii_m : (B,) float
        The contour's distance from the axis at the angles the method was given (the section
        profile's ``angles_rad``), for ovality, deformation and deposit height.
    """

    polygon_m: np.ndarray
    area_m2: float
    radii_m: np.ndarray


def remove_stray_points(
    points: np.ndarray,
    *,
    radius_m: float = 0.02,
    min_neighbours: int = 3,
    relative_density: float = 0.02,
) -> np.ndarray:
    """Drop isolated points (spurious early returns, dust) from a projected section.

    A real surface seen by the sensor leaves many points close together; a stray return has
    few. Points are counted on a grid of ``radius_m`` cells: a point is kept when its cell and
    the 8 around it hold more than ``min_neighbours`` other points, and at least
    ``relative_density`` times the median such count (so that in a section of 100,000 points,
    the few hundred spurious returns scattered through the open area are removed too). This is
    the paper's denoising step, in O(N), and it is what makes a stray point unable to move a
    figure.

    Parameters
    ----------
    points : (N, 2) or (N, 3) float
        Section points; the first two columns are the section plane (metres).

    Returns
    -------
    (K, 2) or (K, 3) float
        The points that have neighbours.
    """
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) <= min_neighbours:
        return pts[:0]
    ij = np.floor((pts[:, :2] - pts[:, :2].min(axis=0)) / radius_m).astype(np.int64) + 1
    others = _others_around(ij[:, 0], ij[:, 1], mode="constant")
    threshold = max(min_neighbours, relative_density * float(np.median(others)))
    return np.compress(others >= threshold, pts, axis=0)  # pts[mask]'s rows, in less time


def polar_coordinates(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Angle (rad, in [0, 2π), counter-clockwise from column 0) and distance from the origin
    of each point of a projected section, (N,) each: the section's filters and its profile
    share them (computed once per section, they are the same numbers in every one).

    Examples
    --------
    >>> ang, rad = polar_coordinates(np.array([[0.0, 2.0], [-1.0, 0.0]]))
    >>> np.round(np.degrees(ang)), rad
    (array([ 90., 180.]), array([2., 1.]))
    """
    xy = np.asarray(points, dtype=np.float64)
    return np.mod(np.arctan2(xy[:, 1], xy[:, 0]), 2.0 * np.pi), np.hypot(xy[:, 0], xy[:, 1])


def angle_bins(angle_rad: np.ndarray, bins: int) -> np.ndarray:
    """Index (N,) int of the equal angle bin each angle in [0, 2π) falls in."""
    return np.minimum((angle_rad * bins / (2.0 * np.pi)).astype(np.int64), bins - 1)


def remove_veil_points(
    points: np.ndarray,
    *,
    bins: int,
    radial_cell_m: float = 0.005,
    relative_density: float = 0.02,
) -> np.ndarray:
    """Drop the veil of mixed returns that an edge leaves behind it (a dense section).

    A ray that grazes an obstacle's edge returns a range between the edge and the surface
    behind it. Over many frames such returns fill the gap behind the edge with a veil: a
    region of the section plane, where a surface is a curve. So the veil's points are thin
    in any band of radius about the centre as thin as a surface's noise, where a surface's
    points are not, whatever the density along it. Points are counted on a polar grid of
    ``bins`` angle bins and ``radial_cell_m`` rings; a point is kept when its cell and the 8
    around it hold at least ``relative_density`` times the median such count.

    The window (three rings, 15 mm by default) is half the radial gap at which two surfaces
    are told apart (``polar_profile``'s ``layer_gap_m``), so a veil across such a gap is
    spread over at least two windows; a surface's noise scales its own count and the median
    alike. docs/measures.md gives what it does to the sections behind an obstacle.
    """
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) == 0:
        return pts
    kept = not_veil(*polar_coordinates(pts), bins, radial_cell_m, relative_density)
    return np.compress(kept, pts, axis=0)


def not_veil(
    angle_rad: np.ndarray,
    radius_m: np.ndarray,
    bins: int,
    radial_cell_m: float = 0.005,
    relative_density: float = 0.02,
) -> np.ndarray:
    """The mask (N,) bool of the points :func:`remove_veil_points` keeps, from their polar
    coordinates (:func:`polar_coordinates`, at least one point)."""
    k = (radius_m / radial_cell_m).astype(np.int64) + 1
    # Round the circle the angle bins wrap; the empty ring beyond the last keeps the radius
    # from wrapping.
    others = _others_around(angle_bins(angle_rad, bins), k, mode="wrap", rows=bins)
    return others >= relative_density * float(np.median(others))


def _others_around(i: np.ndarray, j: np.ndarray, *, mode: str, rows: int | None = None):
    """For each point in grid cell ``(i, j)`` (``j`` from 1, a free cell beyond the largest),
    how many other points its cell and the 8 around it hold."""
    shape = (int(i.max()) + 2 if rows is None else rows, int(j.max()) + 2)
    flat = np.bincount(i * shape[1] + j, minlength=shape[0] * shape[1])
    block = ndimage.convolve(flat.reshape(shape), np.ones((3, 3), dtype=np.int64), mode=mode)
    return block[i, j] - 1


def polygon_area(polygon: np.ndarray) -> float:
    """Area enclosed by a closed contour (M, 2), m².

    A nearest-neighbour chain can cross itself where it doubles back; the shoelace formula
    then subtracts the loops. shapely's ``make_valid`` splits such a ring into simple
    polygons whose areas add up.
    """
    import shapely

    ring = shapely.Polygon(polygon)
    if not ring.is_valid:
        ring = shapely.make_valid(ring)
    return float(ring.area)


def radii_of_polygon(polygon: np.ndarray, angles_rad: np.ndarray) -> np.ndarray:
    """Radius of a star-shaped polygon around the origin at given angles (interpolated)."""
    ang, rad = polar_coordinates(polygon)
    order = np.argsort(ang)
    return np.interp(angles_rad, ang[order], rad[order], period=2.0 * np.pi)
