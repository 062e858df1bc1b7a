"""A real Prefect stack for the deployment and crash-recovery tests and the recovery benchmark:
a ``prefect server start`` on loopback, ``prefect worker start`` processes, and the REST calls
that read what became of the runs.

Everything runs in child processes with their own ``PREFECT_HOME`` and no ``PIPESCAN_*`` or
``PREFECT_API_URL`` from the caller's environment, so that what a test sees is what an operator
would see on a fresh machine.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from contextlib import suppress
from pathlib import Path
from typing import Any

import httpx

PREFECT = str(Path(sys.executable).parent / "prefect")
PIPESCAN = [sys.executable, "-m", "pipescan.cli"]

ACTIVE_STATES = {"SCHEDULED", "PENDING", "RUNNING", "CANCELLING", "PAUSED"}
"""Flow-run state types that are not final: a run left in one of them needs a person."""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def clean_env(home: Path) -> dict[str, str]:
    """The caller's environment without Prefect API or pipescan settings, with its own home."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PREFECT_", "PIPESCAN_"))}
    return env | {
        "PREFECT_HOME": str(home),
        "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
        "PREFECT_UI_ENABLED": "false",
    }


def _stop(proc: subprocess.Popen | None, sig: int = signal.SIGTERM, timeout: float = 30) -> None:
    """Signal a process started in a session of its own, and everything in that session."""
    if proc is None or proc.poll() is not None:
        return
    with suppress(ProcessLookupError):
        os.killpg(proc.pid, sig)
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        with suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


class PrefectServer:
    """``prefect server start`` on 127.0.0.1 with a home (and SQLite database) of its own."""

    def __init__(self, home: Path, *, env: dict[str, str] | None = None) -> None:
        self.home = home
        home.mkdir(parents=True, exist_ok=True)
        self.port = free_port()
        self.env = clean_env(home) | (env or {})
        self.proc: subprocess.Popen | None = None
        self.starts = 0

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}/api"

    def start(self, timeout: float = 180) -> PrefectServer:
        self.starts += 1
        log = (self.home / f"server-{self.starts}.log").open("w")
        self.proc = subprocess.Popen(
            [PREFECT, "server", "start", "--host", "127.0.0.1", "--port", str(self.port)],
            env=self.env,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        log.close()
        deadline = time.monotonic() + timeout
        while True:
            if self.proc.poll() is not None:
                raise RuntimeError(f"the Prefect server exited:\n{self.log()[-3000:]}")
            if time.monotonic() > deadline:
                raise RuntimeError(f"the Prefect server did not start in {timeout:.0f} s")
            with suppress(httpx.HTTPError):
                if httpx.get(f"{self.url}/health", timeout=2).status_code == 200:
                    return self
            time.sleep(0.5)

    def stop(self, sig: int = signal.SIGTERM) -> None:
        _stop(self.proc, sig)

    def log(self) -> str:
        return "".join(
            p.read_text(errors="replace") for p in sorted(self.home.glob("server-*.log"))
        )

    def client_env(self) -> dict[str, str]:
        """The environment of a process that talks to this server."""
        return clean_env(self.home) | {"PREFECT_API_URL": self.url}

    # --- REST -------------------------------------------------------------------------------

    def call(self, method: str, path: str, body: Any = None, *, attempts: int = 5) -> Any:
        """A REST call; a busy server's 503 (its SQLite locked) or timeout is retried, as
        Prefect's client does."""
        for attempt in range(attempts):
            last = attempt == attempts - 1
            try:
                response = httpx.request(method, f"{self.url}{path}", json=body, timeout=30)
            except httpx.TransportError:
                if last:
                    raise
            else:
                if response.status_code != 503 or last:
                    break
            time.sleep(2**attempt)
        response.raise_for_status()
        return response.json() if response.content else None

    def flow_runs(self) -> list[dict]:
        """Every flow run on the server, network runs and their sub-flows, oldest first."""
        return self.call(
            "POST", "/flow_runs/filter", {"limit": 200, "sort": "EXPECTED_START_TIME_ASC"}
        )

    def deployment(self, name: str) -> dict:
        return self.call("GET", f"/deployments/name/{name}")

    def run_deployment(self, name: str) -> str:
        """Create a run of a deployment now (as ``prefect deployment run`` does); its id."""
        deployment = self.deployment(name)
        return self.call("POST", f"/deployments/{deployment['id']}/create_flow_run", {})["id"]


class Worker:
    """``prefect worker start --pool POOL`` in a session of its own."""

    def __init__(self, pool: str, env: dict[str, str], cwd: Path, log_dir: Path) -> None:
        self.pool = pool
        self.env = env
        self.cwd = cwd
        self.log_dir = log_dir
        self.proc: subprocess.Popen | None = None
        self.starts = 0

    def start(self) -> Worker:
        self.starts += 1
        self.cwd.mkdir(parents=True, exist_ok=True)
        log = (self.log_dir / f"worker-{self.starts}.log").open("w")
        self.proc = subprocess.Popen(
            [PREFECT, "worker", "start", "--pool", self.pool],
            env=self.env,
            cwd=self.cwd,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        log.close()
        return self

    def flow_processes(self) -> list[int]:
        """The flow-run processes this worker started (``python -m prefect.engine``)."""
        if self.proc is None:
            return []
        return [pid for pid in descendants(self.proc.pid) if b"prefect.engine" in _cmdline(pid)]

    def kill(self) -> None:
        """SIGKILL the worker process alone (its flow-run processes live on)."""
        if self.proc is not None and self.proc.poll() is None:
            os.kill(self.proc.pid, signal.SIGKILL)
            self.proc.wait()

    def stop(self) -> None:
        """Stop the worker and whatever it started."""
        pids = descendants(self.proc.pid) if self.proc is not None else []
        _stop(self.proc)
        for pid in pids:
            with suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)

    def log(self) -> str:
        return "".join(
            p.read_text(errors="replace") for p in sorted(self.log_dir.glob("worker-*.log"))
        )


def _cmdline(pid: int) -> bytes:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return b""


def descendants(root: int) -> list[int]:
    """Every living process below ``root`` (from /proc; Linux)."""
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        children.setdefault(ppid, []).append(int(entry.name))
    found, queue = [], [root]
    while queue:
        for child in children.get(queue.pop(), []):
            found.append(child)
            queue.append(child)
    return found


def run_pipescan(args: list[str], env: dict[str, str], cwd: Path, timeout: float = 300):
    return subprocess.run(
        [*PIPESCAN, *args], env=env, cwd=cwd, capture_output=True, text=True, timeout=timeout
    )
