"""Debris of killed runs is swept at the next run's start, and only that: a run directory whose
owner process is gone (by id and start time, on this host), and the Prefect API server such a
run had started. A user's folder, a live run, another host's run and links are left alone."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from pipescan.flows.housekeeping import PREFECT_SERVER_APP, start_run_dir
from pipescan.storage.scratch import (
    RUN_MARKER,
    ProcessRef,
    RunOwner,
    create_run_dir,
    sweep_stale_runs,
)


def _sleeper(*extra: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-c", "import time; time.sleep(120)", *extra],
        stdout=subprocess.DEVNULL,
    )


@pytest.fixture
def dead_owner() -> ProcessRef:
    """A process that ran and is gone."""
    proc = _sleeper()
    ref = ProcessRef.of(proc.pid)
    proc.kill()
    proc.wait(timeout=30)
    assert not ref.is_running()
    return ref


def _run_dir(work: Path, name: str, owner: RunOwner) -> Path:
    run = work / name
    run.mkdir(parents=True)
    (run / RUN_MARKER).write_text(owner.to_json(), encoding="utf-8")
    (run / "buckets").mkdir()
    (run / "buckets" / "w.npy").write_bytes(b"\0" * 1000)
    return run


def test_only_the_runs_of_dead_owners_on_this_host_are_swept(tmp_path, dead_owner) -> None:
    work = tmp_path / "work"
    host = socket.gethostname()
    killed = _run_dir(work, "run-killed", RunOwner(dead_owner, host))
    live = create_run_dir(work)  # this process: alive
    elsewhere = _run_dir(work, "run-other-host", RunOwner(dead_owner, host + "-other"))
    # An earlier process that had this process's id: its id is taken, but it is gone.
    me = ProcessRef.of(os.getpid())
    reused = _run_dir(work, "run-pid-reused", RunOwner(ProcessRef(me.pid, me.started - 3600), host))
    users = work / "my-scan"
    users.mkdir()
    (users / "inspection.toml").write_text("asset_id = 'A'")
    outside = _run_dir(tmp_path / "elsewhere", "run-linked", RunOwner(dead_owner, host))
    (work / "link-to-a-dead-run").symlink_to(outside, target_is_directory=True)
    fake_marker = work / "run-fake-marker"
    fake_marker.mkdir()
    (fake_marker / RUN_MARKER).symlink_to(killed / RUN_MARKER)

    swept = sweep_stale_runs(work)

    assert swept.removed == (killed, reused)
    assert not killed.exists() and not reused.exists()
    for kept in (live, elsewhere, users, outside, fake_marker):
        assert kept.exists(), kept
    assert (users / "inspection.toml").read_text() == "asset_id = 'A'"
    assert sweep_stale_runs(tmp_path / "no-such-dir").removed == ()


def test_a_process_id_given_to_a_later_process_is_not_the_same_process(dead_owner) -> None:
    me = ProcessRef.of(os.getpid())
    assert me.is_running()
    assert not ProcessRef(me.pid, me.started - 3600).is_running()


def test_the_api_server_of_a_killed_run_is_stopped(tmp_path, dead_owner) -> None:
    server = _sleeper("--factory", PREFECT_SERVER_APP)  # looks like Prefect's API server
    bystander = _sleeper("--not-a-server")
    try:
        helpers = (ProcessRef.of(server.pid), ProcessRef.of(bystander.pid))
        work = tmp_path / "work"
        killed = _run_dir(work, "run-killed", RunOwner(dead_owner, socket.gethostname(), helpers))
        run = start_run_dir(work)
        assert server.wait(timeout=30) is not None  # stopped
        assert bystander.poll() is None  # recorded, but not a Prefect server: left running
        assert not killed.exists() and (run / RUN_MARKER).is_file()
        assert sorted(p.name for p in work.iterdir()) == [run.name]
    finally:
        for proc in (server, bystander):
            proc.kill()
            proc.wait(timeout=30)
