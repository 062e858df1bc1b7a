"""Kill a real ``pipescan inspect-network`` process mid-way (SIGKILL: no clean-up at all), start
it again, and check that it finishes the remaining archives without redoing the finished ones,
leaving exactly one copy of each inspection in the database."""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import subprocess
import sys
import time
from contextlib import suppress

import pytest

from tests.netstore import asset_id, write_store

pytestmark = pytest.mark.e2e

ARCHIVES = 3
KILL_AFTER_STORED = 1


def _stored(db_path) -> dict[str, int]:
    """asset id -> inspection id, read straight from the SQLite file (empty while missing)."""
    if not db_path.exists():
        return {}
    try:
        with sqlite3.connect(f"file:{db_path}?mode=ro", uri=True, timeout=5) as con:
            rows = con.execute("SELECT asset_id, id FROM inspections").fetchall()
    except sqlite3.OperationalError:  # not migrated yet
        return {}
    assert len(rows) == len({a for a, _ in rows}), f"an asset was stored twice: {rows}"
    return dict(rows)


def _created(db_path) -> dict[str, str]:
    """asset id -> when its inspection was saved (a re-processed archive keeps its id, not
    this)."""
    with sqlite3.connect(f"file:{db_path}?mode=ro", uri=True, timeout=5) as con:
        return dict(con.execute("SELECT asset_id, created_at FROM inspections").fetchall())


def _command(store, db_url) -> list[str]:
    return [
        sys.executable,
        "-m",
        "pipescan.cli",
        "inspect-network",
        str(store),
        "--db",
        db_url,
        "--concurrency",
        "1",
        "--workers",
        "2",
        "--no-network-report",
        "--json",
    ]


def test_a_killed_network_run_resumes_without_redoing_finished_archives(tmp_path):
    store = tmp_path / "store"
    write_store(store, ARCHIVES)
    db_path = tmp_path / "network.db"
    db_url = f"sqlite:///{db_path}"
    env = {
        k: v for k, v in os.environ.items() if not k.startswith(("PREFECT_API_URL", "PIPESCAN_"))
    }
    env |= {
        "PREFECT_HOME": str(tmp_path / "prefect-home"),  # its own ephemeral API database
        "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
        # Its temporary API server migrates a new database first: on a loaded machine that
        # takes longer than Prefect's default 20 s.
        "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS": "120",
        "PIPESCAN_WORK_DIR": str(tmp_path / "work"),
    }
    log = (tmp_path / "killed.log").open("w")
    # A session of its own, so that the temporary Prefect server it starts can be found after.
    run = subprocess.Popen(
        _command(store, db_url),
        env=env,
        cwd=tmp_path,
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 240
        while len(_stored(db_path)) < KILL_AFTER_STORED:
            assert run.poll() is None, (tmp_path / "killed.log").read_text()[-3000:]
            assert time.monotonic() < deadline, "the run stored nothing within 240 s"
            time.sleep(0.1)
        os.kill(run.pid, signal.SIGKILL)
        assert run.wait(timeout=30) == -signal.SIGKILL
    finally:
        with suppress(ProcessLookupError):
            os.killpg(run.pid, signal.SIGKILL)  # what it started (its temporary server)
        log.close()
    before = _stored(db_path)
    saved_before = _created(db_path)
    assert KILL_AFTER_STORED <= len(before) < ARCHIVES, f"not killed mid-way: {before}"

    resumed = subprocess.run(
        _command(store, db_url),
        env=env,
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
        start_new_session=True,
    )
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    summary = json.loads(resumed.stdout)
    outcomes = {o["asset_id"]: o for o in summary["outcomes"]}
    assert summary["counts"] == {
        "inspected": ARCHIVES - len(before),
        "reused": len(before),
        "duplicate": 0,
        "failed": 0,
        "missing": 0,
    }
    after = _stored(db_path)
    assert sorted(after) == [asset_id(i) for i in range(ARCHIVES)]
    for asset, inspection_id in before.items():
        # Not redone: a re-processed archive would have been saved again.
        assert after[asset] == inspection_id
        assert _created(db_path)[asset] == saved_before[asset]
        assert outcomes[asset]["status"] == "reused"
    for asset in set(after) - set(before):
        assert outcomes[asset]["status"] == "inspected"
        assert outcomes[asset]["inspection_id"] == after[asset]
    with sqlite3.connect(db_path) as con:
        identities = con.execute(
            "SELECT COUNT(*), COUNT(DISTINCT asset_id || content_hash || params_hash) "
            "FROM inspections"
        ).fetchone()
        orphans = con.execute(
            "SELECT COUNT(*) FROM sections WHERE inspection_id NOT IN (SELECT id FROM inspections)"
        ).fetchone()
    assert identities == (ARCHIVES, ARCHIVES)
    assert orphans == (0,)
    # The progress lines a person watches.
    assert f"[{ARCHIVES}/{ARCHIVES}]" in resumed.stderr
    assert "reused inspection" in resumed.stderr
