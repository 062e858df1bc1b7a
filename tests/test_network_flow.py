"""The ``inspect-network`` flow on a Prefect server: retries only on I/O, one bad archive failing
alone, a re-run reusing what is stored (one copy of each inspection), the network report."""

from __future__ import annotations

import json
import re
import shutil
import tarfile
import time
import zipfile

import pytest
from prefect import flow, task
from prefect.testing.utilities import prefect_test_harness
from sqlalchemy.engine import make_url
from typer.testing import CliRunner

from pipescan.cli import app
from pipescan.core.errors import GeometryError
from pipescan.flows.network import NetworkIncomplete, format_network_summary, inspect_network
from pipescan.settings import use_settings
from pipescan.simulator.archive import read_ground_truth
from pipescan.storage.database.db import StorageError, connect, upgrade
from pipescan.storage.database.repository import list_inspections
from pipescan.tasks.retries import IO_RETRY_OPTIONS
from tests.netstore import asset_id, write_archive, write_store
from tests.pg_cluster import free_port

pytestmark = pytest.mark.e2e


@pytest.fixture(scope="module")
def prefect():
    with prefect_test_harness(server_startup_timeout=60):
        yield


def test_io_errors_are_retried_with_backoff_and_geometry_errors_never(prefect):
    attempts = {"io": 0, "geometry": 0}

    def flaky_read() -> str:
        attempts["io"] += 1
        if attempts["io"] < 3:
            raise ConnectionResetError("store connection reset")
        return "read"

    def bad_geometry() -> str:
        attempts["geometry"] += 1
        raise GeometryError("the cloud holds no pipe")

    options = {**IO_RETRY_OPTIONS, "retry_delay_seconds": 0}
    read = task(flaky_read).with_options(**options)
    measure = task(bad_geometry).with_options(**options)

    @flow
    def run() -> tuple[str, str]:
        value = read()
        try:
            measure()
        except GeometryError as exc:
            return value, str(exc)
        return value, "no error"

    assert run() == ("read", "the cloud holds no pipe")
    assert attempts == {"io": 3, "geometry": 1}
    assert IO_RETRY_OPTIONS["retries"] == 3
    assert IO_RETRY_OPTIONS["retry_delay_seconds"](3) == [2.0, 4.0, 8.0]


def _stored(db_url: str):
    engine = connect(db_url)
    try:
        return list_inspections(engine)
    finally:
        engine.dispose()


def test_a_bad_archive_fails_alone_and_a_rerun_reuses_what_is_stored(
    prefect, tmp_path, monkeypatch
):
    root = tmp_path / "store"
    paths = write_store(root, 2, bad=True)
    db_url = f"sqlite:///{tmp_path / 'net.db'}"
    monkeypatch.setenv("PIPESCAN_DATABASE_URL", db_url)
    rendered = []

    def fake_network_report(database_url, out_path, *, since=None, inspection_ids=None, failed=()):
        rendered.append((database_url, out_path, inspection_ids))
        reported_failures.extend(failed)
        return out_path

    reported_failures = []

    monkeypatch.setattr(
        "pipescan.tasks.reporting.render_network_report", fake_network_report, raising=False
    )
    monkeypatch.setenv("PIPESCAN_REPORTS_DIR", str(tmp_path / "reports"))
    run = dict(
        store=str(root),
        work_dir=str(tmp_path / "work"),
        concurrency=3,
        task_runner="threads",
        workers=1,
    )
    first_state = inspect_network(**run, return_state=True)
    # An archive not stored: the run is not green, its message names it.
    assert first_state.is_failed(), first_state
    assert "MH99-BAD" in first_state.message and "own content" in first_state.message
    incomplete = first_state.result(raise_on_failure=False)
    assert isinstance(incomplete, NetworkIncomplete), (first_state, incomplete)
    first = incomplete.summary

    assert first.counts == _counts(inspected=2, failed=1)
    [failed] = first.failures
    assert failed.label == "MH99-BAD" and failed.error_type == "MetadataError"
    assert (failed.cause, failed.attempts) == ("content", 1)
    assert "inspection.toml" in failed.error and "inspected_at" in failed.error
    assert [o.label for o in first.outcomes] == ["MH0-MH1", "MH1-MH2", "MH99-BAD"]
    stored = _stored(db_url)
    assert sorted(r.asset_id for r in stored) == [asset_id(0), asset_id(1)]
    by_asset = {r.asset_id: r.id for r in stored}
    for i, outcome in enumerate(first.outcomes[:2]):
        assert outcome.inspection_id == by_asset[asset_id(i)]
        # The worst section is where the simulator put the obstacle, and as large.
        _, truth = read_ground_truth(paths[i])
        at = min(truth, key=lambda t: abs(t.chainage_start_m - outcome.max_blockage_chainage_m))
        assert outcome.max_blockage_ratio == pytest.approx(at.blockage_ratio, abs=0.03)
        assert outcome.max_blockage_ratio > 0.10 and outcome.defect_count >= 1
    assert [o.max_blockage_ratio for o in first.worst] == sorted(
        [o.max_blockage_ratio for o in first.outcomes[:2]], reverse=True
    )
    ids = [by_asset[asset_id(i)] for i in (0, 1)]
    # The network report is named by date and run, in the reports folder.
    [(url, report, report_ids)] = rendered
    assert (url, report.parent, report_ids) == (db_url, tmp_path / "reports", ids)
    run_name = _flow_run(first_state).name
    assert re.fullmatch(rf"network-\d{{4}}-\d\d-\d\d-{run_name}\.pdf", report.name), report
    assert first.network_report_path == str(report)
    # Progress, one line per archive, reaches the run's log in Prefect (and its UI).
    logged = _logged(first_state)
    assert sum(f"[{n}/3]" in line for line in logged for n in (1, 2, 3)) == 3, logged
    assert any("[" in line and "MH99-BAD FAILED" in line for line in logged), logged
    # The report lists the archive that failed, with its one-line reason.
    [(label, reason)] = [(f.label, f.reason) for f in reported_failures]
    assert label == "MH99-BAD" and reason.endswith(failed.error)
    assert reason.startswith("the archive itself (fix it; it is not retried)")

    # Started again: nothing is processed twice, nothing is stored twice; and a network
    # report that fails is recorded, not fatal.
    def broken(database_url, out_path, *, since=None, inspection_ids=None, failed=()):
        raise RuntimeError("no fonts")

    monkeypatch.setattr("pipescan.tasks.reporting.render_network_report", broken)
    second_state = inspect_network(**run, return_state=True)
    incomplete = second_state.result(raise_on_failure=False)
    assert isinstance(incomplete, NetworkIncomplete), (second_state, incomplete)
    second = incomplete.summary
    assert second.counts == _counts(reused=2, failed=1)
    assert [o.label for o in second.outcomes] == ["MH0-MH1", "MH1-MH2", "MH99-BAD"]
    assert [o.inspection_id for o in second.outcomes[:2]] == ids
    assert [(o.max_blockage_ratio, o.defect_count) for o in second.outcomes[:2]] == [
        (o.max_blockage_ratio, o.defect_count) for o in first.outcomes[:2]
    ]
    assert sorted(r.id for r in _stored(db_url)) == sorted(ids)
    assert second.network_report_path is None
    assert second.network_report_error == "RuntimeError: no fonts"
    assert _flow_run(second_state).name != run_name  # so its report would not replace the first


def _counts(**given: int) -> dict[str, int]:
    return {k: given.get(k, 0) for k in ("inspected", "reused", "duplicate", "failed", "missing")}


def _flow_run(state):
    from prefect.client.orchestration import get_client

    with get_client(sync_client=True) as client:
        return client.read_flow_run(state.state_details.flow_run_id)


def _logged(state) -> list[str]:
    """The messages of a flow run's log in Prefect, once its last line (the summary's) is
    there: logs reach the API in batches."""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import LogFilter, LogFilterFlowRunId

    flow_run_id = state.state_details.flow_run_id
    deadline = time.monotonic() + 30
    with get_client(sync_client=True) as client:
        while True:
            logs = client.read_logs(
                LogFilter(flow_run_id=LogFilterFlowRunId(any_=[flow_run_id])), limit=200
            )
            messages = [entry.message for entry in logs]
            if any("network report" in m for m in messages) or time.monotonic() > deadline:
                return messages
            time.sleep(0.5)


def test_zip_and_tar_archives_in_a_store_are_inspected(prefect, tmp_path, monkeypatch):
    monkeypatch.setenv("PIPESCAN_DATABASE_URL", f"sqlite:///{tmp_path / 'z.db'}")
    root = tmp_path / "store"
    root.mkdir()
    packed = [write_archive(root, 5, kind="zip"), write_archive(root, 6, kind="gztar")]
    assert zipfile.is_zipfile(packed[0]) and tarfile.is_tarfile(packed[1])
    summary = inspect_network(
        store=str(root),
        work_dir=str(tmp_path / "work"),
        write_network_report=False,
    )
    assert [o.status for o in summary.outcomes] == ["inspected", "inspected"], summary.failures


def test_one_scan_under_two_names_is_one_inspection_said_once(prefect, tmp_path, monkeypatch):
    db_url = f"sqlite:///{tmp_path / 'dup.db'}"
    monkeypatch.setenv("PIPESCAN_DATABASE_URL", db_url)
    root = tmp_path / "store"
    folder = write_archive(root, 3)
    shutil.make_archive(str(root / "real459-nested"), "zip", folder)  # the same scan, zipped
    run = dict(store=str(root), work_dir=str(tmp_path / "work"), write_network_report=False)
    for _ in range(2):  # processed now, then reused: said once either way
        summary = inspect_network(**run, concurrency=2)
        statuses = sorted((o.label, o.status, o.same_as) for o in summary.outcomes)
        assert statuses[0] == ("MH3-MH4", statuses[0][1], None)
        assert statuses[1] == ("real459-nested", "duplicate", "MH3-MH4")
        assert len({o.inspection_id for o in summary.outcomes}) == 1
        assert [o.label for o in summary.worst] == ["MH3-MH4"]
        text = "\n".join(format_network_summary(summary))
        assert text.count("real459-nested") == 1, text
        assert "real459-nested = MH3-MH4" in text
    assert len(_stored(db_url)) == 1


# --- the database, checked once before any archive ---------------------------------------------


def test_an_unreachable_database_is_one_error_before_any_archive(prefect, tmp_path):
    url = f"postgresql+psycopg://pipescan:secret@127.0.0.1:{free_port()}/pipescan"
    # The store does not exist: the database is checked before the archives are looked for.
    missing = str(tmp_path / "no-such-store")
    with use_settings(database_url=url), pytest.raises(StorageError, match="cannot open database"):
        inspect_network(store=missing)
    result = CliRunner().invoke(app, ["inspect-network", missing, "--db", url])
    assert result.exit_code == 2, result.output
    [line] = result.output.strip().splitlines()
    assert line.startswith("error: cannot open database postgresql+psycopg://127.0.0.1:")
    assert "secret" not in result.output


@pytest.mark.parametrize("problem", ["not migrated", "read-only"])
def test_a_database_that_cannot_take_the_run_is_refused_before_any_archive(
    prefect, postgres_url, tmp_path, problem
):
    url = postgres_url
    if problem == "read-only":
        upgrade(postgres_url)
        options = make_url(postgres_url).query["options"]
        url = (
            make_url(postgres_url)
            .update_query_dict({"options": f"{options} -cdefault_transaction_read_only=on"})
            .render_as_string(hide_password=False)
        )
    expected = {
        "not migrated": r"schema revision none .*pipescan db upgrade",
        "read-only": r"refuses writes: cannot execute UPDATE in a read-only transaction",
    }[problem]
    with use_settings(database_url=url), pytest.raises(StorageError, match=expected):
        inspect_network(store=str(tmp_path / "no-such-store"))


# --- no database URL in Prefect ----------------------------------------------------------------


def test_the_cli_keeps_the_database_url_out_of_the_runs_prefect_keeps(prefect, tmp_path):
    root = tmp_path / "store"
    [archive] = write_store(root, 1)
    marker = "Zq7-not-for-prefect"
    db = f"sqlite:///{tmp_path / marker}.db"
    before = {r.id for r in _all_flow_runs()}
    for args in (["inspect", str(archive)], ["inspect-network", str(root), "--no-network-report"]):
        result = CliRunner().invoke(app, [*args, "--db", db])
        assert result.exit_code == 0, result.output
    # inspect: one inspect-archive run; inspect-network: its run and one inspect-archive run.
    runs = [r for r in _all_flow_runs() if r.id not in before]
    assert len(runs) == 3
    assert all(r.parameters and marker not in json.dumps(r.parameters) for r in runs), [
        r.parameters for r in runs
    ]
    assert len(_stored(db)) == 1  # the same archive: stored once, where --db said


def _all_flow_runs() -> list:
    from prefect.client.orchestration import get_client

    with get_client(sync_client=True) as client:
        return client.read_flow_runs(limit=200)
