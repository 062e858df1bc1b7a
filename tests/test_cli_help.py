"""The CLI's small courtesies: ``--debug`` anywhere on the line, ``--help`` readable at 80
columns with its examples whole, and a re-inspection that says it replaced stored rows."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
from typer.testing import CliRunner

from pipescan.cli import app, scan
from tests.test_cli_journey import cli, stored, write_archive  # noqa: F401  (a fixture)


def test_debug_anywhere_on_the_line(tmp_path):
    for args in (["inspect", str(tmp_path / "nope"), "--debug"], ["--debug", "inspect", "x"]):
        run = cli(*args, cwd=tmp_path)
        assert run.code == 2, run.stderr
        assert "Traceback" in run.stderr and "ArchiveError" in run.stderr
        assert run.lines[-1].startswith("error: ")
    run = cli("inspect", str(tmp_path / "nope"), cwd=tmp_path)
    assert "Traceback" not in run.stderr  # not left on from the runs before


def _commands(group, path=()):
    for name, command in group.commands.items():
        if getattr(command, "commands", None):
            yield from _commands(command, (*path, name))
        yield (*path, name)


def test_help_is_readable_at_80_columns_with_examples_whole():
    import typer.main

    runner = CliRunner()
    root = typer.main.get_command(app)
    helps = {}
    for path in [(), *_commands(root)]:
        result = runner.invoke(app, [*path, "--help"], env={"COLUMNS": "80"})
        assert result.exit_code == 0, (path, result.output)
        helps[path] = result.output
        for line in result.output.splitlines():
            assert len(line) <= 80, (path, line)
        assert "…" not in result.output, path  # rich's cut
        assert "│" not in result.output, path  # no panels squeezing the text
    top = helps[()]
    assert "Simulate a crawler LiDAR scan of a pipe and write it as a\n" in top  # not cut
    simulate = " ".join(helps[("simulate",)].split())
    assert "e.g. spurious_return_ratio=0.02 or slip_duration_s=0.5,2" in simulate
    assert "[default: the scenario's]" in simulate  # once eaten as markup
    inspect = helps[("inspect",)]
    assert "    pipescan inspect runs/MH1042-MH1043.zip --report reports/MH1042.pdf\n" in inspect
    assert (
        "pipescan trend MH1042-MH1043 --chainage 41.5 --plot plots/MH1042.svg"
        in (helps[("trend",)])
    )


@pytest.mark.parametrize("as_json", [False, True])
def test_re_inspecting_says_it_replaced_the_stored_rows(
    as_json,
    tmp_path,
    stored,  # noqa: F811
    monkeypatch,
):
    from pipescan.flows.inspect import InspectionSummary

    def run(db_url: str) -> str:
        def fake_run(archive, url, report, params):
            return InspectionSummary(
                inspection_id=1, asset_id="MH1-MH2", inspected_at="2025-03-14T09:30:00+00:00",
                archive=archive, frame_count=2, point_count=200, scanned_length_m=1.0,
                section_count=10, sections_ok=10, defect_count=0, max_blockage_ratio=0.01,
                max_blockage_chainage_m=0.5, unmeasured_by_status={}, registration={},
                start_source=None, report_path=None, wall_time_s=1.0,
            )  # fmt: skip

        monkeypatch.setattr(scan, "_run_inspection", fake_run)
        monkeypatch.setattr(scan, "_inspection_params", lambda *a, **k: None)
        archive = write_archive(tmp_path / f"site{len(list(tmp_path.iterdir()))}")
        args = ["inspect", str(archive), "--db", db_url] + (["--json"] if as_json else [])
        result = CliRunner().invoke(app, args)
        assert result.exit_code == 0, result.output
        return result.output

    again = run(stored)  # inspection 1 is stored there
    assert "replaced the stored rows of inspection 1" in again
    first = run(f"sqlite:///{tmp_path / 'new.db'}")
    assert "replaced" not in first.replace('"replaced": false', "")
    if as_json:
        assert '"replaced": true' in again and '"replaced": false' in first
    assert not Path(tmp_path / "new.db").exists()  # looking did not create it
    assert dataclasses.is_dataclass(InspectionSummary)


def test_the_summary_names_unmeasured_sections_as_the_report_does(tmp_path):
    from pipescan.core.model import SectionMeasures, SectionStatus
    from pipescan.flows.inspect import InspectionSummary
    from pipescan.storage.database import repository
    from pipescan.storage.database.db import connect
    from tests.test_db import NOMINAL_AREA_M2, item, make_meta, make_sections

    scatter = SectionMeasures(
        0.5, 0.6, NOMINAL_AREA_M2, SectionStatus.TOO_FEW_POINTS, point_count=27_043,
        coverage_ratio=0.99,
    )  # fmt: skip
    url = f"sqlite:///{tmp_path / 'p.db'}"
    engine = connect(url)
    try:
        iid = repository.save_inspection(
            engine, item(meta=make_meta(), sections=[*make_sections(5), scatter])
        )
    finally:
        engine.dispose()
    summary = InspectionSummary(
        inspection_id=iid, asset_id="MH1042-MH1043", inspected_at="x", archive="a",
        frame_count=1, point_count=1, scanned_length_m=0.6, section_count=6, sections_ok=4,
        defect_count=0, max_blockage_ratio=None, max_blockage_chainage_m=None,
        unmeasured_by_status={"too_few_points": 2}, registration={}, start_source=None,
        report_path=None, wall_time_s=1.0,
    )  # fmt: skip
    assert scan._unmeasured_lines(url, summary) == [
        "    1 not measured (too few points)",
        "    1 not measured (uncertain: wall scatter)",
    ]
    # Without the stored sections: the stored names, in words.
    gone = f"sqlite:///{tmp_path / 'gone' / 'p.db'}"
    assert scan._unmeasured_lines(gone, summary) == ["    2 not measured (too few points)"]
