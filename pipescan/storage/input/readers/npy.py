"""``.npy``: an ``(N, 3)`` float array, read without pickle.

The header's shape is checked against the bytes after it before the array is read, so a
128-byte file cannot declare a terabyte.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from pipescan.core.npyheader import read_npy_header
from pipescan.storage.input.readers._common import Where, file_size, joined, require_bytes

SUFFIXES = (".npy",)
_FORMAT_ERRORS = (ValueError, OSError, EOFError, TypeError, SyntaxError, KeyError)


def _header(path: Path, where: Where) -> tuple[tuple[int, ...], bool, np.dtype, int]:
    """Shape, Fortran order, dtype and the offset of the data."""
    try:
        with path.open("rb") as fh:
            shape, fortran, dtype = read_npy_header(fh)
            offset = fh.tell()
    except _FORMAT_ERRORS as exc:
        raise where.corrupt(f"cannot read .npy: {exc}") from exc
    if dtype.hasobject or dtype.names is not None or not np.issubdtype(dtype, np.floating):
        raise where.error(
            f"the array has dtype {dtype}; expected a float array of x, y, z in metres",
            hint="save np.asarray(points, dtype=np.float64) with shape (N, 3)",
        )
    count = math.prod(shape)
    if count and (len(shape) != 2 or shape[1] != 3):
        raise where.error(
            f"the array has shape {shape}; expected (N, 3) columns x, y, z",
            hint="save an (N, 3) array of x, y, z in metres",
        )
    where.check_count(count // 3)
    require_bytes(where, count // 3, offset + count * dtype.itemsize, file_size(path, where))
    return shape, fortran, dtype, offset


def check(path: Path, where: Where) -> int:
    """Check the header against the bytes present; return the point count."""
    return math.prod(_header(path, where)[0]) // 3


def read(path: Path, where: Where) -> np.ndarray:
    """The points, ``(N, 3)`` float64, metres."""
    parts = [pts for pts, _ in iter_chunks(path, where, chunk_points=_WHOLE)]
    return joined(parts, (0, 3))


_WHOLE = 2**62
"""A chunk larger than any file: read in one piece."""


def iter_chunks(
    path: Path, where: Where, *, chunk_points: int = 1_000_000, with_time: bool = False
) -> Iterator[tuple[np.ndarray, None]]:
    """The points of :func:`read`, ``chunk_points`` rows at a time (a ``.npy`` holds no time).
    A C-ordered array is read a chunk at a time; a Fortran-ordered one (columns stored one
    after the other) is mapped and its rows copied out a chunk at a time."""
    shape, fortran, dtype, offset = _header(path, where)
    rows = math.prod(shape) // 3
    step = max(1, chunk_points)
    try:
        if fortran:
            mapped = np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=(rows, 3),
                               order="F")  # fmt: skip
            for a in range(0, rows, step):
                yield np.array(mapped[a : a + step], dtype=np.float64), None
            return
        with path.open("rb") as fh:
            fh.seek(offset)
            for a in range(0, rows, step):
                n = min(step, rows - a)
                flat = np.fromfile(fh, dtype=dtype, count=3 * n)
                if flat.size != 3 * n:
                    raise where.corrupt(f"the header declares {rows:,} points; fewer are present")
                yield flat.reshape(n, 3).astype(np.float64, copy=False), None
    except _FORMAT_ERRORS as exc:
        raise where.corrupt(f"cannot read .npy: {exc}") from exc


def write(path: Path, pts: np.ndarray) -> None:
    """A float64 ``.npy`` (never pickled)."""
    with path.open("wb") as fh:  # np.save(path) would append a second ".npy"
        np.save(fh, pts, allow_pickle=False)
