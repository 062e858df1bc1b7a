"""PLY (ASCII and binary, either byte order), read with numpy.

Open3D does not raise on a bad PLY: given a header that declares more vertices than the file
holds, it returns a cloud of the declared size filled with whatever was in memory. So PLY is
read here: the header is parsed, every element's declared count is checked against the bytes
present (a list element counts at least its length fields) before anything is allocated, and
the vertices are read in chunks of at most :data:`CHUNK_ROWS` (``iter_chunks`` hands them out
one at a time).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipescan.storage.input.readers._common import (
    AXES,
    Where,
    count_lines,
    file_size,
    joined,
    read_head,
    require_bytes,
    text_from,
    write_with_open3d,
)

SUFFIXES = (".ply",)
CHUNK_ROWS = 1_000_000
_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
_FORMATS = {"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"}
EMPTY_HEADER = (
    "ply\nformat binary_little_endian 1.0\nelement vertex 0\n"
    "property double x\nproperty double y\nproperty double z\nend_header\n"
)


@dataclass
class _Element:
    name: str
    count: int
    # (name, numpy type code) for a scalar; (name, (count code, item code)) for a list.
    props: list[tuple[str, str | tuple[str, str]]] = field(default_factory=list)

    @property
    def has_list(self) -> bool:
        return any(not isinstance(t, str) for _, t in self.props)

    def min_row_bytes(self) -> int:
        """Bytes of a row, its lists empty (exact when it has no list)."""
        return sum(np.dtype(t if isinstance(t, str) else t[0]).itemsize for _, t in self.props)


@dataclass
class _Header:
    fmt: str
    body_offset: int
    elements: list[_Element]
    vertex: _Element


def _parse_header(path: Path, where: Where) -> _Header:
    head = read_head(path, where)
    if not head.startswith(b"ply"):
        raise where.corrupt("not a PLY file: it does not start with 'ply'")
    end = head.find(b"end_header")
    newline = head.find(b"\n", end)
    if end < 0 or newline < 0:
        raise where.corrupt("the PLY header has no end_header line in its first 64 KiB")
    fmt = None
    elements: list[_Element] = []
    try:
        for line in head[:end].decode("ascii").splitlines()[1:]:
            tokens = line.split()
            if not tokens or tokens[0] in ("comment", "obj_info"):
                continue
            if tokens[0] == "format":
                fmt = tokens[1]
            elif tokens[0] == "element":
                count = int(tokens[2])
                if count < 0:
                    raise ValueError(f"element {tokens[1]} has a negative count {count}")
                elements.append(_Element(tokens[1], count))
            elif tokens[0] == "property" and elements:
                if tokens[1] == "list":
                    elements[-1].props.append((tokens[4], (_TYPES[tokens[2]], _TYPES[tokens[3]])))
                else:
                    elements[-1].props.append((tokens[2], _TYPES[tokens[1]]))
            else:
                raise ValueError(f"unexpected header line {line!r}")
    except (UnicodeDecodeError, IndexError, ValueError, KeyError) as exc:
        raise where.corrupt(f"the PLY header is malformed: {exc}") from exc
    if fmt not in _FORMATS:
        raise where.corrupt(f"unknown PLY format {fmt!r}")
    vertex = next((e for e in elements if e.name == "vertex"), None)
    if vertex is None:
        raise where.corrupt("the PLY file has no vertex element")
    names = [name for name, _ in vertex.props]
    for axis in AXES:
        if axis not in names:
            raise where.error(
                f"the PLY vertex element has no {axis!r} property",
                field=axis,
                hint="write x, y, z vertex properties",
            )
    if vertex.has_list:
        raise where.error(
            "the PLY vertex element has a list property; pipescan reads vertices of "
            "fixed-size properties",
            hint="export the vertices with scalar properties only",
        )
    where.check_count(vertex.count)
    return _Header(fmt, newline + 1, elements, vertex)


def _row_dtype(element: _Element, order: str) -> np.dtype:
    return np.dtype([(f"p{i}", order + str(t)) for i, (_, t) in enumerate(element.props)])


def _skip_list_rows(fh, element: _Element, order: str, where: Where, size: int) -> None:
    """Walk the rows of an element with list properties (one before the vertices)."""
    for _ in range(element.count):
        for _, t in element.props:
            if isinstance(t, str):
                fh.seek(np.dtype(t).itemsize, 1)
                continue
            count_t, item_t = np.dtype(order + t[0]), np.dtype(t[1])
            raw = fh.read(count_t.itemsize)
            if len(raw) < count_t.itemsize:
                raise where.corrupt(f"the PLY element {element.name!r} ends early")
            n = int(np.frombuffer(raw, dtype=count_t)[0])
            if n < 0 or fh.tell() + n * item_t.itemsize > size:
                raise where.corrupt(f"the PLY element {element.name!r} ends early")
            fh.seek(n * item_t.itemsize, 1)


def _vertex_offset(path: Path, header: _Header, where: Where, size: int) -> int:
    """The byte offset of the first vertex (binary), walking any list element before it."""
    order = _FORMATS[header.fmt]
    offset = header.body_offset
    with path.open("rb") as fh:
        for element in header.elements:
            if element is header.vertex:
                return offset
            if element.has_list:
                fh.seek(offset)
                _skip_list_rows(fh, element, order, where, size)
                offset = fh.tell()
            else:
                offset += element.count * element.min_row_bytes()
    raise AssertionError("the vertex element is among the elements")


def _check(path: Path, where: Where) -> tuple[_Header, int]:
    """Parse and size-check; return the header and (binary) the vertices' byte offset."""
    header = _parse_header(path, where)
    size = file_size(path, where)
    declared = header.vertex.count
    if header.fmt == "ascii":
        rows = sum(e.count for e in header.elements)
        have = count_lines(path, header.body_offset, where, stop_after=rows)
        if have < rows:
            raise where.corrupt(
                f"the header declares {declared:,} points in {rows:,} rows, but the file holds "
                f"{have:,} rows: it is truncated or the header lies"
            )
        return header, -1
    # Every element takes at least its rows with empty lists: a lower bound on the file's size
    # that needs no walking; then the exact offset of the vertices, and their bytes.
    least = header.body_offset + sum(e.count * e.min_row_bytes() for e in header.elements)
    require_bytes(where, declared, least, size)
    offset = _vertex_offset(path, header, where, size)
    require_bytes(where, declared, offset + declared * header.vertex.min_row_bytes(), size)
    return header, offset


def check(path: Path, where: Where) -> int:
    """Check the header against the bytes present; return the vertex count."""
    return _check(path, where)[0].vertex.count


TIME_NAMES = ("time", "timestamp", "gps_time", "t")
"""Vertex properties read as each point's capture time (seconds), the first one present."""


def read(path: Path, where: Where) -> np.ndarray:
    """The vertices' x, y, z, ``(N, 3)`` float64, metres."""
    return _read_properties(path, where, AXES)


def read_time(path: Path, where: Where) -> np.ndarray | None:
    """Each vertex's capture time, ``(N,)`` float64 seconds, from its first property named in
    :data:`TIME_NAMES`; None when it has none."""
    found = _time_name(path, where)
    if found is None:
        return None
    return _read_properties(path, where, (found,))[:, 0]


def read_timed(path: Path, where: Where) -> tuple[np.ndarray, np.ndarray | None, str | None]:
    """The vertices of :func:`read` and each one's raw time, read in one pass: ``(N, 3)``
    float64 metres, the first property named in :data:`TIME_NAMES` in the file's own unit
    (``(N,)`` float64: exact, a PLY property being at most a 32-bit integer or a double) and
    its name; ``None, None`` without such a property."""
    found = _time_name(path, where)
    if found is None:
        return read(path, where), None, None
    rows = _read_properties(path, where, (*AXES, found))
    return np.ascontiguousarray(rows[:, :3]), rows[:, 3].copy(), found


def _time_name(path: Path, where: Where) -> str | None:
    """The vertex property read as each point's time: the first of :data:`TIME_NAMES` the
    file has, or None."""
    names = [name for name, _ in _parse_header(path, where).vertex.props]
    return next((n for n in TIME_NAMES if n in names), None)


def _read_properties(path: Path, where: Where, wanted: tuple[str, ...]) -> np.ndarray:
    """Named vertex properties, ``(N, len(wanted))`` float64."""
    return joined(list(_properties(path, where, wanted, CHUNK_ROWS)), (0, len(wanted)))


def _properties(
    path: Path, where: Where, wanted: tuple[str, ...], chunk_points: int
) -> Iterator[np.ndarray]:
    """Named vertex properties, ``(K, len(wanted))`` float64, at most ``chunk_points`` rows at
    a time: a binary PLY is read a chunk at a time; an ASCII one is read whole, then handed
    out in chunks."""
    header, offset = _check(path, where)
    vertex = header.vertex
    names = [name for name, _ in vertex.props]
    cols = [names.index(a) for a in wanted]
    step = max(1, min(chunk_points, CHUNK_ROWS))
    if vertex.count == 0:
        return
    if header.fmt == "ascii":
        before = 0
        for element in header.elements:
            if element is vertex:
                break
            before += element.count
        try:
            with text_from(path, header.body_offset) as fh:
                pts = np.loadtxt(fh, skiprows=before, max_rows=vertex.count, usecols=cols, ndmin=2)
        except (ValueError, UnicodeError, OSError) as exc:
            raise where.corrupt(f"cannot read the PLY vertex rows: {exc}") from exc
        if len(pts) != vertex.count:
            raise where.corrupt(
                f"the header declares {vertex.count:,} points but the file holds {len(pts):,}"
            )
        pts = pts.reshape(-1, len(wanted)).astype(np.float64, copy=False)
        for a in range(0, len(pts), step):
            yield pts[a : a + step]
        return
    dtype = _row_dtype(vertex, _FORMATS[header.fmt])
    n = 0
    with path.open("rb") as fh:
        fh.seek(offset)
        while n < vertex.count:
            rows = np.fromfile(fh, dtype=dtype, count=min(step, vertex.count - n))
            if len(rows) == 0:
                raise where.corrupt("the PLY vertices end early")
            out = np.empty((len(rows), len(wanted)))
            for j, c in enumerate(cols):
                out[:, j] = rows[f"p{c}"]
            yield out
            n += len(rows)


def iter_chunks(
    path: Path, where: Where, *, chunk_points: int = CHUNK_ROWS, with_time: bool = False
) -> Iterator[tuple[np.ndarray, np.ndarray | None]]:
    """The vertices' x, y, z of :func:`read` (and, with ``with_time``, the time of
    :func:`read_time`), at most ``chunk_points`` at a time (see :func:`_properties`)."""
    found = _time_name(path, where) if with_time else None
    for rows in _properties(path, where, AXES + ((found,) if found else ()), chunk_points):
        if found:
            yield np.ascontiguousarray(rows[:, :3]), rows[:, 3].copy()
        else:
            yield rows, None


def write(path: Path, pts: np.ndarray, time_s: np.ndarray | None = None) -> None:
    """Binary little-endian PLY of float64 vertices (through Open3D), or, with ``time_s``,
    with a float64 ``time`` property too."""
    if time_s is None:
        write_with_open3d(path, pts, EMPTY_HEADER)
        return
    rows = np.empty(len(pts), dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("time", "<f8")])
    rows["x"], rows["y"], rows["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    rows["time"] = time_s
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(pts)}\nproperty double x\nproperty double y\n"
        "property double z\nproperty double time\nend_header\n"
    )
    with path.open("wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(rows.tobytes())
