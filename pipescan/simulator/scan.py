"""Scan simulator: a forward-looking Livox HAP-like LiDAR on a crawler inside a pipe.

The simulator ray-casts a scene (pipe wall with an elliptical deformation, settled deposits,
box obstacles, an end wall) from a sensor that a crawler carries along the pipe axis, so that
occlusion shadows, blind zone and grazing-angle sparsity are real rather than painted on. It
is the ground truth of every accuracy test and benchmark in pipescan.

Frames
    Frame ``i`` is generated lazily and deterministically from ``(seed, i)``: nothing of the
    scan is held in memory beyond one frame and the per-frame poses, so a 100 m scan costs
    the same memory as a 1 m one.
Scan pattern
    A non-repetitive pattern like the HAP's: an R2 low-discrepancy sequence whose index runs
    on across frames (frame ``i`` emits rays ``i * N ... (i + 1) * N - 1``), warped by an odd
    cubic so that the angular spacing at the centre of the field of view is
    ``centre_to_edge_spacing_ratio`` times that at the edges (0.2° versus 0.3°). One frame
    covers the field of view evenly; successive frames fill the gaps.
Frames of reference
    Sensor frame: x forward, y left, z up, metres. Pipe frame: origin on the axis at the scan
    start (where the odometer reads 0), x along the axis (downstream), z up (perpendicular to
    the axis, in the vertical plane), y left. The world frame is the pipe frame turned by
    ``world_yaw_deg``, tilted down by ``world_gradient_ratio`` and shifted by
    ``world_origin_m``, so that no coordinate axis is the pipe axis.
Simplifications (on purpose)
    One pose per frame (no motion within the 0.1 s of a frame) unless
    ``Effects.motion_within_frame`` is set; the crawler's body is not
    modelled (the sensor may pass above deposits and below obstacles, but never through
    them: :class:`Scenario` checks it); returns at 0.5-2 m are not distorted.
Ground truth
    :meth:`SimulatedScan.true_sections` gives per section the exact free cross-section area
    (ellipse minus deposit segment analytically, minus obstacles by quadrature), and the true
    coverage and shadow from a noise-free pass over every frame with one ray in
    ``truth_ray_stride`` (see :meth:`SimulatedScan.true_sections`).

Examples
--------
>>> scan = simulate_scan("paper", seed=1)
>>> frame = scan.frame(0)
>>> frame.points_sensor.shape[1], frame.points_sensor.dtype
(3, dtype('float32'))
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import TypeVar

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from pipescan.core.coding import clock_angle_rad
from pipescan.core.model import FrameRef, InspectionMeta
from pipescan.simulator.sensors import RingProfiler, StaticScanner, WaterLevel

SCENARIO_NAMES = ("paper", "clean", "long", "ring", "static")
"""Names accepted by :func:`get_scenario` and :func:`simulate_scan`."""

SURFACE_NONE = 0
"""Surface id of a ray that hits nothing (cannot happen while the end wall closes the pipe)."""
SURFACE_WALL = 1
"""Surface id of the pipe wall (circular or elliptically deformed)."""
SURFACE_END_WALL = 2
"""Surface id of the end wall that closes the pipe at ``Scenario.end_wall_m``."""
SURFACE_DEPOSIT = 3
"""Surface id of the top of settled deposits."""
SURFACE_OBSTACLE = 4
"""Surface id of a box obstacle."""
SURFACE_WATER = 5
"""Surface id of the water's surface (:class:`~pipescan.simulator.sensors.WaterLevel`)."""
SURFACE_BAND = 6
"""Surface id of attached deposits (a band on the wall, :class:`WallBand`)."""

COVERAGE_BIN_DEG = 2.0
"""Angular bin (degrees, around the pipe axis) of the true coverage."""

COVERAGE_CHAINAGE_BIN_M = 0.01
"""Chainage resolution of the cached true-coverage grid: section steps must be multiples."""

AREA_QUADRATURE_POINTS = 2001
"""Trapezoid nodes over each obstacle's angular span when subtracting it from the free area."""

SUB_SLICES_PER_SECTION = 20
"""Sub-slices whose free areas are averaged into a section's true open area."""

PACKETS_PER_FRAME = 50
"""Packets a frame's rays are fired in with ``Effects.motion_within_frame`` (2 ms each at
10 Hz): the rays of a packet share its time and pose, as a sensor stamps a packet of points.
At 0.5 m/s the sensor moves 1 mm from one packet to the next."""

# R2 sequence (Roberts 2018): the plastic number's powers give the most even 2-D
# Kronecker sequence, with no period a scan could reveal.
_PLASTIC = 1.324717957244746
_R2_ALPHA = (1.0 / _PLASTIC, 1.0 / _PLASTIC**2)

# Attitude jitter: a sum of sinusoids per axis, with periods a crawler's rocking has.
_JITTER_TERMS = 3
_JITTER_PERIOD_RANGE_S = (1.5, 20.0)

# Two returns closer than this in range are one surface seen at a slant, not a depth edge.
_MIXED_PIXEL_MIN_GAP_M = 0.02

_ILLINOIS_STEPS = 7
_MARCH_STEP_M = 0.02
_SENSOR_CLEARANCE_M = 0.02


def sensor_mount_z_m(
    diameter_m: float, deposit_peak_ratios: Sequence[float], mount_jitter_m: float
) -> float:
    """A sensor height (pipe frame, m) that clears every deposit: 5 cm below the axis of a
    0.5 m pipe, scaled with the pipe, or above the highest deposit's top by the clearance
    :class:`Scenario` checks (2 cm and 4σ of the mount jitter) and 5 mm more."""
    clearance_m = _SENSOR_CLEARANCE_M + 4.0 * mount_jitter_m + 0.005
    tops = [-diameter_m / 2.0 + ratio * diameter_m for ratio in deposit_peak_ratios]
    return max([-0.05 * (diameter_m / 0.5)] + [top + clearance_m for top in tops])


@dataclass(frozen=True)
class EllipticalDeformation:
    """The wall squeezed into an ellipse over ``[start_m, end_m]``, ramped in and out.

    Positions are distances along the axis from the scan start (pipe-frame x), in metres.
    At full strength the vertical semi-axis is ``r (1 - vertical_reduction_ratio)`` and the
    horizontal one ``r (1 + horizontal_increase_ratio)``; the strength follows a raised
    cosine over ``ramp_m`` at each end.
    """

    start_m: float
    end_m: float
    ramp_m: float
    vertical_reduction_ratio: float
    horizontal_increase_ratio: float


@dataclass(frozen=True)
class DepositFill:
    """Settled deposits: a flat-topped fill at the invert over ``[start_m, end_m]``.

    Its top is horizontal across the pipe, at ``peak_height_ratio`` of the nominal diameter
    above the nominal invert, and ramps linearly from the invert over ``ramp_m`` at each end.
    """

    start_m: float
    end_m: float
    ramp_m: float
    peak_height_ratio: float


@dataclass(frozen=True)
class BoxObstacle:
    """A box in the pipe frame, e.g. an object intruding from the crown.

    ``start_m``/``end_m`` bound it along the axis (pipe-frame x); ``y_*_m`` across (left
    positive) and ``z_*_m`` vertically (up positive), metres from the axis. Let it reach
    beyond the wall (``z_max_m > r``) for an object that hangs from the crown.
    """

    start_m: float
    end_m: float
    y_min_m: float
    y_max_m: float
    z_min_m: float
    z_max_m: float


@dataclass(frozen=True)
class WallBand:
    """Attached deposits (encrustation, grease): a layer of ``thickness_m`` on the wall.

    It covers ``[start_m, end_m]`` along the axis and the arc running clockwise from
    ``clock_from_h`` to ``clock_to_h`` (clock positions in hours looking downstream, 12 at the
    crown, 3 on the right; see :func:`pipescan.core.coding.clock_angle_rad`, which gives the
    pipe-frame angle ``atan2(z, y)``). Its inner face is the cylinder of
    radius ``r - thickness_m`` (the nominal radius less the thickness), its ends are planes
    across the axis and its sides radial planes, so it stands off the wall with square edges.
    Where a deformation brings the wall inside that face, the band is not there.
    """

    start_m: float
    end_m: float
    clock_from_h: float
    clock_to_h: float
    thickness_m: float

    @property
    def arc_rad(self) -> tuple[float, float]:
        """Its pipe-frame angles ``(first, last)``, radians; ``last > first`` (may pass 2π)."""
        first = clock_angle_rad(self.clock_from_h)
        last = clock_angle_rad(self.clock_to_h)
        return first, last if last > first else last + 2.0 * np.pi

    def covers(self, angle_rad: np.ndarray) -> np.ndarray:
        """Whether each pipe-frame angle (radians) lies on the band's arc."""
        first, last = self.arc_rad
        return np.mod(np.asarray(angle_rad) - first, 2.0 * np.pi) <= last - first


@dataclass(frozen=True)
class Effects:
    """What a real sensor on a real crawler in a real sewer does to a scan.

    Every effect is on by default, at a value in the middle of what sewer inspections meet;
    :meth:`ideal` switches them all off. Each has its own random stream (seeded from the scan's
    seed), so turning one effect on or off leaves the draws of the others unchanged. Add a
    new effect as a field here (with its check in ``__post_init__``) and use it in
    :class:`SimulatedScan`.

    Sensor (per return)
        ``range_noise_sigma_m`` is the 1σ range noise of a return at zero range and normal
        incidence; it grows by ``range_noise_growth_per_m`` per metre of range and by
        ``1 / sqrt(cos(incidence))`` towards grazing incidence (weaker returns), at most by
        ``grazing_noise_max_factor``. Defaults: 3.5 mm at 1 m facing the wall, ~8 mm on the
        wall 2 m ahead, ~11 mm at 5 m. A share ``spurious_return_ratio`` of the rays return
        early (mist, spray, dust, drips), anywhere along the ray between the blind zone and the
        surface; with ``spurious_range_ratio`` (lowest, highest) they land at that share of the
        true range instead, and the sensor reports those inside its blind zone too (dust on the
        window, a drip on the lens: what a real sensor reports, where pipescan's own default
        sensor reports nothing). Where the beam's footprint (``beam_footprint_deg`` from its
        centre) straddles a depth edge between two surfaces, a share ``mixed_pixel_ratio`` of
        such rays return a range between the two (a mixed pixel).
    Attitude and mount (per frame)
        ``rocking_deg``: smooth rocking, per axis a sum of sinusoids with periods of 1.5-20 s
        and peak at most this. ``vibration_deg``: 1σ per axis of an attitude change drawn
        anew every frame. ``mount_jitter_m``: 1σ of the sensor's lateral (y and z) offset,
        drawn anew every frame.
    Odometer (cable counter)
        ``odometer_scale_error_ratio``: the count reads ``(1 + ratio)`` times the distance.
        ``odometer_noise_m``: 1σ per reading. Slip: ``slip_per_m`` events per metre of travel
        (Poisson), each lasting a time drawn from ``slip_duration_s``; half of them *stuck*
        (the crawler stands on debris while the count runs on) and half *sliding* (the crawler
        moves while the count stands).
    IMU
        ``imu`` False: no gravity at all. ``imu_noise_deg``: 1σ per axis of the measured
        gravity direction. ``imu_dropout_ratio``: share of frames that carry no gravity.
    Motion within a frame (off by default)
        ``motion_within_frame``: the frame's rays are fired over the frame period in scan
        order, in :data:`PACKETS_PER_FRAME` packets, and each packet is cast from the sensor's
        pose at its time (the trajectory between this frame's pose and the next one's:
        translation linearly, rotation by slerp; the last frame goes on at its last step).
        Each point's time is :attr:`SimulatedFrame.point_time_s`; the frame's pose
        (``T_world_sensor``) is the pose at its first packet. Off, every ray is cast from the
        frame's pose and the frame carries no point times.
    """

    range_noise_sigma_m: float = 0.003
    range_noise_growth_per_m: float = 0.0005
    grazing_noise_max_factor: float = 2.0
    spurious_return_ratio: float = 0.005
    spurious_range_ratio: tuple[float, float] | None = None
    mixed_pixel_ratio: float = 0.5
    beam_footprint_deg: float = 0.15
    rocking_deg: float = 1.0
    vibration_deg: float = 0.3
    mount_jitter_m: float = 0.002
    odometer_scale_error_ratio: float = 0.02
    odometer_noise_m: float = 0.0005
    slip_per_m: float = 0.1
    slip_duration_s: tuple[float, float] = (0.5, 2.0)
    imu: bool = True
    imu_noise_deg: float = 0.1
    imu_dropout_ratio: float = 0.02
    motion_within_frame: bool = False

    def __post_init__(self) -> None:
        non_negative = (
            "range_noise_sigma_m", "range_noise_growth_per_m", "beam_footprint_deg",
            "rocking_deg", "vibration_deg", "mount_jitter_m", "odometer_noise_m", "slip_per_m",
            "imu_noise_deg",
        )  # fmt: skip
        for name in non_negative:
            if not getattr(self, name) >= 0:
                raise ValueError(f"Effects.{name} must be >= 0, got {getattr(self, name)!r}.")
        for name in ("spurious_return_ratio", "mixed_pixel_ratio", "imu_dropout_ratio"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"Effects.{name} must be in [0, 1], got {getattr(self, name)!r}.")
        if not self.grazing_noise_max_factor >= 1:
            raise ValueError("Effects.grazing_noise_max_factor must be >= 1.")
        if not -0.5 < self.odometer_scale_error_ratio < 0.5:
            raise ValueError("Effects.odometer_scale_error_ratio must be in (-0.5, 0.5).")
        if self.spurious_range_ratio is not None:
            near, far = self.spurious_range_ratio
            if not 0 < near <= far <= 1:
                raise ValueError(
                    "Effects.spurious_range_ratio must be (lowest, highest), 0 < both <= 1."
                )
        lo, hi = self.slip_duration_s
        if not 0 <= lo <= hi:
            raise ValueError("Effects.slip_duration_s must be (shortest, longest), 0 <= shortest.")

    @classmethod
    def ideal(cls, **overrides: object) -> Effects:
        """No effect at all (a perfect sensor on a perfect crawler), except ``overrides``."""
        none: dict[str, object] = {f.name: 0.0 for f in dataclasses.fields(cls)}
        none.update(
            grazing_noise_max_factor=1.0,
            slip_duration_s=(0.0, 0.0),
            spurious_range_ratio=None,
            imu=True,
            imu_noise_deg=0.0,
            motion_within_frame=False,
        )
        none.update(overrides)
        return cls(**none)  # type: ignore[arg-type]

    @property
    def largest_attitude_swing_deg(self) -> float:
        """A bound on the attitude's excursion (rocking plus 4σ of vibration)."""
        return self.rocking_deg + 4.0 * self.vibration_deg

    def range_sigma_m(self, range_m: np.ndarray, cos_incidence: np.ndarray) -> np.ndarray:
        """1σ range noise (m) of returns at ``range_m`` hitting at ``cos_incidence``."""
        grazing = np.minimum(
            1.0 / np.sqrt(np.clip(cos_incidence, 1e-6, 1.0)), self.grazing_noise_max_factor
        )
        return (self.range_noise_sigma_m + self.range_noise_growth_per_m * range_m) * grazing


EFFECT_NAMES: tuple[str, ...] = tuple(f.name for f in dataclasses.fields(Effects))
"""Fields of :class:`Effects`; :func:`get_scenario` accepts them as overrides too."""


@dataclass(frozen=True)
class Scenario:
    """Every parameter of a simulated scan (see :func:`get_scenario` for the named ones).

    Distances in metres, angles in degrees, ratios as fractions. Positions of defects are
    distances along the axis from the scan start. The end wall stands
    ``end_wall_beyond_travel_m`` beyond the crawler's last position.

    Raises
    ------
    ValueError
        From construction, when a parameter is out of range or the sensor's path would cross
        a deposit or an obstacle.
    """

    name: str = "custom"
    nominal_diameter_m: float = 0.5
    travel_m: float = 4.5
    speed_m_s: float = 0.15
    speed_variation_ratio: float = 0.1
    speed_variation_period_s: float = 20.0
    points_per_s: float = 452_000.0
    frame_rate_hz: float = 10.0
    fov_horizontal_deg: float = 120.0
    fov_vertical_deg: float = 25.0
    centre_to_edge_spacing_ratio: float = 2.0 / 3.0
    frame_coverage_ratio: float = 1.0
    """Share of the field of view one frame covers. 1: every frame covers all of it (a
    repetitive pattern, or pipescan's own dense one). Below 1: a non-repetitive (rosette)
    pattern, as Livox's Avia and Mid series have: each frame traces ``ROSETTE_PETALS``
    wedges about the boresight, this share of the field of view in all, turned by the golden
    angle from frame to frame, so that the field of view fills over a few frames."""
    blind_zone_m: float = 0.5
    max_range_m: float = 150.0
    mount_offset_y_m: float = 0.01
    mount_offset_z_m: float = -0.05
    mount_pitch_deg: float = 3.0
    effects: Effects = field(default_factory=lambda: Effects())
    end_wall_beyond_travel_m: float = 2.0
    world_yaw_deg: float = 30.0
    world_gradient_ratio: float = 0.01
    world_origin_m: tuple[float, float, float] = (12.5, -4.0, 1.8)
    deformations: tuple[EllipticalDeformation, ...] = ()
    deposits: tuple[DepositFill, ...] = ()
    obstacles: tuple[BoxObstacle, ...] = ()
    bands: tuple[WallBand, ...] = ()
    truth_ray_stride: int = 4
    asset_id: str = "SIM-CUSTOM"
    upstream_node: str | None = "SIM-MH1"
    downstream_node: str | None = "SIM-MH2"
    inspected_at: datetime = field(default_factory=lambda: datetime(2024, 5, 14, 9, 30, tzinfo=UTC))
    material: str | None = "PVC"
    chainage_offset_m: float = 0.0
    sensor: RingProfiler | StaticScanner | None = None
    """Another sensor than the forward-looking one the fields above describe
    (:mod:`pipescan.simulator.sensors`)."""
    water: WaterLevel | None = None
    """Water standing in the invert (not blockage; the wall below it is never seen)."""

    def __post_init__(self) -> None:
        positive = (
            "nominal_diameter_m", "travel_m", "speed_m_s", "speed_variation_period_s",
            "points_per_s", "frame_rate_hz", "fov_horizontal_deg", "fov_vertical_deg",
            "centre_to_edge_spacing_ratio", "max_range_m", "end_wall_beyond_travel_m",
        )  # fmt: skip
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"Scenario.{name} must be > 0, got {getattr(self, name)!r}.")
        for name in ("blind_zone_m", "chainage_offset_m"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"Scenario.{name} must be >= 0, got {getattr(self, name)!r}.")
        if not 0.05 <= self.frame_coverage_ratio <= 1:
            raise ValueError("Scenario.frame_coverage_ratio must be in [0.05, 1].")
        if not 0 <= self.speed_variation_ratio < 1:
            raise ValueError("Scenario.speed_variation_ratio must be in [0, 1).")
        if self.truth_ray_stride < 1:
            raise ValueError("Scenario.truth_ray_stride must be >= 1.")
        if self.rays_per_frame < 1:
            raise ValueError("points_per_s / frame_rate_hz must give at least one ray per frame.")
        # Every ray must go forward (x > 0 in the pipe frame) for the end wall to close it.
        swing_deg = self.effects.largest_attitude_swing_deg
        if self.sensor is None and self.fov_horizontal_deg / 2 + swing_deg >= 89.0:
            raise ValueError("fov_horizontal_deg is too wide for a forward-looking sensor.")
        if (
            self.sensor is None
            and self.fov_vertical_deg / 2 + abs(self.mount_pitch_deg) + swing_deg >= 89
        ):
            raise ValueError("fov_vertical_deg + mount_pitch_deg point the sensor sideways.")
        if self.sensor is not None and self.effects.motion_within_frame:
            raise ValueError("Effects.motion_within_frame needs the forward-looking sensor.")
        if self.sensor is not None and self.deformations:
            # Deformations are cast for rays that go forward; these sensors also look back.
            raise ValueError("Scenario.deformations need the forward-looking sensor.")
        if self.water is not None and self.water.surface_z_m(self.radius_m) >= (
            self.mount_offset_z_m - _SENSOR_CLEARANCE_M - 4.0 * self.effects.mount_jitter_m
        ):
            raise ValueError("The sensor would be under water: lower WaterLevel.depth_ratio.")
        if (
            math.hypot(self.mount_offset_y_m, self.mount_offset_z_m)
            + 4.0 * self.effects.mount_jitter_m
            >= self.radius_m * 0.8
        ):
            raise ValueError("The sensor mount offset puts the sensor at or outside the wall.")
        for d in self.deformations:
            if not (d.end_m - d.start_m >= 2 * d.ramp_m and d.ramp_m > 0):
                raise ValueError(f"Deformation {d} needs end_m - start_m >= 2 ramp_m > 0.")
            if not (
                0 <= d.vertical_reduction_ratio < 0.5 and -0.5 < d.horizontal_increase_ratio < 0.5
            ):
                raise ValueError(f"Deformation {d} ratios must be below 0.5.")
        for f in self.deposits:
            if not (f.end_m - f.start_m >= 2 * f.ramp_m and f.ramp_m > 0):
                raise ValueError(f"Deposit {f} needs end_m - start_m >= 2 ramp_m > 0.")
            if not 0 <= f.peak_height_ratio < 1:
                raise ValueError(f"Deposit {f} peak_height_ratio must be in [0, 1).")
        spans = sorted((item.start_m, item.end_m) for item in self.deformations)
        for first, second in itertools.pairwise(spans):
            if second[0] < first[1]:
                raise ValueError(
                    f"Scenario.deformations must not overlap: spans {first}, {second}."
                )
        # Obstacles may share a stretch of pipe (one at the crown, one at the invert), not space.
        for a, b in itertools.combinations(self.obstacles, 2):
            if (
                a.start_m < b.end_m
                and b.start_m < a.end_m
                and a.y_min_m < b.y_max_m
                and b.y_min_m < a.y_max_m
                and a.z_min_m < b.z_max_m
                and b.z_min_m < a.z_max_m
            ):
                raise ValueError(f"Scenario.obstacles must not overlap: {a}, {b}.")
        for b in self.obstacles:
            if not (b.start_m < b.end_m and b.y_min_m < b.y_max_m and b.z_min_m < b.z_max_m):
                raise ValueError(f"Obstacle {b} must have min < max on every axis.")
        self._check_bands()
        self._check_sensor_path()

    def _check_bands(self) -> None:
        for band in self.bands:
            if not (band.start_m < band.end_m and 0 < band.thickness_m < 0.5 * self.radius_m):
                raise ValueError(f"Band {band} needs start_m < end_m and 0 < thickness_m < r / 2.")
            first, last = band.arc_rad
            if not 0 < last - first < 2.0 * np.pi - 1e-9:
                raise ValueError(f"Band {band} must cover part of the circumference, not all.")
            # The free area subtracts each solid on its own: a band may not share space with
            # an obstacle or another band.
            for other in (*self.obstacles, *self.bands):
                if other is band or other.end_m <= band.start_m or other.start_m >= band.end_m:
                    continue
                if isinstance(other, WallBand):
                    o_first, o_last = other.arc_rad
                    angles = np.linspace(o_first, o_last, 181)
                else:
                    y = np.linspace(other.y_min_m, other.y_max_m, 41)
                    z = np.linspace(other.z_min_m, other.z_max_m, 41)
                    yy, zz = np.meshgrid(y, z)
                    inside = np.hypot(yy, zz) >= self.radius_m - band.thickness_m
                    angles = np.arctan2(zz[inside], yy[inside])
                if band.covers(angles).any():
                    raise ValueError(f"Band {band} overlaps {other}.")

    def _check_sensor_path(self) -> None:
        # The ray caster assumes the sensor is in free space at every position; the crawler
        # carrying it is not modelled, so a path through a solid would be a silent error.
        x0, x1 = 0.0, self.travel_m
        y, z = self.mount_offset_y_m, self.mount_offset_z_m
        c = _SENSOR_CLEARANCE_M + 4.0 * self.effects.mount_jitter_m
        for f in self.deposits:
            if f.start_m <= x1 and f.end_m >= x0:
                top_z_m = -self.radius_m + f.peak_height_ratio * self.nominal_diameter_m
                if top_z_m > z - c:
                    raise ValueError(
                        f"The sensor (z = {z} m) would pass through deposit {f}: lower its "
                        "peak_height_ratio or raise mount_offset_z_m."
                    )
        for b in self.obstacles:
            if (
                b.start_m <= x1
                and b.end_m >= x0
                and (b.y_min_m - c < y < b.y_max_m + c and b.z_min_m - c < z < b.z_max_m + c)
            ):
                raise ValueError(
                    f"The sensor (y = {y} m, z = {z} m) would pass through obstacle {b}."
                )
            if b.start_m - c < 0 < b.end_m + c and b.z_min_m < z + c:
                raise ValueError(f"Obstacle {b} encloses the scan start.")
        for band in self.bands:
            if math.hypot(y, z) + c >= self.radius_m - band.thickness_m:
                raise ValueError(f"The sensor (y = {y} m, z = {z} m) would touch band {band}.")

    @property
    def radius_m(self) -> float:
        """Nominal inner radius (m)."""
        return self.nominal_diameter_m / 2.0

    @property
    def nominal_area_m2(self) -> float:
        """Nominal cross-section area (m²)."""
        return math.pi * self.radius_m**2

    @property
    def rays_per_frame(self) -> int:
        """Rays emitted per frame (returned points are fewer: blind zone, filtering)."""
        if self.sensor is not None:
            return self.sensor.rays_per_frame
        return round(self.points_per_s / self.frame_rate_hz)

    @property
    def end_wall_m(self) -> float:
        """Pipe-frame x of the end wall (m from the scan start)."""
        return self.travel_m + self.end_wall_beyond_travel_m


@dataclass(frozen=True)
class SimulatedFrame:
    """One LiDAR frame.

    ``points_sensor`` is (N, 3) float32, metres, in the sensor frame (x forward, y left,
    z up), each point as the sensor saw it when it was captured. ``T_world_sensor`` (4, 4)
    float64 is the true pose (at ``time_s``). ``odometer_m`` is the noisy odometer reading, as
    an archive would hold it; ``gravity`` the IMU's unit gravity direction in the sensor frame
    (None when ``Scenario.imu`` is off). ``point_time_s`` (N,) float64 is each point's capture
    time, seconds on the scan's clock (``time_s`` and later), with
    ``Effects.motion_within_frame``; None without (every point at ``time_s``).
    """

    index: int
    time_s: float
    odometer_m: float
    points_sensor: np.ndarray = field(repr=False)
    T_world_sensor: np.ndarray = field(repr=False)
    gravity: tuple[float, float, float] | None = None
    point_time_s: np.ndarray | None = field(default=None, repr=False)


@dataclass(frozen=True)
class TrueSection:
    """Ground truth of one section ``[chainage_start_m, chainage_end_m)``.

    ``open_area_m2`` is the exact free cross-section (wall ellipse minus deposit segment
    minus obstacles), in the plane perpendicular to the axis, averaged over
    :data:`SUB_SLICES_PER_SECTION` sub-slices; ``blockage_ratio = 1 - open / nominal``.
    ``deposit_height_ratio`` (deposit height above the local invert over the local pipe
    height) and ``deformation_ratio`` (largest diameter reduction against the nominal) are
    averaged the same way. ``coverage_ratio`` is the share of :data:`COVERAGE_BIN_DEG` bins
    around the pipe axis in which the section's free boundary (wall, deposit top, obstacle)
    was hit by at least one noise-free ray beyond the blind zone; ``in_shadow`` is true when
    some bin was reachable without deposits and obstacles but is hidden with them.
    """

    chainage_start_m: float
    chainage_end_m: float
    open_area_m2: float
    blockage_ratio: float
    deposit_height_ratio: float
    deformation_ratio: float
    coverage_ratio: float
    in_shadow: bool
    water_depth_ratio: float = 0.0
    """Depth of the water in the invert over the local pipe height (0: dry)."""


# --------------------------------------------------------------------------- scenarios

_PAPER_DEFORMATION = EllipticalDeformation(
    start_m=1.5, end_m=2.2, ramp_m=0.2, vertical_reduction_ratio=0.07,
    horizontal_increase_ratio=0.03,
)  # fmt: skip
# A 0.28 m wide object hanging from the crown to 0.118 m above the axis: 16.8 % blockage
# (Table 1, No. 5).
_PAPER_OBSTACLE = BoxObstacle(
    start_m=2.6, end_m=2.9, y_min_m=-0.14, y_max_m=0.14, z_min_m=0.1184, z_max_m=0.35
)
# Deposits 0.1425 m high (28.5 % of the height) on the plateau: 23.5 % blockage, just over
# Table 1's largest (23.1 %, No. 6); the ramps give the values in between.
_PAPER_DEPOSIT = DepositFill(start_m=3.4, end_m=4.3, ramp_m=0.25, peak_height_ratio=0.2851)
_LONG_REPEAT_M = 10.0


_Defect = TypeVar("_Defect", EllipticalDeformation, DepositFill, BoxObstacle)


def _shifted(defect: _Defect, dx_m: float) -> _Defect:
    return dataclasses.replace(defect, start_m=defect.start_m + dx_m, end_m=defect.end_m + dx_m)


def _named_scenario(name: str) -> Scenario:
    if name == "paper":
        # Defects sit where the forward-looking sensor sees them from 1.2 m and more (its
        # crown and invert rays first reach the wall ~1.1-1.2 m ahead), with clean pipe
        # between them and 2 m of clean pipe after the last one.
        return Scenario(
            name="paper", travel_m=4.5, asset_id="SIM-PAPER",
            deformations=(_PAPER_DEFORMATION,), deposits=(_PAPER_DEPOSIT,),
            obstacles=(_PAPER_OBSTACLE,),
        )  # fmt: skip
    if name == "clean":
        return Scenario(name="clean", travel_m=3.0, asset_id="SIM-CLEAN")
    if name == "ring":
        # A 2D ring profiler on a crawler in a 0.8 m sewer: 120 points a turn, 7.5 turns a
        # second at 0.3 m/s (a ring every 4 cm, about 300 points a section), 15 mm of range
        # noise, an obstacle from the crown and a deposit. Ranges are short: no blind zone.
        return Scenario(
            name="ring", nominal_diameter_m=0.8, travel_m=10.0, speed_m_s=0.3,
            frame_rate_hz=7.5, points_per_s=900.0, blind_zone_m=0.05,
            mount_offset_z_m=-0.08, mount_pitch_deg=0.0, end_wall_beyond_travel_m=0.5,
            sensor=RingProfiler(points_per_revolution=120, tilt_deg=3.0), truth_ray_stride=1,
            effects=Effects(range_noise_sigma_m=0.015, range_noise_growth_per_m=0.0),
            obstacles=(BoxObstacle(4.0, 4.4, -0.18, 0.18, 0.22, 0.5),),
            deposits=(DepositFill(6.5, 8.0, 0.3, 0.15),),
            asset_id="SIM-RING",
        )  # fmt: skip
    if name == "static":
        # A terrestrial scanner at three stations 4 m apart in a 0.8 m sewer, 0.4° steps,
        # 2 mm range noise; a tripod does not rock. The wall between stations is seen from
        # far away, sparse and grazing.
        return Scenario(
            name="static", nominal_diameter_m=0.8, travel_m=8.0, speed_m_s=4.0,
            frame_rate_hz=1.0, speed_variation_ratio=0.0, points_per_s=1.0, blind_zone_m=0.3,
            mount_offset_z_m=-0.1, mount_pitch_deg=0.0, end_wall_beyond_travel_m=1.0,
            sensor=StaticScanner(step_deg=0.4),
            effects=Effects(
                range_noise_sigma_m=0.002, rocking_deg=0.0, vibration_deg=0.0,
                mount_jitter_m=0.0, slip_per_m=0.0,
            ),
            deposits=(DepositFill(5.0, 6.5, 0.3, 0.15),),
            asset_id="SIM-STATIC",
        )  # fmt: skip
    if name == "long":
        offsets = [k * _LONG_REPEAT_M for k in range(10)]
        return Scenario(
            name="long", travel_m=100.0, asset_id="SIM-LONG",
            deformations=tuple(_shifted(_PAPER_DEFORMATION, o) for o in offsets),
            deposits=tuple(_shifted(_PAPER_DEPOSIT, o) for o in offsets),
            obstacles=tuple(_shifted(_PAPER_OBSTACLE, o) for o in offsets),
        )  # fmt: skip
    raise ValueError(f"Unknown scenario {name!r}: choose one of {', '.join(SCENARIO_NAMES)}.")


def get_scenario(name: str, **overrides: object) -> Scenario:
    """Return a named scenario, with some fields overridden.

    Parameters
    ----------
    name
        One of :data:`SCENARIO_NAMES`: ``paper`` (the paper's 0.5 m pipe with a deformation,
        an obstacle and deposits spanning 2.5-23 % blockage, 4.5 m of travel), ``clean``
        (no defects, 3 m), ``long`` (100 m, the paper's defects every 10 m), ``ring`` (a 2D
        ring profiler in a 0.8 m sewer, about 300 points a section, 15 mm noise) or
        ``static`` (a terrestrial scanner at three stations, sparse between them).
    **overrides
        Fields of :class:`Scenario` to replace, e.g. ``travel_m=1.0``, or of its
        :class:`Effects`, e.g. ``spurious_return_ratio=0.02``.

    Raises
    ------
    ValueError
        For an unknown name or field, or an invalid value.

    Examples
    --------
    >>> get_scenario("clean", travel_m=1.0).travel_m
    1.0
    """
    base = _named_scenario(name)
    known = {f.name for f in dataclasses.fields(Scenario)}
    unknown = sorted(set(overrides) - known - set(EFFECT_NAMES))
    if unknown:
        raise ValueError(
            f"Unknown Scenario field(s) {', '.join(unknown)}; "
            f"valid fields: {', '.join(sorted(known | set(EFFECT_NAMES)))}."
        )
    effect_overrides = {k: overrides.pop(k) for k in list(overrides) if k in EFFECT_NAMES}
    if effect_overrides:
        effects = overrides.get("effects", base.effects)
        assert isinstance(effects, Effects)
        overrides["effects"] = dataclasses.replace(effects, **effect_overrides)  # type: ignore[arg-type]
    return dataclasses.replace(base, **overrides)  # type: ignore[arg-type]


# --------------------------------------------------------------------------- geometry


def _rot_x(a_rad: float) -> np.ndarray:
    c, s = math.cos(a_rad), math.sin(a_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_y(a_rad: float) -> np.ndarray:
    c, s = math.cos(a_rad), math.sin(a_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_z(a_rad: float) -> np.ndarray:
    c, s = math.cos(a_rad), math.sin(a_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _pose(rotation: np.ndarray, translation: np.ndarray | tuple[float, ...]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rotation
    T[:3, 3] = translation
    return T


def world_from_pipe(scenario: Scenario) -> np.ndarray:
    """Return ``T_world_pipe`` (4, 4): the pipe frame placed in the world.

    The axis is turned by ``world_yaw_deg`` about the vertical and runs downhill at
    ``world_gradient_ratio``; the pipe frame's z stays in the vertical plane.
    """
    gradient_rad = math.atan(scenario.world_gradient_ratio)
    rotation = _rot_z(math.radians(scenario.world_yaw_deg)) @ _rot_y(gradient_rad)
    return _pose(rotation, scenario.world_origin_m)


def _warp(t: np.ndarray, spacing_ratio: float) -> np.ndarray:
    # Odd cubic w(t) = a t + b t^3 with w(1) = 1 and w'(0) / w'(1) = spacing_ratio: samples
    # uniform in t come out denser at the centre of the field of view.
    a = 3.0 * spacing_ratio / (2.0 * spacing_ratio + 1.0)
    return t * (a + (1.0 - a) * t * t)


def _pattern_dirs(scenario: Scenario, ray_index: np.ndarray) -> np.ndarray:
    k = ray_index.astype(np.float64)
    u = np.mod(0.5 + k * _R2_ALPHA[0], 1.0)
    v = np.mod(0.5 + k * _R2_ALPHA[1], 1.0)
    q = scenario.centre_to_edge_spacing_ratio
    az = np.radians(scenario.fov_horizontal_deg / 2.0) * _warp(2.0 * u - 1.0, q)
    el = np.radians(scenario.fov_vertical_deg / 2.0) * _warp(2.0 * v - 1.0, q)
    cos_el = np.cos(el)
    return np.stack([cos_el * np.cos(az), cos_el * np.sin(az), np.sin(el)], axis=1)


ROSETTE_PETALS = 3
"""Wedges a frame of the non-repetitive pattern traces (``Scenario.frame_coverage_ratio``)."""
_GOLDEN_ANGLE_RAD = math.pi * (3.0 - math.sqrt(5.0))


def _frame_pattern_dirs(
    scenario: Scenario, frame_index: int, stride: int = 1, first: int = 0
) -> np.ndarray:
    """Directions of frame ``frame_index``'s rays (every ``stride``-th from ``first``).

    A repetitive pattern takes rays ``i * N ... (i + 1) * N - 1`` of the endless sequence.
    A non-repetitive one with coverage ``c < 1`` takes the next ``N / c`` rays of the
    sequence and keeps those that fall in the frame's wedges: ``N`` rays on ``c`` of the field
    of view (the wedges are equal shares of the angle about the boresight, in the field of
    view's normalised coordinates, so each holds that share of the rays).
    """
    n, c = scenario.rays_per_frame, scenario.frame_coverage_ratio
    if c >= 1.0:
        return _pattern_dirs(
            scenario, np.arange(frame_index * n + first, (frame_index + 1) * n, stride)
        )
    m = math.ceil(n / c)
    k = np.arange(frame_index * m, (frame_index + 1) * m)
    u = np.mod(0.5 + k * _R2_ALPHA[0], 1.0) - 0.5
    v = np.mod(0.5 + k * _R2_ALPHA[1], 1.0) - 0.5
    phase = np.mod(np.arctan2(v, u) - frame_index * _GOLDEN_ANGLE_RAD, 2.0 * math.pi)
    petal = 2.0 * math.pi / ROSETTE_PETALS
    k = k[np.mod(phase, petal) < c * petal][:n]
    return _pattern_dirs(scenario, k[first::stride])


def ray_directions_sensor(scenario: Scenario, frame_index: int) -> np.ndarray:
    """Unit ray directions of one frame, in the sensor frame.

    Parameters
    ----------
    scenario
        Supplies the field of view, spacing ratio and rays per frame ``N``.
    frame_index
        Frame ``i``; its rays are ``i * N ... (i + 1) * N - 1`` of the endless pattern.

    Returns
    -------
    (N, 3) float64 array of unit vectors (x forward, y left, z up).
    """
    if scenario.sensor is not None:
        return scenario.sensor.directions(frame_index)
    return _frame_pattern_dirs(scenario, frame_index)


def _circle_exit_t(
    oy: float, oz: float, dy: np.ndarray, dz: np.ndarray, radius_m: float | np.ndarray
) -> np.ndarray:
    """Distance along each ray to where it leaves the cylinder of ``radius_m`` (origin inside)."""
    a = dy * dy + dz * dz
    b = oy * dy + oz * dz
    c = oy * oy + oz * oz - radius_m * radius_m
    s = np.sqrt(b * b - a * c)
    with np.errstate(divide="ignore", invalid="ignore"):
        # The two algebraic forms of the positive root, each used where it does not cancel.
        t = np.where(b >= 0.0, -c / (b + s), (s - b) / a)
    return np.where(np.isnan(t), np.inf, t)


def _raised_cosine(x_m: np.ndarray, start_m: float, end_m: float, ramp_m: float) -> np.ndarray:
    u = np.clip(np.minimum(x_m - start_m, end_m - x_m) / ramp_m, 0.0, 1.0)
    return 0.5 - 0.5 * np.cos(np.pi * u)


def ellipse_axes_m(scenario: Scenario, x_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal and vertical semi-axes (m) of the wall at pipe-frame ``x_m`` (any shape)."""
    x_m = np.asarray(x_m, dtype=np.float64)
    r = scenario.radius_m
    a = np.full(x_m.shape, r)
    b = np.full(x_m.shape, r)
    for d in scenario.deformations:
        w = _raised_cosine(x_m, d.start_m, d.end_m, d.ramp_m)
        a = a + r * d.horizontal_increase_ratio * w
        b = b - r * d.vertical_reduction_ratio * w
    return a, b


def deposit_top_z_m(scenario: Scenario, x_m: np.ndarray) -> np.ndarray:
    """Pipe-frame z (m) of the deposit top at ``x_m``; ``-inf`` where there is no deposit."""
    x_m = np.asarray(x_m, dtype=np.float64)
    top = np.full(x_m.shape, -np.inf)
    d_m = scenario.nominal_diameter_m
    for f in scenario.deposits:
        h = (
            f.peak_height_ratio
            * d_m
            * np.clip(np.minimum(x_m - f.start_m, f.end_m - x_m) / f.ramp_m, 0, 1)
        )
        inside = (x_m >= f.start_m) & (x_m <= f.end_m)
        top = np.where(inside, np.maximum(top, -scenario.radius_m + h), top)
    return top


def _deformation_axes_m(
    d: EllipticalDeformation, r: float, x_m: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    w = _raised_cosine(x_m, d.start_m, d.end_m, d.ramp_m)
    return r * (1.0 + d.horizontal_increase_ratio * w), r * (1.0 - d.vertical_reduction_ratio * w)


def _first_root_in_span(
    d: EllipticalDeformation,
    r: float,
    o: np.ndarray,
    ray: tuple[np.ndarray, np.ndarray, np.ndarray],
    t_lo: np.ndarray,
    t_hi: np.ndarray,
) -> np.ndarray:
    """First t in [t_lo, t_hi] where each ray leaves the deformed wall (inf where it does not)."""
    ox, oy, oz = o
    dx, dy, dz = ray

    def g(tt: np.ndarray, sx: np.ndarray, sy: np.ndarray, sz: np.ndarray) -> np.ndarray:
        a, b = _deformation_axes_m(d, r, ox + tt * sx)
        return (oy + tt * sy) ** 2 / (a * a) + (oz + tt * sz) ** 2 / (b * b) - 1.0

    root = np.full(t_lo.shape, np.inf)
    # March at most _MARCH_STEP_M apart along the axis to find the first sign change (a ray
    # could otherwise pierce a short dent between two samples), with rays bucketed by the
    # number of samples they need so that short windows stay cheap.
    n_steps = np.ceil((t_hi - t_lo) * dx / _MARCH_STEP_M).astype(np.int64)
    bucket = np.ceil(np.log2(np.maximum(n_steps, 1))).astype(np.int64)
    for level in np.unique(bucket):
        idx = np.flatnonzero(bucket == level)
        frac = np.linspace(0.0, 1.0, 2**level + 1)[None, :]
        lo, hi = t_lo[idx], t_hi[idx]
        ts = lo[:, None] + (hi - lo)[:, None] * frac
        sx, sy, sz = dx[idx], dy[idx], dz[idx]
        gs = g(ts, sx[:, None], sy[:, None], sz[:, None])
        outside = gs >= 0.0
        has_root = outside.any(axis=1)
        k = np.argmax(outside, axis=1)
        rows = np.arange(idx.size)
        ka = np.maximum(k - 1, 0)
        a_t, b_t = ts[rows, ka], ts[rows, k]
        ga, gb = gs[rows, ka], gs[rows, k]
        # Illinois (regula falsi with halving): superlinear on these smooth brackets.
        side = np.zeros(idx.size, dtype=np.int8)
        c = b_t
        for _ in range(_ILLINOIS_STEPS):
            with np.errstate(divide="ignore", invalid="ignore"):
                c = np.where(gb > ga, (a_t * gb - b_t * ga) / (gb - ga), b_t)
            gc = g(c, sx, sy, sz)
            out = gc >= 0.0
            ga_new = np.where(out, np.where(side == 1, ga / 2, ga), gc)
            gb_new = np.where(out, gc, np.where(side == -1, gb / 2, gb))
            a_t = np.where(out, a_t, c)
            b_t = np.where(out, c, b_t)
            ga, gb = ga_new, gb_new
            side = np.where(out, 1, -1).astype(np.int8)
        root[idx] = np.where(has_root, c, np.inf)
    return root


def _wall_t(
    scenario: Scenario, o: np.ndarray, d: np.ndarray, t_end: np.ndarray, min_range_m: float
) -> np.ndarray:
    ox, oy, oz = o
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
    r = scenario.radius_m
    t_nom = _circle_exit_t(oy, oz, dy, dz, r)
    if not scenario.deformations:
        return t_nom
    # Deformations do not overlap (Scenario checks it), so the first hit is the earliest of:
    # the circle exit where it falls outside every span, the ellipse exit where it falls on
    # a plateau (both exact), and the first root on each ramp (found numerically).
    x_nom = ox + t_nom * dx
    in_span = np.zeros(t_nom.shape, dtype=bool)
    for df in scenario.deformations:
        in_span |= (x_nom >= df.start_m) & (x_nom <= df.end_m)
    t = np.where(in_span, np.inf, t_nom)
    # Inside the inscribed cylinder every ellipse contains the ray; outside the circumscribed
    # one none does: a hit on a deformation lies between the two. Only rays that are between
    # them somewhere in a deformation's span need that deformation's work.
    factors = [1.0]
    for df in scenario.deformations:
        factors += [1.0 - df.vertical_reduction_ratio, 1.0 + df.horizontal_increase_ratio]
    t_in = _circle_exit_t(oy, oz, dy, dz, r * min(factors))
    t_out = np.minimum(_circle_exit_t(oy, oz, dy, dz, r * max(factors)), t_end)
    x_in, x_out = ox + t_in * dx, ox + t_out * dx
    for df in scenario.deformations:
        c = np.flatnonzero((x_out >= df.start_m) & (x_in <= df.end_m) & (t_in <= t_out))
        if c.size:
            t[c] = _deformation_t(
                df, r, o, (dx[c], dy[c], dz[c]), t[c], t_in[c], t_out[c], min_range_m
            )
    return t


def _deformation_t(
    df: EllipticalDeformation,
    r: float,
    o: np.ndarray,
    ray: tuple[np.ndarray, np.ndarray, np.ndarray],
    t: np.ndarray,
    t_in: np.ndarray,
    t_out: np.ndarray,
    min_range_m: float,
) -> np.ndarray:
    """Lower ``t`` to the hit on one deformation's plateau (exact) or ramps (numerical)."""
    ox, oy, oz = o
    dx, dy, dz = ray
    with np.errstate(divide="ignore"):
        inv_dx = 1.0 / dx
    a_m = r * (1.0 + df.horizontal_increase_ratio)
    b_m = r * (1.0 - df.vertical_reduction_ratio)
    plateau = (df.start_m + df.ramp_m, df.end_m - df.ramp_m)
    if plateau[1] > plateau[0]:
        t_ell = _circle_exit_t(oy / a_m, oz / b_m, dy / a_m, dz / b_m, 1.0)
        x_ell = ox + t_ell * dx
        on = (x_ell >= plateau[0]) & (x_ell <= plateau[1])
        t = np.where(on, np.minimum(t, t_ell), t)
    for x0, x1 in ((df.start_m, plateau[0]), (plateau[1], df.end_m)):
        t_lo = np.maximum(t_in, (x0 - ox) * inv_dx)
        t_x1 = (x1 - ox) * inv_dx
        t_hi = np.minimum(t_out, t_x1)
        window = (t_lo <= t_hi) & (t_lo < t)
        # A hit certainly inside the blind zone needs no exact range: it is never returned.
        # (Certain only when the ray leaves the circumscribed cylinder on this ramp.)
        blind = window & (t_out < min_range_m) & (t_out <= t_x1)
        t = np.where(blind, np.minimum(t, t_hi), t)
        idx = np.flatnonzero(window & ~blind)
        if idx.size == 0:
            continue
        sub = (dx[idx], dy[idx], dz[idx])
        root = _first_root_in_span(df, r, o, sub, t_lo[idx], t_hi[idx])
        t[idx] = np.minimum(t[idx], root)
    return t


def _apply_occluders(
    scenario: Scenario, o: np.ndarray, d: np.ndarray, t: np.ndarray, surface: np.ndarray
) -> None:
    """Lower ``t`` (in place) where a deposit or obstacle is hit first, and mark ``surface``."""
    ox, oy, oz = o
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
    x_far = ox + np.minimum(t, 1e6) * dx
    r, d_m = scenario.radius_m, scenario.nominal_diameter_m
    with np.errstate(divide="ignore", invalid="ignore"):
        # Rays may go backwards (a ring profiler, a static scanner): test the span they cross.
        x_lo, x_hi = np.minimum(ox, x_far), np.maximum(ox, x_far)
        for f in scenario.deposits:
            cand = np.flatnonzero((x_hi >= f.start_m) & (x_lo <= f.end_m))
            if cand.size == 0:
                continue
            h = f.peak_height_ratio * d_m
            # The top is three planes z = z0 + slope (x - x0) over [x0, x1]; the sensor is
            # above it, so the first downward crossing of any piece is the entry point.
            pieces = (
                (f.start_m, f.start_m + f.ramp_m, -r, h / f.ramp_m),
                (f.start_m + f.ramp_m, f.end_m - f.ramp_m, -r + h, 0.0),
                (f.end_m - f.ramp_m, f.end_m, -r + h, -h / f.ramp_m),
            )
            cdx, cdz = dx[cand], dz[cand]
            for x0, x1, z0, slope in pieces:
                if x1 <= x0:
                    continue
                denom = cdz - slope * cdx
                tp = (z0 + slope * (ox - x0) - oz) / denom
                xp = ox + tp * cdx
                hit = (denom < 0) & (tp > 0) & (xp >= x0) & (xp <= x1) & (tp < t[cand])
                sel = cand[hit]
                t[sel] = tp[hit]
                surface[sel] = SURFACE_DEPOSIT
        for b in scenario.obstacles:
            cand = np.flatnonzero((x_hi >= b.start_m) & (x_lo <= b.end_m))
            if cand.size == 0:
                continue
            t_enter = np.full(cand.size, -np.inf)
            t_exit = np.full(cand.size, np.inf)
            for o_c, d_c, lo, hi in (
                (ox, dx[cand], b.start_m, b.end_m),
                (oy, dy[cand], b.y_min_m, b.y_max_m),
                (oz, dz[cand], b.z_min_m, b.z_max_m),
            ):
                inv = 1.0 / d_c
                t1, t2 = (lo - o_c) * inv, (hi - o_c) * inv
                t_enter = np.maximum(t_enter, np.minimum(t1, t2))
                t_exit = np.minimum(t_exit, np.maximum(t1, t2))
            hit = (t_enter <= t_exit) & (t_enter > 0) & (t_enter < t[cand])
            sel = cand[hit]
            t[sel] = t_enter[hit]
            surface[sel] = SURFACE_OBSTACLE
        water = scenario.water
        if water is not None:
            z_w = water.surface_z_m(r)
            t_w = (z_w - oz) / dz
            x_w = ox + t_w * dx
            hit = (dz < 0) & (t_w > 0) & (t_w < t) & (x_w >= water.start_m) & (x_w <= water.end_m)
            t[hit] = t_w[hit]
            surface[hit] = SURFACE_WATER
        for band in scenario.bands:
            cand = np.flatnonzero((x_far >= band.start_m) & (ox <= band.end_m))
            if cand.size:
                t_band = _band_t(scenario, band, o, d[cand])
                hit = t_band < t[cand]
                sel = cand[hit]
                t[sel] = t_band[hit]
                surface[sel] = SURFACE_BAND


def _band_t(scenario: Scenario, band: WallBand, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Distance along each ray (origin ``o`` inside the band's inner face) to its first hit on
    ``band``: the inner face, an end face or a side face; ``inf`` where it misses."""
    ox, oy, oz = o
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
    inner = scenario.radius_m - band.thickness_m
    first, last = band.arc_rad
    best = np.full(len(d), np.inf)

    def keep(t_hit: np.ndarray, valid: np.ndarray) -> None:
        ok = valid & (t_hit > 0) & (t_hit < best)
        best[ok] = t_hit[ok]

    with np.errstate(divide="ignore", invalid="ignore"):
        t_face = _circle_exit_t(oy, oz, dy, dz, inner)
        x, y, z = ox + t_face * dx, oy + t_face * dy, oz + t_face * dz
        keep(t_face, (x >= band.start_m) & (x <= band.end_m) & band.covers(np.arctan2(z, y)))
        for x_end in (band.start_m, band.end_m):
            t_end = (x_end - ox) / dx
            y, z = oy + t_end * dy, oz + t_end * dz
            rho = np.hypot(y, z)
            keep(t_end, (rho >= inner) & (rho <= scenario.radius_m) & band.covers(np.arctan2(z, y)))
        for angle in (first, last):
            c, s = math.cos(angle), math.sin(angle)
            # The radial half-plane at this angle: points (y, z) = rho (c, s), rho > 0.
            t_side = (oy * s - oz * c) / (dz * c - dy * s)
            x, y, z = ox + t_side * dx, oy + t_side * dy, oz + t_side * dz
            rho = y * c + z * s
            keep(
                t_side,
                (x >= band.start_m)
                & (x <= band.end_m)
                & (rho >= inner)
                & (rho <= scenario.radius_m),
            )
    return best


def _cast_free(
    scenario: Scenario, o: np.ndarray, d: np.ndarray, min_range_m: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    with np.errstate(divide="ignore"):
        t_end = np.where(d[:, 0] > 0, (scenario.end_wall_m - o[0]) / d[:, 0], np.inf)
    t_wall = _wall_t(scenario, o, d, t_end, min_range_m)
    t = np.minimum(t_wall, t_end)
    surface = np.where(t_wall < t_end, SURFACE_WALL, SURFACE_END_WALL).astype(np.int8)
    surface[~np.isfinite(t)] = SURFACE_NONE
    return t, surface


def cast_rays(
    scenario: Scenario,
    origin_pipe_m: np.ndarray,
    dirs_pipe: np.ndarray,
    *,
    occluders: bool = True,
    min_range_m: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Exact first hits of rays with the scene, noise-free.

    Parameters
    ----------
    scenario
        The scene: wall, deformations, deposits, obstacles, end wall.
    origin_pipe_m
        (3,) ray origin in the pipe frame, metres; must be in free space inside the pipe.
    dirs_pipe
        (N, 3) unit ray directions in the pipe frame.
    occluders
        False leaves deposits and obstacles out (wall, deformation and end wall stay).
    min_range_m
        Ranges below this (the blind zone) may be returned inexactly, still below it: on a
        deformation's ramps, where the hit is found numerically, they are not refined.

    Returns
    -------
    range_m
        (N,) float64 distance to the first hit, metres (``inf`` when nothing is hit).
    surface
        (N,) int8 surface id (:data:`SURFACE_WALL`, :data:`SURFACE_END_WALL`, ...).
    """
    o = np.asarray(origin_pipe_m, dtype=np.float64).reshape(3)
    d = np.asarray(dirs_pipe, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3:
        raise ValueError("dirs_pipe must have shape (N, 3).")
    t, surface = _cast_free(scenario, o, d, min_range_m)
    if occluders:
        _apply_occluders(scenario, o, d, t, surface)
    return t, surface


def surface_normals(
    scenario: Scenario, points_pipe_m: np.ndarray, surface: np.ndarray
) -> np.ndarray:
    """Unit normals (N, 3) of the surfaces at their hit points, in the pipe frame.

    Wall: the gradient of the local ellipse (the slope of a deformation's ramp along the axis
    is left out: under 2°). End wall: the axis. Deposit top: from the slope of the fill along
    the axis. Obstacle: the normal of the box face nearest to the point. Rows of
    :data:`SURFACE_NONE` are (1, 0, 0).
    """
    p = np.asarray(points_pipe_m, dtype=np.float64)
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    normals = np.zeros_like(p)
    normals[:, 0] = 1.0
    wall = surface == SURFACE_WALL
    if wall.any():
        a, b = ellipse_axes_m(scenario, x[wall])
        normals[wall] = np.column_stack((np.zeros(wall.sum()), y[wall] / a**2, z[wall] / b**2))
    deposit = surface == SURFACE_DEPOSIT
    if deposit.any():
        h = 1e-3
        xd = x[deposit]
        slope = (deposit_top_z_m(scenario, xd + h) - deposit_top_z_m(scenario, xd - h)) / (2 * h)
        slope = np.where(np.isfinite(slope), slope, 0.0)
        normals[deposit] = np.column_stack((-slope, np.zeros(xd.size), np.ones(xd.size)))
    banded = np.flatnonzero(surface == SURFACE_BAND)
    for band in scenario.bands:
        q = p[banded]
        inner = scenario.radius_m - band.thickness_m
        rho = np.hypot(q[:, 1], q[:, 2])
        first, last = band.arc_rad
        angle = np.arctan2(q[:, 2], q[:, 1])
        gaps = np.column_stack(
            (
                np.abs(rho - inner),
                np.minimum(np.abs(q[:, 0] - band.start_m), np.abs(q[:, 0] - band.end_m)),
                rho * np.abs(np.sin(angle - first)),
                rho * np.abs(np.sin(angle - last)),
            )
        )
        face = np.argmin(gaps, axis=1)
        on = (q[:, 0] >= band.start_m - 1e-6) & (q[:, 0] <= band.end_m + 1e-6)
        on &= np.mod(angle - first + 1e-6, 2.0 * np.pi) <= last - first + 2e-6
        radial = np.column_stack((np.zeros(len(q)), q[:, 1], q[:, 2]))
        tangent_first = np.tile([0.0, -math.sin(first), math.cos(first)], (len(q), 1))
        tangent_last = np.tile([0.0, -math.sin(last), math.cos(last)], (len(q), 1))
        choices = np.stack(
            (radial, np.tile([1.0, 0.0, 0.0], (len(q), 1)), tangent_first, tangent_last)
        )
        normals[banded[on]] = choices[face, np.arange(len(q))][on]
    obstacle = np.flatnonzero(surface == SURFACE_OBSTACLE)
    if obstacle.size:
        best = np.full(obstacle.size, np.inf)
        for box in scenario.obstacles:
            lo = np.array([box.start_m, box.y_min_m, box.z_min_m])
            hi = np.array([box.end_m, box.y_max_m, box.z_max_m])
            q = p[obstacle]
            gap = np.minimum(np.abs(q - lo), np.abs(q - hi))  # distance to each face pair
            face = np.argmin(gap, axis=1)
            dist = gap[np.arange(obstacle.size), face]
            outside = np.maximum(np.maximum(lo - q, q - hi), 0.0).max(axis=1)
            better = (dist + outside) < best
            best = np.where(better, dist + outside, best)
            normals[obstacle[better]] = np.eye(3)[face[better]]
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


def surface_residual_m(scenario: Scenario, points_pipe_m: np.ndarray) -> np.ndarray:
    """Distance-like residual of points to the nearest modelled surface.

    Parameters
    ----------
    points_pipe_m
        (N, 3) points in the pipe frame, metres.

    Returns
    -------
    (N,) float64, metres: the smallest of the radial offset from the wall ellipse (along the
    ray from the axis), the offset from the end-wall plane, the vertical offset from a
    deposit top and the distance to an obstacle's surface. 0 on a surface.
    """
    p = np.asarray(points_pipe_m, dtype=np.float64)
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    a, b = ellipse_axes_m(scenario, x)
    rho = np.hypot(y, z)
    theta = np.arctan2(z, y)
    rho_wall = a * b / np.hypot(b * np.cos(theta), a * np.sin(theta))
    res = np.abs(rho - rho_wall)
    res = np.minimum(res, np.abs(x - scenario.end_wall_m))
    top = deposit_top_z_m(scenario, x)
    res = np.where(np.isfinite(top), np.minimum(res, np.abs(z - top)), res)
    for box in scenario.obstacles:
        lo = np.array([box.start_m, box.y_min_m, box.z_min_m])
        hi = np.array([box.end_m, box.y_max_m, box.z_max_m])
        centre, half = (lo + hi) / 2, (hi - lo) / 2
        q = np.abs(p - centre) - half
        sdf = np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)
        res = np.minimum(res, np.abs(sdf))
    for band in scenario.bands:
        # Distance to the band's faces, for points over the band's span and arc (or at its
        # ends): enough to check that points seen on it lie on it.
        inner = scenario.radius_m - band.thickness_m
        on_arc = band.covers(theta)
        along = (x >= band.start_m) & (x <= band.end_m)
        res = np.where(along & on_arc, np.minimum(res, np.abs(rho - inner)), res)
        in_ring = (rho >= inner) & (rho <= scenario.radius_m) & on_arc
        for x_end in (band.start_m, band.end_m):
            res = np.where(in_ring, np.minimum(res, np.abs(x - x_end)), res)
        first, last = band.arc_rad
        for angle in (first, last):
            side = rho * np.abs(np.sin(theta - angle))
            near = along & (rho >= inner) & (rho <= scenario.radius_m) & (np.cos(theta - angle) > 0)
            res = np.where(near, np.minimum(res, side), res)
    return res


def free_area_m2(scenario: Scenario, x_m: float) -> float:
    """Exact free cross-section area (m²) at pipe-frame ``x_m``, perpendicular to the axis.

    The wall ellipse minus the deposit segment is analytic; each obstacle's overlap with
    what is left is integrated by the trapezoid rule over its angular span (the integrand
    has kinks only, so the error is below 1e-8 m²). Obstacles must not overlap each other.
    """
    a_arr, b_arr = ellipse_axes_m(scenario, np.array([x_m]))
    a, b = float(a_arr[0]), float(b_arr[0])
    z_dep = float(deposit_top_z_m(scenario, np.array([x_m]))[0])
    area = math.pi * a * b
    if z_dep > -b:
        # Squash the ellipse into a circle of radius a: areas scale by b / a.
        k = min(a + z_dep * a / b, 2.0 * a)  # segment height in the circle
        seg = a * a * math.acos((a - k) / a) - (a - k) * math.sqrt(max(2 * a * k - k * k, 0.0))
        area -= seg * b / a
    for box in scenario.obstacles:
        if not box.start_m <= x_m < box.end_m:
            continue
        y0, y1 = max(box.y_min_m, -a), min(box.y_max_m, a)
        if y1 <= y0:
            continue
        # y = -a cos(phi) removes the square-root singularity where the box meets the side.
        phi = np.linspace(math.acos(-y0 / a), math.acos(-y1 / a), AREA_QUADRATURE_POINTS)
        y = -a * np.cos(phi)
        half = b * np.sqrt(np.clip(1.0 - (y / a) ** 2, 0.0, None))
        lower = np.maximum(np.maximum(-half, z_dep), box.z_min_m)
        upper = np.minimum(half, box.z_max_m)
        overlap = np.clip(upper - lower, 0.0, None) * a * np.sin(phi)
        area -= float(np.sum((overlap[1:] + overlap[:-1]) * np.diff(phi)) / 2.0)
    for band in scenario.bands:
        if band.start_m <= x_m < band.end_m:
            area -= _band_area_m2(band, scenario.radius_m, a, b, z_dep)
    return area


def _band_area_m2(band: WallBand, radius_m: float, a: float, b: float, z_dep: float) -> float:
    """Area (m²) of a band's cross-section between its inner face and the wall ellipse
    (semi-axes ``a`` across, ``b`` up), less the part below the deposit top ``z_dep``: the
    polar integral ``∫ ½ (ρ_hi² − ρ_lo²) dθ`` over the arc, by the trapezoid rule."""
    first, last = band.arc_rad
    theta = np.linspace(first, last, AREA_QUADRATURE_POINTS)
    c, s = np.cos(theta), np.sin(theta)
    hi = a * b / np.hypot(b * c, a * s)
    lo = np.full_like(theta, radius_m - band.thickness_m)
    if np.isfinite(z_dep):
        with np.errstate(divide="ignore", invalid="ignore"):
            crossing = z_dep / s  # where the ray at theta meets the deposit top
        below = s < 0
        # Looking down, the deposit fills beyond its top; looking up, below it.
        hi = np.where(below, np.where(z_dep >= 0, 0.0, np.minimum(hi, crossing)), hi)
        lo = np.where((s > 0) & (z_dep > 0), np.maximum(lo, crossing), lo)
        lo = np.where((s == 0) & (z_dep > 0), hi, lo)
    strip = 0.5 * np.clip(hi * hi - lo * lo, 0.0, None) * (hi > lo)
    return float(np.sum((strip[1:] + strip[:-1]) * np.diff(theta)) / 2.0)


# --------------------------------------------------------------------------- the scan


class SimulatedScan:
    """A simulated scan: poses and odometer up front, frames on demand.

    Build it with :func:`simulate_scan`. Per-frame arrays (``F`` frames) are small; points
    are generated by :meth:`frame` / :meth:`frames`, one frame at a time, so memory stays
    bounded whatever the length of the scan.

    Attributes
    ----------
    scenario, seed
        What was simulated.
    meta
        The :class:`InspectionMeta` an archive of this scan holds (noisy odometer).
    times_s, odometer_m, true_travel_m
        (F,) capture time (s), odometer reading (m, with scale error and noise) and true
        distance travelled along the axis (m).
    gravity_sensor
        (F, 3) the IMU's unit gravity direction in the sensor frame (true attitude plus
        ``imu_noise_deg`` of noise), or None when ``Scenario.imu`` is off.
    T_world_sensor
        (F, 4, 4) true sensor poses.
    T_world_pipe
        (4, 4) the pipe frame: origin on the axis at the scan start, x downstream, z up.
    """

    def __init__(self, scenario: Scenario, seed: int = 0) -> None:
        self.scenario = scenario
        self.seed = int(seed)
        s, e = scenario, scenario.effects
        rng = np.random.default_rng((self.seed, 1))
        # Speed varies smoothly around the set speed so that constant-velocity guesses are off.
        phase = rng.uniform(0.0, 2.0 * math.pi)
        omega = 2.0 * math.pi / s.speed_variation_period_s

        def commanded(t_s: np.ndarray) -> np.ndarray:
            wobble = (np.cos(omega * t_s + phase) - math.cos(phase)) / omega
            return s.speed_m_s * (t_s - s.speed_variation_ratio * wobble)

        stuck_s, slips = self._draw_slips()
        n_max = (
            math.ceil(
                (s.travel_m / (s.speed_m_s * (1 - s.speed_variation_ratio)) + stuck_s)
                * s.frame_rate_hz
            )
            + 2
        )
        times = np.arange(n_max) / s.frame_rate_hz
        step_m = np.diff(commanded(times), prepend=0.0)
        stuck = np.zeros(n_max, dtype=bool)
        sliding = np.zeros(n_max, dtype=bool)
        commanded_m = np.cumsum(step_m)
        for at_m, duration_s, is_stuck in slips:
            first = int(np.searchsorted(commanded_m, at_m))
            last = first + max(1, round(duration_s * s.frame_rate_hz))
            (stuck if is_stuck else sliding)[first:last] = True
        # Stuck: the wheels turn (the count runs on) while the crawler stands. Sliding: the
        # crawler moves while the count stands.
        travel_m = np.cumsum(np.where(stuck, 0.0, step_m))
        counted_m = np.cumsum(np.where(sliding, 0.0, step_m))
        n = int(np.searchsorted(travel_m, s.travel_m, side="right"))
        self.times_s = times[:n]
        self.true_travel_m = travel_m[:n]
        self.slip_frames = np.flatnonzero((stuck | sliding)[:n])
        odo_noise = np.random.default_rng((self.seed, 3)).normal(0.0, e.odometer_noise_m, n)
        odo_noise[0] = 0.0
        self.odometer_m = counted_m[:n] * (1.0 + e.odometer_scale_error_ratio) + odo_noise

        # Rocking: per axis a weighted sum of sinusoids, peak <= rocking_deg.
        periods = rng.uniform(*_JITTER_PERIOD_RANGE_S, size=(3, _JITTER_TERMS))
        weights = rng.uniform(0.5, 1.0, size=(3, _JITTER_TERMS))
        weights /= weights.sum(axis=1, keepdims=True)
        phases = rng.uniform(0.0, 2.0 * math.pi, size=(3, _JITTER_TERMS))
        arg = 2.0 * math.pi * self.times_s[:, None, None] / periods[None] + phases[None]
        attitude_rad = math.radians(e.rocking_deg) * (weights[None] * np.sin(arg)).sum(axis=2)
        # Vibration: a new attitude offset every frame.
        vibration = np.random.default_rng((self.seed, 5)).normal(0.0, 1.0, (n, 3))
        attitude_rad += math.radians(e.vibration_deg) * vibration
        jitter = np.random.default_rng((self.seed, 6)).normal(0.0, 1.0, (n, 2))
        lateral_m = np.array([s.mount_offset_y_m, s.mount_offset_z_m]) + e.mount_jitter_m * jitter

        mount = _rot_y(-math.radians(s.mount_pitch_deg))  # positive pitch = nose up
        self.T_world_pipe = world_from_pipe(s)
        self._T_pipe_sensor = np.empty((n, 4, 4))
        for i in range(n):
            roll, pitch, yaw = attitude_rad[i]
            rotation = mount @ _rot_z(yaw) @ _rot_y(pitch) @ _rot_x(roll)
            position = (self.true_travel_m[i], *lateral_m[i])
            self._T_pipe_sensor[i] = _pose(rotation, position)
        self.T_world_sensor = self.T_world_pipe[None] @ self._T_pipe_sensor
        self.gravity_sensor = self._imu_gravity() if e.imu else None

        self.meta = InspectionMeta(
            asset_id=s.asset_id,
            inspected_at=s.inspected_at,
            nominal_diameter_m=s.nominal_diameter_m,
            upstream_node=s.upstream_node,
            downstream_node=s.downstream_node,
            direction="downstream",
            chainage_offset_m=s.chainage_offset_m,
            material=s.material,
            frames=tuple(
                FrameRef(
                    frame_file_name(i, ".laz" if e.motion_within_frame else ".npy"),
                    float(self.times_s[i]),
                    float(self.odometer_m[i]),
                    self.gravity(i),
                )
                for i in range(n)
            ),
        )
        self._coverage_cache: tuple[np.ndarray, np.ndarray] | None = None

    def _draw_slips(self) -> tuple[float, list[tuple[float, float, bool]]]:
        """Slip events ``(commanded travel at the start (m), duration (s), stuck?)`` and their
        total stuck time (s), from their own random stream."""
        e = self.scenario.effects
        rng = np.random.default_rng((self.seed, 4))
        count = int(rng.poisson(e.slip_per_m * self.scenario.travel_m))
        slips = [
            (
                float(rng.uniform(0.0, self.scenario.travel_m)),
                float(rng.uniform(*e.slip_duration_s)),
                bool(rng.random() < 0.5),
            )
            for _ in range(count)
        ]
        return sum(d for _, d, stuck in slips if stuck), slips

    def _imu_gravity(self) -> np.ndarray:
        """The IMU's gravity directions, (F, 3), in the sensor frame: the true world "down"
        seen from the true attitude, tilted by a random rotation of ``imu_noise_deg`` RMS
        per axis (its own random stream, so the other draws do not change). Rows of frames
        that the IMU missed (``imu_dropout_ratio``) are NaN."""
        effects = self.scenario.effects
        down_sensor = -self.T_world_sensor[:, 2, :3]  # R_world_sensorᵀ (0, 0, -1)
        tilt_rad = np.random.default_rng((self.seed, 2)).normal(
            0.0, math.radians(effects.imu_noise_deg), (len(self), 3)
        )
        noisy = Rotation.from_rotvec(tilt_rad).apply(down_sensor)
        noisy /= np.linalg.norm(noisy, axis=1, keepdims=True)
        dropped = np.random.default_rng((self.seed, 7)).random(len(self))
        noisy[dropped < effects.imu_dropout_ratio] = np.nan
        return noisy

    def gravity(self, i: int) -> tuple[float, float, float] | None:
        """The IMU's unit gravity direction at frame ``i`` in the sensor frame, or None
        (no IMU, or the IMU missed this frame)."""
        if self.gravity_sensor is None or not np.isfinite(self.gravity_sensor[i]).all():
            return None
        gx, gy, gz = (float(v) for v in self.gravity_sensor[i])
        return (gx, gy, gz)

    def __len__(self) -> int:
        return int(self.times_s.size)

    @property
    def n_frames(self) -> int:
        """Number of frames ``F``."""
        return len(self)

    def T_pipe_sensor(self, i: int) -> np.ndarray:
        """True pose (4, 4) of frame ``i`` in the pipe frame."""
        return self._T_pipe_sensor[i].copy()

    def frame(self, i: int, *, noise_free: bool = False) -> SimulatedFrame:
        """Generate frame ``i`` (deterministic in ``(seed, i)``).

        Parameters
        ----------
        i
            Frame index in ``[0, F)``.
        noise_free
            Leave out range noise and spurious returns (same rays, exact ranges).

        Raises
        ------
        IndexError
            When ``i`` is out of range.
        """
        if not 0 <= i < len(self):
            raise IndexError(f"frame {i} out of range: the scan has {len(self)} frames.")
        s = self.scenario
        dirs_sensor = ray_directions_sensor(s, i)
        T = self._T_pipe_sensor[i]
        packet: np.ndarray | None = None
        if s.effects.motion_within_frame:
            # Rays in scan order, in packets; each packet cast from the pose at its time.
            n_rays = len(dirs_sensor)
            packet = np.arange(n_rays) * PACKETS_PER_FRAME // max(n_rays, 1)
            poses = self._poses_within(i, np.arange(PACKETS_PER_FRAME) / PACKETS_PER_FRAME)
            origins = poses[:, :3, 3]
            dirs_pipe = np.einsum("nij,nj->ni", poses[packet, :3, :3], dirs_sensor)
        else:
            origins = T[:3, 3]
            dirs_pipe = dirs_sensor @ T[:3, :3].T
        range_m, surface = _cast_packets(s, origins, packet, dirs_pipe, s.blind_zone_m)
        if not noise_free:
            range_m = self._returned_ranges(i, origins, dirs_pipe, range_m, surface, packet)
        if s.water is not None:
            # Most rays that reach the water give no return (specular, or absorbed below).
            # Turbid water scatters diffusely: returns fall off with the cosine of incidence.
            draw = np.random.default_rng((self.seed, 20, i)).random(range_m.size)
            share = s.water.surface_return_ratio * np.abs(dirs_pipe[:, 2])
            lost = (surface == SURFACE_WATER) & (draw >= share)
            range_m = np.where(lost, np.inf, range_m)
        # Early returns inside the blind zone come back negated from ``_returned_ranges``: a
        # sensor reports them (dust on its window), where it reports no surface that near.
        window = range_m < 0
        range_m = np.abs(range_m)
        keep = np.isfinite(range_m) & (range_m <= s.max_range_m)
        keep &= (range_m >= s.blind_zone_m) | window
        points = (dirs_sensor[keep] * range_m[keep, None]).astype(np.float32)
        point_time_s = None
        if packet is not None:
            share = packet[keep] / PACKETS_PER_FRAME
            point_time_s = float(self.times_s[i]) + share / s.frame_rate_hz
        return SimulatedFrame(
            index=i,
            time_s=float(self.times_s[i]),
            odometer_m=float(self.odometer_m[i]),
            points_sensor=points,
            T_world_sensor=self.T_world_sensor[i].copy(),
            gravity=self.gravity(i),
            point_time_s=point_time_s,
        )

    def _poses_within(self, i: int, share: np.ndarray) -> np.ndarray:
        """True pipe-frame poses (K, 4, 4) at ``share`` (K,) of frame ``i``'s period: between
        its pose and the next frame's (translation linearly, rotation by slerp); the last
        frame goes on by the step that led to it."""
        T_a = self._T_pipe_sensor[i]
        if i + 1 < len(self):
            T_b = self._T_pipe_sensor[i + 1]
        elif i > 0:
            T_b = T_a @ np.linalg.inv(self._T_pipe_sensor[i - 1]) @ T_a
        else:
            T_b = T_a
        share = np.asarray(share, dtype=np.float64)
        out = np.tile(np.eye(4), (len(share), 1, 1))
        rotations = Rotation.from_matrix(np.stack((T_a[:3, :3], T_b[:3, :3])))
        out[:, :3, :3] = Slerp([0.0, 1.0], rotations)(share).as_matrix()
        out[:, :3, 3] = (1.0 - share)[:, None] * T_a[:3, 3] + share[:, None] * T_b[:3, 3]
        return out

    def points_pipe(self, frame: SimulatedFrame) -> np.ndarray:
        """A frame's points in the pipe frame, (N, 3) float64, each placed with the true pose
        at its capture time (the frame's pose when the frame carries no point times)."""
        p = frame.points_sensor.astype(np.float64)
        if frame.point_time_s is None:
            T = self._T_pipe_sensor[frame.index]
            return p @ T[:3, :3].T + T[:3, 3]
        share = (frame.point_time_s - frame.time_s) * self.scenario.frame_rate_hz
        shares, inverse = np.unique(share, return_inverse=True)
        poses = self._poses_within(frame.index, shares)[inverse]
        return np.einsum("nij,nj->ni", poses[:, :3, :3], p) + poses[:, :3, 3]

    def _returned_ranges(
        self,
        i: int,
        origin_pipe_m: np.ndarray,
        dirs_pipe: np.ndarray,
        range_m: np.ndarray,
        surface: np.ndarray,
        packet: np.ndarray | None = None,
    ) -> np.ndarray:
        """The ranges the sensor reports for exact first hits: mixed pixels at depth edges,
        range noise by range and incidence, spurious early returns (see :class:`Effects`).
        Each effect draws from its own stream of ``(seed, effect, frame)``. With ``packet``,
        ray ``j`` starts at ``origin_pipe_m[packet[j]]`` (see :func:`_cast_packets`)."""
        s, e = self.scenario, self.scenario.effects
        n = range_m.size
        hit = np.isfinite(range_m)
        out = range_m.copy()
        ray_origin_m = origin_pipe_m if packet is None else origin_pipe_m[packet]
        if e.mixed_pixel_ratio > 0 and e.beam_footprint_deg > 0:
            rng = np.random.default_rng((self.seed, 12, i))
            # A second ray through the footprint's edge, in a random direction across the beam.
            across = np.cross(dirs_pipe, rng.normal(size=(n, 3)))
            across /= np.linalg.norm(across, axis=1, keepdims=True)
            edge = dirs_pipe + math.radians(e.beam_footprint_deg) * across
            edge /= np.linalg.norm(edge, axis=1, keepdims=True)
            edge_range, edge_surface = _cast_packets(s, origin_pipe_m, packet, edge, s.blind_zone_m)
            straddles = (
                hit
                & np.isfinite(edge_range)
                & (edge_surface != surface)
                & (np.abs(edge_range - range_m) > _MIXED_PIXEL_MIN_GAP_M)
            )
            mixed = straddles & (rng.random(n) < e.mixed_pixel_ratio)
            w = rng.random(n)
            out = np.where(mixed, (1.0 - w) * range_m + w * edge_range, out)
        points = ray_origin_m + dirs_pipe * np.where(hit, range_m, 0.0)[:, None]
        normals = surface_normals(s, points, surface)
        cos_incidence = np.abs(np.einsum("ij,ij->i", normals, dirs_pipe))
        sigma = e.range_sigma_m(np.where(hit, range_m, 0.0), cos_incidence)
        out = out + sigma * np.random.default_rng((self.seed, 10, i)).normal(0.0, 1.0, n)
        rng = np.random.default_rng((self.seed, 11, i))
        if e.spurious_range_ratio is not None:
            near, far = e.spurious_range_ratio
            spurious = (rng.random(n) < e.spurious_return_ratio) & hit
            early = range_m * (near + rng.random(n) * (far - near))
            # Reported wherever they land, the blind zone included (see ``frame``).
            return np.where(spurious, -early, out)
        spurious = (rng.random(n) < e.spurious_return_ratio) & hit & (range_m > s.blind_zone_m)
        early = s.blind_zone_m + rng.random(n) * (range_m - s.blind_zone_m)
        return np.where(spurious, early, out)

    def frames(self) -> Iterator[SimulatedFrame]:
        """Yield every frame in order, generating each one on demand."""
        for i in range(len(self)):
            yield self.frame(i)

    def points_true_poses(self, *, max_range_m: float | None = None) -> np.ndarray:
        """Every frame's points placed in the pipe frame with the true poses, (N, 3) float64:
        the cloud a perfect registration would give.

        Parameters
        ----------
        max_range_m
            Leave out returns further than this from the sensor (as the inspection does).
        """
        parts = []
        for frame in self.frames():
            p = self.points_pipe(frame)
            if max_range_m is not None:
                q = frame.points_sensor.astype(np.float64)
                p = p[np.einsum("ij,ij->i", q, q) <= max_range_m**2]
            parts.append(p)
        return np.concatenate(parts) if parts else np.empty((0, 3))

    def _coverage_grids(self) -> tuple[np.ndarray, np.ndarray]:
        """Hit grids (chainage bins of 1 cm × angle bins) with and without occluders."""
        if self._coverage_cache is not None:
            return self._coverage_cache
        s = self.scenario
        n_x = math.ceil(s.end_wall_m / COVERAGE_CHAINAGE_BIN_M)
        n_a = round(360.0 / COVERAGE_BIN_DEG)
        full = np.zeros((n_x, n_a), dtype=bool)
        free = np.zeros((n_x, n_a), dtype=bool)
        n, stride = s.rays_per_frame, s.truth_ray_stride
        for i in range(len(self)):
            # Every stride-th ray of the endless pattern: still a Kronecker sequence, so the
            # subsample covers the field of view evenly over the frames.
            first = (-i * n) % stride
            if s.sensor is not None:
                dirs_sensor = s.sensor.directions(i, stride)
            else:
                dirs_sensor = _frame_pattern_dirs(s, i, stride, first)
            T = self._T_pipe_sensor[i]
            o, d = T[:3, 3], dirs_sensor @ T[:3, :3].T
            t, surface = _cast_free(s, o, d, s.blind_zone_m)
            for grid, tt, ss in ((free, t, surface), (full, *_occluded(s, o, d, t, surface))):
                ok = (tt >= s.blind_zone_m) & (tt <= s.max_range_m)
                ok &= (ss != SURFACE_END_WALL) & (ss != SURFACE_NONE) & (ss != SURFACE_WATER)
                p = o + d[ok] * tt[ok, None]
                ix = np.floor(p[:, 0] / COVERAGE_CHAINAGE_BIN_M).astype(np.int64)
                ang = np.arctan2(p[:, 2], p[:, 1])
                ia = (
                    np.floor((ang + math.pi) / math.radians(COVERAGE_BIN_DEG)).astype(np.int64)
                    % n_a
                )
                inside = (ix >= 0) & (ix < n_x)
                grid[ix[inside], ia[inside]] = True
        self._coverage_cache = (full, free)
        return self._coverage_cache

    def true_sections(self, step_m: float = 0.1) -> list[TrueSection]:
        """Ground truth of every section from the scan start to the end wall.

        Open area, blockage, deposit height and deformation are exact (see
        :func:`free_area_m2`), averaged over :data:`SUB_SLICES_PER_SECTION` sub-slices.
        Coverage and shadow come from one noise-free pass over all frames with one ray in
        ``scenario.truth_ray_stride`` (4 by default: the `paper` scan's pass takes ~2 s on one
        core; the wall is cast once, deposits and obstacles are added to a copy), recorded on
        a 1 cm × 2° grid (chainage × angle around the axis) that is cached, so later calls
        with another step are free. A section's angle bin is covered when any ray hit the
        section's free boundary in it beyond the blind zone; ``in_shadow`` marks a bin hit
        without occluders but never with them. The subsample makes coverage a slight
        underestimate where a section is seen by few rays (on the `paper` scan, against an
        all-ray pass: at most 0.07 lower at 0.8-1.1 m, where the field of view's edge first
        reaches the crown and invert, at most 0.03 elsewhere, and one section at the edge of
        the deposit's shadow marked ``in_shadow`` that the all-ray pass clears).

        Parameters
        ----------
        step_m
            Section length, a multiple of :data:`COVERAGE_CHAINAGE_BIN_M` (0.01 m).

        Returns
        -------
        list of :class:`TrueSection`, chainages including ``scenario.chainage_offset_m``.

        Raises
        ------
        ValueError
            When ``step_m`` is not a positive multiple of 0.01 m.
        """
        bins_per_section = step_m / COVERAGE_CHAINAGE_BIN_M
        if step_m <= 0 or abs(bins_per_section - round(bins_per_section)) > 1e-6:
            raise ValueError(f"step_m must be a positive multiple of 0.01 m, got {step_m!r}.")
        per = round(bins_per_section)
        s = self.scenario
        full, free = self._coverage_grids()
        n_sections = math.floor(s.end_wall_m / step_m + 1e-9)
        sections = []
        for j in range(n_sections):
            x0 = j * step_m
            xs = x0 + (np.arange(SUB_SLICES_PER_SECTION) + 0.5) * step_m / SUB_SLICES_PER_SECTION
            areas = [free_area_m2(s, float(x)) for x in xs]
            a, b = ellipse_axes_m(s, xs)
            top = deposit_top_z_m(s, xs)
            deposit = np.clip(top + b, 0.0, None) / (2.0 * b)
            deformation = np.clip(1.0 - np.minimum(a, b) / s.radius_m, 0.0, None)
            water = np.zeros_like(xs)
            if s.water is not None:
                wet = (xs >= s.water.start_m) & (xs <= s.water.end_m)
                level = np.clip(s.water.surface_z_m(s.radius_m) + b, 0.0, None) / (2.0 * b)
                water = np.where(wet, level, 0.0)
            seen = full[j * per : (j + 1) * per].any(axis=0)
            reachable = free[j * per : (j + 1) * per].any(axis=0)
            open_m2 = float(np.mean(areas))
            sections.append(
                TrueSection(
                    # Rounded to 1 nm so that 29 * 0.1 reads 2.9, as a user would key it.
                    chainage_start_m=round(s.chainage_offset_m + x0, 9),
                    chainage_end_m=round(s.chainage_offset_m + x0 + step_m, 9),
                    open_area_m2=open_m2,
                    blockage_ratio=1.0 - open_m2 / s.nominal_area_m2,
                    deposit_height_ratio=float(np.mean(deposit)),
                    deformation_ratio=float(np.mean(deformation)),
                    coverage_ratio=float(seen.mean()),
                    in_shadow=bool((reachable & ~seen).any()),
                    water_depth_ratio=float(np.mean(water)),
                )
            )
        return sections


def _cast_packets(
    s: Scenario,
    origins_pipe_m: np.ndarray,
    packet: np.ndarray | None,
    dirs_pipe: np.ndarray,
    min_range_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`cast_rays` from one origin (``packet`` None, ``origins_pipe_m`` (3,)) or from
    one per packet: ray ``j`` from ``origins_pipe_m[packet[j]]`` ((K, 3); ``packet``
    ascending)."""
    if packet is None:
        return cast_rays(s, origins_pipe_m, dirs_pipe, min_range_m=min_range_m)
    range_m = np.empty(len(dirs_pipe))
    surface = np.empty(len(dirs_pipe), dtype=np.int8)
    bounds = np.searchsorted(packet, np.arange(len(origins_pipe_m) + 1))
    for k, (a, b) in enumerate(itertools.pairwise(bounds)):
        if b > a:
            range_m[a:b], surface[a:b] = cast_rays(
                s, origins_pipe_m[k], dirs_pipe[a:b], min_range_m=min_range_m
            )
    return range_m, surface


def _occluded(
    s: Scenario, o: np.ndarray, d: np.ndarray, t: np.ndarray, surface: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    t2, s2 = t.copy(), surface.copy()
    _apply_occluders(s, o, d, t2, s2)
    return t2, s2


def frame_file_name(i: int, suffix: str = ".npy") -> str:
    """Archive-relative file name of frame ``i``: ``frames/000012.npy``. A scan with
    ``Effects.motion_within_frame`` names its frames ``.laz``, a format that holds each
    point's time (``.npy`` does not)."""
    return f"frames/{i:06d}{suffix}"


def simulate_scan(scenario: Scenario | str, seed: int = 0) -> SimulatedScan:
    """Set up a simulated scan; frames are generated lazily.

    Parameters
    ----------
    scenario
        A :class:`Scenario` or one of :data:`SCENARIO_NAMES`.
    seed
        Seeds speed variation, odometer noise, attitude jitter, range noise and spurious
        returns. The scan pattern is the sensor's own and does not depend on it.

    Returns
    -------
    SimulatedScan

    Examples
    --------
    >>> scan = simulate_scan(get_scenario("clean", travel_m=0.5), seed=3)
    >>> float(scan.odometer_m[0])
    0.0
    """
    if isinstance(scenario, str):
        scenario = get_scenario(scenario)
    return SimulatedScan(scenario, seed)
