"""Deskewing frames whose points carry times, against the simulator's motion within a frame.

At 0.5 m/s a frame of 0.1 s is captured over 50 mm of travel. The simulator
(``Effects.motion_within_frame``) casts each packet of a frame's rays from the sensor's pose at
its time, so the truth of every point is known: ``SimulatedScan.points_pipe``.
"""

from __future__ import annotations

import numpy as np
import pytest

from pipescan.core.errors import PointFileError
from pipescan.core.registration import RegistrationParams, iter_registered_points, register_frames
from pipescan.core.registration.deskew import deskew_points, relative_motion
from pipescan.core.registration.engines import transform
from pipescan.simulator.scan import Effects, get_scenario, simulate_scan

SPEED_M_S = 0.5


def _scenario(**overrides):
    """The paper's pipe from its start, its obstacle 1.4-2.9 m ahead (a sharp edge across
    the axis for ICP), a fast crawl, and the attitude's smooth rocking. (Vibration, a new
    attitude every frame, turns the sensor at a rate no constant-velocity motion predicts:
    deskewing leaves that part of the skew, docs/registration.md, *Deskew*.)"""
    effects = Effects.ideal(motion_within_frame=True, range_noise_sigma_m=0.002, rocking_deg=1.0)
    base = dict(travel_m=1.2, speed_m_s=SPEED_M_S, points_per_s=100_000, effects=effects)
    return get_scenario("paper", **{**base, **overrides})


@pytest.fixture(scope="module")
def moving_scan():
    scan = simulate_scan(_scenario(), seed=4)
    return scan, [scan.frame(i) for i in range(len(scan))]


def _along_errors_m(scan, frames, placed):
    """Each placed point's error against its true place (pipe frame, m), (N, 3): the
    registered world is the first frame's sensor frame."""
    T0 = scan.T_pipe_sensor(0)
    return np.concatenate(
        [transform(T0, p) - scan.points_pipe(f) for f, p in zip(frames, placed, strict=True)]
    )


def test_deskew_undoes_the_simulated_motion_within_a_frame(moving_scan):
    scan, frames = moving_scan
    f = frames[5]
    assert f.point_time_s is not None and f.point_time_s.min() == f.time_s
    truth = scan.points_pipe(f)
    T = scan.T_pipe_sensor(5)
    skewed = transform(T, f.points_sensor.astype(np.float64))
    # Without deskew the last packets are placed 49 mm (0.098 s at 0.5 m/s) off.
    assert np.abs(skewed - truth)[:, 0].max() > 0.045
    motion = relative_motion(T, scan.T_pipe_sensor(6))
    period_s = float(scan.times_s[6] - scan.times_s[5])
    deskewed = transform(T, deskew_points(f.points_sensor, f.point_time_s, motion, period_s))
    np.testing.assert_allclose(deskewed, truth, atol=1e-5)  # float32 points


def test_times_in_any_base_give_the_same_points(moving_scan):
    scan, frames = moving_scan
    f = frames[2]
    motion = relative_motion(scan.T_pipe_sensor(2), scan.T_pipe_sensor(3))
    a = deskew_points(f.points_sensor, f.point_time_s, motion, 0.1)
    b = deskew_points(f.points_sensor, f.point_time_s + 4.0e8, motion, 0.1)  # GPS seconds
    np.testing.assert_allclose(a, b, atol=1e-6)


def test_registration_and_placing_deskew_to_the_truth(moving_scan):
    """Registered from the odometer's predicted motion, placed by the registered trajectory:
    each point lands within a few mm of its true place; the same frames without their times
    land up to a frame's motion apart (28 mm RMS along the axis)."""
    scan, frames = moving_scan
    times = [f.time_s for f in frames]
    rms_mm = {}
    for timed in (False, True):

        def point_times(f, timed=timed):
            return f.point_time_s if timed else None

        trajectory = register_frames(
            (f.index, f.points_sensor, f.odometer_m, f.gravity, point_times(f), f.time_s)
            for f in frames
        )
        placed = iter_registered_points(
            ((f.index, f.points_sensor, point_times(f)) for f in frames), trajectory, None, times
        )
        err = _along_errors_m(scan, frames, placed)
        rms_mm[timed] = 1e3 * float(np.sqrt(np.mean(err[:, 0] ** 2)))
        if timed:
            p95_mm = 1e3 * float(np.percentile(np.linalg.norm(err, axis=1), 95))
    assert rms_mm[False] > 20.0
    assert rms_mm[True] < 1.5
    assert p95_mm < 5.0


def test_a_frame_without_times_is_unchanged(moving_scan):
    frames = moving_scan[1][:6]
    plain = register_frames((f.index, f.points_sensor, f.odometer_m) for f in frames)
    untimed = register_frames(
        (f.index, f.points_sensor, f.odometer_m, None, None, f.time_s) for f in frames
    )
    np.testing.assert_array_equal(plain.T_world_frame, untimed.T_world_frame)
    times = [f.time_s for f in frames]
    a = list(iter_registered_points(((f.index, f.points_sensor) for f in frames), plain))
    b = list(
        iter_registered_points(
            ((f.index, f.points_sensor, None) for f in frames), plain, None, times
        )
    )
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    still = simulate_scan(_scenario(effects=Effects.ideal()), seed=4)
    assert still.frame(0).point_time_s is None


def _archive(tmp_path, travel_m=0.6):
    from pipescan.simulator.archive import write_simulated_archive

    scan = simulate_scan(_scenario(travel_m=travel_m, points_per_s=100_000), seed=2)
    return scan, write_simulated_archive(scan, tmp_path / "scan")


def test_archive_frames_carry_gps_time_and_the_run_places_them_deskewed(tmp_path):
    """The simulated archive's LAZ frames hold absolute GPS times (about 4 x 10^8 s, another
    base than inspection.toml's); registering and placing the staged frames through the frame
    store puts each point within a few mm of its truth, at a stride of 2 (tracked frames)."""
    from pipescan.storage.input.archive import open_archive
    from pipescan.storage.scratch import FrameStore
    from pipescan.tasks.staged import StagedArchive, register_staged_frames

    scan, root = _archive(tmp_path)
    with open_archive(root) as arc:
        _, _, time_s = next(arc.iter_timed_frames([1]))
        assert time_s is not None and time_s.min() > 3e8 and np.ptp(time_s) < 0.1
        staged = StagedArchive(arc.name, arc.root, arc.meta, "-", arc.frame_count, None)
        store = FrameStore(tmp_path / "store")
        n = arc.frame_count
        trajectory = register_staged_frames(
            staged, 0, n - 1, RegistrationParams(), store, keep_range_m=np.inf, stride=2
        )
        assert trajectory.tracked_indices  # frames between registered ones were tracked
        stored = list(store.iter_timed_frames(0))
        assert all(t is not None for _, _, t in stored)
        times = [f.time_s for f in arc.meta.frames]
        placed = list(iter_registered_points(iter(stored), trajectory, None, times))
    frames = [scan.frame(i) for i in range(n)]
    err = _along_errors_m(scan, frames, placed)
    assert 1e3 * np.sqrt(np.mean(err[:, 0] ** 2)) < 3.0


def test_frame_times_that_are_not_seconds_are_one_clear_error(tmp_path):
    from pipescan.storage.input.archive import open_archive, validate_archive
    from pipescan.storage.input.pointfiles import read_timed_frame, write_points

    _, root = _archive(tmp_path, travel_m=0.2)
    path = root / "frames" / "000002.laz"
    points, time_s = read_timed_frame(path)
    write_points(path, points, time_s=time_s.min() + (time_s - time_s.min()) * 1e9)  # ns
    with open_archive(root) as arc, pytest.raises(PointFileError) as caught:
        list(arc.iter_timed_frames())
    message = str(caught.value)
    assert "frames/000002.laz" in message and "'gps_time'" in message and "\n" not in message
    # Checking the whole archive before anything is processed finds it too.
    with open_archive(root) as arc, pytest.raises(PointFileError, match="gps_time"):
        validate_archive(arc)


def test_a_laz_frame_with_no_or_constant_times_reads_as_untimed(tmp_path):
    from pipescan.storage.input.pointfiles import read_points, read_timed_frame, write_points

    points = np.random.default_rng(0).normal(size=(200, 3)) + np.array([2.0, 0.0, 0.0])
    write_points(tmp_path / "none.laz", points)  # GPS time 0 for every point
    write_points(tmp_path / "same.laz", points, time_s=np.full(200, 4.0e8))
    for name in ("none.laz", "same.laz"):
        got, time_s = read_timed_frame(tmp_path / name)
        assert time_s is None
        np.testing.assert_array_equal(got, read_points(tmp_path / name))
    nan = np.linspace(4.0e8, 4.0e8 + 0.1, 200)
    nan[7] = np.nan
    write_points(tmp_path / "nan.laz", points, time_s=nan)
    with pytest.raises(PointFileError, match="field 'gps_time'"):
        read_timed_frame(tmp_path / "nan.laz", archive="run", member="frames/nan.laz")


def test_frame_store_keeps_times_beside_points(tmp_path):
    from pipescan.storage.scratch import FrameStore

    rng = np.random.default_rng(1)
    store = FrameStore(tmp_path / "frames")
    sent = [
        (3, rng.normal(size=(40, 3)), None),
        (4, rng.normal(size=(50, 3)), 1e9 + rng.uniform(0, 0.1, 50)),
        (5, rng.normal(size=(0, 3)), np.empty(0)),
        (6, rng.normal(size=(30, 3)), None),
    ]
    with store.writer(3) as w:
        for i, pts, t in sent:
            w.add(i, pts, t)
    back = list(store.iter_timed_frames(3))
    assert [i for i, _, _ in back] == [3, 4, 5, 6]
    assert back[0][2] is None and back[2][2] is None and back[3][2] is None
    np.testing.assert_allclose(back[1][2], sent[1][2] - sent[1][2].min(), atol=1e-7)
    assert [i for i, _ in store.iter_frames(3)] == [3, 4, 5, 6]


# --- the unit of a time field, from the frame's own span ------------------------------------


def test_point_times_unit_is_chosen_by_the_frame_span():
    from pipescan.core.registration.deskew import point_times_s

    rng = np.random.default_rng(3)
    true_s = np.sort(rng.uniform(0.0, 0.1, 1000))
    true_s[[0, -1]] = 0.0, 0.0999
    # Velodyne: float32 seconds since the frame's start.
    np.testing.assert_allclose(point_times_s(true_s.astype(np.float32), 0.1), true_s, atol=1e-8)
    # Ouster: uint32 nanoseconds since the frame's start (as seconds it would span 10^8 s).
    ns = np.round(true_s * 1e9).astype(np.uint32)
    np.testing.assert_allclose(point_times_s(ns, 0.1), true_s, atol=1e-9)
    # Livox: float64 absolute nanoseconds (1.7 x 10^18); only differences matter.
    absolute = 1.7e18 + true_s * 1e9
    got = point_times_s(absolute, 0.1)
    np.testing.assert_allclose(got - got.min(), true_s, atol=1e-6)
    assert got.min() == pytest.approx(1.7e9)
    # Milliseconds and microseconds too, as integers.
    np.testing.assert_allclose(
        point_times_s(np.round(true_s * 1e6).astype(np.int64), 0.1), true_s, atol=1e-6
    )
    # A span of just over one interval (within the ratio) keeps the nearest unit.
    np.testing.assert_allclose(point_times_s(np.array([0.0, 0.15]), 0.1), [0.0, 0.15])


def test_point_times_constant_none_and_impossible_spans():
    from pipescan.core.registration.deskew import point_times_s

    assert point_times_s(np.zeros(50, dtype=np.uint32), 0.1) is None
    assert point_times_s(np.full(50, 4.0e8), 0.1) is None
    assert point_times_s(np.empty(0), 0.1) is None
    # 10^13 is over 2 intervals in every unit (10^4 s as nanoseconds).
    with pytest.raises(ValueError, match="every unit"):
        point_times_s(np.array([0, 10**13], dtype=np.uint64), 0.1)
    # LAS GPS time is seconds: nanoseconds in it are refused, not rescaled.
    with pytest.raises(ValueError, match=r"span 1e\+08 s, more than 2 times the 0.1 s between"):
        point_times_s(np.array([0.0, 1e8]), 0.1, units=("s",))
    with pytest.raises(ValueError, match="NaN or infinite"):
        point_times_s(np.array([0.0, np.nan, 0.05]), 0.1)
    with pytest.raises(ValueError, match="not an integer or a float"):
        point_times_s(np.array([True, False]), 0.1)


# --- PCD, PLY and bag frames with their times ----------------------------------------------


def _pcd_with_t_ns(path, points, t_ns):
    """A binary PCD frame whose uint32 field ``t`` is each point's time in ns since the frame's
    start, as an Ouster driver's cloud saved by PCL."""
    header = (
        "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z t\nSIZE 8 8 8 4\nTYPE F F F U\nCOUNT 1 1 1 1\n"
        f"WIDTH {len(points)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(points)}\n"
        "DATA binary\n"
    )
    rows = np.empty(len(points), dtype=[("xyz", "<f8", 3), ("t", "<u4")])
    rows["xyz"], rows["t"] = points, t_ns
    path.write_bytes(header.encode("ascii") + rows.tobytes())


def _replace_frame(root, i, name, write):
    """Frame ``i`` of a simulated archive (LAZ with GPS times) rewritten as ``name`` by
    ``write(path, points, time_s)``; inspection.toml names the new file."""
    from pipescan.storage.input.pointfiles import read_timed_frame

    old = root / "frames" / f"{i:06d}.laz"
    points, time_s = read_timed_frame(old)
    write(root / "frames" / name, points, time_s)
    toml = root / "inspection.toml"
    toml.write_text(toml.read_text().replace(old.name, name), encoding="utf-8")
    old.unlink()
    return points, time_s


def test_pcd_times_in_ns_and_ply_times_in_s_deskew_alike(tmp_path):
    """The same frame as a PCD with Ouster's uint32 ``t`` in ns and as a PLY with float64
    ``time`` in s: through the archive, the same times (s) and the same deskewed points."""
    from pipescan.storage.input.archive import open_archive
    from pipescan.storage.input.pointfiles import read_points, write_points

    _, root = _archive(tmp_path, travel_m=0.2)

    def as_pcd(path, points, time_s):
        _pcd_with_t_ns(path, points, np.round((time_s - time_s.min()) * 1e9).astype(np.uint32))

    points, gps_s = _replace_frame(root, 2, "000002.pcd", as_pcd)
    ply_points, ply_gps_s = _replace_frame(
        root, 3, "000003.ply", lambda p, x, t: write_points(p, x, time_s=t)
    )
    with open_archive(root) as arc:
        got = {i: (pts, t) for i, pts, t in arc.iter_timed_frames([2, 3])}
        period_s = arc.meta.frames[1].time_s - arc.meta.frames[0].time_s
    pcd_pts, pcd_s = got[2]
    np.testing.assert_array_equal(pcd_pts, points)
    np.testing.assert_allclose(pcd_s, gps_s - gps_s.min(), atol=1e-9)
    ply_pts, ply_s = got[3]
    np.testing.assert_array_equal(ply_pts, ply_points)
    np.testing.assert_array_equal(ply_s, ply_gps_s)  # seconds, kept in their own base
    T = np.eye(4)
    T[0, 3] = 0.05
    np.testing.assert_allclose(
        deskew_points(pcd_pts, pcd_s, T, period_s),
        deskew_points(points, gps_s, T, period_s),
        atol=1e-9,
    )
    # A PCD or PLY frame without a time field reads as before, bit for bit.
    for name in ("plain.pcd", "plain.ply"):
        write_points(root / "frames" / name, points)
        from pipescan.storage.input.pointfiles import read_timed_frame

        got_pts, got_t = read_timed_frame(root / "frames" / name, interval_s=period_s)
        assert got_t is None
        np.testing.assert_array_equal(got_pts, read_points(root / "frames" / name))


def test_a_pcd_time_that_fits_no_unit_is_one_error_naming_the_field(tmp_path):
    from pipescan.storage.input.archive import open_archive

    _, root = _archive(tmp_path, travel_m=0.2)

    def far(path, points, time_s):  # 4 s apart as ns, more in any other unit
        t = np.zeros(len(points), dtype=np.uint32)
        t[-1] = 4_000_000_000
        _pcd_with_t_ns(path, points, t)

    _replace_frame(root, 2, "000002.pcd", far)
    with open_archive(root) as arc, pytest.raises(PointFileError) as caught:
        list(arc.iter_timed_frames())
    message = str(caught.value)
    assert "frames/000002.pcd" in message and "field 't'" in message and "\n" not in message


def test_a_bag_with_ouster_t_is_read_with_times_and_deskewed(tmp_path):
    """A bag of the moving scan: PointCloud2 with a uint32 ``t`` (ns since the stamp) goes
    through the archive with each point's time in s, and deskewing it puts the frame's points
    on their truth."""
    from pipescan.simulator.archive import write_simulated_archive
    from pipescan.storage.input.archive import open_archive

    scan = simulate_scan(_scenario(travel_m=0.3), seed=2)
    write_simulated_archive(scan, tmp_path / "arc", layout="bag")
    with open_archive(tmp_path / "arc") as arc:
        got = {i: (pts, t) for i, pts, t in arc.iter_timed_frames([3])}
        plain = dict(arc.iter_frames([3]))
    f = scan.frame(3)
    pts, time_s = got[3]
    np.testing.assert_array_equal(pts, plain[3])
    np.testing.assert_allclose(pts, f.points_sensor, atol=0)
    np.testing.assert_allclose(time_s - time_s.min(), f.point_time_s - f.time_s, atol=1e-9)
    T = scan.T_pipe_sensor(3)
    motion = relative_motion(T, scan.T_pipe_sensor(4))
    period_s = float(scan.times_s[4] - scan.times_s[3])
    deskewed = transform(T, deskew_points(pts, time_s, motion, period_s))
    np.testing.assert_allclose(deskewed, scan.points_pipe(f), atol=1e-5)
    skewed = transform(T, pts)
    assert np.abs(skewed - scan.points_pipe(f))[:, 0].max() > 0.04


def _cloud_msg(points, t, *, datatype=6, count=1, bigendian=False):
    """A PointCloud2 message of float32 x, y, z and a field ``t`` (PointField ``datatype``)."""
    from rosbags.typesys import Stores, get_typestore

    types = get_typestore(Stores.ROS2_HUMBLE).types
    order = ">" if bigendian else "<"
    t_type = {6: "u4", 7: "f4", 8: "f8"}[datatype]
    shape = (count,) if count > 1 else ()
    rows = np.empty(len(points), dtype=[("xyz", order + "f4", 3), ("t", order + t_type, shape)])
    rows["xyz"], rows["t"] = points, t
    field = types["sensor_msgs/msg/PointField"]
    fields = [field(name=a, offset=4 * k, datatype=7, count=1) for k, a in enumerate("xyz")]
    fields.append(field(name="t", offset=12, datatype=datatype, count=count))
    stamp = types["builtin_interfaces/msg/Time"](sec=0, nanosec=0)
    return types["sensor_msgs/msg/PointCloud2"](
        header=types["std_msgs/msg/Header"](stamp=stamp, frame_id="lidar"),
        height=1,
        width=len(points),
        fields=fields,
        is_bigendian=bigendian,
        point_step=rows.itemsize,
        row_step=rows.itemsize * len(points),
        data=rows.view(np.uint8).reshape(-1),
        is_dense=False,
    )


def test_a_pointcloud2_time_follows_its_points_and_is_one_number():
    from pipescan.storage.input.readers.bags import cloud_to_points, cloud_to_timed_points

    points = np.array([[2.0, 0.0, 0.0], [np.nan, 0.0, 0.0], [2.0, 1.0, 0.0], [1.0, 0.0, 0.5]])
    t = np.array([0, 10, 20, 30], dtype=np.uint32)
    for bigendian in (False, True):
        msg = _cloud_msg(points, t, bigendian=bigendian)
        got, time, field = cloud_to_timed_points(msg)
        assert field == "t" and time.dtype == np.uint32 and time.tolist() == [0, 20, 30]
        np.testing.assert_array_equal(got, points[[0, 2, 3]])
        np.testing.assert_array_equal(cloud_to_points(msg), got)  # without times: the same
    with pytest.raises(ValueError, match=r"time field t .* not one number per point"):
        cloud_to_timed_points(_cloud_msg(points, np.zeros((4, 2)), datatype=8, count=2))


def test_a_pcd_time_field_of_two_numbers_is_an_error_naming_it(tmp_path):
    from pipescan.storage.input.pointfiles import read_timed_frame

    header = (
        "VERSION 0.7\nFIELDS x y z t\nSIZE 4 4 4 4\nTYPE F F F U\nCOUNT 1 1 1 2\nWIDTH 2\n"
        "HEIGHT 1\nPOINTS 2\nDATA ascii\n"
    )
    (tmp_path / "f.pcd").write_text(header + "2 0 0 0 0\n2 1 0 5 0\n", encoding="ascii")
    with pytest.raises(PointFileError, match=r"field 't'.*COUNT 2") as caught:
        read_timed_frame(tmp_path / "f.pcd", interval_s=0.1, archive="a", member="frames/f.pcd")
    assert "frames/f.pcd" in str(caught.value)


def test_a_bag_without_time_fields_reads_as_before(tmp_path):
    from pipescan.simulator.archive import write_simulated_archive
    from pipescan.storage.input.archive import open_archive

    scan = simulate_scan(get_scenario("paper", travel_m=0.3), seed=0)
    write_simulated_archive(scan, tmp_path / "arc", layout="bag")
    with open_archive(tmp_path / "arc") as arc:
        timed = list(arc.iter_timed_frames([1, 2]))
        plain = list(arc.iter_frames([1, 2]))
    for (i, pts, time_s), (j, expected) in zip(timed, plain, strict=True):
        assert i == j and time_s is None
        np.testing.assert_array_equal(pts, expected)


def test_the_survey_reads_the_instrument_from_deskewed_frames(tmp_path):
    """A frame's motion reads as range noise: at 0.5 m/s the moving scan's frames as read
    show 2.7 mm where the same scan without motion shows 2.2. The survey deskews them by the
    odometer's travel and reads much nearer the still scan's figure."""
    import dataclasses

    from pipescan.core.instrument import consecutive_frame_indices, estimate_instrument
    from pipescan.core.registration import sample_frame_indices
    from pipescan.simulator.archive import write_simulated_archive
    from pipescan.storage.input.archive import open_archive
    from pipescan.tasks.inspection import survey_scan
    from pipescan.tasks.staged import StagedArchive

    noise = {}
    for moving in (True, False):
        scenario = _scenario(travel_m=0.6)
        effects = dataclasses.replace(scenario.effects, motion_within_frame=moving)
        scan = simulate_scan(dataclasses.replace(scenario, effects=effects), seed=2)
        root = write_simulated_archive(scan, tmp_path / f"moving-{moving}")
        with open_archive(root) as arc:
            n = arc.frame_count
            staged = StagedArchive(arc.name, arc.root, arc.meta, "-", n, None)
            survey = survey_scan.fn(
                staged, max_range_m=5.0, step_m=0.1, section_points=20_000, keyframe_distance_m=0.15
            )
            sample, run = sample_frame_indices(n), consecutive_frame_indices(n)
            read = dict(arc.iter_frames(sorted(set(sample) | set(run))))
            as_read = estimate_instrument(
                [read[i] for i in sample], [read[i] for i in run], max_range_m=5.0
            )
        noise[moving] = (survey.instrument.range_noise_m, as_read.range_noise_m)
    still = noise[False][0]
    assert noise[False][1] == pytest.approx(still)  # nothing to deskew: the same frames
    deskewed, as_read = noise[True]
    assert as_read - still > 0.3e-3  # the motion shows as noise...
    assert deskewed - still < 0.6 * (as_read - still)  # ...and the survey takes most of it out
