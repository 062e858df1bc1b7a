"""The database at network scale: bulk writes, one asset's trend, the network's worst pipes.

    python benchmarks/bench_db.py                   # 2,000 pipes x 5 inspections x 500 sections
    python benchmarks/bench_db.py --scale 0.05      # 100 pipes, a quick run
    python benchmarks/bench_db.py --pg-url postgresql+psycopg://user@host/db   # existing server
    python benchmarks/bench_db.py --skip-sqlite

Generates a network of pipes whose deposits grow at random rates, surveyed five times a year
apart with chainage errors of up to 0.3 m and a few unmeasured sections, and writes it through
``repository.save_inspections`` (a bulk import: the same validated, idempotent writes as the
flows' ``save_inspection``, with ``--batch`` pipes per transaction) into PostgreSQL and into
SQLite. Then a further 2 % of pipes are saved one inspection per transaction, as the flows
do. Section objects are built before the clock starts; the write rates count only the saves.

Without ``--pg-url`` a throwaway PostgreSQL cluster is started on loopback (tests/pg_cluster.py)
with PostgreSQL's default durability (fsync and synchronous commit on), and deleted at the end.

Then, on each database after ``ANALYZE``: the time of one asset's trend (the two queries alone
and the whole ``asset_trend`` with alignment and slopes), of ``worst --by growth`` and
``--by current``, of the network report's queries (the latest inspection of each asset and the
earlier scans of each, both window functions; their sections; the whole input of the report),
and PostgreSQL's ``EXPLAIN (ANALYZE, BUFFERS)`` of the trend and network queries, to show they
use indexes. Every figure is printed; nothing is asserted.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import sqlalchemy as sa

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pipescan.core.model import InspectionMeta, SectionMeasures, SectionStatus  # noqa: E402
from pipescan.storage.database import db, queries, repository, trends  # noqa: E402
from pipescan.storage.database.models import Inspection  # noqa: E402

PIPES = 2000
INSPECTIONS = 5
SECTIONS = 500
STEP_M = 0.1
NOMINAL_DIAMETER_M = 0.6
NOMINAL_AREA_M2 = float(np.pi * NOMINAL_DIAMETER_M**2 / 4)
T0 = datetime(2021, 4, 1, 8, 0, tzinfo=UTC)
YEAR = timedelta(days=365.25)


def asset_id(i: int) -> str:
    return f"MH{10000 + i}-MH{10001 + i}"


def pipe_profiles(i: int) -> np.ndarray:
    """(INSPECTIONS, SECTIONS) blockage of pipe ``i``, each survey in its own chainage; NaN
    where unmeasured. Seeded by ``i``: the same network every run."""
    rng = np.random.default_rng(i)
    x = (np.arange(SECTIONS) + 0.5) * STEP_M
    out = np.empty((INSPECTIONS, SECTIONS))
    bumps = [
        (rng.uniform(2, SECTIONS * STEP_M - 2), rng.uniform(0.2, 1.0), rng.uniform(0.02, 0.3))
        for _ in range(rng.integers(1, 4))
    ]
    rates = rng.gamma(1.0, 0.01, size=len(bumps))  # ratio per year, mostly small
    for year in range(INSPECTIONS):
        error_m = 0.0 if year == INSPECTIONS - 1 else STEP_M * int(rng.integers(-3, 4))
        true_x = x - error_m
        value = np.full(SECTIONS, 0.02)
        for (centre, sigma, amplitude), rate in zip(bumps, rates, strict=True):
            value += np.exp(-((true_x - centre) ** 2) / (2 * sigma**2)) * (amplitude + rate * year)
        value += rng.normal(0, 0.004, SECTIONS)
        value[rng.random(SECTIONS) < 0.03] = np.nan
        out[year] = value
    return out


def sections_of(profile: np.ndarray) -> list[SectionMeasures]:
    out = []
    for k, blockage in enumerate(profile.tolist()):
        measured = blockage == blockage  # not NaN
        out.append(
            SectionMeasures(
                chainage_start_m=k * STEP_M,
                chainage_end_m=(k + 1) * STEP_M,
                nominal_area_m2=NOMINAL_AREA_M2,
                status=SectionStatus.OK if measured else SectionStatus.LOW_COVERAGE,
                point_count=900 if measured else 7,
                coverage_ratio=0.97 if measured else 0.12,
                open_area_m2=NOMINAL_AREA_M2 * (1 - blockage) if measured else None,
                blockage_ratio=blockage if measured else None,
                ovality_ratio=0.01 if measured else None,
                deformation_ratio=0.004 if measured else None,
                deposit_height_ratio=max(0.0, blockage * 1.4) if measured else None,
                grade=4 if measured else None,
            )
        )
    return out


def inspections_of(i: int) -> list[repository.InspectionToSave]:
    """Pipe ``i``'s five inspections, ready to save."""
    profiles = pipe_profiles(i)
    return [
        repository.InspectionToSave(
            meta=InspectionMeta(
                asset_id=asset_id(i),
                inspected_at=T0 + year * YEAR + timedelta(days=int(i % 90)),
                nominal_diameter_m=NOMINAL_DIAMETER_M,
                upstream_node=f"MH{10000 + i}",
                downstream_node=f"MH{10001 + i}",
                material="concrete",
            ),
            archive_uri=f"s3://surveys/{asset_id(i)}/{year}.tar.gz",
            content_hash=f"sha256:{i:06d}{year}",
            params={"section_step_m": STEP_M, "contour_method": "polar"},
            software_version="0.1.0",
            sections=sections_of(profiles[year]),
            defects=[],
            threshold_table="vsa-2023",
            scanned_length_m=SECTIONS * STEP_M,
        )
        for year in range(INSPECTIONS)
    ]


def server_cpu_s(server_root: Path | None) -> float:
    """CPU seconds used so far by the PostgreSQL server whose data directory is under
    ``server_root`` (the postmaster and its children, from /proc); 0 when unknown."""
    if server_root is None:
        return 0.0
    try:
        postmaster = int((server_root / "data" / "postmaster.pid").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 0.0
    ticks = 0
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        pid, ppid = int(stat.parent.name), int(fields[1])
        if postmaster in (pid, ppid):
            ticks += int(fields[11]) + int(fields[12])  # utime + stime
    return ticks / os.sysconf("SC_CLK_TCK")


def write_network(
    engine: sa.Engine, pipes: int, label: str, batch_pipes: int, server_root: Path | None = None
) -> None:
    """Bulk import: ``save_inspections``, one transaction per ``batch_pipes`` pipes."""
    rows = 0
    spent_s = client_cpu_s = server_s = 0.0
    started = time.perf_counter()
    for first in range(0, pipes, batch_pipes):
        batch = [
            x for i in range(first, min(pipes, first + batch_pipes)) for x in inspections_of(i)
        ]
        t, cpu, server = time.perf_counter(), time.process_time(), server_cpu_s(server_root)
        repository.save_inspections(engine, batch)
        spent_s += time.perf_counter() - t
        client_cpu_s += time.process_time() - cpu
        server_s += server_cpu_s(server_root) - server
        rows += sum(len(x.sections) for x in batch)
        done = min(pipes, first + batch_pipes)
        if done % max(batch_pipes, pipes // 10 // batch_pipes * batch_pipes) == 0 or done == pipes:
            print(
                f"  {label}: {done}/{pipes} pipes, {rows:,} section rows, "
                f"{rows / spent_s:,.0f} rows/s so far ({time.perf_counter() - started:.0f} s)",
                flush=True,
            )
    print(
        f"{label} bulk write (save_inspections, {batch_pipes * INSPECTIONS} inspections per "
        f"transaction): {rows:,} section rows in {spent_s:.1f} s = {rows / spent_s:,.0f} rows/s"
    )
    # On a shared machine the wall clock also counts other people's work: the CPU time says
    # what the writes themselves cost.
    cpu = f"{label} CPU: client {rows / client_cpu_s:,.0f} rows per CPU-second"
    if server_root is not None:
        cpu += (
            f", server {rows / server_s:,.0f} rows per CPU-second; with a core each, "
            f"{rows / max(client_cpu_s, server_s):,.0f} rows/s; on one core, "
            f"{rows / (client_cpu_s + server_s):,.0f} rows/s"
        )
    print(cpu)


def write_one_by_one(engine: sa.Engine, pipes: range, label: str) -> None:
    """The flows' path: ``save_inspection``, one transaction (and commit) per inspection."""
    rows = 0
    spent_s = 0.0
    for i in pipes:
        for item in inspections_of(i):
            t = time.perf_counter()
            repository.save_inspections(engine, [item])
            spent_s += time.perf_counter() - t
            rows += len(item.sections)
    print(
        f"{label} one inspection per transaction (save_inspection, {len(pipes) * INSPECTIONS} "
        f"inspections): {rows / spent_s:,.0f} rows/s, {len(pipes) * INSPECTIONS / spent_s:.0f} "
        "inspections/s"
    )


def timed(fn, repeat: int) -> tuple[float, float]:
    """(median, best) wall time of ``fn()`` in milliseconds."""
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t) * 1000)
    return statistics.median(times), min(times)


def trend_queries(engine: sa.Engine, asset: str) -> int:
    """The two queries of asset_trend alone: the asset's inspections, then their sections."""
    with engine.connect() as connection:
        ids = connection.scalars(sa.select(Inspection.id).where(Inspection.asset_id == asset)).all()
        return len(connection.execute(trends.trend_statement(ids)).all())


def query_figures(engine: sa.Engine, pipes: int, label: str) -> None:
    rng = np.random.default_rng(0)
    picks = [asset_id(int(i)) for i in rng.integers(0, pipes, 40)]
    assert trend_queries(engine, picks[0]) == INSPECTIONS * SECTIONS
    for a in picks[:3]:  # warm the cache as a server in use would be
        trends.asset_trend(engine, a)
    it = iter(picks * 3)
    median, best = timed(lambda: trend_queries(engine, next(it)), 40)
    print(
        f"{label} trend queries, one asset (2,500 rows): median {median:.1f} ms, best {best:.1f} ms"
    )
    it = iter(picks * 3)
    median, best = timed(lambda: trends.asset_trend(engine, next(it)), 40)
    print(
        f"{label} asset_trend, one asset (queries + alignment + slopes): median {median:.1f} ms,"
        f" best {best:.1f} ms"
    )
    for by in ("growth", "current"):
        median, best = timed(lambda by=by: trends.worst_assets(engine, by=by, limit=10), 3)
        print(f"{label} worst --by {by}, whole network: median {median:.0f} ms, best {best:.0f} ms")
    top = trends.worst_assets(engine, by="growth", limit=3)
    for r in top:
        print(
            f"    {r.asset_id}: peak {100 * r.current_peak_blockage_ratio:.1f} % at "
            f"{r.current_peak_chainage_m:.2f} m, {100 * (r.peak_change_per_year or 0):+.2f} pt/yr"
        )


def network_report_figures(engine: sa.Engine, url: str, label: str) -> None:
    """The network report's queries over the whole network: the latest inspection of each
    asset, the earlier scans of each (window functions), their sections without contours, the
    defect counts, and all of it as the report task gathers it (``load_network_input``)."""
    from pipescan.tasks.reporting import load_network_input

    latest = queries.list_network_inspections(engine)
    ids = [r.id for r in latest]
    history = queries.list_earlier_scans(engine, ids)
    steps = (
        ("latest inspection of each asset", lambda: queries.list_network_inspections(engine)),
        ("earlier scans of each (history)", lambda: queries.list_earlier_scans(engine, ids)),
        ("their sections, no contours", lambda: queries.section_profiles(engine, ids)),
        ("defect counts", lambda: queries.defect_counts(engine, ids)),
        ("all, as the report task reads it", lambda: load_network_input(url)),
    )
    rows = sum(len(v) for v in queries.section_profiles(engine, ids[:1]).values())
    print(
        f"{label} network report queries: {len(latest):,} assets, "
        f"{sum(len(h) for h in history.values()):,} earlier scans, about {rows * len(ids):,} "
        "section rows read"
    )
    for title, fn in steps:
        median, best = timed(fn, 3)
        print(f"    {title}: median {median:,.0f} ms, best {best:,.0f} ms")
    one = ids[len(ids) // 2]
    median, best = timed(lambda: queries.list_earlier_inspections(engine, one, limit=4), 20)
    print(
        f"{label} one inspection report's history (earlier scans, 4): median {median:.1f} ms,"
        f" best {best:.1f} ms"
    )


def _short(line: str, width: int = 160) -> str:
    # A plan line can quote a list of thousands of ids.
    return line if len(line) <= width else line[: width - 5] + " ..."


def explain_network(engine: sa.Engine) -> None:
    """PostgreSQL's plans of the two window-function queries of the network report."""
    with engine.connect() as connection:
        latest = queries.latest_per_asset_statement()
        ids = connection.scalars(latest).all()
        for title, statement in (
            ("latest inspection of each asset", latest),
            ("earlier scans of each", queries.earlier_scans_statement(ids)),
        ):
            sql = statement.compile(connection, compile_kwargs={"literal_binds": True})
            plan = connection.exec_driver_sql(f"EXPLAIN (ANALYZE, BUFFERS) {sql}").scalars().all()
            print(f"EXPLAIN (ANALYZE, BUFFERS), network report: {title}")
            for line in plan:
                print(f"    {_short(line)}")


def explain(engine: sa.Engine, asset: str) -> None:
    with engine.connect() as connection:
        ids = connection.scalars(sa.select(Inspection.id).where(Inspection.asset_id == asset)).all()
        for title, statement in (
            (
                "inspections of the asset",
                sa.select(Inspection.id).where(Inspection.asset_id == asset),
            ),
            ("their sections", trends.trend_statement(ids)),
        ):
            sql = statement.compile(connection, compile_kwargs={"literal_binds": True})
            plan = connection.exec_driver_sql(f"EXPLAIN (ANALYZE, BUFFERS) {sql}").scalars().all()
            print(f"EXPLAIN (ANALYZE, BUFFERS), trend query: {title}")
            for line in plan:
                print(f"    {_short(line)}")


def table_size(engine: sa.Engine) -> str:
    with engine.connect() as connection:
        if engine.dialect.name == "postgresql":
            return connection.exec_driver_sql(
                "SELECT pg_size_pretty(pg_total_relation_size('sections'))"
            ).scalar_one()
    return "-"


def run_postgres(url: str | None, pipes: int, batch: int, one_by_one: int) -> None:
    cluster = None
    database_url = url
    if database_url is None:
        from tests.pg_cluster import PostgresCluster, create_database

        cluster = PostgresCluster(durable=True).start()
        database_url = create_database(cluster.admin_url, "pipescan_bench")
        print(f"PostgreSQL: throwaway cluster on 127.0.0.1:{cluster.port} (fsync on)")
    try:
        db.upgrade(database_url)
        engine = db.connect(database_url)
        try:
            with engine.connect() as connection:
                version = connection.exec_driver_sql("SHOW server_version").scalar_one()
            print(f"PostgreSQL {version}")
            write_network(
                engine, pipes, "PostgreSQL", batch, None if cluster is None else cluster.root
            )
            write_one_by_one(engine, range(pipes, pipes + one_by_one), "PostgreSQL")
            with engine.connect() as connection:
                connection.execution_options(isolation_level="AUTOCOMMIT").exec_driver_sql(
                    "VACUUM ANALYZE"
                )
            print(f"PostgreSQL sections table with its indexes: {table_size(engine)}")
            query_figures(engine, pipes, "PostgreSQL")
            network_report_figures(engine, database_url, "PostgreSQL")
            explain(engine, asset_id(pipes // 2))
            explain_network(engine)
        finally:
            engine.dispose()
    finally:
        if cluster is not None:
            cluster.stop()


def run_sqlite(path: Path, pipes: int, batch: int, one_by_one: int, keep: bool = False) -> None:
    """Write the network into a SQLite file and time the queries; with ``keep``, a file that
    exists already (from an earlier ``--sqlite-file`` run) is only queried."""
    reuse = keep and path.exists()
    if not reuse:
        path.unlink(missing_ok=True)
    engine = db.connect(f"sqlite:///{path}")
    try:
        if reuse:
            print(f"SQLite: querying the network already in {path}")
        else:
            write_network(engine, pipes, "SQLite", batch)
            write_one_by_one(engine, range(pipes, pipes + one_by_one), "SQLite")
            with engine.connect() as connection:
                connection.exec_driver_sql("ANALYZE")
        print(f"SQLite file: {path.stat().st_size / 1e6:,.0f} MB")
        query_figures(engine, pipes, "SQLite")
        network_report_figures(engine, f"sqlite:///{path}", "SQLite")
    finally:
        engine.dispose()
        for suffix in ("", "-wal", "-shm"):
            if not keep:
                Path(f"{path}{suffix}").unlink(missing_ok=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--scale", type=float, default=1.0, help="fraction of the 2,000 pipes (default 1)"
    )
    parser.add_argument("--pg-url", help="an existing PostgreSQL database to write into")
    parser.add_argument("--skip-postgres", action="store_true")
    parser.add_argument("--skip-sqlite", action="store_true")
    parser.add_argument(
        "--sqlite-dir", type=Path, default=None, help="where the SQLite file goes (default: tmp)"
    )
    parser.add_argument(
        "--sqlite-file",
        type=Path,
        default=None,
        help="write the SQLite database here and keep it; if it exists, only time the queries",
    )
    parser.add_argument(
        "--batch", type=int, default=20, help="pipes per bulk transaction (default 20)"
    )
    args = parser.parse_args()
    pipes = max(1, round(PIPES * args.scale))
    # A further 2 % of pipes (at least 10) saved one inspection per transaction, as the flows do.
    one_by_one = max(10, pipes // 50)
    print(
        f"network: {pipes:,} pipes x {INSPECTIONS} inspections x {SECTIONS} sections = "
        f"{pipes * INSPECTIONS * SECTIONS:,} section rows; {os.cpu_count()} CPUs (shared)"
    )
    if not args.skip_postgres:
        run_postgres(args.pg_url, pipes, args.batch, one_by_one)
    if not args.skip_sqlite and args.sqlite_file is not None:
        run_sqlite(args.sqlite_file, pipes, args.batch, one_by_one, keep=True)
    elif not args.skip_sqlite:
        with tempfile.TemporaryDirectory(dir=args.sqlite_dir) as tmp:
            run_sqlite(Path(tmp) / "bench.db", pipes, args.batch, one_by_one)


if __name__ == "__main__":
    main()
