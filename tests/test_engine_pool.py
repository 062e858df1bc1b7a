"""The engine pool: chunks registered in lean worker processes, with the results, the errors
and the lifetime of a call made in the flow's own process."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from pipescan.core.errors import PointFileError
from pipescan.flows.runners import limit_library_threads
from pipescan.tasks import enginepool


def _raise_point_file_error(file: str) -> None:
    raise PointFileError("truncated: 12 of 24 bytes", archive="scan.zip", file=file)


def test_a_call_runs_in_another_process_and_returns_its_result():
    assert enginepool.run(2, os.getpid) != os.getpid()
    assert enginepool.pool_size() == 2


def test_an_error_comes_back_as_raised_with_its_file():
    with pytest.raises(PointFileError) as caught:
        enginepool.run(2, _raise_point_file_error, "frames/000007.laz")
    assert caught.value.file == "frames/000007.laz"
    assert str(caught.value) == (
        "archive scan.zip, file frames/000007.laz: truncated: 12 of 24 bytes"
    )


def test_a_dying_worker_is_replaced_and_its_call_tried_once_more():
    before = enginepool.run(2, os.getpid)
    with pytest.raises(RuntimeError, match="died twice"):
        enginepool.run(2, os._exit, 9)
    after = enginepool.run(2, os.getpid)  # a new pool, new workers
    assert after != before
    assert enginepool.pool_size() == 2


def test_workers_do_not_outlive_a_killed_parent(tmp_path):
    script = textwrap.dedent(
        """
        import os, sys
        from pipescan.tasks import enginepool
        for f in enginepool.prestart(2):
            f.result()
        print("ready", flush=True)
        sys.stdin.read()
        """
    )
    parent = subprocess.Popen(
        [sys.executable, "-c", script],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        assert parent.stdout.readline().strip() == "ready"
        # Both workers, started by prestart before any work, and multiprocessing's tracker.
        workers = _children(parent.pid)
        assert sum("resource_tracker" not in _cmdline(p) for p in workers) == 2
        assert all(_alive(p) for p in workers)
        parent.send_signal(signal.SIGKILL)
        parent.wait(timeout=10)
        deadline = time.monotonic() + 10
        while any(_alive(p) for p in workers) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert not any(_alive(p) for p in workers)
    finally:
        parent.kill()


def _children(pid: int) -> list[int]:
    found: list[int] = []
    for task in os.listdir(f"/proc/{pid}/task"):
        with open(f"/proc/{pid}/task/{task}/children") as fh:
            found += [int(c) for c in fh.read().split()]
    return found


def _cmdline(pid: int) -> str:
    with open(f"/proc/{pid}/cmdline", "rb") as fh:
        return fh.read().decode(errors="replace")


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().split(")")[-1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_relative_paths_mean_what_they_mean_to_the_caller(tmp_path, monkeypatch):
    (tmp_path / "inputs").mkdir()
    monkeypatch.chdir(tmp_path)
    assert enginepool.run(2, os.path.abspath, "inputs") == str(tmp_path / "inputs")


def test_staging_starts_the_workers_for_frames_and_not_for_a_cloud(tmp_path, monkeypatch):
    from pipescan.simulator.archive import write_simulated_archive
    from pipescan.simulator.scan import get_scenario, simulate_scan
    from pipescan.storage.scratch import create_run_dir
    from pipescan.tasks.storing import stage_archive

    started: list[int] = []
    monkeypatch.setattr(enginepool, "prestart", started.append)
    frames = simulate_scan(get_scenario("paper", travel_m=0.3), seed=0)
    cloud = simulate_scan(get_scenario("ring", travel_m=0.5), seed=0)  # one registered cloud
    for scan, name, expected in ((frames, "frames", [2]), (cloud, "cloud", [2])):
        root = write_simulated_archive(scan, tmp_path / name)
        staged = stage_archive.fn(str(root), create_run_dir(tmp_path / "work"), engine_processes=2)
        assert (staged.frame_count > 0) == (name == "frames")
        assert started == expected  # started for the frames; the cloud starts nothing more
    stage_archive.fn(str(tmp_path / "frames"), create_run_dir(tmp_path / "work"))
    assert started == [2]  # and only when asked


def _library_threads() -> dict[str, set[int]]:
    import open3d  # noqa: F401  (OpenMP is loaded with the engines)
    import small_gicp  # noqa: F401
    from threadpoolctl import threadpool_info

    threads: dict[str, set[int]] = {}
    for pool in threadpool_info():
        threads.setdefault(pool["user_api"], set()).add(pool["num_threads"])
    return threads


def test_workers_started_after_the_library_limit_keep_to_it(monkeypatch):
    """A run limits BLAS and OpenMP in its own process and in the engine workers it starts
    after."""
    from threadpoolctl import threadpool_limits

    for name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):
        monkeypatch.setenv(name, "2")  # a user's environment; restored after
    enginepool.shutdown()
    try:
        with threadpool_limits(limits=2):
            before = enginepool.run(1, _library_threads)
            assert before == {"blas": {2}, "openmp": {2}}  # the limit is not inherited
            enginepool.shutdown()
            limit_library_threads(1)
            assert _library_threads() == {"blas": {1}, "openmp": {1}}
            assert enginepool.run(1, _library_threads) == {"blas": {1}, "openmp": {1}}
    finally:
        enginepool.shutdown()


def test_a_pool_started_ahead_stops_again_only_if_nothing_ran_on_it():
    enginepool.shutdown()
    enginepool.prestart(2, ahead=True)
    assert enginepool.pool_size() == 2
    enginepool.release_unused()
    assert enginepool.pool_size() == 0
    enginepool.prestart(2, ahead=True)
    enginepool.run(2, os.getpid)
    enginepool.release_unused()
    assert enginepool.pool_size() == 2  # it did work: kept for the next run
    enginepool.prestart(2, ahead=True)  # already running: not "ahead" any more
    enginepool.release_unused()
    assert enginepool.pool_size() == 2


def test_the_command_line_starts_the_workers_ahead_and_a_cloud_stops_them(tmp_path):
    """``pipescan inspect`` starts the engine workers before Prefect's API; a registered
    cloud, which registers nothing, stops them again, and frames keep them."""
    from typer.testing import CliRunner

    from pipescan.cli import app
    from pipescan.simulator.archive import write_simulated_archive
    from pipescan.simulator.scan import get_scenario, simulate_scan

    db = f"sqlite:///{tmp_path / 'p.db'}"
    cloud = write_simulated_archive(
        simulate_scan(get_scenario("ring", travel_m=0.5), seed=0), tmp_path / "cloud"
    )
    frames = write_simulated_archive(
        simulate_scan(get_scenario("paper", travel_m=0.3), seed=0), tmp_path / "frames"
    )
    enginepool.shutdown()
    started: list[bool] = []
    real_prestart = enginepool.prestart

    def prestart(workers, *, ahead=False):
        started.append(ahead)
        return real_prestart(workers, ahead=ahead)

    runner = CliRunner()
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(enginepool, "prestart", prestart)
        result = runner.invoke(app, ["inspect", str(cloud), "--db", db])
        assert result.exit_code == 0, result.output
        assert started == [True]  # ahead, by the command line; staging a cloud starts none
        assert enginepool.pool_size() == 0
        result = runner.invoke(app, ["inspect", str(frames), "--db", db])
        assert result.exit_code == 0, result.output
        assert started == [True, True, False]  # and staging the frames finds it running
        assert enginepool.pool_size() == 2


def test_a_window_measured_in_a_worker_is_the_window_measured_here(tmp_path):
    """The measure-window task hands its window to a worker process where registration ran
    there: the same sections, field by field, as measured in the flow's own process."""
    import dataclasses

    import numpy as np

    from pipescan.core.axis import fit_axis
    from pipescan.core.measures import MeasureParams
    from pipescan.core.sections import plan_windows
    from pipescan.storage.scratch import write_buckets
    from pipescan.tasks.staged import measure_placed_window

    rng = np.random.default_rng(7)
    s = rng.uniform(0.0, 2.0, 200_000)
    theta = rng.uniform(0, 2 * np.pi, s.size)
    r = np.where((s > 0.8) & (s < 1.1) & (np.sin(theta) > 0.8), 0.2, 0.25)  # a crown obstacle
    points = np.column_stack((s, r * np.cos(theta), r * np.sin(theta)))
    points += rng.normal(scale=0.002, size=points.shape)
    axis = fit_axis(points, start_m=np.zeros(3), travel_m=np.array([2.0, 0.0, 0.0]))
    window = plan_windows(0.0, 2.0, step_m=0.1, window_m=2.0)[0]
    write_buckets(points, axis, [window], tmp_path, "chunk_0000000")
    args = (tmp_path, window, axis, 0.5, MeasureParams())
    here, read_here = measure_placed_window(*args)
    there, read_there = enginepool.run(1, measure_placed_window, *args)
    assert read_here == read_there > 0.95 * len(points)
    assert any(sec.is_ok for sec in here)
    assert len(here) == len(there) == 20
    for a, b in zip(here, there, strict=True):
        for field in dataclasses.fields(a):
            x, y = getattr(a, field.name), getattr(b, field.name)
            if isinstance(x, np.ndarray):
                np.testing.assert_array_equal(x, y)
            else:
                assert x == y, (a.chainage_start_m, field.name)
