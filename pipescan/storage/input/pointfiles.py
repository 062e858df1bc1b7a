"""Read and write point files: LAS/LAZ, PLY, PCD, ``.npy`` and ASCII ``x y z``.

:func:`read_points` is the one entry point for reading. It returns an ``(N, 3)`` float64
array in metres and turns every problem with the file into a :class:`PointFileError` that
names the archive, the member file and the field, with a hint on how to fix it: unknown
suffix, corrupt or truncated file, wrong shape, no points, NaN/inf values, and values that
are almost surely millimetres rather than metres.

Open3D reads PLY and PCD, but it does not raise on a bad file: it returns an empty cloud,
or (for a truncated PLY) a cloud of the declared size filled with whatever was in memory.
So the PLY and PCD headers are parsed here first, and the file size (binary) or the number
of data rows (ASCII) is checked against the point count they declare.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from pipescan.core.errors import PointFileError

POINT_SUFFIXES = (".las", ".laz", ".ply", ".pcd", ".npy", ".xyz", ".txt")
"""Suffixes of the point files pipescan reads (compared case-insensitively)."""

FRAME_MM_MEDIAN_RANGE_M = 50.0
"""A frame (sensor coordinates) whose median point range exceeds this is in millimetres.

Inside a pipe the median return is a pipe radius or two away from the sensor; 50 m would
be a tunnel far larger than any sewer, while 50 mm-units is only 5 cm."""

CLOUD_MM_DIAMETER_M = 20.0
"""A cloud whose second-largest principal extent (≈ the pipe diameter) exceeds this is in
millimetres. A cloud may be georeferenced, so its distance from the origin says nothing."""

LAS_SCALE_M = 1e-4
"""Scale of the LAS/LAZ integer coordinates that :func:`write_points` writes (0.1 mm)."""

MM_HINT = "the values look like millimetres; pipescan expects metres: divide by 1000"

PointKind = Literal["frame", "cloud"]

_HEADER_SCAN_BYTES = 65536
_ASCII_HEADER_LINES = 50
_READ_ERRORS = (ValueError, RuntimeError, OSError, EOFError, IndexError, KeyError, TypeError)
_PLY_TYPE_BYTES = {
    "char": 1, "int8": 1, "uchar": 1, "uint8": 1,
    "short": 2, "int16": 2, "ushort": 2, "uint16": 2,
    "int": 4, "int32": 4, "uint": 4, "uint32": 4,
    "float": 4, "float32": 4, "double": 8, "float64": 8,
}  # fmt: skip
_AXES = ("x", "y", "z")
_CORRUPT_HINT = "the file is corrupt or truncated: copy or export it again"


def point_suffix(name: str | Path) -> str:
    """Return the lower-case suffix of a file name (``"frames/A.LAZ"`` → ``".laz"``)."""
    return Path(name).suffix.lower()


def is_point_file(name: str | Path) -> bool:
    """True when ``name`` has one of the :data:`POINT_SUFFIXES`."""
    return point_suffix(name) in POINT_SUFFIXES


@dataclass(frozen=True)
class _Where:
    """Where a point file sits, to build errors that name it."""

    archive: str | None
    member: str

    def error(
        self, reason: str, *, field: str = "points", hint: str | None = None
    ) -> PointFileError:
        return PointFileError(
            reason, archive=self.archive, file=self.member, field=field, hint=hint
        )


def read_points(
    path: Path,
    *,
    archive: str | None = None,
    member: str | None = None,
    kind: PointKind = "frame",
) -> np.ndarray:
    """Read one point file and check that it holds usable points in metres.

    Parameters
    ----------
    path
        The file on disk. Its suffix picks the reader: ``.las``/``.laz`` (laspy, scaled
        coordinates), ``.ply``/``.pcd`` (Open3D), ``.npy`` (an ``(N, 3)`` float array) or
        ``.xyz``/``.txt`` (ASCII rows ``x y z ...``, space or comma separated; extra columns,
        non-numeric header lines and ``#`` comments are ignored).
    archive, member
        The archive and the member path inside it, used in error messages. ``member``
        defaults to the file name.
    kind
        ``"frame"``: a LiDAR frame in sensor coordinates; ``"cloud"``: a registered cloud in
        a common (possibly georeferenced) frame. Only the millimetre check differs: a frame
        is tested on its median range (> :data:`FRAME_MM_MEDIAN_RANGE_M`), a cloud on its
        second principal extent (> :data:`CLOUD_MM_DIAMETER_M`).

    Returns
    -------
    numpy.ndarray
        Shape ``(N, 3)``, float64, metres, with ``N >= 1`` and every value finite.

    Raises
    ------
    PointFileError
        Unknown suffix, missing, unreadable, corrupt or truncated file, wrong shape or dtype,
        no points, NaN or infinite values, or values in millimetres. The error names
        ``archive``, ``member`` and the field (``"points"`` or the affected axes).

    Examples
    --------
    >>> pts = read_points(Path("frames/000001.laz"), archive="run.zip")  # doctest: +SKIP
    >>> pts.shape, pts.dtype  # doctest: +SKIP
    ((28412, 3), dtype('float64'))
    """
    path = Path(path)
    where = _Where(archive, member if member is not None else path.name)
    suffix = point_suffix(path)
    if suffix not in POINT_SUFFIXES:
        raise where.error(
            f"unsupported point-file suffix {suffix or '(none)'!r}",
            hint=f"use one of {', '.join(POINT_SUFFIXES)}",
        )
    if not path.is_file():
        raise where.error("the point file does not exist", hint="check the path and the archive")
    if suffix in (".las", ".laz"):
        points = _read_las(path, where)
    elif suffix == ".ply":
        points = _read_open3d(path, _check_ply_header(path, where), where)
    elif suffix == ".pcd":
        points = _read_open3d(path, _check_pcd_header(path, where), where)
    elif suffix == ".npy":
        points = _read_npy(path, where)
    else:
        points = _read_ascii(path, where)
    _check_points(points, kind, where)
    return points


def write_points(path: Path, points: np.ndarray) -> None:
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
    path.parent.mkdir(parents=True, exist_ok=True)
    if suffix in (".las", ".laz"):
        _write_las(path, pts)
    elif suffix in (".ply", ".pcd"):
        _write_open3d(path, pts)
    elif suffix == ".npy":
        with path.open("wb") as fh:  # np.save(path) would append a second ".npy"
            np.save(fh, pts, allow_pickle=False)
    else:
        np.savetxt(path, pts, fmt="%.17g")


# --- readers ----------------------------------------------------------------------------------


def _read_las(path: Path, where: _Where) -> np.ndarray:
    import laspy

    try:
        with laspy.open(path, laz_backend=laspy.LazBackend.Lazrs) as reader:
            declared = int(reader.header.point_count)
            las = reader.read()
    except (laspy.errors.LaspyException, *_READ_ERRORS) as exc:
        raise where.error(f"cannot read LAS/LAZ: {exc}", hint=_CORRUPT_HINT) from exc
    if len(las.points) != declared:
        raise where.error(
            f"the LAS header declares {declared} points but the file holds {len(las.points)}",
            hint=_CORRUPT_HINT,
        )
    # las.x/y/z are the scaled coordinates in metres; las.X/Y/Z would be the raw integers.
    return np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)]).astype(
        np.float64, copy=False
    )


def _read_npy(path: Path, where: _Where) -> np.ndarray:
    try:
        arr = np.load(path, allow_pickle=False)
    except _READ_ERRORS as exc:
        raise where.error(f"cannot read .npy: {exc}", hint=_CORRUPT_HINT) from exc
    if not isinstance(arr, np.ndarray):  # an .npz archive renamed to .npy
        raise where.error("not a single .npy array (an .npz archive?)", hint=_CORRUPT_HINT)
    if arr.dtype.names is not None or not np.issubdtype(arr.dtype, np.floating):
        raise where.error(
            f"the array has dtype {arr.dtype}; expected a float array of x, y, z in metres",
            hint="save np.asarray(points, dtype=np.float64) with shape (N, 3)",
        )
    if arr.size == 0:
        return np.empty((0, 3))
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise where.error(
            f"the array has shape {arr.shape}; expected (N, 3) columns x, y, z",
            hint="save an (N, 3) array of x, y, z in metres",
        )
    return arr.astype(np.float64, copy=False)


def _read_ascii(path: Path, where: _Where) -> np.ndarray:
    # Find the first data row: header lines (e.g. "x y z intensity") come before it. A row is
    # data when its first token is a number; short rows then fail loudly in loadtxt.
    first_data_line = None
    delimiter = None
    lineno = -1
    try:
        with path.open("r", encoding="utf-8") as fh:
            for lineno, line in enumerate(fh):
                if lineno >= _ASCII_HEADER_LINES:
                    break
                text = line.strip()
                if not text or text.startswith(("#", "//")):
                    continue
                delimiter = "," if "," in text else None
                first = text.split(delimiter)[0].strip()
                try:
                    float(first)
                except ValueError:
                    continue
                first_data_line = lineno
                break
    except (UnicodeDecodeError, OSError) as exc:
        raise where.error(f"cannot read ASCII points: {exc}", hint=_CORRUPT_HINT) from exc
    if first_data_line is None:
        if lineno < _ASCII_HEADER_LINES:  # read to the end: only headers/comments, no rows
            return np.empty((0, 3))
        raise where.error(
            f"no numeric x y z row in the first {_ASCII_HEADER_LINES} lines",
            hint="each data row must start with x y z in metres, separated by spaces or commas",
        )
    try:
        pts = np.loadtxt(
            path,
            delimiter=delimiter,
            skiprows=first_data_line,
            usecols=(0, 1, 2),
            comments=("#", "//"),
            dtype=np.float64,
            ndmin=2,
            encoding="utf-8",
        )
    except (*_READ_ERRORS, UnicodeDecodeError) as exc:
        raise where.error(
            f"cannot read x y z rows (after {first_data_line} header lines): {exc}",
            hint="each data row must start with x y z in metres, separated by spaces or commas",
        ) from exc
    return pts


def _read_open3d(path: Path, declared: int, where: _Where) -> np.ndarray:
    if declared == 0:
        return np.empty((0, 3))
    import open3d as o3d

    # Open3D reports failures as warnings on stdout and returns an empty (PCD) or garbage
    # (PLY) cloud; the header checks before this call catch the truncated cases, and the
    # count check below catches the rest. Silence the warnings: we raise instead.
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        cloud = o3d.io.read_point_cloud(
            path,
            format=path.suffix.lower().lstrip("."),
            remove_nan_points=False,
            remove_infinite_points=False,
        )
    points = np.array(cloud.points, dtype=np.float64)  # a copy: the Open3D cloud dies here
    if len(points) != declared:
        raise where.error(
            f"the header declares {declared} points but Open3D read {len(points)}",
            hint=_CORRUPT_HINT,
        )
    return points


def _read_head(path: Path, where: _Where) -> bytes:
    try:
        with path.open("rb") as fh:
            return fh.read(_HEADER_SCAN_BYTES)
    except OSError as exc:
        raise where.error(f"cannot read the file: {exc}", hint=_CORRUPT_HINT) from exc


def _count_data_rows(path: Path, offset: int, *, skip_comments: bool = False) -> int:
    rows = 0
    with path.open("rb") as fh:
        fh.seek(offset)
        for line in fh:
            text = line.strip()
            if text and not (skip_comments and text.startswith(b"#")):
                rows += 1
    return rows


def _truncated(where: _Where, declared: int, have: str, need: str) -> PointFileError:
    return where.error(
        f"the header declares {declared} points, which need {need}, but the file holds {have}: "
        "it is truncated",
        hint=_CORRUPT_HINT,
    )


def _check_ply_header(path: Path, where: _Where) -> int:
    """Parse a PLY header, check the body is complete, return the declared vertex count."""
    head = _read_head(path, where)
    if not head.startswith(b"ply"):
        raise where.error("not a PLY file: it does not start with 'ply'", hint=_CORRUPT_HINT)
    end = head.find(b"end_header")
    newline = head.find(b"\n", end)
    if end < 0 or newline < 0:
        raise where.error("the PLY header has no end_header line", hint=_CORRUPT_HINT)
    body_offset = newline + 1
    fmt = None
    # Each element: [name, count, bytes per row or None when it has a list property, props]
    elements: list[list] = []
    try:
        for line in head[:end].decode("ascii").splitlines():
            tokens = line.split()
            if not tokens:
                continue
            if tokens[0] == "format":
                fmt = tokens[1]
            elif tokens[0] == "element":
                elements.append([tokens[1], int(tokens[2]), 0, []])
            elif tokens[0] == "property" and elements:
                element = elements[-1]
                element[3].append(tokens[-1])
                if tokens[1] == "list" or element[2] is None:
                    element[2] = None
                else:
                    element[2] += _PLY_TYPE_BYTES[tokens[1]]
    except (UnicodeDecodeError, IndexError, ValueError, KeyError) as exc:
        raise where.error(f"the PLY header is malformed: {exc}", hint=_CORRUPT_HINT) from exc
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise where.error(f"unknown PLY format {fmt!r}", hint=_CORRUPT_HINT)
    vertex = next((e for e in elements if e[0] == "vertex"), None)
    if vertex is None:
        raise where.error("the PLY file has no vertex element", hint=_CORRUPT_HINT)
    for axis in _AXES:
        if axis not in vertex[3]:
            raise where.error(
                f"the PLY vertex element has no {axis!r} property",
                field=axis,
                hint="write x, y, z vertex properties",
            )
    declared = vertex[1]
    if fmt == "ascii":
        needed_rows = sum(e[1] for e in elements)
        rows = _count_data_rows(path, body_offset)
        if rows < needed_rows:
            raise _truncated(where, declared, f"{rows} rows", f"{needed_rows} rows")
    else:
        # Check the fixed-size elements up to the first one with a list property (faces).
        needed = body_offset
        for element in elements:
            if element[2] is None:
                break
            needed += element[1] * element[2]
        size = path.stat().st_size
        if size < needed:
            raise _truncated(where, declared, f"{size} bytes", f"{needed} bytes")
    return declared


def _check_pcd_header(path: Path, where: _Where) -> int:
    """Parse a PCD header, check the body is complete, return the declared point count."""
    head = _read_head(path, where)
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
    if data is None or "FIELDS" not in fields:
        raise where.error(
            "not a PCD file: no FIELDS or DATA line in its header", hint=_CORRUPT_HINT
        )
    for axis in _AXES:
        if axis not in fields["FIELDS"]:
            raise where.error(
                f"the PCD file has no {axis!r} field", field=axis, hint="write x, y, z fields"
            )
    try:
        if "POINTS" in fields:
            declared = int(fields["POINTS"][0])
        else:
            declared = int(fields["WIDTH"][0]) * int(fields["HEIGHT"][0])
        sizes = [int(s) for s in fields.get("SIZE", [])]
        counts = [int(c) for c in fields.get("COUNT", ["1"] * len(sizes))]
    except (KeyError, IndexError, ValueError) as exc:
        raise where.error(f"the PCD header is malformed: {exc}", hint=_CORRUPT_HINT) from exc
    if data == "ascii":
        rows = _count_data_rows(path, offset, skip_comments=True)
        if rows < declared:
            raise _truncated(where, declared, f"{rows} rows", f"{declared} rows")
    elif data == "binary":
        needed = offset + declared * sum(s * c for s, c in zip(sizes, counts, strict=False))
        size = path.stat().st_size
        if size < needed:
            raise _truncated(where, declared, f"{size} bytes", f"{needed} bytes")
    elif data != "binary_compressed":
        raise where.error(f"unknown PCD DATA kind {data!r}", hint=_CORRUPT_HINT)
    # binary_compressed cannot be sized up front; Open3D returns an empty cloud on failure.
    return declared


# --- content checks ---------------------------------------------------------------------------


def _check_points(points: np.ndarray, kind: PointKind, where: _Where) -> None:
    n = len(points)
    if n == 0:
        raise where.error(
            f"the file holds no points (empty {kind})",
            hint="re-export the file, or remove it and its [[frames]] entry from the archive",
        )
    bad = ~np.isfinite(points)
    if bad.any():
        rows = int(bad.any(axis=1).sum())
        per_axis = ", ".join(f"{a}: {int(bad[:, j].sum())}" for j, a in enumerate(_AXES))
        raise where.error(
            f"{rows} of {n} points have NaN or infinite coordinates ({per_axis})",
            field=",".join(a for j, a in enumerate(_AXES) if bad[:, j].any()),
            hint="drop the non-finite points (keep rows where every coordinate is finite)",
        )
    if kind == "frame":
        median_range = float(np.median(np.linalg.norm(points, axis=1)))
        if median_range > FRAME_MM_MEDIAN_RANGE_M:
            raise where.error(
                f"the median distance of the points from the sensor is {median_range:.4g}, "
                f"more than {FRAME_MM_MEDIAN_RANGE_M:g} m",
                hint=MM_HINT,
            )
    else:
        extent = _second_principal_extent(points)
        if extent > CLOUD_MM_DIAMETER_M:
            raise where.error(
                f"the cloud is {extent:.4g} across its second principal axis (≈ the pipe "
                f"diameter), more than {CLOUD_MM_DIAMETER_M:g} m",
                hint=MM_HINT,
            )


def _second_principal_extent(points: np.ndarray) -> float:
    """Extent of ``points`` (N, 3) along their second principal axis, robust to outliers."""
    # A strided sample is plenty for a covariance and keeps this cheap on 10^8-point clouds.
    sample = points[:: max(1, len(points) // 200_000)]
    if len(sample) < 3:
        return 0.0
    centred = sample - sample.mean(axis=0)
    _, vectors = np.linalg.eigh(centred.T @ centred)  # eigenvalues ascending
    along = centred @ vectors[:, 1]
    low, high = np.percentile(along, [0.5, 99.5])
    return float(high - low)


# --- writers ----------------------------------------------------------------------------------


def _write_las(path: Path, pts: np.ndarray) -> None:
    import laspy

    if not np.isfinite(pts).all():
        raise ValueError("LAS/LAZ cannot store NaN or infinite coordinates")
    offsets = pts.min(axis=0) if len(pts) else np.zeros(3)
    if len(pts) and ((pts.max(axis=0) - offsets) / LAS_SCALE_M >= 2**31 - 1).any():
        raise ValueError("the points span more than the 0.1 mm LAS integer grid can hold")
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.full(3, LAS_SCALE_M)
    header.offsets = offsets
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
    las.write(path, laz_backend=laspy.LazBackend.Lazrs)


def _write_open3d(path: Path, pts: np.ndarray) -> None:
    if len(pts) == 0:
        # Open3D refuses to write an empty cloud; an empty file is still useful for tests.
        path.write_text(_EMPTY_HEADERS[point_suffix(path)], encoding="ascii")
        return
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    if not o3d.io.write_point_cloud(path, cloud, write_ascii=False):
        raise OSError(f"Open3D could not write {path}")


_EMPTY_HEADERS = {
    ".ply": "ply\nformat binary_little_endian 1.0\nelement vertex 0\n"
    "property double x\nproperty double y\nproperty double z\nend_header\n",
    ".pcd": "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\n"
    "SIZE 8 8 8\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 0\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
    "POINTS 0\nDATA binary\n",
}
