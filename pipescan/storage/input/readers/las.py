"""LAS and LAZ (laspy, lazrs): scaled coordinates in metres.

The header's point count is checked before anything is allocated: for LAS against the bytes
after the point-data offset; LAZ cannot be sized from its header, so it is read in chunks of
:data:`CHUNK_POINTS` and a file that ends early fails at the chunk where it ends.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from pipescan.storage.input.readers._common import (
    Where,
    file_size,
    joined,
    read_head,
    require_bytes,
)

SUFFIXES = (".las", ".laz")
LAS_SCALE_M = 1e-4
"""Scale of the LAS/LAZ integer coordinates that :func:`write` writes (0.1 mm)."""
CHUNK_POINTS = 1_000_000
"""Points decoded at a time: bounds what a lying header can make pipescan allocate."""


def _errors():
    import laspy

    # laspy parses headers with struct and int.from_bytes as they come: a crafted header
    # surfaces as any of these.
    return (
        laspy.errors.LaspyException,
        ValueError,
        RuntimeError,
        OSError,
        EOFError,
        KeyError,
        IndexError,
        TypeError,
        OverflowError,
        ZeroDivisionError,
        struct.error,
    )


def _laz_backend():
    """lazrs in parallel mode: a LAZ file's chunks (50,000 points each, as written by common
    tools) are decompressed on all cores; a small frame is one chunk, decoded as before."""
    import laspy

    parallel = laspy.LazBackend.LazrsParallel
    return parallel if parallel.is_available() else laspy.LazBackend.Lazrs


_VLR_HEADER_BYTES = 54
_EVLR_HEADER_BYTES = 60


def _check_layout(path: Path, where: Where) -> None:
    """Check the header's record counts against the file before laspy sees it.

    laspy reads as many variable-length records as the header declares, from wherever the
    file ends: 2 billion of them from a 675-byte file, without end. The records sit between
    the header and the point data (VLRs) and after the points (LAS 1.4 EVLRs), so their
    counts are bounded by the bytes there.
    """
    head = read_head(path, where, 375)
    size = file_size(path, where)
    if not head.startswith(b"LASF"):
        raise where.corrupt("cannot read LAS/LAZ: the file does not start with 'LASF'")
    if len(head) < 227:
        raise where.corrupt(f"cannot read LAS/LAZ: the header is cut short ({len(head)} bytes)")
    (header_bytes,) = struct.unpack_from("<H", head, 94)
    offset, vlrs = struct.unpack_from("<II", head, 96)
    if not header_bytes <= offset <= size:
        raise where.corrupt(
            f"the LAS header puts the points at byte {offset:,}, outside the file's "
            f"{size:,} bytes (after its {header_bytes}-byte header)"
        )
    if vlrs * _VLR_HEADER_BYTES > offset - header_bytes:
        raise where.corrupt(
            f"the LAS header declares {vlrs:,} variable-length records, more than the "
            f"{offset - header_bytes:,} bytes before the points can hold"
        )
    if head[24:26] >= b"\x01\x04" and header_bytes >= 375 and len(head) >= 251:
        start, evlrs = struct.unpack_from("<QI", head, 235)
        if evlrs and (start > size or evlrs * _EVLR_HEADER_BYTES > size - start):
            raise where.corrupt(
                f"the LAS header declares {evlrs:,} extended records from byte {start:,}, "
                f"more than the file's {size:,} bytes hold"
            )


def _declared(reader, path: Path, where: Where) -> int:
    """The header's point count, checked against the cap and (LAS) the bytes present."""
    header = reader.header
    declared = int(header.point_count)
    where.check_count(declared)
    if not header.are_points_compressed:
        record = int(header.point_format.size)
        needed = int(header.offset_to_point_data) + declared * record
        require_bytes(where, declared, needed, file_size(path, where))
    return declared


def _scale_into(out: np.ndarray, chunk, scales: np.ndarray, offsets: np.ndarray) -> None:
    """Write a chunk's coordinates in metres into ``out`` (len(chunk), 3): each raw integer
    times the header's scale plus its offset, as laspy's ``chunk.x`` computes them (the same
    two operations, so the same values to the bit), without its temporaries."""
    for j, raw in enumerate((chunk.X, chunk.Y, chunk.Z)):
        column = out[:, j]
        np.multiply(raw, scales[j], out=column)
        column += offsets[j]


def _chunks(
    path: Path,
    where: Where,
    *,
    chunk_points: int = CHUNK_POINTS,
    time: bool = False,
    field: str = "points",
):
    """The file's decoded chunks, at most ``chunk_points`` points each, as ``(header, chunk)``:
    the layout and the declared count are checked before the first, the count against what
    the file held after the last (a LAZ cannot be sized from its header, so one that ends
    early fails at the chunk where it ends). A decoding error names ``field``."""
    import laspy

    _check_layout(path, where)
    # In a LAS 1.4 point format 6-10 LAZ, each field is compressed on its own: decode only
    # x, y, z, and GPS time when asked (older formats decode whole records, whatever is asked).
    selection = laspy.DecompressionSelection.xy_returns_channel() | laspy.DecompressionSelection.Z
    if time:
        selection |= laspy.DecompressionSelection.GPS_TIME
    n = declared = 0
    try:
        backend = _laz_backend()
        with laspy.open(path, laz_backend=backend, decompression_selection=selection) as reader:
            declared = _declared(reader, path, where)
            for chunk in reader.chunk_iterator(max(1, min(chunk_points, CHUNK_POINTS))):
                if len(chunk) == 0:
                    break
                n += len(chunk)
                if n > declared:
                    break
                yield reader.header, chunk
    except _errors() as exc:
        what = "GPS time" if field == "gps_time" else field
        raise where.corrupt(f"cannot read LAS/LAZ {what}: {exc}", field=field) from exc
    if n != declared:
        raise where.corrupt(f"the LAS header declares {declared:,} points but the file holds {n:,}")


def _scales_offsets(header) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(header.scales, dtype=np.float64), np.asarray(header.offsets, np.float64)


def _read(path: Path, where: Where, *, keep: bool) -> tuple[int, np.ndarray | None]:
    out: np.ndarray | None = None
    parts: list[np.ndarray] = []
    n = 0
    for header, chunk in _chunks(path, where):
        scales, offsets = _scales_offsets(header)
        if keep and out is None and not parts and not header.are_points_compressed:
            # A LAS was sized by _declared, so its count can be trusted; a LAZ is collected
            # chunk by chunk and so never allocates more than it decoded.
            out = np.empty((int(header.point_count), 3))
        if out is not None:
            _scale_into(out[n : n + len(chunk)], chunk, scales, offsets)
        elif keep:
            part = np.empty((len(chunk), 3))
            _scale_into(part, chunk, scales, offsets)
            parts.append(part)
        n += len(chunk)
    if not keep:
        return n, None
    return n, out if out is not None else joined(parts, (0, 3))


def iter_chunks(
    path: Path, where: Where, *, chunk_points: int = CHUNK_POINTS, with_time: bool = False
) -> Iterator[tuple[np.ndarray, np.ndarray | None]]:
    """The points in chunks of at most ``chunk_points``: ``(K, 3)`` float64 metres each, the
    same values as :func:`read`, with each point's GPS time (K,) when ``with_time`` and the
    point format has it (else None). A registered cloud of any size streams through this
    with one chunk in memory; a file that ends early fails at the chunk where it ends."""
    for header, chunk in _chunks(path, where, chunk_points=chunk_points, time=with_time):
        scales, offsets = _scales_offsets(header)
        points = np.empty((len(chunk), 3))
        _scale_into(points, chunk, scales, offsets)
        timed = with_time and "gps_time" in header.point_format.dimension_names
        yield points, np.asarray(chunk.gps_time, dtype=np.float64) if timed else None


def check(path: Path, where: Where) -> int:
    """Check the header and that every declared point is present; return the count."""
    return _read(path, where, keep=False)[0]


def read(path: Path, where: Where) -> np.ndarray:
    """The points, ``(N, 3)`` float64, metres."""
    points = _read(path, where, keep=True)[1]
    assert points is not None
    return points


def read_timed(path: Path, where: Where) -> tuple[np.ndarray, np.ndarray | None]:
    """The points, ``(N, 3)`` float64 metres, as :func:`read` returns them, and each point's
    GPS time ``(N,)`` float64 seconds (None when the point format has none), decoded in one
    pass."""
    points, times = [], []
    for header, chunk in _chunks(path, where, time=True, field="points"):
        part = np.empty((len(chunk), 3))
        _scale_into(part, chunk, *_scales_offsets(header))
        points.append(part)
        if "gps_time" in header.point_format.dimension_names:
            times.append(np.asarray(chunk.gps_time, dtype=np.float64))
    pts = joined(points, (0, 3))
    return pts, joined(times, (0,)) if len(times) == len(points) and times else None


def read_time(path: Path, where: Where) -> np.ndarray | None:
    """Each point's GPS time, ``(N,)`` float64 seconds, or None when the point format has
    none."""
    parts = []
    for header, chunk in _chunks(path, where, time=True, field="gps_time"):
        if "gps_time" not in header.point_format.dimension_names:
            return None
        parts.append(np.asarray(chunk.gps_time, dtype=np.float64))
    return joined(parts, (0,))


def write_chunks(
    path: Path,
    chunks: Iterable[tuple[np.ndarray, np.ndarray | None]],
    *,
    offsets: np.ndarray,
    timed: bool,
) -> int:
    """Write ``(points (K, 3), time_s (K,) or None)`` chunks as one LAS 1.4 file, point format
    6, scale :data:`LAS_SCALE_M`, the given ``offsets`` (``.laz`` compressed with lazrs); with
    ``timed``, each chunk's time is its GPS time. The points decode as :func:`write` writes
    them with the same offsets (the same rounding to the grid); one chunk is in memory at a
    time. Returns the number of points written.

    Raises
    ------
    ValueError
        A coordinate that is not finite, or beyond what the 0.1 mm grid holds from ``offsets``.
    """
    import laspy

    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.full(3, LAS_SCALE_M)
    header.offsets = np.asarray(offsets, dtype=np.float64)
    limit = (2**31 - 1) * LAS_SCALE_M
    written = 0
    compress = Path(path).suffix.lower() == ".laz"
    with laspy.open(path, mode="w", header=header, do_compress=compress,
                    laz_backend=laspy.LazBackend.Lazrs) as writer:  # fmt: skip
        for pts, time_s in chunks:
            if not np.isfinite(pts).all():
                raise ValueError("LAS/LAZ cannot store NaN or infinite coordinates")
            if len(pts) and (np.abs(pts - header.offsets).max(axis=0) >= limit).any():
                raise ValueError("the points span more than the 0.1 mm LAS integer grid can hold")
            record = laspy.ScaleAwarePointRecord.zeros(len(pts), header=header)
            record.x, record.y, record.z = pts[:, 0], pts[:, 1], pts[:, 2]
            if timed:
                record.gps_time = np.asarray(time_s, dtype=np.float64)
            writer.write_points(record)
            written += len(pts)
    return written


def write(path: Path, pts: np.ndarray, time_s: np.ndarray | None = None) -> None:
    """LAS 1.4, point format 6, scale :data:`LAS_SCALE_M`, offset at the points' minimum;
    ``.laz`` compressed with lazrs. ``time_s`` (N,), when given, is stored as GPS time (see
    :func:`write_chunks`)."""
    if not np.isfinite(pts).all():
        raise ValueError("LAS/LAZ cannot store NaN or infinite coordinates")
    offsets = pts.min(axis=0) if len(pts) else np.zeros(3)
    write_chunks(path, [(pts, time_s)], offsets=offsets, timed=time_s is not None)
