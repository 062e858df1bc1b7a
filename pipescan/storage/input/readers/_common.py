"""What every point reader shares: where a file sits (for errors), bounded reads of headers
and ASCII lines, and the checks of a declared count against the bytes present."""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipescan.core.errors import PointFileError
from pipescan.storage.input.limits import InputLimits, point_limit_error

CORRUPT_HINT = "the file is corrupt or truncated: copy or export it again"
HEADER_SCAN_BYTES = 65536
"""Headers (PLY, PCD) must end within this many bytes."""
AXES = ("x", "y", "z")
_SCAN_BLOCK_BYTES = 4 << 20
_NEWLINE = 10


@dataclass(frozen=True)
class Where:
    """Where a point file sits and the limits it is read under, to build errors that name it."""

    archive: str | None
    member: str
    limits: InputLimits

    def error(
        self, reason: str, *, field: str = "points", hint: str | None = None
    ) -> PointFileError:
        return PointFileError(
            reason, archive=self.archive, file=self.member, field=field, hint=hint
        )

    def corrupt(self, reason: str, *, field: str = "points") -> PointFileError:
        return self.error(reason, field=field, hint=CORRUPT_HINT)

    def over(self, cap: str, what: str, *, field: str = "points") -> PointFileError:
        return point_limit_error(
            cap, self.limits, what, archive=self.archive, file=self.member, field=field
        )

    def check_count(self, declared: int) -> None:
        """Refuse a declared point count that is negative or over ``points_max_count``."""
        if declared < 0:
            raise self.corrupt(f"the header declares {declared} points")
        if declared > self.limits.points_max_count:
            raise self.over("points_max_count", f"the header declares {declared:,} points")


def joined(parts: list[np.ndarray], empty_shape: tuple[int, ...]) -> np.ndarray:
    """Chunks read one after the other as one array: the chunk itself when there is one (no
    copy), an empty array of ``empty_shape`` when there is none."""
    if not parts:
        return np.empty(empty_shape)
    return parts[0] if len(parts) == 1 else np.concatenate(parts)


def file_size(path: Path, where: Where) -> int:
    try:
        return path.stat().st_size
    except OSError as exc:
        raise where.corrupt(f"cannot read the file: {exc}") from exc


def read_head(path: Path, where: Where, size: int = HEADER_SCAN_BYTES) -> bytes:
    """The first ``size`` bytes of the file (fewer if it is shorter)."""
    try:
        with path.open("rb") as fh:
            return fh.read(size)
    except OSError as exc:
        raise where.corrupt(f"cannot read the file: {exc}") from exc


def require_bytes(where: Where, declared: int, needed: int, size: int) -> None:
    """Refuse a file that holds fewer than the ``needed`` bytes its ``declared`` points take."""
    if size < needed:
        raise where.corrupt(
            f"the header declares {declared:,} points, which need {needed:,} bytes, but the "
            f"file holds {size:,} bytes: it is truncated or the header lies"
        )


def count_lines(
    path: Path,
    offset: int,
    where: Where,
    *,
    comment: bytes | None = None,
    stop_after: int | None = None,
) -> int:
    """Count the non-empty lines from byte ``offset`` on, streaming in fixed blocks, and refuse
    a line longer than ``line_max_bytes`` as soon as it is seen (nothing is held but one block).

    Lines starting with ``comment`` are not counted. Counting stops once ``stop_after`` lines
    were seen, when given.
    """
    cap = where.limits.line_max_bytes
    rows = 0
    carry = b""  # the unfinished line at the end of the previous block
    try:
        with path.open("rb") as fh:
            fh.seek(offset)
            while True:
                block = fh.read(_SCAN_BLOCK_BYTES)
                data = carry + block
                if not data:
                    break
                raw = np.frombuffer(data, dtype=np.uint8)
                ends = np.flatnonzero(raw == _NEWLINE)
                if not block:  # end of file: the last line needs no newline
                    ends = np.append(ends, len(data))
                starts = np.concatenate(([0], ends[:-1] + 1)) if len(ends) else ends
                lengths = ends - starts
                if len(lengths) and lengths.max() > cap:
                    raise _too_long(where, int(lengths.max()))
                tail = len(data) - (int(ends[-1]) + 1 if len(ends) else 0)
                if block and tail > cap:
                    raise _too_long(where, tail)
                # A line counts when it holds more than a CR, and does not start a comment.
                full = lengths - (raw[np.maximum(ends - 1, 0)] == 13) * (lengths > 0)
                keep = full > 0
                if comment is not None and len(starts):
                    keep &= raw[np.minimum(starts, len(raw) - 1)] != comment[0]
                rows += int(keep.sum())
                if not block:
                    break
                carry = data[int(ends[-1]) + 1 :] if len(ends) else data
                if stop_after is not None and rows >= stop_after:
                    return rows
    except OSError as exc:
        raise where.corrupt(f"cannot read the file: {exc}") from exc
    return rows


def _too_long(where: Where, length: int) -> PointFileError:
    return where.over(
        "line_max_bytes", f"a line is {length:,} bytes long or more (no newline?)", field="line"
    )


def text_from(path: Path, offset: int) -> io.TextIOWrapper:
    """The file as UTF-8 text from byte ``offset`` on (for ``np.loadtxt``)."""
    fh = path.open("rb")
    fh.seek(offset)
    return io.TextIOWrapper(fh, encoding="utf-8")


def write_with_open3d(path: Path, pts: np.ndarray, empty_header: str) -> None:
    """Write a PLY or PCD (binary) through Open3D; an empty cloud as ``empty_header`` alone
    (Open3D refuses to write one, and an empty file is still useful for tests)."""
    if len(pts) == 0:
        path.write_text(empty_header, encoding="ascii")
        return
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    if not o3d.io.write_point_cloud(path, cloud, write_ascii=False):
        raise OSError(f"Open3D could not write {path}")
