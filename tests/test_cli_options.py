"""Options that name a registry entry, as a user meets them: the CLI run as a subprocess."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import pytest

from pipescan.core.contour import CONTOUR_METHODS


def run_cli(args: list[str], cwd: Path, **env: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "pipescan.cli", *args],
        cwd=cwd,
        env={**os.environ, "PREFECT_SERVER_ANALYTICS_ENABLED": "false", **env},
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


@pytest.mark.parametrize("command", ["inspect", "inspect-network"])
def test_an_unknown_contour_method_is_one_line_and_nothing_runs(command, tmp_path):
    store = tmp_path / "store"
    store.mkdir()
    db = tmp_path / "p.db"
    known = ", ".join(CONTOUR_METHODS)
    given = run_cli([command, str(store), "--db", f"sqlite:///{db}", "--contour", "polr"], tmp_path)
    from_env = run_cli(
        [command, str(store), "--db", f"sqlite:///{db}"], tmp_path, PIPESCAN_CONTOUR_METHOD="polr"
    )
    for result, origin in ((given, "--contour 'polr'"), (from_env, "PIPESCAN_CONTOUR_METHOD")):
        assert result.returncode == 2, result.stderr
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1, result.stderr
        assert origin in lines[0] and known in lines[0]
    assert not db.exists()


def test_help_lists_the_registered_contour_methods(tmp_path):
    result = run_cli(["inspect", "--help"], tmp_path, COLUMNS="200")
    assert result.returncode == 0
    assert " or ".join(CONTOUR_METHODS) in result.stdout


def test_the_summary_says_the_odometer_slipped_and_where_that_widened_the_chainage(capsys):
    from pipescan.cli.scan import _print_summary
    from pipescan.flows.inspect import InspectionSummary

    reg = {
        "engine": "small_gicp gicp", "mean_fitness": 0.99, "mean_rmse_m": 0.007, "frames": 300,
        "degenerate_frames": 120, "slides": 0, "chainage_uncertainty_m": 0.62,
        "odometer_slips_caught_m": [0.21, 0.4384],
    }  # fmt: skip
    summary = InspectionSummary(
        1, "A", "2024-05-14", "scan", 300, 10, 4.0, 40, 30, 0, None, None, {}, reg, None, None, 1.0
    )
    _print_summary(summary)
    out = capsys.readouterr().out
    assert "chainage within ±62.0 cm at the end" in out
    assert (
        "the odometer slipped twice where features were in view (up to 44 cm); allowed for "
        "where it was alone"
    ) in out  # a summary stored before the allowance was kept
    allowed = reg | {"unseen_slips_allowed_m": 0.44}
    _print_summary(dataclasses.replace(summary, registration=allowed))
    out = capsys.readouterr().out
    assert "(up to 44 cm); the ± allows 0.44 m for unseen ones where it was alone" in out
    assert "as large as the largest caught (0.44 m); a larger one there is not" in out
    # Frames rested on the odometer, but never for a slide window: nothing could hide there.
    none = reg | {"unseen_slips_allowed_m": 0.0}
    _print_summary(dataclasses.replace(summary, registration=none))
    out = capsys.readouterr().out
    assert "(up to 44 cm); no stretch rested on the odometer long enough to hide one" in out
    assert "largest caught" not in out
    # Where no frame rested on the odometer there is nothing to allow for.
    _print_summary(dataclasses.replace(summary, registration=reg | {"degenerate_frames": 0}))
    out = capsys.readouterr().out
    assert "(up to 44 cm)\n" in out and "allows for" not in out
    assert "rested on the odometer alone" not in out


def test_the_summary_says_what_the_chainage_cannot_allow_for_when_no_slip_was_caught(capsys):
    """Held frames and no slip caught: the ± is the odometer's own, and the user is told."""
    from pipescan.cli.scan import _print_summary
    from pipescan.flows.inspect import InspectionSummary

    reg = {
        "engine": "small_gicp gicp", "mean_fitness": 0.99, "mean_rmse_m": 0.007, "frames": 300,
        "degenerate_frames": 120, "slides": 0, "chainage_uncertainty_m": 0.09,
        "odometer_slips_caught_m": [], "odometer_uncertainty_ratio": 0.03,
        "along_axis_prior": "odometer",
        "unconstrained_spans": [
            {"first_frame": 10, "last_frame": 70, "start_travel_m": 0.3, "end_travel_m": 1.2},
            {"first_frame": 200, "last_frame": 260, "start_travel_m": 3.0, "end_travel_m": 3.9},
        ],
    }  # fmt: skip
    summary = InspectionSummary(
        1, "A", "2024-05-14", "scan", 300, 10, 4.0, 40, 30, 0, None, None, {}, reg, None, None, 1.0
    )
    _print_summary(summary)
    out = capsys.readouterr().out
    assert "slipped" not in out
    assert (
        "  1.8 m of travel rested on the odometer alone: the ± there is the odometer's 3 % and "
        "allows for no slip (none was caught where features were in view; one where it was "
        "alone would not be seen; state the crawler's largest slip as odometer_slip_m in "
        "inspection.toml)\n"
    ) in out
    # The operator stated the crawler's largest slip: one such is allowed for, and said so.
    stated = reg | {"odometer_slip_stated_m": 0.25, "unseen_slips_allowed_m": 0.25}
    _print_summary(dataclasses.replace(summary, registration=stated))
    assert (
        "  1.8 m of travel rested on the odometer alone: the ± there is the odometer's 3 % and "
        "one unseen slip of the stated 0.25 m (none was caught; more than one, or a larger "
        "one, is not allowed for)\n"
    ) in capsys.readouterr().out
    # Slips caught: the ± allows for them (the line of the test above), no caveat.
    _print_summary(
        dataclasses.replace(summary, registration=reg | {"odometer_slips_caught_m": [0.2]})
    )
    assert "rested on the odometer alone" not in capsys.readouterr().out
    # No odometer at all: the summary's warning says the chainage is extrapolated instead.
    _print_summary(
        dataclasses.replace(summary, registration=reg | {"along_axis_prior": "constant_velocity"})
    )
    assert "rested on the odometer alone" not in capsys.readouterr().out


def test_the_cli_keeps_prefects_log_handler_and_writes_to_the_stderr_of_the_moment(capsys):
    """In a process whose Prefect logging was set up first (a test session, a notebook), a
    command must not take Prefect's handler off the ``pipescan`` logger: that handler sends a
    flow run's lines to its API (the network run's progress in the UI). And its own lines go
    to the stderr of the moment, not to one a caller has closed since."""
    import logging

    from pipescan.cli._app import _setup_logging

    logger = logging.getLogger("pipescan")
    saved = (logger.handlers[:], logger.level, logger.propagate)
    prefects = logging.NullHandler()  # stands for Prefect's API handler
    try:
        logger.handlers[:] = [prefects]
        _setup_logging(verbose=False)
        _setup_logging(verbose=False)  # a second command in the same process
        assert logger.handlers[0] is prefects and len(logger.handlers) == 2
        capsys.readouterr()
        logger.info("windows measured")
        assert "windows measured" in capsys.readouterr().err
    finally:
        logger.handlers[:], logger.level, logger.propagate = saved


def test_a_database_given_as_a_file_path_is_that_sqlite_file(tmp_path):
    """``--db surveys/p.db`` (a path, not a URL) is the SQLite file there; it used to end in a
    traceback from SQLAlchemy's URL parser."""
    made = run_cli(["db", "upgrade", "--db", "surveys/p.db"], tmp_path)
    assert made.returncode == 0, made.stderr
    assert (tmp_path / "surveys" / "p.db").is_file()
    listed = run_cli(["inspections"], tmp_path, PIPESCAN_DATABASE_URL="surveys/p.db")
    assert listed.returncode == 0, listed.stderr
    assert "Traceback" not in listed.stderr
    missing = run_cli(["inspections", "--db", "elsewhere.db"], tmp_path)
    assert missing.returncode == 2
    assert "elsewhere.db does not exist" in missing.stderr


@pytest.mark.parametrize("command", [["inspections"], ["db", "current"], ["db", "upgrade"]])
def test_a_database_url_that_cannot_be_parsed_is_one_line(command, tmp_path):
    result = run_cli([*command, "--db", "postgresql://h:port/db"], tmp_path)
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "cannot parse database URL 'postgresql://h:port/db'" in lines[0]
    assert list(tmp_path.iterdir()) == []


def test_inspect_refuses_a_report_path_it_cannot_write_before_any_work(tmp_path):
    """``inspect --report`` into a folder it cannot make: one line, exit 2, before the
    archive is even opened (it used to run the whole inspection, store it, then fail)."""
    (tmp_path / "notes.txt").write_text("x")
    result = run_cli(
        ["inspect", "no-such-archive", "--db", "p.db", "--report", "notes.txt/r.pdf"], tmp_path
    )
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "file notes.txt/r.pdf: cannot write the report" in lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


@pytest.mark.parametrize(
    "args",
    [["simulate", "afile/scan"], ["demo", "--out", "afile"], ["demo", "--out", "afile/demo"]],
)
def test_an_output_folder_behind_a_file_is_one_line(args, tmp_path):
    """``simulate`` and ``demo`` into a path a file stands in: one line naming the file, exit
    2, and nothing written (they ended in a traceback from mkdir)."""
    (tmp_path / "afile").write_text("x")
    result = run_cli(args, tmp_path)
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and f"{tmp_path / 'afile'} is a file" in lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]
    assert (tmp_path / "afile").read_text() == "x"
