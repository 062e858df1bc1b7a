"""The first seconds of ``pipescan inspect``: what it says before Prefect starts, and the bad
point files it refuses there. The CLI runs as a subprocess whose flow is replaced by a stub
(nothing here starts Prefect), so each case takes about a second."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tests.test_cli_journey import TOML, cli, write_archive

# Each log line says whether Prefect was imported when it was written; the flow is a stub.
_BOOT = """
import logging, sys
class _Mark(logging.Filter):
    def filter(self, record):
        record.msg = ("[prefect] " if "prefect" in sys.modules else "") + str(record.msg)
        return True
logging.getLogger("pipescan").addFilter(_Mark())
import pipescan.cli.scan as scan
def _stub(*args, **kwargs):
    sys.stderr.write("RUN\\n")
    sys.exit(0)
scan._run_flow = _stub
scan._inspection_params = lambda *a, **k: None  # imports Prefect: not in these tests
from pipescan.cli import app
sys.argv[0] = "pipescan"
app()
"""


def _run(*args: str, cwd: Path, **env: str) -> tuple[subprocess.CompletedProcess[str], float]:
    clean = {k: v for k, v in os.environ.items() if not k.startswith(("PIPESCAN_", "PREFECT_"))}
    started = time.perf_counter()
    result = subprocess.run(
        [sys.executable, "-c", _BOOT, *args],
        cwd=cwd,
        env={**clean, "PREFECT_HOME": str(cwd / ".prefect"), "COLUMNS": "200", **env},
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    return result, time.perf_counter() - started


def _pipe_frame(diameter_m: float, n: int = 2000, seed: int = 0) -> np.ndarray:
    """A forward-looking sensor's frame inside a straight pipe: points on the wall, 0.3 to
    4 m ahead (x along the pipe)."""
    rng = np.random.default_rng(seed)
    angle = rng.uniform(0, 2 * np.pi, n)
    x = rng.uniform(0.3, 4.0, n)
    r = diameter_m / 2
    return np.column_stack([x, r * np.cos(angle), r * np.sin(angle)])


def _archive(folder: Path, frames: list[np.ndarray], toml: str = TOML) -> Path:
    (folder / "frames").mkdir(parents=True)
    lines = toml.split("[[frames]]")[0]
    for i, points in enumerate(frames):
        np.save(folder / "frames" / f"{i:06d}.npy", points)
        lines += f'\n[[frames]]\nfile = "frames/{i:06d}.npy"\n'
    (folder / "inspection.toml").write_text(lines)
    return folder


def test_inspect_says_what_it_found_and_that_prefect_starts_before_importing_it(tmp_path):
    archive = _archive(tmp_path / "site7", [_pipe_frame(0.5, seed=i) for i in range(3)])
    result, elapsed = _run(
        "inspect", str(archive), "--db", f"sqlite:///{tmp_path / 'p.db'}", cwd=tmp_path
    )
    assert result.returncode == 0, result.stderr
    lines = result.stderr.splitlines()
    assert lines[-1] == "RUN"
    said = [line.split("  ", 1)[1] for line in lines[:-1]]  # without the time stamp
    assert said[0].startswith(f"archive {archive}: asset MH1-MH2, DN 500")
    assert "3 frames (.npy)" in said[0]
    assert re.fullmatch(
        r"checked the first and last frames: 2,000 and 2,000 points, in metres, "
        r"0\.5\d and 0\.5\d m across the pipe \(nominal 0\.5 m\)",
        said[1],
    ), said[1]
    assert said[2] == (
        "starting Prefect's local API (about 10 s; set PREFECT_API_URL to a running server "
        "to skip this)"
    )
    assert not any(line.startswith("[prefect]") for line in said), said
    assert elapsed < 5, f"{elapsed:.1f} s to the flow's start"  # ~1 s on a quiet machine


def test_a_prefect_server_that_is_set_is_not_started(tmp_path):
    archive = _archive(tmp_path / "site7", [_pipe_frame(0.5)])
    result, _ = _run(
        "inspect", str(archive), cwd=tmp_path, PREFECT_API_URL="http://127.0.0.1:4200/api"
    )
    assert result.returncode == 0, result.stderr
    assert "starting Prefect's local API" not in result.stderr
    profile = tmp_path / ".prefect" / "profiles.toml"
    profile.parent.mkdir()
    profile.write_text('active = "srv"\n[profiles.srv]\nPREFECT_API_URL = "http://h:4200/api"\n')
    result, _ = _run("inspect", str(archive), cwd=tmp_path)
    assert "starting Prefect's local API" not in result.stderr, result.stderr


@pytest.mark.parametrize(
    ("case", "expected"),
    [
        ("nan", "have NaN or infinite coordinates"),
        ("millimetres", "the median distance of the points from the sensor"),
        ("empty", "the file holds no points"),
        ("radius for diameter", "field 'nominal_diameter_m': the points span"),
        ("feet", "field 'nominal_diameter_m': the points span"),
    ],
)
def test_a_bad_point_file_is_one_line_in_seconds_before_prefect(case, expected, tmp_path):
    frames = [_pipe_frame(0.5, seed=i) for i in range(4)]
    toml = TOML
    if case == "nan":
        frames[-1][7, 2] = np.nan  # the last file: the first one is fine
    elif case == "millimetres":
        frames[0] *= 1000
    elif case == "empty":
        frames[-1] = np.zeros((0, 3))
    elif case == "radius for diameter":
        toml = TOML.replace("= 0.5", "= 0.25")
    elif case == "feet":
        frames = [f / 0.3048 for f in frames]
    archive = _archive(tmp_path / "site7", frames, toml)
    db = tmp_path / "p.db"
    started = time.perf_counter()
    run = cli("inspect", str(archive), "--db", f"sqlite:///{db}", cwd=tmp_path)
    elapsed = time.perf_counter() - started
    line = run.one_line_error()
    assert expected in line and str(archive) in line, line
    assert elapsed < 3.0, f"{elapsed:.1f} s"
    assert not db.exists()


def test_a_pipe_of_the_right_size_with_odd_ends_passes(tmp_path):
    """Only when every file checked is off the diameter is the archive refused: a first frame
    in a manhole's chamber, twice as wide, is not enough."""
    frames = [_pipe_frame(1.0), _pipe_frame(0.5, seed=1), _pipe_frame(0.5, seed=2)]
    archive = _archive(tmp_path / "site7", frames)
    result, _ = _run("inspect", str(archive), cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert re.search(r"1\.\d\d and 0\.5\d m across the pipe", result.stderr), result.stderr


def test_a_date_without_time_zone_is_a_warning_naming_the_utc_it_was_read_as(tmp_path):
    archive = write_archive(tmp_path / "site7", TOML.replace("2025-03-14T09:30:00Z", "2025-03-14"))
    result, _ = _run("inspect", str(archive), cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    warning = next(line for line in result.stderr.splitlines() if "warning:" in line)
    assert "inspected_at has no time zone; read as 2025-03-14T00:00:00Z (UTC)" in warning
    result, _ = _run("inspect", str(write_archive(tmp_path / "tz")), cwd=tmp_path)
    assert "warning" not in result.stderr


def test_a_run_s_stages_become_progress_bars_on_a_terminal_only(monkeypatch):
    import io
    import logging

    from rich.console import Console

    from pipescan.cli import _progress

    handler = _progress.ProgressHandler(
        Console(file=io.StringIO(), force_terminal=True, width=100),
        logging.Formatter("%(message)s"),
    )
    lines = [
        "every 3rd frame used, 89 of 265",
        "registering 89 of 265 frames in 2 chunks",
        "registered frames 132-264 of 265 (small_gicp gicp)",
        "registered frames 0-132 of 265 (small_gicp gicp)",
        "registered 101 of 265 frames (12 read where ICP disagreed with the odometer)",
        "axis fitted; chainage 0.45-6.01 m in 3 windows",
        "measured 0.4-2.4 m (701847 points)",
        "measured 2.4-4.4 m (1094682 points)",
    ]
    shown = []
    for text in lines:
        record = logging.LogRecord("pipescan", logging.INFO, __file__, 0, text, None, None)
        if not handler._stage(record.getMessage()):
            shown.append(text)
    frames, windows = handler.progress.tasks
    assert (frames.description, frames.completed, frames.total) == ("frames registered", 265, 265)
    assert (windows.description, windows.completed, windows.total) == ("windows measured", 2, 3)
    # The chunk and window lines are the bars'; the others still print.
    assert shown == [lines[0], lines[1], lines[4], lines[5]]
    monkeypatch.setattr("sys.stderr", io.StringIO())  # not a terminal: no bars, lines as lines
    assert not _progress.on_a_terminal()
