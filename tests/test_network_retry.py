"""No pipe left behind: a network run retries an archive that failed for a transient cause
(within a stated window, with backoff), never one that failed for its own content, ends Failed
naming what is still missing, and the next run takes the missing archives first.

The sub-flow is replaced by a fake that fails on cue, so that these run in seconds; the real
sub-flow's failures are classified by ``failure_cause``, tested on the errors it raises."""

from __future__ import annotations

import json

import httpx
import pytest
import sqlalchemy as sa
from prefect import flow
from prefect.exceptions import CrashedRun
from prefect.testing.utilities import prefect_test_harness
from typer.testing import CliRunner

import pipescan.flows.network as network
from pipescan.cli import app
from pipescan.core.errors import MetadataError
from pipescan.flows.inspect import InspectionSummary
from pipescan.flows.network import (
    ArchiveOutcome,
    NetworkIncomplete,
    backoff_delay,
    format_network_summary,
    inspect_network,
    merge_duplicates,
)
from pipescan.settings import database_url, get_settings
from pipescan.storage.database.db import StorageError, connect
from pipescan.tasks.network import unstored_first
from pipescan.tasks.retries import failure_cause
from tests.test_db import save

# --- what counts as transient -------------------------------------------------------------------


def _wrapped(outer: BaseException, inner: BaseException) -> BaseException:
    try:
        try:
            raise inner
        except BaseException as exc:
            raise outer from exc
    except BaseException as raised:
        return raised


class _PgError(Exception):
    def __init__(self, message: str, sqlstate: str | None):
        super().__init__(message)
        self.sqlstate = sqlstate


def _db_error(message: str, sqlstate: str | None) -> BaseException:
    return _wrapped(
        StorageError(f"cannot open database: {message}"),
        sa.exc.OperationalError("connect", {}, _PgError(message, sqlstate)),
    )


def _slot_error() -> BaseException:
    from prefect.concurrency._asyncio import ConcurrencySlotAcquisitionError

    return _wrapped(
        ConcurrencySlotAcquisitionError("Unable to acquire concurrency slots on ['x']"),
        httpx.ConnectError("All connection attempts failed"),
    )


def _http_500() -> BaseException:
    request = httpx.Request("POST", "http://prefect/api/task_runs/")
    response = httpx.Response(500, request=request)
    return httpx.HTTPStatusError("Internal Server Error", request=request, response=response)


@pytest.mark.parametrize(
    ("make", "cause"),
    [
        (lambda: _db_error("connection refused", None), "transient"),
        (lambda: _db_error("unable to open database file", None), "transient"),
        (lambda: _db_error('password authentication failed for user "p"', "28P01"), "content"),
        (lambda: _db_error('database "nope" does not exist', "3D000"), "content"),
        (_slot_error, "transient"),
        (lambda: httpx.ConnectError("All connection attempts failed"), "transient"),
        (_http_500, "transient"),
        (lambda: CrashedRun("the sub-flow was marked Crashed"), "transient"),
        (lambda: ConnectionRefusedError(111, "refused"), "transient"),
        (lambda: MetadataError("missing inspected_at"), "content"),
        (lambda: _wrapped(MetadataError("bad toml"), OSError(5, "io")), "content"),
        (lambda: KeyError("a defect of pipescan"), "error"),
    ],
)
def test_failures_are_classed_as_transient_content_or_error(make, cause):
    assert failure_cause(make()) == cause


def test_backoff_doubles_up_to_its_cap():
    assert [backoff_delay(15, 120, n) for n in range(1, 7)] == [15, 30, 60, 120, 120, 120]


def test_archives_without_a_stored_inspection_go_first():
    archives = ["/s/a", "/s/b", "/s/c", "/s/d"]
    assert unstored_first(archives, {"/s/a", "/s/c"}) == ["/s/b", "/s/d", "/s/a", "/s/c"]


def _outcome(label: str, status: str, inspection_id: int | None = None, **kw) -> ArchiveOutcome:
    return ArchiveOutcome(
        archive=f"/s/{label}",
        label=label,
        status=status,
        wall_time_s=1.0,
        inspection_id=inspection_id,
        asset_id="A" if inspection_id else None,
        **kw,
    )


def test_the_same_content_under_two_names_is_one_entry_said_once():
    merged = merge_duplicates(
        [
            _outcome("good-real", "reused", 1),
            _outcome("other", "inspected", 2),
            _outcome("real459-nested", "inspected", 1),
        ]
    )
    assert [(o.label, o.status, o.same_as) for o in merged] == [
        ("good-real", "inspected", None),
        ("other", "inspected", None),
        ("real459-nested", "duplicate", "good-real"),
    ]
    summary = network.NetworkSummary(
        store="/s",
        executor="local",
        outcomes=merged,
        worst=[],
        wall_time_s=1.0,
        counts={k: sum(o.status == k for o in merged) for k in network.STATUSES},
    )
    text = "\n".join(format_network_summary(summary))
    assert "2 inspected, 0 reused (already stored), 1 the same content as another" in text
    assert text.count("real459-nested") == 1 and "real459-nested = good-real" in text


# --- the flow, with a fake sub-flow --------------------------------------------------------------


@pytest.fixture(scope="module")
def prefect():
    with prefect_test_harness(server_startup_timeout=60):
        yield


def _summary(archive: str, inspection_id: int) -> InspectionSummary:
    return InspectionSummary(
        inspection_id=inspection_id,
        asset_id=f"A-{inspection_id}",
        inspected_at="2026-12-01T02:00:00+00:00",
        archive=archive,
        frame_count=1,
        point_count=1,
        scanned_length_m=1.0,
        section_count=1,
        sections_ok=1,
        defect_count=0,
        max_blockage_ratio=0.05,
        max_blockage_chainage_m=0.5,
        unmeasured_by_status={},
        registration={},
        start_source=None,
        report_path=None,
        wall_time_s=0.1,
    )


class Countdown:
    """Fails ``times`` times with ``exc``, then passes."""

    def __init__(self, times: int, exc: BaseException):
        self.times, self.exc = times, exc

    def __call__(self) -> None:
        if self.times > 0:
            self.times -= 1
            raise self.exc


class FakeSubflow:
    """Stands for ``inspect-archive``: archive ``aN`` is stored as inspection N, unless its
    countdown fails it; records the order of the calls."""

    def __init__(self, monkeypatch, failures: dict[str, Countdown]):
        self.failures = failures
        self.calls: list[str] = []
        fake = self

        @flow(name="inspect-archive")
        def fake_inspect_archive(archive, report_path=None, params=None, work_dir=None, **kw):
            name = archive.rstrip("/").rsplit("/", 1)[-1]
            fake.calls.append(name)
            if name in fake.failures:
                fake.failures[name]()
            engine = connect(database_url(get_settings()))
            try:
                stored = save(engine, archive_uri=archive, content_hash=f"sha256:{name}")
            finally:
                engine.dispose()
            return _summary(archive, stored)

        monkeypatch.setattr(network, "inspect_archive", fake_inspect_archive)


def _store(root, names):
    for name in names:
        (root / name).mkdir(parents=True)
        (root / name / "inspection.toml").write_text("", encoding="utf-8")
    return str(root)


@pytest.fixture
def fast_retries(monkeypatch, tmp_path):
    monkeypatch.setattr(network, "RETRY_FIRST_DELAY_S", 0.2)
    monkeypatch.setattr(network, "RETRY_MAX_DELAY_S", 0.4)
    monkeypatch.setenv("PIPESCAN_DATABASE_URL", f"sqlite:///{tmp_path / 'r.db'}")


def _run(store, tmp_path, **kw):
    return inspect_network(
        store=store,
        work_dir=str(tmp_path / "work"),
        write_network_report=False,
        concurrency=2,
        return_state=True,
        **kw,
    )


def test_a_transient_failure_is_retried_within_the_run_and_a_bad_archive_is_not(
    prefect, tmp_path, fast_retries, monkeypatch
):
    fake = FakeSubflow(
        monkeypatch,
        {
            "a2": Countdown(2, _db_error("unable to open database file", None)),
            "a3": Countdown(1, _slot_error()),  # the Prefect server came back
            "a9": Countdown(99, MetadataError("missing inspected_at", file="inspection.toml")),
        },
    )
    store = _store(tmp_path / "store", ["a1", "a2", "a3", "a9"])
    state = _run(store, tmp_path, retry_window_s=30)

    assert state.is_failed(), state  # a bad archive is an archive not stored: not green
    exc = state.result(raise_on_failure=False)
    assert isinstance(exc, NetworkIncomplete)
    by = {o.label: o for o in exc.summary.outcomes}
    assert {k: (o.status, o.attempts) for k, o in by.items()} == {
        "a1": ("inspected", 1),
        "a2": ("inspected", 3),
        "a3": ("inspected", 2),
        "a9": ("failed", 1),
    }
    assert by["a9"].cause == "content" and fake.calls.count("a9") == 1  # never retried
    assert exc.summary.missing == []
    assert state.message.startswith("1 of 4 archives not stored")
    assert "a9" in state.message and "own content" in state.message


def test_what_is_still_missing_fails_the_run_and_goes_first_next_time(
    prefect, tmp_path, fast_retries, monkeypatch
):
    refused = _db_error("connection refused", None)
    fake = FakeSubflow(
        monkeypatch, {"a2": Countdown(10**6, refused), "a4": Countdown(10**6, refused)}
    )
    store = _store(tmp_path / "store", ["a1", "a2", "a3", "a4"])
    state = _run(store, tmp_path, retry_window_s=1.0)

    assert state.is_failed(), state
    summary = state.result(raise_on_failure=False).summary
    assert [o.label for o in summary.missing] == ["a2", "a4"]
    assert all(o.cause == "transient" and o.attempts >= 2 for o in summary.missing)
    assert "missing after" in state.message and "a2" in state.message and "a4" in state.message
    text = "\n".join(format_network_summary(summary))
    assert "MISSING" in text and "the next run takes them first" in text

    # The next run: the missing archives first, then the stored ones (reused).
    fake.failures.clear()
    fake.calls.clear()
    summary = inspect_network(
        store=store, work_dir=str(tmp_path / "work"), write_network_report=False, concurrency=1
    )
    assert fake.calls == ["a2", "a4", "a1", "a3"]
    assert summary.failures == []


def test_the_network_report_goes_into_the_reports_folder(
    prefect, tmp_path, fast_retries, monkeypatch
):
    FakeSubflow(monkeypatch, {})
    written = []

    def fake_report(database_url, out_path, *, inspection_ids=None, failed=(), since=None):
        written.append(out_path)
        return out_path

    monkeypatch.setattr("pipescan.tasks.reporting.render_network_report", fake_report)
    monkeypatch.setenv("PIPESCAN_REPORTS_DIR", str(tmp_path / "elsewhere"))
    store = _store(tmp_path / "store", ["a1"])
    inspect_network(store=store, work_dir=str(tmp_path / "work"), reports_dir=str(tmp_path / "r"))
    [out] = written
    assert out.parent == tmp_path / "r"


# --- start-up survives a blip -------------------------------------------------------------------


def test_the_database_check_at_the_start_waits_out_a_blip(
    prefect, tmp_path, fast_retries, monkeypatch
):
    FakeSubflow(monkeypatch, {})
    monkeypatch.setattr(network, "DATABASE_FIRST_DELAY_S", 0.2)
    real_check = network.checked_database_url
    blip = Countdown(2, _db_error("connection refused", None))

    def flaky_check(settings=None):
        blip()
        return real_check(settings)

    monkeypatch.setattr(network, "checked_database_url", flaky_check)
    store = _store(tmp_path / "store", ["a1"])
    summary = inspect_network(
        store=store, work_dir=str(tmp_path / "work"), write_network_report=False, startup_wait_s=10
    )
    assert [o.status for o in summary.outcomes] == ["inspected"] and blip.times == 0

    # Down for longer than the wait: one error saying how long it tried.
    blip.times = 10**6
    with pytest.raises(StorageError, match=r"connection refused \(still so after \d+ s of trying"):
        inspect_network(store=store, write_network_report=False, startup_wait_s=0.5)


def test_a_refused_login_is_not_waited_on(prefect, tmp_path, fast_retries, monkeypatch):
    calls = []

    def refused(settings=None):
        calls.append(1)
        raise _db_error('password authentication failed for user "p"', "28P01")

    monkeypatch.setattr(network, "checked_database_url", refused)
    with pytest.raises(StorageError, match="password authentication failed"):
        inspect_network(store=str(tmp_path), write_network_report=False, startup_wait_s=60)
    assert len(calls) == 1


def test_a_scheduled_run_waits_five_minutes_for_its_database_and_a_person_does_not(monkeypatch):
    assert network.DATABASE_WAIT_S == 300 and network.RETRY_WINDOW_S == 900
    waits = []
    monkeypatch.setattr(
        network, "wait_for_database", lambda s, wait_s, log: waits.append(wait_s) or 1 / 0
    )
    monkeypatch.setattr(network, "get_run_logger", lambda: network.log)
    for deployed in (True, False):
        monkeypatch.setattr(network, "in_deployment", lambda deployed=deployed: deployed)
        with pytest.raises(ZeroDivisionError):
            inspect_network.fn(store="/nowhere")
    assert waits == [300, 0]


# --- pipescan runs ----------------------------------------------------------------------------


def test_runs_shows_each_runs_outcome_and_what_was_stored_since(
    prefect, tmp_path, fast_retries, monkeypatch
):
    bad = MetadataError("missing inspected_at", file="inspection.toml")
    fake = FakeSubflow(
        monkeypatch,
        {"a2": Countdown(10**6, _db_error("connection refused", None)), "a9": Countdown(99, bad)},
    )
    store = _store(tmp_path / "store", ["a1", "a2", "a9"])
    assert _run(store, tmp_path, retry_window_s=0.5).is_failed()
    fake.failures.pop("a2")  # the database is back: the next run stores a2
    assert _run(store, tmp_path).is_failed()  # a9 is still bad

    result = CliRunner().invoke(app, ["runs", "--json", "--limit", "2"])
    assert result.exit_code == 0, result.output
    newest, older = json.loads(result.output)
    assert (older["state"], older["source"]) == ("FAILED", "outcomes")
    assert {k: v for k, v in older["counts"].items() if v} == {
        "inspected": 1,
        "failed": 1,
        "missing": 1,
    }
    [missing] = older["missing"]
    assert missing["archive"] == "a2" and "connection refused" in missing["why"]
    assert missing["stored_since"] is True
    # (the fake sub-flow stores again what a real one would reuse)
    assert {k: v for k, v in newest["counts"].items() if v} == {"inspected": 2, "failed": 1}
    [failed] = newest["failed"]
    assert failed["archive"] == "a9" and "missing inspected_at" in failed["why"]
    assert failed["stored_since"] is False and newest["missing"] == []
    assert newest["started"] and newest["finished"]

    text = CliRunner().invoke(app, ["runs", "--limit", "2"]).output
    assert "missing a2 [stored since]: " in text
    assert "failed  a9 [still not stored]: " in text


def test_a_run_that_did_not_finish_is_counted_from_its_sub_flows():
    from types import SimpleNamespace as NS

    from pipescan.flows.runs import outcomes_from_subflows

    def sub(name, state, at, message=None):
        return NS(
            name=name,
            expected_start_time=at,
            created=at,
            state=NS(type=NS(value=state), message=message),
        )

    counts, failed, missing = outcomes_from_subflows(
        [
            sub("a1", "COMPLETED", 1),
            sub("a2", "CRASHED", 2, "no heartbeat for 90 s"),
            sub("a3", "FAILED", 3, "cannot open database"),
            sub("a3", "COMPLETED", 4),  # its retry
        ]
    )
    assert (counts["inspected"], counts["missing"], failed) == (2, 1, [])
    assert [(n.archive, n.why) for n in missing] == [("a2", "crashed: no heartbeat for 90 s")]


def test_the_cli_prints_the_summary_and_exits_1_when_an_archive_is_not_stored(
    prefect, tmp_path, fast_retries, monkeypatch
):
    bad = MetadataError("missing inspected_at", file="inspection.toml")
    FakeSubflow(monkeypatch, {"a9": Countdown(99, bad)})
    store = _store(tmp_path / "store", ["a1", "a9"])
    result = CliRunner().invoke(app, ["inspect-network", store, "--no-network-report"])
    assert result.exit_code == 1, result.output
    assert "1 inspected, 0 reused (already stored), 1 failed" in result.stdout
    assert "failed for their own content" in result.stdout and "a9: " in result.stdout
    result = CliRunner().invoke(app, ["inspect-network", store, "--no-network-report", "--json"])
    assert result.exit_code == 1
    payload = json.loads(result.stdout)
    assert [(f["label"], f["cause"]) for f in payload["failures"]] == [("a9", "content")]


def test_a_sub_flow_that_failed_for_a_transient_cause_leaves_no_task_run_pending(prefect):
    from prefect import task
    from prefect.client.orchestration import get_client
    from prefect.states import Pending

    from pipescan.flows.recovery import close_task_runs_of

    @flow(name="inspect-archive")
    def subflow():
        pass

    @task(name="fit-axis")
    def fit_axis():
        pass

    with get_client(sync_client=True) as client:
        run = client.create_flow_run(subflow)
        left = client.create_task_run(fit_axis, run.id, dynamic_key="0", state=Pending())
        assert close_task_runs_of(str(run.id), "slot refused, tried again") == 1
        state = client.read_task_run(left.id).state
    assert (state.type.value, state.message) == ("CRASHED", "slot refused, tried again")


def _stand_in_runs():
    """A network run, an archive's sub-flow and the task that wraps it, by the names the
    recovery looks for (bodies are never run: runs are created through the client)."""
    from prefect import task

    @flow(name="inspect-network")
    def network_run():
        pass

    @flow(name="inspect-archive")
    def subflow():
        pass

    @task(name="archive")
    def archive():
        pass

    return network_run, subflow, archive


def test_what_an_outage_of_prefects_database_left_active_is_closed_at_the_end(prefect):
    """PostgreSQL stopped for 20 s under Prefect left a sub-flow Running and task runs Pending
    after the run was over (their final states were lost). At the end of the run: its sub-flow
    runs still active, their unfinished task runs, and its own task runs whose state is older
    than 30 s (here 2 s) are marked Crashed; a task run whose state is recent (maybe on its way
    through Prefect's event pipeline) is left alone."""
    import time

    from prefect import task
    from prefect.client.orchestration import get_client
    from prefect.states import Pending, Running

    from pipescan.flows.recovery import close_leftovers

    network_run, subflow, archive = _stand_in_runs()

    @task(name="fit-axis")
    def fit_axis():
        pass

    with get_client(sync_client=True) as client:
        run = client.create_flow_run(network_run, state=Running())
        wrapper = client.create_task_run(archive, run.id, "0", state=Running())
        lost = client.create_task_run(archive, run.id, "1", state=Pending())
        sub = client.create_flow_run(subflow, parent_task_run_id=wrapper.id, state=Running())
        inner = client.create_task_run(fit_axis, sub.id, "0", state=Pending())
        time.sleep(2.5)
        recent = client.create_task_run(archive, run.id, "2", state=Running())

        closed = close_leftovers(str(run.id), stale_s=2)
        states = {
            name: client.read_task_run(t.id).state.type.value
            for name, t in [
                ("wrapper", wrapper),
                ("lost", lost),
                ("recent", recent),
                ("inner", inner),
            ]
        }
        sub_state = client.read_flow_run(sub.id).state.type.value
    assert closed == (1, 3)
    assert states == {
        "wrapper": "CRASHED",
        "lost": "CRASHED",
        "recent": "RUNNING",
        "inner": "CRASHED",
    }
    assert sub_state == "CRASHED"
    assert close_leftovers(None) == (0, 0)  # the flow's function called as such


def test_what_a_run_cancelled_on_a_dead_host_left_active_is_closed_by_a_later_run(prefect):
    """A run whose host died is Cancelled by the automation with its sub-flow still Running:
    no process is left to close it, and no automation watches sub-flows. A later run of the
    same deployment closes it (here: once the earlier run ended 1 s ago, not 30 min)."""
    import time

    from prefect.client.orchestration import get_client
    from prefect.states import Cancelled, Running

    from pipescan.flows.recovery import close_abandoned_runs

    network_run, subflow, archive = _stand_in_runs()

    with get_client(sync_client=True) as client:
        deployment = client.create_deployment(client.create_flow(network_run), "nightly")
        dead = client.create_flow_run_from_deployment(deployment, state=Running())
        wrapper = client.create_task_run(archive, dead.id, "0", state=Running())
        sub = client.create_flow_run(subflow, parent_task_run_id=wrapper.id, state=Running())
        client.set_flow_run_state(dead.id, Cancelled(message="its host died"), force=True)
        now = client.create_flow_run_from_deployment(deployment, state=Running())
        assert close_abandoned_runs(str(now.id)) == (0, 0)  # 30 min have not passed
        time.sleep(1.5)
        assert close_abandoned_runs(str(now.id), abandoned_after_s=1) == (1, 1)
        sub_state = client.read_flow_run(sub.id).state
        wrapper_state = client.read_task_run(wrapper.id).state
        alone = client.create_flow_run(network_run, state=Running())
        assert close_abandoned_runs(str(alone.id), abandoned_after_s=1) == (0, 0)
    assert (sub_state.type.value, wrapper_state.type.value) == ("CANCELLED", "CANCELLED")
    assert sub_state.message.startswith("left active by run ")


def test_the_cli_waits_for_its_database_when_told(prefect, tmp_path, fast_retries, monkeypatch):
    FakeSubflow(monkeypatch, {})
    monkeypatch.setattr(network, "DATABASE_FIRST_DELAY_S", 0.2)
    real_check = network.checked_database_url
    blip = Countdown(2, _db_error("connection refused", None))

    def flaky_check(settings=None):
        blip()
        return real_check(settings)

    monkeypatch.setattr(network, "checked_database_url", flaky_check)
    store = _store(tmp_path / "store", ["a1"])
    args = ["inspect-network", store, "--no-network-report"]
    refused = CliRunner().invoke(app, args)  # a person at the terminal: no wait
    assert refused.exit_code == 2 and "connection refused" in refused.output
    blip.times = 2
    waited = CliRunner().invoke(app, [*args, "--wait-for-database", "10"])
    assert waited.exit_code == 0, waited.output
    assert "1 inspected" in waited.stdout and blip.times == 0
