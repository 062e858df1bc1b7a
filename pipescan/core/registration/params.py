"""The parameters of frame registration, with the reasons for their defaults."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal

RegistrationMethod = Literal["point_to_plane", "gicp", "point_to_point"]
REGISTRATION_METHODS: tuple[str, ...] = ("gicp", "point_to_plane", "point_to_point")
"""``gicp`` (default, small_gicp only), ``point_to_plane`` and the paper's ``point_to_point``."""

RegistrationEngine = Literal["small_gicp", "open3d", "open3d_tensor"]
REGISTRATION_ENGINES: tuple[str, ...] = ("small_gicp", "open3d", "open3d_tensor")
"""Libraries that run the ICP step of ``point_to_plane`` and ``gicp``."""

_MIN_ICP_POINTS = 100
"""Fewer points than this are too few for ICP to place a frame in six degrees of freedom."""

AlongAxisPrior = Literal["odometer", "constant_velocity", "mixed"]


@dataclass(frozen=True)
class RegistrationParams:
    """Parameters of frame registration (see ``docs/registration.md`` for the measurements
    behind each default).

    Attributes
    ----------
    method : {"gicp", "point_to_plane", "point_to_point"}
        ``gicp`` (default; plane-to-plane) and ``point_to_plane`` run the full pipeline
        (filtering, fusion with the odometer, slide detection); ``point_to_point`` is the
        paper's ICP with the Kabsch/SVD step, kept as printed (NumPy, no fusion).
    engine : {"small_gicp", "open3d", "open3d_tensor"}
        Library running the ICP step. ``gicp`` needs ``small_gicp``. The Open3D engines use a
        Tukey robust kernel of width ``max_correspondence_m / 2``; small_gicp's Python API
        has none (its correspondence gate and the map filter stand in).
    voxel_m : float
        Voxel size of the local map, and of the test that keeps only map points seen from
        at least two frames (a surface persists from frame to frame; a spurious return, a
        mixed pixel or a drop does not).
    max_range_m : float
        Points further than this from the sensor are left out of registration (grazing,
        sparse and noisy at range).
    min_range_m : float
        Points nearer than this are left out: the sensor's blind zone, where what returns is
        its window, dust or a drip on it, never a surface
        (:class:`~pipescan.core.instrument.Instrument`, from the sensor's profile or the
        scan). Such returns travel with the sensor and pull ICP back along the pipe.
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
        pipe); there the prior attitude (IMU-corrected when gravity is given) is kept.
    odometer_scale_error_ratio : float
        The odometer's stated uncertainty: the largest share by which its count may be off
        the distance travelled (±3 % for a cable counter or wheel encoder on wet pipe). It
        weighs the odometer against ICP along the axis, bounds the chainage uncertainty of
        odometer-held stretches, and is what a slide must exceed to be caught.
    odometer_noise_m : float
        1σ noise of one odometer reading (its resolution and jitter).
    odometer_slip_m : float
        The largest slip the crawler's odometer may make where nothing can see it, as its
        operator states it (0: none stated). The chainage uncertainty allows for unseen slips
        at least this large, even where none was caught
        (:func:`~pipescan.core.registration.fusion.unseen_slip_allowance`).
    slide_window_m : float
        Slide detection compares registered and odometer travel over the frames of this
        much travel. Over 0.5 m, a 3 % odometer allows 1.5 cm (plus 3σ of its reading noise,
        4 mm): a smaller slide passes for the odometer's own error. The window must fit in a
        chunk of frames (60 frames are 0.9 m at 0.15 m/s).
    source_voxel_m : float, optional
        Voxel size of each frame, coarser than the map's: fewer points, faster ICP. ``None``
        uses ``voxel_m``.
    early_return_ratio : float
        A frame's (downsampled) return is dropped when fewer than two of the returns around
        it in direction (its ``EARLY_RETURN_NEIGHBOURS`` nearest rays) lie within
        ``1 / early_return_ratio`` of its range or nearer: it sits in front of every surface
        its neighbours hit, in free space they saw through. That is a spurious early return
        (mist, spray, a drip; issue 12 has them land at 20-100 % of the true range, so 0.8
        drops three quarters of them). Kept in, they crowd near the sensor and travel with
        it, and pull ICP back along a pipe (``docs/registration.md``, *Early returns*). 0
        turns the filter off.
    icp_max_points : int, optional
        At most this many of the frame's (downsampled) points enter ICP, a stride through
        them; the evidence read after ICP (the correspondences that weigh it against the
        odometer and give the fitness) still uses every point. ``None`` uses all.
    converged_rotation_rad, converged_translation_m : float
        small_gicp stops iterating once a step turns the frame by less than this and moves it
        by less than that. 0.5 mrad (1 mm at 2 m) and 0.5 mm: a fraction of the across-axis
        error the sweep measures with any setting (1-2 mm RMS); tighter, the last iterations
        only creep along the axis, where the fusion weighs ICP by its information anyway
        (swept: ``docs/registration.md``, *Convergence*). Steps along the axis where ICP has
        no information, and about it where roll is held, are not counted: the fusion
        discards them (``FrameRegistrar._icp``).
    map_seed_frames : int
        Frames that seed the local map, at the start and after a slide restarted it: each is
        registered against the frames before it and added to the map at once, as a keyframe
        of its own, instead of grouped over ``keyframe_distance_m``. 1 for a sensor whose
        every frame covers its field of view. A non-repetitive (rosette) pattern covers a part
        of it in one frame, and ICP against a map of one such frame has only the parts both
        saw to hold on to (measured: ``docs/instrument.md``).
        :func:`~pipescan.core.instrument.view_coverage` chooses it from what the scan's own
        consecutive frames cover.
    wide_correspondence_m : float, optional
        The gate a frame is registered with instead, where it finds fewer than 30
        correspondences within ``max_correspondence_m``: a partial view's tight gate
        (:func:`~pipescan.core.instrument.partial_view_gate_m`) against a map just restarted
        from a frame or two, from a prediction without an IMU, can find none. None: no
        second try (the frame is an error, as before).
    num_threads : int
        Threads the engine may use for one frame. 1 by default: parallelism comes from
        registering chunks of frames in parallel, in processes. On a thread pool, small_gicp
        (which holds the GIL) registers one chunk at a time, and the inspect flow gives each
        call the pool's cores instead (:func:`pipescan.flows.runners.engine_threads`).

    Raises
    ------
    ValueError
        From construction, for an unknown method or engine or an out-of-range value.
    """

    method: RegistrationMethod = "gicp"
    engine: RegistrationEngine = "small_gicp"
    voxel_m: float = 0.03
    max_range_m: float = 6.0
    min_range_m: float = 0.0
    max_correspondence_m: float = 0.08
    max_iterations: int = 15
    keyframe_distance_m: float = 0.15
    map_keyframes: int = 8
    degeneracy_ratio: float = 0.01
    odometer_scale_error_ratio: float = 0.03
    odometer_noise_m: float = 0.001
    odometer_slip_m: float = 0.0
    slide_window_m: float = 0.5
    source_voxel_m: float | None = 0.045
    early_return_ratio: float = 0.8
    icp_max_points: int | None = None
    converged_rotation_rad: float = 5e-4
    converged_translation_m: float = 5e-4
    num_threads: int = 1
    map_seed_frames: int = 1
    wide_correspondence_m: float | None = None

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
        positive = (
            "voxel_m", "max_range_m", "max_correspondence_m", "keyframe_distance_m",
            "odometer_scale_error_ratio", "odometer_noise_m", "slide_window_m",
            "converged_rotation_rad", "converged_translation_m",
        )  # fmt: skip
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(
                    f"RegistrationParams.{name} must be > 0, got {getattr(self, name)!r}."
                )
        if not 0 <= self.min_range_m < self.max_range_m:
            raise ValueError(
                "RegistrationParams.min_range_m must be in [0, max_range_m), "
                f"got {self.min_range_m!r}."
            )
        if not self.odometer_slip_m >= 0:
            raise ValueError(
                f"RegistrationParams.odometer_slip_m must be >= 0, got {self.odometer_slip_m!r}."
            )
        if self.wide_correspondence_m is not None and not self.wide_correspondence_m > 0:
            raise ValueError(
                "RegistrationParams.wide_correspondence_m must be > 0 or None, "
                f"got {self.wide_correspondence_m!r}."
            )
        if self.source_voxel_m is not None and not self.source_voxel_m > 0:
            raise ValueError(
                "RegistrationParams.source_voxel_m must be > 0 or None, "
                f"got {self.source_voxel_m!r}."
            )
        if self.icp_max_points is not None and self.icp_max_points < _MIN_ICP_POINTS:
            raise ValueError(
                f"RegistrationParams.icp_max_points must be >= {_MIN_ICP_POINTS} or None, "
                f"got {self.icp_max_points!r}."
            )
        if not 0.0 <= self.early_return_ratio < 1.0:
            raise ValueError(
                "RegistrationParams.early_return_ratio must be in [0, 1), "
                f"got {self.early_return_ratio!r}."
            )
        for name in ("max_iterations", "map_keyframes", "num_threads", "map_seed_frames"):
            if getattr(self, name) < 1:
                raise ValueError(
                    f"RegistrationParams.{name} must be >= 1, got {getattr(self, name)!r}."
                )
        if not 0 <= self.degeneracy_ratio < 1:
            raise ValueError(
                "RegistrationParams.degeneracy_ratio must be in [0, 1), "
                f"got {self.degeneracy_ratio!r}."
            )

    def for_odometer(
        self, uncertainty_ratio: float | None, slip_m: float | None = None
    ) -> RegistrationParams:
        """These parameters with the crawler's own stated odometer uncertainty and largest
        unseen slip (from ``inspection.toml``), each unchanged where it states none.

        >>> RegistrationParams().for_odometer(0.05).odometer_scale_error_ratio
        0.05
        >>> RegistrationParams().for_odometer(None, 0.2).odometer_slip_m
        0.2
        >>> RegistrationParams().for_odometer(None) == RegistrationParams()
        True
        """
        params = self
        if uncertainty_ratio is not None:
            params = dataclasses.replace(
                params, odometer_scale_error_ratio=float(uncertainty_ratio)
            )
        if slip_m is not None:
            params = dataclasses.replace(params, odometer_slip_m=float(slip_m))
        return params

    @property
    def label(self) -> str:
        """The engine and method as a user reads them, e.g. ``small_gicp point_to_plane``."""
        if self.method == "point_to_point":
            return "paper point_to_point (Kabsch, NumPy)"
        return f"{self.engine} {self.method}"
