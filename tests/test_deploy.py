"""``pipescan deploy`` against a real Prefect server (``prefect server start`` on loopback, started
and stopped here): the deployment holds no database URL, ships its recovery automations, checks
the server, the store and the database first; Prefect's own CLI works against the server; a
worker runs the deployment with its own settings and nothing secret reaches Prefect."""

from __future__ import annotations

import json
import os
import re
import sqlite3
import subprocess
import time
from contextlib import contextmanager
from datetime import UTC
from pathlib import Path

import pytest
from prefect.settings import PREFECT_API_URL, temporary_settings
from sqlalchemy.engine import make_url
from typer.testing import CliRunner

from pipescan.cli import app
from pipescan.flows.deploy import (
    CANCELLING_AFTER_S,
    HEARTBEAT_S,
    MAX_ATTEMPTS,
    RECOVERY_TAG,
    RETRY_AFTER_S,
    SILENT_AFTER_S,
)
from pipescan.flows.notification import RUN_ENDED_EVENT
from pipescan.settings import Settings, database_url
from pipescan.storage.database.db import connect, upgrade
from pipescan.storage.database.repository import list_inspections
from tests.netstore import asset_id, write_bad_archive, write_store
from tests.pg_cluster import free_port
from tests.prefect_stack import PIPESCAN, PREFECT, PrefectServer, Worker

pytestmark = pytest.mark.e2e

POOL = "pipescan-test"


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """A Prefect server on 127.0.0.1 with its own home and database."""
    # The scheduler plans runs within a second of a deployment's creation.
    server = PrefectServer(
        tmp_path_factory.mktemp("prefect-home"),
        env={"PREFECT_SERVER_SERVICES_SCHEDULER_LOOP_SECONDS": "1"},
    )
    server.start()
    try:
        yield server
    finally:
        # Send the events this process emitted to the server (deployments, blocks) while it
        # still listens, instead of retrying against a closed port at exit.
        from prefect.events.worker import EventsWorker

        EventsWorker.drain_all(timeout=30)
        server.stop()


@contextmanager
def _on(server: PrefectServer):
    with temporary_settings({PREFECT_API_URL: server.url}):
        yield


def _deploy(server: PrefectServer | None, cwd: Path, *args: str, db: str | None = None):
    """``pipescan deploy`` in this process (no interpreter start-up), from ``cwd``."""
    env = {"PIPESCAN_DATABASE_URL": db} if db else {}
    here = Path.cwd()
    os.chdir(cwd)
    try:
        with temporary_settings({PREFECT_API_URL: server.url if server else None}):
            return CliRunner().invoke(app, ["deploy", "--pool", POOL, *args], env=env)
    finally:
        os.chdir(here)


@pytest.fixture(scope="module")
def deployed(server, tmp_path_factory):
    """A store of one archive, a migrated SQLite database, and ``pipescan deploy`` (given a
    relative store); returns (deploy result, folder, database URL)."""
    root = tmp_path_factory.mktemp("deployed")
    write_store(root / "store", 1)
    db = f"sqlite:///{root / 'network.db'}"
    upgrade(db)
    result = _deploy(
        server, root, "--store", "store", "--cron", "0 2 * * *", "--concurrency", "3", db=db
    )
    return result, root, db


def test_the_deployment_holds_no_database_and_ships_its_recovery(server, deployed):
    result, root, _ = deployed
    assert result.exit_code == 0, result.output[-3000:]
    assert "prefect worker start --pool pipescan-test" in result.stdout
    assert "PIPESCAN_DATABASE_URL=sqlite:///" in result.stdout  # what the workers need
    assert "--param reuse_stored=false" in result.stdout  # how to force a full re-run
    assert "alerts: none for a run that ends Failed (PIPESCAN_SMTP_ALERT_TO" in result.stdout

    deployment = server.deployment("inspect-network/network-nightly")
    assert deployment["entrypoint"] == "pipescan.flows.network.inspect_network"
    assert deployment["work_pool_name"] == POOL
    # The store, stored absolute (the worker runs elsewhere); no database, no local folder.
    assert deployment["parameters"] == {"store": str(root / "store"), "concurrency": 3}
    assert deployment["job_variables"] == {
        "stream_output": False,
        "env": {"PREFECT_FLOWS_HEARTBEAT_FREQUENCY": str(HEARTBEAT_S)},
    }
    assert RECOVERY_TAG in deployment["tags"]
    [schedule] = deployment["schedules"]
    assert schedule["active"] and schedule["schedule"]["cron"] == "0 2 * * *"
    assert schedule["schedule"]["timezone"] == "UTC"

    automations = _automations(server)
    silent = automations["pipescan: crash silent runs"]
    retry = automations["pipescan: retry crashed runs of inspect-network/network-nightly"]
    cancelling = automations["pipescan: end stuck cancellations"]
    assert all(a["enabled"] for a in (silent, retry, cancelling))
    trigger = silent["trigger"]
    assert (trigger["posture"], trigger["within"]) == ("Proactive", SILENT_AFTER_S)
    assert trigger["after"] == ["prefect.flow-run.heartbeat"]
    assert {"prefect.flow-run.heartbeat", RUN_ENDED_EVENT} <= set(trigger["expect"])
    tag, deployment_role = trigger["match_related"]  # a deployment's runs, not sub-flows
    assert tag["prefect.resource.id"] == f"prefect.tag.{RECOVERY_TAG}"
    assert deployment_role == {"prefect.resource.role": "deployment"}
    assert silent["actions"][0]["state"] == "CRASHED"
    trigger = retry["trigger"]
    assert (trigger["posture"], trigger["within"]) == ("Proactive", RETRY_AFTER_S)
    assert trigger["after"] == ["prefect.flow-run.Crashed"]
    assert trigger["expect"] == ["prefect.flow-run.*"]  # any sign of life ends the wait
    assert trigger["match"]["prefect.run-count"] == [str(n) for n in range(MAX_ATTEMPTS)]
    assert trigger["match_related"]["prefect.resource.id"] == (
        f"prefect.deployment.{deployment['id']}"
    )
    assert (retry["actions"][0]["state"], retry["actions"][0]["name"]) == (
        "SCHEDULED",
        "AwaitingRetry",
    )
    assert cancelling["trigger"]["within"] == CANCELLING_AFTER_S
    assert cancelling["actions"][0]["state"] == "CANCELLED"

    # Deploying again updates the same deployment and the same automations.
    again = _deploy(
        server,
        root,
        *("--store", "store", "--cron", "30 3 * * 1", "--timezone", "Europe/Zurich"),
        db=deployed[2],
    )
    assert again.exit_code == 0, again.output[-3000:]
    updated = server.deployment("inspect-network/network-nightly")
    assert updated["id"] == deployment["id"]
    assert [(s["schedule"]["cron"], s["schedule"]["timezone"]) for s in updated["schedules"]] == [
        ("30 3 * * 1", "Europe/Zurich")
    ]
    names = [a["name"] for a in server.call("POST", "/automations/filter", {"limit": 100})]
    assert sorted(names) == sorted(automations)


def _automations(server: PrefectServer) -> dict[str, dict]:
    return {a["name"]: a for a in server.call("POST", "/automations/filter", {"limit": 100})}


def test_prefects_own_list_commands_work_against_the_server(server, deployed):
    assert deployed[0].exit_code == 0
    deadline = time.monotonic() + 30  # the scheduler plans the cron runs
    while not server.flow_runs() and time.monotonic() < deadline:
        time.sleep(0.5)
    env = server.client_env() | {"COLUMNS": "200"}
    outputs = {}
    for command in (["flow-run", "ls"], ["deployment", "ls"], ["work-pool", "ls"]):
        run = subprocess.run(
            [PREFECT, *command], env=env, capture_output=True, text=True, timeout=120
        )
        outputs[command[0]] = run.stdout
        assert run.returncode == 0, run.stdout + run.stderr
        # An HTTP 422 (the API refusing the client's request), not "422" inside an id.
        assert not re.search(r"(?<![\w-])422(?![\w-])", run.stdout + run.stderr)
    print(outputs["flow-run"])  # shown with pytest -s
    assert "inspect-network" in outputs["flow-run"] and "SCHEDULED" in outputs["flow-run"]
    assert "inspect-network/network-nightly" in outputs["deployment"]
    assert POOL in outputs["work-pool"]


def _run_log(server: PrefectServer, flow_run_id: str) -> list[str]:
    """A flow run's log lines on the server, once its closing summary is there (logs reach
    the API in batches)."""
    body = {"logs": {"flow_run_id": {"any_": [flow_run_id]}}, "limit": 200}
    deadline = time.monotonic() + 30
    while True:
        messages = [entry["message"] for entry in server.call("POST", "/logs/filter", body)]
        if any(m.startswith("network run over") for m in messages) or time.monotonic() > deadline:
            return messages
        time.sleep(0.5)


@pytest.mark.parametrize("verbose", [False, True])
def test_a_run_the_cli_starts_logs_to_prefect_and_its_errors_once_to_the_terminal(
    server, tmp_path, verbose
):
    """The network run's closing summary goes to its Prefect run only through the run's
    logger, and a failed archive's error through Prefect's run loggers: both must reach the
    server (its UI), while the terminal shows the failure as pipescan's one line, with
    Prefect's own lines and traceback only under --verbose."""
    store = tmp_path / "store"
    write_bad_archive(store)
    env = server.client_env() | {"PIPESCAN_DATABASE_URL": f"sqlite:///{tmp_path / 'n.db'}"}
    command = [*PIPESCAN, *(["--verbose"] if verbose else [])]
    command += ["inspect-network", str(store), "--no-network-report"]
    run = subprocess.run(
        command, env=env, cwd=tmp_path, capture_output=True, text=True, timeout=300
    )
    assert run.returncode == 1, run.stdout + run.stderr
    assert "MH99-BAD" in run.stderr  # pipescan's own progress line names the failed archive
    assert ("Traceback" in run.stderr) is verbose, run.stderr
    assert ("Finished in state Failed" in run.stderr) is verbose, run.stderr
    runs = [r for r in server.flow_runs() if r["parameters"].get("store") == str(store)]
    assert len(runs) == 1
    logged = _run_log(server, runs[0]["id"])
    assert any(m.startswith("network run over") for m in logged), logged  # the summary
    progress = [m for m in logged if m.startswith("[1/1] MH99-BAD FAILED")]
    assert len(progress) == 1, "\n".join(logged)  # once: not again through pipescan's logger


@pytest.mark.parametrize(
    "case",
    [
        "no server",
        "no PREFECT_API_URL",
        "no database",
        "relative SQLite",
        "unreachable database",
        "no store",
        "bad cron",
    ],
)
def test_deploy_says_what_is_missing_in_one_line(server, tmp_path, case):
    (tmp_path / "store").mkdir()
    db = f"sqlite:///{tmp_path / 'ok.db'}"
    args = {"store": str(tmp_path / "store"), "cron": "0 2 * * *"}
    on: PrefectServer | None = server
    expected = {
        "no server": "no Prefect server answers at PREFECT_API_URL=http://127.0.0.1:",
        "no PREFECT_API_URL": "PREFECT_API_URL is not set",
        "no database": "no database named",
        "relative SQLite": "relative SQLite path",
        "unreachable database": "cannot open database postgresql+psycopg://127.0.0.1:",
        "no store": "the store does not exist",
        "bad cron": "invalid schedule 'nightly'",
    }[case]
    if case == "no server":
        on = PrefectServer(tmp_path / "down")  # never started: nothing listens on its port
    elif case == "no PREFECT_API_URL":
        on = None
    elif case == "no database":
        db = ""
    elif case == "relative SQLite":
        db = "sqlite:///network.db"
    elif case == "unreachable database":
        db = f"postgresql+psycopg://pipescan:secret@127.0.0.1:{free_port()}/pipescan"
    elif case == "no store":
        args["store"] = str(tmp_path / "missing")
    elif case == "bad cron":
        args["cron"] = "nightly"
    result = _deploy(on, tmp_path, "--store", args["store"], "--cron", args["cron"], db=db)
    assert result.exit_code == 2, result.output
    [line] = result.output.strip().splitlines()
    assert line.startswith("error: ") and expected in line, line
    if case == "no server":
        assert "prefect server start" in line  # what to start
    assert "secret" not in result.output


def test_a_secret_block_gives_the_database_password(server):
    from prefect.blocks.system import Secret

    with _on(server):
        Secret(value="s3cr3t/pw").save("pipescan-test-db-password", overwrite=True)
        settings = Settings(
            database_url="postgresql+psycopg://pipescan@db.example/pipescan",
            database_password_block="pipescan-test-db-password",
        )
        url = make_url(database_url(settings))
        assert (url.username, url.password, url.host) == ("pipescan", "s3cr3t/pw", "db.example")
        missing = Settings(database_url="sqlite:////x.db", database_password_block="nope")
        with pytest.raises(Exception, match="PIPESCAN_DATABASE_PASSWORD_BLOCK"):
            database_url(missing)


@pytest.mark.slow
def test_the_servers_scheduler_plans_runs_at_the_cron_times(server, tmp_path):
    write_store(tmp_path / "store", 1)
    db = f"sqlite:///{tmp_path / 'network.db'}"
    result = _deploy(
        server, tmp_path, "--store", "store", "--cron", "0 2 * * *", "--name", "planned", db=db
    )
    assert result.exit_code == 0, result.output[-3000:]
    deployment = server.deployment("inspect-network/planned")
    deadline = time.monotonic() + 20
    while True:
        runs = [r for r in server.flow_runs() if r["deployment_id"] == deployment["id"]]
        if runs or time.monotonic() > deadline:
            break
        time.sleep(0.5)
    assert runs, "the scheduler planned no run within 20 s"
    from datetime import datetime

    for run in runs:
        assert run["state_type"] == "SCHEDULED"
        start = datetime.fromisoformat(run["expected_start_time"]).astimezone(UTC)
        assert (start.hour, start.minute) == (2, 0)
        assert run["parameters"]["store"] == str(tmp_path / "store")


@pytest.mark.slow
def test_a_worker_runs_the_deployment_with_its_own_settings_and_no_secret_reaches_prefect(
    server, postgres_url, tmp_path
):
    write_store(tmp_path / "store", 1)
    upgrade(postgres_url)
    marker = "Pw-Zq7-not-for-prefect"  # trust authentication ignores it, Prefect must not see it
    secret_url = make_url(postgres_url).set(password=marker).render_as_string(hide_password=False)
    deployed = _deploy(
        server, tmp_path, "--store", "store", "--cron", "0 2 * * *", "--name", "worked",
        db=secret_url,
    )  # fmt: skip
    assert deployed.exit_code == 0, deployed.output[-3000:]
    assert marker not in deployed.output and ":<password>@" in deployed.output
    assert "***" not in deployed.output  # a mask copied as a value would become the password

    # A worker whose environment names no database: the run fails at once, saying so.
    bare = Worker(POOL, server.client_env(), tmp_path / "bare", tmp_path).start()
    try:
        failed = _wait(server, server.run_deployment("inspect-network/worked"))
    finally:
        bare.stop()
    assert failed["state_type"] == "FAILED", failed
    assert "no database for this scheduled run" in failed["state"]["message"]
    assert "PIPESCAN_DATABASE_URL" in failed["state"]["message"]

    # A worker with its settings: the run stores the inspection where they say, writes a
    # network report named by date and run, and logs its progress in Prefect.
    reports = tmp_path / "reports"
    env = server.client_env() | {
        "PIPESCAN_DATABASE_URL": secret_url,
        "PIPESCAN_REPORTS_DIR": str(reports),
        "PIPESCAN_WORK_DIR": str(tmp_path / "work"),
    }
    worker = Worker(POOL, env, tmp_path / "worker", tmp_path).start()
    try:
        done = _wait(server, server.run_deployment("inspect-network/worked"))
        assert done["state_type"] == "COMPLETED", (done, worker.log()[-3000:])
        assert any("[1/1] MH0-MH1 inspected in" in m for m in _logs(server, done["id"]))
        # Forcing a full re-run: the documented parameter, through Prefect's own CLI.
        forced = subprocess.run(
            [PREFECT, "deployment", "run", "inspect-network/worked", "--param",
             "reuse_stored=false"],
            env=server.client_env(), capture_output=True, text=True, timeout=120,
        )  # fmt: skip
        assert forced.returncode == 0, forced.stdout + forced.stderr
        [forced_id] = re.findall(r"UUID: ([0-9a-f-]{36})", forced.stdout)
        again = _wait(server, forced_id)
        assert again["state_type"] == "COMPLETED", (again, worker.log()[-3000:])
    finally:
        worker.stop()
    engine = connect(postgres_url)
    try:
        rows = list_inspections(engine)
        assert len(rows) == 1, [(r.id, r.asset_id, r.archive_uri, r.inspected_at) for r in rows]
        [stored] = rows
    finally:
        engine.dispose()
    assert stored.asset_id == asset_id(0)
    assert sorted(p.name for p in reports.glob("*.pdf")) == sorted(
        f"network-{r['expected_start_time'][:10]}-{r['name']}.pdf" for r in (done, again)
    )
    # Each run's process output beside its report, under the same name.
    assert sorted(p.name for p in (reports / "logs").iterdir()) == sorted(
        f"network-{r['expected_start_time'][:10]}-{r['name']}.log" for r in (done, again)
    )
    assert any("[1/1] MH0-MH1 inspected in" in m for m in _logs(server, done["id"]))
    assert any("[1/1] MH0-MH1 inspected in" in m for m in _logs(server, again["id"]))
    assert again["parameters"]["reuse_stored"] is False

    # Nothing of the database URL anywhere in Prefect's database: parameters, logs, events.
    dump = "\n".join(sqlite3.connect(server.home / "prefect.db").iterdump())
    assert marker not in dump
    assert json.dumps(server.deployment("inspect-network/worked")).count(marker) == 0


def _wait(server: PrefectServer, run_id: str, timeout: float = 300) -> dict:
    deadline = time.monotonic() + timeout
    while True:
        run = server.call("GET", f"/flow_runs/{run_id}")
        if run["state_type"] in ("COMPLETED", "FAILED", "CRASHED", "CANCELLED"):
            return run
        assert time.monotonic() < deadline, f"the run is still {run['state_name']}"
        time.sleep(1)


def _logs(server: PrefectServer, run_id: str) -> list[str]:
    deadline = time.monotonic() + 30  # logs reach the API in batches
    while True:
        logs = server.call(
            "POST", "/logs/filter", {"logs": {"flow_run_id": {"any_": [run_id]}}, "limit": 200}
        )
        messages = [entry["message"] for entry in logs]
        if any("network run over" in m for m in messages) or time.monotonic() > deadline:
            return messages
        time.sleep(1)


def test_a_run_that_ends_failed_sends_a_notification(server, tmp_path):
    """``deploy --notify TYPE/NAME``: the server sends a notification through that block when a
    run of the deployment ends Failed (as one that left archives unstored does), with the
    run's message."""
    import threading
    from http.server import BaseHTTPRequestHandler, HTTPServer

    from prefect.blocks.notifications import CustomWebhookNotificationBlock

    received: list[dict] = []

    class Receiver(BaseHTTPRequestHandler):
        def do_POST(self):
            received.append(json.loads(self.rfile.read(int(self.headers["Content-Length"]))))
            self.send_response(204)
            self.end_headers()

        def log_message(self, *args):
            pass

    httpd = HTTPServer(("127.0.0.1", 0), Receiver)
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    (tmp_path / "store").mkdir()
    db = f"sqlite:///{tmp_path / 'n.db'}"
    upgrade(db)
    try:
        with _on(server):
            CustomWebhookNotificationBlock(
                name="pipescan-alerts",
                url=f"http://127.0.0.1:{httpd.server_port}/hook",
                json_data={"subject": "{{subject}}", "body": "{{body}}"},
                allow_private_urls=True,
            ).save("pipescan-alerts", overwrite=True)
        result = _deploy(
            server, tmp_path, "--store", "store", "--cron", "0 2 * * *", "--name", "notified",
            "--notify", "custom-webhook/pipescan-alerts", db=db,
        )  # fmt: skip
        assert result.exit_code == 0, result.output[-3000:]
        assert "pipescan: notify when a run of inspect-network/notified fails" in result.stdout
        assert (
            "alerts: a run that ends Failed (archives missing or failed) sends the notification "
            "block custom-webhook/pipescan-alerts" in result.stdout
        )
        bad = _deploy(
            server, tmp_path, "--store", "store", "--cron", "0 2 * * *", "--name", "notified",
            "--notify", "custom-webhook/nope", db=db,
        )  # fmt: skip
        assert bad.exit_code == 2 and "no notification block 'custom-webhook/nope'" in bad.output

        run_id = server.run_deployment("inspect-network/notified")
        message = "2 of 4 archives not stored: missing after 15 min of retries: MH1-MH2 (...)"
        server.call(
            "POST",
            f"/flow_runs/{run_id}/set_state",
            {"state": {"type": "FAILED", "message": message}, "force": True},
        )
        deadline = time.monotonic() + 90
        while not received and time.monotonic() < deadline:
            time.sleep(1)
    finally:
        httpd.shutdown()
    [note] = received
    assert (
        note["subject"].startswith("pipescan: run ")
        and "inspect-network/notified" in note["subject"]
    )
    assert message in note["body"] and "pipescan runs" in note["body"]


def _post_event(server: PrefectServer, run_id: str, deployment_id: str, name: str) -> None:
    """An event of a run of the deployment, as its process sends it (now)."""
    import uuid
    from datetime import datetime

    server.call(
        "POST",
        "/events",
        [
            {
                "id": str(uuid.uuid4()),
                "occurred": datetime.now(UTC).isoformat(),
                "event": name,
                "resource": {"prefect.resource.id": f"prefect.flow-run.{run_id}"},
                "related": [
                    {
                        "prefect.resource.id": f"prefect.deployment.{deployment_id}",
                        "prefect.resource.role": "deployment",
                    },
                    {
                        "prefect.resource.id": f"prefect.tag.{RECOVERY_TAG}",
                        "prefect.resource.role": "tag",
                    },
                ],
                "payload": {},
            }
        ],
    )


def _set_state(server: PrefectServer, run_id: str, state: str) -> None:
    server.call("POST", f"/flow_runs/{run_id}/set_state", {"state": {"type": state}, "force": True})


def test_the_silent_rule_crashes_a_silent_run_and_not_one_that_ended(server, deployed):
    """Issue 53: the rule fired on finished runs ("Run is already COMPLETED"). A heartbeat sent
    just before the final state reaches the server's triggers after that state's event (which
    the server emits itself) and starts a wait nothing ends. The run's end event
    (``pipescan.flow-run.ended``, sent after its heartbeats) ends it. The same rule, with a
    10 s wait, on three runs of the deployment: one that goes silent (crashed), one that ends
    with such a late heartbeat and its end event (left alone), and one that ends with the late
    heartbeat alone (the rule fires, and Prefect refuses to crash a finished run: this is
    what the end event prevents; if this stops firing, Prefect has fixed it)."""
    from pipescan.flows.deploy import ensure_automations, recovery_automations

    assert deployed[0].exit_code == 0
    deployment_id = server.deployment("inspect-network/network-nightly")["id"]
    with _on(server):
        [silent, *_] = recovery_automations(deployment_id, "test", silent_after_s=10)
        silent.name = "pipescan test: crash silent runs after 10 s"
        ensure_automations([silent])
    time.sleep(12)  # the triggers service reads new automations every few seconds
    runs = {
        case: server.run_deployment("inspect-network/network-nightly")
        for case in ("silent", "announced", "unannounced")
    }
    for run_id in runs.values():
        _set_state(server, run_id, "RUNNING")
        _post_event(server, run_id, deployment_id, "prefect.flow-run.heartbeat")
    for case in ("announced", "unannounced"):
        _set_state(server, runs[case], "COMPLETED")
        time.sleep(1)
        _post_event(server, runs[case], deployment_id, "prefect.flow-run.heartbeat")  # late
    _post_event(server, runs["announced"], deployment_id, RUN_ENDED_EVENT)

    def fired_on() -> set[str]:
        events = server.call(
            "POST",
            "/events/filter",
            {"filter": {"event": {"prefix": ["prefect.automation.action.triggered"]}}},
        )["events"]
        targets = {
            r["prefect.resource.id"].removeprefix("prefect.flow-run.")
            for e in events
            if e["resource"].get("prefect.resource.name") == silent.name
            for r in e["related"]
            if r.get("prefect.resource.role") == "target"
        }
        return {case for case, run_id in runs.items() if run_id in targets}

    try:
        deadline = time.monotonic() + 90
        while fired_on() != {"silent", "unannounced"} and time.monotonic() < deadline:
            time.sleep(2)
        time.sleep(10)  # as long again for the announced run, which must not come
        states = {
            case: server.call("GET", f"/flow_runs/{r}")["state_type"] for case, r in runs.items()
        }
        assert fired_on() == {"silent", "unannounced"}, (fired_on(), states)
        assert states == {"silent": "CRASHED", "announced": "COMPLETED", "unannounced": "COMPLETED"}
    finally:
        server.call("DELETE", f"/automations/{silent.id}")
        for run_id in runs.values():
            server.call("DELETE", f"/flow_runs/{run_id}")
