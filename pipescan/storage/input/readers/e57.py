"""E57 (ASTM E2807), one or several scans, read with pye57 (libE57).

Each scan's Cartesian points are read in chunks of :data:`CHUNK_POINTS`, placed in the file's
common frame by the scan's pose (rotation quaternion and translation), and joined; points
flagged invalid (``cartesianInvalidState`` not 0) are left out. A scan's ``timeStamp`` is
seconds after its ``acquisitionStart``, so a point's time is their sum. libE57 checks every
1 KiB page's checksum as it reads, so a corrupt or truncated file fails with an error that
names the scan; the declared point counts are checked against the limit before anything is
allocated.
"""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from pipescan.storage.input.readers._common import Where, joined
from pipescan.storage.input.readers._e57file import check_layout

SUFFIXES = (".e57",)
CHUNK_POINTS = 1_000_000
"""Points decoded at a time per scan."""
_XYZ = ("cartesianX", "cartesianY", "cartesianZ")


def _errors():
    from pye57 import libe57

    return (libe57.E57Exception, RuntimeError, ValueError, KeyError, IndexError, OSError)


def _short(exc: BaseException) -> str:
    """libE57's first line (its message), without the debug trace it appends."""
    text = str(exc).replace("\\n", "\n")
    return text.split("\n", 1)[0].strip()


@contextmanager
def _opened(path: Path, where: Where) -> Iterator[object]:
    import pye57

    check_layout(path, where)  # before libE57's XML parser sees the file
    try:
        e57 = pye57.E57(str(path))
    except _errors() as exc:
        raise where.corrupt(f"cannot read E57: {_short(exc)}") from exc
    try:
        yield e57
    finally:
        e57.close()


def _scan_name(header, index: int) -> str:
    try:
        name = header["name"].value()
    except Exception:  # a scan without a name: libE57 raises for a missing child
        return f"scan {index}"
    return f"scan {index} ({name!r})"


def _fields(header) -> list[str]:
    return list(header.point_fields)


def _headers(e57, where: Where) -> list:
    headers = []
    total = 0
    for i in range(e57.scan_count):
        try:
            header = e57.get_header(i)
            count = int(header.point_count)
            fields = _fields(header)
        except _errors() as exc:
            raise where.corrupt(f"cannot read E57 scan {i}'s header: {_short(exc)}") from exc
        missing = [f for f in _XYZ if f not in fields]
        if missing:
            raise where.error(
                f"E57 {_scan_name(header, i)} has no Cartesian {', '.join(missing)}",
                field=f"scan {i}",
                hint="export the scans with Cartesian coordinates",
            )
        where.check_count(count)
        total += count
        where.check_count(total)
        headers.append(header)
    return headers


def check(path: Path, where: Where) -> int:
    """Open the file (libE57 checks its header and XML), check every scan's declared count
    against the limit; return the total."""
    with _opened(path, where) as e57:
        return sum(int(h.point_count) for h in _headers(e57, where))


def _iter_scan(
    e57, header, index: int, where: Where, names: tuple[str, ...], chunk_points: int
) -> Iterator[dict[str, np.ndarray]]:
    """One scan's valid points' fields, a chunk of at most ``chunk_points`` read at a time
    (fewer are yielded where points are invalid); the scan's count is checked at its end."""
    from pye57 import libe57

    count = int(header.point_count)
    fields = _fields(header)
    wanted = [n for n in names if n in fields]
    if count == 0:
        return
    if "cartesianInvalidState" in fields:
        wanted.append("cartesianInvalidState")
    chunk = max(1, min(chunk_points, CHUNK_POINTS, count))
    arrays = {
        n: np.empty(chunk, np.int8 if n == "cartesianInvalidState" else np.float64) for n in wanted
    }
    read = 0
    try:
        buffers = libe57.VectorSourceDestBuffer()
        for n in wanted:
            buffers.append(libe57.SourceDestBuffer(e57.image_file, n, arrays[n], chunk, True, True))
        reader = header.points.reader(buffers)
        try:
            while read < count:
                got = reader.read()
                if got == 0:
                    break
                read += got
                part = {n: arrays[n][:got].copy() for n in wanted}
                if "cartesianInvalidState" in part:
                    valid = part.pop("cartesianInvalidState") == 0
                    part = {n: v[valid] for n, v in part.items()}
                yield part
        finally:
            reader.close()
    except _errors() as exc:
        raise where.corrupt(
            f"cannot read E57 {_scan_name(header, index)} after {read:,} of its {count:,} "
            f"points: {_short(exc)}",
            field=f"scan {index}",
        ) from exc
    if read != count:
        raise where.corrupt(
            f"E57 {_scan_name(header, index)} declares {count:,} points but holds {read:,}",
            field=f"scan {index}",
        )


def _pose(header) -> tuple[np.ndarray, np.ndarray]:
    from scipy.spatial.transform import Rotation

    if not header.has_pose():  # the scan is in the common frame already
        return np.eye(3), np.zeros(3)
    w, x, y, z = (float(v) for v in header.rotation)
    translation = np.asarray(header.translation, dtype=np.float64)
    return Rotation.from_quat([x, y, z, w]).as_matrix(), translation


def _timed(headers: list) -> bool:
    """Whether the file gives each point a time: every scan has a ``timeStamp`` field."""
    return bool(headers) and all("timeStamp" in _fields(h) for h in headers)


def _placed(
    e57, headers: list, where: Where, *, xyz: bool, time: bool, chunk_points: int
) -> Iterator[tuple[np.ndarray | None, np.ndarray | None]]:
    """Every scan's valid points a chunk at a time: with ``xyz`` their x, y, z placed in the
    file's common frame by the scan's pose, with ``time`` their time (the scan's
    ``acquisitionStart`` plus the point's ``timeStamp``); None for what is not asked."""
    names = (_XYZ if xyz else ()) + (("timeStamp",) if time else ())
    for i, header in enumerate(headers):
        rotation, translation = _pose(header)
        start = 0.0
        if time and header.node.isDefined("acquisitionStart/dateTimeValue"):
            start = float(header["acquisitionStart"]["dateTimeValue"].value())
        for part in _iter_scan(e57, header, i, where, names, chunk_points):
            pts = None
            if xyz:
                pts = np.column_stack([part[n] for n in _XYZ]) @ rotation.T + translation
            yield pts, part["timeStamp"] + start if time else None


def read(path: Path, where: Where) -> np.ndarray:
    """Every scan's valid points in the file's common frame, ``(N, 3)`` float64, metres."""
    with _opened(path, where) as e57:
        chunks = _placed(
            e57, _headers(e57, where), where, xyz=True, time=False, chunk_points=CHUNK_POINTS
        )
        parts = [pts for pts, _ in chunks if pts is not None]
    return joined(parts, (0, 3))


def read_time(path: Path, where: Where) -> np.ndarray | None:
    """Each valid point's time: its scan's ``acquisitionStart`` plus its ``timeStamp``,
    seconds; None unless every scan has a ``timeStamp`` field."""
    with _opened(path, where) as e57:
        headers = _headers(e57, where)
        if not _timed(headers):
            return None
        chunks = _placed(e57, headers, where, xyz=False, time=True, chunk_points=CHUNK_POINTS)
        parts = [t for _, t in chunks if t is not None]
    return joined(parts, (0,))


def iter_chunks(
    path: Path, where: Where, *, chunk_points: int = CHUNK_POINTS, with_time: bool = False
) -> Iterator[tuple[np.ndarray, np.ndarray | None]]:
    """The valid points of every scan, in the file's common frame, a chunk of at most
    ``chunk_points`` read at a time: the points of :func:`read`, in its order, and with
    ``with_time`` their time as :func:`read_time` gives it (None unless every scan has a
    ``timeStamp``)."""
    with _opened(path, where) as e57:
        headers = _headers(e57, where)
        timed = with_time and _timed(headers)
        for pts, time_s in _placed(
            e57, headers, where, xyz=True, time=timed, chunk_points=chunk_points
        ):
            assert pts is not None
            yield pts, time_s


def write(path: Path, pts: np.ndarray, time_s: np.ndarray | None = None) -> None:
    """One scan of double-precision Cartesian points (and ``timeStamp``, seconds after an
    ``acquisitionStart`` of the first time), through pye57's libE57 bindings."""
    write_scans(path, [(pts, time_s, None)])


def write_scans(
    path: Path,
    scans: list[tuple[np.ndarray, np.ndarray | None, tuple[np.ndarray, np.ndarray] | None]],
) -> None:
    """Write several scans: ``(points (N, 3) in the scan's frame, times (N,) or None, pose)``,
    a pose being ``(quaternion w x y z, translation)`` or None (the common frame)."""
    import pye57
    from pye57 import libe57

    e57 = pye57.E57(str(path), mode="w")
    try:
        imf = e57.image_file
        for index, (pts, time_s, pose) in enumerate(scans):
            pts = np.asarray(pts, dtype=np.float64)
            node = libe57.StructureNode(imf)
            node.set("guid", libe57.StringNode(imf, f"{{{uuid.uuid4()}}}"))
            node.set("name", libe57.StringNode(imf, f"Scan {index}"))
            columns = {n: np.ascontiguousarray(pts[:, j]) for j, n in enumerate(_XYZ)}
            prototype = libe57.StructureNode(imf)
            for n, values in columns.items():
                lo, hi = (float(values.min()), float(values.max())) if len(values) else (0.0, 0.0)
                prototype.set(n, libe57.FloatNode(imf, lo, libe57.E57_DOUBLE, lo, hi))
            if time_s is not None:
                t = np.asarray(time_s, dtype=np.float64)
                start = float(t.min()) if len(t) else 0.0
                columns["timeStamp"] = np.ascontiguousarray(t - start)
                top = float(columns["timeStamp"].max()) if len(t) else 0.0
                prototype.set("timeStamp", libe57.FloatNode(imf, 0.0, libe57.E57_DOUBLE, 0.0, top))
                acquisition = libe57.StructureNode(imf)
                acquisition.set("dateTimeValue", libe57.FloatNode(imf, start))
                acquisition.set("isAtomicClockReferenced", libe57.IntegerNode(imf, 0))
                node.set("acquisitionStart", acquisition)
            if pose is not None:
                quaternion, translation = pose
                pose_node = libe57.StructureNode(imf)
                rotation_node = libe57.StructureNode(imf)
                for key, value in zip("wxyz", quaternion, strict=True):
                    rotation_node.set(key, libe57.FloatNode(imf, float(value)))
                translation_node = libe57.StructureNode(imf)
                for key, value in zip("xyz", translation, strict=True):
                    translation_node.set(key, libe57.FloatNode(imf, float(value)))
                pose_node.set("rotation", rotation_node)
                pose_node.set("translation", translation_node)
                node.set("pose", pose_node)
            codecs = libe57.VectorNode(imf, True)
            points = libe57.CompressedVectorNode(imf, prototype, codecs)
            node.set("points", points)
            e57.data3d.append(node)
            buffers = libe57.VectorSourceDestBuffer()
            for n, values in columns.items():
                buffers.append(libe57.SourceDestBuffer(imf, n, values, len(values), True, True))
            writer = points.writer(buffers)
            if len(pts):
                writer.write(len(pts))
            writer.close()
    finally:
        e57.close()
