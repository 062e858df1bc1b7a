"""PCD (ASCII, binary and binary_compressed), read through Open3D after checking the header.

Open3D does not raise on a bad PCD: it returns an empty cloud. So the header is parsed here
and the point count it declares is checked against the bytes present before Open3D runs:
the rows of an ASCII file, the size of a binary one, and for ``binary_compressed`` the sizes
its own header gives (the uncompressed size must be the points' size, and the compressed
bytes must be present and within LZF's greatest expansion).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipescan.storage.input.readers._common import (
    AXES,
    Where,
    count_lines,
    file_size,
    read_head,
    require_bytes,
    write_with_open3d,
)

SUFFIXES = (".pcd",)
LZF_MAX_RATIO = 100
"""LZF expands a block by at most ~88× (back-references of at most 264 bytes in 3)."""
EMPTY_HEADER = (
    "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\n"
    "SIZE 8 8 8\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 0\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
    "POINTS 0\nDATA binary\n"
)


def check(path: Path, where: Where) -> int:
    """Check the header against the bytes present; return the point count."""
    return _check(path, where).declared


@dataclass(frozen=True)
class _Header:
    """A checked header: its point count, its lines by key (``FIELDS``, ``TYPE``...), its
    ``DATA`` kind and where its body starts."""

    declared: int
    fields: dict[str, list[str]]
    data: str
    body_offset: int


def _check(path: Path, where: Where) -> _Header:
    """As :func:`check`, returning the header."""
    head = read_head(path, where)
    fields: dict[str, list[str]] = {}
    offset = 0
    data = None
    for raw in head.split(b"\n"):
        offset += len(raw) + 1
        line = raw.decode("ascii", errors="replace").strip()
        if not line or line.startswith("#"):
            continue
        key, _, rest = line.partition(" ")
        fields[key.upper()] = rest.split()
        if key.upper() == "DATA":
            data = rest.strip().lower()
            break
    if data is None or "FIELDS" not in fields or offset > len(head):
        raise where.corrupt("not a PCD file: no FIELDS or DATA line in its first 64 KiB")
    for axis in AXES:
        if axis not in fields["FIELDS"]:
            raise where.error(
                f"the PCD file has no {axis!r} field", field=axis, hint="write x, y, z fields"
            )
    try:
        width, height = int(fields["WIDTH"][0]), int(fields.get("HEIGHT", ["1"])[0])
        declared = int(fields["POINTS"][0]) if "POINTS" in fields else width * height
        sizes = [int(s) for s in fields.get("SIZE", [])]
        counts = [int(c) for c in fields.get("COUNT", ["1"] * len(sizes))]
    except (KeyError, IndexError, ValueError) as exc:
        raise where.corrupt(f"the PCD header is malformed: {exc}") from exc
    if min([width, height, *sizes, *counts], default=0) < 0 or declared != width * height:
        raise where.corrupt(
            f"the PCD header's POINTS {declared} is not WIDTH × HEIGHT = {width} × {height}"
        )
    if len(sizes) != len(fields["FIELDS"]) or len(counts) != len(sizes):
        raise where.corrupt("the PCD header's FIELDS, SIZE and COUNT differ in length")
    where.check_count(declared)
    point_bytes = sum(s * c for s, c in zip(sizes, counts, strict=True))
    size = file_size(path, where)
    if data == "ascii":
        rows = count_lines(path, offset, where, comment=b"#", stop_after=declared)
        if rows < declared:
            raise where.corrupt(
                f"the header declares {declared:,} points, but the file holds {rows:,} rows: "
                "it is truncated or the header lies"
            )
    elif data == "binary":
        require_bytes(where, declared, offset + declared * point_bytes, size)
    elif data == "binary_compressed":
        sizes_raw = head[offset : offset + 8]
        if len(sizes_raw) < 8:
            raise where.corrupt("the compressed PCD body has no size fields")
        compressed, uncompressed = struct.unpack("<II", sizes_raw)
        if uncompressed != declared * point_bytes:
            raise where.corrupt(
                f"the header declares {declared:,} points of {point_bytes} bytes, but the "
                f"compressed body unpacks to {uncompressed:,} bytes"
            )
        require_bytes(where, declared, offset + 8 + compressed, size)
        if uncompressed > max(compressed, 1) * LZF_MAX_RATIO:
            raise where.corrupt(
                f"{compressed:,} compressed bytes cannot unpack to {uncompressed:,} bytes"
            )
    else:
        raise where.corrupt(f"unknown PCD DATA kind {data!r}")
    return _Header(declared, fields, data, offset)


def read(path: Path, where: Where) -> np.ndarray:
    """The points, ``(N, 3)`` float64, metres."""
    declared = check(path, where)
    if declared == 0:
        return np.empty((0, 3))
    import open3d as o3d

    # Open3D reports failures as warnings and returns an empty cloud: silence them, and
    # compare what it read with the (checked) declared count instead.
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        cloud = o3d.io.read_point_cloud(
            path, format="pcd", remove_nan_points=False, remove_infinite_points=False
        )
    points = np.array(cloud.points, dtype=np.float64)  # a copy: the Open3D cloud dies here
    if len(points) != declared:
        raise where.corrupt(
            f"the header declares {declared:,} points but Open3D read {len(points):,}"
        )
    return points


_NUMBERS = {("F", "4"), ("F", "8")} | {(k, n) for k in "IU" for n in ("1", "2", "4", "8")}
"""The (TYPE, SIZE) pairs a time field may have: the PCD format's numbers."""
TIME_NAMES = ("time", "timestamp", "gps_time", "t")
"""Fields read as each point's capture time (seconds), the first one present."""


def read_time(path: Path, where: Where) -> np.ndarray | None:
    """Each point's capture time, ``(N,)`` float64 seconds, from its first field named in
    :data:`TIME_NAMES` (read through Open3D's tensor API, which keeps extra fields); None
    when it has none."""
    declared = check(path, where)
    import open3d as o3d

    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        cloud = o3d.t.io.read_point_cloud(str(path))
    found = next((n for n in TIME_NAMES if n in cloud.point), None)
    if found is None:
        return None
    time_s = cloud.point[found].numpy().astype(np.float64).reshape(-1)
    if len(time_s) != declared:
        raise where.corrupt(
            f"the header declares {declared:,} points but {len(time_s):,} times were read",
            field=found,
        )
    return time_s


def read_timed(path: Path, where: Where) -> tuple[np.ndarray, np.ndarray | None, str | None]:
    """The points of :func:`read` and each point's raw time, decoded once: ``(N, 3)`` float64
    metres, the first field named in :data:`TIME_NAMES` as the file holds it (``(N,)``, its
    own dtype and unit) and that field's name; ``None, None`` without such a field, the points
    then read by :func:`read` itself."""
    header = _check(path, where)
    declared, fields = header.declared, header.fields
    names = fields["FIELDS"]
    found = next((n for n in TIME_NAMES if n in names), None)
    if found is None or declared == 0:
        return read(path, where), None, None
    k = names.index(found)
    types = fields.get("TYPE", [])
    counts = fields.get("COUNT", ["1"] * len(names))
    kind, size, count = (types[k : k + 1] or ["?"])[0].upper(), fields["SIZE"][k], counts[k]
    if (kind, size) not in _NUMBERS or count != "1":
        raise where.error(
            f"the time field is of TYPE {kind}, SIZE {size} and COUNT {count}, not one number "
            "per point (F 4 or 8, I or U 1, 2, 4 or 8)",
            field=found,
            hint="write one numeric time per point, or no time field",
        )
    # A binary body of numbers is read with numpy (0.6 ms for 45,200 points against Open3D's
    # tensor reader's 27 ms: benchmarks/bench_point_times.py); other bodies by Open3D.
    if (
        header.data == "binary"
        and len(types) == len(names)
        and all((t.upper(), z) in _NUMBERS for t, z in zip(types, fields["SIZE"], strict=True))
        and all(counts[names.index(a)] == "1" for a in AXES)
    ):
        return (*_binary_fields(path, where, header, found), found)
    import open3d as o3d

    # The tensor API keeps every field in its own dtype: one decode gives points and times.
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        cloud = o3d.t.io.read_point_cloud(str(path))
    if "positions" not in cloud.point or found not in cloud.point:
        raise where.corrupt(f"Open3D read no points or no {found!r} from the file", field=found)
    points = cloud.point["positions"].numpy().astype(np.float64).reshape(-1, 3)
    time = cloud.point[found].numpy().reshape(-1).copy()
    if len(points) != declared or len(time) != declared:
        raise where.corrupt(
            f"the header declares {declared:,} points but Open3D read {len(points):,} points "
            f"and {len(time):,} times",
            field=found,
        )
    return points, time, found


def _binary_fields(
    path: Path, where: Where, header: _Header, found: str
) -> tuple[np.ndarray, np.ndarray]:
    """x, y, z ``(N, 3)`` float64 and the field ``found`` ``(N,)`` of a binary PCD whose
    fields are all numbers, read with numpy: :func:`check` has matched the bytes present
    against ``declared`` rows of the fields' sizes, so nothing more is allocated."""
    declared, fields = header.declared, header.fields
    names = fields["FIELDS"]
    counts = [int(c) for c in fields.get("COUNT", ["1"] * len(names))]
    row = np.dtype(
        [
            (f"f{k}", f"<{'f' if t.upper() == 'F' else t.lower()}{z}", (c,) if c != 1 else ())
            for k, (t, z, c) in enumerate(zip(fields["TYPE"], fields["SIZE"], counts, strict=True))
        ]
    )
    with path.open("rb") as fh:
        fh.seek(header.body_offset)
        rows = np.fromfile(fh, dtype=row, count=declared)
    if len(rows) != declared:
        raise where.corrupt(
            f"the header declares {declared:,} points, the file holds {len(rows):,}"
        )
    points = np.column_stack([rows[f"f{names.index(a)}"].astype(np.float64) for a in AXES])
    return points, rows[f"f{names.index(found)}"].copy()


def write(path: Path, pts: np.ndarray, time_s: np.ndarray | None = None) -> None:
    """Binary PCD through Open3D (which stores x, y, z as float32); with ``time_s``, a
    float64 ``time`` field too (and x, y, z as float64)."""
    if time_s is None or len(pts) == 0:
        write_with_open3d(path, pts, EMPTY_HEADER)
        return
    import open3d as o3d

    cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(np.ascontiguousarray(pts)))
    cloud.point["time"] = o3d.core.Tensor(np.asarray(time_s, dtype=np.float64).reshape(-1, 1))
    if not o3d.t.io.write_point_cloud(str(path), cloud, write_ascii=False):
        raise OSError(f"Open3D could not write {path}")
