"""ASCII ``x y z`` rows (``.xyz``, ``.txt``), space or comma separated.

Extra columns, non-numeric header lines before the first row and ``#``/``//`` comments are
ignored. The whole file is first scanned in fixed blocks: a line longer than
``line_max_bytes`` (a file with no newlines) is refused before any of it is parsed.
"""

from __future__ import annotations

import itertools
import re
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from pipescan.storage.input.readers._common import Where, count_lines, joined, text_from

SUFFIXES = (".xyz", ".txt")
HEADER_LINES = 50
"""The first data row must come within this many lines."""
_ROW_HINT = "each data row must start with x y z in metres, separated by spaces or commas"
_NUMPY_ROW = re.compile(r",? at row \d+(, column \d+| with \d+ columns)?\.?")
_ERRORS = (ValueError, RuntimeError, OSError, EOFError, IndexError, TypeError, UnicodeError)


def _layout(path: Path, where: Where) -> tuple[int | None, str | None, int]:
    """The first data row's line number (None: no rows), its delimiter and the line count."""
    lines = count_lines(path, 0, where)  # refuses over-long lines before anything is parsed
    if lines > where.limits.points_max_count + HEADER_LINES:
        raise where.over("points_max_count", f"the file has {lines:,} lines")
    lineno = -1
    try:
        with path.open("r", encoding="utf-8") as fh:
            for lineno, line in enumerate(fh):
                if lineno >= HEADER_LINES:
                    break
                text = line.strip()
                if not text or text.startswith(("#", "//")):
                    continue
                delimiter = "," if "," in text else None
                try:
                    float(text.split(delimiter)[0].strip())
                except ValueError:
                    continue
                return lineno, delimiter, lines
    except (UnicodeDecodeError, OSError) as exc:
        raise where.corrupt(f"cannot read ASCII points: {exc}") from exc
    if lineno < HEADER_LINES:  # read to the end: only headers and comments, no rows
        return None, None, lines
    raise where.error(f"no numeric x y z row in the first {HEADER_LINES} lines", hint=_ROW_HINT)


def check(path: Path, where: Where) -> int:
    """Check line lengths and find the rows; return an upper bound of the point count."""
    first, _, lines = _layout(path, where)
    return 0 if first is None else lines - first


def read(path: Path, where: Where) -> np.ndarray:
    """The points, ``(N, 3)`` float64, metres."""
    parts = [rows for rows, _ in iter_chunks(path, where)]
    return joined(parts, (0, 3))


def iter_chunks(
    path: Path, where: Where, *, chunk_points: int = 1_000_000, with_time: bool = False
) -> Iterator[tuple[np.ndarray, None]]:
    """The rows of :func:`read`, parsed ``chunk_points`` lines at a time (fewer rows where
    lines are comments or blank); an ASCII file holds no time."""
    first, delimiter, _ = _layout(path, where)
    if first is None:
        return
    step = max(1, chunk_points)
    line = first
    with text_from(path, 0) as fh:
        lines = itertools.islice(fh, first, None)
        while True:
            try:
                block = list(itertools.islice(lines, step))
            except (UnicodeError, OSError) as exc:
                raise where.corrupt(f"cannot read ASCII points after line {line:,}: {exc}") from exc
            if not block:
                break
            try:
                with warnings.catch_warnings():  # a block of comments alone holds no data
                    warnings.simplefilter("ignore", UserWarning)
                    rows = np.loadtxt(block, delimiter=delimiter, usecols=(0, 1, 2),
                                      comments=("#", "//"), dtype=np.float64, ndmin=2)  # fmt: skip
            except _ERRORS as exc:
                bad = line + 1 + _first_bad_row(block, delimiter)
                reason = _NUMPY_ROW.sub("", str(exc))  # numpy counts rows within the block
                raise where.error(
                    f"cannot read x y z rows at line {bad:,}: {reason}", hint=_ROW_HINT
                ) from exc
            line += len(block)
            if len(rows):
                yield rows, None


def _first_bad_row(block: list[str], delimiter: str | None) -> int:
    """The index in ``block`` of the first line that is not a comment, blank or x y z row."""
    for k, text in enumerate(block):
        text = text.strip()
        if not text or text.startswith(("#", "//")):
            continue
        try:
            fields = text.split(delimiter)
            [float(f) for f in fields[:3]]
            if len(fields) < 3:
                return k
        except ValueError:
            return k
    return 0


def write(path: Path, pts: np.ndarray) -> None:
    """Rows ``x y z`` with 17 significant digits (lossless)."""
    np.savetxt(path, pts, fmt="%.17g")
