"""E57 files and ROS bags, written with the libraries' own writers and read back end to end."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipescan.core.errors import PointFileError
from pipescan.simulator.archive import write_simulated_archive
from pipescan.simulator.scan import get_scenario, simulate_scan
from pipescan.storage.input.archive import open_archive, validate_archive
from pipescan.storage.input.readers import e57
from pipescan.storage.input.readers.bags import write_bag

TOML = 'asset_id = "A-1"\ninspected_at = 2025-01-02\nnominal_diameter_m = 0.5\n'


def _archive(tmp_path: Path, extra: str = "") -> Path:
    root = tmp_path / "arc"
    root.mkdir(parents=True)
    (root / "inspection.toml").write_text(TOML + extra, encoding="utf-8")
    return root


def _pipe(n: int, rng: np.random.Generator, length_m: float = 3.0) -> np.ndarray:
    t, x = rng.uniform(0, 2 * np.pi, n), rng.uniform(0, length_m, n)
    return np.column_stack((x, 0.25 * np.cos(t), 0.25 * np.sin(t)))


# --- E57 ----------------------------------------------------------------------------------


def test_e57_scans_with_poses_from_pye57s_writer(tmp_path):
    import pye57

    rng = np.random.default_rng(0)
    pipe = _pipe(6000, rng)
    halves = (pipe[:3000], pipe[3000:])
    rotation = Rotation.from_euler("z", 40, degrees=True)
    translation = np.array([10.0, -3.0, 1.5])
    root = _archive(tmp_path)
    writer = pye57.E57(str(root / "cloud.e57"), mode="w")
    x, y, z, w = rotation.as_quat()
    for half in halves:
        # Each scan is stored in its own frame, with the pose that places it.
        local = rotation.inv().apply(half - translation)
        data = {"cartesianX": local[:, 0], "cartesianY": local[:, 1], "cartesianZ": local[:, 2]}
        writer.write_scan_raw(data, rotation=np.array([w, x, y, z]), translation=translation)
    writer.close()
    with open_archive(root) as arc:
        assert arc.cloud_member == "cloud.e57"
        points = arc.read_cloud()
        assert arc.read_cloud_time() is None
        summary = validate_archive(arc)
    assert summary.point_count == 6000
    # pye57 stores Cartesian coordinates in single precision.
    np.testing.assert_allclose(points, pipe, atol=2e-5)


def test_e57_time_and_several_scans(tmp_path):
    rng = np.random.default_rng(1)
    pipe = _pipe(4000, rng)
    order = np.argsort(pipe[:, 0])
    pipe = pipe[order]
    time_s = 1.7e9 + np.linspace(0.0, 40.0, len(pipe))
    root = _archive(tmp_path)
    e57.write_scans(root / "cloud.e57", [(pipe[:2000], time_s[:2000], None),
                                         (pipe[2000:], time_s[2000:], None)])  # fmt: skip
    with open_archive(root) as arc:
        np.testing.assert_allclose(arc.read_cloud(), pipe)
        np.testing.assert_allclose(arc.read_cloud_time(), time_s)


@pytest.mark.parametrize("damage", ["truncate", "flip"])
def test_a_damaged_e57_names_the_file_and_the_scan(tmp_path, damage):
    rng = np.random.default_rng(2)
    root = _archive(tmp_path)
    path = root / "cloud.e57"
    e57.write_scans(path, [(_pipe(3000, rng), None, None), (_pipe(3000, rng), None, None)])
    data = bytearray(path.read_bytes())
    if damage == "truncate":
        path.write_bytes(bytes(data[: len(data) // 2]))
        match = "cannot read E57"
    else:
        data[len(data) // 3] ^= 0xFF  # inside the first scan's points
        path.write_bytes(bytes(data))
        match = "scan 0"
    with pytest.raises(PointFileError, match=match) as info, open_archive(root) as arc:
        validate_archive(arc)
    assert info.value.file == "cloud.e57"
    assert "corrupt or truncated" in str(info.value)


# --- ROS bags -----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def short_scan():
    return simulate_scan(get_scenario("paper", travel_m=0.6), seed=0)


@pytest.mark.parametrize("bag_name", ["scan.bag", "scan.db3", "scan.mcap"])
def test_bag_frames_odometry_and_imu(tmp_path, short_scan, bag_name):
    write_simulated_archive(short_scan, tmp_path / "arc", layout="bag", bag_name=bag_name)
    with open_archive(tmp_path / "arc") as arc:
        assert arc.bag is not None and arc.frame_count == len(short_scan)
        assert arc.bag.points_topic == "/lidar/points"
        frames = arc.meta.frames
        times = [f.time_s for f in frames]
        np.testing.assert_allclose(times, short_scan.times_s - short_scan.times_s[0], atol=1e-6)
        np.testing.assert_allclose([f.odometer_m for f in frames], short_scan.odometer_m, atol=1e-6)
        g = frames[3].gravity
        assert g is not None
        np.testing.assert_allclose(g, short_scan.gravity(3), atol=1e-6)
        got = dict(arc.iter_frames([2, 5]))
        assert set(got) == {2, 5}
        np.testing.assert_allclose(got[5], short_scan.frame(5).points_sensor, atol=0)
        summary = validate_archive(arc)
        assert summary.frame_count == len(short_scan)


def test_bag_topics_named_or_found_by_type(tmp_path):
    rng = np.random.default_rng(3)
    frames = [(10**18 + k * 10**8, _pipe(500, rng)) for k in range(4)]
    root = _archive(tmp_path)
    write_bag(root / "run.bag", frames, points_topic="/front/points")
    # A second point-cloud topic makes the choice ambiguous.
    from rosbags.rosbag1 import Reader, Writer

    two = _archive(tmp_path / "two")
    with Reader(root / "run.bag") as reader, Writer(two / "run.bag") as writer:
        conns = {}
        for conn in reader.connections:
            for topic in ("/front/points", "/rear/points"):
                conns[topic] = writer.add_connection(
                    topic, conn.msgtype, msgdef=conn.msgdef.data, md5sum=conn.digest
                )
        for _, t, raw in reader.messages():
            for c in conns.values():
                writer.write(c, t, raw)
    with pytest.raises(PointFileError, match="several sensor_msgs/msg/PointCloud2") as info:
        open_archive(two)
    assert "points_topic" in str(info.value)
    (two / "inspection.toml").write_text(
        TOML + '[ros]\npoints_topic = "/rear/points"\n', encoding="utf-8"
    )
    with open_archive(two) as arc:
        assert arc.bag.points_topic == "/rear/points" and arc.frame_count == 4
    (two / "inspection.toml").write_text(
        TOML + '[ros]\npoints_topic = "/side/points"\n', encoding="utf-8"
    )
    with pytest.raises(PointFileError, match="no topic '/side/points'") as info:
        open_archive(two)
    assert info.value.field == "/side/points"


def test_a_truncated_bag_names_the_file_and_the_topic(tmp_path, short_scan):
    write_simulated_archive(short_scan, tmp_path / "arc", layout="bag")
    bag = tmp_path / "arc" / "scan.bag"
    data = bag.read_bytes()
    bag.write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises(PointFileError) as info, open_archive(tmp_path / "arc") as arc:
        validate_archive(arc)
    assert info.value.file == "scan.bag"
    assert "corrupt or truncated" in str(info.value)


def test_a_bag_and_frames_together_are_refused(tmp_path, short_scan):
    write_simulated_archive(short_scan, tmp_path / "arc", layout="bag")
    (tmp_path / "arc" / "frames").mkdir()
    np.save(tmp_path / "arc" / "frames" / "0.npy", np.ones((10, 3)))
    with pytest.raises(Exception, match="holds both the ROS bag"):
        open_archive(tmp_path / "arc")


@pytest.mark.e2e
@pytest.mark.slow  # three CLI runs, each starting Prefect: 2-3 minutes
def test_bag_and_e57_archives_end_to_end_and_nothing_stored_from_a_bad_one(tmp_path, short_scan):
    """`pipescan inspect` on a bag archive and on an E57 cloud archive stores their sections;
    on a damaged bag it fails with one line naming the bag, and stores nothing."""
    db = f"sqlite:///{tmp_path / 'p.db'}"
    scan = simulate_scan(get_scenario("paper", travel_m=1.2), seed=1)
    write_simulated_archive(scan, tmp_path / "bag", layout="bag", bag_name="scan.mcap")
    write_simulated_archive(
        simulate_scan(get_scenario("ring", travel_m=2.0), seed=0),
        tmp_path / "e57",
        layout="cloud",
        cloud_name="cloud.e57",
    )
    shutil.copytree(tmp_path / "bag", tmp_path / "bad")
    (tmp_path / "bad" / "inspection.toml").write_text(
        (tmp_path / "bag" / "inspection.toml").read_text().replace("SIM-PAPER", "SIM-BAD")
    )
    mcap = tmp_path / "bad" / "scan" / "scan.mcap"
    mcap.write_bytes(mcap.read_bytes()[: mcap.stat().st_size // 2])

    def inspect(archive: Path) -> subprocess.CompletedProcess:
        return subprocess.run(
            [sys.executable, "-m", "pipescan.cli", "inspect", str(archive), "--db", db, "--json"],
            capture_output=True,
            text=True,
            cwd=tmp_path,
            timeout=600,
        )

    import json

    ok = inspect(tmp_path / "bag")
    assert ok.returncode == 0, ok.stderr[-2000:]
    summary = json.loads(ok.stdout)
    assert summary["frame_count"] == len(scan) and summary["sections_ok"] >= 3
    assert summary["start_source"] == "first_frame"
    cloud = inspect(tmp_path / "e57")
    assert cloud.returncode == 0, cloud.stderr[-2000:]
    cloud_summary = json.loads(cloud.stdout)
    assert cloud_summary["start_source"] == "point_time"
    assert cloud_summary["sections_ok"] >= 15
    assert "a registered cloud (cloud.e57)" in cloud.stderr  # not "0 frames"
    assert f"read the cloud: {cloud_summary['point_count']:,} points" in cloud.stderr
    bad = inspect(tmp_path / "bad")
    assert bad.returncode == 2
    assert "scan" in bad.stderr and "corrupt or truncated" in bad.stderr
    listing = subprocess.run(
        [sys.executable, "-m", "pipescan.cli", "inspections", "--db", db],
        capture_output=True, text=True, cwd=tmp_path, timeout=120,
    )  # fmt: skip
    assert "SIM-BAD" not in listing.stdout
    assert "SIM-PAPER" in listing.stdout and "SIM-RING" in listing.stdout
