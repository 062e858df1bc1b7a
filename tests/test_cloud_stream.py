"""A registered cloud is read in one pass, a chunk at a time: the chunks are the file, the
checks still hold, and the axis and the sections come from a stride through the cloud, so
memory does not grow with it."""

from __future__ import annotations

import logging
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipescan.core.errors import PointFileError
from pipescan.simulator.archive import write_simulated_archive
from pipescan.simulator.scan import get_scenario, simulate_scan
from pipescan.storage.input import archive as archive_module
from pipescan.storage.input import pointfiles
from pipescan.storage.input.pointfiles import (
    MM_HINT,
    StridedSample,
    iter_point_chunks,
    read_point_time,
    read_points,
    write_points,
)
from pipescan.storage.input.readers import READERS
from pipescan.storage.scratch import FrameStore, create_run_dir
from pipescan.tasks import inspection
from pipescan.tasks.inspection import bucket_points, fit_pipe_axis
from pipescan.tasks.storing import stage_archive


def _cloud(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A georeferenced 0.5 m pipe wall along x, and a time that runs along it."""
    rng = np.random.default_rng(seed)
    x = np.sort(rng.uniform(0.0, 6.0, n))
    angle = rng.uniform(0.0, 2 * np.pi, n)
    points = np.column_stack((x, 0.25 * np.cos(angle), 0.25 * np.sin(angle)))
    return points + np.array([512_000.0, 6_170_000.0, 40.0]), x / 0.15


@pytest.mark.parametrize("suffix", [".laz", ".las", ".e57", ".npy", ".ply", ".xyz", ".pcd"])
@pytest.mark.parametrize("chunk_points", [1, 333, 5000])
def test_the_chunks_are_the_file_in_order(tmp_path: Path, suffix: str, chunk_points: int):
    """LAS, LAZ, E57, binary PLY, ASCII and ``.npy`` stream; PCD is read whole and handed out
    in chunks: the same points and times as reading the file whole, in the same order."""
    points, time_s = _cloud(2000)
    timed = READERS[suffix].read_time is not None
    path = tmp_path / f"cloud{suffix}"
    write_points(path, points, time_s=time_s if timed else None)
    chunks = list(iter_point_chunks(path, chunk_points=chunk_points, with_time=True))
    assert all(len(c.points) <= chunk_points for c in chunks)
    assert [c.first for c in chunks] == list(np.cumsum([0] + [len(c.points) for c in chunks]))[:-1]
    whole = read_points(path, kind="cloud")
    assert np.array_equal(np.concatenate([c.points for c in chunks]), whole)
    if timed:
        assert np.array_equal(np.concatenate([c.time_s for c in chunks]), read_point_time(path))
    else:
        assert all(c.time_s is None for c in chunks)
    plain = list(iter_point_chunks(path, chunk_points=chunk_points))
    assert all(c.time_s is None for c in plain)


def test_a_fortran_ordered_npy_streams_as_it_reads(tmp_path: Path):
    points, _ = _cloud(1000)
    path = tmp_path / "cloud.npy"
    np.save(path, np.asfortranarray(points.astype(np.float32)))
    chunks = [c.points for c in iter_point_chunks(path, chunk_points=300)]
    assert [len(c) for c in chunks] == [300, 300, 300, 100]
    assert np.array_equal(np.concatenate(chunks), read_points(path, kind="cloud"))


@pytest.mark.parametrize("fmt", ["ascii", "binary_big_endian"])
def test_ascii_and_big_endian_ply_chunks_are_the_file(tmp_path: Path, fmt: str):
    points, time_s = _cloud(700)
    rows = np.column_stack((points, time_s)).astype(">f8")
    header = (
        f"ply\nformat {fmt} 1.0\nelement vertex {len(rows)}\nproperty double x\n"
        "property double y\nproperty double z\nproperty double timestamp\nend_header\n"
    )
    path = tmp_path / "cloud.ply"
    with path.open("wb") as fh:
        fh.write(header.encode("ascii"))
        if fmt == "ascii":
            np.savetxt(fh, rows.astype(np.float64), fmt="%.17g")
        else:
            fh.write(rows.tobytes())
    chunks = list(iter_point_chunks(path, chunk_points=300, with_time=True))
    assert [len(c.points) for c in chunks] == [300, 300, 100]
    assert np.array_equal(
        np.concatenate([c.points for c in chunks]), read_points(path, kind="cloud")
    )
    assert np.array_equal(np.concatenate([c.time_s for c in chunks]), read_point_time(path))
    np.testing.assert_array_equal(np.concatenate([c.time_s for c in chunks]), time_s)


def test_ascii_chunks_skip_headers_and_comments_and_name_a_bad_line(tmp_path: Path):
    points, _ = _cloud(500)
    lines = ["X,Y,Z,intensity", "# exported"]
    for k, (x, y, z) in enumerate(points):
        lines.append(f"{x:.17g},{y:.17g},{z:.17g},7")
        if k % 97 == 0:
            lines += ["// a comment", ""]
    path = tmp_path / "cloud.txt"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "input contained no data" for a comments-only block
        chunks = [c.points for c in iter_point_chunks(path, chunk_points=2)]
    assert max(len(c) for c in chunks) <= 2
    assert np.array_equal(np.concatenate(chunks), read_points(path, kind="cloud"))
    assert np.array_equal(np.concatenate(chunks), points)
    lines[400] = "1.0,oops,2.0,7"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    bad_line = lines.index("1.0,oops,2.0,7") + 1
    expected = rf"cannot read x y z rows at line {bad_line}: "
    with pytest.raises(PointFileError, match=expected) as info:
        list(iter_point_chunks(path, member="cloud.txt", chunk_points=64))
    assert info.value.file == "cloud.txt"


def test_an_e57_of_several_posed_scans_streams_as_it_reads(tmp_path: Path):
    """Each scan is placed by its own pose, chunk by chunk; times add each scan's start."""
    from scipy.spatial.transform import Rotation

    from pipescan.storage.input.readers import e57

    points, time_s = _cloud(2500)
    rotation = Rotation.from_euler("z", 35, degrees=True)
    translation = np.array([10.0, -3.0, 1.5])
    x, y, z, w = rotation.as_quat()
    local = rotation.inv().apply(points[1000:] - translation)
    path = tmp_path / "cloud.e57"
    pose = (np.array([w, x, y, z]), translation)
    e57.write_scans(path, [(points[:1000], time_s[:1000], None), (local, time_s[1000:], pose)])
    chunks = list(iter_point_chunks(path, chunk_points=400, with_time=True))
    assert [len(c.points) for c in chunks] == [400, 400, 200, 400, 400, 400, 300]
    assert np.array_equal(
        np.concatenate([c.points for c in chunks]), read_points(path, kind="cloud")
    )
    assert np.array_equal(np.concatenate([c.time_s for c in chunks]), read_point_time(path))
    np.testing.assert_allclose(np.concatenate([c.points for c in chunks]), points, atol=1e-6)


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(1, 3000),
    limit=st.integers(1, 400),
    cuts=st.lists(st.integers(1, 500), min_size=1, max_size=40),
)
def test_a_strided_sample_is_every_stride_th_row_and_at_most_the_limit(n, limit, cuts):
    rows = np.arange(n)
    times = rows * 0.1
    sample = StridedSample(limit)
    first, k = 0, 0
    while first < n:
        size = cuts[k % len(cuts)]
        sample.add(first, rows[first : first + size], times[first : first + size], None)
        first, k = first + size, k + 1
    kept, kept_time, none = sample.columns()
    assert none is None
    s = sample.stride
    assert s & (s - 1) == 0  # a power of two
    assert np.array_equal(kept, rows[::s]) and np.array_equal(kept_time, times[::s])
    assert len(kept) <= limit
    assert s == 1 or len(rows[:: s // 2]) > limit  # the smallest stride that fits


def test_a_bad_time_in_a_later_chunk_names_the_field_and_the_rows(tmp_path: Path):
    points, time_s = _cloud(2000)
    time_s[1700] = np.nan
    path = tmp_path / "cloud.laz"
    write_points(path, points, time_s=time_s)
    chunks = iter_point_chunks(path, archive="run.zip", member="cloud.laz", chunk_points=500,
                               with_time=True)  # fmt: skip
    assert len(next(chunks).points) == 500
    with pytest.raises(PointFileError, match=r"1 of the points in rows 1,500-1,999") as info:
        list(chunks)
    assert info.value.field == "time" and info.value.file == "cloud.laz"


def test_a_millimetre_cloud_fails_after_its_last_chunk_and_leaves_no_cloud(tmp_path: Path):
    points, _ = _cloud(3000)
    path = tmp_path / "cloud.las"
    write_points(path, points * 1000.0)
    store = FrameStore(tmp_path / "frames")
    chunks = (c.points for c in iter_point_chunks(path, member="cloud.las", chunk_points=700))
    with pytest.raises(PointFileError, match="across its second principal axis") as info:
        store.save_cloud(chunks)
    assert MM_HINT in str(info.value)
    assert store.cloud_rows() == 0
    assert sorted(p.name for p in (tmp_path / "frames").iterdir()) == []


@pytest.fixture(scope="module")
def cloud_archive(tmp_path_factory) -> Path:
    scan = simulate_scan(get_scenario("paper", travel_m=1.0, points_per_s=150_000), seed=0)
    out = tmp_path_factory.mktemp("cloud") / "arc"
    return write_simulated_archive(scan, out, layout="cloud")


def _fit(archive: Path, tmp_path: Path, name: str):
    staged = stage_archive.fn(str(archive), create_run_dir(tmp_path / name))
    store = FrameStore(tmp_path / name / "frames")
    fit = fit_pipe_axis.fn(staged, None, max_range_m=5.0, frame_store=store)
    return staged, store, fit


def test_a_cloud_is_read_once_in_chunks_and_its_axis_fitted_on_a_stride(
    cloud_archive: Path, tmp_path: Path, monkeypatch, caplog
):
    """The axis task never reads the cloud whole; it keeps the cloud for the sections, row for
    row. A stride through it, a quarter to an eighth of the cloud, places every point within
    two millimetres of where the whole cloud (within the default sample) places it."""
    _, whole_store, whole = _fit(cloud_archive, tmp_path, "whole")
    n = whole_store.cloud_rows()
    assert n > 400_000  # in many chunks

    def refuse(*args, **kwargs):
        raise AssertionError("the cloud was read whole")

    monkeypatch.setattr(archive_module, "read_points", refuse)
    monkeypatch.setattr(archive_module, "read_point_time", refuse)
    monkeypatch.setattr(pointfiles, "CLOUD_CHUNK_POINTS", 50_000)
    monkeypatch.setattr(inspection, "CLOUD_SAMPLE_POINTS", n // 4)
    monkeypatch.setattr(inspection, "CLOUD_PROGRESS_POINTS", 200_000)
    caplog.clear()  # the lines of the first fit, where an earlier test let INFO through
    with caplog.at_level(logging.INFO, logger="pipescan"):
        staged, store, fit = _fit(cloud_archive, tmp_path, "strided")
    progress = [r.getMessage() for r in caplog.records if r.name == "pipescan"]
    assert progress[:2] == ["read 200,000 points of the cloud", "read 400,000 points of the cloud"]
    assert progress[-1] == f"read the cloud: {n:,} points; its axis comes from 1 point in 8"
    assert store.cloud_rows() == n
    assert np.array_equal(store.read_cloud_rows(0, n), whole_store.read_cloud_rows(0, n))
    assert fit.start_source == whole.start_source == "point_time"
    assert abs(fit.axis.direction @ whole.axis.direction) > np.cos(1e-3)
    sample = whole_store.read_cloud_rows(0, n)[::997]
    shift_m = fit.axis.chainage(sample) - whole.axis.chainage(sample)
    print(f"chainage shift {np.abs(shift_m).max() * 1e3:.2f} mm, ends "
          f"{(fit.chainage_min_m - whole.chainage_min_m) * 1e3:+.2f} / "
          f"{(fit.chainage_max_m - whole.chainage_max_m) * 1e3:+.2f} mm")  # fmt: skip
    assert np.abs(shift_m).max() < 2e-3  # 2 % of a section: 0.86 mm here
    assert fit.chainage_min_m == pytest.approx(whole.chainage_min_m, abs=5e-3)
    assert fit.chainage_max_m == pytest.approx(whole.chainage_max_m, abs=5e-3)
    placed = bucket_points.fn(staged, None, 0, n, fit.axis, [], tmp_path / "b", 5.0, None)
    assert placed.points == 0  # no windows: read through in chunks, nothing placed


def test_the_simulator_writes_a_laz_cloud_without_holding_it(tmp_path: Path):
    """``pipescan simulate --layout cloud`` spools the frames and writes the LAZ a chunk at a
    time: the same points and times, decoded, as writing the whole cloud at once."""
    from pipescan.simulator.archive import world_cloud

    scan = simulate_scan(get_scenario("paper", travel_m=0.4, points_per_s=100_000), seed=3)
    archive = write_simulated_archive(scan, tmp_path / "arc", layout="cloud")
    points, time_s = world_cloud(scan)
    write_points(tmp_path / "whole.laz", points, time_s=time_s)
    streamed = archive / "cloud.laz"
    assert np.array_equal(read_points(streamed, kind="cloud"),
                          read_points(tmp_path / "whole.laz", kind="cloud"))  # fmt: skip
    assert np.array_equal(read_point_time(streamed), read_point_time(tmp_path / "whole.laz"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["arc", "whole.laz"]  # no spool left
