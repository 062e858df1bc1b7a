"""End to end: simulate, inspect (a real Prefect flow run), export, report; check the figures
against the simulator's ground truth, and the PDF's text against the database."""

from __future__ import annotations

import csv
import io
import json
from collections import Counter

import numpy as np
import pytest
from prefect.testing.utilities import prefect_test_harness
from pypdf import PdfReader
from threadpoolctl import threadpool_info, threadpool_limits
from typer.testing import CliRunner

from pipescan.cli import app
from pipescan.core.instrument import consecutive_frame_indices
from pipescan.core.registration import (
    RegistrationParams,
    plan_chunks,
    sample_frame_indices,
    used_frame_indices,
)
from pipescan.flows.inspect import InspectionParams, inspect_archive
from pipescan.settings import use_settings
from pipescan.simulator.archive import read_ground_truth, write_simulated_archive
from pipescan.simulator.scan import get_scenario, simulate_scan
from pipescan.storage.input import archive as archive_module
from pipescan.storage.input.metadata import read_inspection_toml
from pipescan.storage.scratch import FrameStore, create_run_dir
from pipescan.tasks.inspection import register_chunk
from pipescan.tasks.storing import stage_archive

pytestmark = pytest.mark.e2e


@pytest.fixture(scope="module")
def prefect():
    with prefect_test_harness(server_startup_timeout=60):
        yield


@pytest.fixture(scope="module")
def archive(tmp_path_factory):
    # The paper scenario up to the obstacle and into the deposits, at 2/3 of the point rate.
    scan = simulate_scan(get_scenario("paper", travel_m=2.6, points_per_s=300_000), seed=1)
    return write_simulated_archive(scan, tmp_path_factory.mktemp("scan") / "arc")


_decoded: Counter[str] = Counter()
"""How many times the inspection decoded each frame file."""

_library_threads: dict[str, set[int]] = {}
"""The native libraries' thread counts (BLAS, OpenMP) in this process, before and after the
inspection."""


def _threads() -> set[int]:
    return {pool["num_threads"] for pool in threadpool_info()}


@pytest.fixture(scope="module")
def inspected(prefect, archive, tmp_path_factory):
    work = tmp_path_factory.mktemp("run")
    db_url = f"sqlite:///{work / 'pipescan.db'}"
    read_points = archive_module.read_points

    def counted(path, **kwargs):
        _decoded[kwargs.get("member") or str(path)] += 1
        return read_points(path, **kwargs)

    with (
        use_settings(database_url=db_url),  # the database is a setting, not a flow parameter
        pytest.MonkeyPatch.context() as mp,
    ):
        mp.setattr(archive_module, "read_points", counted)
        # As a process whose libraries use two threads (their default on two cores).
        threadpool_limits(limits=2)
        _library_threads["before"] = _threads()
        summary = inspect_archive(
            archive=str(archive),
            report_path=str(work / "report.pdf"),
            params=InspectionParams(chunk_frames=50),
            work_dir=str(work / "scratch"),
        )
    _library_threads["after"] = _threads()
    return summary, db_url, work


def test_the_run_lets_the_libraries_use_one_thread(inspected):
    """pipescan keeps the cores busy itself: the libraries' own threads would only spin on
    them (``PIPESCAN_LIBRARY_THREADS``, default 1; flows.runners.limit_library_threads)."""
    assert _library_threads["before"] == {2}
    assert _library_threads["after"] == {1}


def test_each_frame_is_decoded_once(inspected, archive, tmp_path):
    """Registration decodes every frame once (the frame two chunks share: once per chunk),
    registers the stride's frames and those it read to look closer, and keeps every frame for
    the sections; the axis and the sections read what it kept, never the archive. In
    the flow, chunks register in the engine pool's processes: the flow's own process decodes
    only the few frames the instrument and the stride are read from (survey_scan). The same
    chunks registered here count what registration decodes."""
    summary, _, _ = inspected
    assert summary.frame_count > 100
    stride = summary.registration["frame_stride"]
    assert stride > 1  # the scan is denser in time than its sections need
    meta_files = [
        f.file for f in read_inspection_toml(archive / "inspection.toml", archive="arc").frames
    ]
    n = summary.frame_count
    looked = set(sample_frame_indices(n)) | set(consecutive_frame_indices(n))
    sampled = {meta_files[i] for i in looked}
    assert set(_decoded) == sampled, "the flow's own process decoded other frames"
    assert set(_decoded.values()) == {1}
    staged = stage_archive.fn(str(archive), create_run_dir(tmp_path / "work"))
    chunks = plan_chunks(summary.frame_count, 20, stride)
    assert len(chunks) > 1
    read_points = archive_module.read_points
    read_timed_frame = archive_module.read_timed_frame
    decoded: Counter[str] = Counter()

    def counted(path, **kwargs):
        decoded[kwargs.get("member") or str(path)] += 1
        return read_points(path, **kwargs)

    def counted_timed(path, **kwargs):  # LAS/LAZ frames, read with their point times
        decoded[kwargs.get("member") or str(path)] += 1
        return read_timed_frame(path, **kwargs)

    store = FrameStore(tmp_path / "frames")
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(archive_module, "read_points", counted)
        mp.setattr(archive_module, "read_timed_frame", counted_timed)
        registered = {
            i
            for a, b in chunks
            for i in register_chunk.fn(
                staged, a, b, RegistrationParams(), store, 6.0, stride=stride
            ).frame_indices
        }
    shared = {meta_files[b] for _, b in chunks[:-1]}
    used = used_frame_indices(summary.frame_count, stride)
    # The stride's frames, and those read to look closer where ICP disagreed with the
    # odometer: each decoded once.
    closer = summary.registration["frames_looked_closer"]
    assert summary.registration["frames"] == len(used) + closer < summary.frame_count
    assert set(used) <= registered < set(range(n))
    assert set(decoded) == set(meta_files)
    assert {f for f, n in decoded.items() if n != 1} == shared
    assert {decoded[f] for f in shared} == {2}
    # Every frame is kept for the sections, registered or not.
    kept = [i for a, _ in chunks for i, _ in store.iter_frames(a)]
    assert set(kept) == set(range(n))
    assert len(kept) == n + len(shared)


def test_a_chunk_registers_the_same_in_an_engine_worker(archive, tmp_path):
    """The engine pool's worker gives the trajectory this process gives, to the bit, and
    stores the same frames for the sections."""
    staged = stage_archive.fn(str(archive), create_run_dir(tmp_path / "work"))
    params = RegistrationParams()
    here = register_chunk.fn(staged, 40, 99, params, FrameStore(tmp_path / "here"), 6.0)
    there = register_chunk.fn(
        staged, 40, 99, params, FrameStore(tmp_path / "there"), 6.0, engine_processes=2
    )
    assert there.frame_indices == here.frame_indices
    assert np.array_equal(there.T_world_frame, here.T_world_frame)
    assert repr(there.quality) == repr(here.quality)  # NaN where a figure does not apply
    ours = list(FrameStore(tmp_path / "here").iter_frames(40))
    theirs = list(FrameStore(tmp_path / "there").iter_frames(40))
    assert [i for i, _ in theirs] == [i for i, _ in ours] == list(range(40, 100))
    assert all(np.array_equal(p, q) for (_, p), (_, q) in zip(ours, theirs, strict=True))


def _exported_sections(db_url: str, inspection_id: int) -> list[dict[str, str]]:
    result = CliRunner().invoke(
        app,
        [
            "export",
            "sections",
            "--inspection",
            str(inspection_id),
            "--format",
            "csv",
            "--db",
            db_url,
        ],
    )
    assert result.exit_code == 0, result.output
    return list(csv.DictReader(io.StringIO(result.stdout)))


def test_flow_stores_sections_that_match_ground_truth(inspected, archive):
    summary, db_url, _ = inspected
    rows = _exported_sections(db_url, summary.inspection_id)
    assert len(rows) == summary.section_count > 20
    for column in (
        "asset_id",
        "inspected_at",
        "chainage_start_m",
        "chainage_end_m",
        "open_area_m2",
        "blockage_ratio",
        "coverage_ratio",
        "status",
    ):
        assert column in rows[0]
    _, truth = read_ground_truth(archive)
    true_by_start = {round(t.chainage_start_m, 1): t for t in truth}
    ok = [r for r in rows if r["status"] == "ok"]
    assert len(ok) >= 15
    errors = [
        abs(
            float(r["blockage_ratio"])
            - true_by_start[round(float(r["chainage_start_m"]), 1)].blockage_ratio
        )
        for r in ok
    ]
    # Issue 4's targets, here with estimated poses (measured: mean 0.10 pp, max 0.67 pp at the
    # rear of the obstacle, where part of the free space beside it is hidden from the sensor).
    assert sum(errors) / len(errors) < 0.003
    assert max(errors) < 0.010
    # Sections that are not ok export no figure (empty cells, never 0), only the reason.
    not_ok = [r for r in rows if r["status"] != "ok"]
    assert not_ok
    for r in not_ok:
        assert r["blockage_ratio"] == r["open_area_m2"] == r["ovality_ratio"] == "", r
        assert r["coverage_ratio"] != "" and int(r["point_count"]) >= 0
    # Every section in an occlusion shadow is reported as not ok.
    for r in rows:
        t = true_by_start.get(round(float(r["chainage_start_m"]), 1))
        if t is not None and t.in_shadow and t.coverage_ratio < 0.9:
            assert r["status"] != "ok", r


def test_pdf_holds_asset_flagged_chainages_and_database_figures(inspected):
    summary, db_url, work = inspected
    text = "\n".join(page.extract_text() for page in PdfReader(work / "report.pdf").pages)
    assert summary.asset_id in text
    assert "None" not in text and "nan" not in text
    defects = CliRunner().invoke(
        app, ["export", "defects", "--inspection", str(summary.inspection_id), "--db", db_url]
    )
    rows = list(csv.DictReader(io.StringIO(defects.stdout)))
    assert rows, "the paper scenario has defects to flag"
    for d in rows:
        assert f"{float(d['chainage_start_m']):.2f}" in text
    worst = f"{100 * summary.max_blockage_ratio:.1f}"
    assert worst in text


def test_cli_report_and_json_summary(inspected, archive, tmp_path):
    summary, db_url, _ = inspected
    out = tmp_path / "again.pdf"
    result = CliRunner().invoke(
        app, ["report", "--inspection", str(summary.inspection_id), "-o", str(out), "--db", db_url]
    )
    assert result.exit_code == 0, result.output
    assert out.read_bytes().startswith(b"%PDF")
    # Re-inspecting the same archive with the same parameters replaces, never duplicates,
    # and keeps the inspection's id: the report of that id still works.
    again = CliRunner().invoke(app, ["inspect", str(archive), "--db", db_url, "--json"])
    assert again.exit_code == 0, again.output
    payload = json.loads(again.stdout[again.stdout.index("{") :])
    assert payload["asset_id"] == summary.asset_id
    assert payload["inspection_id"] == summary.inspection_id
    listing = CliRunner().invoke(app, ["inspections", "--db", db_url])
    assert listing.stdout.count(summary.asset_id) == 1
    result = CliRunner().invoke(
        app, ["report", "--inspection", str(summary.inspection_id), "-o", str(out), "--db", db_url]
    )
    assert result.exit_code == 0, result.output


def test_bad_archive_fails_cleanly_and_writes_nothing(prefect, tmp_path):
    bad = tmp_path / "bad"
    (bad / "frames").mkdir(parents=True)
    (bad / "inspection.toml").write_text(
        'asset_id = "X1"\ninspected_at = "2025-13-45"\nnominal_diameter_m = 500\n'
    )
    db_url = f"sqlite:///{tmp_path / 'p.db'}"
    result = CliRunner().invoke(app, ["inspect", str(bad), "--db", db_url])
    assert result.exit_code == 2
    assert "inspection.toml" in result.output and "inspected_at" in result.output
    # Nothing written: not even the database was created.
    assert not (tmp_path / "p.db").exists()
    listing = CliRunner().invoke(app, ["inspections", "--db", db_url])
    assert listing.exit_code == 2 and "no database at" in listing.output
