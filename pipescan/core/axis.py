"""The pipe axis: a robust straight centreline and the chainage along it.

The paper takes the coordinate axis with the largest extent as the pipe direction. That breaks as
soon as a scan is tilted, so pipescan starts from PCA and then refines the line with robust circle
fits on short slices, which the wall defines and deposits or obstacles do not (they are rejected
as outliers of the circle).
"""

from __future__ import annotations

import functools
import itertools
import math
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import make_smoothing_spline

from pipescan.core.errors import GeometryError
from pipescan.core.uncertainty import MAD_TO_SIGMA


@dataclass(frozen=True)
class PipeAxis:
    """The pipe's centreline with a chainage origin and a section-plane basis.

    A straight pipe is a line (``nodes_m`` is None). A pipe with gentle bends or sags also
    carries a smoothed centreline: nodes a few centimetres apart, each with its own tangent and
    up vector. A point then belongs to its nearest node; its distance along the pipe is the
    node's arc length plus its offset along the node's tangent, and its section plane is the
    node's.

    Attributes
    ----------
    origin_m : (3,) float
        The point on the centreline where chainage is ``chainage_offset_m`` (the scan's start).
    direction : (3,) float
        Unit vector along the (mean) axis, pointing the way the survey travelled.
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
    nodes_m, tangents, ups : (K, 3) float, optional
        The curved centreline's nodes, unit tangents and unit up vectors (world frame).
    arc_m : (K,) float, optional
        Each node's distance along the centreline from ``origin_m`` (negative before it).
    has_invert : bool
        False for a vertical pipe (a shaft): no side of it is up, so ``up`` is only a
        reference direction across it, and there is no invert to read deposits or water at.
    """

    origin_m: np.ndarray
    direction: np.ndarray
    up: np.ndarray
    chainage_offset_m: float = 0.0
    chainage_sign: float = 1.0
    radius_m: float = float("nan")
    nodes_m: np.ndarray | None = field(default=None, repr=False, compare=False)
    tangents: np.ndarray | None = field(default=None, repr=False, compare=False)
    ups: np.ndarray | None = field(default=None, repr=False, compare=False)
    arc_m: np.ndarray | None = field(default=None, repr=False, compare=False)
    has_invert: bool = True

    @property
    def right(self) -> np.ndarray:
        """Unit vector completing the right-handed section basis (right, up, direction)."""
        return np.cross(self.up, self.direction)

    @property
    def is_curved(self) -> bool:
        return self.nodes_m is not None

    @functools.cached_property
    def _node_rows(self) -> tuple[list[np.ndarray], list[list[np.ndarray]]]:
        """The curved centreline's nodes relative to ``origin_m`` as their x, y and z, and
        each node's (along, across, up) unit vectors as their x, y and z, (K,) each."""
        assert self.tangents is not None and self.ups is not None
        basis = np.stack((self.tangents, np.cross(self.ups, self.tangents), self.ups), axis=1)
        nodes = self._node_locator.nodes_m  # the nodes relative to origin_m
        return (
            [np.ascontiguousarray(nodes[:, c]) for c in range(3)],
            [[np.ascontiguousarray(basis[:, row, c]) for c in range(3)] for row in range(3)],
        )

    @functools.cached_property
    def _node_locator(self) -> NodeLocator:
        """The curved centreline's node search, on nodes relative to ``origin_m``."""
        assert self.nodes_m is not None
        return NodeLocator(self.nodes_m - self.origin_m)

    def local_coordinates(
        self, points_m: np.ndarray, *, relative: bool = False
    ) -> tuple[np.ndarray, np.ndarray]:
        """Distance along the centreline and section-plane coordinates of each point.

        Parameters
        ----------
        points_m : (N, 3) float
            Points in the world frame, metres; or, with ``relative=True``, their offsets from
            ``origin_m`` (float32 is then kept as float32: half the memory traffic).

        Returns
        -------
        along_m : (N,) float
            Signed distance along the centreline from ``origin_m``, in the survey's direction.
        plane_m : (N, 2) float
            Coordinates in the local section plane: column 0 across (right), column 1 up, the
            centreline at the origin.
        """
        if relative:
            pts = np.asarray(points_m)
            if pts.dtype != np.float32:
                pts = pts.astype(np.float64, copy=False)
        else:
            pts = np.asarray(points_m, dtype=np.float64) - self.origin_m
        if self.nodes_m is None:
            # One matrix product gives (along, across, up); the two results are views of it.
            basis = np.column_stack((self.direction, self.right, self.up)).astype(pts.dtype)
            local = pts @ basis
            return local[:, 0], local[:, 1:]
        assert self.tangents is not None and self.ups is not None and self.arc_m is not None
        i = self._node_locator.nearest(pts)
        # The offset from the node and each coordinate of it from gathers of one component
        # at a time: a third of the time of gathering a 3x3 basis per point and contracting
        # it (equal to rounding, 1e-16 m).
        nodes, rows = self._node_rows
        dx, dy, dz = (pts[:, c].astype(np.float64) - nodes[c][i] for c in range(3))
        along, across, up = (dx * cx[i] + dy * cy[i] + dz * cz[i] for cx, cy, cz in rows)
        return self.arc_m[i] + along, np.column_stack((across, up))

    def distance_along(self, points_m: np.ndarray) -> np.ndarray:
        """Signed distance of each point along the centreline from ``origin_m``, shape (N,)."""
        if self.nodes_m is None:
            return (np.asarray(points_m, dtype=np.float64) - self.origin_m) @ self.direction
        return self.local_coordinates(points_m)[0]

    def chainage(self, points_m: np.ndarray) -> np.ndarray:
        """Chainage of each point in metres from the upstream node, shape (N,)."""
        return self.chainage_offset_m + self.chainage_sign * self.distance_along(points_m)

    def to_section_plane(self, points_m: np.ndarray) -> np.ndarray:
        """Project points onto the (local) plane perpendicular to the axis.

        Returns (N, 2) metres: column 0 across (``right``), column 1 up, with the axis at the
        origin.
        """
        return self.local_coordinates(points_m)[1]

    def point_at(self, along_m: float, across_m: float, up_m: float) -> np.ndarray:
        """World position (3,) of local coordinates: ``along_m`` on the centreline from
        ``origin_m``, offset ``across_m`` and ``up_m`` in that place's section plane."""
        if self.nodes_m is None:
            return self.origin_m + along_m * self.direction + across_m * self.right + up_m * self.up
        assert self.tangents is not None and self.ups is not None and self.arc_m is not None
        i = int(np.clip(np.searchsorted(self.arc_m, along_m), 1, len(self.arc_m) - 1))
        if along_m - self.arc_m[i - 1] < self.arc_m[i] - along_m:
            i -= 1
        t, u = self.tangents[i], self.ups[i]
        base = self.nodes_m[i] + (along_m - self.arc_m[i]) * t
        return base + across_m * np.cross(u, t) + up_m * u

    def section_coordinates(
        self, points_m: np.ndarray, *, relative: bool = False
    ) -> tuple[np.ndarray, np.ndarray]:
        """Chainage (N,) and section-plane coordinates (N, 2) in one pass (see
        ``local_coordinates`` for ``relative``)."""
        along, plane = self.local_coordinates(points_m, relative=relative)
        return self.chainage_offset_m + self.chainage_sign * along, plane


def nearest_node(nodes_m: np.ndarray, points_m: np.ndarray) -> np.ndarray:
    """Index of the node nearest to each point, (N,) int64 (exact; small_gicp's k-d tree,
    1.5-1.7x faster than SciPy's on 262,144 points against a 656-node centreline).

    :class:`NodeLocator` gives the same answer faster for a centreline's ordered nodes."""
    import small_gicp

    tree = small_gicp.KdTree(np.asarray(nodes_m, np.float64), num_threads=1)
    queries = np.asarray(points_m, np.float64)
    return np.asarray(tree.batch_nearest_neighbor_search(queries, num_threads=1)[0], np.int64)


_LOCATOR_SAMPLE = 4096
_LOCATOR_MAX_CELLS = 1_000_000


class NodeLocator:
    """The nearest of a centreline's ordered nodes to each point, found along the line.

    A k-d tree over a centreline's nodes has to visit every node within the pipe's radius of
    a point, a dozen for nodes 5 cm apart in a 0.6 m pipe. Along the chord from the first
    node to the last, the nodes come in order, so a point's nearest node is almost always
    the one its projection falls on. ``nearest`` takes that node when it is proven nearest,
    and asks the k-d tree (:func:`nearest_node`) for every other point, so the answer is the
    same (ties aside).

    The proof, for the node ``j`` nearer to the point than both its neighbours: with the
    point at ``u`` along the chord from node ``j`` and ``ρ`` from it across the chord, a node
    ``k`` at least two nodes away lies ``Δ ≥ g`` along the chord from ``j`` and at most
    ``λ Δ`` across from it (``λ``, the centreline's largest lateral slope between ``j`` and
    the nodes within ``reach_m``). It is then no nearer when ``g − 2|u| ≥ 2 ρ λ`` on its side
    (``(Δ ∓ u)² + (ρ − λΔ)² ≥ u² + ρ²``), and a node further than ``reach_m`` along the chord
    is no nearer when the point is within ``reach_m − |u|`` of node ``j``.

    Parameters
    ----------
    nodes_m : (K, 3) float
        The centreline's nodes in order, metres (any frame; points must be in the same one).
    reach_m : float
        How far along the chord the lateral slope is bounded: points further than this from
        their node (beyond any pipe's radius) are left to the k-d tree.

    Examples
    --------
    >>> s = np.arange(0.0, 10.0, 0.05)
    >>> nodes = np.column_stack((s, 0.02 * np.sin(s / 3), np.zeros_like(s)))
    >>> rng = np.random.default_rng(0)
    >>> pts = np.column_stack((rng.uniform(0, 10, 1000), rng.normal(0, 0.3, (1000, 2))))
    >>> bool(np.array_equal(NodeLocator(nodes).nearest(pts), nearest_node(nodes, pts)))
    True
    """

    def __init__(self, nodes_m: np.ndarray, *, reach_m: float = 2.0) -> None:
        nodes = np.asarray(nodes_m, dtype=np.float64)
        if nodes.ndim != 2 or nodes.shape[1] != 3:
            raise ValueError(f"NodeLocator needs nodes of shape (K, 3), got {nodes.shape}.")
        self.nodes_m = nodes
        self.reach_m = float(reach_m)
        self.ordered = False
        if len(nodes) < 3:
            return  # every point goes to the k-d tree
        chord = nodes[-1] - nodes[0]
        a = chord / max(float(np.linalg.norm(chord)), 1e-12)
        across = _orthonormal_up(a, np.array([0.0, 0.0, 1.0]))
        self._basis = np.column_stack((a, np.cross(across, a), across))
        local = nodes @ self._basis
        self._along, self._x, self._y = (np.ascontiguousarray(c) for c in local.T)
        steps = np.diff(self._along)
        # Nodes that do not advance along the chord (a bend of more than 90°): no order.
        self.ordered = bool(np.all(steps > 0))
        if not self.ordered:
            return
        k = len(nodes)
        # A first guess per quarter of the shortest step along the chord: the node whose
        # projection is nearest to the cell's centre (nodes 1 to K - 2, so both neighbours
        # exist; a point nearest to an end node is left unproven).
        self._first = float(self._along[0])
        extent = float(self._along[-1]) - self._first
        self._cell_m = max(float(steps.min()) / 4.0, extent / (_LOCATOR_MAX_CELLS - 1))
        cells = min(int(np.ceil(extent / self._cell_m)) + 1, _LOCATOR_MAX_CELLS)
        centres = self._first + (np.arange(cells) + 0.5) * self._cell_m
        above = np.clip(np.searchsorted(self._along, centres), 1, k - 1)
        nearer_below = centres - self._along[above - 1] < self._along[above] - centres
        self._guess = np.clip(above - nearer_below, 1, k - 2).astype(np.int64)
        # The chord distance from each node to the node two after it (and two before it).
        two_steps = self._along[2:] - self._along[:-2]
        self._gap_after = np.concatenate((two_steps, [np.inf, np.inf]))
        self._gap_before = np.concatenate(([np.inf, np.inf], two_steps))
        # λ_j = max |ℓ_k − ℓ_j| / Δ_jk over 2 ≤ |k − j|, Δ_jk ≤ reach_m.
        slope = np.zeros(k)
        for m in range(2, k):
            delta = self._along[m:] - self._along[:-m]
            near = delta <= self.reach_m
            if not near.any():
                break
            lateral = np.hypot(self._x[m:] - self._x[:-m], self._y[m:] - self._y[:-m])
            ratio = np.where(near, lateral / delta, 0.0)
            np.maximum(slope[:-m], ratio, out=slope[:-m])
            np.maximum(slope[m:], ratio, out=slope[m:])
        self._slope = slope

    def nearest(self, points_m: np.ndarray) -> np.ndarray:
        """Index of the node nearest to each point, (N,) int64; points (N, 3) in the nodes'
        frame, float32 or float64."""
        pts = np.asarray(points_m)
        if not self.ordered or len(pts) == 0:
            return nearest_node(self.nodes_m, pts)
        # A strongly bent centreline (its chord far from its tangents) proves few points:
        # try a sample first, and leave all to the k-d tree when it proves under half.
        sample = min(len(pts), _LOCATOR_SAMPLE)
        if len(pts) > sample:
            _, proven = self._along_chord(pts[:sample])
            if proven.mean() < 0.5:
                return nearest_node(self.nodes_m, pts)
        j, proven = self._along_chord(pts)
        unproven = np.flatnonzero(~proven)
        if len(unproven):
            j[unproven] = nearest_node(self.nodes_m, pts[unproven])
        return j

    def _along_chord(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each point's candidate node and whether it is proven the nearest, (N,) each."""
        # (3, N): each coordinate contiguous, a third faster to gather against than columns.
        s, x, y = self._basis.T @ pts.astype(np.float64, copy=False).T
        k = len(self._along)
        cell = np.clip(((s - self._first) / self._cell_m).astype(np.int64), 0, len(self._guess) - 1)
        j = self._guess[cell]

        def squared(i: np.ndarray, at: slice | np.ndarray = slice(None)) -> np.ndarray:
            return (
                (s[at] - self._along[i]) ** 2
                + (x[at] - self._x[i]) ** 2
                + (y[at] - self._y[i]) ** 2
            )

        here, before, after = squared(j), squared(j - 1), squared(j + 1)
        # One step towards the nearer neighbour where the guess was off by a node.
        move = np.flatnonzero((before < here) ^ (after < here))
        if len(move):
            j[move] = np.clip(j[move] + np.where(after[move] < here[move], 1, -1), 1, k - 2)
            jm = j[move]
            here[move], before[move], after[move] = (
                squared(jm, move), squared(jm - 1, move), squared(jm + 1, move)
            )  # fmt: skip
        u = s - self._along[j]
        rho = np.sqrt(np.maximum(here - u * u, 0.0))
        bound = 2.0 * rho * self._slope[j]
        proven = (
            (here <= before)
            & (here <= after)
            & (self._gap_after[j] - 2.0 * u >= bound)
            & (self._gap_before[j] + 2.0 * u >= bound)
            & (np.sqrt(here) + np.abs(u) <= self.reach_m)
        )
        return j, proven


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


def _circles_through(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Circles through triples of points (T, 3, 2): centres (T, 2), radii (T,), and whether
    each triple defines one (False where the points are nearly collinear)."""
    ax, ay, bx, by, cx, cy = (p[:, i, j] for i in range(3) for j in range(2))
    d = 2.0 * (ax * (by - cy) + bx * (cy - ay) + cx * (ay - by))
    ok = np.abs(d) >= 1e-12
    d = np.where(ok, d, 1.0)
    a2, b2, c2 = ax * ax + ay * ay, bx * bx + by * by, cx * cx + cy * cy
    ux = (a2 * (by - cy) + b2 * (cy - ay) + c2 * (ay - by)) / d
    uy = (a2 * (cx - bx) + b2 * (ax - cx) + c2 * (bx - ax)) / d
    return np.column_stack((ux, uy)), np.hypot(ax - ux, ay - uy), ok


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
    # Every trial's triple is drawn first (the same draws, in the same order, as one at a
    # time), then all circles are scored against the sample at once.
    triples = np.stack([sample[rng.choice(len(sample), 3, replace=False)] for _ in range(trials)])
    centres, radii, valid = _circles_through(triples)
    valid &= radii <= span
    if valid.any():
        centres, radii = centres[valid], radii[valid]
        dist = np.hypot(sample[:, 0] - centres[:, :1], sample[:, 1] - centres[:, 1:])
        scores = (np.abs(dist - radii[:, None]) < inlier_m).sum(axis=1)
        best = int(np.argmax(scores))  # the first of the best, as the loop kept it
        centre, radius = centres[best], float(radii[best])
    else:
        centre, radius = fit_circle(pts)
    inliers = np.ones(len(pts), dtype=bool)
    for _ in range(iterations):
        resid = np.hypot(*(pts - centre).T) - radius
        near = np.abs(resid) < inlier_m
        if near.sum() < 10:
            break
        sigma = MAD_TO_SIGMA * np.median(np.abs(resid[near]))  # about the circle: 0
        new = np.abs(resid) <= max(3.0 * sigma, inlier_m / 2.0)
        if new.sum() < 10:
            break
        inliers = new
        centre, radius = fit_circle(pts[inliers])
    return centre, radius, inliers


VERTICAL_WITHIN_DEG = 5.0
"""A pipe whose axis lies within this of the up direction is vertical (a shaft): it has no
invert, and the section's reference direction "up" is chosen across it (``_reference_up``)."""


def is_vertical(direction: np.ndarray, up_hint: np.ndarray) -> bool:
    """True when ``direction`` lies within :data:`VERTICAL_WITHIN_DEG` of ``up_hint``."""
    up = np.asarray(up_hint, dtype=np.float64)
    cos = abs(float(direction @ up)) / max(float(np.linalg.norm(up)), 1e-12)
    return cos >= math.cos(math.radians(VERTICAL_WITHIN_DEG))


def _reference_up(direction: np.ndarray) -> np.ndarray:
    """A fixed direction across a vertical axis: the world axis most perpendicular to it, made
    perpendicular (so the same shaft always gets the same section orientation)."""
    axis = np.eye(3)[int(np.argmin(np.abs(direction)))]
    up = axis - (axis @ direction) * direction
    return up / np.linalg.norm(up)


def _orthonormal_up(direction: np.ndarray, up_hint: np.ndarray) -> np.ndarray:
    if is_vertical(direction, up_hint):
        return _reference_up(direction)
    up = np.asarray(up_hint, dtype=np.float64)
    up = up - (up @ direction) * direction
    return up / np.linalg.norm(up)


def _slice_centres(
    pts: np.ndarray, axis: PipeAxis, slice_m: float, min_points: int = 200, workers: int = 1
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Robust circle centres of consecutive slices along an axis (straight or curved).

    Returns the slices' median distance along the axis (K,), their centres in the world frame
    (K, 3), radii (K,) and inlier counts (K,). With ``workers`` > 1 the slices are fitted on
    that many threads (NumPy releases the GIL in the fits' array work); each fit has its own
    seed, so the result does not depend on it.
    """
    along, plane = axis.local_coordinates(pts)
    edges = np.arange(along.min(), along.max() + slice_m, slice_m)
    order = np.argsort(along)
    bounds = np.searchsorted(along[order], edges)
    slices = [order[lo:hi] for lo, hi in itertools.pairwise(bounds) if hi - lo >= min_points]

    def fit(idx: np.ndarray) -> tuple[np.ndarray, float, np.ndarray] | None:
        try:
            return fit_circle_robust(plane[idx])
        except GeometryError:
            return None

    if workers > 1 and len(slices) > 1:
        with ThreadPoolExecutor(workers) as pool:
            fits = list(pool.map(fit, slices))
    else:
        fits = [fit(idx) for idx in slices]
    rows = []
    for idx, fitted in zip(slices, fits, strict=True):
        if fitted is None:
            continue
        c2, r, inl = fitted
        s_mid = float(np.median(along[idx]))
        rows.append((s_mid, axis.point_at(s_mid, c2[0], c2[1]), r, float(inl.sum())))
    if not rows:
        return np.empty(0), np.empty((0, 3)), np.empty(0), np.empty(0)
    s_k, c_k, r_k, w_k = zip(*rows, strict=True)
    return np.asarray(s_k), np.asarray(c_k), np.asarray(r_k), np.asarray(w_k)


def _plausible(radii: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Slices whose circle fit can be trusted: radius within 3 % of the median, and at least
    a third of the median number of inliers."""
    if len(radii) == 0:
        return np.zeros(0, dtype=bool)
    r_med, w_med = np.median(radii), np.median(weights)
    return (np.abs(radii - r_med) <= 0.03 * r_med) & (weights >= w_med / 3.0)


def _line_through(
    centres: np.ndarray, weights: np.ndarray, near_dir: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least-squares line through points: (a point on it, unit direction)."""
    cm = (centres * weights[:, None]).sum(0) / weights.sum()
    _, _, vt = np.linalg.svd((centres - cm) * np.sqrt(weights)[:, None], full_matrices=False)
    direction = vt[0] if vt[0] @ near_dir > 0 else -vt[0]
    return cm, direction / np.linalg.norm(direction)


def _centreline(
    s_k: np.ndarray,
    centres: np.ndarray,
    up_hint: np.ndarray,
    node_step_m: float,
    extend_m: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A smoothing spline through slice centres, sampled as nodes every ``node_step_m``.

    The spline's smoothing is chosen by generalised cross-validation; beyond the first and last
    centre the line continues straight along the end tangents for ``extend_m``.

    Returns nodes (K, 3), unit tangents (K, 3), unit ups (K, 3) and arc lengths (K,) measured
    from the first node.
    """
    order = np.argsort(s_k)
    s_k, centres = s_k[order], centres[order]
    splines = [make_smoothing_spline(s_k, centres[:, d]) for d in range(3)]
    grid = np.arange(s_k[0], s_k[-1] + node_step_m / 2, node_step_m)
    pos = np.column_stack([sp(grid) for sp in splines])
    tan = np.column_stack([sp.derivative()(grid) for sp in splines])
    tan /= np.linalg.norm(tan, axis=1, keepdims=True)
    steps = np.arange(1, int(extend_m / node_step_m) + 1) * node_step_m
    before = pos[0] - steps[::-1, None] * tan[0]
    after = pos[-1] + steps[:, None] * tan[-1]
    nodes = np.vstack((before, pos, after))
    tangents = np.vstack(
        (np.repeat(tan[:1], len(steps), 0), tan, np.repeat(tan[-1:], len(steps), 0))
    )
    arc = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(nodes, axis=0), axis=1))))
    ups = np.array([_orthonormal_up(t, up_hint) for t in tangents])
    return nodes, tangents, ups, arc


def fit_cylinder(
    points_m: np.ndarray, radius_m: float, *, max_points: int = 20_000, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Robust fit of a cylinder of known radius: its axis, where PCA cannot find it.

    (Over 80 lines for its reference docstring: the body is the three fits it describes.)

    PCA needs a cloud longer than it is wide; a stub scanned over 1.5 diameters, or a shaft
    seen from one station, is not. A cylinder's surface normals all lie across its axis, so
    the axis is the direction least present among the normals (Open3D estimates them), with
    normals that do not lie across it (end walls, faces) dropped and the direction found
    again. The centre in the plane across it comes from a RANSAC circle (scikit-image); then
    axis and centre are refined together by least squares with a robust loss (SciPy) on the
    points' distance from the axis against ``radius_m``. Deposits and obstacles are outliers
    of both.

    Parameters
    ----------
    points_m : (N, 3) float
        The cloud, metres.
    radius_m : float
        The pipe's nominal inner radius.

    Returns
    -------
    point_m : (3,) float
        A point on the axis.
    direction : (3,) float
        Unit direction of the axis (sign arbitrary).

    Raises
    ------
    GeometryError
        When no cylinder of that radius fits (too few points on it).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> t, s = rng.uniform(0, 2 * np.pi, 8000), rng.uniform(0, 0.6, 8000)
    >>> pts = np.column_stack((0.2 * np.cos(t), 0.2 * np.sin(t), s))  # a short vertical stub
    >>> _, d = fit_cylinder(pts, 0.2)
    >>> round(abs(float(d[2])), 3)
    1.0
    """
    import open3d as o3d
    from scipy.optimize import least_squares
    from skimage.measure import CircleModel, ransac

    pts = np.asarray(points_m, dtype=np.float64)
    rng = np.random.default_rng(seed)
    if len(pts) > max_points:
        pts = pts[rng.choice(len(pts), max_points, replace=False)]
    if len(pts) < 50:
        raise GeometryError(f"a cylinder fit needs at least 50 points, got {len(pts)}")
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius_m / 2, max_nn=30))
    normals = np.asarray(cloud.normals)
    keep = np.ones(len(normals), dtype=bool)
    direction = np.array([0.0, 0.0, 1.0])
    for _ in range(5):
        _, vectors = np.linalg.eigh(normals[keep].T @ normals[keep])
        direction = vectors[:, 0]
        keep = np.abs(normals @ direction) < math.sin(math.radians(20.0))
        if keep.sum() < 20:
            raise GeometryError("no cylinder fits the cloud: its normals agree on no axis")
    u = _reference_up(direction)
    v = np.cross(direction, u)
    xy = pts @ np.column_stack((u, v))
    tolerance = max(0.01, 0.03 * radius_m)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)  # scikit-image 0.26 renames params
        model, inliers = ransac(
            xy, CircleModel, min_samples=3, residual_threshold=tolerance, max_trials=300, rng=seed
        )
    if model is None or inliers is None or inliers.sum() < 20:
        raise GeometryError("no cylinder of the nominal diameter fits the cloud")
    centre = getattr(model, "center", None)
    centre2 = np.asarray(model.params[:2] if centre is None else centre, dtype=np.float64)
    point = centre2[0] * u + centre2[1] * v

    def residuals(x: np.ndarray) -> np.ndarray:
        d = direction + x[0] * u + x[1] * v
        d = d / np.linalg.norm(d)
        p = point + x[2] * u + x[3] * v
        rel = pts - p
        dist = np.linalg.norm(rel - np.outer(rel @ d, d), axis=1)
        return dist - radius_m

    fit = least_squares(residuals, np.zeros(4), loss="soft_l1", f_scale=tolerance)
    x = fit.x
    d = direction + x[0] * u + x[1] * v
    return point + x[2] * u + x[3] * v, d / np.linalg.norm(d)


def axis_direction(points_m: np.ndarray, nominal_diameter_m: float | None = None) -> np.ndarray:
    """The pipe's rough axis direction (sign arbitrary): PCA's first axis for a cloud longer
    than it is wide, else a cylinder fit of the nominal diameter (:func:`fit_cylinder`).

    Raises
    ------
    GeometryError
        When the cloud is not elongated and no nominal diameter is given.
    """
    pts = np.asarray(points_m, dtype=np.float64)
    sample = pts[:: max(1, len(pts) // 200_000)]
    centred = sample - sample.mean(axis=0)
    _, sing, vt = np.linalg.svd(centred, full_matrices=False)
    if sing[0] >= ELONGATION * sing[1]:
        return vt[0]
    if nominal_diameter_m is None or not math.isfinite(nominal_diameter_m):
        raise GeometryError(
            "the cloud is not elongated enough to define a pipe axis",
            hint="give nominal_diameter_m (a cylinder of that diameter is then fitted), or "
            "scan at least about two pipe diameters of length",
        )
    return fit_cylinder(sample, nominal_diameter_m / 2.0)[1]


ELONGATION = 1.5
"""PCA's first axis defines the pipe's axis when the cloud's spread along it is this many
times its spread across; a shorter cloud needs a cylinder fit (:func:`fit_cylinder`)."""


_Slices = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
"""What ``_slice_centres`` returns: each slice's place along the axis, circle centre, radius
and weight."""


def _first_direction(
    pts: np.ndarray,
    centroid: np.ndarray,
    travel_m: np.ndarray | None,
    nominal_diameter_m: float | None,
) -> np.ndarray:
    """The axis's first guess: the cloud's principal direction (or, for a cloud too short
    for it, :func:`axis_direction`), oriented along ``travel_m`` (else so that its largest
    world component is positive)."""
    _, sing, vt = np.linalg.svd(pts - centroid, full_matrices=False)
    elongated = sing[0] >= ELONGATION * sing[1]
    axis_dir = vt[0] if elongated else axis_direction(pts, nominal_diameter_m)
    if travel_m is not None and np.linalg.norm(travel_m) > 1e-9:
        if axis_dir @ travel_m < 0:
            axis_dir = -axis_dir
    elif axis_dir[np.argmax(np.abs(axis_dir))] < 0:
        axis_dir = -axis_dir
    return axis_dir


def _straight_axis(
    pts: np.ndarray,
    centroid: np.ndarray,
    axis_dir: np.ndarray,
    up_hint: np.ndarray,
    slice_m: float,
    workers: int,
) -> tuple[PipeAxis, _Slices]:
    """A straight axis refined twice: a line through the slice centres, the slices cut again
    across it. Returns the axis and its slices."""

    def straight(point: np.ndarray, d: np.ndarray) -> PipeAxis:
        return PipeAxis(origin_m=point, direction=d, up=_orthonormal_up(d, up_hint))

    axis = straight(centroid, axis_dir)
    s_k, c_k, r_k, w_k = _slice_centres(pts, axis, slice_m, workers=workers)
    for _ in range(2):
        good = _plausible(r_k, w_k)
        if good.sum() < 2:
            break
        point, axis_dir = _line_through(c_k[good], w_k[good], axis_dir)
        axis = straight(point, axis_dir)
        s_k, c_k, r_k, w_k = _slice_centres(pts, axis, slice_m, workers=workers)
    return axis, (s_k, c_k, r_k, w_k)


def _curved_axis(
    pts: np.ndarray,
    axis: PipeAxis,
    slices: _Slices,
    up_hint: np.ndarray,
    slice_m: float,
    curve_tolerance_m: float,
    node_step_m: float,
    workers: int,
) -> tuple[PipeAxis, np.ndarray]:
    """A bend or a sag: where the slice centres leave the straight axis, a smoothing spline
    through them, refined once with slices cut across it. Returns the axis (the straight one
    unchanged) and the radii of its slices.

    Slices whose circle is implausible (an end wall, a section mostly blocked) do not count,
    and one slice off the line is not a bend.
    """
    s_k, c_k, r_k, w_k = slices
    trusted = _plausible(r_k, w_k)
    if trusted.sum() < 5:
        return axis, r_k
    rel = c_k[trusted] - axis.origin_m
    off_line = np.linalg.norm(rel - np.outer(rel @ axis.direction, axis.direction), axis=1)
    if (off_line > curve_tolerance_m).sum() < 2:
        return axis, r_k
    s_k, c_k = s_k[trusted], c_k[trusted]
    for _ in range(2):
        nodes, tangents, ups, arc = _centreline(
            s_k, c_k, up_hint, node_step_m, extend_m=slice_m + 1.0
        )
        axis = PipeAxis(
            origin_m=nodes[0],
            direction=axis.direction,
            up=axis.up,
            nodes_m=nodes,
            tangents=tangents,
            ups=ups,
            arc_m=arc,
        )
        s_k, c_k, r_k, w_k = _slice_centres(pts, axis, slice_m / 2, workers=workers)
        keep = _plausible(r_k, w_k)
        s_k, c_k = s_k[keep], c_k[keep]
        if len(c_k) < 5:
            break
    return axis, r_k


def fit_axis(
    points_m: np.ndarray,
    *,
    start_m: np.ndarray | None = None,
    travel_m: np.ndarray | None = None,
    up_hint: np.ndarray = np.array([0.0, 0.0, 1.0]),
    chainage_offset_m: float = 0.0,
    direction: str = "downstream",
    slice_m: float = 0.5,
    curve_tolerance_m: float = 0.005,
    node_step_m: float = 0.05,
    max_points: int = 200_000,
    seed: int = 0,
    nominal_diameter_m: float | None = None,
    workers: int = 1,
) -> PipeAxis:
    """Fit the pipe's centreline: PCA for a first guess, then robust circle fits on slices.

    (Over 80 lines for this reference docstring only: the body is its steps,
    ``_first_direction``, ``_straight_axis``, ``_curved_axis``, then the start and chainage.)

    The circles are fitted to the wall, so deposits and obstacles do not pull the axis. When
    the slice centres deviate from a straight line by more than ``curve_tolerance_m`` (a bend
    or a sag), the centreline becomes a smoothing spline through them, refined once with slices
    cut perpendicular to it, and chainage is measured along it.

    Parameters
    ----------
    points_m : (N, 3) float
        Registered points, metres, in the common (world) frame.
    start_m : (3,) float, optional
        The sensor position at the scan's start (first frame). Chainage ``chainage_offset_m``
        is placed at its projection on the centreline. Without it, the scan starts at the end
        of the cloud with the lowest distance along the axis.
    travel_m : (3,) float, optional
        A vector along the direction the crawler moved (e.g. last minus first sensor position);
        orients the axis. Without it, the axis is oriented so that its largest world component
        is positive: arbitrary, but deterministic for a given cloud.
    up_hint : (3,) float
        Roughly "up" in the world frame (against gravity where an IMU measured it, else the
        first sensor frame's z for frame archives, a cloud's z). An axis within
        :data:`VERTICAL_WITHIN_DEG` of it is a vertical shaft: ``has_invert`` is then False
        and a reference direction across the axis stands for "up".
    chainage_offset_m : float
        Chainage of the scan's start from the upstream node.
    direction : {"downstream", "upstream"}
        The survey direction; upstream surveys count chainage down from the offset.
    slice_m : float
        Length of the slices whose circle centres define the centreline.
    curve_tolerance_m : float
        Largest deviation of the slice centres from a straight line that still counts as
        straight.
    node_step_m : float
        Spacing of a curved centreline's nodes.
    max_points : int
        The fit uses a random subsample of at most this many points.
    nominal_diameter_m : float, optional
        The pipe's nominal diameter: with it, a cloud too short for PCA (a stub, a shaft seen
        from one station) gets its axis from a cylinder fit (:func:`fit_cylinder`).
    workers : int
        Threads that fit the slices' circles (the axis is the same for any number).

    Returns
    -------
    PipeAxis

    Raises
    ------
    GeometryError
        When the cloud is too small, or not elongated enough to have an axis and no nominal
        diameter is given.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> t, x = rng.uniform(0, 2 * np.pi, 20000), rng.uniform(0, 3, 20000)
    >>> pts = np.column_stack((x, 0.25 * np.cos(t), 0.25 * np.sin(t)))
    >>> axis = fit_axis(pts, start_m=np.zeros(3), travel_m=np.array([1.0, 0, 0]))
    >>> (np.round(axis.direction, 3) + 0.0).tolist(), round(axis.radius_m, 3)
    ([1.0, 0.0, 0.0], 0.25)
    """
    pts = np.asarray(points_m, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise GeometryError(f"points must have shape (N, 3), got {pts.shape}")
    if len(pts) < 100:
        raise GeometryError(f"too few points to fit a pipe axis: {len(pts)}")
    rng = np.random.default_rng(seed)
    if len(pts) > max_points:
        pts = pts[rng.choice(len(pts), max_points, replace=False)]
    up_hint = np.asarray(up_hint, dtype=np.float64)
    centroid = pts.mean(axis=0)
    axis_dir = _first_direction(pts, centroid, travel_m, nominal_diameter_m)
    axis, slices = _straight_axis(pts, centroid, axis_dir, up_hint, slice_m, workers)
    axis, r_k = _curved_axis(
        pts, axis, slices, up_hint, slice_m, curve_tolerance_m, node_step_m, workers
    )
    radius = float(np.median(r_k)) if len(r_k) else float("nan")
    vertical = is_vertical(axis.direction, up_hint)
    if start_m is not None:
        start_along = float(axis.distance_along(np.asarray(start_m, dtype=np.float64)[None])[0])
    else:
        start_along = float(axis.distance_along(pts).min())
    origin = axis.point_at(start_along, 0.0, 0.0)
    return PipeAxis(
        origin_m=origin,
        direction=axis.direction,
        up=axis.up,
        chainage_offset_m=float(chainage_offset_m),
        chainage_sign=-1.0 if direction == "upstream" else 1.0,
        radius_m=radius,
        nodes_m=axis.nodes_m,
        tangents=axis.tangents,
        ups=axis.ups,
        arc_m=None if axis.arc_m is None else axis.arc_m - start_along,
        has_invert=not vertical,
    )
