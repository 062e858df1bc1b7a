"""Where a registered cloud's scan starts, and which way it went.

A cloud (SLAM output, a terrestrial scanner's export) carries no sensor poses, so the end of
the pipe the scan started from (chainage ``chainage_offset_m``) is taken from the first source
that applies (docs/archive.md, "Where a registered cloud starts"):

1. ``start_xyz`` from ``inspection.toml``: the sensor's first position, in the cloud's frame;
2. each point's capture time (LAS GPS time, a time field of a PLY, PCD or E57): the end where
   the earliest points lie, when time runs along the pipe, moved back by how far ahead of the
   sensor its first points lie (its minimum range, from ``[sensor]``:
   :func:`sensor_start_offset`), with that as the start's uncertainty;
3. the end nearer the cloud frame's origin, which is where SLAM puts its first pose.

A frames archive starts where its first frame was taken (``first_frame``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np

if TYPE_CHECKING:
    from pipescan.core.model import SensorProfile

StartSource = Literal["first_frame", "start_xyz", "point_time", "nearer_origin"]

START_SOURCES: dict[str, str] = {
    "first_frame": "the sensor's position at the first frame",
    "start_xyz": "start_xyz in inspection.toml",
    "point_time": "the points' capture time (the earliest points' end)",
    "nearer_origin": "the end nearer the cloud frame's origin (no start_xyz, no point time)",
}
"""What each start source means, as the summary and the report say it."""

TIME_SHARE = 0.05
"""The earliest and latest points compared are this share of the cloud each."""

MIN_TIME_SEPARATION_RATIO = 0.25
"""Time says which end came first only when the earliest and the latest points lie at least
this share of the cloud's length apart along it (a static scanner's time sweeps round a
station, not along the pipe)."""


@dataclass(frozen=True)
class CloudStart:
    """The scan's start and travel for a registered cloud.

    Attributes
    ----------
    start_m : (3,) float
        A point at the start (the sensor's first position, or the end of the cloud where the
        scan began), in the cloud's frame.
    travel_m : (3,) float
        A vector along the pipe in the direction the scan went.
    source : str
        Which rule decided (a key of :data:`START_SOURCES`).
    """

    start_m: np.ndarray
    travel_m: np.ndarray
    source: StartSource
    uncertainty_m: float = 0.0
    """How far the sensor's true start may be from ``start_m`` along the pipe (m)."""


UNSTATED_MIN_RANGE_M = 1.0
"""A cloud dated by its points' time, from a sensor whose minimum range is not stated: the
largest blind zone of the forward-looking sensors pipescan knows (Livox Avia, 1 m). Its first
points lie up to about this far ahead of where it started, so the start is within ± this."""

_SENSOR_ECCENTRICITY_RATIO = 1.0 / 3.0
"""How far off the axis a crawler's sensor may sit, as a share of the radius."""


def sensor_start_offset(
    min_range_m: float, radius_m: float, half_fov_deg: float
) -> tuple[float, float]:
    """How far ahead of a forward-looking sensor its nearest wall returns lie along the pipe,
    and how well that is known: ``(offset_m, uncertainty_m)``.

    A ray reaches the wall (radius ``R`` from a sensor on the axis) no nearer than the
    sensor's minimum range ``r`` and no steeper than its half field of view ``α``: the
    nearest return lies ``√(r² − R²)`` ahead when the ray at range ``r`` is within the field
    of view, ``R / tan α`` otherwise. A sensor ``e`` off the axis sees one side nearer and one
    further: the offset is the middle of the two, and half their difference, for ``e`` up to
    a third of the radius, is its uncertainty.

    >>> [round(v, 2) for v in sensor_start_offset(0.5, 0.3, 60.0)]
    [0.38, 0.08]
    """

    def ahead(radius: float) -> float:
        if min_range_m > radius and np.degrees(np.arcsin(radius / min_range_m)) <= half_fov_deg:
            return float(np.sqrt(min_range_m**2 - radius**2))
        return float(radius / np.tan(np.radians(min(half_fov_deg, 89.0))))

    e = _SENSOR_ECCENTRICITY_RATIO * radius_m
    near, far = ahead(radius_m + e), ahead(radius_m - e)
    return (near + far) / 2.0, abs(far - near) / 2.0


def cloud_start(
    points_m: np.ndarray,
    direction: np.ndarray,
    *,
    time_s: np.ndarray | None = None,
    start_xyz: np.ndarray | None = None,
    sensor_ahead_m: tuple[float, float] = (0.0, UNSTATED_MIN_RANGE_M),
) -> CloudStart:
    """Choose a registered cloud's start (see the module's rules).

    Parameters
    ----------
    points_m : (N, 3) float
        The cloud, metres, in its own frame.
    direction : (3,) float
        The pipe's axis direction (either sign).
    time_s : (N,) float, optional
        Each point's capture time.
    start_xyz : (3,) float, optional
        The sensor's first position, from ``inspection.toml``.
    sensor_ahead_m : (float, float)
        How far ahead of the sensor its first points lie, and how well that is known
        (:func:`sensor_start_offset`; by default unknown, up to :data:`UNSTATED_MIN_RANGE_M`):
        a start read from the points' time is moved back by it, and carries it as its
        uncertainty.

    Returns
    -------
    CloudStart

    Examples
    --------
    >>> x = np.linspace(10.0, 0.0, 1000)
    >>> pts = np.column_stack((x, np.zeros(1000), np.zeros(1000)))
    >>> c = cloud_start(pts, np.array([1.0, 0, 0]), time_s=np.arange(1000.0))
    >>> c.source, c.start_m.round(2).tolist(), c.travel_m.tolist(), c.uncertainty_m
    ('point_time', [9.99, 0.0, 0.0], [-1.0, -0.0, -0.0], 1.0)
    >>> cloud_start(pts, np.array([1.0, 0, 0])).source
    'nearer_origin'
    """
    pts = np.asarray(points_m, dtype=np.float64)
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    centre = pts.mean(axis=0)
    along = (pts - centre) @ d
    lo, hi = (float(v) for v in np.percentile(along, [0.1, 99.9]))
    end_lo, end_hi = centre + lo * d, centre + hi * d

    if start_xyz is not None:
        start = np.asarray(start_xyz, dtype=np.float64)
        s = float((start - centre) @ d)
        sign = 1.0 if abs(s - lo) <= abs(s - hi) else -1.0
        return CloudStart(start, sign * d, "start_xyz")

    if time_s is not None and len(time_s) == len(pts) and float(np.ptp(time_s)) > 0:
        t = np.asarray(time_s, dtype=np.float64)
        early_t, late_t = np.quantile(t, [TIME_SHARE, 1.0 - TIME_SHARE])
        early = along[t <= early_t]
        late = along[t >= late_t]
        if len(early) and len(late):
            gap = float(np.median(late) - np.median(early))
            if abs(gap) >= MIN_TIME_SEPARATION_RATIO * (hi - lo):
                travel = (1.0 if gap > 0 else -1.0) * d
                offset, uncertainty = sensor_ahead_m
                start = (end_lo if gap > 0 else end_hi) - offset * travel
                return CloudStart(start, travel, "point_time", uncertainty)

    if np.linalg.norm(end_lo) <= np.linalg.norm(end_hi):
        return CloudStart(end_lo, d, "nearer_origin")
    return CloudStart(end_hi, -d, "nearer_origin")


def sensor_ahead_m(sensor: SensorProfile | None, nominal_diameter_m: float) -> tuple[float, float]:
    """How far ahead of the sensor a registered cloud's first points lie, and how well that
    is known (:func:`sensor_start_offset`), for the ``[sensor]`` profile: a forward-looking
    sensor (field of view under 180° both ways) with a stated minimum range. Otherwise
    unknown: ``(0, UNSTATED_MIN_RANGE_M)``.

    >>> from pipescan.core.model import SensorProfile
    >>> hap = SensorProfile(min_range_m=0.5, fov_horizontal_deg=120.0, fov_vertical_deg=25.0)
    >>> [round(v, 2) for v in sensor_ahead_m(hap, 0.6)]
    [0.38, 0.08]
    >>> sensor_ahead_m(None, 0.6)
    (0.0, 1.0)
    """
    fovs = [] if sensor is None else [sensor.fov_horizontal_deg, sensor.fov_vertical_deg]
    if (
        sensor is None
        or sensor.min_range_m is None
        or None in fovs
        or max(fovs) >= 180.0
        or not np.isfinite(nominal_diameter_m)
    ):
        return 0.0, UNSTATED_MIN_RANGE_M
    return sensor_start_offset(sensor.min_range_m, nominal_diameter_m / 2.0, max(fovs) / 2.0)
