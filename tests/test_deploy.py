"""``pipescan deploy`` against a real Prefect server (``prefect server start`` on loopback, started
and stopped here): the deployment, its work pool and its cron schedule exist, and the server's
scheduler plans runs at the scheduled times."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from contextlib import suppress
from datetime import UTC
from pathlib import Path

import pytest
from prefect.settings import PREFECT_API_URL, temporary_settings
from typer.testing import CliRunner

from pipescan.cli import app
from pipescan.storage.database.db import connect
from pipescan.storage.database.repository import list_inspections
from tests.netstore import asset_id, write_store

pytestmark = pytest.mark.e2e

PREFECT = str(Path(sys.executable).parent / "prefect")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _base_env(home: Path) -> dict[str, str]:
    env = {
        k: v for k, v in os.environ.items() if not k.startswith(("PREFECT_API_URL", "PIPESCAN_"))
    }
    return env | {"PREFECT_HOME": str(home), "PREFECT_SERVER_ANALYTICS_ENABLED": "false"}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """A Prefect server on 127.0.0.1 with its own home and database; yields its API URL."""
    home = tmp_path_factory.mktemp("prefect-home")
    port = _free_port()
    env = _base_env(home) | {
        # Plan runs within a second of a deployment's creation, not at the next minute.
        "PREFECT_SERVER_SERVICES_SCHEDULER_LOOP_SECONDS": "1",
        "PREFECT_UI_ENABLED": "false",
    }
    log = (home / "server.log").open("w")
    proc = subprocess.Popen(
        [PREFECT, "server", "start", "--host", "127.0.0.1", "--port", str(port), "--no-ui"],
        env=env,
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    url = f"http://127.0.0.1:{port}/api"
    try:
        deadline = time.monotonic() + 120
        while True:
            assert proc.poll() is None, (home / "server.log").read_text()[-3000:]
            assert time.monotonic() < deadline, "the Prefect server did not start in 120 s"
            with (
                suppress(OSError),
                urllib.request.urlopen(f"{url}/health", timeout=2) as response,
            ):
                if response.status == 200:
                    break
            time.sleep(0.5)
        yield url, home
    finally:
        with suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        log.close()


def _deploy(server, tmp_path, *extra: str):
    """``pipescan deploy`` in this process (no interpreter start-up), against the server."""
    url, home = server
    (tmp_path / "store").mkdir(exist_ok=True)
    env = _base_env(home) | {"PREFECT_API_URL": url}
    db_url = f"sqlite:///{tmp_path / 'network.db'}"
    args = ["deploy", "--store", "store", "--db", db_url, "--pool", "pipescan-test", *extra]
    cwd = Path.cwd()
    os.chdir(tmp_path)
    try:
        with temporary_settings({PREFECT_API_URL: url}):
            result = CliRunner().invoke(app, args)
    finally:
        os.chdir(cwd)
    return result, env, db_url


def _read(url: str, name: str = "inspect-network/network-nightly"):
    from prefect.client.orchestration import get_client

    with temporary_settings({PREFECT_API_URL: url}), get_client(sync_client=True) as client:
        return client.read_deployment_by_name(name), client.read_work_pool("pipescan-test")


def test_deploy_creates_a_cron_scheduled_deployment_on_the_server(server, tmp_path):
    # The store is given relative: it is stored absolute, as the worker runs elsewhere.
    result, _, db_url = _deploy(server, tmp_path, "--cron", "0 2 * * *", "--concurrency", "3")
    assert result.exit_code == 0, result.output[-3000:]
    assert "prefect worker start --pool pipescan-test" in result.stdout
    assert "cron '0 2 * * *' (UTC)" in result.stdout

    deployment, pool = _read(server[0])
    assert deployment.entrypoint == "pipescan.flows.network.inspect_network"
    assert deployment.work_pool_name == "pipescan-test"
    assert pool.type == "process"
    assert deployment.parameters == {
        "store": str(tmp_path / "store"),
        "database_url": db_url,
        "concurrency": 3,
        "work_dir": str(tmp_path / ".pipescan-work"),
        "network_report_path": str(tmp_path / "reports" / "network-report.pdf"),
    }
    [schedule] = deployment.schedules
    assert schedule.active
    assert schedule.schedule.cron == "0 2 * * *"
    assert schedule.schedule.timezone == "UTC"

    # Deploying again updates the same deployment: the new schedule replaces the old one.
    again, _, _ = _deploy(server, tmp_path, "--cron", "30 3 * * 1", "--timezone", "Europe/Zurich")
    assert again.exit_code == 0, again.output[-3000:]
    updated, _ = _read(server[0])
    assert updated.id == deployment.id
    assert [(s.schedule.cron, s.schedule.timezone) for s in updated.schedules] == [
        ("30 3 * * 1", "Europe/Zurich")
    ]


@pytest.mark.slow
def test_the_servers_scheduler_plans_runs_at_the_cron_times(server, tmp_path):
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import DeploymentFilter, DeploymentFilterId
    from prefect.client.schemas.sorting import FlowRunSort

    result, _, _ = _deploy(server, tmp_path, "--cron", "0 2 * * *", "--name", "planned")
    assert result.exit_code == 0, result.output[-3000:]
    deployment, _ = _read(server[0], "inspect-network/planned")
    with temporary_settings({PREFECT_API_URL: server[0]}), get_client(sync_client=True) as client:
        deadline = time.monotonic() + 20
        while True:
            runs = client.read_flow_runs(
                deployment_filter=DeploymentFilter(id=DeploymentFilterId(any_=[deployment.id])),
                sort=FlowRunSort.EXPECTED_START_TIME_ASC,
                limit=20,
            )
            if runs or time.monotonic() > deadline:
                break
            time.sleep(0.5)
    assert runs, "the scheduler planned no run within 20 s"
    for run in runs:
        assert run.state.is_scheduled()
        start = run.expected_start_time.astimezone(UTC)
        assert (start.hour, start.minute) == (2, 0)
        assert run.parameters["store"] == str(tmp_path / "store")


@pytest.mark.slow
def test_a_worker_picks_up_a_run_of_the_deployment(server, tmp_path):
    write_store(tmp_path / "store", 1)
    result, env, db_url = _deploy(server, tmp_path, "--cron", "0 2 * * *", "--name", "worked")
    assert result.exit_code == 0, result.output[-3000:]
    run = subprocess.run(
        [PREFECT, "deployment", "run", "inspect-network/worked"],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 0, run.stdout + run.stderr
    worker = subprocess.run(
        [PREFECT, "worker", "start", "--pool", "pipescan-test", "--run-once"],
        env=env,
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=400,
    )
    assert worker.returncode == 0, worker.stdout[-3000:] + worker.stderr[-3000:]
    # What the run did, not what the worker printed: whether the flow run's logs reach the
    # worker's output depends on Prefect's log settings.
    engine = connect(db_url)
    try:
        [stored] = list_inspections(engine)
    finally:
        engine.dispose()
    assert stored.asset_id == asset_id(0)


def test_a_bad_cron_line_or_no_server_is_a_clear_error(tmp_path):
    # Both are refused before any request: no server is needed to see them.
    with temporary_settings({PREFECT_API_URL: "http://127.0.0.1:9/api"}):
        bad = CliRunner().invoke(app, ["deploy", "--store", str(tmp_path), "--cron", "nightly"])
    assert bad.exit_code == 2
    assert "invalid schedule 'nightly'" in bad.output
    with temporary_settings({PREFECT_API_URL: None}):
        nowhere = CliRunner().invoke(
            app, ["deploy", "--store", str(tmp_path), "--cron", "0 2 * * *"]
        )
    assert nowhere.exit_code == 2
    assert "no Prefect server" in nowhere.output and "PREFECT_API_URL" in nowhere.output
