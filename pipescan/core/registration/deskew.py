"""Deskew a frame: place each point as the sensor saw it from its pose at the frame's start.

A scanning LiDAR fires a frame's rays over the frame period (0.1 s at 10 Hz) while the crawler
moves: at 0.15 m/s the sensor travels 15 mm within a frame, at 0.5 m/s 50 mm. Placing every
point with the frame's one pose smears the frame along the motion by that much. Where the
points carry their capture times, :func:`deskew_points` moves each point into the sensor
frame at the frame's reference time, from the motion over the frame: translation linear in
time, rotation by slerp (constant velocity and angular rate within the frame).

The reference time is the frame's earliest point time, so only differences between a frame's
own point times matter: times in any base (seconds since the scan start, GPS week seconds,
adjusted GPS seconds) give the same result, and the frame's pose is its pose when its first
point was captured.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

FRAME_TIME_SPAN_RATIO = 2.0
"""A frame's point times may span at most this many intervals between frames. Beyond it they
are not one frame's capture times in seconds (nanoseconds, a cloud's times, a clock jump):
reading them is an error rather than a deskew by a motion they do not describe."""


def deskew_points(
    points_sensor_m: np.ndarray,
    time_s: np.ndarray,
    T_motion: np.ndarray,
    motion_period_s: float,
    reference_time_s: float | None = None,
) -> np.ndarray:
    """Move each point of a frame into the sensor frame at the reference time.

    The sensor's pose at time ``t``, seen from its pose at the reference time ``t0``, is
    ``T_motion`` scaled to ``s = (t - t0) / motion_period_s`` of the way: translation
    ``s`` times ``T_motion``'s, rotation ``s`` times its rotation vector (slerp from the
    identity). A point ``p`` captured at ``t`` is then ``T(s) p`` in the sensor frame at ``t0``.

    Parameters
    ----------
    points_sensor_m : (N, 3) float
        The frame's points, sensor frame, metres, each as seen at its own time.
    time_s : (N,) float
        Each point's capture time, seconds (any base).
    T_motion : (4, 4) float
        The sensor's pose ``motion_period_s`` after the reference time in the sensor frame at
        the reference time: ``inv(T_world_frame_i) @ T_world_frame_j`` for frames ``i`` and
        ``j`` that far apart.
    motion_period_s : float
        The time over which ``T_motion`` happens (> 0).
    reference_time_s : float, optional
        The time to deskew to; default the earliest of ``time_s``.

    Returns
    -------
    (N, 3) float64, metres, in the sensor frame at the reference time.

    Raises
    ------
    ValueError
        For shapes that do not match, times that are not finite, or a period that is not
        positive.

    Examples
    --------
    >>> T = np.eye(4)
    >>> T[0, 3] = 0.05  # 50 mm forward over 0.1 s
    >>> p = np.array([[2.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    >>> deskew_points(p, np.array([0.0, 0.05]), T, 0.1).round(3).tolist()
    [[2.0, 0.0, 0.0], [2.025, 0.0, 0.0]]
    """
    pts = np.asarray(points_sensor_m, dtype=np.float64)
    t = np.asarray(time_s, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points_sensor_m must have shape (N, 3), got {pts.shape}.")
    if t.shape != (len(pts),):
        raise ValueError(f"time_s must have shape ({len(pts)},), got {t.shape}.")
    if np.shape(T_motion) != (4, 4):
        raise ValueError(f"T_motion must have shape (4, 4), got {np.shape(T_motion)}.")
    if not motion_period_s > 0:
        raise ValueError(f"motion_period_s must be > 0, got {motion_period_s!r}.")
    if len(pts) == 0:
        return pts.copy()
    if not np.isfinite(t).all():
        raise ValueError("time_s must be finite.")
    t0 = float(t.min()) if reference_time_s is None else float(reference_time_s)
    share = (t - t0) / motion_period_s
    rotvec = Rotation.from_matrix(np.asarray(T_motion)[:3, :3]).as_rotvec()
    translation = np.asarray(T_motion, dtype=np.float64)[:3, 3]
    # Rotation by s times the rotation vector (slerp from the identity), by Rodrigues'
    # formula per point: R p = p + sin(s a) k x p + (1 - cos(s a)) k x (k x p). In place into
    # one scratch array: a fresh (N, 3) array per term costs more than the arithmetic.
    angle_rad = float(np.linalg.norm(rotvec))
    moved = pts.copy()
    term = np.empty_like(pts)
    if angle_rad > 0.0:
        kx, ky, kz = rotvec / angle_rad
        K = np.array([[0.0, -kz, ky], [kz, 0.0, -kx], [-ky, kx, 0.0]])  # K p = k x p
        for matrix, weight in (
            (K, np.sin(share * angle_rad)),
            (K @ K, 1.0 - np.cos(share * angle_rad)),
        ):
            np.matmul(pts, np.ascontiguousarray(matrix.T), out=term)
            term *= weight[:, None]
            moved += term
    np.multiply(share[:, None], translation[None, :], out=term)
    moved += term
    return moved


def relative_motion(T_world_a: np.ndarray, T_world_b: np.ndarray) -> np.ndarray:
    """The pose of ``b`` in the frame of ``a``, (4, 4): what :func:`deskew_points` takes as
    ``T_motion`` for the time from ``a`` to ``b``."""
    return np.linalg.inv(np.asarray(T_world_a, dtype=np.float64)) @ np.asarray(T_world_b)


def travel_motion(T_world_a: np.ndarray, T_world_b: np.ndarray) -> np.ndarray:
    """:func:`relative_motion` without its rotation, (4, 4): the translation from ``a`` to
    ``b`` in the frame of ``a``. What pipescan deskews by: a crawler's travel is smooth and
    well measured from frame to frame, while the turn between two frames' estimated attitudes
    is mostly their errors (docs/registration.md, *Deskew*: with the rotation too, points
    land further from their truth when the sensor vibrates, and no nearer without)."""
    T_a = np.asarray(T_world_a, dtype=np.float64)
    T = np.eye(4)
    T[:3, 3] = T_a[:3, :3].T @ (np.asarray(T_world_b, dtype=np.float64)[:3, 3] - T_a[:3, 3])
    return T


def odometer_motion(step_m: float) -> np.ndarray:
    """The odometer's travel over a frame interval as the motion to deskew by, (4, 4):
    ``step_m`` along the sensor's x. Before the frames are registered there is no pose, and
    the sensor looks along the pipe (the registrar's own assumption until the map gives an
    axis); a mount pitched 3° puts the travel 0.14 % off the axis.

    >>> odometer_motion(0.015)[:3, 3].tolist()
    [0.015, 0.0, 0.0]
    """
    T = np.eye(4)
    T[0, 3] = float(step_m)
    return T


def frame_intervals(
    index: int, frame_time_s: Sequence[float | None]
) -> Iterator[tuple[int, int, float]]:
    """The intervals whose travel stands for frame ``index``'s own, in order of preference:
    to the next frame, then from the one before (the last frame has no next). Each is
    ``(a, b, seconds)``, only where both frames' times are known and increase.

    >>> [(a, b) for a, b, _ in frame_intervals(1, [0.0, 0.1, 0.2])]
    [(1, 2), (0, 1)]
    >>> [(a, b) for a, b, _ in frame_intervals(2, [0.0, 0.1, None])]
    []
    """
    for a, b in ((index, index + 1), (index - 1, index)):
        if a < 0 or b >= len(frame_time_s):
            continue
        t_a, t_b = frame_time_s[a], frame_time_s[b]
        if t_a is not None and t_b is not None and t_b > t_a:
            yield a, b, t_b - t_a


def odometer_travel(
    index: int, frame_time_s: Sequence[float | None], odometer_m: Sequence[float | None]
) -> tuple[np.ndarray, float] | None:
    """The odometer's travel over frame ``index`` (:func:`frame_intervals`), as the motion
    to deskew by and its time (:func:`odometer_motion`), or None where no interval has both
    readings: what is read before the frames are registered (the survey's instrument)."""
    for a, b, period_s in frame_intervals(index, frame_time_s):
        odo_a, odo_b = odometer_m[a], odometer_m[b]
        if odo_a is not None and odo_b is not None:
            return odometer_motion(odo_b - odo_a), period_s
    return None


TIME_UNITS_S: dict[str, float] = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
"""The units a point time field may be in, and one of each in seconds."""


def point_times_s(
    raw_time: np.ndarray, frame_interval_s: float, *, units: tuple[str, ...] = tuple(TIME_UNITS_S)
) -> np.ndarray | None:
    """A frame's raw point times in seconds, their unit chosen from the frame's own span.

    A PLY, PCD or PointCloud2 time field has no fixed unit (Ouster's ``t`` is uint32
    nanoseconds, Velodyne's ``time`` float32 seconds, Livox's ``timestamp`` float64
    nanoseconds), but physics fixes it: a frame is captured over about one frame interval.
    So the unit is the one of ``units`` whose span is nearest ``frame_interval_s`` (by
    ratio) among those spanning more than 0 and at most :data:`FRAME_TIME_SPAN_RATIO`
    intervals. The units are 1000 apart, so two never both fall within a factor of 2 of the
    interval; a uint32 offset in nanoseconds (span ~10^8) cannot be seconds.

    Parameters
    ----------
    raw_time : (N,) integer or float
        Each point's time as the file holds it, any base.
    frame_interval_s : float
        The interval between frames (> 0), seconds.
    units : tuple of str
        The keys of :data:`TIME_UNITS_S` the field may be in (``("s",)`` for LAS GPS time).

    Returns
    -------
    (N,) float64 seconds, in the field's own base; None when there are no points or every
    point has the same time (a frame without times).

    Raises
    ------
    ValueError
        For a dtype that is not integer or float, a NaN or infinite time, or a span that no
        unit of ``units`` puts within :data:`FRAME_TIME_SPAN_RATIO` frame intervals.

    Examples
    --------
    >>> ns = np.array([0, 50_000_000, 99_000_000], dtype=np.uint32)  # Ouster's t
    >>> point_times_s(ns, 0.1).tolist()
    [0.0, 0.05, 0.099]
    >>> point_times_s(np.array([0.0, 0.05, 0.099], dtype=np.float32), 0.1).round(3).tolist()
    [0.0, 0.05, 0.099]
    """
    raw = np.asarray(raw_time)
    if raw.dtype.kind not in "iuf":
        raise ValueError(f"the time field is of type {raw.dtype}, not an integer or a float")
    if not frame_interval_s > 0:
        raise ValueError(f"frame_interval_s must be > 0, got {frame_interval_s!r}")
    if raw.size == 0:
        return None
    if raw.dtype.kind == "f" and not np.isfinite(raw).all():
        raise ValueError(f"{int((~np.isfinite(raw)).sum())} points have a NaN or infinite time")
    low, high = raw.min(), raw.max()
    # Integers' span exactly (Python ints: no overflow for int64 or uint64 values).
    span = (int(high) - int(low)) if raw.dtype.kind in "iu" else float(high) - float(low)
    if span == 0:
        return None
    fitting = [
        (abs(np.log(span * TIME_UNITS_S[u] / frame_interval_s)), u)
        for u in units
        if span * TIME_UNITS_S[u] <= FRAME_TIME_SPAN_RATIO * frame_interval_s
    ]
    if not fitting:
        limit = f"{FRAME_TIME_SPAN_RATIO:g} times the {frame_interval_s:.6g} s between frames"
        if len(units) == 1:
            raise ValueError(
                f"the points' times span {span * TIME_UNITS_S[units[0]]:.4g} s, more than "
                f"{limit}: they are not one frame's capture times"
            )
        spans = ", ".join(f"{span * TIME_UNITS_S[u]:.4g} s if in {u}" for u in units)
        raise ValueError(
            f"the points' times span {span:.6g} ({spans}), more than {limit} in every unit: "
            "they are not one frame's capture times"
        )
    scale = TIME_UNITS_S[min(fitting)[1]]
    # The offsets from the earliest point are small (within the bound): exact for integers.
    if raw.dtype.kind == "u":
        offsets = (raw - low).astype(np.float64)
    elif raw.dtype.kind == "i":
        offsets = (raw.astype(np.int64) - np.int64(low)).astype(np.float64)
    else:
        offsets = raw.astype(np.float64) - float(low)
    return offsets * scale + float(low) * scale
