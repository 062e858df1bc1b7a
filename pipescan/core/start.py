"""Where a registered cloud's scan starts, and which way it went.

A cloud (SLAM output, a terrestrial scanner's export) carries no sensor poses, so the end of
the pipe the scan started from (chainage ``chainage_offset_m``) is taken from the first source
that applies (docs/archive.md, "Where a registered cloud starts"):

1. ``start_xyz`` from ``inspection.toml``: the sensor's first position, in the cloud's frame;
2. each point's capture time (LAS GPS time, a time field of a PLY, PCD or E57): the end where
   the earliest points lie, when time runs along the pipe;
3. the end nearer the cloud frame's origin, which is where SLAM puts its first pose.

A frames archive starts where its first frame was taken (``first_frame``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

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


def cloud_start(
    points_m: np.ndarray,
    direction: np.ndarray,
    *,
    time_s: np.ndarray | None = None,
    start_xyz: np.ndarray | None = None,
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

    Returns
    -------
    CloudStart

    Examples
    --------
    >>> x = np.linspace(10.0, 0.0, 1000)
    >>> pts = np.column_stack((x, np.zeros(1000), np.zeros(1000)))
    >>> c = cloud_start(pts, np.array([1.0, 0, 0]), time_s=np.arange(1000.0))
    >>> c.source, c.start_m.round(2).tolist(), c.travel_m.tolist()
    ('point_time', [9.99, 0.0, 0.0], [-1.0, -0.0, -0.0])
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
                start = end_lo if gap > 0 else end_hi
                return CloudStart(start, (1.0 if gap > 0 else -1.0) * d, "point_time")

    if np.linalg.norm(end_lo) <= np.linalg.norm(end_hi):
        return CloudStart(end_lo, d, "nearer_origin")
    return CloudStart(end_hi, -d, "nearer_origin")
