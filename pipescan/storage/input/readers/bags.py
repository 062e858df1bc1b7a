"""ROS bags as scan archives: ROS 1 ``.bag``, ROS 2 ``.db3`` and ``.mcap`` files and ROS 2 bag
folders, read with ``rosbags`` (no ROS install).

A bag's ``sensor_msgs/PointCloud2`` messages are the frames, in the sensor's frame;
``nav_msgs/Odometry`` becomes the odometer (the distance travelled along the odometry's
positions, at each frame's time) and ``sensor_msgs/Imu`` the gravity direction (against the
mean specific force the accelerometer measured over the frame's period; the IMU is taken to be
mounted in the LiDAR's axes). The topics are named in ``inspection.toml``'s ``[ros]`` table, or
found by message type when the bag has one topic of the type.

Frames are streamed: :func:`index_bag` reads the bag once to list the frames (their bag times)
and the odometry and IMU (small messages), keeping per frame only a time, an odometer reading
and a gravity direction; :func:`iter_bag_frames` then reads the point messages of a range of
frames, one at a time. A bag that cannot be read (corrupt, truncated, a message whose bytes do
not match its own fields) raises :class:`PointFileError` naming the bag and the topic.
"""

from __future__ import annotations

import itertools
import threading
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipescan.core.errors import PointFileError
from pipescan.core.model import FrameRef, RosTopics
from pipescan.storage.input.limits import DEFAULT_LIMITS, InputLimits, point_limit_error
from pipescan.storage.input.readers.bagguard import BagOverCap, bag_limits

BAG_SUFFIXES = (".bag", ".db3", ".mcap")
"""Suffixes of bag files; a ROS 2 bag folder is recognised by its ``metadata.yaml``."""

POINTS_TYPE = "sensor_msgs/msg/PointCloud2"
ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
IMU_TYPE = "sensor_msgs/msg/Imu"
_FLOAT_TYPES = {7: "f4", 8: "f8"}  # sensor_msgs/PointField FLOAT32, FLOAT64
_FIELD_BYTES = {1: 1, 2: 1, 3: 2, 4: 2, 5: 4, 6: 4, 7: 4, 8: 8}  # PointField datatypes' sizes
_FIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
TIME_NAMES = ("t", "time", "timestamp", "offset_time")
"""PointCloud2 fields read as each point's capture time, the first one present: Ouster's
``t`` (uint32 ns since the frame's start), Velodyne's ``time`` (float32 s since it), Hesai's
and Livox's ``timestamp`` (float64, absolute), Livox's ``offset_time`` (uint32 ns). Their unit
is told by the frame's span (:func:`~pipescan.core.registration.deskew.point_times_s`)."""
_HINT = "the bag is corrupt or truncated: copy or record it again"


def is_bag(path: Path) -> bool:
    """True for a bag file (by suffix) or a ROS 2 bag folder (holding ``metadata.yaml``)."""
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    return path.suffix.lower() in BAG_SUFFIXES


@dataclass(frozen=True)
class BagIndex:
    """What :func:`index_bag` found: the bag, its topics and each frame's bag time (ns)."""

    member: str
    points_topic: str
    odometry_topic: str | None
    imu_topic: str | None
    frame_times_ns: tuple[int, ...]


def _error(archive: str | None, member: str, topic: str | None, reason: str, hint=_HINT):
    return PointFileError(reason, archive=archive, file=member, field=topic or "topics", hint=hint)


def _reader(path: Path):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    return AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))


def _read_errors():
    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as Reader1Error
    from rosbags.rosbag2 import ReaderError as Reader2Error
    from rosbags.serde import SerdeError

    errors: tuple[type[BaseException], ...] = ()
    try:
        import apsw

        errors = (apsw.Error,)
    except ImportError:  # pragma: no cover - rosbags' sqlite reader needs it
        pass
    return (
        *errors,
        AnyReaderError,
        Reader1Error,
        Reader2Error,
        SerdeError,
        OSError,
        EOFError,
        ValueError,
        KeyError,
        IndexError,
        TypeError,
        AssertionError,
        __import__("struct").error,
        __import__("sqlite3").Error,
    )


def _choose(
    reader, wanted: str | None, msgtype: str, archive, member, *, required: bool
) -> object | None:
    """The connection of the topic named ``wanted``, or the one topic of ``msgtype``."""
    conns = reader.connections
    if wanted is not None:
        found = [c for c in conns if c.topic == wanted]
        if not found:
            topics = ", ".join(sorted({c.topic for c in conns})) or "none"
            raise _error(
                archive, member, wanted, f"the bag has no topic {wanted!r} (it has: {topics})",
                hint="fix the topic in inspection.toml's [ros] table",
            )  # fmt: skip
        if found[0].msgtype != msgtype:
            raise _error(
                archive, member, wanted,
                f"topic {wanted!r} holds {found[0].msgtype}, not {msgtype}",
                hint="name a topic of that type in inspection.toml's [ros] table",
            )  # fmt: skip
        return found[0]
    typed = [c for c in conns if c.msgtype == msgtype]
    topics = sorted({c.topic for c in typed})
    if len(topics) > 1:
        key = {POINTS_TYPE: "points_topic", ODOMETRY_TYPE: "odometry_topic"}.get(
            msgtype, "imu_topic"
        )
        raise _error(
            archive, member, None, f"the bag has several {msgtype} topics: {', '.join(topics)}",
            hint=f"name one as {key} in inspection.toml's [ros] table",
        )  # fmt: skip
    if not typed:
        if required:
            raise _error(
                archive, member, None, f"the bag has no {msgtype} topic",
                hint="record the LiDAR's point clouds, or name their topic in [ros]",
            )  # fmt: skip
        return None
    return typed[0]


_CACHE: dict[tuple, tuple[BagIndex, tuple[FrameRef, ...]]] = {}
_CACHE_LOCK = threading.Lock()


def _stat_key(path: Path) -> tuple:
    # Relative names, sizes and times: the same bag moved (a staged extraction) is found.
    files = sorted(path.rglob("*")) if path.is_dir() else [path]
    return tuple(
        (str(f.relative_to(path)), f.stat().st_size, f.stat().st_mtime_ns)
        for f in files
        if f.is_file()
    )


def _over(exc: BagOverCap, limits: InputLimits, archive, member, topic) -> PointFileError:
    return point_limit_error(
        exc.cap, limits, exc.what, archive=archive, file=member, field=topic or "topics"
    )


def index_bag(
    path: Path,
    member: str,
    *,
    archive: str | None,
    topics: RosTopics | None,
    limits: InputLimits = DEFAULT_LIMITS,
) -> tuple[BagIndex, tuple[FrameRef, ...]]:
    """List a bag's frames with their time, odometer reading and gravity.

    Read once per bag and process (cached by the files' sizes and times): the tasks of one
    inspection reopen the archive and must not read the bag again to find its frames.

    Returns
    -------
    BagIndex, and one FrameRef per PointCloud2 message (``file`` is ``member#i``,
    ``time_s`` from the first frame, ``odometer_m`` when the bag has odometry, ``gravity``
    when it has an IMU with readings near the frame's time).

    Raises
    ------
    PointFileError
        A topic missing or ambiguous, or the bag unreadable; naming the bag and the topic.
    """
    topics = topics or RosTopics()
    key = (_stat_key(path), member, topics)
    with _CACHE_LOCK:
        if key in _CACHE:
            return _CACHE[key]
    reading = None
    try:
        with bag_limits(limits), _reader(path) as reader:
            points = _choose(reader, topics.points_topic, POINTS_TYPE, archive, member,
                             required=True)  # fmt: skip
            odometry = _choose(reader, topics.odometry_topic, ODOMETRY_TYPE, archive, member,
                               required=False)  # fmt: skip
            imu = _choose(reader, topics.imu_topic, IMU_TYPE, archive, member, required=False)
            times: list[int] = []
            odo_t, odo_xyz, imu_t, imu_acc = [], [], [], []
            conns = [c for c in (points, odometry, imu) if c is not None]
            for conn, t_ns, raw in reader.messages(connections=conns):
                reading = conn.topic
                if conn is points:
                    times.append(int(t_ns))
                elif conn is odometry:
                    p = reader.deserialize(raw, conn.msgtype).pose.pose.position
                    odo_t.append(int(t_ns))
                    odo_xyz.append((p.x, p.y, p.z))
                else:
                    a = reader.deserialize(raw, conn.msgtype).linear_acceleration
                    imu_t.append(int(t_ns))
                    imu_acc.append((a.x, a.y, a.z))
    except PointFileError:
        raise
    except BagOverCap as exc:
        raise _over(exc, limits, archive, member, reading) from None
    except _read_errors() as exc:
        raise _error(archive, member, reading, f"cannot read the bag: {exc}") from exc
    if not times:
        raise _error(archive, member, points.topic, "the point-cloud topic has no messages",
                     hint="record the LiDAR's point clouds")  # fmt: skip
    t = np.asarray(times, dtype=np.int64)
    time_s = (t - t[0]) / 1e9
    odometer = _odometer(t, np.asarray(odo_t, np.int64), np.asarray(odo_xyz, float))
    gravity = _gravity(t, np.asarray(imu_t, np.int64), np.asarray(imu_acc, float))
    frames = tuple(
        FrameRef(
            file=f"{member}#{i}",
            time_s=float(time_s[i]),
            odometer_m=None if odometer is None else float(odometer[i]),
            gravity=None if gravity is None or not np.isfinite(gravity[i]).all()
            else (float(gravity[i, 0]), float(gravity[i, 1]), float(gravity[i, 2])),
        )
        for i in range(len(t))
    )  # fmt: skip
    index = BagIndex(
        member=member,
        points_topic=points.topic,
        odometry_topic=None if odometry is None else odometry.topic,
        imu_topic=None if imu is None else imu.topic,
        frame_times_ns=tuple(times),
    )
    with _CACHE_LOCK:
        if len(_CACHE) > 16:
            _CACHE.clear()
        _CACHE[key] = (index, frames)
    return index, frames


def _odometer(frame_t: np.ndarray, odo_t: np.ndarray, xyz: np.ndarray) -> np.ndarray | None:
    """Distance travelled along the odometry's positions, at each frame's time (m)."""
    if len(odo_t) < 2:
        return None
    order = np.argsort(odo_t, kind="stable")
    odo_t, xyz = odo_t[order], xyz[order]
    path = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(xyz, axis=0), axis=1))))
    return np.interp(frame_t, odo_t, path)


def _gravity(frame_t: np.ndarray, imu_t: np.ndarray, acc: np.ndarray) -> np.ndarray | None:
    """Unit gravity per frame: against the mean specific force over the frame's period (NaN
    rows where no IMU reading falls within it)."""
    if len(imu_t) == 0:
        return None
    period = np.median(np.diff(frame_t)) if len(frame_t) > 1 else 1e8
    lo = np.searchsorted(imu_t, frame_t - period / 2)
    hi = np.searchsorted(imu_t, frame_t + period / 2)
    sums = np.vstack((np.zeros(3), np.cumsum(acc, axis=0)))
    counts = (hi - lo)[:, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = (sums[hi] - sums[lo]) / counts
        g = -mean / np.linalg.norm(mean, axis=1, keepdims=True)
    g[(hi - lo) == 0] = np.nan
    return g


def cloud_to_points(msg, *, points_max_count: int | None = None) -> np.ndarray:
    """A ``sensor_msgs/PointCloud2`` as ``(N, 3)`` float64; points with a NaN or infinite
    coordinate (no return, in an organised cloud) are left out.

    As :func:`cloud_to_timed_points`, without the times.
    """
    return cloud_to_timed_points(msg, points_max_count=points_max_count, time_names=())[0]


def cloud_to_timed_points(
    msg, *, points_max_count: int | None = None, time_names: Sequence[str] = TIME_NAMES
) -> tuple[np.ndarray, np.ndarray | None, str | None]:
    """A ``sensor_msgs/PointCloud2`` as ``(N, 3)`` float64 points, each point's raw time and
    the time field's name: the first field of ``time_names`` the message has, ``(N,)`` in its
    own dtype (None, None when it has none). Points with a NaN or infinite coordinate (no
    return, in an organised cloud) are left out, and their times with them.

    The message must hold exactly ``height`` rows of ``row_step`` bytes, each row at least
    ``width`` points of ``point_step`` bytes, and its fields must lie within a point without
    overlapping: nothing is allocated for what the message does not hold.

    Raises
    ------
    ValueError
        When the message's fields, steps and data disagree, it declares more than
        ``points_max_count`` points, or its time field is not one number per point.
    """
    fields = {f.name: f for f in msg.fields}
    missing = [a for a in "xyz" if a not in fields]
    if missing:
        raise ValueError(f"the point cloud has no {', '.join(missing)} field")
    rows, width = int(msg.height), int(msg.width)
    step, row_step = int(msg.point_step), int(msg.row_step)
    data = msg.data
    if points_max_count is not None and rows * width > points_max_count:
        raise ValueError(f"{rows:,} x {width:,} points are over the limit of "
                         f"{points_max_count:,} (points_max_count)")  # fmt: skip
    if rows * width and (row_step < width * step or len(data) != rows * row_step):
        raise ValueError(
            f"{rows:,} rows x {width:,} points of {step:,} bytes (rows of {row_step:,} bytes) "
            f"need {rows * row_step:,} bytes, the message holds {len(data):,}"
        )
    spans = []
    for f in msg.fields:
        size = _FIELD_BYTES.get(int(f.datatype))
        if size is None:
            raise ValueError(f"field {f.name} has an unknown datatype {f.datatype}")
        end = int(f.offset) + size * max(1, int(f.count))
        if end > step:
            raise ValueError(f"field {f.name} lies beyond the point step {step}")
        spans.append((int(f.offset), end, f.name))
    spans.sort()
    for (_, end, first), (start, _, second) in itertools.pairwise(spans):
        if start < end:
            raise ValueError(f"fields {first} and {second} overlap")
    order = ">" if msg.is_bigendian else "<"
    formats, offsets = [], []
    for a in "xyz":
        f = fields[a]
        if f.datatype not in _FLOAT_TYPES:
            raise ValueError(f"field {a} has datatype {f.datatype}, not FLOAT32 or FLOAT64")
        formats.append(order + _FLOAT_TYPES[f.datatype])
        offsets.append(int(f.offset))
    names = ["x", "y", "z"]
    found = next((n for n in time_names if n in fields), None)
    if found is not None:
        f = fields[found]
        if int(f.datatype) not in _FIELD_TYPES or int(f.count) > 1:
            raise ValueError(
                f"time field {found} has datatype {f.datatype} and count {f.count}, not one "
                "number per point"
            )
        names.append(found)
        formats.append(order + _FIELD_TYPES[int(f.datatype)])
        offsets.append(int(f.offset))
    if rows * width == 0:
        return np.empty((0, 3)), None, None
    data = np.asarray(data, dtype=np.uint8)
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets,
                      "itemsize": step})  # fmt: skip
    table = np.lib.stride_tricks.as_strided(
        np.frombuffer(data.tobytes(), dtype=np.uint8),
        shape=(rows, width * step),
        strides=(row_step, 1),
    )
    records = np.ascontiguousarray(table).view(dtype).reshape(-1)
    pts = np.column_stack([records[a].astype(np.float64) for a in "xyz"])
    finite = np.isfinite(pts).all(axis=1)
    if found is None:
        return pts[finite], None, None
    # Native byte order, so that the time's dtype is what point_times_s expects.
    time = records[found][finite]
    return pts[finite], time.astype(time.dtype.newbyteorder("=")), found


def iter_bag_frames(
    path: Path,
    index: BagIndex,
    indices: Sequence[int],
    *,
    archive: str | None,
    limits: InputLimits = DEFAULT_LIMITS,
    with_time: bool = False,
) -> Iterator[tuple[int, np.ndarray, np.ndarray | None, str | None]]:
    """Yield ``(i, points, raw_time, time_field)`` for the frames ``indices`` (ascending), one
    message at a time; with ``with_time``, each point's raw time and its field's name as
    :func:`cloud_to_timed_points` gives them, decoded with the points (None, None without).

    Raises
    ------
    PointFileError
        Naming the bag, the topic and the frame, when a message cannot be read.
    """
    wanted = sorted(set(int(i) for i in indices))
    if not wanted:
        return
    times = index.frame_times_ns
    want = set(wanted)
    # Frames are numbered in bag-time order; count from the first one at the start time.
    first_at_start = times.index(times[wanted[0]])
    i = first_at_start - 1
    where = f"{index.points_topic}"
    try:
        with bag_limits(limits), _reader(path) as reader:
            conns = [c for c in reader.connections if c.topic == index.points_topic]
            messages = reader.messages(
                connections=conns, start=times[wanted[0]], stop=times[wanted[-1]] + 1
            )
            for conn, _, raw in messages:
                i += 1
                if i not in want:
                    continue
                try:
                    msg = reader.deserialize(raw, conn.msgtype)
                    points, time, field = cloud_to_timed_points(
                        msg,
                        points_max_count=limits.points_max_count,
                        time_names=TIME_NAMES if with_time else (),
                    )
                except _read_errors() as exc:
                    raise _error(
                        archive, index.member, where, f"frame {i} cannot be read: {exc}"
                    ) from exc
                yield i, points, time, field
                if i >= wanted[-1]:
                    return
    except PointFileError:
        raise
    except BagOverCap as exc:
        raise _over(exc, limits, archive, index.member, where) from None
    except _read_errors() as exc:
        raise _error(archive, index.member, where, f"cannot read the bag: {exc}") from exc
    raise _error(archive, index.member, where, f"the bag ends before frame {wanted[-1]}")


def write_bag(
    path: Path,
    frames: Iterable[tuple[int, np.ndarray] | tuple[int, np.ndarray, np.ndarray | None]],
    *,
    odometry: Sequence[tuple[int, tuple[float, float, float]]] = (),
    imu: Sequence[tuple[int, tuple[float, float, float]]] = (),
    storage: str = "rosbag1",
    points_topic: str = "/lidar/points",
    odometry_topic: str = "/odom",
    imu_topic: str = "/imu/data",
) -> Path:
    """Write a bag with the ``rosbags`` writers: ``frames`` as ``(time_ns, points (N, 3))``
    PointCloud2 messages (float32 x, y, z), or ``(time_ns, points, t (N,))`` with a uint32
    field ``t`` too (each point's time, ns since ``time_ns``, as Ouster's driver writes it),
    ``odometry`` as ``(time_ns, position)`` and ``imu`` as ``(time_ns, linear_acceleration)``.

    ``storage``: ``"rosbag1"`` (a ``.bag`` file), ``"sqlite3"`` or ``"mcap"`` (a ROS 2 bag
    folder at ``path``). Returns ``path``.
    """
    from rosbags.typesys import Stores, get_typestore

    ros1 = storage == "rosbag1"
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    types = store.types
    serialize = store.serialize_ros1 if ros1 else store.serialize_cdr

    def header(t_ns: int, frame_id: str):
        stamp = types["builtin_interfaces/msg/Time"](sec=t_ns // 10**9, nanosec=t_ns % 10**9)
        if ros1:
            return types["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame_id)
        return types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)

    field_cls = types["sensor_msgs/msg/PointField"]
    fields = [field_cls(name=a, offset=4 * k, datatype=7, count=1) for k, a in enumerate("xyz")]
    timed_fields = [*fields, field_cls(name="t", offset=12, datatype=6, count=1)]
    vector = types["geometry_msgs/msg/Vector3"]

    def cloud(t_ns: int, pts: np.ndarray, point_t_ns: np.ndarray | None = None):
        if point_t_ns is None:
            data = np.ascontiguousarray(pts, dtype="<f4").view(np.uint8).reshape(-1)
            step, names = 12, fields
        else:
            rows = np.empty(len(pts), dtype=[("xyz", "<f4", 3), ("t", "<u4")])
            rows["xyz"], rows["t"] = pts, point_t_ns
            data = rows.view(np.uint8).reshape(-1)
            step, names = 16, timed_fields
        return types[POINTS_TYPE](
            header=header(t_ns, "lidar"), height=1, width=len(pts), fields=names,
            is_bigendian=False, point_step=step, row_step=step * len(pts), data=data,
            is_dense=True,
        )  # fmt: skip

    def odom(t_ns: int, xyz):
        pose = types["geometry_msgs/msg/Pose"](
            position=types["geometry_msgs/msg/Point"](x=xyz[0], y=xyz[1], z=xyz[2]),
            orientation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        )
        cov = np.zeros(36)
        twist = types["geometry_msgs/msg/Twist"](linear=vector(x=0.0, y=0.0, z=0.0),
                                                 angular=vector(x=0.0, y=0.0, z=0.0))  # fmt: skip
        return types[ODOMETRY_TYPE](
            header=header(t_ns, "odom"), child_frame_id="base_link",
            pose=types["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=cov),
            twist=types["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=cov),
        )  # fmt: skip

    def imu_msg(t_ns: int, acc):
        zero = np.zeros(9)
        return types[IMU_TYPE](
            header=header(t_ns, "lidar"),
            orientation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=zero, angular_velocity=vector(x=0.0, y=0.0, z=0.0),
            angular_velocity_covariance=zero,
            linear_acceleration=vector(x=acc[0], y=acc[1], z=acc[2]),
            linear_acceleration_covariance=zero,
        )  # fmt: skip

    if ros1:
        from rosbags.rosbag1 import Writer as Writer1

        writer = Writer1(path)
    else:
        from rosbags.rosbag2 import StoragePlugin
        from rosbags.rosbag2 import Writer as Writer2

        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        writer = Writer2(path, version=9, storage_plugin=plugin)
    with writer:
        c_points = writer.add_connection(points_topic, POINTS_TYPE, typestore=store)
        messages: list[tuple[int, object, object]] = []
        if odometry:
            c_odom = writer.add_connection(odometry_topic, ODOMETRY_TYPE, typestore=store)
            messages += [(t, c_odom, odom(t, xyz)) for t, xyz in odometry]
        if imu:
            c_imu = writer.add_connection(imu_topic, IMU_TYPE, typestore=store)
            messages += [(t, c_imu, imu_msg(t, acc)) for t, acc in imu]
        small = iter(sorted(messages, key=lambda m: m[0]))
        pending = next(small, None)
        for t_ns, pts, *point_t_ns in frames:
            while pending is not None and pending[0] <= t_ns:
                writer.write(pending[1], pending[0], serialize(pending[2], pending[2].__msgtype__))
                pending = next(small, None)
            message = cloud(t_ns, pts, *point_t_ns)
            writer.write(c_points, t_ns, serialize(message, POINTS_TYPE))
        while pending is not None:
            writer.write(pending[1], pending[0], serialize(pending[2], pending[2].__msgtype__))
            pending = next(small, None)
    return path
