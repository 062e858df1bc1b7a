"""``inspect-network`` on a Dask cluster (a LocalCluster of two worker processes): each archive is
one task, both workers do the work, the figures are right, and only small values cross the wire."""

from __future__ import annotations

import pytest
from distributed import Client, LocalCluster, get_task_stream
from distributed.diagnostics.plugin import SchedulerPlugin
from prefect.testing.utilities import prefect_test_harness

from pipescan.flows.network import inspect_network
from pipescan.simulator.archive import read_ground_truth
from tests.netstore import asset_id, write_store

pytestmark = pytest.mark.e2e

SMALL_RESULT_BYTES = 1_000_000
"""Every task result must stay below this; one archive's points alone are ~11 MB."""


class ResultSizes(SchedulerPlugin):
    """Records the size of every task result the scheduler sees."""

    def __init__(self) -> None:
        self.nbytes: dict[str, int] = {}

    def transition(self, key, start, finish, *args, **kwargs) -> None:
        if finish == "memory" and "nbytes" in kwargs:
            self.nbytes[str(key)] = int(kwargs["nbytes"])


@pytest.fixture(scope="module")
def cluster():
    with (
        LocalCluster(
            n_workers=2,
            threads_per_worker=1,
            processes=True,
            memory_limit="1.5GiB",
            dashboard_address=None,
        ) as cluster,
        Client(cluster) as client,
    ):
        yield cluster, client


def test_tasks_run_on_both_dask_workers_with_small_inputs_and_results(
    cluster, tmp_path, monkeypatch
):
    cluster, client = cluster
    monkeypatch.setenv("PIPESCAN_DATABASE_URL", f"sqlite:///{tmp_path / 'dask.db'}")
    root = tmp_path / "store"
    paths = write_store(root, 2)
    sizes = ResultSizes()
    cluster.scheduler.add_plugin(sizes, name="result-sizes")
    with prefect_test_harness(server_startup_timeout=60), get_task_stream(client) as stream:
        summary = inspect_network(
            store=str(root),
            work_dir=str(tmp_path / "work"),
            concurrency=2,
            dask_address=cluster.scheduler_address,
            write_network_report=False,
        )

    assert summary.executor == f"dask {cluster.scheduler_address} (threads x2 per archive)"
    assert (summary.counts["inspected"], summary.counts["reused"]) == (2, 0), summary.failures
    assert summary.failures == []
    for i, outcome in enumerate(summary.outcomes):
        assert outcome.asset_id == asset_id(i)
        _, truth = read_ground_truth(paths[i])
        at = min(truth, key=lambda t: abs(t.chainage_start_m - outcome.max_blockage_chainage_m))
        assert outcome.max_blockage_ratio == pytest.approx(at.blockage_ratio, abs=0.03)

    # Each archive is one Dask task: both workers took archives, and the work (registration,
    # sections: seconds) happened inside those tasks, on the workers.
    archive_tasks = [r for r in stream.data if r["key"].startswith("inspect_one_archive")]
    assert len(archive_tasks) == 2, [r["key"] for r in stream.data]
    assert {r["worker"] for r in archive_tasks} == set(cluster.scheduler_info["workers"])
    for record in archive_tasks:
        [compute] = [s for s in record["startstops"] if s["action"] == "compute"]
        assert compute["stop"] - compute["start"] > 1.0
    assert sizes.nbytes, "the scheduler saw no task result"
    biggest = max(sizes.nbytes, key=sizes.nbytes.get)
    assert sizes.nbytes[biggest] < SMALL_RESULT_BYTES, biggest
