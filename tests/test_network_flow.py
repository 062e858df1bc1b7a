"""The ``inspect-network`` flow on a Prefect server: retries only on I/O, one bad archive failing
alone, a re-run reusing what is stored (one copy of each inspection), the network report."""

from __future__ import annotations

import tarfile
import zipfile

import pytest
from prefect import flow, task
from prefect.testing.utilities import prefect_test_harness

from pipescan.core.errors import GeometryError
from pipescan.flows.network import inspect_network
from pipescan.simulator.archive import read_ground_truth
from pipescan.storage.database.db import connect
from pipescan.storage.database.repository import list_inspections
from pipescan.tasks.retries import IO_RETRY_OPTIONS
from tests.netstore import asset_id, write_archive, write_store

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
    rendered = []

    def fake_network_report(database_url, out_path, *, since=None, inspection_ids=None, failed=()):
        rendered.append((database_url, out_path, inspection_ids))
        reported_failures.extend(failed)
        return out_path

    reported_failures = []

    monkeypatch.setattr(
        "pipescan.tasks.reporting.render_network_report", fake_network_report, raising=False
    )
    run = dict(
        store=str(root),
        database_url=db_url,
        work_dir=str(tmp_path / "work"),
        concurrency=3,
        task_runner="threads",
        workers=1,
        network_report_path=str(tmp_path / "network.pdf"),
    )
    first = inspect_network(**run)

    assert first.counts == {"inspected": 2, "reused": 0, "failed": 1}
    [failed] = first.failures
    assert failed.label == "MH99-BAD" and failed.error_type == "MetadataError"
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
    assert rendered == [(db_url, tmp_path / "network.pdf", ids)]
    assert first.network_report_path == str(tmp_path / "network.pdf")
    # The report lists the archive that failed, with its one-line reason.
    assert [(f.label, f.reason) for f in reported_failures] == [("MH99-BAD", failed.error)]

    # Started again: nothing is processed twice, nothing is stored twice; and a network
    # report that fails is recorded, not fatal.
    def broken(database_url, out_path, *, since=None, inspection_ids=None, failed=()):
        raise RuntimeError("no fonts")

    monkeypatch.setattr("pipescan.tasks.reporting.render_network_report", broken)
    second = inspect_network(**run)
    assert second.counts == {"inspected": 0, "reused": 2, "failed": 1}
    assert [o.inspection_id for o in second.outcomes[:2]] == ids
    assert [(o.max_blockage_ratio, o.defect_count) for o in second.outcomes[:2]] == [
        (o.max_blockage_ratio, o.defect_count) for o in first.outcomes[:2]
    ]
    assert sorted(r.id for r in _stored(db_url)) == sorted(ids)
    assert second.network_report_path is None
    assert second.network_report_error == "RuntimeError: no fonts"


def test_zip_and_tar_archives_in_a_store_are_inspected(prefect, tmp_path):
    root = tmp_path / "store"
    root.mkdir()
    packed = [write_archive(root, 5, kind="zip"), write_archive(root, 6, kind="gztar")]
    assert zipfile.is_zipfile(packed[0]) and tarfile.is_tarfile(packed[1])
    summary = inspect_network(
        store=str(root),
        database_url=f"sqlite:///{tmp_path / 'z.db'}",
        work_dir=str(tmp_path / "work"),
        write_network_report=False,
    )
    assert [o.status for o in summary.outcomes] == ["inspected", "inspected"], summary.failures
