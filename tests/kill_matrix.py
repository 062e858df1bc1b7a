"""Crash a scheduled network run and watch whether it finishes without a person.

One scenario: a fresh Prefect server, ``pipescan deploy``, a worker whose environment names
the database, a run of the deployment over a store of archives (one at a time), and, once the
first inspection is stored and the next archive's sub-flow is running, a crash:

- ``worker``: SIGKILL of the worker process alone; a supervisor starts it again;
- ``flow``: SIGKILL of the flow-run process alone (the worker lives on);
- ``both``: SIGKILL of both at once, as a host crash; the worker is started again;
- ``server``: SIGKILL of the Prefect server; it is started again on the same database.

And outages, at the same moment, that end by themselves after their seconds:

- ``db45``, ``db120``, ``db600``: the database refuses connections (the SQLite file is moved
  away and a folder stands in its place: "unable to open database file"), then comes back;
- ``dbstart30``: the database refuses connections when the run starts, for 30 s;
- ``server105``: the Prefect server is down for 105 s (SIGKILL, started again after 105 s);
- ``pg20``: PostgreSQL, which holds both pipescan's database and Prefect's state (as
  docs/operations.md recommends), is stopped for 20 s.

And ``cancel``: the run is cancelled (``prefect flow-run cancel``) at that moment; it ends
when the run is Cancelled and its process (and every process it started) is gone.

Then it waits, doing nothing a person would do, until every archive has its inspection and no
run is left active, or a time limit passes. Used by ``tests/test_crash_recovery.py`` and
``benchmarks/bench_recovery.py``.
"""

from __future__ import annotations

import json
import shutil
import signal
import sqlite3
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from tests.prefect_stack import (
    ACTIVE_STATES,
    PrefectServer,
    Worker,
    descendants,
    run_pipescan,
)

SCENARIOS = ("worker", "flow", "both", "server")
CANCEL = "cancel"
OUTAGES = {
    "db45": 45.0,
    "db120": 120.0,
    "db600": 600.0,
    "dbstart30": 30.0,
    "server105": 105.0,
    "pg20": 20.0,
}
"""The outage scenarios and how long each outage lasts (s)."""
RESTART_DELAY_S = 5.0
"""How long a supervisor (systemd's RestartSec) takes to start a killed process again."""
DEPLOYMENT = "inspect-network/network-nightly"
POOL = "pipescan"


@dataclass
class Outcome:
    """What became of one scenario."""

    scenario: str
    archives: int
    stored_at_kill: int
    inspections: int
    distinct_identities: int
    finished_after_s: float | None
    """Seconds from the kill until every archive was stored and no run was active; None when
    that did not happen within the time limit."""
    network_run: str
    """Final state (name) of the network run, with its run count."""
    network_run_type: str
    subflow_states: dict[str, int]
    """Sub-flow runs by final state name."""
    active_subflows: int
    active_task_runs: int
    """Task runs left Running or Pending (the tasks of a dead process)."""
    active_task_run_names: list[str] = field(default_factory=list)
    """Those task runs: name (state, of flow run)."""
    silent_rule_on_ended_runs: int = 0
    """Times the "crash silent runs" automation acted on a run that had ended (the server
    refused: "Run is already ...")."""
    timeline: list[str] = field(default_factory=list)
    runs_says: dict | None = None
    """``pipescan runs --json --limit 1`` at the end: what an operator sees of the run."""
    runs_text: str = ""
    """``pipescan runs --limit 1`` at the end, as printed."""


def stored(db: Path | str) -> tuple[int, int]:
    """(inspections, distinct (asset, content, parameters) identities) in a SQLite file, or a
    PostgreSQL database given by its URL (0, 0 while it does not answer)."""
    if isinstance(db, str):
        import sqlalchemy as sa

        engine = sa.create_engine(db, connect_args={"connect_timeout": 5})
        try:
            with engine.connect() as con:
                row = con.execute(
                    sa.text(
                        "SELECT COUNT(*), COUNT(DISTINCT asset_id || content_hash || params_hash) "
                        "FROM inspections"
                    )
                ).one()
        except sa.exc.DBAPIError:
            return 0, 0
        finally:
            engine.dispose()
        return int(row[0]), int(row[1])
    if not db.exists():
        return 0, 0
    try:
        with sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=10) as con:
            row = con.execute(
                "SELECT COUNT(*), COUNT(DISTINCT asset_id || content_hash || params_hash) "
                "FROM inspections"
            ).fetchone()
    except sqlite3.OperationalError:  # not migrated yet, or locked for longer than 10 s
        return 0, 0
    return int(row[0]), int(row[1])


def _runs(server: PrefectServer, run_id: str) -> tuple[dict, list[dict]]:
    """The network run made for the scenario, and every sub-flow run. (The runs that the
    schedule plans for the coming nights are left out.)"""
    runs = server.flow_runs()
    [network] = [r for r in runs if r["id"] == run_id]
    return network, [r for r in runs if r["parent_task_run_id"] is not None]


def _subflow_running(server: PrefectServer) -> bool:
    return any(
        r["parent_task_run_id"] is not None and r["state_type"] == "RUNNING"
        for r in server.flow_runs()
    )


def _settled(server: PrefectServer, run_id: str, db: Path, archives: int) -> bool:
    if stored(db)[0] < archives:
        return False
    network, subflows = _runs(server, run_id)
    active = [r for r in subflows if r["state_type"] in ACTIVE_STATES]
    # Task-run states reach the server's database through its event pipeline, a moment after
    # the flow run's: wait for them too.
    return network["state_type"] == "COMPLETED" and not active and not _active_task_runs(server)


def _failed_for_good(server: PrefectServer, run_id: str) -> bool:
    """The run ended Failed (not green: nothing retries it) and left nothing active."""
    network, subflows = _runs(server, run_id)
    return network["state_type"] == "FAILED" and not any(
        r["state_type"] in ACTIVE_STATES for r in subflows
    )


def break_database(db: Path) -> Path:
    """Make a SQLite database refuse connections: the file (and its WAL files) moved aside, a
    folder in its place. Returns where the file went (see :func:`mend_database`)."""
    aside = db.with_name(db.name + ".away")
    aside.mkdir()
    for suffix in ("", "-wal", "-shm"):
        source = db.with_name(db.name + suffix)
        if source.exists():
            source.rename(aside / source.name)
    db.mkdir()
    return aside


def mend_database(db: Path, aside: Path) -> None:
    db.rmdir()
    for moved in aside.iterdir():
        moved.rename(db.with_name(moved.name))
    aside.rmdir()


def _active_task_runs(server: PrefectServer) -> int:
    return server.call(
        "POST",
        "/task_runs/count",
        {"task_runs": {"state": {"type": {"any_": sorted(ACTIVE_STATES)}}}},
    )


def _active_task_run_names(server: PrefectServer) -> list[str]:
    """Each task run left active: its name, state, and the flow run it belongs to."""
    flow_runs = {r["id"]: r["name"] for r in server.flow_runs()}
    task_runs = server.call(
        "POST",
        "/task_runs/filter",
        {"task_runs": {"state": {"type": {"any_": sorted(ACTIVE_STATES)}}}, "limit": 50},
    )
    return [
        f"{t['name']} ({t['state_name']}, of {flow_runs.get(t['flow_run_id'], t['flow_run_id'])})"
        for t in task_runs
    ]


def run_scenario(
    scenario: str,
    root: Path,
    store: Path,
    archives: int,
    *,
    time_limit_s: float = 600,
    worker_env: dict[str, str] | None = None,
) -> Outcome:
    """Run one scenario under ``root`` (a fresh folder) over ``store``; see the module doc."""
    assert scenario in SCENARIOS or scenario in OUTAGES or scenario == CANCEL, scenario
    outage_s = OUTAGES.get(scenario)
    root.mkdir(parents=True)
    pg = _Postgres() if scenario == "pg20" else None
    server = PrefectServer(
        root / "prefect",
        env={"PREFECT_API_DATABASE_CONNECTION_URL": pg.url("prefect", "asyncpg")} if pg else None,
    ).start()
    worker: Worker | None = None
    db: Path | str = pg.url("pipescan") if pg else root / "network.db"
    env = server.client_env() | {
        "PIPESCAN_DATABASE_URL": db if pg else f"sqlite:///{db}",
        "PIPESCAN_WORK_DIR": str(root / "work"),
        "PIPESCAN_REPORTS_DIR": str(root / "reports"),
        **(worker_env or {}),
    }
    timeline: list[str] = []
    started = time.monotonic()

    def note(what: str) -> None:
        timeline.append(f"{time.monotonic() - started:6.1f} s  {what}")

    try:
        upgraded = run_pipescan(["db", "upgrade"], env, root)
        assert upgraded.returncode == 0, upgraded.stderr
        deployed = run_pipescan(
            [
                "deploy",
                "--store",
                str(store),
                "--cron",
                "0 2 * * *",
                "--pool",
                POOL,
                "--concurrency",
                "1",
            ],
            env,
            root,
        )
        assert deployed.returncode == 0, deployed.stdout + deployed.stderr
        worker = Worker(POOL, env, root / "worker-cwd", root).start()
        aside: Path | None = None
        mend_at: float | None = None
        if scenario == "dbstart30":
            aside = break_database(db)
            killed = time.monotonic()
            mend_at = killed + (outage_s or 0)
            note("database refusing connections")
        run_id = server.run_deployment(DEPLOYMENT)
        note("run created")
        at_kill = 0
        if scenario != "dbstart30":
            # The crash comes when one archive is stored and the next one's sub-flow is running.
            deadline = time.monotonic() + 300
            while stored(db)[0] < 1 or not _subflow_running(server):
                assert time.monotonic() < deadline, (
                    "nothing stored in 300 s:\n" + worker.log()[-3000:]
                )
                time.sleep(0.2)
            at_kill = stored(db)[0]
            flow_pids = worker.flow_processes()
            assert flow_pids, "no flow-run process under the worker"
            killed = time.monotonic()
            note(f"{at_kill} stored; {scenario}")
        if scenario in ("worker", "both"):
            worker.kill()
        if scenario in ("flow", "both"):
            for pid in flow_pids:
                _kill(pid)
        if scenario in ("server", "server105"):
            server.stop(signal.SIGKILL)
        if scenario == CANCEL:
            server.call(
                "POST",
                f"/flow_runs/{run_id}/set_state",
                {"state": {"type": "CANCELLING", "name": "Cancelling"}},
            )
            note("cancel requested")
            flow_tree = flow_pids + [d for pid in flow_pids for d in descendants(pid)]
        if scenario.startswith("db") and scenario != "dbstart30":
            aside = break_database(db)
            mend_at = killed + (outage_s or 0)
        if pg is not None:
            pg.stop()
            time.sleep(max(0.0, killed + (outage_s or 0) - time.monotonic()))
            pg.start()
            note("PostgreSQL started again")
        if scenario in SCENARIOS:
            time.sleep(RESTART_DELAY_S)
        if scenario in ("worker", "both"):
            worker.start()
            note("worker started again")
        if scenario == "server":
            server.start()
            note("server started again")
        if scenario == "server105":
            time.sleep(max(0.0, killed + (outage_s or 0) - time.monotonic()))
            server.start()
            note("server started again")

        finished: float | None = None
        last = ""
        while time.monotonic() - killed < time_limit_s:
            if aside is not None and mend_at is not None and time.monotonic() >= mend_at:
                mend_database(db, aside)
                aside = None
                note("database answering again")
            try:
                settled = _settled(server, run_id, db, archives)
                network, subflows = _runs(server, run_id)
            except Exception as exc:  # the server may be busy or restarting
                note(f"server unreachable: {type(exc).__name__}")
                time.sleep(2)
                continue
            now = (
                f"{stored(db)[0]} stored; run {network['state_name']} "
                f"(run count {network['run_count']}); "
                f"sub-flows {dict(Counter(r['state_name'] for r in subflows))}"
            )
            if now != last:
                note(now)
                last = now
            if scenario == CANCEL:
                settled = network["state_type"] == "CANCELLED" and not any(
                    _alive(pid) for pid in flow_tree
                )
                if network["state_type"] == "CANCELLED" and "run Cancelled" not in last:
                    note("run Cancelled")
                    last += " run Cancelled"
            if settled or (aside is None and _failed_for_good(server, run_id)):
                finished = time.monotonic() - killed
                break
            time.sleep(2)
        if aside is not None:
            mend_database(db, aside)
        network, subflows = _runs(server, run_id)
        count, distinct = stored(db)
        said = run_pipescan(["runs", "--json", "--limit", "1"], env, root)
        runs_says = json.loads(said.stdout)[0] if said.returncode == 0 and said.stdout else None
        runs_text = run_pipescan(["runs", "--limit", "1"], env, root).stdout
        return Outcome(
            scenario=scenario,
            archives=archives,
            stored_at_kill=at_kill,
            inspections=count,
            distinct_identities=distinct,
            finished_after_s=finished,
            network_run=f"{network['state_name']} (run count {network['run_count']})",
            network_run_type=network["state_type"],
            subflow_states=dict(Counter(r["state_name"] for r in subflows)),
            active_subflows=sum(r["state_type"] in ACTIVE_STATES for r in subflows),
            active_task_runs=_active_task_runs(server),
            active_task_run_names=_active_task_run_names(server),
            silent_rule_on_ended_runs=_silent_rule_on_ended_runs(server),
            timeline=timeline,
            runs_says=runs_says,
            runs_text=runs_text,
        )
    finally:
        if worker is not None:
            worker.stop()
        server.stop()
        if pg is not None:
            (root / "postgres.log").write_text(pg.log())
            pg.cluster.stop()
        (root / "worker.log").write_text(worker.log() if worker else "")
        shutil.rmtree(root / "work", ignore_errors=True)


def _silent_rule_on_ended_runs(server: PrefectServer) -> int:
    events = server.call(
        "POST",
        "/events/filter",
        {"filter": {"event": {"name": ["prefect.automation.action.failed"]}}, "limit": 50},
    )["events"]
    return sum(
        e["resource"].get("prefect.resource.name") == "pipescan: crash silent runs"
        and "already" in json.dumps(e["payload"])
        for e in events
    )


def _alive(pid: int) -> bool:
    """The process lives (a zombie, exited but not yet reaped, does not)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def _kill(pid: int) -> None:
    import os
    from contextlib import suppress

    with suppress(ProcessLookupError):
        os.kill(pid, signal.SIGKILL)


def format_outcome(o: Outcome) -> str:
    finished = f"{o.finished_after_s:.0f} s" if o.finished_after_s is not None else "not finished"
    text = (
        f"{o.scenario:<7} stored at kill {o.stored_at_kill}/{o.archives}; "
        f"finished: {finished}; inspections {o.inspections} "
        f"({o.distinct_identities} distinct); network run: {o.network_run}; "
        f"sub-flows: {o.subflow_states}; task runs left active: {o.active_task_runs}"
        + (f" {o.active_task_run_names}" if o.active_task_run_names else "")
        + f"; silent rule on ended runs: {o.silent_rule_on_ended_runs}"
    )
    if o.runs_says is not None:
        r = o.runs_says
        counts = {k: v for k, v in r["counts"].items() if v}
        missing = [m["archive"] for m in r["missing"]]
        text += f"\n        pipescan runs: {r['state_name']}, {counts}" + (
            f", missing {missing}" if missing else ""
        )
    text += "".join(f"\n        | {line}" for line in o.runs_text.splitlines())
    return text


class _Postgres:
    """A PostgreSQL cluster (tests/pg_cluster.py) holding databases ``pipescan`` and
    ``prefect``, that can be stopped and started again on its data."""

    def __init__(self) -> None:
        import psycopg

        from tests.pg_cluster import PostgresCluster

        self.cluster = PostgresCluster(durable=True).start()
        with psycopg.connect(
            f"host=127.0.0.1 port={self.cluster.port} user=postgres dbname=postgres",
            autocommit=True,
        ) as con:
            for name in ("pipescan", "prefect"):
                con.execute(f"CREATE DATABASE {name}")
        self._options = " ".join(
            [
                "-c listen_addresses=127.0.0.1",
                f"-p {self.cluster.port}",
                f"-k {self.cluster.root}",
                "-c max_connections=100",
            ]
        )
        self._ctl("-m", "fast", "-w", "stop")
        self.start()

    def url(self, database: str, driver: str = "psycopg") -> str:
        return f"postgresql+{driver}://postgres@127.0.0.1:{self.cluster.port}/{database}"

    def _ctl(self, *args: str) -> None:
        root = self.cluster.root
        assert root is not None
        self.cluster._run(str(self.cluster.bin_dir / "pg_ctl"), "-D", str(root / "data"), *args)

    def stop(self) -> None:
        self._ctl("-m", "fast", "-w", "stop")

    def start(self) -> None:
        root = self.cluster.root
        assert root is not None
        self._ctl("-l", str(root / "server.log"), "-w", "-t", "60", "-o", self._options, "start")

    def log(self) -> str:
        root = self.cluster.root
        path = root / "server.log" if root is not None else None
        return path.read_text(errors="replace")[-20000:] if path and path.exists() else ""
