"""The ``grid`` contour method: the paper's grid partition.

Cell size from eq. 9, cell counts from eq. 10, isolated empty cells filled, boundary cells with
more than one empty neighbour of the 8, the k-nearest-neighbour angle-gap test of eqs. 11-13,
k-d tree ordering, smoothing and interpolation.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from pipescan.core.contour.base import ContourResult, polygon_area, radii_of_polygon
from pipescan.core.defaults import GRID_K, GRID_S_THRESHOLD_RAD
from pipescan.core.errors import GeometryError

if TYPE_CHECKING:
    from pipescan.core.contour.polar import PolarProfile


@dataclass(frozen=True)
class GridParams:
    """Parameters of the paper's grid method.

    Attributes
    ----------
    k : int
        Neighbours in the angle-gap test (eqs. 11-13).
    s_threshold_rad : float
        A candidate is a boundary point when the standard deviation S of its angle gaps exceeds
        this. Uniform surroundings give S near 0.5 * 2π/k for random points; an edge point has
        one gap of about π and S well above 2π/k.
    closing : {"circular", "paper"}
        The last gap: ``2π − (α'_{k−1} − α'_1)`` (the usual circular form, default) or the
        paper's ``α'_{k−1} − α'_1`` as printed.
    downsample_m : float
        The projected points are thinned to one per square of this size first (the paper's
        0.2 m interval is taken to be a typo for a much smaller value).
    smooth_window : int
        Moving-average window, in contour points, applied to the ordered boundary.
    resample_m : float
        Spacing of the interpolated contour.
    max_jump_m : float
        The nearest-neighbour chain may cross a gap in the data up to this long (e.g. between a
        wall and an obstacle that hides part of it); a longer jump ends the chain.
    min_chain_share : float
        A chain that ends before it has passed through this share of the boundary cells has
        not gone round the section (it ran along a deposit's top and back, say): the method
        found no contour, rather than a small one.
    """

    k: int = GRID_K
    s_threshold_rad: float = GRID_S_THRESHOLD_RAD
    closing: Literal["circular", "paper"] = "circular"
    downsample_m: float = 0.003
    smooth_window: int = 5
    resample_m: float = 0.005
    max_jump_m: float = 0.10
    min_chain_share: float = 0.8


def _thin(points_2d: np.ndarray, cell_m: float) -> np.ndarray:
    if cell_m <= 0 or len(points_2d) == 0:
        return points_2d
    keys = np.floor(points_2d / cell_m).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return points_2d[np.sort(first)]


def grid_cell_size(points_2d: np.ndarray) -> tuple[float, int, int, np.ndarray]:
    """Equations 9 and 10: cell size ``L = sqrt(Δx Δy / n)`` and the cell counts.

    Returns
    -------
    L : float
        Cell size, metres.
    x_num, y_num : int
        ``floor(Δ / L) + 1``.
    lower : (2,) float
        The bounding box's lower corner.
    """
    lower = points_2d.min(axis=0)
    span = points_2d.max(axis=0) - lower
    n = len(points_2d)
    cell = float(np.sqrt(span[0] * span[1] / n))
    if not np.isfinite(cell) or cell <= 0:
        raise GeometryError("the section's points are collinear or too few for a grid")
    x_num = int(np.floor(span[0] / cell)) + 1
    y_num = int(np.floor(span[1] / cell)) + 1
    return cell, x_num, y_num, lower


def angle_gap_std(
    points_2d: np.ndarray, candidates: np.ndarray, k: int, closing: str
) -> np.ndarray:
    """Equations 11-13: the standard deviation S of the sorted angle gaps around each candidate.

    For candidate P with k nearest neighbours Q_1..Q_k (Q_1 the nearest), α_j is the angle from
    PQ_1 to PQ_j, counter-clockwise in [0, 2π). Sorted, the gaps are ``D_i = α'_{i+1} − α'_i``,
    closed by ``2π − (α'_k − α'_1)`` (``closing="circular"``) or by ``α'_k − α'_1`` as the paper
    prints it (``closing="paper"``). ``S = sqrt(Σ (D_i − D̄)² / (k − 1))``.

    Returns
    -------
    (C,) float
        S for each candidate index.
    """
    tree = cKDTree(points_2d)
    kk = min(k + 1, len(points_2d))
    _, nbr = tree.query(points_2d[candidates], k=kk)
    vec = points_2d[nbr[:, 1:]] - points_2d[candidates][:, None, :]
    ang = np.arctan2(vec[..., 1], vec[..., 0])
    alpha = np.sort(np.mod(ang - ang[:, :1], 2.0 * np.pi), axis=1)
    gaps = np.diff(alpha, axis=1)
    span = alpha[:, -1] - alpha[:, 0]
    last = 2.0 * np.pi - span if closing == "circular" else span
    d = np.concatenate((gaps, last[:, None]), axis=1)
    dof = max(d.shape[1] - 1, 1)
    return np.sqrt(((d - d.mean(axis=1, keepdims=True)) ** 2).sum(axis=1) / dof)


def _order_nearest_neighbour(points_2d: np.ndarray, max_jump_m: float) -> np.ndarray:
    """Chain points by repeated nearest unvisited neighbour (a k-d tree query each step).

    Starts at the lowest point. The chain ends when the nearest unvisited point is further than
    ``max_jump_m`` and five median steps: such points are off the contour, or were passed by,
    and joining them would cut across the section.
    """
    n = len(points_2d)
    tree = cKDTree(points_2d)
    visited = np.zeros(n, dtype=bool)
    current = int(np.argmin(points_2d[:, 1]))
    order = [current]
    visited[current] = True
    steps: list[float] = []
    k = min(16, n)
    while len(order) < n:
        dist, idx = tree.query(points_2d[current], k=k)
        dist, idx = np.atleast_1d(dist), np.atleast_1d(idx)
        free = ~visited[idx]
        if free.any():
            j = int(np.argmax(free))
            nxt, step = int(idx[j]), float(dist[j])
        else:
            remaining = np.flatnonzero(~visited)
            d = np.hypot(*(points_2d[remaining] - points_2d[current]).T)
            j = int(np.argmin(d))
            nxt, step = int(remaining[j]), float(d[j])
            if k < n:
                k = min(2 * k, n)
        if len(steps) > 10 and step > max(5.0 * float(np.median(steps)), max_jump_m):
            break
        steps.append(step)
        visited[nxt] = True
        order.append(nxt)
        current = nxt
    return points_2d[np.asarray(order)]


def _smooth_closed(points_2d: np.ndarray, window: int) -> np.ndarray:
    if window <= 1 or len(points_2d) < 2 * window:
        return points_2d
    kernel = np.ones(window) / window
    pad = window
    wrapped = np.concatenate((points_2d[-pad:], points_2d, points_2d[:pad]))
    out = np.column_stack(
        [np.convolve(wrapped[:, i], kernel, mode="same")[pad:-pad] for i in range(2)]
    )
    return out


def _resample_closed(points_2d: np.ndarray, spacing_m: float) -> np.ndarray:
    closed = np.vstack((points_2d, points_2d[:1]))
    seg = np.hypot(*np.diff(closed, axis=0).T)
    s = np.concatenate(([0.0], np.cumsum(seg)))
    if s[-1] <= 0:
        return points_2d
    n = max(int(s[-1] / spacing_m), 8)
    t = np.linspace(0.0, s[-1], n, endpoint=False)
    return np.column_stack((np.interp(t, s, closed[:, 0]), np.interp(t, s, closed[:, 1])))


@dataclass(frozen=True)
class GridContour:
    """Result of the grid method: the contour and the intermediate sets, for inspection."""

    polygon: np.ndarray  # (M, 2) ordered, smoothed, resampled
    boundary_points: np.ndarray  # (K, 2) points that passed the angle-gap test
    cell_size_m: float


def grid_contour(points_2d: np.ndarray, params: GridParams = GridParams()) -> GridContour:
    """The paper's grid-partition contour of a section's inner wall.

    (Over 80 lines for its docstring: the body is the paper's steps in its order, the grid,
    the open region round the centre, its boundary cells, the chain and its smoothing.)

    Parameters
    ----------
    points_2d : (N, 2) float
        Projected, denoised section points, metres, with the pipe axis at the origin.
    params : GridParams

    Returns
    -------
    GridContour

    Raises
    ------
    GeometryError
        When there are too few points, or no inner boundary can be found.

    Notes
    -----
    A cross-section is a ring of points, so it has two boundaries, inner and outer. The paper
    wants the inner one (the open area), so boundary cells are taken only where they touch the
    empty region that holds the pipe centre. That is the one interpretation added to the
    paper's steps.
    """
    pts = _thin(np.asarray(points_2d, dtype=np.float64), params.downsample_m)
    if len(pts) < max(params.k + 1, 30):
        raise GeometryError(f"too few points for the grid method: {len(pts)}")
    cell, x_num, y_num, lower = grid_cell_size(pts)
    ij = np.floor((pts - lower) / cell).astype(np.int64)
    ij[:, 0] = np.clip(ij[:, 0], 0, x_num - 1)
    ij[:, 1] = np.clip(ij[:, 1], 0, y_num - 1)
    occupied = np.zeros((x_num, y_num), dtype=bool)
    occupied[ij[:, 0], ij[:, 1]] = True

    # Fill isolated empty cells (holes in the sampling, not in the pipe): an empty cell with at
    # least 6 of its 8 neighbours occupied.
    eight = np.ones((3, 3), dtype=int)
    eight[1, 1] = 0
    occ_nbrs = ndimage.convolve(occupied.astype(int), eight, mode="constant", cval=0)
    occupied = occupied | (occ_nbrs >= 6)

    empty = ~occupied
    empty_nbrs = ndimage.convolve(empty.astype(int), eight, mode="constant", cval=1)
    boundary = occupied & (empty_nbrs > 1)

    # The empty region that holds the pipe centre is the open area.
    labels, _ = ndimage.label(empty)
    centre_ij = np.floor((np.zeros(2) - lower) / cell).astype(int)
    centre_ij = np.clip(centre_ij, 0, [x_num - 1, y_num - 1])
    label = labels[centre_ij[0], centre_ij[1]]
    if label == 0:
        # The centre cell is occupied (a heavily blocked section): take the nearest empty cell.
        e = np.argwhere(empty)
        if len(e) == 0:
            raise GeometryError("the grid has no empty cell: no open area")
        near = e[np.argmin(((e - centre_ij) ** 2).sum(axis=1))]
        label = labels[near[0], near[1]]
    interior = labels == label
    touches_interior = ndimage.binary_dilation(interior, structure=np.ones((3, 3), dtype=bool))
    inner_boundary = boundary & touches_interior

    candidates = np.flatnonzero(inner_boundary[ij[:, 0], ij[:, 1]])
    if len(candidates) < 8:
        raise GeometryError("the grid method found no inner boundary")
    s = angle_gap_std(pts, candidates, params.k, params.closing)
    passed = candidates[s > params.s_threshold_rad]
    edge = pts[passed]
    if len(edge) < 8:
        raise GeometryError("no point passed the angle-gap boundary test")
    # A noisy wall leaves a band of boundary points two or three deep; a nearest-neighbour
    # chain through a band runs out along one side and back along the other. One point per
    # boundary cell (the mean of its boundary points) makes the chain one cell wide.
    cell_id = ij[passed, 0] * y_num + ij[passed, 1]
    _, inverse, counts = np.unique(cell_id, return_inverse=True, return_counts=True)
    per_cell = np.zeros((len(counts), 2))
    np.add.at(per_cell, inverse.ravel(), edge)
    per_cell /= counts[:, None]
    ordered = _order_nearest_neighbour(per_cell, max_jump_m=max(4.0 * cell, params.max_jump_m))
    if len(ordered) < params.min_chain_share * len(per_cell):
        raise GeometryError(
            f"the boundary chain ended after {len(ordered)} of {len(per_cell)} boundary cells:"
            " it did not go round the section"
        )
    smoothed = _smooth_closed(ordered, params.smooth_window)
    polygon = _resample_closed(smoothed, params.resample_m)
    return GridContour(polygon=polygon, boundary_points=edge, cell_size_m=cell)


def contour(points: np.ndarray, profile: PolarProfile, params: GridParams) -> ContourResult:
    """The grid method on a section's points, with its own ``params``; radii at the
    profile's angles.

    Raises
    ------
    GeometryError
        When the method finds no closed inner contour (see :func:`grid_contour`).
    """
    polygon = grid_contour(points[:, :2], params).polygon
    return ContourResult(
        polygon_m=polygon,
        area_m2=polygon_area(polygon),
        radii_m=radii_of_polygon(polygon, profile.angles_rad),
    )
