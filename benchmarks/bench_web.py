"""The web view at network scale: server time of the network page, the API and a pipe page.

    python benchmarks/bench_web.py                      # 1,000 pipes x 5 x 100 = 500,000 rows
    python benchmarks/bench_web.py --pipes 10000        # the target: 10,000 pipes, 5 M rows
    python benchmarks/bench_web.py --pg-url postgresql+psycopg://user@host/db   # existing server
    python benchmarks/bench_web.py --skip-sqlite

Generates a network laid out on a grid (node positions in EPSG:25832), each pipe surveyed five
times a year apart with growing deposits and a few unmeasured sections, graded by a simple
blockage rule (a stand-in for the threshold table: this is load, not accuracy), and written with
``repository.save_inspections``. Then it builds ``pipescan serve``'s app on the database, opened
read-only as ``serve`` opens it, and times requests through FastAPI's TestClient (in-process:
the time is the server's, with no network in between): the network page cold (the first
request, which reads the network) and warm (cached until the database changes), ``/api/pipes``,
a pipe page, a pipe's trend, a page of sections and an inspection page. Targets (issue 55): the
network page and API over 10,000 pipes and 5 M section rows on PostgreSQL in at most 1 s, a pipe
page in at most 300 ms. Every figure is printed, marked met or NOT MET; nothing is asserted.

Without ``--pg-url`` a throwaway PostgreSQL cluster is started on loopback (tests/pg_cluster.py)
and deleted at the end.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import replace
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")

from pipescan.core.model import InspectionMeta, SectionMeasures, SectionStatus  # noqa: E402
from pipescan.storage.database import db, repository  # noqa: E402

INSPECTIONS = 5
SECTIONS = 100
STEP_M = 0.1
NOMINAL_DIAMETER_M = 0.4
NOMINAL_AREA_M2 = float(np.pi * NOMINAL_DIAMETER_M**2 / 4)
T0 = datetime(2021, 4, 1, 8, 0, tzinfo=UTC)
YEAR = timedelta(days=365.25)
CRS = "EPSG:25832"
GRID_M = 40.0
NETWORK_TARGET_MS = 1000.0
PIPE_TARGET_MS = 300.0


def asset_id(i: int) -> str:
    return f"MH{100000 + i}-MH{100001 + i}"


def _grade(blockage: float) -> int:
    """A stand-in grading (class 0 worst ... 4 best) by blockage alone, for load only."""
    for grade, limit in ((4, 0.05), (3, 0.10), (2, 0.20), (1, 0.35)):
        if blockage < limit:
            return grade
    return 0


def inspections_of(i: int, columns: int) -> list[repository.InspectionToSave]:
    """Pipe ``i``: an edge of a grid ``columns`` nodes wide, five surveys."""
    rng = np.random.default_rng(i)
    row, col = divmod(i, columns)
    start = (col * GRID_M, row * GRID_M, 100.0)
    end = ((col + 1) * GRID_M, row * GRID_M + rng.uniform(-8, 8), 99.5)
    x = (np.arange(SECTIONS) + 0.5) * STEP_M
    centre, sigma = rng.uniform(1, SECTIONS * STEP_M - 1), rng.uniform(0.2, 1.0)
    amplitude, rate = rng.uniform(0.01, 0.3), rng.gamma(1.0, 0.02)
    out = []
    for year in range(INSPECTIONS):
        profile = 0.02 + np.exp(-((x - centre) ** 2) / (2 * sigma**2)) * (amplitude + rate * year)
        profile += rng.normal(0, 0.004, SECTIONS)
        gaps = rng.random(SECTIONS) < 0.03
        sections = []
        for k, value in enumerate(profile.tolist()):
            ok = not gaps[k]
            sections.append(
                SectionMeasures(
                    chainage_start_m=k * STEP_M,
                    chainage_end_m=(k + 1) * STEP_M,
                    nominal_area_m2=NOMINAL_AREA_M2,
                    status=SectionStatus.OK if ok else SectionStatus.LOW_COVERAGE,
                    point_count=900 if ok else 7,
                    coverage_ratio=0.97 if ok else 0.12,
                    open_area_m2=NOMINAL_AREA_M2 * (1 - value) if ok else None,
                    blockage_ratio=value if ok else None,
                    deposit_height_ratio=max(0.0, value * 1.4) if ok else None,
                    grade=_grade(value) if ok else None,
                )
            )
        out.append(
            repository.InspectionToSave(
                meta=InspectionMeta(
                    asset_id=asset_id(i),
                    inspected_at=T0 + year * YEAR + timedelta(days=i % 90),
                    nominal_diameter_m=NOMINAL_DIAMETER_M,
                    upstream_node=f"MH{100000 + i}",
                    downstream_node=f"MH{100001 + i}",
                    material="concrete",
                    upstream_node_xyz=start,
                    downstream_node_xyz=end,
                    crs=CRS,
                ),
                archive_uri=f"s3://surveys/{asset_id(i)}/{year}.tar.gz",
                content_hash=f"sha256:{i:06d}{year}",
                params={"section_step_m": STEP_M},
                software_version="0.1.0",
                sections=sections,
                defects=[],
                threshold_table="vsa-2023",
                scanned_length_m=SECTIONS * STEP_M,
            )
        )
    return out


def write_network(url: str, pipes: int, label: str, batch: int = 50) -> None:
    engine = db.connect(url)
    columns = max(1, round(math.sqrt(pipes)))
    started = time.perf_counter()
    try:
        for first in range(0, pipes, batch):
            items = [
                x
                for i in range(first, min(pipes, first + batch))
                for x in inspections_of(i, columns)
            ]
            repository.save_inspections(engine, items)
            done = min(pipes, first + batch)
            if done % max(batch, pipes // 10 // batch * batch) == 0 or done == pipes:
                print(
                    f"  {label}: {done:,}/{pipes:,} pipes written "
                    f"({time.perf_counter() - started:.0f} s)",
                    flush=True,
                )
        with engine.connect() as connection:
            if engine.dialect.name == "postgresql":
                connection.execution_options(isolation_level="AUTOCOMMIT").exec_driver_sql(
                    "VACUUM ANALYZE"
                )
            else:
                connection.exec_driver_sql("ANALYZE")
    finally:
        engine.dispose()


def _ms(fn: Callable[[], object], repeat: int) -> tuple[float, float, list[float]]:
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(1000 * (time.perf_counter() - t))
    return statistics.median(times), min(times), times


def time_app(url: str, pipes: int, label: str, repeat: int) -> None:
    from fastapi.testclient import TestClient

    from pipescan.web import WebConfig, create_app

    t = time.perf_counter()
    app = create_app(WebConfig(database_url=url))
    print(f"{label}: app built in {1000 * (time.perf_counter() - t):.0f} ms (read-only engine)")
    t = time.perf_counter()
    with TestClient(app) as client:
        print(
            f"{label}: started (the network read before listening) in "
            f"{1000 * (time.perf_counter() - t):.0f} ms"
        )

        def get(path: str) -> None:
            response = client.get(path)
            if response.status_code != 200:
                raise RuntimeError(f"{path}: HTTP {response.status_code}: {response.text[:300]}")

        t = time.perf_counter()
        get("/")
        cold = 1000 * (time.perf_counter() - t)
        middle = asset_id(pipes // 2)
        inspection = client.get(f"/api/pipes/{middle}").json()["last_inspection_id"]
        rows = [
            ("network page, first request after start", cold, cold, NETWORK_TARGET_MS),
        ]
        for name, path, target in (
            ("network page, warm (cached until the database changes)", "/", NETWORK_TARGET_MS),
            ("network page, sorted by growth, page 3", "/?sort=growth&page=3", NETWORK_TARGET_MS),
            ("network page, search", "/?q=MH1000", NETWORK_TARGET_MS),
            ("API /api/pipes (100 pipes)", "/api/pipes", NETWORK_TARGET_MS),
            ("API /api/pipes?limit=1000", "/api/pipes?limit=1000", NETWORK_TARGET_MS),
            ("pipe page", f"/pipes/{middle}", PIPE_TARGET_MS),
            ("pipe page at a chainage", f"/pipes/{middle}?at=5.0", PIPE_TARGET_MS),
            ("API a pipe's trend", f"/api/pipes/{middle}/trend", PIPE_TARGET_MS),
            ("API a page of 500 sections", f"/api/inspections/{inspection}/sections", None),
            ("inspection page, first (draws the report's charts)", None, None),
            ("inspection page, again (cached)", f"/inspections/{inspection}", None),
        ):
            if path is None:
                t = time.perf_counter()
                get(f"/inspections/{inspection}")
                first = 1000 * (time.perf_counter() - t)
                rows.append((name, first, first, target))
                continue
            median, best, _ = _ms(lambda p=path: get(p), repeat)
            rows.append((name, median, best, target))
        print(f"{label}, {pipes:,} pipes, {pipes * INSPECTIONS * SECTIONS:,} section rows:")
        print(f"  {'request':58} {'median ms':>10} {'best ms':>9}  target")
        for name, median, best, target in rows:
            verdict = ""
            if target is not None:
                verdict = f"<= {target:.0f} ms: " + ("met" if median <= target else "NOT MET")
            print(f"  {name:58} {median:>10.1f} {best:>9.1f}  {verdict}")
        # A save while serving: the next request gets the previous read and starts a new one.
        extra = inspections_of(0, max(1, round(math.sqrt(pipes))))[-1]
        later = replace(
            extra,
            meta=replace(extra.meta, inspected_at=extra.meta.inspected_at + YEAR),
            content_hash="sha256:bench-web-later",
        )
        writer = db.connect(url)
        try:
            (new_id,) = repository.save_inspections(writer, [later])
        finally:
            writer.dispose()
        median, _, _ = _ms(lambda: get("/"), 1)
        print(f"  {'network page right after a save (the previous read)':58} {median:>10.1f}")
        t = time.perf_counter()
        while client.get(f"/api/pipes/{asset_id(0)}").json()["last_inspection_id"] != new_id:
            time.sleep(0.05)
        waited = 1000 * (time.perf_counter() - t)
        print(f"  {'... until the new read is served':58} {waited:>10.1f}")
        # Where a read of the network goes, part by part.
        from pipescan.storage.database import web_queries
        from pipescan.storage.database.network import asset_geometries
        from pipescan.storage.database.queries import defect_counts, latest_per_asset_statement
        from pipescan.storage.database.trends import worst_assets

        engine = app.state.engine
        latest = client.get("/api/pipes", params={"limit": 1000}).json()["items"]
        ids = [p["last_inspection_id"] for p in latest]
        assets = [asset_id(i) for i in range(pipes)]
        for name, fn in (
            ("  network_pipes, a whole read", lambda: web_queries.network_pipes(engine)),
            (
                "    worst_grades (over the latest inspections' sections)",
                lambda: web_queries.worst_grades(engine, latest_per_asset_statement()),
            ),
            (
                "    worst_assets (every pipe's growth)",
                lambda: worst_assets(engine, by="current", limit=pipes + 10),
            ),
            ("    asset_geometries (every line)", lambda: asset_geometries(engine, assets)),
            ("    defect_counts (1,000 ids)", lambda: defect_counts(engine, ids)),
            (
                "  database_version (each request's check)",
                lambda: web_queries.database_version(engine),
            ),
        ):
            median, best, _ = _ms(fn, max(1, repeat // 2))
            print(f"{name:60} {median:>10.1f} {best:>9.1f}")


def run_postgres(url: str | None, pipes: int, repeat: int, write: bool = True) -> None:
    cluster = None
    database_url = url
    if database_url is None:
        from tests.pg_cluster import PostgresCluster, create_database

        cluster = PostgresCluster().start()
        database_url = create_database(cluster.admin_url, "pipescan_bench_web")
        print(f"PostgreSQL: throwaway cluster on 127.0.0.1:{cluster.port}")
    try:
        if write:
            db.upgrade(database_url)
            write_network(database_url, pipes, "PostgreSQL")
        time_app(database_url, pipes, "PostgreSQL", repeat)
    finally:
        if cluster is not None:
            cluster.stop()


def run_sqlite(folder: Path, pipes: int, repeat: int) -> None:
    path = folder / "bench_web.db"
    write_network(f"sqlite:///{path}", pipes, "SQLite")
    print(f"SQLite file: {path.stat().st_size / 1e6:,.0f} MB")
    time_app(f"sqlite:///{path}", pipes, "SQLite", repeat)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pipes", type=int, default=1000, help="pipes (default 1,000)")
    parser.add_argument("--repeat", type=int, default=5, help="requests per figure (median)")
    parser.add_argument("--pg-url", help="an existing PostgreSQL database to write into")
    parser.add_argument(
        "--no-write", action="store_true", help="with --pg-url: time the network already there"
    )
    parser.add_argument("--skip-postgres", action="store_true")
    parser.add_argument("--skip-sqlite", action="store_true")
    args = parser.parse_args()
    print(
        f"network: {args.pipes:,} pipes x {INSPECTIONS} inspections x {SECTIONS} sections = "
        f"{args.pipes * INSPECTIONS * SECTIONS:,} section rows; {os.cpu_count()} CPUs (shared), "
        f"load average {os.getloadavg()[0]:.1f}"
    )
    if not args.skip_postgres:
        run_postgres(args.pg_url, args.pipes, args.repeat, write=not args.no_write)
    if not args.skip_sqlite:
        with tempfile.TemporaryDirectory() as tmp:
            run_sqlite(Path(tmp), args.pipes, args.repeat)
    print(f"load average at the end {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
