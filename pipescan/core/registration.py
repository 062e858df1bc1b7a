"""Frame registration: odometer-initialised ICP that holds where a smooth pipe cannot.

In a smooth straight pipe, ICP cannot tell where along the axis one frame sits relative to the
next, nor how it is rolled about the axis: the cost is flat in those directions. pipescan finds
them from the eigenvalues of the point-to-plane Hessian and keeps the prior (the odometer along
the axis, the previous attitude for roll, turned to agree with an IMU's gravity when frames
carry it) there, letting the geometry decide only the directions it constrains ("solution
remapping").

Each frame is registered against a local map of the last few keyframes. A keyframe groups the
consecutive frames registered while the crawler moved less than ``keyframe_distance_m``, so the
map is denser than any one frame of the sensor's non-repetitive pattern.

Three engines run the same pipeline (preprocessing, map, prior, degeneracy handling, quality):
``small_gicp`` (default, the fastest and as accurate; see ``docs/registration.md``), Open3D's
legacy ``open3d`` and its tensor pipeline ``open3d_tensor``. The paper's point-to-point ICP with
the Kabsch step is kept as ``method="point_to_point"``, as printed (no degeneracy guard).

Poses are 4×4 matrices ``T_world_frame`` mapping frame (sensor) coordinates into the world
frame, which is the first frame's sensor frame.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from pipescan.core.errors import RegistrationError
from pipescan.core.model import FrameQuality

RegistrationMethod = Literal["point_to_plane", "gicp", "point_to_point"]
REGISTRATION_METHODS: tuple[str, ...] = ("gicp", "point_to_plane", "point_to_point")
"""``gicp`` (default, small_gicp only), ``point_to_plane`` and the paper's ``point_to_point``."""

RegistrationEngine = Literal["small_gicp", "open3d", "open3d_tensor"]
REGISTRATION_ENGINES: tuple[str, ...] = ("small_gicp", "open3d", "open3d_tensor")
"""Libraries that run the ICP step of ``point_to_plane`` and ``gicp``."""

AlongAxisPrior = Literal["odometer", "constant_velocity", "mixed"]

_MIN_FRAME_POINTS = 50
_MIN_CORRESPONDENCES = 30
_NORMAL_NEIGHBOURS = 12
_FACING_AXIS_COS = np.cos(np.radians(45.0))
# Gravity says nothing about roll about an axis within ~6° of vertical (a shaft): there the
# components of gravity across the axis are below this and the IMU correction is skipped.
_MIN_GRAVITY_ACROSS_AXIS = 0.1


@dataclass(frozen=True)
class RegistrationParams:
    """Parameters of frame registration.

    Attributes
    ----------
    method : {"gicp", "point_to_plane", "point_to_point"}
        ``gicp`` (default; plane-to-plane, the most accurate in ``docs/registration.md``) and
        ``point_to_plane``, both with degeneracy handling, or the paper's point-to-point ICP
        with the Kabsch/SVD step (NumPy, ``engine`` is not used).
    engine : {"small_gicp", "open3d", "open3d_tensor"}
        Library running the ICP step. ``gicp`` needs ``small_gicp``.
    voxel_m : float
        Voxel size of the local map (its keyframes group several frames, so it is denser than
        one frame).
    max_range_m : float
        Points further than this from the sensor are left out of registration (grazing,
        sparse and noisy at range).
    max_correspondence_m : float
        ICP correspondence distance; also the inlier distance of the reported fitness.
    max_iterations : int
    keyframe_distance_m : float
        Consecutive frames are grouped into one keyframe of the local map until the sensor
        moved this far.
    map_keyframes : int
        Keyframes kept in the local map.
    degeneracy_ratio : float
        A rotation-dominated direction of the (unit-balanced) Hessian whose eigenvalue is
        below this share of the largest is degenerate (the roll about the axis of a round
        pipe); there the previous attitude is kept. 0.01 holds roll while leaving pitch and
        yaw free (0.03 already froze them and let the attitude drift by 1-2° over 2.5 m of
        the simulator's scans). 0 lets ICP decide roll.
    axial_feature_ratio : float
        With an odometer, the translation along the pipe axis is degenerate, and held to the
        odometer, when surfaces facing along the axis (within 45°; weighted by ``(n·a)²``)
        make up less than this share of the frame's points. On the simulator's scans a
        featureless pipe reads 0.001-0.008 and the `paper` scenario 0.007-0.07 (median
        0.06). 0 lets ICP decide the along-axis position everywhere.
    source_voxel_m : float, optional
        Voxel size of each frame, coarser than the map's: fewer points, faster ICP (0.045 m:
        about 1.5× the frames/s of 0.03 m for 0.1-0.3 mm more across-axis error). ``None``
        uses ``voxel_m``.
    num_threads : int
        Threads the engine may use for one frame. 1 by default: parallelism comes from
        registering chunks of frames in parallel.

    Raises
    ------
    ValueError
        From construction, for an unknown method or engine or an out-of-range value.
    """

    method: RegistrationMethod = "gicp"
    engine: RegistrationEngine = "small_gicp"
    voxel_m: float = 0.03
    max_range_m: float = 6.0
    max_correspondence_m: float = 0.08
    max_iterations: int = 15
    keyframe_distance_m: float = 0.15
    map_keyframes: int = 8
    degeneracy_ratio: float = 0.01
    axial_feature_ratio: float = 0.015
    source_voxel_m: float | None = 0.045
    num_threads: int = 1

    def __post_init__(self) -> None:
        if self.method not in REGISTRATION_METHODS:
            raise ValueError(
                f"RegistrationParams.method {self.method!r} is unknown; "
                f"use one of {', '.join(REGISTRATION_METHODS)}."
            )
        if self.engine not in REGISTRATION_ENGINES:
            raise ValueError(
                f"RegistrationParams.engine {self.engine!r} is unknown; "
                f"use one of {', '.join(REGISTRATION_ENGINES)}."
            )
        if self.method == "gicp" and self.engine != "small_gicp":
            raise ValueError("RegistrationParams.method 'gicp' needs engine='small_gicp'.")
        for name in ("voxel_m", "max_range_m", "max_correspondence_m", "keyframe_distance_m"):
            if not getattr(self, name) > 0:
                raise ValueError(
                    f"RegistrationParams.{name} must be > 0, got {getattr(self, name)!r}."
                )
        if self.source_voxel_m is not None and not self.source_voxel_m > 0:
            raise ValueError(
                "RegistrationParams.source_voxel_m must be > 0 or None, "
                f"got {self.source_voxel_m!r}."
            )
        for name in ("max_iterations", "map_keyframes", "num_threads"):
            if getattr(self, name) < 1:
                raise ValueError(
                    f"RegistrationParams.{name} must be >= 1, got {getattr(self, name)!r}."
                )
        if not 0 <= self.axial_feature_ratio < 1:
            raise ValueError(
                "RegistrationParams.axial_feature_ratio must be in [0, 1), "
                f"got {self.axial_feature_ratio!r}."
            )
        if not 0 <= self.degeneracy_ratio < 1:
            raise ValueError(
                "RegistrationParams.degeneracy_ratio must be in [0, 1), "
                f"got {self.degeneracy_ratio!r}."
            )

    @property
    def label(self) -> str:
        """The engine and method as a user reads them, e.g. ``small_gicp point_to_plane``."""
        if self.method == "point_to_point":
            return "paper point_to_point (Kabsch, NumPy)"
        return f"{self.engine} {self.method}"


@dataclass(frozen=True)
class Trajectory:
    """Poses of consecutive frames and their registration quality.

    Attributes
    ----------
    T_world_frame : (F, 4, 4) float
        Poses; the first is the identity unless the trajectory was chained.
    quality : tuple of FrameQuality
        One per frame (the first frame's fitness is 1 by definition). ``degenerate`` marks
        frames whose along-axis position (and roll) the geometry did not constrain: they
        were held to the prior (``along_axis_prior``).
    frame_indices : tuple of int
        Archive frame indices of the poses.
    along_axis_prior : {"odometer", "constant_velocity", "mixed"}
        What held degenerate frames: the odometer, or without one a constant-velocity
        extrapolation (which is not a measurement: such frames were *not* registered along
        the axis), or a mix when only some frames had an odometer reading.
    """

    T_world_frame: np.ndarray
    quality: tuple[FrameQuality, ...]
    frame_indices: tuple[int, ...]
    along_axis_prior: AlongAxisPrior = "odometer"

    def positions_m(self) -> np.ndarray:
        """Sensor positions in the world frame, (F, 3)."""
        return self.T_world_frame[:, :3, 3]


# --------------------------------------------------------------------------- preprocessing


def voxel_downsample(points_m: np.ndarray, voxel_m: float) -> np.ndarray:
    """Centroid of the points in each occupied voxel, (K, 3) float64, same frame as the input."""
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points_m, np.float64)))
    return np.asarray(pcd.voxel_down_sample(voxel_m).points)


def preprocess_frame(points_m: np.ndarray, params: RegistrationParams) -> np.ndarray:
    """Range-crop and voxel-downsample a frame (at ``source_voxel_m``, or ``voxel_m`` when it
    is None); returns (K, 3) float64 (sensor frame)."""
    pts = np.asarray(points_m, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"A frame must have shape (N, 3), got {pts.shape}.")
    pts = pts[np.einsum("ij,ij->i", pts, pts) <= params.max_range_m**2]
    if len(pts) == 0:
        return pts
    return voxel_downsample(pts, params.source_voxel_m or params.voxel_m)


def estimate_normals(points_m: np.ndarray, *, k: int = _NORMAL_NEIGHBOURS) -> np.ndarray:
    """Unit normals from the k-neighbourhood covariance, (N, 3)."""
    import small_gicp

    cloud = small_gicp.PointCloud(np.asarray(points_m, np.float64))
    small_gicp.estimate_normals(cloud, num_neighbors=k)
    return cloud.normals()[:, :3].copy()


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


# --------------------------------------------------------------------------- degeneracy


def point_to_plane_hessian(source_m: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Gauss-Newton Hessian ``Σ J_iᵀ J_i`` of point-to-plane ICP, (6, 6), order (rot, trans).

    ``J_i = [(p_i × n_i)ᵀ, n_iᵀ]`` for a source point p_i matched to a target point with
    normal n_i, both in one frame; rotation is about that frame's origin. Pass points in the
    sensor frame (normals rotated into it) to get the Hessian of a perturbation about the
    sensor, ``T = T_pred @ exp(δ)``.
    """
    j = np.hstack((np.cross(source_m, normals), normals))
    return j.T @ j


def degenerate_directions(
    hessian: np.ndarray, length_m: float, ratio: float
) -> tuple[np.ndarray, np.ndarray]:
    """Weak directions of a point-to-plane Hessian, in unit-balanced coordinates.

    The rotation part is scaled by ``length_m`` (the points' RMS distance from the rotation
    centre) so that both parts are in metres and one eigenvalue ratio means the same for
    both. In a smooth pipe the two weak modes are the translation along the axis and the roll
    about it.

    Returns
    -------
    weak : (6, W) float
        Orthonormal weak directions (W = 0 when the geometry constrains every direction).
    scale : (6,) float
        Multiply ``(rotvec_rad, translation_m)`` by it to reach the balanced coordinates.
    """
    scale = np.array([length_m] * 3 + [1.0] * 3)
    balanced = hessian / np.outer(scale, scale)
    evals, evecs = np.linalg.eigh(balanced)
    return evecs[:, evals < ratio * evals[-1]], scale


def _small_motion(T: np.ndarray) -> np.ndarray:
    """(rotation vector, translation) of a small relative motion."""
    return np.concatenate((Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]))


def _from_small_motion(x: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(x[:3]).as_matrix()
    T[:3, 3] = x[3:]
    return T


# --------------------------------------------------------------------------- engines


class _LocalMap:
    """The last keyframes, merged, voxelised, with normals and the engines' search structures."""

    def __init__(self, params: RegistrationParams) -> None:
        import small_gicp

        self.params = params
        self.keyframes: deque[np.ndarray] = deque(maxlen=params.map_keyframes)
        self.points = np.empty((0, 3))
        self.normals = np.empty((0, 3))
        self._sg = small_gicp
        self._sg_cloud: Any = None
        self._sg_tree: Any = None
        self._cache: dict[str, Any] = {}

    def add_keyframe(self, points_world: np.ndarray) -> None:
        sg, p = self._sg, self.params
        self.keyframes.append(points_world)
        merged = np.vstack(self.keyframes)
        self.points = voxel_downsample(merged, p.voxel_m) if len(self.keyframes) > 1 else merged
        self._sg_cloud = sg.PointCloud(self.points)
        self._sg_tree = sg.KdTree(self._sg_cloud, num_threads=p.num_threads)
        if p.method == "gicp":
            sg.estimate_normals_covariances(
                self._sg_cloud, self._sg_tree, _NORMAL_NEIGHBOURS, p.num_threads
            )
        else:
            sg.estimate_normals(self._sg_cloud, self._sg_tree, _NORMAL_NEIGHBOURS, p.num_threads)
        self.normals = self._sg_cloud.normals()[:, :3].copy()
        self._cache.clear()

    def nearest(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Index of and distance to the closest map point, (K,) each."""
        idx, sq = self._sg_tree.batch_nearest_neighbor_search(points_world, self.params.num_threads)
        return np.asarray(idx, dtype=np.int64), np.sqrt(np.asarray(sq))

    def cached(self, key: str, build):
        if key not in self._cache:
            self._cache[key] = build()
        return self._cache[key]

    def axis_world(self, forward_world: np.ndarray) -> np.ndarray:
        """The pipe axis: the direction the wall's normals avoid (weakest eigenvector of their
        scatter matrix), pointing along ``forward_world``."""
        axis = np.linalg.eigh(self.normals.T @ self.normals)[1][:, 0]
        return axis if axis @ forward_world >= 0 else -axis


def _align_small_gicp(m: _LocalMap, source: np.ndarray, init: np.ndarray) -> np.ndarray:
    sg, p = m._sg, m.params
    cloud = sg.PointCloud(source)
    if p.method == "gicp":
        sg.estimate_covariances(cloud, sg.KdTree(cloud), _NORMAL_NEIGHBOURS, p.num_threads)
    result = sg.align(
        m._sg_cloud,
        cloud,
        m._sg_tree,
        init_T_target_source=init,
        registration_type="GICP" if p.method == "gicp" else "PLANE_ICP",
        max_correspondence_distance=p.max_correspondence_m,
        num_threads=p.num_threads,
        max_iterations=p.max_iterations,
        rotation_epsilon=1e-4,
        translation_epsilon=1e-4,
    )
    return np.asarray(result.T_target_source)


def _align_open3d(m: _LocalMap, source: np.ndarray, init: np.ndarray) -> np.ndarray:
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
        reg.TransformationEstimationPointToPlane(),
        reg.ICPConvergenceCriteria(max_iteration=m.params.max_iterations),
    )
    return np.asarray(result.transformation).copy()


def _align_open3d_tensor(m: _LocalMap, source: np.ndarray, init: np.ndarray) -> np.ndarray:
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
        reg.TransformationEstimationPointToPlane(),
        reg.ICPConvergenceCriteria(max_iteration=m.params.max_iterations),
    )
    return result.transformation.numpy().astype(np.float64)


def _align_point_to_point(m: _LocalMap, source: np.ndarray, init: np.ndarray) -> np.ndarray:
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


_ALIGNERS = {
    "small_gicp": _align_small_gicp,
    "open3d": _align_open3d,
    "open3d_tensor": _align_open3d_tensor,
}


# --------------------------------------------------------------------------- the registrar


class FrameRegistrar:
    """Streaming frame-to-local-map registration.

    Feed frames in order with ``add``; each returns the frame's pose and quality. Only the
    downsampled keyframes of the local map (and the downsampled frames of the keyframe being
    grouped) are kept in memory, never the full frames.

    Examples
    --------
    >>> reg = FrameRegistrar(RegistrationParams())          # doctest: +SKIP
    >>> for pts, odo in frames:                              # doctest: +SKIP
    ...     T_world_frame, quality = reg.add(pts, odo)
    """

    def __init__(self, params: RegistrationParams = RegistrationParams()) -> None:
        self.params = params
        self._map = _LocalMap(params)
        self._align = (
            _align_point_to_point if params.method == "point_to_point" else _ALIGNERS[params.engine]
        )
        self._pending: list[np.ndarray] = []
        self._last_key_position: np.ndarray | None = None
        self._axis_world: np.ndarray | None = None
        self._prev: np.ndarray | None = None
        self._prev_constrained = False
        self._velocity_m = np.zeros(3)
        self._prev_odometer: float | None = None
        self._down_world: np.ndarray | None = None
        self.odometer_frames = 0
        self.count = 0

    # -- prediction -------------------------------------------------------------------------
    def _gravity_corrected(self, pred: np.ndarray, gravity_sensor: np.ndarray) -> np.ndarray:
        """Turn the predicted attitude about the pipe axis so that it agrees with the IMU.

        The world "down" (the first frame's measured gravity) seen from the prediction
        should read as this frame's measured gravity. The roll about the axis that best
        aligns them is the signed angle between the two directions' components across the
        axis (both in the sensor frame); the predicted attitude is turned by it about the
        sensor. Pitch and yaw are left to ICP, which observes them to ~0.01°.
        """
        assert self._axis_world is not None and self._down_world is not None
        R = pred[:3, :3]
        axis = R.T @ self._axis_world
        predicted = R.T @ self._down_world
        across_pred = predicted - axis * (axis @ predicted)
        across_meas = gravity_sensor - axis * (axis @ gravity_sensor)
        if min(np.linalg.norm(across_pred), np.linalg.norm(across_meas)) < (
            _MIN_GRAVITY_ACROSS_AXIS
        ):
            return pred
        # R_new = R @ Rot(axis, θ) reads down as Rot(axis, -θ) @ predicted: θ turns the
        # measured direction onto the predicted one.
        theta = np.arctan2(axis @ np.cross(across_meas, across_pred), across_meas @ across_pred)
        corrected = pred.copy()
        corrected[:3, :3] = R @ Rotation.from_rotvec(theta * axis).as_matrix()
        return corrected

    def _predict(self, odometer_m: float | None) -> np.ndarray:
        assert self._prev is not None
        prev = self._prev
        pred = prev.copy()
        if odometer_m is not None and self._prev_odometer is not None:
            assert self._axis_world is not None
            pred[:3, 3] = prev[:3, 3] + (odometer_m - self._prev_odometer) * self._axis_world
        else:
            # No odometer: constant velocity, in translation only (extrapolating the rotation
            # too would let a held roll drift on at its last rate for ever), measured between
            # two consecutive constrained frames only: a frame that re-anchors on a feature
            # after a held stretch jumps, and that jump is not a speed.
            pred[:3, 3] = prev[:3, 3] + self._velocity_m
        return pred

    # -- one frame --------------------------------------------------------------------------
    def add(
        self,
        points_sensor_m: np.ndarray,
        odometer_m: float | None = None,
        gravity: np.ndarray | tuple[float, float, float] | None = None,
    ) -> tuple[np.ndarray, FrameQuality]:
        """Register the next frame.

        Parameters
        ----------
        points_sensor_m : (N, 3) float
            The frame in sensor coordinates, metres.
        odometer_m : float, optional
            The crawler's cable-counter reading at this frame. Without it, the along-axis
            motion is extrapolated at constant velocity where the Hessian shows no
            constraint at all, and such frames are flagged ``degenerate``.
        gravity : (3,) float, optional
            The direction of gravity an IMU measured at this frame, in the sensor frame (any
            length). The first frame's reading defines the world "down"; later readings turn
            the predicted roll about the pipe axis into agreement with it before ICP, and a
            held (degenerate) roll stays there instead of at the previous attitude. Without
            it (or without one on the first frame), roll is held to the previous attitude.

        Returns
        -------
        T_world_frame : (4, 4) float
        quality : FrameQuality

        Raises
        ------
        RegistrationError
            When the frame leaves too few points to register (after range cropping) or
            finds too few correspondences in the local map.
        """
        p = self.params
        index = self.count
        gravity_sensor = _unit_gravity(gravity, index)
        pts = preprocess_frame(points_sensor_m, p)
        if len(pts) < _MIN_FRAME_POINTS:
            raise RegistrationError(
                f"frame {index} has only {len(pts)} points within {p.max_range_m} m after "
                "downsampling; it cannot be registered",
                hint="check the frame, or raise max_range_m",
            )
        if self._prev is None:
            T = np.eye(4)
            quality = FrameQuality(index=index, fitness=1.0, rmse_m=0.0, degenerate=False)
            self._map.add_keyframe(pts)
            self._last_key_position = T[:3, 3].copy()
            self._axis_world = self._map.axis_world(T[:3, 0])
            self._down_world = gravity_sensor  # the world frame is this frame's sensor frame
        else:
            has_odometer = odometer_m is not None and self._prev_odometer is not None
            pred = self._predict(odometer_m)
            if gravity_sensor is not None and self._down_world is not None:
                pred = self._gravity_corrected(pred, gravity_sensor)
            T, quality = self._register(pts, pred, index, has_odometer)
            self._pending.append(_transform(T, pts))
            assert self._last_key_position is not None
            if np.linalg.norm(T[:3, 3] - self._last_key_position) >= p.keyframe_distance_m:
                # Group the frames since the last keyframe into one keyframe.
                self._map.add_keyframe(voxel_downsample(np.vstack(self._pending), p.voxel_m))
                self._pending.clear()
                self._last_key_position = T[:3, 3].copy()
                self._axis_world = self._map.axis_world(T[:3, 0])
        if self._prev is not None and self._prev_constrained and not quality.degenerate:
            self._velocity_m = T[:3, 3] - self._prev[:3, 3]
        self._prev, self._prev_constrained = T, not quality.degenerate
        self._prev_odometer = odometer_m
        self.odometer_frames += odometer_m is not None
        self.count += 1
        return T, quality

    def _register(
        self, pts: np.ndarray, pred: np.ndarray, index: int, has_odometer: bool
    ) -> tuple[np.ndarray, FrameQuality]:
        m = self._map
        T = self._align(m, pts, pred)
        if not np.isfinite(T).all():
            raise RegistrationError(f"frame {index}: ICP diverged (non-finite pose)")

        # Correspondences at the solution, the same for every engine: they give the fitness,
        # the point-to-plane RMSE and the Hessian of the degeneracy test.
        src_idx, tgt_idx = self._correspondences(pts, T)
        if len(src_idx) < _MIN_CORRESPONDENCES:
            raise RegistrationError(
                f"frame {index}: ICP found only {len(src_idx)} correspondences",
                hint="the frame does not overlap the previous ones; check frame order",
            )
        T, degenerate = self._hold_degenerate(
            pts[src_idx], m.normals[tgt_idx], pred, T, has_odometer
        )
        # The residuals at the held pose, with the ICP solution's correspondences: the hold
        # moves the frame along the wall, where point-to-plane residuals do not change.
        moved = _transform(T, pts[src_idx])
        resid = np.einsum("ij,ij->i", moved - m.points[tgt_idx], m.normals[tgt_idx])
        rmse = float(np.sqrt(np.mean(resid**2)))
        fitness = len(src_idx) / len(pts)
        return T, FrameQuality(index=index, fitness=fitness, rmse_m=rmse, degenerate=degenerate)

    def _hold_degenerate(
        self,
        src: np.ndarray,
        normals_world: np.ndarray,
        pred: np.ndarray,
        T: np.ndarray,
        has_odometer: bool,
    ) -> tuple[np.ndarray, bool]:
        """Keep the prior along the directions the geometry does not constrain.

        Two tests, because the two weak modes of a pipe differ. Along the axis, the wall's
        own normals are perpendicular to it, but their noise (5 mm ranges over 3 cm voxels)
        fakes an eigenvalue share of 1-2 % in the Hessian, right where a threshold would
        have to sit; so the translation counts only surfaces that face along the axis
        (within 45°: end walls, obstacle faces, deposit ramps), weighted by ``(n·a)²``, as
        a share of the frame's points. Roll about the axis is judged on the unit-balanced
        6×6 Hessian: rotation-dominated modes below ``degeneracy_ratio`` of the largest.
        Without an odometer the prior is a mere extrapolation, so every mode of the Hessian
        below ``degeneracy_ratio`` is held and the weak geometry decides the rest (on the
        `paper` scan the deformation's shallow ramps then fix the axis where the strict test
        would have held 0.5 m of travel to a guess).
        """
        p = self.params
        if p.method == "point_to_point":
            # The paper's point-to-point ICP is kept as printed, without the guard.
            return T, False
        assert self._axis_world is not None
        axis_sensor = pred[:3, :3].T @ self._axis_world
        normals_sensor = normals_world @ pred[:3, :3]
        axial = np.abs(normals_sensor @ axis_sensor)
        axial_share = float(np.sum(np.where(axial > _FACING_AXIS_COS, axial**2, 0.0))) / len(src)
        along_held = axial_share < p.axial_feature_ratio
        length = float(np.sqrt(np.mean(np.einsum("ij,ij->i", src, src))))
        hessian = point_to_plane_hessian(src, normals_sensor)
        weak, scale = degenerate_directions(hessian, length, p.degeneracy_ratio)
        if has_odometer:
            weak = weak[:, np.linalg.norm(weak[:3], axis=0) > 0.5]  # rotation-dominated: roll
            if along_held:
                weak = np.column_stack((weak, np.concatenate(([0.0, 0.0, 0.0], axis_sensor))))
        else:
            # Without an odometer the prior is only an extrapolation: let even weak geometry
            # (the shallow ramps of a deformation) decide, and hold only what the Hessian
            # cannot see at all.
            along_held = bool((np.linalg.norm(weak[3:], axis=0) > 0.5).any())
        if weak.shape[1] == 0:
            return T, False
        weak = np.linalg.qr(weak)[0]
        # Express the ICP correction relative to the prediction, about the sensor, and drop
        # its components along the weak directions: there the prior stands.
        x = _small_motion(np.linalg.inv(pred) @ T) * scale
        x -= weak @ (weak.T @ x)
        return pred @ _from_small_motion(x / scale), along_held

    def _correspondences(self, pts: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        idx, dist = self._map.nearest(_transform(T, pts))
        ok = (idx >= 0) & (dist <= self.params.max_correspondence_m)
        return np.flatnonzero(ok), idx[ok]

    @property
    def along_axis_prior(self) -> AlongAxisPrior:
        """What held the frames so far along degenerate directions."""
        if self.odometer_frames >= self.count:
            return "odometer"
        return "constant_velocity" if self.odometer_frames == 0 else "mixed"


def _unit_gravity(
    gravity: np.ndarray | tuple[float, float, float] | None, index: int
) -> np.ndarray | None:
    if gravity is None:
        return None
    g = np.asarray(gravity, dtype=np.float64)
    norm = float(np.linalg.norm(g)) if g.shape == (3,) else 0.0
    if not (np.isfinite(norm) and norm > 0):
        raise RegistrationError(
            f"gravity must be a finite, non-zero 3-vector, got {gravity!r} (frame {index})",
            hint="pass the IMU's gravity direction in the sensor frame, or None",
        )
    return g / norm


def register_frames(
    frames: Iterable[
        tuple[int, np.ndarray, float | None]
        | tuple[int, np.ndarray, float | None, np.ndarray | tuple[float, float, float] | None]
    ],
    params: RegistrationParams = RegistrationParams(),
) -> Trajectory:
    """Register a sequence of frames into one trajectory.

    Parameters
    ----------
    frames : iterable of (frame_index, points_sensor_m (N, 3), odometer_m or None[, gravity])
        Streamed in order; each full frame is dropped once registered. The optional fourth
        element is the IMU's gravity direction in the sensor frame, (3,) or None (see
        :meth:`FrameRegistrar.add`): it holds the roll about the pipe axis to the IMU.
    params : RegistrationParams

    Returns
    -------
    Trajectory
        Poses relative to the first frame of the sequence.

    Raises
    ------
    RegistrationError
        When there is no frame, or one cannot be registered (the message names it).

    Examples
    --------
    >>> from pipescan.simulator.scan import get_scenario, simulate_scan
    >>> scan = simulate_scan(get_scenario("paper", travel_m=0.3), seed=1)
    >>> traj = register_frames((f.index, f.points_sensor, f.odometer_m) for f in scan.frames())
    >>> traj.T_world_frame.shape[1:], traj.along_axis_prior
    ((4, 4), 'odometer')
    """
    reg = FrameRegistrar(params)
    poses, quality, indices = [], [], []
    for frame_index, points, odometer, *rest in frames:
        gravity = rest[0] if rest else None
        try:
            T, q = reg.add(points, odometer, gravity)
        except RegistrationError as exc:
            raise RegistrationError(f"frame {frame_index}: {exc.reason}", hint=exc.hint) from exc
        poses.append(T)
        quality.append(FrameQuality(frame_index, q.fitness, q.rmse_m, q.degenerate))
        indices.append(frame_index)
    if not poses:
        raise RegistrationError("no frames to register")
    return Trajectory(np.asarray(poses), tuple(quality), tuple(indices), reg.along_axis_prior)


# --------------------------------------------------------------------------- chunks


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
    priors = {c.along_axis_prior for c in chunks}
    prior: AlongAxisPrior = priors.pop() if len(priors) == 1 else "mixed"
    return Trajectory(np.concatenate(poses), tuple(quality), tuple(indices), prior)


# --------------------------------------------------------------------------- reporting


def degenerate_spans(trajectory: Trajectory) -> list[tuple[int, int]]:
    """Runs of consecutive degenerate frames, as (first, last) archive frame indices."""
    spans: list[tuple[int, int]] = []
    previous_degenerate = False
    for q in trajectory.quality:
        if q.degenerate and previous_degenerate:
            spans[-1] = (spans[-1][0], q.index)
        elif q.degenerate:
            spans.append((q.index, q.index))
        previous_degenerate = q.degenerate
    return spans


def registration_summary(trajectory: Trajectory, params: RegistrationParams) -> dict:
    """What to store and print about a registration: engine, quality, and where it held.

    ``unconstrained_spans`` lists the runs of frames whose along-axis position the geometry
    did not constrain, with the distance travelled (from the first frame, metres) at each
    end. With an odometer they were held to it; without one (``along_axis_prior`` =
    ``constant_velocity``) they are extrapolated, *not measured*, and ``warning`` says so.
    """
    q = trajectory.quality[1:] or trajectory.quality
    positions = trajectory.positions_m()
    travel = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(positions, axis=0), axis=1))))
    pos_of = {i: k for k, i in enumerate(trajectory.frame_indices)}
    spans = [
        {
            "first_frame": a,
            "last_frame": b,
            "start_travel_m": round(float(travel[pos_of[a]]), 4),
            "end_travel_m": round(float(travel[pos_of[b]]), 4),
        }
        for a, b in degenerate_spans(trajectory)
    ]
    degenerate = sum(x.degenerate for x in q)
    summary: dict = {
        "engine": params.label,
        "frames": len(trajectory.quality),
        "mean_fitness": float(np.mean([x.fitness for x in q])),
        "mean_rmse_m": float(np.mean([x.rmse_m for x in q])),
        "degenerate_frames": degenerate,
        "along_axis_prior": trajectory.along_axis_prior,
        "unconstrained_spans": spans,
    }
    if degenerate and trajectory.along_axis_prior != "odometer":
        summary["warning"] = (
            f"{degenerate} frame(s) in {len(spans)} span(s) had no odometer and no geometry "
            "along the pipe axis: their chainage is extrapolated, not measured"
        )
    return summary


@dataclass(frozen=True)
class TrajectoryErrors:
    """Pose errors of an estimated trajectory against the truth (both from the first frame).

    Translation errors are split along the pipe axis (the direction from the first to the
    last true position) and across it; rotation errors into roll about that axis (which a
    round pipe cannot observe, and which moves neither chainages nor areas) and the tilt of
    the axis (pitch and yaw together).
    """

    across_rms_m: float
    along_final_m: float
    along_max_m: float
    tilt_rms_deg: float
    roll_rms_deg: float


def trajectory_errors(T_estimated: np.ndarray, T_true: np.ndarray) -> TrajectoryErrors:
    """Compare poses, (F, 4, 4) each; both are re-expressed relative to their first pose.

    Raises
    ------
    ValueError
        When the shapes differ or the truth does not move (no axis to split along).
    """
    est, true = np.asarray(T_estimated, np.float64), np.asarray(T_true, np.float64)
    if est.shape != true.shape or est.ndim != 3 or est.shape[1:] != (4, 4):
        raise ValueError(f"Poses must both have shape (F, 4, 4), got {est.shape}, {true.shape}.")
    est = np.einsum("ij,fjk->fik", np.linalg.inv(est[0]), est)
    true = np.einsum("ij,fjk->fik", np.linalg.inv(true[0]), true)
    travel = true[-1, :3, 3]
    if np.linalg.norm(travel) < 1e-6:
        raise ValueError("The true trajectory does not move; there is no axis to split along.")
    axis = travel / np.linalg.norm(travel)
    err = est[:, :3, 3] - true[:, :3, 3]
    along = err @ axis
    across = np.linalg.norm(err - np.outer(along, axis), axis=1)
    rotvec = Rotation.from_matrix(est[:, :3, :3] @ true[:, :3, :3].transpose(0, 2, 1)).as_rotvec()
    roll = rotvec @ axis
    tilt = np.linalg.norm(rotvec - np.outer(roll, axis), axis=1)
    return TrajectoryErrors(
        across_rms_m=float(np.sqrt(np.mean(across**2))),
        along_final_m=float(along[-1]),
        along_max_m=float(np.abs(along).max()),
        tilt_rms_deg=float(np.degrees(np.sqrt(np.mean(tilt**2)))),
        roll_rms_deg=float(np.degrees(np.sqrt(np.mean(roll**2)))),
    )


def iter_registered_points(
    frames: Iterable[tuple[int, np.ndarray]], trajectory: Trajectory
) -> Iterator[np.ndarray]:
    """Transform frames into the world frame, one at a time, (N, 3) each."""
    pose_of = dict(zip(trajectory.frame_indices, trajectory.T_world_frame, strict=True))
    for frame_index, points in frames:
        yield _transform(pose_of[frame_index], np.asarray(points, dtype=np.float64))
