"""Frame registration: odometer-initialised ICP that holds where a smooth pipe cannot.

In a smooth straight pipe, ICP cannot tell where along the axis one frame sits relative to the
next, nor how it is rolled about the axis: the cost is flat in those directions. pipescan finds
them from the eigenvalues of the point-to-plane Hessian and keeps the prior (the odometer along
the axis, the previous attitude for roll) there, letting the geometry decide only the directions
it constrains ("solution remapping").

Poses are 4×4 matrices ``T_world_frame`` mapping frame (sensor) coordinates into the world
frame, which is the first frame's sensor frame.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from pipescan.core.errors import RegistrationError
from pipescan.core.model import FrameQuality

RegistrationMethod = Literal["point_to_plane", "point_to_point"]
REGISTRATION_METHODS: tuple[str, ...] = ("point_to_plane", "point_to_point")


@dataclass(frozen=True)
class RegistrationParams:
    """Parameters of frame registration.

    Attributes
    ----------
    method : {"point_to_plane", "point_to_point"}
        ``point_to_plane`` (default) with degeneracy handling, or the paper's point-to-point
        ICP with the Kabsch/SVD step.
    voxel_m : float
        Voxel size for downsampling each frame.
    max_range_m : float
        Points further than this from the sensor are left out of registration (grazing,
        sparse and noisy at range).
    max_correspondence_m : float
        ICP correspondence distance.
    max_iterations : int
    keyframe_distance_m : float
        A frame becomes a keyframe of the local map once the sensor moved this far.
    map_keyframes : int
        Keyframes kept in the local map.
    degeneracy_ratio : float
        A direction of the (unit-balanced) Hessian whose eigenvalue is below this share of the
        largest is degenerate; there the prior is kept. 0.01 holds a featureless pipe to the
        odometer while leaving pitch and yaw free (0.03 already froze them and let the
        attitude drift by 1-2° over 2.5 m of the simulator's scans).
    """

    method: RegistrationMethod = "point_to_plane"
    voxel_m: float = 0.03
    max_range_m: float = 6.0
    max_correspondence_m: float = 0.08
    max_iterations: int = 15
    keyframe_distance_m: float = 0.15
    map_keyframes: int = 8
    degeneracy_ratio: float = 0.01


@dataclass(frozen=True)
class Trajectory:
    """Poses of consecutive frames and their registration quality.

    Attributes
    ----------
    T_world_frame : (F, 4, 4) float
        Poses; the first is the identity unless the trajectory was chained.
    quality : tuple of FrameQuality
        One per frame (the first frame's fitness is 1 by definition).
    frame_indices : tuple of int
        Archive frame indices of the poses.
    """

    T_world_frame: np.ndarray
    quality: tuple[FrameQuality, ...]
    frame_indices: tuple[int, ...]

    def positions_m(self) -> np.ndarray:
        """Sensor positions in the world frame, (F, 3)."""
        return self.T_world_frame[:, :3, 3]


def preprocess_frame(points_m: np.ndarray, params: RegistrationParams) -> np.ndarray:
    """Range-crop and voxel-downsample a frame; returns (K, 3) float64 (sensor frame)."""
    pts = np.asarray(points_m, dtype=np.float64)
    rng = np.einsum("ij,ij->i", pts, pts)
    pts = pts[rng <= params.max_range_m**2]
    if len(pts) == 0:
        return pts
    keys = np.floor(pts / params.voxel_m).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inverse.ravel(), pts)
    return sums / counts[:, None]


def estimate_normals(points_m: np.ndarray, *, k: int = 12) -> np.ndarray:
    """Unit normals from the k-neighbourhood covariance, (N, 3)."""
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points_m))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=k))
    return np.asarray(pcd.normals).copy()


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


def _transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ T[:3, :3].T + T[:3, 3]


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
        moved = _transform(T, source_m)
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


def point_to_plane_hessian(source_world_m: np.ndarray, target_normals: np.ndarray) -> np.ndarray:
    """Gauss-Newton Hessian ``Σ J_iᵀ J_i`` of point-to-plane ICP, (6, 6), order (rot, trans).

    ``J_i = [(p_i × n_i)ᵀ, n_iᵀ]`` for a source point p_i (world frame) matched to a target
    point with normal n_i. Rotation is about the world origin; callers that compare it with
    translation should pass points centred on the sensor.
    """
    j = np.hstack((np.cross(source_world_m, target_normals), target_normals))
    return j.T @ j


def _small_motion(T: np.ndarray) -> np.ndarray:
    """(rotation vector, translation) of a small relative motion."""
    return np.concatenate((Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]))


def _from_small_motion(x: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(x[:3]).as_matrix()
    T[:3, 3] = x[3:]
    return T


class FrameRegistrar:
    """Streaming frame-to-local-map registration.

    Feed frames in order with ``add``; each returns the frame's pose and quality. Only the
    downsampled keyframes of the local map are kept in memory, never the full frames.

    Examples
    --------
    >>> reg = FrameRegistrar(RegistrationParams())          # doctest: +SKIP
    >>> for pts, odo in frames:                              # doctest: +SKIP
    ...     T_world_frame, quality = reg.add(pts, odo)
    """

    def __init__(self, params: RegistrationParams = RegistrationParams()) -> None:
        self.params = params
        self._keyframes: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=params.map_keyframes)
        self._map_points: np.ndarray | None = None
        self._map_normals: np.ndarray | None = None
        self._map_tree: cKDTree | None = None
        self._o3d_target = None
        self._poses: list[np.ndarray] = []
        self._odometer: list[float | None] = []
        self._last_key_position: np.ndarray | None = None
        self._axis_world: np.ndarray | None = None
        self.count = 0

    # -- local map --------------------------------------------------------------------------
    def _add_keyframe(self, points_sensor: np.ndarray, T_world_frame: np.ndarray) -> None:
        normals = estimate_normals(points_sensor) @ T_world_frame[:3, :3].T
        self._keyframes.append((_transform(T_world_frame, points_sensor), normals))
        self._map_points = np.vstack([k[0] for k in self._keyframes])
        self._map_normals = np.vstack([k[1] for k in self._keyframes])
        self._map_tree = cKDTree(self._map_points)
        self._o3d_target = None
        self._last_key_position = T_world_frame[:3, 3].copy()
        # The pipe axis is the direction the wall's normals avoid: the weakest eigenvector of
        # their scatter matrix.
        scatter = self._map_normals.T @ self._map_normals
        axis = np.linalg.eigh(scatter)[1][:, 0]
        forward = T_world_frame[:3, 0]
        self._axis_world = axis if axis @ forward >= 0 else -axis

    def _target(self):
        import open3d as o3d

        if self._o3d_target is None:
            pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self._map_points))
            pcd.normals = o3d.utility.Vector3dVector(self._map_normals)
            self._o3d_target = pcd
        return self._o3d_target

    # -- prediction -------------------------------------------------------------------------
    def _predict(self, odometer_m: float | None) -> np.ndarray:
        prev = self._poses[-1]
        pred = prev.copy()
        prev_odo = self._odometer[-1]
        if odometer_m is not None and prev_odo is not None and self._axis_world is not None:
            pred[:3, 3] = prev[:3, 3] + (odometer_m - prev_odo) * self._axis_world
        elif len(self._poses) >= 2:
            # No odometer: constant velocity.
            delta = np.linalg.inv(self._poses[-2]) @ prev
            pred = prev @ delta
        return pred

    # -- one frame --------------------------------------------------------------------------
    def add(
        self, points_sensor_m: np.ndarray, odometer_m: float | None = None
    ) -> tuple[np.ndarray, FrameQuality]:
        """Register the next frame.

        Parameters
        ----------
        points_sensor_m : (N, 3) float
            The frame in sensor coordinates, metres.
        odometer_m : float, optional
            The crawler's cable-counter reading at this frame.

        Returns
        -------
        T_world_frame : (4, 4) float
        quality : FrameQuality

        Raises
        ------
        RegistrationError
            When the frame leaves too few points to register (after range cropping).
        """
        p = self.params
        index = self.count
        pts = preprocess_frame(points_sensor_m, p)
        if len(pts) < 50:
            raise RegistrationError(
                f"frame {index} has only {len(pts)} points within {p.max_range_m} m after "
                "downsampling; it cannot be registered",
                hint="check the frame, or raise max_range_m",
            )
        if not self._poses:
            T = np.eye(4)
            quality = FrameQuality(index=index, fitness=1.0, rmse_m=0.0, degenerate=False)
            self._add_keyframe(pts, T)
        else:
            T, quality = self._register(pts, self._predict(odometer_m), index)
            assert self._last_key_position is not None
            if np.linalg.norm(T[:3, 3] - self._last_key_position) >= p.keyframe_distance_m:
                self._add_keyframe(pts, T)
        self._poses.append(T)
        self._odometer.append(odometer_m)
        self.count += 1
        return T, quality

    def _register(
        self, pts: np.ndarray, pred: np.ndarray, index: int
    ) -> tuple[np.ndarray, FrameQuality]:
        p = self.params
        assert self._map_points is not None and self._map_tree is not None
        if p.method == "point_to_point":
            T, src_idx, tgt_idx = icp_point_to_point(
                pts,
                self._map_tree,
                self._map_points,
                pred,
                max_correspondence_m=p.max_correspondence_m,
                max_iterations=p.max_iterations,
            )
        else:
            import open3d as o3d

            reg = o3d.pipelines.registration
            source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
            result = reg.registration_icp(
                source,
                self._target(),
                p.max_correspondence_m,
                pred,
                reg.TransformationEstimationPointToPlane(),
                reg.ICPConvergenceCriteria(max_iteration=p.max_iterations),
            )
            T = np.asarray(result.transformation).copy()
            corr = np.asarray(result.correspondence_set)
            src_idx = corr[:, 0] if len(corr) else np.empty(0, dtype=np.int64)
            tgt_idx = corr[:, 1] if len(corr) else np.empty(0, dtype=np.int64)
        if len(src_idx) < 30:
            raise RegistrationError(
                f"frame {index}: ICP found only {len(src_idx)} correspondences",
                hint="the frame does not overlap the previous ones; check frame order",
            )

        # Degeneracy, from the Gauss-Newton Hessian about the predicted sensor position. The
        # rotation part is scaled by the points' RMS distance so that both parts are in metres
        # and one eigenvalue ratio means the same for both: in a smooth pipe the two weak
        # modes are the translation along the axis and the roll about the axis (a rotation
        # about the sensor combined with a shift, since the sensor is off the axis).
        centre = pred[:3, 3]
        src_world = _transform(T, pts[src_idx]) - centre
        normals = self._map_normals[tgt_idx]
        length = float(np.sqrt(np.mean(np.einsum("ij,ij->i", src_world, src_world))))
        scale = np.array([length] * 3 + [1.0] * 3)
        hessian = point_to_plane_hessian(src_world, normals) / np.outer(scale, scale)
        evals, evecs = np.linalg.eigh(hessian)
        weak = evecs[:, evals < p.degeneracy_ratio * evals[-1]]
        degenerate = weak.shape[1] > 0
        if degenerate and p.method == "point_to_plane":
            # The paper's point-to-point ICP is kept as printed, without this guard.
            # Express the ICP correction relative to the prediction, about the sensor, and drop
            # its components along the weak directions: there the prior stands.
            shift = np.eye(4)
            shift[:3, 3] = -centre
            delta = shift @ T @ np.linalg.inv(pred) @ np.linalg.inv(shift)
            x = _small_motion(delta) * scale
            x -= weak @ (weak.T @ x)
            T = np.linalg.inv(shift) @ _from_small_motion(x / scale) @ shift @ pred

        moved = _transform(T, pts[src_idx])
        resid = np.einsum("ij,ij->i", moved - self._map_points[tgt_idx], normals)
        rmse = float(np.sqrt(np.mean(resid**2)))
        fitness = len(src_idx) / len(pts)
        return T, FrameQuality(index=index, fitness=fitness, rmse_m=rmse, degenerate=degenerate)


def register_frames(
    frames: Iterable[tuple[int, np.ndarray, float | None]],
    params: RegistrationParams = RegistrationParams(),
) -> Trajectory:
    """Register a sequence of frames into one trajectory.

    Parameters
    ----------
    frames : iterable of (frame_index, points_sensor_m (N, 3), odometer_m or None)
        Streamed in order; each full frame is dropped once registered.
    params : RegistrationParams

    Returns
    -------
    Trajectory
        Poses relative to the first frame of the sequence.
    """
    reg = FrameRegistrar(params)
    poses, quality, indices = [], [], []
    for frame_index, points, odometer in frames:
        try:
            T, q = reg.add(points, odometer)
        except RegistrationError as exc:
            raise RegistrationError(f"frame {frame_index}: {exc.reason}", hint=exc.hint) from exc
        poses.append(T)
        quality.append(FrameQuality(frame_index, q.fitness, q.rmse_m, q.degenerate))
        indices.append(frame_index)
    if not poses:
        raise RegistrationError("no frames to register")
    return Trajectory(np.asarray(poses), tuple(quality), tuple(indices))


def plan_chunks(frame_count: int, chunk_frames: int) -> list[tuple[int, int]]:
    """Split frames into chunks ``[first, last]`` (inclusive) that overlap by one frame.

    The shared frame lets consecutive chunks, registered independently and in parallel, be
    chained into one trajectory.
    """
    if frame_count <= 0:
        return []
    chunk_frames = max(2, chunk_frames)
    chunks, first = [], 0
    while True:
        last = min(first + chunk_frames - 1, frame_count - 1)
        chunks.append((first, last))
        if last >= frame_count - 1:
            return chunks
        first = last


def chain_trajectories(chunks: list[Trajectory]) -> Trajectory:
    """Chain chunk trajectories that overlap by one frame into one trajectory.

    Chunk k's first frame is chunk k−1's last; its poses are re-expressed in the world frame
    of chunk 0: ``T_world_frame = T_world_shared @ T_chunk_frame``.
    """
    if not chunks:
        raise RegistrationError("no chunks to chain")
    poses = [chunks[0].T_world_frame]
    quality = list(chunks[0].quality)
    indices = list(chunks[0].frame_indices)
    for chunk in chunks[1:]:
        if chunk.frame_indices[0] != indices[-1]:
            raise RegistrationError(
                f"chunks do not overlap: frame {indices[-1]} then {chunk.frame_indices[0]}"
            )
        T_world_shared = poses[-1][-1]
        poses.append(np.einsum("ij,fjk->fik", T_world_shared, chunk.T_world_frame[1:]))
        quality.extend(chunk.quality[1:])
        indices.extend(chunk.frame_indices[1:])
    return Trajectory(np.concatenate(poses), tuple(quality), tuple(indices))


def iter_registered_points(
    frames: Iterable[tuple[int, np.ndarray]], trajectory: Trajectory
) -> Iterator[np.ndarray]:
    """Transform frames into the world frame, one at a time, (N, 3) each."""
    pose_of = dict(zip(trajectory.frame_indices, trajectory.T_world_frame, strict=True))
    for frame_index, points in frames:
        yield _transform(pose_of[frame_index], np.asarray(points, dtype=np.float64))
