"""Write a simulated scan to disk as a scan archive, with its ground truth beside it.

The archive is an ordinary scan archive (docs/archive.md): ``inspection.toml`` and
``frames/NNNNNN.npy`` (``frames/NNNNNN.laz``, each point with its capture time as GPS time
(:func:`gps_time_offset_s`), when the scan has ``Effects.motion_within_frame``); or, with
``layout="cloud"`` (the default for the ring profiler and the static scanner, whose data
arrive as one registered cloud), ``inspection.toml`` and one ``cloud.laz`` in the world
frame, each point with its capture time as GPS time.
The ground truth sits in ``ground_truth/``, which archive readers
ignore:

- ``poses.csv``: ``frame_index, time_s, odometer_m, true_travel_m`` and the 16 entries of
  ``T_world_sensor``, row-major (``T00 ... T33``).
- ``sections.csv``: one :class:`~pipescan.simulator.scan.TrueSection` per row (0.1 m sections).
- ``features.csv``: one :class:`~pipescan.simulator.features.TrueFeature` per row: the true
  feature list (code, chainage span, clock arc, own figures), what the defect coder should find.
- ``scene.toml``: the generator, the seed, ``T_world_pipe`` and every scenario parameter.

TOML is written with tomli-w; ``tomllib`` reads it back.
The archive is written into a temporary sibling directory and renamed into place at the end,
so a crash never leaves half an archive under ``out_dir``.
"""

from __future__ import annotations

import csv
import dataclasses
import os
import shutil
import tempfile
import tomllib
from collections.abc import Callable, Iterator, Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w

from pipescan.core.errors import ArchiveError
from pipescan.simulator.features import TRUE_FEATURE_COLUMNS, TrueFeature, true_features
from pipescan.simulator.scan import (
    EFFECT_NAMES,
    BoxObstacle,
    DepositFill,
    Effects,
    EllipticalDeformation,
    Scenario,
    SimulatedScan,
    TrueSection,
    WallBand,
)
from pipescan.simulator.sensors import RingProfiler, StaticScanner, WaterLevel
from pipescan.storage.input.pointfiles import write_points

_SENSORS = {"ring_profiler": RingProfiler, "static_scanner": StaticScanner}

GENERATOR = "pipescan.simulator.scan"
"""Value of ``generator`` in ``ground_truth/scene.toml``: marks a simulated archive."""

SECTION_STEP_M = 0.1
"""Section length of ``ground_truth/sections.csv``."""

POSE_COLUMNS = (
    "frame_index",
    "time_s",
    "odometer_m",
    "true_travel_m",
    *(f"T{r}{c}" for r in range(4) for c in range(4)),
)
SECTION_COLUMNS = tuple(f.name for f in dataclasses.fields(TrueSection))

_SCENE = Path("ground_truth") / "scene.toml"


_GPS_EPOCH = datetime(1980, 1, 6, tzinfo=UTC)
_GPS_LEAP_S = 18.0  # GPS time runs ahead of UTC by the leap seconds since 1980 (18 since 2017)
_ADJUSTED_GPS_S = 1e9  # LAS "adjusted standard GPS time": GPS seconds less 10^9


def gps_time_offset_s(scan: SimulatedScan) -> float:
    """What a frame's LAZ adds to the scan's clock (seconds from the first frame) to write
    each point's GPS time: the inspection's start as LAS adjusted standard GPS time (GPS
    seconds less 10^9), about 4 x 10^8 s, as a real scanner writes absolute times. Frames
    written so hold times in another base than ``inspection.toml``'s ``time_s``, as real
    archives do."""
    start = scan.scenario.inspected_at
    return (start - _GPS_EPOCH).total_seconds() + _GPS_LEAP_S - _ADJUSTED_GPS_S


# --------------------------------------------------------------------------- TOML


def _plain(value: Any) -> Any:
    # tomli-w takes Python's own types: numpy scalars and arrays become numbers and lists, and
    # None (TOML has no null) is left out of tables.
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items() if v is not None}
    if isinstance(value, list | tuple | np.ndarray):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def dumps_toml(doc: Mapping[str, Any]) -> str:
    """Serialise a mapping to TOML (with tomli-w); ``None`` values are left out.

    Raises ``TypeError`` for values TOML cannot hold.
    """
    return tomli_w.dumps(_plain(doc))


# --------------------------------------------------------------------------- writing


def _inspection_doc(scan: SimulatedScan, layout: str = "frames") -> dict[str, Any]:
    meta = scan.meta
    doc = {
        "asset_id": meta.asset_id,
        "inspected_at": meta.inspected_at,
        "nominal_diameter_m": meta.nominal_diameter_m,
        "upstream_node": meta.upstream_node,
        "downstream_node": meta.downstream_node,
        "direction": meta.direction,
        "chainage_offset_m": meta.chainage_offset_m,
        "material": meta.material,
        "pipe_shape": meta.pipe_shape,
        "frames": [
            {
                "file": f.file,
                "time_s": f.time_s,
                "odometer_m": f.odometer_m,
                "gravity": list(f.gravity) if f.gravity is not None else None,
            }
            for f in meta.frames
        ],
    }
    if layout != "frames":  # a cloud has none, a bag holds its own
        del doc["frames"]
    return doc


def _scene_doc(scan: SimulatedScan) -> dict[str, Any]:
    scenario = dataclasses.asdict(scan.scenario)
    sensor = scan.scenario.sensor
    return {
        "sensor_kind": next(
            (kind for kind, cls in _SENSORS.items() if isinstance(sensor, cls)), "forward"
        ),
        "generator": GENERATOR,
        "seed": scan.seed,
        "n_frames": len(scan),
        "rays_per_frame": scan.scenario.rays_per_frame,
        "end_wall_m": scan.scenario.end_wall_m,
        "T_world_pipe": scan.T_world_pipe.tolist(),
        # TOML has no null: name the fields that are None so that they read back as None.
        "null_fields": [k for k, v in scenario.items() if v is None],
        "scenario": scenario,
    }


def _is_simulated_archive(path: Path) -> bool:
    try:
        with (path / _SCENE).open("rb") as fh:
            return tomllib.load(fh).get("generator") == GENERATOR
    except (OSError, tomllib.TOMLDecodeError):
        return False


def file_in_the_way(path: Path) -> str | None:
    """Why a folder cannot be made at ``path``: "<p> is a file" for the nearest existing
    path at or above it when that is not a folder, else None."""
    existing = Path(path).absolute()
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    return None if existing.is_dir() else f"{existing} is a file"


def write_simulated_archive(
    scan: SimulatedScan,
    out_dir: Path,
    *,
    progress: Callable[[int, int], None] | None = None,
    layout: str | None = None,
    cloud_name: str = "cloud.laz",
    bag_name: str = "scan.bag",
) -> Path:
    """Write ``scan`` as a scan archive directory with its ground truth.

    Parameters
    ----------
    scan
        The simulated scan; its frames are generated and written one at a time.
    out_dir
        The archive directory to create. It may exist if it is empty or holds a previous
        simulated archive (which is replaced).
    progress
        Called as ``progress(frames_done, frames_total)`` after each frame.
    layout
        ``"frames"`` (one point file per frame, sensor coordinates) or ``"cloud"`` (one
        registered cloud, ``cloud_name``, in the world frame placed with the true poses, each
        point's capture time stored with it); default ``"cloud"`` for the ring profiler and
        the static scanner, ``"frames"`` otherwise;
        ``"bag"`` writes the frames as a ROS bag, ``bag_name`` (:func:`write_simulated_bag`).
    cloud_name
        File name of the cloud; its suffix picks the format (one that holds time: ``.laz``,
        ``.las``, ``.ply``, ``.pcd``, ``.e57``).
    bag_name
        ``scan.bag`` (ROS 1), or a name ending ``.db3`` or ``.mcap`` for a ROS 2 bag folder of
        that storage.

    Returns
    -------
    Path
        ``out_dir``.

    Raises
    ------
    ArchiveError
        When ``out_dir`` is a file, or a non-empty directory that is not a simulated archive.
    """
    out_dir = Path(out_dir)
    if layout is None:
        layout = "frames" if scan.scenario.sensor is None else "cloud"
    if layout not in ("frames", "cloud", "bag"):
        raise ValueError(f"layout must be 'frames', 'cloud' or 'bag', got {layout!r}")
    if out_dir.exists() and not out_dir.is_dir():
        raise ArchiveError(
            "exists and is not a directory", archive=str(out_dir), hint="choose another path"
        )
    replace_existing = out_dir.is_dir() and any(out_dir.iterdir())
    if replace_existing and not _is_simulated_archive(out_dir):
        raise ArchiveError(
            "is a non-empty directory that is not a simulated archive; refusing to overwrite it",
            archive=str(out_dir),
            file=str(_SCENE),
            hint="choose an empty or new directory, or delete it first",
        )
    try:
        out_dir.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.partial-", dir=out_dir.parent))
    except OSError as exc:  # a file on the way to it, no permission
        raise ArchiveError(
            f"cannot make its folder: {file_in_the_way(out_dir) or exc.strerror or exc}",
            archive=str(out_dir),
            hint="choose a path in a folder you can write to",
        ) from exc
    try:
        (tmp / "ground_truth").mkdir()
        if layout == "frames":
            (tmp / "frames").mkdir()
            total = len(scan)
            for frame in scan.frames():
                path = tmp / scan.meta.frames[frame.index].file
                if frame.point_time_s is None:
                    np.save(path, frame.points_sensor)
                else:
                    gps_time_s = frame.point_time_s + gps_time_offset_s(scan)
                    write_points(path, frame.points_sensor.astype(np.float64), time_s=gps_time_s)
                if progress is not None:
                    progress(frame.index + 1, total)
        elif layout == "bag":
            write_simulated_bag(scan, tmp / bag_name, progress=progress)
        else:
            _write_world_cloud(scan, tmp / cloud_name, progress=progress)
        (tmp / "inspection.toml").write_text(
            dumps_toml(_inspection_doc(scan, layout)), encoding="utf-8"
        )
        _write_poses(tmp / "ground_truth" / "poses.csv", scan)
        _write_sections(tmp / "ground_truth" / "sections.csv", scan.true_sections(SECTION_STEP_M))
        _write_features(tmp / "ground_truth" / "features.csv", true_features(scan.scenario))
        # Written last: its presence marks a complete simulated archive.
        (tmp / _SCENE).write_text(dumps_toml(_scene_doc(scan)), encoding="utf-8")
        _swap_into_place(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out_dir


def write_simulated_bag(
    scan: SimulatedScan, path: Path, *, progress: Callable[[int, int], None] | None = None
) -> Path:
    """Write the scan's frames as a ROS bag: PointCloud2 frames in the sensor frame at their
    capture times, odometry (the odometer's reading along x) and IMU readings (the specific
    force against the measured gravity, 9.81 m/s², one per frame) when the scan has them.
    With ``Effects.motion_within_frame``, each point carries its capture time as an Ouster
    driver writes it: a uint32 field ``t``, nanoseconds since the frame's stamp.

    ``path`` ending ``.bag`` is a ROS 1 bag; ``.db3`` or ``.mcap`` a ROS 2 bag folder named
    without the suffix, holding that storage.
    """
    from pipescan.storage.input.readers.bags import write_bag

    t0_ns = 1_700_000_000 * 10**9

    def ns(t_s: float) -> int:
        return t0_ns + round(t_s * 1e9)

    def frames():
        for frame in scan.frames():
            if progress is not None:
                progress(frame.index + 1, len(scan))
            t_ns = None
            if frame.point_time_s is not None:
                t_ns = np.round((frame.point_time_s - frame.time_s) * 1e9).astype(np.uint32)
            yield ns(frame.time_s), frame.points_sensor, t_ns

    # Odometry and IMU just before each frame, so that the frame's period holds them.
    odometry = [
        (ns(float(t)) - 1000, (float(o), 0.0, 0.0))
        for t, o in zip(scan.times_s, scan.odometer_m, strict=True)
    ]
    imu = [
        (ns(float(scan.times_s[i])) - 1000, tuple(-9.81 * np.asarray(g)))
        for i in range(len(scan))
        if (g := scan.gravity(i)) is not None
    ]
    suffix = Path(path).suffix
    storage = {".bag": "rosbag1", ".db3": "sqlite3", ".mcap": "mcap"}[suffix]
    target = Path(path) if storage == "rosbag1" else Path(path).with_suffix("")
    return write_bag(target, frames(), odometry=odometry, imu=imu, storage=storage)


def world_cloud(
    scan: SimulatedScan, *, progress: Callable[[int, int], None] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Every frame's points placed in the world frame with the true poses, and each point's
    capture time: the registered cloud a perfect SLAM would export.

    Returns
    -------
    points : (N, 3) float64, metres, world frame
    time_s : (N,) float64, seconds: the frame's time plus the ray's share of the frame period
    """
    parts, times = [], []
    for points, time_s in _world_frames(scan, progress):
        parts.append(points)
        times.append(time_s)
    if not parts:
        return np.empty((0, 3)), np.empty(0)
    return np.concatenate(parts), np.concatenate(times)


def _world_frames(
    scan: SimulatedScan, progress: Callable[[int, int], None] | None
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Each frame of :func:`world_cloud`, in order: its points (world frame) and times."""
    period_s = 1.0 / scan.scenario.frame_rate_hz
    T_world_pipe = scan.T_world_pipe
    for frame in scan.frames():
        if frame.point_time_s is not None:
            # Each point placed with the true pose at its own time.
            p = scan.points_pipe(frame) @ T_world_pipe[:3, :3].T + T_world_pipe[:3, 3]
            yield p, frame.point_time_s
        else:
            p = frame.points_sensor.astype(np.float64)
            T = frame.T_world_sensor
            yield (
                p @ T[:3, :3].T + T[:3, 3],
                frame.time_s + period_s * np.arange(len(p)) / max(len(p), 1),
            )
        if progress is not None:
            progress(frame.index + 1, len(scan))


_SPOOL_ROWS = 1_000_000
"""Rows of x, y, z, time read back at a time from a simulated cloud's spool file."""


def _write_world_cloud(
    scan: SimulatedScan, path: Path, *, progress: Callable[[int, int], None] | None
) -> None:
    """Write :func:`world_cloud` to ``path``. A LAS or LAZ cloud is written without holding
    it: the frames go to a spool file (float64 x, y, z, time) while their minimum is found,
    then into the file a million points at a time, with the offset at that minimum, as
    :func:`~pipescan.storage.input.pointfiles.write_points` puts it (the same points, decoded,
    to the bit). Other formats are written whole."""
    if path.suffix.lower() not in (".las", ".laz"):
        points, time_s = world_cloud(scan, progress=progress)
        write_points(path, points, time_s=time_s)
        return
    from pipescan.storage.input.readers import las

    low = np.full(3, np.inf)
    with tempfile.TemporaryFile(dir=path.parent) as spool:
        for points, time_s in _world_frames(scan, progress):
            if len(points):
                low = np.minimum(low, points.min(axis=0))
                np.column_stack((points, time_s)).tofile(spool)
        spool.seek(0)

        def chunks() -> Iterator[tuple[np.ndarray, np.ndarray]]:
            while (rows := np.fromfile(spool, dtype=np.float64, count=4 * _SPOOL_ROWS)).size:
                rows = rows.reshape(-1, 4)
                yield rows[:, :3], rows[:, 3]

        las.write_chunks(
            path, chunks(), offsets=low if np.isfinite(low).all() else np.zeros(3), timed=True
        )


def _swap_into_place(tmp: Path, out_dir: Path) -> None:
    if out_dir.exists():
        # Move the old archive aside first: rename is atomic, rmtree is not.
        trash = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.old-", dir=out_dir.parent))
        os.replace(out_dir, trash / "archive")
        os.replace(tmp, out_dir)
        shutil.rmtree(trash, ignore_errors=True)
    else:
        os.replace(tmp, out_dir)


def _write_poses(path: Path, scan: SimulatedScan) -> None:
    with path.open("w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(POSE_COLUMNS)
        for i in range(len(scan)):
            row = [i, scan.times_s[i], scan.odometer_m[i], scan.true_travel_m[i]]
            row += scan.T_world_sensor[i].reshape(16).tolist()
            writer.writerow([repr(float(v)) if not isinstance(v, int) else v for v in row])


def _write_sections(path: Path, sections: list[TrueSection]) -> None:
    with path.open("w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(SECTION_COLUMNS)
        for s in sections:
            writer.writerow(
                [
                    str(getattr(s, c)).lower() if c == "in_shadow" else repr(getattr(s, c))
                    for c in SECTION_COLUMNS
                ]
            )


def _write_features(path: Path, features: list[TrueFeature]) -> None:
    with path.open("w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(TRUE_FEATURE_COLUMNS)
        for f in features:
            writer.writerow(
                ["" if (v := getattr(f, c)) is None else v if isinstance(v, str) else repr(v)
                 for c in TRUE_FEATURE_COLUMNS]
            )  # fmt: skip


# --------------------------------------------------------------------------- reading


def read_true_features(archive_dir: Path) -> list[TrueFeature]:
    """The true feature list of a simulated archive (``ground_truth/features.csv``).

    Raises
    ------
    ArchiveError
        When the file is missing (an archive written before it existed: write it again) or a
        row cannot be read.
    """
    path = _ground_truth_file(Path(archive_dir), "features.csv")
    with path.open(newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    _check_header(rows, TRUE_FEATURE_COLUMNS, Path(archive_dir), "features.csv")
    out = []
    try:
        for row in rows[1:]:
            values: dict[str, Any] = dict(zip(TRUE_FEATURE_COLUMNS, row, strict=True))
            for key, text in values.items():
                if key not in ("code", "measure"):
                    values[key] = None if text == "" else float(text)
            out.append(TrueFeature(**values))
    except ValueError as exc:
        raise _bad_rows(Path(archive_dir), "features.csv", exc) from exc
    return out


def _ground_truth_file(archive_dir: Path, name: str) -> Path:
    path = Path(archive_dir) / "ground_truth" / name
    if not path.is_file():
        raise ArchiveError(
            "has no ground truth",
            archive=str(archive_dir),
            file=f"ground_truth/{name}",
            hint="only archives written by write_simulated_archive carry ground truth",
        )
    return path


def read_ground_truth(archive_dir: Path) -> tuple[np.ndarray, list[TrueSection]]:
    """Read the true poses and sections of a simulated archive.

    Parameters
    ----------
    archive_dir
        A directory written by :func:`write_simulated_archive`.

    Returns
    -------
    poses
        (F, 4, 4) float64 true ``T_world_sensor`` per frame.
    sections
        The :class:`TrueSection` list (0.1 m sections).

    Raises
    ------
    ArchiveError
        When a ground-truth file is missing or has the wrong columns.
    """
    archive_dir = Path(archive_dir)
    poses_path = _ground_truth_file(archive_dir, "poses.csv")
    sections_path = _ground_truth_file(archive_dir, "sections.csv")
    with poses_path.open(newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    _check_header(rows, POSE_COLUMNS, archive_dir, "poses.csv")
    try:
        table = np.array([[float(v) for v in row] for row in rows[1:]], dtype=np.float64)
    except ValueError as exc:
        raise _bad_rows(archive_dir, "poses.csv", exc) from exc
    if table.size and table.shape[1] != len(POSE_COLUMNS):
        raise _bad_rows(archive_dir, "poses.csv", "a row has the wrong number of values")
    poses = table[:, 4:].reshape(-1, 4, 4) if table.size else np.empty((0, 4, 4))
    with sections_path.open(newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    _check_header(rows, SECTION_COLUMNS, archive_dir, "sections.csv")
    sections = []
    try:
        for row in rows[1:]:
            values = dict(zip(SECTION_COLUMNS, row, strict=True))
            in_shadow = values.pop("in_shadow") == "true"
            floats = {k: float(v) for k, v in values.items()}
            sections.append(TrueSection(**floats, in_shadow=in_shadow))
    except ValueError as exc:
        raise _bad_rows(archive_dir, "sections.csv", exc) from exc
    return poses, sections


def _bad_rows(archive_dir: Path, name: str, reason: object) -> ArchiveError:
    return ArchiveError(
        f"unreadable row: {reason}",
        archive=str(archive_dir),
        file=f"ground_truth/{name}",
        hint="write the archive again with write_simulated_archive",
    )


def _check_header(
    rows: list[list[str]], expected: tuple[str, ...], archive_dir: Path, name: str
) -> None:
    if not rows or tuple(rows[0]) != expected:
        raise ArchiveError(
            f"unexpected columns (expected {', '.join(expected)})",
            archive=str(archive_dir),
            file=f"ground_truth/{name}",
            hint="write the archive again with write_simulated_archive",
        )


def read_simulated_scene(archive_dir: Path) -> tuple[Scenario, int, np.ndarray]:
    """Read back the scenario, seed and ``T_world_pipe`` (4, 4) of a simulated archive.

    ``simulate_scan(scenario, seed)`` then regenerates the same scan.

    Raises
    ------
    ArchiveError
        When ``ground_truth/scene.toml`` is missing or not written by the simulator.
    """
    path = _ground_truth_file(Path(archive_dir), "scene.toml")
    with path.open("rb") as fh:
        doc = tomllib.load(fh)
    if doc.get("generator") != GENERATOR:
        raise ArchiveError(
            f"generator is not {GENERATOR!r}",
            archive=str(archive_dir),
            file=str(_SCENE),
            field="generator",
        )
    raw = dict(doc["scenario"])
    nested = {
        "deformations": EllipticalDeformation,
        "deposits": DepositFill,
        "obstacles": BoxObstacle,
        "bands": WallBand,
    }
    for key, cls in nested.items():
        raw[key] = tuple(cls(**item) for item in raw.get(key, []))
    raw["world_origin_m"] = tuple(raw["world_origin_m"])
    sensor_cls = _SENSORS.get(doc.get("sensor_kind", "forward"))
    raw["sensor"] = sensor_cls(**raw["sensor"]) if sensor_cls and raw.get("sensor") else None
    raw["water"] = WaterLevel(**raw["water"]) if raw.get("water") else None
    # Effects are a table of their own; archives written before that hold some of them at
    # the top level (and the rest then read back at today's defaults).
    effects = {k: raw.pop(k) for k in EFFECT_NAMES if k in raw} | dict(raw.get("effects", {}))
    if "slip_duration_s" in effects:
        effects["slip_duration_s"] = tuple(effects["slip_duration_s"])
    raw["effects"] = Effects(**{k: v for k, v in effects.items() if k in EFFECT_NAMES})
    raw.update(dict.fromkeys(doc.get("null_fields", [])))
    known = {f.name for f in dataclasses.fields(Scenario)}
    scenario = Scenario(**{k: v for k, v in raw.items() if k in known})
    return scenario, int(doc["seed"]), np.array(doc["T_world_pipe"], dtype=np.float64)
