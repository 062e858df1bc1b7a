"""The pipe axis: a robust straight centreline and the chainage along it.

The paper takes the coordinate axis with the largest extent as the pipe direction. That breaks as
soon as a scan is tilted, so pipescan starts from PCA and then refines the line with robust circle
fits on short slices, which the wall defines and deposits or obstacles do not (they are rejected
as outliers of the circle).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from pipescan.core.errors import GeometryError


@dataclass(frozen=True)
class PipeAxis:
    """A straight pipe axis with a chainage origin and a section-plane basis.

    Attributes
    ----------
    origin_m : (3,) float
        The point on the axis where chainage is ``chainage_offset_m`` (the scan's start).
    direction : (3,) float
        Unit vector along the axis, pointing the way chainage grows.
    up : (3,) float
        Unit vector perpendicular to ``direction``, pointing to the crown (against gravity).
    chainage_offset_m : float
        Chainage of ``origin_m``, measured from the upstream node.
    chainage_sign : float
        +1 when chainage grows along ``direction`` (a downstream survey), -1 when it shrinks
        (an upstream survey, which starts ``chainage_offset_m`` from the upstream node and
        moves towards it).
    radius_m : float
        The wall radius the fit found (median over slices), for diagnostics.
    """

    origin_m: np.ndarray
    direction: np.ndarray
    up: np.ndarray
    chainage_offset_m: float = 0.0
    chainage_sign: float = 1.0
    radius_m: float = float("nan")

    @property
    def right(self) -> np.ndarray:
        """Unit vector completing the right-handed section basis (right, up, direction)."""
        return np.cross(self.up, self.direction)

    def distance_along(self, points_m: np.ndarray) -> np.ndarray:
        """Signed distance of each point along ``direction`` from ``origin_m``, shape (N,)."""
        return (np.asarray(points_m, dtype=np.float64) - self.origin_m) @ self.direction

    def chainage(self, points_m: np.ndarray) -> np.ndarray:
        """Chainage of each point in metres from the upstream node, shape (N,)."""
        return self.chainage_offset_m + self.chainage_sign * self.distance_along(points_m)

    def to_section_plane(self, points_m: np.ndarray) -> np.ndarray:
        """Project points onto the plane perpendicular to the axis.

        Returns (N, 2) metres: column 0 across (``right``), column 1 up, with the axis at the
        origin.
        """
        rel = np.asarray(points_m, dtype=np.float64) - self.origin_m
        return np.column_stack((rel @ self.right, rel @ self.up))


def fit_circle(points_2d: np.ndarray) -> tuple[np.ndarray, float]:
    """Algebraic (Kasa) least-squares circle fit.

    Parameters
    ----------
    points_2d : (N, 2) float
        Points in a plane, metres. N >= 3.

    Returns
    -------
    centre : (2,) float
    radius_m : float
    """
    x, y = points_2d[:, 0], points_2d[:, 1]
    a = np.column_stack((x, y, np.ones_like(x)))
    b = x * x + y * y
    sol, *_ = np.linalg.lstsq(a, b, rcond=None)
    centre = sol[:2] / 2.0
    radius = float(np.sqrt(max(sol[2] + centre @ centre, 0.0)))
    return centre, radius


def _circle_through(p: np.ndarray) -> tuple[np.ndarray, float] | None:
    """Circle through three points (3, 2), or None when they are (nearly) collinear."""
    (ax, ay), (bx, by), (cx, cy) = p
    d = 2.0 * (ax * (by - cy) + bx * (cy - ay) + cx * (ay - by))
    if abs(d) < 1e-12:
        return None
    a2, b2, c2 = ax * ax + ay * ay, bx * bx + by * by, cx * cx + cy * cy
    ux = (a2 * (by - cy) + b2 * (cy - ay) + c2 * (ay - by)) / d
    uy = (a2 * (cx - bx) + b2 * (ax - cx) + c2 * (bx - ax)) / d
    centre = np.array([ux, uy])
    return centre, float(np.hypot(ax - ux, ay - uy))


def fit_circle_robust(
    points_2d: np.ndarray,
    *,
    inlier_m: float = 0.01,
    trials: int = 150,
    iterations: int = 5,
    seed: int = 0,
) -> tuple[np.ndarray, float, np.ndarray]:
    """Circle fit that ignores deposits, obstacles and stray points.

    A least-squares fit is pulled inwards by a deposit that holds a third of the points. So the
    wall is first found as the largest consensus set of a small RANSAC (circles through three
    random points, scored by points within ``inlier_m``), then refined by least squares on the
    points within three robust standard deviations of it (at least ``inlier_m / 2``).
    Deterministic for a given ``seed``.

    Parameters
    ----------
    points_2d : (N, 2) float
        Points in a plane, metres.

    Returns
    -------
    centre : (2,) float
    radius_m : float
    inliers : (N,) bool
        The points the final fit used.

    Raises
    ------
    GeometryError
        With fewer than 10 points.
    """
    pts = np.asarray(points_2d, dtype=np.float64)
    if len(pts) < 10:
        raise GeometryError(f"a circle fit needs at least 10 points, got {len(pts)}")
    rng = np.random.default_rng(seed)
    sample = pts if len(pts) <= 4000 else pts[rng.choice(len(pts), 4000, replace=False)]
    span = float(np.ptp(sample, axis=0).max())
    best, best_score = None, -1
    for _ in range(trials):
        fit = _circle_through(sample[rng.choice(len(sample), 3, replace=False)])
        if fit is None or fit[1] > span:
            continue
        score = int((np.abs(np.hypot(*(sample - fit[0]).T) - fit[1]) < inlier_m).sum())
        if score > best_score:
            best, best_score = fit, score
    centre, radius = best if best is not None else fit_circle(pts)
    inliers = np.ones(len(pts), dtype=bool)
    for _ in range(iterations):
        resid = np.hypot(*(pts - centre).T) - radius
        near = np.abs(resid) < inlier_m
        if near.sum() < 10:
            break
        sigma = 1.4826 * np.median(np.abs(resid[near]))
        new = np.abs(resid) <= max(3.0 * sigma, inlier_m / 2.0)
        if new.sum() < 10:
            break
        inliers = new
        centre, radius = fit_circle(pts[inliers])
    return centre, radius, inliers


def _orthonormal_up(direction: np.ndarray, up_hint: np.ndarray) -> np.ndarray:
    up = np.asarray(up_hint, dtype=np.float64)
    up = up - (up @ direction) * direction
    norm = np.linalg.norm(up)
    if norm < 1e-6:
        raise GeometryError(
            "the up hint is parallel to the pipe axis",
            hint="a vertical shaft needs an explicit up direction",
        )
    return up / norm


def fit_axis(
    points_m: np.ndarray,
    *,
    start_m: np.ndarray | None = None,
    travel_m: np.ndarray | None = None,
    up_hint: np.ndarray = np.array([0.0, 0.0, 1.0]),
    chainage_offset_m: float = 0.0,
    direction: str = "downstream",
    slice_m: float = 0.5,
    max_points: int = 200_000,
    seed: int = 0,
) -> PipeAxis:
    """Fit a straight pipe axis: PCA for a first guess, then robust circle fits on slices.

    Parameters
    ----------
    points_m : (N, 3) float
        Registered points, metres, in the common (world) frame.
    start_m : (3,) float, optional
        The sensor position at the scan's start (first frame). Chainage ``chainage_offset_m``
        is placed at its projection on the axis. Without it, the scan starts at the end of the
        cloud with the lowest coordinate along the axis.
    travel_m : (3,) float, optional
        A vector along the direction the crawler moved (e.g. last minus first sensor position);
        orients the axis. Without it, the axis points along the cloud's larger half... see Notes.
    up_hint : (3,) float
        Roughly "up" in the world frame (the first sensor frame's z for frame archives).
    chainage_offset_m : float
        Chainage of the scan's start from the upstream node.
    direction : {"downstream", "upstream"}
        The survey direction; upstream surveys count chainage down from the offset.
    slice_m : float
        Length of the slices whose circle centres define the line.
    max_points : int
        PCA and slice fits use a random subsample of at most this many points.

    Returns
    -------
    PipeAxis

    Raises
    ------
    GeometryError
        When the cloud is too small or not elongated enough to have an axis.

    Notes
    -----
    Without ``travel_m`` the axis is oriented so that its largest world component is positive:
    arbitrary, but deterministic for a given cloud.
    """
    pts = np.asarray(points_m, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise GeometryError(f"points must have shape (N, 3), got {pts.shape}")
    if len(pts) < 100:
        raise GeometryError(f"too few points to fit a pipe axis: {len(pts)}")
    rng = np.random.default_rng(seed)
    if len(pts) > max_points:
        pts = pts[rng.choice(len(pts), max_points, replace=False)]

    centroid = pts.mean(axis=0)
    _, sing, vt = np.linalg.svd(pts - centroid, full_matrices=False)
    if sing[0] < 1.5 * sing[1]:
        raise GeometryError(
            "the cloud is not elongated enough to define a pipe axis",
            hint="a scan should cover at least about two pipe diameters of length",
        )
    axis_dir = vt[0]
    if travel_m is not None and np.linalg.norm(travel_m) > 1e-9:
        if axis_dir @ travel_m < 0:
            axis_dir = -axis_dir
    elif axis_dir[np.argmax(np.abs(axis_dir))] < 0:
        axis_dir = -axis_dir

    # Refine: circle centres of slices along the PCA axis, then a line through them.
    for _ in range(2):
        up = _orthonormal_up(axis_dir, up_hint)
        right = np.cross(up, axis_dir)
        rel = pts - centroid
        along = rel @ axis_dir
        plane = np.column_stack((rel @ right, rel @ up))
        edges = np.arange(along.min(), along.max() + slice_m, slice_m)
        centres_3d, radii, weights = [], [], []
        order = np.argsort(along)
        bounds = np.searchsorted(along[order], edges)
        for lo, hi in itertools.pairwise(bounds):
            idx = order[lo:hi]
            if len(idx) < 200:
                continue
            try:
                c2, r, inl = fit_circle_robust(plane[idx])
            except GeometryError:
                continue
            s_mid = float(np.median(along[idx]))
            centres_3d.append(centroid + s_mid * axis_dir + c2[0] * right + c2[1] * up)
            radii.append(r)
            weights.append(inl.sum())
        if len(centres_3d) < 2:
            break
        c = np.asarray(centres_3d)
        w = np.asarray(weights, dtype=np.float64)
        cm = (c * w[:, None]).sum(0) / w.sum()
        _, _, vtc = np.linalg.svd((c - cm) * np.sqrt(w)[:, None], full_matrices=False)
        new_dir = vtc[0] if vtc[0] @ axis_dir > 0 else -vtc[0]
        centroid, axis_dir = cm, new_dir / np.linalg.norm(new_dir)

    up = _orthonormal_up(axis_dir, up_hint)
    radius = float(np.median(radii)) if radii else float("nan")
    if start_m is not None:
        start = np.asarray(start_m, dtype=np.float64)
        origin = centroid + ((start - centroid) @ axis_dir) * axis_dir
    else:
        origin = centroid + ((pts - centroid) @ axis_dir).min() * axis_dir
    return PipeAxis(
        origin_m=origin,
        direction=axis_dir,
        up=up,
        chainage_offset_m=float(chainage_offset_m),
        chainage_sign=-1.0 if direction == "upstream" else 1.0,
        radius_m=radius,
    )
