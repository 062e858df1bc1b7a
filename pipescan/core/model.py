"""Small frozen dataclasses passed between stages (and between Prefect tasks).

Units are in the names: ``_m`` metres, ``_m2`` square metres, ``_s`` seconds, ``_ratio`` a
fraction (usually in [0, 1]). Point arrays are never stored here, except the (M, 2) contour
of a section, kept for report figures.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from datetime import datetime
from enum import StrEnum
from typing import Literal

import numpy as np


@dataclass(frozen=True)
class FrameRef:
    """One LiDAR frame listed in an archive.

    ``file`` is relative to the archive root (e.g. ``frames/000012.npy``). ``time_s`` and
    ``odometer_m`` are None when the archive does not give them. ``gravity`` is the unit
    direction of gravity an IMU measured in the sensor frame, or None without an IMU.
    """

    file: str
    time_s: float | None = None
    odometer_m: float | None = None
    gravity: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class RosTopics:
    """The ``[ros]`` table of ``inspection.toml``: which topics of a ROS bag hold the frames
    (``sensor_msgs/PointCloud2``), the odometry (``nav_msgs/Odometry``) and the IMU
    (``sensor_msgs/Imu``). None: found by message type."""

    points_topic: str | None = None
    odometry_topic: str | None = None
    imu_topic: str | None = None


SCAN_PATTERNS = ("repetitive", "non_repetitive", "profiler", "static")
"""``repetitive``: every frame covers the field of view (spinning or image-like scanners);
``non_repetitive``: a rosette that fills it over several frames (Livox Avia, Mid series);
``profiler``: a 2D LiDAR spinning across the pipe, one ring a frame; ``static``: a
terrestrial scanner, one station a frame."""


@dataclass(frozen=True)
class SensorProfile:
    """What a sensor's maker states, or what the user states for it.

    Attributes
    ----------
    model : str
        A name in :data:`SENSOR_MODELS`, or the user's own (``custom``).
    min_range_m : float, optional
        Nearest range the sensor measures (its blind zone).
    max_range_m : float, optional
    fov_horizontal_deg, fov_vertical_deg : float, optional
    pattern : str, optional
        One of :data:`SCAN_PATTERNS`.
    points_per_s : float, optional
    range_noise_m : float, optional
        1σ range noise as published (along the ray, at the maker's test range and target).
    source : str
        Where the figures come from.
    """

    model: str = "custom"
    min_range_m: float | None = None
    max_range_m: float | None = None
    fov_horizontal_deg: float | None = None
    fov_vertical_deg: float | None = None
    pattern: str | None = None
    points_per_s: float | None = None
    range_noise_m: float | None = None
    source: str = "inspection.toml"

    def __post_init__(self) -> None:
        if self.pattern is not None and self.pattern not in SCAN_PATTERNS:
            raise ValueError(
                f"pattern {self.pattern!r} is unknown; use one of {', '.join(SCAN_PATTERNS)}"
            )
        for name in ("min_range_m", "max_range_m", "range_noise_m", "points_per_s"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
        for name in ("fov_horizontal_deg", "fov_vertical_deg"):
            value = getattr(self, name)
            if value is not None and not 0 < value <= 360:
                raise ValueError(f"{name} must be in (0, 360], got {value!r}")
        if (
            self.min_range_m is not None
            and self.max_range_m is not None
            and not self.min_range_m < self.max_range_m
        ):
            raise ValueError("min_range_m must be below max_range_m")


@dataclass(frozen=True)
class InspectionMeta:
    """The validated content of ``inspection.toml``.

    ``upstream_node_xyz`` and ``downstream_node_xyz`` are the nodes' positions ``(x, y)`` or
    ``(x, y, z)`` in the coordinate reference system ``crs`` (e.g. ``"EPSG:25832"``), given
    together or not at all (docs/archive.md).
    ``start_xyz`` is the sensor's first position in a registered cloud's frame (where its
    scan starts: docs/archive.md); ``ros`` names a bag's topics.
    ``odometer_uncertainty_ratio`` is the crawler's odometer's stated uncertainty, a share of
    the distance (None: registration's default, 3 %); ``odometer_slip_m`` the largest slip its
    operator says it may make unseen (None: none stated).
    """

    asset_id: str
    inspected_at: datetime
    nominal_diameter_m: float
    upstream_node: str | None = None
    downstream_node: str | None = None
    direction: Literal["downstream", "upstream"] = "downstream"
    chainage_offset_m: float = 0.0
    material: str | None = None
    pipe_shape: str = "circular"
    frames: tuple[FrameRef, ...] = ()
    upstream_node_xyz: tuple[float, ...] | None = None
    downstream_node_xyz: tuple[float, ...] | None = None
    crs: str | None = None
    start_xyz: tuple[float, float, float] | None = None
    ros: RosTopics | None = None
    odometer_uncertainty_ratio: float | None = None
    odometer_slip_m: float | None = None
    sensor: SensorProfile | None = None
    """The ``[sensor]`` table (:mod:`pipescan.core.instrument`); None: estimated from the scan."""

    @property
    def nominal_area_m2(self) -> float:
        return math.pi * self.nominal_diameter_m**2 / 4.0


class SectionStatus(StrEnum):
    """Why a section's figures can or cannot be trusted."""

    OK = "ok"
    LOW_COVERAGE = "low_coverage"
    TOO_FEW_POINTS = "too_few_points"
    OUTSIDE_SCAN = "outside_scan"
    NO_CONTOUR = "no_contour"
    WEAK_REGISTRATION = "weak_registration"
    """Most frames that saw the section slid along the pipe axis (registration caught it
    against the odometer, and left them out), or one had neither odometer nor geometry along
    the axis (its place was extrapolated)."""
    SMEARED_WALL = "smeared_wall"
    """The frames that saw the section disagree: the wall's points spread around the contour
    by more than the sensor's noise allows, or a surface was seen in front of the wall where
    other frames saw the wall itself, or the section holds the edge of such a surface seen
    in the next section (``withhold_smeared_object_edges``)."""
    INVERT_UNDER_WATER = "invert_under_water"


@dataclass(frozen=True)
class SectionMeasures:
    """The measures of one section ``[chainage_start_m, chainage_end_m)``.

    Every measured figure is None when ``status`` is not ``ok`` and the figure could not be
    computed at all; when it could be computed but is not trusted, it is kept (for
    diagnostics) but must never be presented as measured.
    ``contour_m`` is the inner contour, shape (M, 2), in metres, in the section plane with
    the pipe centre at the origin, first column across (right), second up.
    ``chainage_uncertainty_m`` bounds how far the section's true place along the pipe may be
    from its chainage (the odometer-held travel before it; None when not known).
    ``wall_spread_m`` is the robust spread of the wall's points around the contour (a
    diagnostic of registration; not stored).
    ``wall_behind_deg`` is the widest arc over which an object was seen in front of a wall
    that other frames saw bare (``PolarProfile.wall_behind_deg``; a diagnostic, not stored).
    """

    chainage_start_m: float
    chainage_end_m: float
    nominal_area_m2: float
    status: SectionStatus
    point_count: int
    coverage_ratio: float
    open_area_m2: float | None = None
    blockage_ratio: float | None = None
    ovality_ratio: float | None = None
    deformation_ratio: float | None = None
    deposit_height_ratio: float | None = None
    grade: int | None = None
    # The 95 % uncertainty (half-width, ±) of each figure, as a ratio like the figure.
    blockage_uncertainty_ratio: float | None = None
    ovality_uncertainty_ratio: float | None = None
    deformation_uncertainty_ratio: float | None = None
    deposit_height_uncertainty_ratio: float | None = None
    # Depth of water in the invert over the nominal diameter: 0 when the invert was seen dry,
    # None when it could not be told.
    water_depth_ratio: float | None = None
    # Its 95 % uncertainty (±, ``core.water.WaterLevel.uncertainty_ratio``); None where no
    # water was read (the invert seen dry, or not known).
    water_depth_uncertainty_ratio: float | None = None
    contour_m: np.ndarray | None = field(default=None, compare=False, repr=False)
    chainage_uncertainty_m: float | None = None
    wall_spread_m: float | None = field(default=None, compare=False)
    water_from_surface: bool | None = field(default=None, compare=False)
    """Whether the water depth was read from returns on its surface (else from where the wall
    stops, confirmed along the pipe: ``core.water.confirm_surfaceless_water``; not stored)."""
    wall_behind_deg: float | None = field(default=None, compare=False)
    above_water_ok: bool | None = field(default=None, compare=False)
    """For a section with water in its invert: whether what was seen above the water passed
    every check an ``ok`` section passes (coverage of the arc above it, registration, the
    contour, the ±, the smear). None without water. Not stored: the defects coded from it
    are (:attr:`is_lower_bound`)."""

    @property
    def is_ok(self) -> bool:
        return self.status == SectionStatus.OK

    @property
    def is_lower_bound(self) -> bool:
        """Whether the section's figures are lower bounds: water fills its invert, which
        returned nothing below the level, and all above the water passed every check. The
        contour runs along the nominal wall under the water, so whatever stands there
        unseen is not counted: a blockage is at least the figure, never more."""
        return self.status == SectionStatus.INVERT_UNDER_WATER and bool(self.above_water_ok)

    @property
    def nominal_diameter_m(self) -> float:
        """The diameter of a circle of ``nominal_area_m2`` (the nominal inner diameter)."""
        return 2.0 * math.sqrt(self.nominal_area_m2 / math.pi)


@dataclass(frozen=True)
class Defect:
    """One physical feature along the pipe, coded and graded (docs/coding.md, docs/grading.md).

    ``code`` is the EN 13508-2 main code of its family (``BBC``, ``BBB``, ``BBE``, ``BAA``), or
    ``"unclassified"`` when no coding rule fits with confidence. ``measure`` is the column it
    was graded on, ``peak_value`` that measure's worst value (a ratio) at
    ``peak_chainage_m`` (the start of the worst section), ``grade`` its condition class.

    ``clock_from_h`` and ``clock_to_h`` are clock positions in hours, in (0, 12]: 12 at the
    crown, 3 on the right looking in the survey's direction; the displaced arc runs clockwise
    from ``clock_from_h`` to ``clock_to_h``. Both are None for a deformation, which moves the
    whole ring. ``characterisation`` is the EN 13508-2 characterisation where the geometry
    tells it (``A`` vertical or ``B`` horizontal for a deformation), else None.

    ``lower_bound`` is True when part of the feature stood in water that returned nothing
    (a section of it ``is_lower_bound``): the part under the water was not seen, so the
    feature is at least ``peak_value`` and its class at least as bad as ``grade``.
    """

    code: str
    measure: str
    chainage_start_m: float
    chainage_end_m: float
    peak_chainage_m: float
    peak_value: float
    peak_blockage_ratio: float | None
    grade: int | None
    clock_from_h: float | None = None
    clock_to_h: float | None = None
    characterisation: str | None = None
    lower_bound: bool = False


@dataclass(frozen=True)
class FrameQuality:
    """Registration quality of one frame: ICP fitness in [0, 1], inlier RMSE in metres, and
    whether the along-axis translation was held to the odometer (degenerate geometry).

    ``along_axis_weight`` is ICP's weight along the pipe axis against the odometer (0: held to
    it, 1: ICP alone); ``degenerate`` is that weight below one half. ``chainage_uncertainty_m``
    bounds the frame's along-axis position from the first frame. ``fault`` is ``"slide"``
    when registration slid along the axis and the frame was put back on the odometer (its
    sections are then not trusted), ``"odometer_slip"`` when the odometer disagreed with
    what ICP saw of features in view.
    """

    index: int
    fitness: float
    rmse_m: float
    degenerate: bool
    along_axis_weight: float = 0.0
    chainage_uncertainty_m: float = 0.0
    fault: str | None = None
    gate_sigma_m: float = float("inf")
    """The σ the innovation gate weighed ICP's disagreement with the odometer against: ICP's
    own error along the axis and the prior's together (``√(P² + 1/I)``; infinite where ICP
    had no information there). Where it is below a third of the crawler's step, a slip shows
    frame by frame."""
    overrode: bool = False
    """Whether ICP overrode the odometer along the axis at this frame (its disagreement beyond
    the innovation gate's 3σ): an odometer slip going on in view."""
