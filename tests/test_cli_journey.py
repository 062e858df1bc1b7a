"""The mistakes a new user makes, met as they meet them: ``pipescan`` run as a subprocess, its
exit code and stderr checked. Every case here fails before Prefect starts, so each run takes
about a second."""

from __future__ import annotations

import os
import re
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pipescan.storage.database import repository
from pipescan.storage.database.db import connect
from tests.test_db import item, make_meta

# Runs the CLI, and on exit records whether Prefect was imported: "before Prefect starts" is
# a fact a test can check, not a hope.
_BOOT = """
import atexit, os, sys
def _record():
    with open(os.environ["PIPESCAN_TEST_MODULES"], "w") as fh:
        fh.write("prefect" if "prefect" in sys.modules else "")
atexit.register(_record)
from pipescan.cli import app
sys.argv[0] = "pipescan"
app()
"""


class Run:
    def __init__(self, result: subprocess.CompletedProcess[str], prefect_imported: bool):
        self.code = result.returncode
        self.stdout = result.stdout
        self.stderr = result.stderr
        self.lines = result.stderr.strip().splitlines()
        self.prefect_imported = prefect_imported

    def one_line_error(self) -> str:
        """The single stderr line of an expected error (exit 2, no traceback, no Prefect)."""
        assert self.code == 2, self.stderr
        assert len(self.lines) == 1, self.stderr
        assert "Traceback" not in self.stderr
        assert self.lines[0].startswith("error: ")
        assert not self.prefect_imported, "Prefect started before the error was found"
        return self.lines[0]

    def error_after_first_lines(self) -> str:
        """The error of a command that had said what it found first (``inspect``'s first lines,
        printed before the checks that take longer): its lines, then one error line."""
        assert self.code == 2, self.stderr
        assert "Traceback" not in self.stderr
        assert self.lines[-1].startswith("error: ")
        assert all(re.match(r"\d\d:\d\d:\d\d  ", line) for line in self.lines[:-1]), self.stderr
        assert not self.prefect_imported, "Prefect started before the error was found"
        return self.lines[-1]


def cli(*args: str, cwd: Path, **env: str) -> Run:
    marker = cwd / ".modules"
    clean = {k: v for k, v in os.environ.items() if not k.startswith("PIPESCAN_")}
    result = subprocess.run(
        [sys.executable, "-c", _BOOT, *args],
        cwd=cwd,
        env={
            **clean,
            "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
            "PIPESCAN_TEST_MODULES": str(marker),
            "COLUMNS": "200",
            **env,
        },
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    imported = marker.exists() and marker.read_text() == "prefect"
    marker.unlink(missing_ok=True)
    return Run(result, imported)


TOML = """asset_id = "MH1-MH2"
inspected_at = 2025-03-14T09:30:00Z
nominal_diameter_m = 0.5

[[frames]]
file = "frames/000000.npy"

[[frames]]
file = "frames/000001.npy"
"""


def write_archive(folder: Path, toml: str | None = TOML, frames: int = 2) -> Path:
    (folder / "frames").mkdir(parents=True)
    if toml is not None:
        (folder / "inspection.toml").write_text(toml)
    ring = np.column_stack([np.full(100, 1.0), np.cos(np.arange(100)), np.sin(np.arange(100))])
    for i in range(frames):
        np.save(folder / "frames" / f"{i:06d}.npy", 0.25 * ring)
    return folder


@pytest.fixture
def stored(tmp_path: Path) -> str:
    """A SQLite database holding one inspection (id 1) of asset MH1042-MH1043."""
    url = f"sqlite:///{tmp_path / 'stored.db'}"
    engine = connect(url)
    try:
        repository.save_inspection(engine, item(meta=make_meta()))
    finally:
        engine.dispose()
    return url


# --- 1. expected errors: one line, exit 2, before Prefect ------------------------------------


@pytest.mark.parametrize(
    ("case", "expected"),
    [
        ("missing", "the archive does not exist"),
        ("no toml", "file inspection.toml"),
        ("millimetres", "field 'nominal_diameter_m'"),
        ("missing frame", "field 'frames[1].file'"),
    ],
)
def test_a_bad_archive_is_one_line_before_prefect_starts(case, expected, tmp_path):
    archive = tmp_path / "site7"
    if case == "no toml":
        write_archive(archive, toml=None)
    elif case == "millimetres":
        write_archive(archive, TOML.replace("= 0.5", "= 500"))
    elif case == "missing frame":
        write_archive(archive, frames=1)
    db = tmp_path / "p.db"
    line = cli("inspect", str(archive), "--db", f"sqlite:///{db}", cwd=tmp_path).one_line_error()
    assert str(archive) in line and expected in line
    assert not db.exists()


@pytest.mark.parametrize(
    ("args", "env", "expected"),
    [
        (["--registration", "icp"], {}, "--registration 'icp' is not a registration method"),
        ([], {"PIPESCAN_REGISTRATION_METHOD": "icp"}, "PIPESCAN_REGISTRATION_METHOD"),
        ([], {"PIPESCAN_REGISTRATION_ENGINE": "open3d"}, "PIPESCAN_REGISTRATION_ENGINE='open3d'"),
        ([], {"PIPESCAN_THRESHOLD_TABLE": "vsa2023"}, "PIPESCAN_THRESHOLD_TABLE='vsa2023'"),
        ([], {"PIPESCAN_PIPE_CLASS": "stiff"}, "PIPESCAN_PIPE_CLASS='stiff'"),
        ([], {"PIPESCAN_STEP_M": "-1"}, "PIPESCAN_STEP_M='-1'"),
    ],
)
def test_a_bad_choice_or_setting_is_one_line_before_prefect_starts(args, env, expected, tmp_path):
    archive = write_archive(tmp_path / "ok")
    db = tmp_path / "p.db"
    run = cli("inspect", str(archive), "--db", f"sqlite:///{db}", *args, cwd=tmp_path, **env)
    # After the archive's first lines (they come at once; these checks load scipy).
    assert expected in run.error_after_first_lines()
    assert not db.exists()


def test_usage_errors_are_one_line_that_points_to_help(tmp_path):
    for args, expected in [
        (["inpsect"], "No such command 'inpsect'"),
        (["inspect"], "Missing argument"),
        (["simulate", "--scenario", "nope", "out"], "'nope' is not one of"),
        (["report"], "give either --inspection ID or --network"),
    ]:
        line = cli(*args, cwd=tmp_path).one_line_error()
        assert expected in line, line
    assert (
        "pipescan simulate --help"
        in cli("simulate", "--scenario", "nope", "x", cwd=tmp_path).one_line_error()
    )


def test_debug_shows_the_traceback_of_an_expected_error(tmp_path):
    for args, env in [(["--debug"], {}), ([], {"PIPESCAN_DEBUG": "1"})]:
        run = cli(*args, "inspect", str(tmp_path / "nope"), cwd=tmp_path, **env)
        assert run.code == 2
        assert "Traceback" in run.stderr and "ArchiveError" in run.stderr
        assert run.lines[-1].startswith("error: ")


def test_an_unexpected_error_keeps_its_traceback_and_says_how_to_report_it(
    monkeypatch, tmp_path, stored
):
    from typer.testing import CliRunner

    from pipescan.cli import app

    def broken(*args, **kwargs):
        raise ZeroDivisionError("a bug")

    monkeypatch.setattr(repository, "list_assets", broken)
    result = CliRunner().invoke(app, ["assets", "--db", stored])
    assert result.exit_code == 1
    assert "Traceback" in result.stderr and "ZeroDivisionError: a bug" in result.stderr
    assert "this is a bug" in result.stderr.strip().splitlines()[-1]


# --- 3. no silent wrong or empty results -----------------------------------------------------


@pytest.mark.parametrize(
    "args",
    [
        ["report", "--network", "-o", "n.pdf"],
        ["report", "--inspection", "1", "-o", "r.pdf"],
        ["export", "sections"],
        ["trend", "MH1-MH2"],
        ["worst"],
        ["assets"],
        ["inspections"],
    ],
)
def test_a_command_that_reads_never_creates_a_database(args, tmp_path):
    line = cli(*args, cwd=tmp_path).one_line_error()
    assert "no database at sqlite:///pipescan.db" in line
    assert str(tmp_path / "pipescan.db") in line and "the default" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_the_missing_database_is_named_with_where_its_url_came_from(tmp_path):
    given = cli("worst", "--db", f"sqlite:///{tmp_path}/elsewhere.db", cwd=tmp_path)
    assert f"no database at sqlite:///{tmp_path}/elsewhere.db (--db)" in given.one_line_error()
    from_env = cli("assets", cwd=tmp_path, PIPESCAN_DATABASE_URL=f"sqlite:///{tmp_path}/e.db")
    assert "(PIPESCAN_DATABASE_URL)" in from_env.one_line_error()
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_exports_refuse_an_unknown_inspection_or_asset(tmp_path, stored):
    for what, args, expected in [
        ("sections", ["--inspection", "999"], "no inspection with id 999"),
        ("defects", ["--asset", "NOPE"], "no asset 'NOPE'"),
        (
            "sections",
            ["--asset", "NOPE", "--inspection", "1"],
            "inspection 1 is of asset 'MH1042-MH1043'",
        ),
    ]:
        run = cli("export", what, *args, "--db", stored, cwd=tmp_path)
        assert expected in run.one_line_error()
        assert run.stdout == ""
    listing = cli("inspections", "--asset", "NOPE", "--db", stored, cwd=tmp_path)
    assert "no asset 'NOPE'" in listing.one_line_error()
    report = cli("report", "--inspection", "999", "--db", stored, cwd=tmp_path)
    assert "`pipescan inspections`" in report.one_line_error()  # a command, not a Python call


def test_an_export_creates_its_folder_and_files_follow_the_umask(tmp_path, stored):
    out = tmp_path / "new" / "deeper" / "sections.csv"
    run = cli(
        "export", "sections", "--inspection", "1", "--db", stored, "-o", str(out), cwd=tmp_path
    )
    assert run.code == 0, run.stderr
    assert run.lines == [f"wrote 5 rows to {out}"]
    assert out.read_text().count("\n") == 6  # header and 5 sections
    assert [p.name for p in out.parent.iterdir()] == ["sections.csv"]  # no .part left
    dash = cli("export", "sections", "--inspection", "1", "--db", stored, "-o", "-", cwd=tmp_path)
    assert dash.code == 0, dash.stderr
    assert dash.stdout == out.read_text()  # "-" is stdout, not a file called "-"
    assert not (tmp_path / "-").exists()
    umask = os.umask(0)
    os.umask(umask)
    pdf = tmp_path / "reports" / "r.pdf"
    run = cli("report", "--inspection", "1", "--db", stored, "-o", str(pdf), cwd=tmp_path)
    assert run.code == 0, run.stderr
    expected = 0o666 & ~umask
    assert stat.S_IMODE(pdf.stat().st_mode) == expected
    assert stat.S_IMODE(out.stat().st_mode) == expected


def test_listings_have_headers_and_plurals(tmp_path, stored):
    assets = cli("assets", "--db", stored, cwd=tmp_path).stdout.splitlines()
    assert assets[0].split()[:2] == ["asset", "upstream"]
    assert "1 inspection, last" in assets[1]
    inspections = cli("inspections", "--db", stored, cwd=tmp_path).stdout.splitlines()
    assert inspections[0].split()[:3] == ["id", "asset", "inspected"]
    assert inspections[1].split()[:2] == ["1", "MH1042-MH1043"]


# --- 4. a trend to demonstrate: simulate an asset's surveys at their dates --------------------


def test_simulate_sets_asset_date_and_grows_deposits(tmp_path):
    import tomllib

    out = tmp_path / "survey-2026"
    run = cli(
        "simulate", str(out), "--travel-m", "0.3", "--asset-id", "MH1042-MH1043",
        "--inspected-at", "2026-05-14T09:30:00Z", "--deposit-growth", "0.02",
        cwd=tmp_path,
    )  # fmt: skip
    assert run.code == 0, run.stderr
    meta = tomllib.loads((out / "inspection.toml").read_text())
    assert meta["asset_id"] == "MH1042-MH1043"
    assert meta["inspected_at"].isoformat() == "2026-05-14T09:30:00+00:00"
    scene = tomllib.loads((out / "ground_truth" / "scene.toml").read_text())
    (deposit,) = scene["scenario"]["deposits"]
    # The paper's deposit (0.2851 of the diameter on 2024-05-14), two years on at 0.02 a year.
    assert deposit["peak_height_ratio"] == pytest.approx(0.2851 + 0.02 * 730 / 365.25)
    for args, expected in [
        (["--deposit-growth", "0.02"], "--deposit-growth needs --inspected-at"),
        (["--inspected-at", "14.5.2026"], "--inspected-at '14.5.2026' is not an ISO 8601"),
        (
            ["--scenario", "clean", "--inspected-at", "2026-01-01", "--deposit-growth", "0.1"],
            "scenario 'clean' has no deposit to grow",
        ),
        (
            ["--inspected-at", "2034-01-01", "--deposit-growth", "0.05"],
            "would pass through deposit",
        ),
    ]:
        line = cli("simulate", str(tmp_path / "x"), *args, cwd=tmp_path).one_line_error()
        assert expected in line
    assert not (tmp_path / "x").exists()


def test_a_network_report_of_nothing_is_an_error_not_an_empty_pdf(tmp_path):
    url = f"sqlite:///{tmp_path / 'empty.db'}"
    connect(url).dispose()  # a migrated database without inspections
    run = cli("report", "--network", "--db", url, "-o", str(tmp_path / "n.pdf"), cwd=tmp_path)
    assert run.code == 2 and len(run.lines) == 1, run.stderr
    assert "no inspection to report on in the database" in run.lines[0]
    assert not (tmp_path / "n.pdf").exists()
