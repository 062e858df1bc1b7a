"""The local map and the ICP engines that align a frame to it.

Every engine takes the map, the frame's points (sensor frame) and a prior pose, and returns
the pose ICP converged to; what happens next (fusion with the odometer and the IMU, quality)
is the same for all of them (``pipescan.core.registration.fusion``).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from pipescan.core.registration.fusion import FACING_COS
from pipescan.core.registration.params import RegistrationParams
from pipescan.core.registration.preprocess import NORMAL_NEIGHBOURS, seen_twice, voxel_downsample


def transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4×4 pose to (N, 3) points."""
    return points @ T[:3, :3].T + T[:3, 3]


class LocalMap:
    """The last keyframes, merged, voxelised, with normals and the engines' search structures.

    A keyframe is built from several registered frames and keeps only what at least two of
    them saw (``preprocess.seen_twice``).
    """

    def __init__(self, params: RegistrationParams) -> None:
        import small_gicp

        self.params = params
        self.keyframes: deque[np.ndarray] = deque(maxlen=params.map_keyframes)
        self.points = np.empty((0, 3))
        self.normals = np.empty((0, 3))
        self.surface_variation = np.empty(0)
        self.axis: np.ndarray | None = None
        self._sg = small_gicp
        self.sg_cloud: Any = None
        self.sg_tree: Any = None
        self._cache: dict[str, Any] = {}

    def __len__(self) -> int:
        return len(self.points)

    def clear(self) -> None:
        """Forget every keyframe (after a slide: the map holds misplaced frames)."""
        self.keyframes.clear()
        self.points = np.empty((0, 3))
        self.normals = np.empty((0, 3))
        self._cache.clear()

    def add_keyframe(self, frames_world: list[np.ndarray], forward_world: np.ndarray) -> None:
        """Add a keyframe made of registered, downsampled frames (world frame);
        ``forward_world`` orients the pipe axis (the sensor's x) until there is one."""
        sg, p = self._sg, self.params
        keyframe = seen_twice(frames_world, p.voxel_m)
        if len(keyframe) == 0:
            return
        self.keyframes.append(voxel_downsample(keyframe, p.voxel_m))
        merged = np.vstack(self.keyframes)
        self.points = voxel_downsample(merged, p.voxel_m) if len(self.keyframes) > 1 else merged
        self.sg_cloud = sg.PointCloud(self.points)
        self.sg_tree = sg.KdTree(self.sg_cloud, num_threads=p.num_threads)
        if p.method == "gicp":
            sg.estimate_normals_covariances(
                self.sg_cloud, self.sg_tree, NORMAL_NEIGHBOURS, p.num_threads
            )
        else:
            sg.estimate_normals(self.sg_cloud, self.sg_tree, NORMAL_NEIGHBOURS, p.num_threads)
        self.normals = self.sg_cloud.normals()[:, :3].copy()
        self.axis = self.axis_world(self.axis if self.axis is not None else forward_world)
        # Only points facing along the axis can inform it (fusion.axial_information): the
        # surface test is run on those alone.
        self.surface_variation = np.ones(len(self.points))
        facing = np.flatnonzero(np.abs(self.normals @ self.axis) >= FACING_COS)
        if len(facing):
            self.surface_variation[facing] = _surface_variation(
                self.points, facing, self.sg_tree, p.num_threads
            )
        self._cache.clear()

    def nearest(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Index of and distance to the closest map point, (K,) each."""
        idx, sq = self.sg_tree.batch_nearest_neighbor_search(points_world, self.params.num_threads)
        return np.asarray(idx, dtype=np.int64), np.sqrt(np.asarray(sq))

    def cached(self, key: str, build: Callable[[], Any]) -> Any:
        if key not in self._cache:
            self._cache[key] = build()
        return self._cache[key]

    def axis_world(self, forward_world: np.ndarray) -> np.ndarray:
        """The pipe axis: the direction the wall's normals avoid (weakest eigenvector of their
        scatter matrix), pointing along ``forward_world``."""
        axis = np.linalg.eigh(self.normals.T @ self.normals)[1][:, 0]
        return axis if axis @ forward_world >= 0 else -axis


_SURFACE_NEIGHBOURS = 24


def _surface_variation(
    points: np.ndarray, which: np.ndarray, tree: Any, num_threads: int
) -> np.ndarray:
    """``λ_min / (λ1 + λ2 + λ3)`` of the neighbourhood covariance of ``points[which]``: near 0
    on a surface, up to 1/3 in a blob (a cluster of spurious returns, a corner)."""
    idx, _ = tree.batch_knn_search(points[which], _SURFACE_NEIGHBOURS, num_threads)
    nb = points[np.asarray(idx, dtype=np.int64)]
    nb = nb - nb.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", nb, nb)
    evals = np.linalg.eigvalsh(cov)
    return evals[:, 0] / np.maximum(evals.sum(axis=1), 1e-30)


# --------------------------------------------------------------------------- the paper's ICP


def kabsch(source_m: np.ndarray, target_m: np.ndarray) -> np.ndarray:
    """Best rigid transform mapping ``source`` onto ``target`` (paired rows), least squares.

    The paper's step: centre both sets, ``W = Σ x'_i y'_iᵀ``, SVD, rotation from the singular
    vectors. A reflection (det = −1) is corrected by flipping the last singular vector, as any
    correct Kabsch solution must.

    Parameters
    ----------
    source_m, target_m : (N, 3) float
        Corresponding points.

    Returns
    -------
    (4, 4) float
        ``T`` with ``target ≈ R @ source + t``.
    """
    src_c = source_m.mean(axis=0)
    dst_c = target_m.mean(axis=0)
    w = (source_m - src_c).T @ (target_m - dst_c)
    u, _, vt = np.linalg.svd(w)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    rot = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    t = np.eye(4)
    t[:3, :3] = rot
    t[:3, 3] = dst_c - rot @ src_c
    return t


def icp_point_to_point(
    source_m: np.ndarray,
    target_tree: cKDTree,
    target_m: np.ndarray,
    init: np.ndarray,
    *,
    max_correspondence_m: float,
    max_iterations: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The paper's point-to-point ICP: closest points, then the Kabsch step, iterated.

    Returns the pose and the matched (source index, target index) pairs of the last iteration.
    """
    T = init.copy()
    src_idx = np.empty(0, dtype=np.int64)
    tgt_idx = np.empty(0, dtype=np.int64)
    for _ in range(max_iterations):
        moved = transform(T, source_m)
        dist, idx = target_tree.query(moved, distance_upper_bound=max_correspondence_m)
        ok = np.isfinite(dist)
        if ok.sum() < 6:
            break
        src_idx, tgt_idx = np.flatnonzero(ok), idx[ok]
        step = kabsch(moved[src_idx], target_m[tgt_idx])
        T = step @ T
        if np.linalg.norm(step[:3, 3]) < 1e-5 and np.abs(step[:3, :3] - np.eye(3)).max() < 1e-6:
            break
    return T, src_idx, tgt_idx


# --------------------------------------------------------------------------- engines


def small_gicp_source(m: LocalMap, source: np.ndarray) -> Any:
    """A frame as small_gicp aligns it: its cloud, with covariances for GICP."""
    sg, p = m._sg, m.params
    cloud = sg.PointCloud(source)
    if p.method == "gicp":
        tree = sg.KdTree(cloud, num_threads=p.num_threads)
        sg.estimate_covariances(cloud, tree, NORMAL_NEIGHBOURS, p.num_threads)
    return cloud


def small_gicp_steps(
    m: LocalMap, cloud: Any, init: np.ndarray, iterations: int
) -> tuple[np.ndarray, bool]:
    """At most ``iterations`` of small_gicp from ``init``; the pose, and whether a step fell
    below both convergence thresholds."""
    sg, p = m._sg, m.params
    result = sg.align(
        m.sg_cloud,
        cloud,
        m.sg_tree,
        init_T_target_source=init,
        registration_type="GICP" if p.method == "gicp" else "PLANE_ICP",
        max_correspondence_distance=p.max_correspondence_m,
        num_threads=p.num_threads,
        max_iterations=iterations,
        rotation_epsilon=p.converged_rotation_rad,
        translation_epsilon=p.converged_translation_m,
    )
    return np.asarray(result.T_target_source), bool(result.converged)


def plane_icp_steps(
    m: LocalMap, source: np.ndarray, init: np.ndarray, iterations: int
) -> np.ndarray:
    """At most ``iterations`` of small_gicp's point-to-plane ICP of ``source`` (sensor frame)
    from ``init`` against the map's normals: no neighbourhood of the source is needed (GICP's
    covariances), which is most of what aligning a few hundred points costs."""
    sg, p = m._sg, m.params
    result = sg.align(
        m.sg_cloud,
        sg.PointCloud(source),
        m.sg_tree,
        init_T_target_source=init,
        registration_type="PLANE_ICP",
        max_correspondence_distance=p.max_correspondence_m,
        num_threads=p.num_threads,
        max_iterations=iterations,
        rotation_epsilon=p.converged_rotation_rad,
        translation_epsilon=p.converged_translation_m,
    )
    return np.asarray(result.T_target_source)


def _align_small_gicp(m: LocalMap, source: np.ndarray, init: np.ndarray) -> np.ndarray:
    return small_gicp_steps(m, small_gicp_source(m, source), init, m.params.max_iterations)[0]


def _open3d_estimation(params: RegistrationParams):
    import open3d as o3d

    reg = o3d.pipelines.registration
    # Tukey's biweight ignores residuals beyond its width: spurious returns and mixed pixels
    # that survived the filters, and surfaces the map does not hold yet.
    return reg.TransformationEstimationPointToPlane(reg.TukeyLoss(params.max_correspondence_m / 2))


def _align_open3d(m: LocalMap, source: np.ndarray, init: np.ndarray) -> np.ndarray:
    import open3d as o3d

    def target():
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(m.points))
        pcd.normals = o3d.utility.Vector3dVector(m.normals)
        return pcd

    reg = o3d.pipelines.registration
    result = reg.registration_icp(
        o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source)),
        m.cached("open3d", target),
        m.params.max_correspondence_m,
        init,
        _open3d_estimation(m.params),
        reg.ICPConvergenceCriteria(max_iteration=m.params.max_iterations),
    )
    return np.asarray(result.transformation).copy()


def _align_open3d_tensor(m: LocalMap, source: np.ndarray, init: np.ndarray) -> np.ndarray:
    import open3d as o3d

    tensor = o3d.core.Tensor.from_numpy

    def target():
        pcd = o3d.t.geometry.PointCloud(tensor(np.ascontiguousarray(m.points)))
        pcd.point.normals = tensor(np.ascontiguousarray(m.normals))
        return pcd

    reg = o3d.t.pipelines.registration
    result = reg.icp(
        o3d.t.geometry.PointCloud(tensor(np.ascontiguousarray(source))),
        m.cached("open3d_tensor", target),
        m.params.max_correspondence_m,
        tensor(np.ascontiguousarray(init)),
        reg.TransformationEstimationPointToPlane(
            reg.robust_kernel.RobustKernel(
                reg.robust_kernel.RobustKernelMethod.TukeyLoss,
                m.params.max_correspondence_m / 2,
            )
        ),
        reg.ICPConvergenceCriteria(max_iteration=m.params.max_iterations),
    )
    return result.transformation.numpy().astype(np.float64)


def _align_point_to_point(m: LocalMap, source: np.ndarray, init: np.ndarray) -> np.ndarray:
    tree = m.cached("kdtree", lambda: cKDTree(m.points))
    T, _, _ = icp_point_to_point(
        source,
        tree,
        m.points,
        init,
        max_correspondence_m=m.params.max_correspondence_m,
        max_iterations=m.params.max_iterations,
    )
    return T


Aligner = Callable[[LocalMap, np.ndarray, np.ndarray], np.ndarray]


def aligner(params: RegistrationParams) -> Aligner:
    """The function that runs ICP for ``params`` (engine and method)."""
    if params.method == "point_to_point":
        return _align_point_to_point
    return {
        "small_gicp": _align_small_gicp,
        "open3d": _align_open3d,
        "open3d_tensor": _align_open3d_tensor,
    }[params.engine]
