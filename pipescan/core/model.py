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
class InspectionMeta:
    """The validated content of ``inspection.toml``."""

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


@dataclass(frozen=True)
class SectionMeasures:
    """The measures of one section ``[chainage_start_m, chainage_end_m)``.

    Every measured figure is None when ``status`` is not ``ok`` and the figure could not be
    computed at all; when it could be computed but is not trusted, it is kept (for
    diagnostics) but must never be presented as measured.
    ``contour_m`` is the inner contour, shape (M, 2), in metres, in the section plane with
    the pipe centre at the origin, first column across (right), second up.
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
    contour_m: np.ndarray | None = field(default=None, compare=False, repr=False)

    @property
    def is_ok(self) -> bool:
        return self.status == SectionStatus.OK


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


@dataclass(frozen=True)
class FrameQuality:
    """Registration quality of one frame: ICP fitness in [0, 1], inlier RMSE in metres, and
    whether the along-axis translation was held to the odometer (degenerate geometry)."""

    index: int
    fitness: float
    rmse_m: float
    degenerate: bool
