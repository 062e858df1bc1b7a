# ruff: noqa: E501  (the corpus reads best as one case per line)
"""A corpus of crafted, hostile scan archives, one per way an input can try to hurt pipescan.

Each :class:`Case` builds its input in a folder and says how pipescan must refuse it: the
error class and a fragment of the message (the cap, the field). ``tests/test_hostile_inputs.py``
runs them all; ``benchmarks/bench_hostile.py`` measures each one's peak memory, on this code
and on an older checkout. ``scale`` shrinks the few inputs that are large by nature (the
bombs), so the test suite stays fast; the benchmark builds them full size.
"""

from __future__ import annotations

import gzip
import hashlib
import io
import os
import struct
import tarfile
import warnings
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipescan.core.errors import ArchiveError, FetchError, MetadataError, PointFileError
from pipescan.storage.input.pointfiles import write_points

TOML = b'asset_id = "MH1-MH2"\ninspected_at = 2024-05-17\nnominal_diameter_m = 0.5\n'
MIB = 1 << 20


def frame(n: int = 400, seed: int = 0) -> np.ndarray:
    """(n, 3) points on a 0.5 m pipe wall, sensor coordinates, metres."""
    rng = np.random.default_rng(seed)
    angle = rng.uniform(0.0, 2.0 * np.pi, n)
    return np.column_stack([rng.uniform(0.5, 3.0, n), 0.25 * np.cos(angle), 0.25 * np.sin(angle)])


@dataclass(frozen=True)
class Case:
    """One crafted input: what it is, how it is built, and how pipescan must refuse it."""

    cls: str  # the class: expansion, lying header, unsafe name, link, text, remote
    name: str
    build: Callable[[Path, float], str]  # (folder, scale) -> what is given to pipescan
    error: type[Exception]
    match: str
    limits: dict = field(default_factory=dict)  # InputLimits overrides (caps set low)


# --- builders ---------------------------------------------------------------------------------


def _dir_archive(where: Path, frames: dict[str, bytes] | None = None, toml: bytes = TOML) -> Path:
    root = where / "scan"
    (root / "frames").mkdir(parents=True, exist_ok=True)
    (root / "inspection.toml").write_bytes(toml)
    for name, data in (frames or {}).items():
        (root / "frames" / name).write_bytes(data)
    return root


def _npy_bytes(points: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, points)
    return buf.getvalue()


def _point_file(where: Path, suffix: str, points: np.ndarray | None = None) -> bytes:
    path = where / f"legit{suffix}"
    write_points(path, frame() if points is None else points)
    return path.read_bytes()


def _zip(where: Path, name: str, members: list[tuple[str, bytes]], stored: bool = False) -> str:
    path = where / name
    method = zipfile.ZIP_STORED if stored else zipfile.ZIP_DEFLATED
    with zipfile.ZipFile(path, "w", method) as zf, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a duplicate name is the point of one case
        for member, data in members:
            zf.writestr(member, data)
    return str(path)


def _tar(where: Path, name: str, members: list[tuple[tarfile.TarInfo, bytes]], mode="w") -> str:
    path = where / name
    with tarfile.open(path, mode) as tf:
        for info, data in members:
            info.size = len(data) if info.isfile() else 0
            tf.addfile(info, io.BytesIO(data) if info.isfile() else None)
    return str(path)


def _file(name: str) -> tarfile.TarInfo:
    return tarfile.TarInfo(name)


def zip_bomb(where: Path, scale: float) -> str:
    """A zip whose one frame inflates ~1000:1 (2 GiB from 2 MB at full scale)."""
    size = max(8 * MIB, int(2048 * MIB * scale))
    path = where / "bomb.zip"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("inspection.toml", TOML)
        with zf.open("frames/000000.xyz", "w", force_zip64=True) as fh:
            block = b"0" * MIB
            for _ in range(size // MIB):
                fh.write(block)
    return str(path)


def targz_bomb(where: Path, scale: float) -> str:
    """A tar.gz whose member inflates ~1000:1: the tar's own sizes are honest, the ratio is not."""
    size = max(8 * MIB, int(1024 * MIB * scale))
    path = where / "bomb.tar.gz"
    info = _file("frames/000000.xyz")
    info.size = size
    with gzip.open(path, "wb", compresslevel=9) as gz:
        gz.write(_file_header(_file("inspection.toml"), TOML))
        gz.write(info.tobuf(format=tarfile.PAX_FORMAT))
        block = b"0" * MIB
        for _ in range(size // MIB):
            gz.write(block)
        gz.write(b"\0" * 1024)
    return str(path)


def _file_header(info: tarfile.TarInfo, data: bytes) -> bytes:
    info.size = len(data)
    pad = (-len(data)) % tarfile.BLOCKSIZE
    return info.tobuf(format=tarfile.PAX_FORMAT) + data + b"\0" * pad


def tar_longname_bomb(where: Path, scale: float) -> str:
    """A tar.gz whose GNU long-name header declares 1 GiB (tarfile reads it in one go)."""
    path = where / "longname.tar.gz"
    header = _file("././@LongLink")
    header.type = tarfile.GNUTYPE_LONGNAME
    header.size = 1 << 30
    with gzip.open(path, "wb", compresslevel=1) as gz:
        gz.write(header.tobuf(format=tarfile.GNU_FORMAT))
        gz.write(b"a" * max(MIB, int(64 * MIB * scale)))
    return str(path)


def tar_pax_bomb(where: Path, scale: float) -> str:
    """A tar.gz whose pax extended header declares 512 MiB of records."""
    path = where / "pax.tar.gz"
    header = _file("./PaxHeaders/x")
    header.type = tarfile.XHDTYPE
    header.size = 512 * MIB
    with gzip.open(path, "wb", compresslevel=1) as gz:
        gz.write(header.tobuf(format=tarfile.USTAR_FORMAT))
        gz.write(b"9 a=b\n" * max(1000, int(1_000_000 * scale)))
    return str(path)


def zip_many(where: Path, scale: float) -> str:
    names = [("inspection.toml", TOML)]
    names += [(f"frames/{i:06d}.xyz", b"") for i in range(max(50_001, int(100_000 * scale)))]
    return _zip(where, "many.zip", names, stored=True)


def tar_many(where: Path, scale: float) -> str:
    path = where / "many.tar"
    with tarfile.open(path, "w") as tf:
        tf.addfile(_sized(_file("inspection.toml"), TOML), io.BytesIO(TOML))
        for i in range(max(50_001, int(100_000 * scale))):
            tf.addfile(_file(f"frames/{i:06d}.xyz"), io.BytesIO(b""))
    return str(path)


def _sized(info: tarfile.TarInfo, data: bytes) -> tarfile.TarInfo:
    info.size = len(data)
    return info


def sparse_tar(where: Path, scale: float) -> str:
    info = _file("frames/000000.xyz")
    info.type = tarfile.GNUTYPE_SPARSE
    path = where / "sparse.tar"
    with tarfile.open(path, "w", format=tarfile.GNU_FORMAT) as tf:
        tf.addfile(_sized(_file("inspection.toml"), TOML), io.BytesIO(TOML))
        tf.addfile(info, io.BytesIO(b""))
    return str(path)


def ascii_no_newline(where: Path, scale: float) -> str:
    """An ASCII frame of one endless line (a directory archive: nothing to decompress)."""
    size = max(4 * MIB, int(512 * MIB * scale))
    root = _dir_archive(where)
    with (root / "frames" / "000000.xyz").open("wb") as fh:
        block = b"1" * MIB
        for _ in range(size // MIB):
            fh.write(block)
    return str(root)


def ascii_long_line_in_tar(where: Path, scale: float) -> str:
    data = b"1 2 3\n" + b"4" * (2 * MIB) + b"\n"
    return _tar(
        where, "longline.tar", [(_file("inspection.toml"), TOML), (_file("frames/1.xyz"), data)]
    )


def ply_header_long_line(where: Path, scale: float) -> str:
    body = b"ply\nformat ascii 1.0\ncomment " + b"x" * (1 * MIB) + b"\n"
    return str(_dir_archive(where, {"1.ply": body}))


def big_toml(where: Path, scale: float) -> str:
    toml = TOML + b"# " + b"x" * (40 * MIB) + b"\n"
    return str(_dir_archive(where, {"1.npy": _npy_bytes(frame())}, toml=toml))


def legit_zip(where: Path, scale: float) -> str:
    """A genuine archive, refused only because a cap was set below it."""
    members = [("inspection.toml", TOML)]
    members += [(f"frames/{i}.npy", _npy_bytes(frame(20_000, seed=i))) for i in range(4)]
    return _zip(where, "legit.zip", members)


def legit_dir(where: Path, scale: float) -> str:
    return str(_dir_archive(where, {"1.npy": _npy_bytes(frame(20_000))}))


def ply_binary(header: str, body: bytes) -> bytes:
    return header.encode("ascii") + body


_XYZ_DOUBLE = "property double x\nproperty double y\nproperty double z\n"


def in_dir(name: str, data: Callable[[Path], bytes]) -> Callable[[Path, float], str]:
    def build(where: Path, scale: float) -> str:
        return str(_dir_archive(where, {name: data(where)}))

    return build


def ply_list_then_vertices(where: Path) -> bytes:
    header = (
        "ply\nformat binary_little_endian 1.0\nelement face 0\n"
        "property list uchar int vertex_indices\nelement vertex 100000000\n"
        + _XYZ_DOUBLE
        + "end_header\n"
    )
    return ply_binary(header, np.zeros(6, "<f8").tobytes())


def ply_1000_of_2(where: Path) -> bytes:
    header = (
        "ply\nformat binary_little_endian 1.0\nelement vertex 1000\n" + _XYZ_DOUBLE + "end_header\n"
    )
    return ply_binary(header, frame(2).astype("<f8").tobytes())


def ply_list_before_truncated(where: Path) -> bytes:
    header = (
        "ply\nformat binary_little_endian 1.0\nelement face 3\n"
        "property list uchar int vertex_indices\nelement vertex 2\n" + _XYZ_DOUBLE + "end_header\n"
    )
    # The first face claims 200 indices; the file ends long before.
    return ply_binary(header, bytes([200]) + b"\0" * 60)


def ply_ascii_lies(where: Path) -> bytes:
    header = "ply\nformat ascii 1.0\nelement vertex 1000000000\n" + _XYZ_DOUBLE + "end_header\n"
    return (header + "1 0 0\n0 1 0\n0 0 1\n").encode()


def ply_negative(where: Path) -> bytes:
    header = (
        "ply\nformat binary_little_endian 1.0\nelement vertex -5\n" + _XYZ_DOUBLE + "end_header\n"
    )
    return header.encode()


def ply_huge_count(where: Path) -> bytes:
    header = (
        f"ply\nformat binary_big_endian 1.0\nelement vertex {2**63}\n"
        + _XYZ_DOUBLE
        + "end_header\n"
    )
    return header.encode() + b"\0" * 48


def ply_big_endian_short(where: Path) -> bytes:
    header = "ply\nformat binary_big_endian 1.0\nelement vertex 50\n" + _XYZ_DOUBLE + "end_header\n"
    return header.encode() + frame(49).astype(">f8").tobytes()


def _pcd_header(points: int, data: str, width: int | None = None) -> bytes:
    return (
        "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
        f"WIDTH {points if width is None else width}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
        f"POINTS {points}\nDATA {data}\n"
    ).encode()


def pcd_binary_lies(where: Path) -> bytes:
    return _pcd_header(100_000_000, "binary") + frame(10).astype("<f4").tobytes()


def pcd_ascii_lies(where: Path) -> bytes:
    return _pcd_header(1_000_000_000, "ascii") + b"1 0 0\n0 1 0\n"


def pcd_compressed_lies(where: Path) -> bytes:
    body = struct.pack("<II", 40, 12 * 100_000_000) + b"\0" * 40
    return _pcd_header(100_000_000, "binary_compressed") + body


def pcd_width_mismatch(where: Path) -> bytes:
    return _pcd_header(10, "binary", width=10_000_000) + frame(10).astype("<f4").tobytes()


def _las_patched(where: Path, suffix: str, count: int) -> bytes:
    data = bytearray(_point_file(where, suffix, frame(10)))
    struct.pack_into("<Q", data, 247, count)  # LAS 1.4: the 64-bit point count
    return bytes(data)


def las_vlr_count_lies(where: Path) -> bytes:
    """2 billion variable-length records declared: laspy would read them from EOF forever."""
    data = bytearray(_point_file(where, ".las", frame(10)))
    struct.pack_into("<I", data, 100, 2_000_000_000)
    return bytes(data)


def las_evlr_count_lies(where: Path) -> bytes:
    data = bytearray(_point_file(where, ".laz", frame(10)))
    struct.pack_into("<QI", data, 235, len(data) - 10, 4_000_000_000)
    return bytes(data)


def las_offset_past_end(where: Path) -> bytes:
    data = bytearray(_point_file(where, ".las", frame(10)))
    struct.pack_into("<I", data, 96, 10_000_000)  # offset to point data
    return bytes(data)


def _npy_header(shape: tuple[int, ...], descr: str = "<f8") -> bytes:
    header = f"{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}"
    header += " " * (-(len(header) + 11) % 64) + "\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header.encode("latin1")


def npy_lies(shape: tuple[int, ...]) -> Callable[[Path], bytes]:
    return lambda where: _npy_header(shape) + b"\0" * 48


def npy_pickle(where: Path) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.array([{"x": 1}], dtype=object), allow_pickle=True)
    return buf.getvalue()


def link_frame_outside(where: Path, scale: float) -> str:
    secret = where / "outside.npy"
    secret.write_bytes(_npy_bytes(frame()))
    root = _dir_archive(where)
    (root / "frames" / "000000.npy").symlink_to(secret)
    return str(root)


def link_frames_dir_outside(where: Path, scale: float) -> str:
    elsewhere = where / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "000000.npy").write_bytes(_npy_bytes(frame()))
    root = where / "scan"
    root.mkdir()
    (root / "inspection.toml").write_bytes(TOML)
    (root / "frames").symlink_to(elsewhere, target_is_directory=True)
    return str(root)


def link_toml_outside(where: Path, scale: float) -> str:
    (where / "other.toml").write_bytes(TOML)
    root = where / "scan"
    (root / "frames").mkdir(parents=True)
    (root / "frames" / "1.npy").write_bytes(_npy_bytes(frame()))
    (root / "inspection.toml").symlink_to(where / "other.toml")
    return str(root)


def link_cloud_to_device(where: Path, scale: float) -> str:
    root = where / "scan"
    root.mkdir()
    (root / "inspection.toml").write_bytes(TOML)
    (root / "cloud.xyz").symlink_to("/dev/zero")
    return str(root)


def fifo_frame(where: Path, scale: float) -> str:
    root = _dir_archive(where, {"1.npy": _npy_bytes(frame())})
    os.mkfifo(root / "frames" / "2.npy")
    toml = TOML + b'[[frames]]\nfile = "frames/1.npy"\n[[frames]]\nfile = "frames/2.npy"\n'
    (root / "inspection.toml").write_bytes(toml)
    return str(root)


def dangling_link(where: Path, scale: float) -> str:
    root = _dir_archive(where, {"1.npy": _npy_bytes(frame())})
    (root / "frames" / "2.npy").symlink_to(where / "gone.npy")
    toml = TOML + b'[[frames]]\nfile = "frames/1.npy"\n[[frames]]\nfile = "frames/2.npy"\n'
    (root / "inspection.toml").write_bytes(toml)
    return str(root)


# --- E57: the XML that libE57 parses, rewritten (with each page's CRC-32C) ---------------------

_E57_HEADER = struct.Struct("<8sIIQQQQ")


def _crc32c_table() -> list[int]:
    table = []
    for i in range(256):
        c = i
        for _ in range(8):
            c = (c >> 1) ^ 0x82F63B78 if c & 1 else c >> 1
        table.append(c)
    return table


_CRC32C = _crc32c_table()


def crc32c(data: bytes) -> int:
    c = 0xFFFFFFFF
    table = _CRC32C
    for byte in data:
        c = table[(c ^ byte) & 0xFF] ^ (c >> 8)
    return c ^ 0xFFFFFFFF


def e57_xml(data: bytes) -> str:
    """The XML of an E57 file."""
    logical = b"".join(data[i : i + 1020] for i in range(0, len(data), 1024))
    _, _, _, _, offset, length, _ = _E57_HEADER.unpack(data[:48])
    start = (offset // 1024) * 1020 + offset % 1024
    return logical[start : start + length].decode("utf-8")


def e57_with_xml(data: bytes, xml: str | bytes) -> bytes:
    """An E57 file's bytes with its XML replaced (the binary sections where they were), its
    header and every page's checksum right: what libE57 opens as a sound file."""
    logical = bytearray(b"".join(data[i : i + 1020] for i in range(0, len(data), 1024)))
    sig, major, minor, _, offset, _, page = _E57_HEADER.unpack(bytes(logical[:48]))
    start = (offset // 1024) * 1020 + offset % 1024
    body = xml.encode("utf-8") if isinstance(xml, str) else xml
    logical = logical[:start] + body
    logical += b"\0" * (-len(logical) % 1020)
    pages = len(logical) // 1020
    logical[:48] = _E57_HEADER.pack(sig, major, minor, pages * 1024, offset, len(body), page)
    out = bytearray()
    for i in range(pages):
        chunk = bytes(logical[i * 1020 : (i + 1) * 1020])
        out += chunk + struct.pack(">I", crc32c(chunk))
    return bytes(out)


def _e57_scans(where: Path, scans: int = 2, n: int = 2000) -> bytes:
    from pipescan.storage.input.readers.e57 import write_scans

    path = where / "legit.e57"
    write_scans(path, [(frame(n, seed=i), None, None) for i in range(scans)])
    return path.read_bytes()


def e57_doctype(url: str) -> Callable[[Path], bytes]:
    """An E57 whose XML names an external DTD at ``url`` (libE57's parser fetches it)."""

    def build(where: Path) -> bytes:
        data = _e57_scans(where)
        xml = e57_xml(data).replace("<e57Root", f'<!DOCTYPE e57Root SYSTEM "{url}">\n<e57Root', 1)
        return e57_with_xml(data, xml)

    return build


def e57_entities(where: Path) -> bytes:
    """An E57 whose XML declares nested internal entities (a "billion laughs")."""
    data = _e57_scans(where)
    decl = (
        '<!DOCTYPE e57Root [\n<!ENTITY a "aaaaaaaaaa">\n'
        + "".join(
            f'<!ENTITY {c} "{("&" + p + ";") * 10}">\n'
            for p, c in zip("abcdefgh", "bcdefghi", strict=True)
        )
        + "]>\n"
    )
    xml = e57_xml(data).replace("<e57Root", decl + "<e57Root", 1)
    xml = xml.replace("<![CDATA[Scan 0]]>", "&i;", 1)
    return e57_with_xml(data, xml)


def e57_deep(where: Path, scale: float) -> str:
    """An E57 whose XML nests 200,000 elements (libE57's parser recurses on each; 2,000 at
    the tests' scale, still far past the bound)."""
    depth = max(2000, int(200_000 * scale))
    data = _e57_scans(where, scans=1, n=100)
    nest = '<d type="Structure">' * depth + "</d>" * depth
    xml = e57_xml(data).replace("</e57Root>", nest + "</e57Root>", 1)
    root = _dir_archive(where)
    (root / "cloud.e57").write_bytes(e57_with_xml(data, xml))
    return str(root)


def e57_shared_section(copies: int) -> Callable[[Path], bytes]:
    """An E57 of ``copies`` scans that all point at the first scan's binary section."""

    def build(where: Path) -> bytes:
        data = _e57_scans(where, scans=1, n=2000)
        xml = e57_xml(data)
        begin = xml.index("<vectorChild")
        end = xml.index("</vectorChild>") + len("</vectorChild>")
        scan = xml[begin:end]
        return e57_with_xml(data, xml[:end] + scan * (copies - 1) + xml[end:])

    return build


def e57_count_lies(where: Path) -> bytes:
    """An E57 scan whose recordCount says 100 M records, in a section of 2,000."""
    data = _e57_scans(where, scans=1, n=2000)
    xml = e57_xml(data).replace('recordCount="2000"', 'recordCount="100000000"', 1)
    return e57_with_xml(data, xml)


def in_cloud(name: str, data: Callable[[Path], bytes]) -> Callable[[Path, float], str]:
    """A directory archive whose registered cloud is ``name``, of ``data``'s bytes."""

    def build(where: Path, scale: float) -> str:
        root = _dir_archive(where)
        (root / name).write_bytes(data(where))
        return str(root)

    return build


# --- ROS bags: a PointCloud2 of many points in a few KB, and bags whose sizes lie ------------


def _cloud_msg(
    store,
    ros1: bool,
    points: int,
    *,
    step: int = 4,
    offsets=(0, 0, 0),
    height: int = 1,
    data: bytes | None = None,
):
    """A PointCloud2 of ``height`` rows of ``points`` points of ``step`` bytes, all zeros (or
    ``data``), x y z at ``offsets``."""
    types = store.types
    stamp = types["builtin_interfaces/msg/Time"](sec=1, nanosec=0)
    if ros1:
        header = types["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id="lidar")
    else:
        header = types["std_msgs/msg/Header"](stamp=stamp, frame_id="lidar")
    field = types["sensor_msgs/msg/PointField"]
    fields = [
        field(name=a, offset=o, datatype=7, count=1) for a, o in zip("xyz", offsets, strict=True)
    ]
    body = np.zeros(points * step, np.uint8) if data is None else np.frombuffer(data, np.uint8)
    return types["sensor_msgs/msg/PointCloud2"](
        header=header,
        height=height,
        width=points,
        fields=fields,
        is_bigendian=False,
        point_step=step,
        row_step=step * points,
        data=body,
        is_dense=True,
    )


def _bag_points(scale: float) -> int:
    """50 M points at full scale; at least 2 M (8 MB of zeros), past the 4 MiB ratio floor."""
    return max(2_000_000, int(50_000_000 * scale))


def ros1_bag(where: Path, compression: str | None, msg_kwargs: dict, points: int) -> Path:
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    root = _dir_archive(where)
    (root / "frames").rmdir()
    path = root / "scan.bag"
    writer = Writer(path)
    if compression:
        writer.set_compression(getattr(Writer.CompressionFormat, compression.upper()))
    with writer:
        conn = writer.add_connection(
            "/lidar/points", "sensor_msgs/msg/PointCloud2", typestore=store
        )
        msg = _cloud_msg(store, True, points, **msg_kwargs)
        writer.write(conn, 10**9, store.serialize_ros1(msg, "sensor_msgs/msg/PointCloud2"))
    return root


def ros2_bag(where: Path, plugin: str, mode: str | None, msg_kwargs: dict, points: int) -> Path:
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    root = _dir_archive(where)
    (root / "frames").rmdir()
    path = root / "scan"
    writer = Writer(path, version=9, storage_plugin=getattr(StoragePlugin, plugin.upper()))
    if mode:
        writer.set_compression(getattr(CompressionMode, mode.upper()), CompressionFormat.ZSTD)
    with writer:
        conn = writer.add_connection(
            "/lidar/points", "sensor_msgs/msg/PointCloud2", typestore=store
        )
        msg = _cloud_msg(store, False, points, **msg_kwargs)
        writer.write(conn, 10**9, store.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2"))
    return root


def bag_bz2_bomb(where: Path, scale: float) -> str:
    return str(ros1_bag(where, "bz2", {}, _bag_points(scale)))


def bag_lz4_bomb(where: Path, scale: float) -> str:
    return str(ros1_bag(where, "lz4", {}, _bag_points(scale)))


def mcap_zstd_bomb(where: Path, scale: float) -> str:
    return str(ros2_bag(where, "mcap", "storage", {}, _bag_points(scale)))


def bag_file_compressed_bomb(where: Path, scale: float) -> str:
    """A ROS 2 bag folder with ``compression_mode: file``: one zstd file of a few KB."""
    return str(ros2_bag(where, "sqlite3", "file", {}, _bag_points(scale)))


def db3_generated_zeroblob(where: Path, scale: float) -> str:
    """A ``.db3`` whose ``messages.data`` is ``GENERATED ALWAYS AS (zeroblob(N))``: N bytes
    per row that the file does not hold."""
    import sqlite3

    root = ros2_bag(where, "sqlite3", None, {"offsets": (0, 4, 8), "step": 12}, 10)
    db = next((root / "scan").glob("*.db3"))
    size = max(16 * MIB, int(600 * MIB * scale))
    with sqlite3.connect(db) as conn:
        conn.executescript(
            "ALTER TABLE messages RENAME TO old;"
            "CREATE TABLE messages (id INTEGER PRIMARY KEY, topic_id INTEGER NOT NULL, "
            f"timestamp INTEGER NOT NULL, data BLOB GENERATED ALWAYS AS (zeroblob({size})) VIRTUAL);"
            "INSERT INTO messages (id, topic_id, timestamp) SELECT id, topic_id, timestamp FROM old;"
            "DROP TABLE old;"
        )
    return str(root)


def mcap_record_length(where: Path, scale: float) -> str:
    """An MCAP whose first summary record (after the data section's end) declares 2^40
    bytes."""
    root = ros2_bag(where, "mcap", None, {"offsets": (0, 4, 8), "step": 12}, 10)
    path = next((root / "scan").glob("*.mcap"))
    data = bytearray(path.read_bytes())
    at, op = 8, 0
    while op != 0x0F:  # DataEnd
        op, length = data[at], struct.unpack_from("<Q", data, at + 1)[0]
        at += 9 + length
    struct.pack_into("<Q", data, at + 1, 1 << 40)
    path.write_bytes(bytes(data))
    return str(root)


def bag_cloud(msg_kwargs: dict, points: int) -> Callable[[Path, float], str]:
    """An uncompressed ROS 1 bag of one PointCloud2 built with ``msg_kwargs``."""
    return lambda where, scale: str(ros1_bag(where, None, msg_kwargs, points))


def toml_nested(body: Callable[[], str]) -> Callable[[Path, float], str]:
    """A directory archive whose inspection.toml ends with ``body()`` (nested past the bound)."""

    def build(where: Path, scale: float) -> str:
        toml = TOML + body().encode("ascii")
        return str(_dir_archive(where, {"1.npy": _npy_bytes(frame())}, toml=toml))

    return build


def _toml_with(line: str) -> Callable[[Path, float], str]:
    def build(where: Path, scale: float) -> str:
        toml = TOML.replace(b'asset_id = "MH1-MH2"\n', b"") + line.encode("utf-8") + b"\n"
        return str(_dir_archive(where, {"1.npy": _npy_bytes(frame())}, toml=toml))

    return build


def _ok_members() -> list[tuple[str, bytes]]:
    return [("inspection.toml", TOML), ("frames/1.npy", _npy_bytes(frame()))]


# --- the corpus -------------------------------------------------------------------------------

_LOW = {"member_max_bytes": 256 * 1024}

CASES: tuple[Case, ...] = (
    # 2. what an archive expands to
    Case("expansion", "zip bomb, one member ~1000:1", zip_bomb, ArchiveError, "compression_max_ratio"),
    Case("expansion", "tar.gz bomb ~1000:1", targz_bomb, ArchiveError, "compression_max_ratio"),
    Case("expansion", "tar.gz long-name header of 1 GiB", tar_longname_bomb, ArchiveError, "tar header declares"),
    Case("expansion", "tar.gz pax header of 512 MiB", tar_pax_bomb, ArchiveError, "tar header declares"),
    Case("expansion", "zip of 100,000 members", zip_many, ArchiveError, "archive_max_members"),
    Case("expansion", "tar of 100,000 members", tar_many, ArchiveError, "archive_max_members"),
    Case("expansion", "tar with a sparse member", sparse_tar, ArchiveError, "sparse"),
    Case("expansion", "ASCII frame with no newline (512 MiB)", ascii_no_newline, PointFileError, "line_max_bytes"),
    Case("expansion", "ASCII frame with a 2 MiB line, in a tar", ascii_long_line_in_tar, PointFileError, "line_max_bytes"),
    Case("expansion", "PLY header line of 1 MiB", ply_header_long_line, PointFileError, "end_header"),
    Case("expansion", "inspection.toml of 40 MiB", big_toml, MetadataError, "metadata_max_bytes"),
    Case("expansion", "archive over archive_max_bytes", legit_zip, ArchiveError, "archive_max_bytes", {"archive_max_bytes": 1 * MIB}),
    Case("expansion", "member over member_max_bytes", legit_zip, ArchiveError, "member_max_bytes", _LOW),
    Case("expansion", "points over points_max_count", legit_dir, PointFileError, "points_max_count", {"points_max_count": 10_000}),
    # 3. headers that lie
    Case("lying header", "PLY: 100 M vertices after an empty list element", in_dir("1.ply", ply_list_then_vertices), PointFileError, "truncated or the header lies"),
    Case("lying header", "PLY: 1,000 vertices declared, 2 present", in_dir("1.ply", ply_1000_of_2), PointFileError, "truncated or the header lies"),
    Case("lying header", "PLY: a list element before the vertices ends early", in_dir("1.ply", ply_list_before_truncated), PointFileError, "ends early"),
    Case("lying header", "PLY ASCII: 1e9 vertices declared, 3 rows", in_dir("1.ply", ply_ascii_lies), PointFileError, "points_max_count"),
    Case("lying header", "PLY: negative vertex count", in_dir("1.ply", ply_negative), PointFileError, "negative"),
    Case("lying header", "PLY: 2^63 vertices", in_dir("1.ply", ply_huge_count), PointFileError, "points_max_count"),
    Case("lying header", "PLY big-endian: 50 declared, 49 present", in_dir("1.ply", ply_big_endian_short), PointFileError, "truncated or the header lies"),
    Case("lying header", "PCD binary: 1e8 points declared, 10 present", in_dir("1.pcd", pcd_binary_lies), PointFileError, "truncated or the header lies"),
    Case("lying header", "PCD ASCII: 1e9 points declared", in_dir("1.pcd", pcd_ascii_lies), PointFileError, "points_max_count"),
    Case("lying header", "PCD compressed: sizes that cannot be", in_dir("1.pcd", pcd_compressed_lies), PointFileError, "cannot unpack"),
    Case("lying header", "PCD: WIDTH x HEIGHT is not POINTS", in_dir("1.pcd", pcd_width_mismatch), PointFileError, "WIDTH"),
    Case("lying header", "LAS (675 bytes) claiming 1e8 points", in_dir("1.las", lambda w: _las_patched(w, ".las", 10**8)), PointFileError, "truncated or the header lies"),
    Case("lying header", "LAS claiming 1e12 points", in_dir("1.las", lambda w: _las_patched(w, ".las", 10**12)), PointFileError, "points_max_count"),
    Case("lying header", "LAZ claiming 1e8 points", in_dir("1.laz", lambda w: _las_patched(w, ".laz", 10**8)), PointFileError, "cannot read LAS/LAZ"),
    Case("lying header", "LAZ claiming 1e12 points", in_dir("1.laz", lambda w: _las_patched(w, ".laz", 10**12)), PointFileError, "points_max_count"),
    Case("lying header", "LAS point data offset past the end", in_dir("1.las", las_offset_past_end), PointFileError, "outside the file"),
    Case("lying header", "LAS declaring 2e9 variable-length records", in_dir("1.las", las_vlr_count_lies), PointFileError, "variable-length records"),
    Case("lying header", "LAZ declaring 4e9 extended records", in_dir("1.laz", las_evlr_count_lies), PointFileError, "extended records"),
    Case("lying header", ".npy of shape (1e8, 3) in 176 bytes", in_dir("1.npy", npy_lies((10**8, 3))), PointFileError, "truncated or the header lies"),
    Case("lying header", ".npy of shape (1e12, 3)", in_dir("1.npy", npy_lies((10**12, 3))), PointFileError, "points_max_count"),
    Case("lying header", ".npy holding a pickle", in_dir("1.npy", npy_pickle), PointFileError, "dtype object"),
    # 5. links and special files in directory archives
    Case("link", "frame symlinked to a file outside", link_frame_outside, ArchiveError, "outside the archive"),
    Case("link", "frames/ symlinked to a folder outside", link_frames_dir_outside, ArchiveError, "outside the archive"),
    Case("link", "inspection.toml symlinked outside", link_toml_outside, ArchiveError, "outside the archive"),
    Case("link", "cloud symlinked to /dev/zero", link_cloud_to_device, ArchiveError, "outside the archive"),
    Case("link", "a frame that is a FIFO", fifo_frame, ArchiveError, "not a regular file"),
    Case("link", "a dangling symlink frame", dangling_link, ArchiveError, "cannot be resolved"),
    # 6. names that no file system holds, clashes
    Case("name", "zip member name of 300 bytes", lambda w, s: _zip(w, "long.zip", [*_ok_members(), ("frames/" + "a" * 300 + ".xyz", b"1 2 3\n")]), ArchiveError, "file systems allow 255"),
    Case("name", "tar member name of 300 bytes", lambda w, s: _tar(w, "long.tar", [(_file("inspection.toml"), TOML), (_file("frames/" + "b" * 300 + ".xyz"), b"1 2 3\n")]), ArchiveError, "file systems allow 255"),
    Case("name", "zip: a file where a folder is", lambda w, s: _zip(w, "clash.zip", [("inspection.toml", TOML), ("frames", b"x"), ("frames/1.npy", b"")]), ArchiveError, "name clash"),
    Case("name", "zip: the same member twice", lambda w, s: _zip(w, "dup.zip", [*_ok_members(), ("frames/1.npy", b"")]), ArchiveError, "name clash"),
    Case("name", "tar: a member 2,100 folders deep", lambda w, s: _tar(w, "deep.tar", [(_file("inspection.toml"), TOML), (_file("/".join(["d"] * 2100) + "/1.xyz"), b"1 2 3\n")]), ArchiveError, "folders deep"),
    # 6. remote archives that cannot be reached
    Case("remote", "ftp:// with the connection refused", lambda w, s: "ftp://127.0.0.1:9/run.zip", FetchError, "cannot copy the archive"),
    Case("remote", "an unknown protocol", lambda w, s: "nosuchproto://bucket/run.zip", ArchiveError, "cannot open the URL"),
    # 7. text fields
    Case("text", "asset_id with an ESC sequence", _toml_with('asset_id = "MH1\\u001b[2J"'), MetadataError, "control or invisible"),
    Case("text", "asset_id of a million characters", _toml_with('asset_id = "' + "M" * 1_000_000 + '"'), MetadataError, "at most 64 characters"),
    Case("text", "asset_id of 300 characters", _toml_with('asset_id = "' + "M" * 300 + '"'), MetadataError, "at most 64 characters"),
    Case("text", "upstream_node with CR LF", _toml_with('asset_id = "A"\nupstream_node = "MH1\\r\\nMH2"'), MetadataError, "control or invisible"),
    Case("text", "asset_id with a NUL", _toml_with('asset_id = "MH1\\u0000"'), MetadataError, "control or invisible"),
    # round 2: E57 (no fetch, no shared section, bounded XML)
    Case("fetch", "E57 XML with an external DTD (http)", in_cloud("cloud.e57", e57_doctype("http://127.0.0.1:9/d")), PointFileError, "DOCTYPE"),
    Case("fetch", "E57 XML with an external DTD (file)", in_cloud("cloud.e57", e57_doctype("file:///etc/passwd")), PointFileError, "DOCTYPE"),
    Case("fetch", "E57 XML with nested entities (billion laughs)", in_cloud("cloud.e57", e57_entities), PointFileError, "DOCTYPE"),
    Case("parse", "E57 XML nested 200,000 deep", e57_deep, PointFileError, "more than 64 deep"),
    Case("expansion", "E57: 200 scans sharing one binary section", in_cloud("cloud.e57", e57_shared_section(200)), PointFileError, "shares its binary section"),
    Case("lying header", "E57: 1e8 records in a section of 2,000", in_cloud("cloud.e57", e57_count_lies), PointFileError, "its section holds"),
    # round 2: bounded parsing of inspection.toml
    Case("parse", "inspection.toml: a table header of 200,000 parts", toml_nested(lambda: "[" + ".".join(["a"] * 200_000) + "]\n"), MetadataError, "more than 32 deep"),
    Case("parse", "inspection.toml: 2,000 headers nesting one deeper each", toml_nested(lambda: "".join(f"[{'.'.join(['a'] * k)}]\n" for k in range(1, 2000))), MetadataError, "more than 32 deep"),
    Case("parse", "inspection.toml: arrays nested 200,000 deep", toml_nested(lambda: "x = " + "[" * 200_000 + "]" * 200_000 + "\n"), MetadataError, "more than 32 deep"),
    Case("parse", "inspection.toml: inline tables nested 100,000 deep", toml_nested(lambda: "x = " + "{a = " * 100_000 + "1" + "}" * 100_000 + "\n"), MetadataError, "more than 32 deep"),
    # round 2: ROS bags (every expansion bounded by what was read)
    Case("expansion", "ROS 1 bag, bz2 chunk of 50 M points", bag_bz2_bomb, PointFileError, "compression_max_ratio"),
    Case("expansion", "ROS 1 bag, lz4 chunk of 50 M points", bag_lz4_bomb, PointFileError, "compression_max_ratio"),
    Case("expansion", "MCAP, zstd chunk of 50 M points", mcap_zstd_bomb, PointFileError, "compression_max_ratio"),
    Case("expansion", "ROS 2 bag folder, compression_mode file", bag_file_compressed_bomb, PointFileError, "compression_max_ratio"),
    Case("expansion", ".db3 with a GENERATED zeroblob data column", db3_generated_zeroblob, PointFileError, "generated or hidden"),
    Case("lying header", "MCAP record length 2^40", mcap_record_length, PointFileError, "declares 1,099,511,627,776 bytes"),
    Case("lying header", "PointCloud2 x, y, z at offset 0", bag_cloud({}, 1000), PointFileError, "fields x and y overlap"),
    Case("lying header", "PointCloud2 height 2^32-1", bag_cloud({"height": 2**32 - 1, "data": b"\0" * 48, "offsets": (0, 4, 8), "step": 12}, 4), PointFileError, "points_max_count"),
    # round 2: values out of any plausible range
    Case("value", "inspected_at of year 9999 with an offset", lambda w, s: str(_dir_archive(w, {"1.npy": _npy_bytes(frame())}, toml=TOML.replace(b"2024-05-17", b"9999-12-31T23:00:00-05:00"))), MetadataError, "not a plausible inspection date"),
    Case("value", "inspected_at of year 1 with an offset", lambda w, s: str(_dir_archive(w, {"1.npy": _npy_bytes(frame())}, toml=TOML.replace(b"2024-05-17", b"0001-01-01T00:00:00+05:00"))), MetadataError, "not a plausible inspection date"),
    Case("text", "asset_id with a right-to-left override", _toml_with('asset_id = "MH1\\u202eFDP"'), MetadataError, "control or invisible"),
)  # fmt: skip


def fingerprint(path: Path) -> dict[str, tuple]:
    """Every entry under ``path`` (links not followed): kind, mode, bytes' hash, link target."""
    entries: dict[str, tuple] = {}
    top = Path(path)
    if not top.exists() and not top.is_symlink():
        return entries
    walk = [top] + (sorted(top.rglob("*")) if top.is_dir() and not top.is_symlink() else [])
    for p in walk:
        key = p.relative_to(top).as_posix()
        st = p.lstat()
        if p.is_symlink():
            entries[key] = ("link", os.readlink(p))
        elif p.is_dir():
            entries[key] = ("dir", st.st_mode)
        elif p.is_file():
            digest = hashlib.sha256()
            with p.open("rb") as fh:
                while chunk := fh.read(MIB):
                    digest.update(chunk)
            entries[key] = ("file", st.st_mode, digest.hexdigest())
        else:
            entries[key] = ("special", st.st_mode)
    return entries
