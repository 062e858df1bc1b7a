"""Ctrl-C in a terminal sends SIGINT to the whole foreground process group: pipescan, the
Prefect API server it started and the engine pool's workers. pipescan says so in one line,
exits with 130 (the shell's code for an interrupt), stores nothing half, shows no traceback and
leaves no process behind."""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import psutil
import pytest

from pipescan.cli._app import INTERRUPT_GRACE_S
from pipescan.simulator.archive import write_simulated_archive
from pipescan.simulator.scan import get_scenario, simulate_scan


@pytest.fixture(scope="module")
def archive(tmp_path_factory) -> Path:
    scan = simulate_scan(get_scenario("paper", travel_m=3.0), seed=3)
    return write_simulated_archive(scan, tmp_path_factory.mktemp("scan") / "arc")


def _sigint_at_default() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


class _Run:
    """``pipescan inspect`` in a session of its own, as a terminal's foreground job."""

    def __init__(self, archive: Path, tmp_path: Path) -> None:
        self.db = tmp_path / "p.db"
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "pipescan.cli", "inspect", str(archive), "--db",
             f"sqlite:///{self.db}"],
            cwd=tmp_path,
            env={**os.environ, "PREFECT_SERVER_ANALYTICS_ENABLED": "false"},
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            start_new_session=True,
            # A terminal's foreground job has Ctrl-C at its default, even where the tests run
            # in the background (a shell's background job inherits SIGINT ignored).
            preexec_fn=_sigint_at_default,
        )  # fmt: skip
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line.rstrip("\n"))

    def wait_for(self, text: str, timeout_s: float = 120) -> None:
        deadline = time.monotonic() + timeout_s
        while not any(text in line for line in self.lines):
            assert self.proc.poll() is None, "\n".join(self.lines)
            assert time.monotonic() < deadline, "\n".join(self.lines)
            time.sleep(0.1)

    def descendants(self) -> list[int]:
        try:
            return [p.pid for p in psutil.Process(self.proc.pid).children(recursive=True)]
        except psutil.NoSuchProcess:
            return []

    def ctrl_c(self) -> None:
        os.killpg(self.proc.pid, signal.SIGINT)

    def finish(self, timeout_s: float) -> tuple[int, float]:
        started = time.monotonic()
        code = self.proc.wait(timeout=timeout_s)
        self._reader.join(timeout=10)
        return code, time.monotonic() - started


def _stored_inspections(db: Path) -> int:
    if not db.exists():
        return 0
    with sqlite3.connect(db) as con:
        tables = {r[0] for r in con.execute("select name from sqlite_master where type='table'")}
        if "inspections" not in tables:
            return 0
        return con.execute("select count(*) from inspections").fetchone()[0]


def _no_traceback_of_ours(out: str) -> bool:
    """No traceback from pipescan or its engine workers. Prefect's temporary API server,
    which the same Ctrl-C stops, writes to the same terminal and may log the errors of its
    own shutdown (its database sessions cancelled): those are Prefect's, not pipescan's."""
    frames = [line for line in out.splitlines() if line.strip().startswith("File ")]
    ours = [f for f in frames if "pipescan/" in f or "multiprocessing/spawn.py" in f]
    return not ours and "this is a bug" not in out


def _all_gone(pids: list[int], timeout_s: float = 15) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        alive = [p for p in pids if psutil.pid_exists(p) and psutil.Process(p).status() != "zombie"]
        if not alive:
            return True
        time.sleep(0.2)
    return False


@pytest.mark.parametrize(
    ("presses", "last_line", "within_s"),
    [
        # Once: the command unwinds, then stops; Prefect's complaints about its API server
        # (stopped by the same Ctrl-C) are not shown, and it is not waited for.
        (1, "error: interrupted: nothing more was stored", INTERRUPT_GRACE_S + 5),
        # Twice: at once.
        (2, "error: interrupted again: stopped at once", 10),
    ],
    ids=["once-within-the-grace", "twice-at-once"],
)
def test_ctrl_c_ends_the_run_in_one_line(archive, tmp_path, presses, last_line, within_s):
    run = _Run(archive, tmp_path)
    try:
        run.wait_for("registering")
        helpers = run.descendants()  # the API server, the engine workers
        assert len(helpers) >= 3, helpers
        run.ctrl_c()
        for _ in range(presses - 1):
            time.sleep(1.0)
            run.ctrl_c()
        code, took = run.finish(timeout_s=120)
    finally:
        run.proc.kill()
    out = "\n".join(run.lines)
    assert code == 130, out
    assert took < within_s, (took, out)
    assert _no_traceback_of_ours(out), out
    assert "interrupted: stopping (Ctrl-C again to stop at once)" in run.lines
    assert run.lines[-1].startswith(last_line), out
    assert _stored_inspections(run.db) == 0
    assert _all_gone(helpers), [p for p in helpers if psutil.pid_exists(p)]
