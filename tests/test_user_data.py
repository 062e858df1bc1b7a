"""A user's scan is never moved, changed or deleted: not by a run, a failed run or a killed run.

Every form an archive can be given in is tried: a directory (absolute and relative path, and as a
``file://`` URL), a symlink to a directory, a ``.zip``, ``.tar`` and ``.tar.gz`` (as paths and as
``file://`` URLs), and a ``memory://`` URL. Each input is fingerprinted before and after, byte for
byte, with its file modes and link targets.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import signal
import subprocess
import sys
import tarfile
import textwrap
import zipfile
from collections.abc import Callable
from pathlib import Path

import fsspec
import pytest
from prefect.testing.utilities import prefect_test_harness

from pipescan.flows.housekeeping import start_run_dir
from pipescan.flows.inspect import InspectionParams, inspect_archive
from pipescan.simulator.archive import write_simulated_archive
from pipescan.simulator.scan import get_scenario, simulate_scan
from pipescan.storage.scratch import RUN_MARKER, create_run_dir, remove_workspace

MEMORY_URL = "memory://pipescan-user-data/run.zip"


def fingerprint(path: Path) -> dict[str, tuple]:
    """Every entry under ``path`` (or ``path`` itself): kind, mode, bytes' hash, link target."""
    entries: dict[str, tuple] = {}
    top = Path(path)
    walk = [top] + (sorted(top.rglob("*")) if top.is_dir() and not top.is_symlink() else [])
    for p in walk:
        key = p.relative_to(top).as_posix()
        st = p.lstat()
        if p.is_symlink():
            entries[key] = ("link", os.readlink(p))
        elif p.is_dir():
            entries[key] = ("dir", st.st_mode)
        else:
            entries[key] = ("file", st.st_mode, hashlib.sha256(p.read_bytes()).hexdigest())
    return entries


def _zip(src: Path, dst: Path) -> Path:
    with zipfile.ZipFile(dst, "w", zipfile.ZIP_DEFLATED) as zf:
        for p in sorted(src.rglob("*")):
            if p.is_file():
                zf.write(p, p.relative_to(src).as_posix())
    return dst


def _tar(src: Path, dst: Path, mode: str) -> Path:
    with tarfile.open(dst, mode) as tf:
        tf.add(src, arcname=".")
    return dst


@pytest.fixture(scope="module")
def source(tmp_path_factory) -> Path:
    """A small but real simulated archive (frames, odometer, IMU), as a directory."""
    scan = simulate_scan(get_scenario("paper", travel_m=0.6, points_per_s=60_000), seed=3)
    return write_simulated_archive(scan, tmp_path_factory.mktemp("src") / "scan")


def input_forms(source: Path, where: Path) -> dict[str, tuple[str, Path]]:
    """Each form of input: ``name -> (what is passed to pipescan, the path to fingerprint)``."""
    where.mkdir(parents=True, exist_ok=True)
    folder = where / "folder"
    shutil.copytree(source, folder, symlinks=True)
    link_target = where / "linked-target"
    shutil.copytree(source, link_target, symlinks=True)
    link = where / "linked"
    link.symlink_to(link_target, target_is_directory=True)
    packed = {
        "zip": _zip(source, where / "run.zip"),
        "tar": _tar(source, where / "run.tar", "w"),
        "tar.gz": _tar(source, where / "run.tar.gz", "w:gz"),
    }
    forms: dict[str, tuple[str, Path]] = {
        "directory": (str(folder.resolve()), folder),
        "directory, relative": (os.path.relpath(folder), folder),
        "directory, file:// URL": (folder.resolve().as_uri(), folder),
        "directory, file:// URL with a trailing slash": (folder.resolve().as_uri() + "/", folder),
        "symlinked directory": (str(link), link_target),
        "symlinked directory, file:// URL": (link.absolute().as_uri(), link_target),
    }
    forms["zip, relative"] = (os.path.relpath(packed["zip"]), packed["zip"])
    for kind, path in packed.items():
        forms[kind] = (str(path), path)
        forms[f"{kind}, file:// URL"] = (path.resolve().as_uri(), path)
    return forms


@pytest.fixture
def memory_archive(source: Path) -> Callable[[], dict]:
    """The archive as a zip at a ``memory://`` URL; returns a fingerprint of its bytes."""
    fs = fsspec.filesystem("memory")
    data = _zip(source, source.parent / "mem.zip").read_bytes()
    with fs.open(MEMORY_URL, "wb") as fh:
        fh.write(data)

    def snapshot() -> dict:
        return {path: hashlib.sha256(fs.cat(path)).hexdigest() for path in fs.find("/")}

    yield snapshot
    fs.rm("memory://pipescan-user-data", recursive=True)


@pytest.fixture(scope="module")
def prefect():
    with prefect_test_harness(server_startup_timeout=60):
        yield


@pytest.mark.e2e
@pytest.mark.parametrize("outcome", ["ok", "failed"])
def test_runs_leave_every_input_form_unchanged(
    prefect, source, memory_archive, tmp_path, monkeypatch, outcome
) -> None:
    monkeypatch.chdir(tmp_path)
    forms = input_forms(source, tmp_path / "inputs")
    before = {name: fingerprint(path) for name, (_, path) in forms.items()}
    memory_before = memory_archive()
    work = tmp_path / "work"
    # A run that fails after the archive was staged: its database cannot be created, so the
    # first look at it (reuse_stored) fails, a deterministic error that is not retried.
    db = (
        f"sqlite:///{tmp_path / 'pipescan.db'}"
        if outcome == "ok"
        else "sqlite:////proc/pipescan-no-such-dir/x.db"
    )
    monkeypatch.setenv("PIPESCAN_DATABASE_URL", db)
    params = InspectionParams(chunk_frames=200)
    for name, (given, _) in [*forms.items(), ("memory://", (MEMORY_URL, None))]:
        if outcome == "ok":
            summary = inspect_archive(archive=given, params=params, work_dir=str(work))
            assert summary.section_count > 0, name
        else:
            with pytest.raises(Exception):  # noqa: B017 - any failure; what matters is below
                inspect_archive(
                    archive=given,
                    params=params,
                    work_dir=str(work),
                    reuse_stored=True,
                )
        assert list(work.iterdir()) == [], f"{name}: the run's scratch space was left behind"
    for name, (_, path) in forms.items():
        assert path.exists(), f"{name}: the input is gone"
        assert fingerprint(path) == before[name], f"{name}: the input was changed"
    assert memory_archive() == memory_before


def test_a_killed_run_leaves_every_input_form_unchanged(source, tmp_path, monkeypatch) -> None:
    """SIGKILL a process after it staged every form (extracted or used in place): no input
    moved or changed. The staging task is what touches the input; the kill lands while the
    staged content is held, as a run killed mid-registration would."""
    monkeypatch.chdir(tmp_path)
    forms = input_forms(source, tmp_path / "inputs")
    before = {name: fingerprint(path) for name, (_, path) in forms.items()}
    # (A memory:// archive lives in this process only: the run and failed-run test cover it.)
    given = [g for g, _ in forms.values()]
    script = textwrap.dedent(
        f"""
        import json, os, sys, time
        from pathlib import Path
        from pipescan.storage.scratch import create_run_dir
        from pipescan.tasks.storing import stage_archive
        for archive in json.loads(sys.argv[1]):
            stage_archive.fn(archive, create_run_dir(Path({str(tmp_path / "work")!r})))
        print("staged", flush=True)
        time.sleep(600)
        """
    )
    import json

    proc = subprocess.Popen(
        [sys.executable, "-c", script, json.dumps(given)],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == "staged"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    for name, (_, path) in forms.items():
        assert path.exists(), f"{name}: the input is gone"
        assert fingerprint(path) == before[name], f"{name}: the input was changed"
    assert len(list((tmp_path / "work").iterdir())) == len(given)  # each staged, then killed
    # The next run sweeps what the killed one left, and still touches no input.
    run = start_run_dir(tmp_path / "work")
    assert list((tmp_path / "work").iterdir()) == [run]
    for name, (_, path) in forms.items():
        assert fingerprint(path) == before[name], f"{name}: the input was changed by the sweep"


def test_only_a_marked_run_directory_is_ever_deleted(tmp_path: Path) -> None:
    users = tmp_path / "my-scans"
    users.mkdir()
    (users / "keep.txt").write_text("mine")
    remove_workspace(users)
    assert (users / "keep.txt").read_text() == "mine"

    link = tmp_path / "link-to-run"
    run = create_run_dir(tmp_path / "work")
    link.symlink_to(run, target_is_directory=True)
    remove_workspace(link)  # a link, even to a run directory, is not followed
    assert (run / RUN_MARKER).is_file()

    remove_workspace(run)
    assert not run.exists()
    remove_workspace(run)  # gone already: no error


def test_a_run_directory_written_to_while_removed_keeps_its_marker(tmp_path, monkeypatch):
    """An interrupted run's tasks may still write while its directory is removed: whatever
    they leave stays marked, so that the next run can remove it (an unmarked directory is
    never deleted, and would stay forever)."""
    import shutil

    from pipescan.storage import scratch

    run = create_run_dir(tmp_path / "work")
    (run / "frames").mkdir()
    (run / "frames" / "chunk_0000000.f32").write_bytes(b"\0" * 12)
    real_rmtree = shutil.rmtree

    def rmtree_while_a_task_writes(path, *args, **kwargs):
        real_rmtree(path, *args, **kwargs)
        (run / "buckets" / "w0").mkdir(parents=True, exist_ok=True)  # a late bucket file
        (run / "buckets" / "w0" / "b-00000.npy").write_bytes(b"late")

    monkeypatch.setattr(scratch.shutil, "rmtree", rmtree_while_a_task_writes)
    remove_workspace(run)
    assert (run / RUN_MARKER).is_file()
    assert not (run / "frames").exists()
    monkeypatch.setattr(scratch.shutil, "rmtree", real_rmtree)
    remove_workspace(run)  # the writer is done: the next removal takes it all
    assert not run.exists()
