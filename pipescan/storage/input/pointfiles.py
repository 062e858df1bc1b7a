"""Read and write point files: LAS/LAZ, PLY, PCD, ``.npy`` and ASCII ``x y z``.

:func:`read_points` is the one entry point for reading. It picks the reader for the file's
suffix from :data:`~pipescan.storage.input.readers.READERS` (one module per format), returns
an ``(N, 3)`` float64 array in metres and turns every problem with the file into a
:class:`PointFileError` that names the archive, the member file and the field, with a hint on
how to fix it: unknown suffix, corrupt or truncated file, a header that declares more points
than the file holds, a file over a limit, wrong shape, no points, NaN/inf values, and values
that are almost surely millimetres rather than metres.

Every reader checks the counts a header declares against the bytes actually present before it
allocates anything, so a lying header costs nothing (docs/security.md).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from pipescan.core.registration.deskew import TIME_UNITS_S, point_times_s
from pipescan.storage.input.limits import DEFAULT_LIMITS, InputLimits
from pipescan.storage.input.readers import READERS, Where, las, pcd, ply
from pipescan.storage.input.readers.las import LAS_SCALE_M

POINT_SUFFIXES: tuple[str, ...] = tuple(READERS)
"""Suffixes of the point files pipescan reads (compared case-insensitively)."""

FRAME_MM_MEDIAN_RANGE_M = 50.0
"""A frame (sensor coordinates) whose median point range exceeds this is in millimetres.

Inside a pipe the median return is a pipe radius or two away from the sensor; 50 m would
be a tunnel far larger than any sewer, while 50 mm-units is only 5 cm."""

CLOUD_MM_DIAMETER_M = 20.0
"""A cloud whose second-largest principal extent (≈ the pipe diameter) exceeds this is in
millimetres. A cloud may be georeferenced, so its distance from the origin says nothing."""

MAX_COORDINATE = 1e11
"""No coordinate is larger than this, in metres or in millimetres (an earth-centred frame
reaches 6.4 × 10^9 mm): larger values are not a position, and would overflow the checks
below."""

_MEDIAN_SAMPLE_POINTS = 4096
"""About this many points (a stride through the frame) decide a frame's median range."""

MM_HINT = "the values look like millimetres; pipescan expects metres: divide by 1000"

PointKind = Literal["frame", "cloud"]

_AXES = ("x", "y", "z")
__all__ = [
    "LAS_SCALE_M",
    "POINT_SUFFIXES",
    "TIMED_FRAME_SUFFIXES",
    "PointChunk",
    "StridedSample",
    "check_point_file",
    "frame_times_s",
    "is_point_file",
    "iter_point_chunks",
    "point_suffix",
    "read_point_time",
    "read_points",
    "read_timed_frame",
    "width_across_m",
    "write_points",
]


def point_suffix(name: str | Path) -> str:
    """Return the lower-case suffix of a file name (``"frames/A.LAZ"`` → ``".laz"``)."""
    return Path(name).suffix.lower()


def is_point_file(name: str | Path) -> bool:
    """True when ``name`` has one of the :data:`POINT_SUFFIXES`."""
    return point_suffix(name) in POINT_SUFFIXES


def read_points(
    path: Path,
    *,
    archive: str | None = None,
    member: str | None = None,
    kind: PointKind = "frame",
    limits: InputLimits = DEFAULT_LIMITS,
) -> np.ndarray:
    """Read one point file and check that it holds usable points in metres.

    Parameters
    ----------
    path
        The file on disk. Its suffix picks the reader: ``.las``/``.laz`` (laspy, scaled
        coordinates), ``.ply`` (numpy), ``.pcd`` (Open3D, after a header check), ``.npy``
        (an ``(N, 3)`` float array) or ``.xyz``/``.txt`` (ASCII rows ``x y z ...``, space or
        comma separated; extra columns, non-numeric header lines and ``#`` comments are
        ignored).
    archive, member
        The archive and the member path inside it, used in error messages. ``member``
        defaults to the file name.
    kind
        ``"frame"``: a LiDAR frame in sensor coordinates; ``"cloud"``: a registered cloud in
        a common (possibly georeferenced) frame. Only the millimetre check differs: a frame
        is tested on its median range (> :data:`FRAME_MM_MEDIAN_RANGE_M`), a cloud on its
        second principal extent (> :data:`CLOUD_MM_DIAMETER_M`).
    limits
        Caps on the file (points, line length); the error for a file over one names it.

    Returns
    -------
    numpy.ndarray
        Shape ``(N, 3)``, float64, metres, with ``N >= 1`` and every value finite.

    Raises
    ------
    PointFileError
        Unknown suffix, missing, unreadable, corrupt or truncated file, a header declaring
        more than the file holds, a file over a limit, wrong shape or dtype, no points, NaN
        or infinite values, or values in millimetres. The error names
        ``archive``, ``member`` and the field (``"points"`` or the affected axes).

    Examples
    --------
    >>> pts = read_points(Path("frames/000001.laz"), archive="run.zip")  # doctest: +SKIP
    >>> pts.shape, pts.dtype  # doctest: +SKIP
    ((28412, 3), dtype('float64'))
    """
    path = Path(path)
    where, reader = _reader(path, archive, member, limits)
    points = reader.read(path, where)
    _check_points(points, kind, where)
    return points


TIMED_FRAME_SUFFIXES = (".las", ".laz", ".pcd", ".ply")
"""Frame formats whose point times :func:`read_timed_frame` reads: LAS/LAZ GPS time (seconds,
by the LAS specification), a PCD field or PLY property named in ``TIME_NAMES`` (no fixed unit:
seconds, milliseconds, microseconds or nanoseconds, told by the frame's span)."""


def read_timed_frame(
    path: Path,
    *,
    interval_s: float | None = None,
    archive: str | None = None,
    member: str | None = None,
    limits: InputLimits = DEFAULT_LIMITS,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Read a frame and each point's capture time, decoding the file once.

    Parameters
    ----------
    path, archive, member, limits
        As :func:`read_points`.
    interval_s : float, optional
        The interval between frames (s). With it, the times' span is checked against it and
        a field of no fixed unit (PCD, PLY) gets its unit from it
        (:func:`~pipescan.core.registration.deskew.point_times_s`); without it, only LAS/LAZ
        GPS time is read, unchecked.

    Returns
    -------
    points : (N, 3) float64, metres, sensor frame, as :func:`read_points` returns them
    time_s : (N,) float64 seconds, or None when the file is not a
        :data:`TIMED_FRAME_SUFFIXES` file, holds no time, gives every point the same time, or
        (PCD, PLY) no ``interval_s`` is given

    Raises
    ------
    PointFileError
        As :func:`read_points`; for a time that is NaN or infinite, a time field that is not
        one number per point, or times that span more than
        :data:`~pipescan.core.registration.deskew.FRAME_TIME_SPAN_RATIO` frame intervals in
        every unit; naming the time field.
    """
    path = Path(path)
    suffix = point_suffix(path)
    if suffix not in TIMED_FRAME_SUFFIXES:
        points = read_points(path, archive=archive, member=member, kind="frame", limits=limits)
        return points, None
    where, _ = _reader(path, archive, member, limits)
    units: tuple[str, ...]
    if suffix in las.SUFFIXES:
        points, raw = las.read_timed(path, where)
        field, units = "gps_time", ("s",)
    else:
        points, raw, found = (pcd if suffix in pcd.SUFFIXES else ply).read_timed(path, where)
        field, units = found or "time", tuple(TIME_UNITS_S)
    _check_points(points, "frame", where)
    if raw is None or len(raw) != len(points):
        return points, None
    if interval_s is None:
        if suffix not in las.SUFFIXES:
            return points, None
        if not np.isfinite(raw).all():
            raise where.error(
                f"{int((~np.isfinite(raw)).sum())} points have a NaN or infinite GPS time",
                field=field,
                hint="export the frame again, or without GPS time",
            )
        return points, raw if float(np.ptp(raw)) > 0.0 else None
    return points, frame_times_s(raw, interval_s, where, field=field, units=units)


def frame_times_s(
    raw: np.ndarray,
    interval_s: float,
    where: Where,
    *,
    field: str,
    units: tuple[str, ...] = tuple(TIME_UNITS_S),
) -> np.ndarray | None:
    """:func:`~pipescan.core.registration.deskew.point_times_s` on a frame's raw times, its
    error as a :class:`PointFileError` naming ``where``'s file and ``field``."""
    try:
        return point_times_s(raw, interval_s, units=units)
    except ValueError as exc:
        unit = "seconds" if units == ("s",) else "s, ms, us or ns"
        raise where.error(
            f"{exc} ({unit})",
            field=field,
            hint="write each point's capture time within its frame, or no time field",
        ) from None


CLOUD_CHUNK_POINTS = 1_000_000
"""Points of a registered cloud read at a time (24 MB as float64)."""

_CHECK_SAMPLE_POINTS = 200_000
"""At most this many points (a stride through the cloud) decide the millimetre check of a
cloud read in chunks, as :func:`width_across_m` strides a whole one."""


@dataclass(frozen=True)
class PointChunk:
    """Consecutive points of a file: ``points`` (K, 3) float64 metres, ``time_s`` (K,) seconds
    or None, and ``first``, the row of its first point in the file."""

    points: np.ndarray
    time_s: np.ndarray | None
    first: int


class StridedSample:
    """Every ``stride``-th row of a stream of chunks (rows 0, s, 2s, ...), with ``stride``
    doubled whenever more than ``limit`` rows are held: a uniform sample of at most ``limit``
    rows of a stream of unknown length, in one pass.

    Examples
    --------
    >>> sample = StridedSample(4)
    >>> for first in range(0, 10, 3):
    ...     sample.add(first, np.arange(first, min(first + 3, 10)))
    >>> sample.stride, sample.columns()[0].tolist()
    (4, [0, 4, 8])
    """

    def __init__(self, limit: int) -> None:
        if limit < 1:
            raise ValueError(f"limit must be >= 1, got {limit}")
        self.limit = limit
        self.stride = 1
        self._next = 0
        self._parts: list[tuple[np.ndarray | None, ...]] = []
        self._rows = 0

    def add(self, first: int, *columns: np.ndarray | None) -> None:
        """Offer rows ``first..first + len - 1`` (consecutive with the rows offered before);
        a column may be None (kept as None)."""
        n = next(len(c) for c in columns if c is not None)
        start = self._next - first
        if start >= n:
            return
        take = slice(start, n, self.stride)
        part = tuple(None if c is None else np.array(c[take]) for c in columns)
        count = len(range(start, n, self.stride))
        self._parts.append(part)
        self._rows += count
        self._next += count * self.stride
        while self._rows > self.limit:
            merged = self.columns()
            self._parts = [tuple(None if c is None else c[::2] for c in merged)]
            self._rows = (self._rows + 1) // 2
            self.stride *= 2
            self._next = -(-self._next // self.stride) * self.stride

    def columns(self) -> tuple[np.ndarray | None, ...]:
        """The sampled rows of each column, in order (a column offered as None stays None)."""
        if not self._parts:
            return ()
        return tuple(
            None if parts[0] is None else np.concatenate(parts)
            for parts in zip(*self._parts, strict=True)
        )


def iter_point_chunks(
    path: Path,
    *,
    archive: str | None = None,
    member: str | None = None,
    kind: PointKind = "cloud",
    limits: InputLimits = DEFAULT_LIMITS,
    chunk_points: int | None = None,
    with_time: bool = False,
) -> Iterator[PointChunk]:
    """Read a point file a chunk at a time, with the checks of :func:`read_points`.

    LAS, LAZ, E57, binary PLY, ASCII x y z and ``.npy`` stream: one chunk of at most
    ``chunk_points`` is in memory at a time, so a registered cloud of any size can be read. ASCII
    PLY and PCD files are read whole and handed out in chunks. Each chunk is checked as it comes
    (finite, within :data:`MAX_COORDINATE`; with ``with_time``, a finite time); the millimetre check
    runs on a strided sample once the last chunk is read, and raises after it, so a caller must
    treat what it did with the chunks as unfinished until the iteration ends.

    Parameters
    ----------
    path, archive, member, kind, limits
        As :func:`read_points`.
    chunk_points : int, optional
        Largest chunk, in points (default :data:`CLOUD_CHUNK_POINTS`).
    with_time : bool
        Also read each point's capture time (as :func:`read_point_time`); ``time_s`` is None
        when the file holds none.

    Raises
    ------
    PointFileError
        As :func:`read_points` and :func:`read_point_time`; the error names the field.
    """
    path = Path(path)
    where, reader = _reader(path, archive, member, limits)
    chunk_points = CLOUD_CHUNK_POINTS if chunk_points is None else chunk_points
    check = StridedSample(_CHECK_SAMPLE_POINTS)
    first = 0
    for points, time_s in _raw_chunks(path, where, reader, chunk_points, with_time):
        _check_finite(points, where, first)
        if time_s is not None and not np.isfinite(time_s).all():
            bad = int((~np.isfinite(time_s)).sum())
            last = first + len(time_s) - 1
            raise where.error(
                f"{bad} of the points in rows {first:,}-{last:,} have a NaN or infinite time",
                field="time",
                hint="export the cloud again, or without its time field",
            )
        check.add(first, points)
        yield PointChunk(points, time_s, first)
        first += len(points)
    if first == 0:
        raise where.error(
            f"the file holds no points (empty {kind})",
            hint="re-export the file, or remove it and its [[frames]] entry from the archive",
        )
    (sample,) = check.columns()
    assert sample is not None
    _check_units(sample, kind, where)


def _raw_chunks(path: Path, where: Where, reader, chunk_points: int, with_time: bool):
    if reader.iter_chunks is not None:
        yield from reader.iter_chunks(path, where, chunk_points=chunk_points, with_time=with_time)
        return
    points = reader.read(path, where)
    time_s = reader.read_time(path, where) if with_time and reader.read_time else None
    if time_s is not None and len(time_s) != len(points):
        raise where.corrupt(
            f"the file holds {len(time_s):,} times for {len(points):,} points", field="time"
        )
    step = max(1, chunk_points)
    for a in range(0, len(points), step):
        yield points[a : a + step], None if time_s is None else time_s[a : a + step]


def check_point_file(
    path: Path,
    *,
    archive: str | None = None,
    member: str | None = None,
    limits: InputLimits = DEFAULT_LIMITS,
) -> int:
    """Check a point file's header against the bytes present, without reading its points
    into memory; return the point count it declares (for ASCII, its row count).

    Raises
    ------
    PointFileError
        As :func:`read_points`, for everything that can be told without the points.
    """
    path = Path(path)
    where, reader = _reader(path, archive, member, limits)
    return reader.check(path, where)


def _reader(path: Path, archive: str | None, member: str | None, limits: InputLimits):
    where = Where(archive, member if member is not None else path.name, limits)
    suffix = point_suffix(path)
    reader = READERS.get(suffix)
    if reader is None:
        raise where.error(
            f"unsupported point-file suffix {suffix or '(none)'!r}",
            hint=f"use one of {', '.join(POINT_SUFFIXES)}",
        )
    if not path.is_file():
        raise where.error("the point file does not exist", hint="check the path and the archive")
    return where, reader


def read_point_time(
    path: Path,
    *,
    archive: str | None = None,
    member: str | None = None,
    limits: InputLimits = DEFAULT_LIMITS,
) -> np.ndarray | None:
    """Each point's capture time, ``(N,)`` float64 seconds, in the order :func:`read_points`
    returns the points: LAS/LAZ GPS time, a ``time`` (``timestamp``, ``gps_time``, ``t``)
    property of a PLY or field of a PCD, an E57 scan's ``timeStamp``. None when the file
    holds no time, or its format never does.

    Raises
    ------
    PointFileError
        As :func:`read_points`; and when a time is NaN or infinite.
    """
    path = Path(path)
    where, reader = _reader(path, archive, member, limits)
    if reader.read_time is None:
        return None
    time_s = reader.read_time(path, where)
    if time_s is not None and not np.isfinite(time_s).all():
        raise where.error(
            f"{int((~np.isfinite(time_s)).sum())} points have a NaN or infinite time",
            field="time",
            hint="export the cloud again, or without its time field",
        )
    return time_s


def write_points(path: Path, points: np.ndarray, *, time_s: np.ndarray | None = None) -> None:
    """Write an ``(N, 3)`` array of metres to a point file, in the format of its suffix.

    LAS/LAZ are written as LAS 1.4, point format 6, with a scale of :data:`LAS_SCALE_M`
    (0.1 mm) and the offset at the minimum of the points; ``.laz`` is compressed with
    lazrs. PLY (binary, float64) and PCD (binary) go through Open3D; note that Open3D
    stores PCD coordinates as float32, which keeps 0.1 mm only within ~1 km of the
    origin. ``.npy`` is a float64 array; ``.xyz``/``.txt`` are ASCII rows ``x y z`` with
    17 significant digits (lossless). Missing parent directories are created.

    Parameters
    ----------
    path
        Target file; its suffix must be one of :data:`POINT_SUFFIXES`.
    points
        Shape ``(N, 3)``, metres. ``N`` may be 0. NaN is kept except in LAS/LAZ.

    Raises
    ------
    ValueError
        Wrong shape, unknown suffix, or (LAS/LAZ) values that the 0.1 mm integer grid
        cannot hold (non-finite, or a span over ~214 km).
    """
    path = Path(path)
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3); got {pts.shape}")
    suffix = point_suffix(path)
    if suffix not in POINT_SUFFIXES:
        raise ValueError(f"unsupported point-file suffix {suffix!r}; use one of {POINT_SUFFIXES}")
    writer = READERS[suffix].write
    if writer is None:
        raise ValueError(f"pipescan cannot write {READERS[suffix].name} files")
    path.parent.mkdir(parents=True, exist_ok=True)
    if time_s is None:
        writer(path, pts)
        return
    if READERS[suffix].read_time is None:
        raise ValueError(f"{READERS[suffix].name} files hold no time per point")
    time_s = np.asarray(time_s, dtype=np.float64)
    if time_s.shape != (len(pts),):
        raise ValueError(f"time_s must have shape ({len(pts)},); got {time_s.shape}")
    writer(path, pts, time_s)


# --- content checks ---------------------------------------------------------------------------


def check_points(
    points: np.ndarray,
    *,
    archive: str | None,
    member: str,
    kind: PointKind = "frame",
    limits: InputLimits = DEFAULT_LIMITS,
) -> np.ndarray:
    """The checks :func:`read_points` makes on what a reader returned (no points, NaN,
    millimetres), for points that came from elsewhere (a bag's message); returns them."""
    _check_points(points, kind, Where(archive, member, limits))
    return points


def _check_points(points: np.ndarray, kind: PointKind, where: Where) -> None:
    n = len(points)
    if n == 0:
        raise where.error(
            f"the file holds no points (empty {kind})",
            hint="re-export the file, or remove it and its [[frames]] entry from the archive",
        )
    _check_finite(points, where)
    _check_units(points, kind, where)


def _check_finite(points: np.ndarray, where: Where, first: int | None = None) -> None:
    """No NaN or infinite coordinate, none beyond :data:`MAX_COORDINATE`; ``first``, the row
    of a chunk's first point, is named in the error."""
    if len(points) == 0:
        return
    n = len(points)
    bad = ~np.isfinite(points)
    if bad.any():
        rows = int(bad.any(axis=1).sum())
        per_axis = ", ".join(f"{a}: {int(bad[:, j].sum())}" for j, a in enumerate(_AXES))
        rows_of = f"rows {first:,}-{first + n - 1:,}" if first is not None else ""
        of = f"of the points in {rows_of}" if rows_of else f"of {n} points"
        raise where.error(
            f"{rows} {of} have NaN or infinite coordinates ({per_axis})",
            field=",".join(a for j, a in enumerate(_AXES) if bad[:, j].any()),
            hint="drop the non-finite points (keep rows where every coordinate is finite)",
        )
    largest = max(abs(float(points.max())), abs(float(points.min())))  # no (N, 3) temporary
    if largest > MAX_COORDINATE:
        raise where.error(
            f"a coordinate is {largest:.3g}, beyond any position ({MAX_COORDINATE:g})",
            hint="check the file's units and scale",
        )


def _check_units(points: np.ndarray, kind: PointKind, where: Where) -> None:
    """Refuse millimetres: a frame by its median range, a cloud by its second principal
    extent (both on a strided sample)."""
    n = len(points)
    if kind == "frame":
        # A units check: the median of a strided sample decides it as well as all points do.
        sample = points[:: max(1, n // _MEDIAN_SAMPLE_POINTS)]
        median_range = float(np.sqrt(np.median(np.einsum("ij,ij->i", sample, sample))))
        if median_range > FRAME_MM_MEDIAN_RANGE_M:
            raise where.error(
                f"the median distance of the points from the sensor is {median_range:.4g}, "
                f"more than {FRAME_MM_MEDIAN_RANGE_M:g} m",
                hint=MM_HINT,
            )
    else:
        extent = width_across_m(points)
        if extent > CLOUD_MM_DIAMETER_M:
            raise where.error(
                f"the cloud is {extent:.4g} across its second principal axis (≈ the pipe "
                f"diameter), more than {CLOUD_MM_DIAMETER_M:g} m",
                hint=MM_HINT,
            )


def width_across_m(points: np.ndarray) -> float:
    """The extent of ``points`` (N, 3), metres, along their second principal axis, between
    the 0.5th and 99.5th percentiles: about the pipe's inside diameter for a frame of a
    forward-looking sensor (whose first axis runs along the pipe), a ring profile or a piece
    of a registered cloud. 0 for fewer than 3 points."""
    # A strided sample is plenty for a covariance and keeps this cheap on 10^8-point clouds.
    sample = points[:: max(1, len(points) // _CHECK_SAMPLE_POINTS)]
    if len(sample) < 3:
        return 0.0
    centred = sample - sample.mean(axis=0)
    _, vectors = np.linalg.eigh(centred.T @ centred)  # eigenvalues ascending
    along = centred @ vectors[:, 1]
    low, high = np.percentile(along, [0.5, 99.5])
    return float(high - low)
