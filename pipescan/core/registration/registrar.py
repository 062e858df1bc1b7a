"""Streaming frame-to-local-map registration: the loop that ties the stages together."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Iterator, Sequence

import numpy as np

from pipescan.core.errors import RegistrationError
from pipescan.core.model import FrameQuality
from pipescan.core.registration.deskew import deskew_points, travel_motion
from pipescan.core.registration.engines import (
    LocalMap,
    aligner,
    plane_icp_steps,
    small_gicp_source,
    small_gicp_steps,
    transform,
)
from pipescan.core.registration.fusion import (
    AxialFilter,
    Fault,
    SlideDetector,
    SlipLog,
    axial_information,
    degenerate_directions,
    from_small_motion,
    gravity_corrected,
    point_to_plane_hessian,
    small_motion,
)
from pipescan.core.registration.params import AlongAxisPrior, RegistrationParams
from pipescan.core.registration.preprocess import preprocess_frame, range_mask
from pipescan.core.registration.stride import frames_to_register
from pipescan.core.registration.trajectory import (
    Trajectory,
    interpolate_pose,
    share_of_way,
)

_MIN_FRAME_POINTS = 50
_MIN_CORRESPONDENCES = 30
# small_gicp's iterations before the frame's evidence is read to see whether ICP is only
# creeping along directions the fusion will discard (the axis without facing surfaces, a
# degenerate roll). In a smooth stretch of the 30 m scan the steps across the axis and in
# tilt fall below 0.1 mm and 0.1 mrad by the third iteration while the frame creeps on along
# it; frames with features in view converge in 3 (median) and never read it. It decides when
# the evidence is read, not what is kept (docs/registration.md, *Convergence*).
_ITERATIONS_BEFORE_EVIDENCE = 4

TRACK_ITERATIONS = 8
"""ICP iterations a tracked frame gets. Along the axis, which tracking leaves to the
interpolation, a smooth pipe's ICP creeps on to any cap, so the cap is what a tracked frame
costs: 8 iterations of 1,500 points, about 2 ms. Four left a vibration of 1.1° a frame (a
harsh sweep draw) half corrected: ok sections up to 1.1 pp off in a 0.3 m pipe, 0.53 pp with
eight (docs/registration.md, *Every frame placed*)."""

TRACK_POINTS = 1500
"""Returns of a frame between registered ones that tracking aligns (a regular share of those
in range): four directions (tilt and offset across the axis) against a map of thousands of
points, where registering a frame takes all of its voxels and six (docs/registration.md,
*Every frame placed*)."""


@dataclasses.dataclass(frozen=True)
class _Matches:
    """A frame's correspondences with the local map at a pose: the frame's points (sensor
    frame) and, for the map points they match, normals (world) and surface variation."""

    src: np.ndarray
    target: np.ndarray
    normals_world: np.ndarray
    surface_variation: np.ndarray

    def residuals(self, T: np.ndarray) -> np.ndarray:
        """Point-to-plane residuals with the frame at pose ``T`` (m)."""
        return np.einsum("ij,ij->i", transform(T, self.src) - self.target, self.normals_world)


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
        self._map = LocalMap(params)
        self._align = aligner(params)
        self._axial = AxialFilter(
            params.odometer_scale_error_ratio, params.odometer_noise_m, params.keyframe_distance_m
        )
        self._slides = SlideDetector(
            params.slide_window_m, params.odometer_scale_error_ratio, params.odometer_noise_m
        )
        self._pending: list[np.ndarray] = []
        self._last_key_position: np.ndarray | None = None
        self._key_positions: list[np.ndarray] = []
        self._axis_world: np.ndarray | None = None
        self._prev: np.ndarray | None = None
        self._prev_constrained = False
        self._velocity_m = np.zeros(3)
        self._prev_odometer: float | None = None
        self._prev_time_s: float | None = None
        self._motion: tuple[np.ndarray, float] | None = None
        """The last registered step's travel (as a pose, and its time, s): what a tracked
        frame is deskewed by (constant velocity)."""
        self._first: tuple[np.ndarray, np.ndarray] | None = None
        """The first frame's points and times (sensor frame), until the second frame gives
        the travel to deskew it by."""
        self._down_world: np.ndarray | None = None
        self.slid: list[tuple[int, int]] = []
        """Runs of frames (first, last, counted from 0) that slid along the axis."""
        self._slips = SlipLog(params.slide_window_m)
        self._last_sigma = float("inf")
        """ICP's own error along the axis for this frame (infinite without information)."""
        self._last_move = (0.0, float("inf"))
        """This frame's move from the prior along the axis by ICP's share, and ICP's own error
        where it overrode the odometer (else infinite): what the slide window needs."""
        self.odometer_frames = 0
        self.count = 0
        self._seed: list[np.ndarray] = []
        """The frames (world frame) the local map was (re)started from, while they are fewer
        than ``map_seed_frames`` (:meth:`_seeding`)."""

    # -- prediction -------------------------------------------------------------------------
    def _predict(self, odometer_m: float | None) -> tuple[np.ndarray, float]:
        """The prior pose and its along-axis step (odometer, or constant velocity)."""
        assert self._prev is not None and self._axis_world is not None
        prev = self._prev
        pred = prev.copy()
        if odometer_m is not None and self._prev_odometer is not None:
            step = odometer_m - self._prev_odometer
            pred[:3, 3] = prev[:3, 3] + step * self._axis_world
        else:
            # No odometer: constant velocity, in translation only (extrapolating the rotation
            # too would let a held roll drift on at its last rate for ever), measured between
            # two consecutive constrained frames only: a frame that re-anchors on a feature
            # after a held stretch jumps, and that jump is not a speed.
            pred[:3, 3] = prev[:3, 3] + self._velocity_m
            step = float(self._velocity_m @ self._axis_world)
        return pred, step

    def _map_extent_m(self, position: np.ndarray) -> float:
        """How far behind the current position the local map reaches (m)."""
        if not self._key_positions:
            return 0.0
        return float(np.linalg.norm(position - self._key_positions[0]))

    # -- one frame --------------------------------------------------------------------------
    def add(
        self,
        points_sensor_m: np.ndarray,
        odometer_m: float | None = None,
        gravity: np.ndarray | tuple[float, float, float] | None = None,
        point_time_s: np.ndarray | None = None,
        time_s: float | None = None,
    ) -> tuple[np.ndarray, FrameQuality]:
        """Register the next frame.

        Parameters
        ----------
        points_sensor_m : (N, 3) float
            The frame in sensor coordinates, metres.
        odometer_m : float, optional
            The crawler's cable-counter reading at this frame. Without it, the along-axis
            motion is extrapolated at constant velocity where the geometry has no
            information, and such frames are flagged ``degenerate``.
        gravity : (3,) float, optional
            The direction of gravity an IMU measured at this frame, in the sensor frame (any
            length). The first reading defines the world "down"; later readings turn the
            predicted roll about the pipe axis into agreement with it before ICP, and a held
            (degenerate) roll stays there. A frame without it keeps the previous roll.
        point_time_s : (N,) float, optional
            Each point's capture time (s, any base). With ``time_s``, the frame is deskewed
            before ICP (:func:`~pipescan.core.registration.deskew.deskew_points`) by the
            predicted travel (the odometer's step or constant velocity, over the time since
            the last registered frame; :func:`~pipescan.core.registration.deskew.travel_motion`),
            and its pose is the sensor's at its earliest point.
            The first frame, with no travel yet, is deskewed once the second gives one: the
            map restarts from it then.
        time_s : float, optional
            The frame's time (s, the base of the other frames' ``time_s``; it need not be that
            of ``point_time_s``).

        Returns
        -------
        T_world_frame : (4, 4) float
        quality : FrameQuality

        Raises
        ------
        RegistrationError
            When the frame leaves too few points to register (after filtering) or finds too
            few correspondences in the local map.
        """
        p = self.params
        index = self.count
        gravity_sensor = _unit_gravity(gravity, index)
        if point_time_s is not None and time_s is not None and self._prev is not None:
            period_s = time_s - self._prev_time_s if self._prev_time_s is not None else 0.0
            if period_s > 0:
                pred, _ = self._predict(odometer_m)
                motion = (travel_motion(self._prev, pred), period_s)
                points_sensor_m = self._deskewed(points_sensor_m, point_time_s, motion)
                if self._first is not None:
                    # The first frame had no motion to be deskewed by: now it has (this
                    # step's, at constant velocity); the map restarts from it deskewed.
                    first = self._deskewed(*self._first, motion)
                    self._start_map(preprocess_frame(first, p))
        self._first = None
        pts = preprocess_frame(points_sensor_m, p)
        if len(pts) < _MIN_FRAME_POINTS:
            raise RegistrationError(
                f"frame {index} has only {len(pts)} points within {p.max_range_m} m after "
                "filtering; it cannot be registered",
                hint="check the frame, or raise max_range_m",
            )
        if self._prev is None:
            T = np.eye(4)
            quality = FrameQuality(index, 1.0, 0.0, False, along_axis_weight=1.0)
            self._start_map(pts)
            if point_time_s is not None and time_s is not None:
                self._first = (np.asarray(points_sensor_m), np.asarray(point_time_s))
        else:
            has_odometer = odometer_m is not None and self._prev_odometer is not None
            pred, step = self._predict(odometer_m)
            if gravity_sensor is not None and self._down_world is not None:
                assert self._axis_world is not None
                pred = gravity_corrected(pred, gravity_sensor, self._axis_world, self._down_world)
            step_bound = self._axial.predict(
                step, map_extent_m=self._map_extent_m(pred[:3, 3]), odometer=has_odometer
            )
            self._last_move = (0.0, float("inf"))
            self._last_sigma = float("inf")
            T, quality = self._register(pts, pred, index, step_bound)
            if has_odometer:
                assert odometer_m is not None
                T, quality = self._check_slide(T, quality, odometer_m)
            if self._seeding() and quality.fault != "slide":
                self._add_seed(T, pts)
            else:
                self._add_to_map(T, pts, quality)
        if self._down_world is None and gravity_sensor is not None:
            self._down_world = T[:3, :3] @ gravity_sensor
        if self._prev is not None and self._prev_constrained and not quality.degenerate:
            self._velocity_m = T[:3, 3] - self._prev[:3, 3]
        t_prev = self._prev_time_s
        if self._prev is not None and time_s is not None and t_prev is not None and time_s > t_prev:
            self._motion = (travel_motion(self._prev, T), time_s - t_prev)
        self._prev, self._prev_constrained = T, not quality.degenerate
        self._prev_odometer = odometer_m
        self._prev_time_s = time_s
        self.odometer_frames += odometer_m is not None
        self.count += 1
        return T, quality

    def _deskewed(
        self,
        points_sensor_m: np.ndarray,
        point_time_s: np.ndarray,
        motion: tuple[np.ndarray, float],
    ) -> np.ndarray:
        """The frame's points within the registration's range, deskewed by ``motion`` (a
        travel as a pose, and its time, s): the points beyond the range are never used."""
        p = self.params
        keep = range_mask(points_sensor_m, p.max_range_m, p.min_range_m)
        points = np.compress(keep, points_sensor_m, axis=0)
        return deskew_points(points, np.compress(keep, point_time_s), *motion)

    def _start_map(self, pts: np.ndarray) -> None:
        """Start the local map from the first frame (its points, sensor = world frame)."""
        self._map = LocalMap(self.params)
        self._seed = [pts]
        self._map.add_keyframe([pts], np.eye(4)[:3, 0])
        self._last_key_position = np.zeros(3)
        self._key_positions = [np.zeros(3)]
        self._axis_world = self._map.axis

    @property
    def last_pose(self) -> np.ndarray | None:
        """The pose of the frame registered last (None before the first)."""
        return self._prev

    def track_source(
        self, points_sensor_m: np.ndarray, point_time_s: np.ndarray | None = None
    ) -> np.ndarray:
        """What :meth:`track` aligns of a frame: at most ``TRACK_POINTS`` of its returns within
        the registration's range, a regular share of them (cheap to hold until the next
        registered frame). With ``point_time_s`` (N,) s, these points are deskewed by the
        last registered step's travel (constant velocity)."""
        p = self.params
        points = np.asarray(points_sensor_m)
        keep = np.flatnonzero(range_mask(points, p.max_range_m, p.min_range_m))
        if len(keep) > TRACK_POINTS:
            keep = keep[np.linspace(0, len(keep) - 1, TRACK_POINTS).astype(np.int64)]
        pts = points[keep].astype(np.float64)
        if point_time_s is not None and self._motion is not None:
            pts = deskew_points(pts, np.asarray(point_time_s)[keep], *self._motion)
        return pts

    def track(self, source: np.ndarray, init: np.ndarray) -> np.ndarray | None:
        """The pose of a frame that is not registered, between two that are: ``init``
        (interpolated between them) corrected by ICP against the local map in tilt and
        across the axis, the directions a pipe's wall fixes. A crawler's vibration changes the
        attitude from frame to frame, which interpolation cannot follow (0.3° at 2 m is 10 mm
        on the wall). Its place along the axis and its roll stay the interpolation's, which
        the registered frames' fusion decided. ``source``: :meth:`track_source`.

        ``init`` itself where ICP's pose fits the map no better (the median point-to-plane
        distance of its points); None when the frame cannot be tracked (too few points, or
        ICP diverged). The size of the correction is no test: the vibration tilts a frame by
        up to a degree or so between registered frames, 10 cm on the wall 6 m ahead, while
        its nearer points still hold ICP.
        """
        if len(source) < _MIN_FRAME_POINTS or self._axis_world is None:
            return None
        p = self.params
        if p.engine == "small_gicp" and p.method != "point_to_point":
            T = plane_icp_steps(self._map, source, init, TRACK_ITERATIONS)
        else:
            T = self._align(self._map, source, init)
        if not np.isfinite(T).all():
            return None
        x = small_motion(np.linalg.inv(init) @ T)
        axis_sensor = init[:3, :3].T @ self._axis_world
        x[:3] -= axis_sensor * (axis_sensor @ x[:3])  # roll: the interpolation's
        x[3:] -= axis_sensor * (axis_sensor @ x[3:])  # along the axis: the interpolation's
        T = init @ from_small_motion(x)
        # ICP's pose only where it fits the map better than the interpolation: a frame the
        # vibration did not move keeps the interpolated pose.
        return T if self._plane_misfit(source, T) <= self._plane_misfit(source, init) else init

    def _plane_misfit(self, source: np.ndarray, T: np.ndarray) -> float:
        """The median point-to-plane distance of the frame's points at pose ``T`` to their
        correspondences in the map (infinite with none)."""
        matches = self._matches(source, T)
        if not len(matches.src):
            return float("inf")
        return float(np.median(np.abs(matches.residuals(T))))

    def _seeding(self) -> bool:
        """Whether the local map is still being seeded: it was (re)started from fewer than
        ``map_seed_frames`` frames."""
        return 0 < len(self._seed) < self.params.map_seed_frames

    def _add_seed(self, T: np.ndarray, pts: np.ndarray) -> None:
        """Add a registered frame to the map as a keyframe of its own while the map is being
        seeded: a frame that covers only part of the field of view finds too little of a map
        of one frame to be held by it, and each frame added widens what the next one finds.
        A one-frame keyframe drops its isolated points (``seen_twice``)."""
        self._seed.append(transform(T, pts))
        self._pending = self._seed[-1:]
        self._close_keyframe(T)
        if not self._seeding():
            self._seed = []

    def _close_keyframe(self, T: np.ndarray) -> None:
        """Group the frames since the last keyframe into one keyframe, at pose ``T``."""
        self._map.add_keyframe(self._pending, T[:3, 0])
        self._pending = []
        self._last_key_position = T[:3, 3].copy()
        self._key_positions = [*self._key_positions, T[:3, 3].copy()][-self.params.map_keyframes :]
        self._axis_world = self._map.axis

    def _add_to_map(self, T: np.ndarray, pts: np.ndarray, quality: FrameQuality) -> None:
        p = self.params
        self._pending.append(transform(T, pts))
        assert self._last_key_position is not None
        if quality.fault == "slide":
            # The map holds frames that slid: start it again from this frame (and, for a
            # frame that covers part of the field of view, the next ones: ``_seeding``).
            self._map.clear()
            self._map.add_keyframe(self._pending[-1:], T[:3, 0])
            self._seed = self._pending[-1:]
            self._pending.clear()
            self._last_key_position = T[:3, 3].copy()
            self._key_positions = [T[:3, 3].copy()]
            return
        if np.linalg.norm(T[:3, 3] - self._last_key_position) >= p.keyframe_distance_m:
            self._close_keyframe(T)

    def _register(
        self, pts: np.ndarray, pred: np.ndarray, index: int, step_bound: float
    ) -> tuple[np.ndarray, FrameQuality]:
        T = self._icp(pts, pred)
        if not np.isfinite(T).all():
            raise RegistrationError(f"frame {index}: ICP diverged (non-finite pose)")
        # Correspondences at the solution, the same for every engine: they give the fitness,
        # the point-to-plane RMSE, the Hessian and the information along the axis.
        matches = self._matches(pts, T)
        wide = self.params.wide_correspondence_m
        if (
            len(matches.src) < _MIN_CORRESPONDENCES
            and wide
            and wide > self.params.max_correspondence_m
        ):
            T, matches = self._icp_with_gate(pts, pred, wide)
        if len(matches.src) < _MIN_CORRESPONDENCES:
            raise RegistrationError(
                f"frame {index}: ICP found only {len(matches.src)} correspondences",
                hint="the frame does not overlap the previous ones; check frame order",
            )
        T, weight = self._fuse(matches, pred, T, step_bound)
        # The residuals at the fused pose, with the ICP solution's correspondences: the fusion
        # moves the frame along the wall, where point-to-plane residuals hardly change.
        resid = matches.residuals(T)
        rmse = float(np.sqrt(np.mean(resid**2)))
        fitness = len(matches.src) / len(pts)
        return T, FrameQuality(
            index=index,
            fitness=fitness,
            rmse_m=rmse,
            degenerate=weight < 0.5,
            along_axis_weight=weight,
            chainage_uncertainty_m=self._axial.chainage_uncertainty_m,
            gate_sigma_m=self._axial.last_gate_sigma_m,
            overrode=self._axial.last_overrode,
        )

    def _icp_with_gate(
        self, pts: np.ndarray, pred: np.ndarray, gate_m: float
    ) -> tuple[np.ndarray, _Matches]:
        """ICP from ``pred`` and its correspondences with the gate ``gate_m`` for this frame
        only (``RegistrationParams.wide_correspondence_m``): the engines and the map read the
        gate from the parameters, which are put back after."""
        own = self.params
        self.params = self._map.params = dataclasses.replace(own, max_correspondence_m=gate_m)
        try:
            T = self._icp(pts, pred)
            return T, self._matches(pts, T)
        finally:
            self.params = self._map.params = own

    def _icp(self, pts: np.ndarray, pred: np.ndarray) -> np.ndarray:
        """ICP from the prior pose ``pred``.

        With small_gicp, iterating stops once the steps are below the convergence thresholds
        in every direction the fusion keeps: a step along the axis while the frame sees no
        surface facing along it (no information: ICP's weight there is 0), or about the axis
        while roll is degenerate (held), changes nothing the fusion returns. In a smooth
        stretch ICP otherwise creeps along the axis and about it to the iteration cap, a
        millimetre and two milliradians a step: 14 iterations where 4 converge.
        """
        p, m = self.params, self._map
        source = pts
        if p.icp_max_points is not None and len(pts) > p.icp_max_points:
            source = pts[np.linspace(0, len(pts) - 1, p.icp_max_points).astype(np.int64)]
        if p.engine != "small_gicp" or p.method == "point_to_point":
            return self._align(m, source, pred)
        cloud = small_gicp_source(m, source)
        first = min(_ITERATIONS_BEFORE_EVIDENCE, p.max_iterations)
        T, converged = small_gicp_steps(m, cloud, pred, first)
        left = p.max_iterations - first
        if converged or left <= 0 or not np.isfinite(T).all():
            return T
        discarded = self._discarded_directions(pts, T, pred)
        if discarded is None:
            return small_gicp_steps(m, cloud, T, left)[0]
        basis, scale = discarded
        for _ in range(left):
            T_next, converged = small_gicp_steps(m, cloud, T, 1)
            x = small_motion(np.linalg.inv(T) @ T_next) * scale
            x = (x - basis @ (basis.T @ x)) / scale
            T = T_next
            if converged or (
                np.linalg.norm(x[:3]) < p.converged_rotation_rad
                and np.linalg.norm(x[3:]) < p.converged_translation_m
            ):
                break
        return T

    def _discarded_directions(
        self, pts: np.ndarray, T: np.ndarray, pred: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """The directions of a correction about the sensor that the fusion will discard at
        pose ``T``, as an orthonormal basis in balanced coordinates (and the scale to them),
        or None when it keeps every direction."""
        matches = self._matches(pts, T)
        if len(matches.src) < _MIN_CORRESPONDENCES:
            return None
        information, weak, scale, axis_sensor = self._evidence(matches, T, pred)
        directions = [weak]
        if information <= 0:
            directions.append(np.concatenate(([0.0, 0.0, 0.0], axis_sensor))[:, None])
        stacked = np.hstack(directions)
        if stacked.shape[1] == 0:
            return None
        return np.linalg.qr(stacked)[0], scale

    def _evidence(
        self, matches: _Matches, T: np.ndarray, pred: np.ndarray
    ) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        """What the frame's correspondences tell about the pose, with the frame at ``T``,
        about the sensor at ``pred``: ICP's information along the axis, the weak roll
        directions (balanced coordinates), the scale to those coordinates and the axis in
        the sensor frame."""
        assert self._axis_world is not None
        src = matches.src
        axis_sensor = pred[:3, :3].T @ self._axis_world
        normals_sensor = matches.normals_world @ pred[:3, :3]
        information = axial_information(
            normals_sensor, matches.surface_variation, matches.residuals(T), axis_sensor, src
        )
        length = float(np.sqrt(np.mean(np.einsum("ij,ij->i", src, src))))
        hessian = point_to_plane_hessian(src, normals_sensor)
        weak, scale = degenerate_directions(hessian, length, self.params.degeneracy_ratio)
        weak = weak[:, np.linalg.norm(weak[:3], axis=0) > 0.5]  # rotation-dominated: roll
        return information, weak, scale, axis_sensor

    def _fuse(
        self, matches: _Matches, pred: np.ndarray, T: np.ndarray, step_bound: float
    ) -> tuple[np.ndarray, float]:
        """Weigh ICP's correction from the prior: along the axis by its information against
        the prior's uncertainty, about the axis (roll) held where the Hessian is degenerate.
        Returns the fused pose and ICP's weight along the axis."""
        p = self.params
        if p.method == "point_to_point":
            # The paper's point-to-point ICP is kept as printed, without fusion.
            return T, 1.0
        information, weak, scale, axis_sensor = self._evidence(matches, T, pred)
        x = small_motion(np.linalg.inv(pred) @ T)
        correction = float(x[3:] @ axis_sensor)
        weight, overrode = self._axial.update(information, step_bound, correction)
        self._last_sigma = 1.0 / float(np.sqrt(information)) if information > 0 else float("inf")
        self._last_move = (weight * correction, self._last_sigma if overrode else float("inf"))
        # Express the ICP correction relative to the prior, about the sensor, in balanced
        # coordinates; drop it along the weak roll directions and keep ICP's share ``weight``
        # of it along the axis.
        x = x * scale
        if weak.shape[1]:
            weak = np.linalg.qr(weak)[0]
            x -= weak @ (weak.T @ x)
        along = np.concatenate(([0.0, 0.0, 0.0], axis_sensor))
        x -= (1.0 - weight) * along * (along @ x)
        return pred @ from_small_motion(x / scale), weight

    def _check_slide(
        self, T: np.ndarray, quality: FrameQuality, odometer_m: float
    ) -> tuple[np.ndarray, FrameQuality]:
        """Compare registered and odometer travel over the slide window; put a frame that
        slid back on the odometer."""
        assert self._axis_world is not None
        w = quality.along_axis_weight
        along = float(T[:3, 3] @ self._axis_world)
        fault: Fault | None
        moved, override_sigma = self._last_move
        fault, disagreement = self._slides.add(
            odometer_m, along, w, self._axial.last_icp_var, moved, override_sigma
        )
        self._slips.add(
            odometer_m, along, disagreement if fault == "odometer_slip" else None, fault == "slide"
        )
        if fault is None:
            return T, quality
        if fault == "slide":
            T = T.copy()
            T[:3, 3] -= disagreement * self._axis_world
            self._axial.widen(disagreement)
            self._axial.P = 0.0
            # Every frame of the window slid with it: their sections are not trusted.
            self.slid.append((self.count - self._slides.window_frames + 1, self.count))
        self._slides.add(odometer_m, float(T[:3, 3] @ self._axis_world), w, 0.0)
        return T, dataclasses.replace(
            quality,
            fault=fault,
            chainage_uncertainty_m=self._axial.chainage_uncertainty_m,
        )

    def _matches(self, pts: np.ndarray, T: np.ndarray) -> _Matches:
        m = self._map
        idx, dist = m.nearest(transform(T, pts))
        ok = (idx >= 0) & (dist <= self.params.max_correspondence_m)
        target = idx[ok]
        # np.compress and np.take: the same rows as indexing, a quarter of the time.
        return _Matches(
            np.compress(ok, pts, axis=0),
            np.take(m.points, target, axis=0),
            np.take(m.normals, target, axis=0),
            m.surface_variation[target],
        )

    @property
    def disagreement_sigmas(self) -> float:
        """How far the last frame's ICP disagreed with the odometer along the axis, in σ of
        both errors together (0 where ICP had no information along the axis, or there was no
        odometer): what :func:`~pipescan.core.registration.stride.frames_to_register` looks
        closer at."""
        return self._axial.last_innovation_sigmas

    @property
    def odometer_slips_m(self) -> tuple[float, ...]:
        """Sizes of the odometer slips caught against features so far, one per slip (m)."""
        return self._slips.sizes_m

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
    *,
    registrar: FrameRegistrar | None = None,
) -> Trajectory:
    """Register a sequence of frames into one trajectory.

    Parameters
    ----------
    frames : iterable of (frame_index, points (N, 3), odometer_m[, gravity[, point_time_s, time_s]])
        Streamed in order; each full frame is dropped once registered. The optional fourth
        element is the IMU's gravity direction in the sensor frame, (3,) or None (see
        :meth:`FrameRegistrar.add`): it holds the roll about the pipe axis to the IMU. The
        optional fifth and sixth are each point's time (N,) and the frame's time (s, or
        None): with both, the frame is deskewed before ICP.
    params : RegistrationParams
    registrar : FrameRegistrar, optional
        A new registrar made with ``params`` for the frames to come, when the caller chooses
        the next frame from what the last one showed
        (:func:`~pipescan.core.registration.stride.frames_to_register`).

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
    reg = registrar if registrar is not None else FrameRegistrar(params)
    if reg.count:
        raise ValueError("register_frames needs a new FrameRegistrar")
    poses, quality, indices = [], [], []
    for frame_index, points, odometer, *rest in frames:
        gravity = rest[0] if rest else None
        point_time_s, time_s = (rest[1], rest[2]) if len(rest) >= 3 else (None, None)
        try:
            T, q = reg.add(points, odometer, gravity, point_time_s, time_s)
        except RegistrationError as exc:
            raise RegistrationError(f"frame {frame_index}: {exc.reason}", hint=exc.hint) from exc
        poses.append(T)
        quality.append(dataclasses.replace(q, index=frame_index))
        indices.append(frame_index)
    if not poses:
        raise RegistrationError("no frames to register")
    for first, last in reg.slid:
        for k in range(max(first, 1), last + 1):
            if quality[k].fault is None:
                quality[k] = dataclasses.replace(quality[k], fault="slide")
    return Trajectory(
        np.asarray(poses),
        tuple(quality),
        tuple(indices),
        reg.along_axis_prior,
        odometer_slips_m=reg.odometer_slips_m,
        slip_window_m=params.slide_window_m,
        stated_slip_m=params.odometer_slip_m,
    )


def register_keyframes(
    frames: Iterable[tuple],
    first: int,
    last: int,
    stride: int,
    params: RegistrationParams = RegistrationParams(),
    *,
    along: Sequence[float | None] | None = None,
) -> Trajectory:
    """Register chunk ``first..last`` from every one of its frames, in order: the frames
    :func:`~pipescan.core.registration.stride.frames_to_register` chooses with ``stride`` k
    (every k-th and the last, and every frame for a while after one whose ICP disagreed with
    the odometer) are registered; each frame between two registered ones is tracked once the
    later one is (:meth:`FrameRegistrar.track`, from the pose interpolated between them at
    :func:`~pipescan.core.registration.trajectory.share_of_way` along ``along``).

    ``frames`` yields ``(frame_index, points, odometer_m, gravity[, point_time_s, time_s])``
    for every frame of the chunk, as :func:`register_frames` takes them. The trajectory
    carries the tracked frames' poses (NaN for a frame that could not be tracked).
    """
    reg = FrameRegistrar(params)
    chosen = frames_to_register(first, last, stride, lambda: reg.disagreement_sigmas)
    tracked: dict[int, np.ndarray] = {}

    def registered() -> Iterator[tuple]:
        source = iter(frames)
        held: list[tuple[int, np.ndarray]] = []
        previous: tuple[int, np.ndarray] | None = None
        for wanted in chosen:
            for frame in source:
                if frame[0] == wanted:
                    break
                point_time_s = frame[4] if len(frame) > 4 else None
                held.append((frame[0], reg.track_source(frame[1], point_time_s)))
            else:
                return  # the source ended before the frame wanted
            yield frame
            pose = reg.last_pose  # the frame just yielded, now registered
            assert pose is not None
            for i, pts in held:
                if previous is None:
                    continue
                a, T_a = previous
                init = interpolate_pose(T_a, pose, share_of_way(along, i, a, wanted))
                T = reg.track(pts, init)
                tracked[i] = T if T is not None else np.full((4, 4), np.nan)
            held = []
            previous = (wanted, pose.copy())

    trajectory = register_frames(registered(), params, registrar=reg)
    order = sorted(tracked)
    poses = np.array([tracked[i] for i in order]).reshape(-1, 4, 4)
    return dataclasses.replace(trajectory, tracked_indices=tuple(order), T_world_tracked=poses)
