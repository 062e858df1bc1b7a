"""A scheduled network run survives SIGKILL of its worker, of its flow process, of both (a host
crash), and a restart of the Prefect server, without a person: a real ``prefect server start``,
``pipescan deploy``, a real worker (tests/kill_matrix.py). Afterwards the database holds exactly
one inspection per archive and no run is left active.

Each scenario takes one to three minutes: ``pytest -m slow tests/test_crash_recovery.py``;
``python benchmarks/bench_recovery.py`` prints the same matrix with its timings."""

from __future__ import annotations

import pytest

from tests.kill_matrix import SCENARIOS, format_outcome, run_scenario
from tests.netstore import write_store

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

ARCHIVES = 3


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    root = tmp_path_factory.mktemp("store")
    write_store(root, ARCHIVES)
    return root


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_a_scheduled_run_finishes_after_a_crash_without_a_person(store, tmp_path, scenario):
    outcome = run_scenario(scenario, tmp_path / scenario, store, ARCHIVES, time_limit_s=400)
    report = format_outcome(outcome) + "\n" + "\n".join(outcome.timeline)
    assert outcome.stored_at_kill < ARCHIVES, report  # killed mid-way
    assert outcome.finished_after_s is not None, report
    assert (outcome.inspections, outcome.distinct_identities) == (ARCHIVES, ARCHIVES), report
    assert outcome.network_run_type == "COMPLETED", report
    assert (outcome.active_subflows, outcome.active_task_runs) == (0, 0), report


@pytest.mark.parametrize("scenario", ["db45", "dbstart30", "server105"])
def test_a_scheduled_run_stores_every_archive_through_an_outage(store, tmp_path, scenario):
    """The database refusing connections mid-run (45 s) or at the start (30 s), the Prefect
    server down for 105 s: the run tries again within itself and ends Completed with every
    archive stored once, and ``pipescan runs`` says so."""
    outcome = run_scenario(scenario, tmp_path / scenario, store, ARCHIVES, time_limit_s=400)
    report = format_outcome(outcome) + "\n" + "\n".join(outcome.timeline)
    assert outcome.finished_after_s is not None, report
    assert (outcome.inspections, outcome.distinct_identities) == (ARCHIVES, ARCHIVES), report
    assert outcome.network_run_type == "COMPLETED", report
    assert (outcome.active_subflows, outcome.active_task_runs) == (0, 0), report
    assert outcome.runs_says is not None, report
    assert outcome.runs_says["state"] == "COMPLETED", report
    assert outcome.runs_says["counts"]["inspected"] == ARCHIVES, report
