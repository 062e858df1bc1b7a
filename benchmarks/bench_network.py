"""Network runs: Dask scaling (2 workers against 1) and Prefect's overhead per task run against
the work of one register-chunk and one measure-window task.

Prints:
- Prefect's overhead per task run: N trivial tasks on the flow's API (a temporary server),
  submitted to a local thread pool and to a one-worker Dask cluster;
- the work of each register-chunk and measure-window task on one simulated archive (the task
  functions timed without Prefect), and the overhead as a share of it;
- the wall time of ``inspect_network`` over A simulated archives on a Dask LocalCluster of 1 and
  of 2 worker processes (one thread each), and the speedup.

Usage::

    python benchmarks/bench_network.py                 # 20 archives, 200 trivial tasks
    python benchmarks/bench_network.py --archives 4 --tasks 50   # quick
    python benchmarks/bench_network.py --skip-dask     # overhead and task work only

The archives are the paper's scenario over 1.3 m at 100,000 points/s (a real Livox HAP gives
~4.5x the points per frame, so its tasks do ~4.5x the work for the same overhead).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

# Prefect reads its settings at import: a temporary home keeps the run out of ~/.prefect.
_HOME = tempfile.mkdtemp(prefix="bench-network-prefect-")
os.environ.setdefault("PREFECT_HOME", _HOME)
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from prefect import flow, task  # noqa: E402
from prefect.task_runners import ThreadPoolTaskRunner  # noqa: E402

from pipescan.core.registration import plan_chunks  # noqa: E402
from pipescan.core.sections import plan_windows  # noqa: E402
from pipescan.flows.inspect import InspectionParams  # noqa: E402
from pipescan.flows.network import inspect_network  # noqa: E402
from pipescan.settings import use_settings  # noqa: E402
from pipescan.tasks.inspection import (  # noqa: E402
    bucket_points,
    fit_pipe_axis,
    measure_sections,
    register_chunk,
)
from pipescan.tasks.storing import stage_archive  # noqa: E402
from tests.netstore import write_store  # noqa: E402


@task
def _noop(i: int) -> int:
    return i


def prefect_overhead_s(n: int, runner) -> float:
    """Mean wall time per trivial task run: submit n, wait for all, divide."""

    @flow(task_runner=runner)
    def trivial(n: int) -> float:
        _noop.submit(-1).result()  # warm-up: first-run set-up is not per-task overhead
        started = time.perf_counter()
        futures = [_noop.submit(i) for i in range(n)]
        assert [f.result() for f in futures] == list(range(n))
        return (time.perf_counter() - started) / n

    return trivial(n)


def task_work_s(archive: Path, work: Path, params: InspectionParams) -> dict[str, list[float]]:
    """Time each register-chunk and measure-window task's function on one archive."""
    staged = stage_archive.fn(str(archive), work)
    times: dict[str, list[float]] = {"register-chunk": [], "measure-window": []}
    parts = []
    for a, b in plan_chunks(staged.frame_count, params.chunk_frames):
        t = time.perf_counter()
        parts.append(register_chunk.fn(staged, a, b, params.registration))
        times["register-chunk"].append(time.perf_counter() - t)
    from pipescan.core.registration import chain_trajectories

    trajectory = chain_trajectories(parts)
    fit = fit_pipe_axis.fn(staged, trajectory, max_range_m=params.max_section_range_m)
    windows = plan_windows(
        fit.chainage_min_m, fit.chainage_max_m, step_m=params.step_m, window_m=params.window_m
    )
    buckets = work / "buckets"
    for a, b in plan_chunks(staged.frame_count, params.chunk_frames):
        bucket_points.fn(
            staged, trajectory, a, b, fit.axis, windows, buckets, params.max_section_range_m
        )
    for w in windows:
        t = time.perf_counter()
        measure_sections.fn(buckets, w, fit.axis, staged.meta.nominal_diameter_m, params.measure)
        times["measure-window"].append(time.perf_counter() - t)
    return times


def dask_wall_s(
    store: Path, work: Path, n_workers: int, concurrency: int, threads_per_archive: int
) -> tuple[float, dict]:
    from distributed import Client, LocalCluster

    with (
        LocalCluster(
            n_workers=n_workers,
            threads_per_worker=1,
            processes=True,
            memory_limit="3GiB",
            dashboard_address=None,
        ) as cluster,
        Client(cluster) as client,
    ):
        # Warm the workers (imports of Open3D, Prefect, pipescan) outside the timing.
        client.run(lambda: __import__("pipescan.flows.inspect"))
        started = time.perf_counter()
        with use_settings(database_url=f"sqlite:///{work / f'dask{n_workers}.db'}"):
            summary = inspect_network(
                store=str(store),
                work_dir=str(work / f"scratch{n_workers}"),
                concurrency=concurrency,
                dask_address=cluster.scheduler_address,
                workers=threads_per_archive,
                write_network_report=False,
                reuse_stored=False,
            )
        return time.perf_counter() - started, summary.counts


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--archives", type=int, default=20, help="simulated archives (20)")
    parser.add_argument("--tasks", type=int, default=200, help="trivial tasks for overhead")
    parser.add_argument("--concurrency", type=int, default=4, help="archives in flight (4)")
    parser.add_argument(
        "--threads-per-archive",
        type=int,
        default=1,
        help="threads of each archive's chunk/window pool on its worker (1: one worker = one core)",
    )
    parser.add_argument("--skip-dask", action="store_true", help="no Dask scaling run")
    parser.add_argument(
        "--skip-overhead", action="store_true", help="no overhead and task-work figures"
    )
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench-network-"))
    params = InspectionParams()
    print(f"bench_network: {os.cpu_count()} CPUs; load average {os.getloadavg()[0]:.1f} at start")

    store = work / "store"
    t = time.perf_counter()
    write_store(store, args.archives)
    print(f"simulated {args.archives} archives in {time.perf_counter() - t:.0f} s")
    if not args.skip_overhead:
        overhead_and_work(args.tasks, store, work, params)
    if args.skip_dask:
        return
    walls = {}
    for n in (1, 2):
        walls[n], counts = dask_wall_s(store, work, n, args.concurrency, args.threads_per_archive)
        print(
            f"Dask LocalCluster, {n} worker(s) x 1 thread, {args.threads_per_archive} thread(s) "
            f"per archive: {walls[n]:6.1f} s for {args.archives} archives "
            f"({walls[n] / args.archives:.2f} s each) {counts}"
        )
    print(f"speedup 2 workers vs 1: {walls[1] / walls[2]:.2f}x")
    print(f"load average {os.getloadavg()[0]:.1f} at end (the CPU may be shared)")


def overhead_and_work(tasks: int, store: Path, work: Path, params: InspectionParams) -> None:
    from distributed import Client, LocalCluster
    from prefect_dask import DaskTaskRunner

    threads = prefect_overhead_s(tasks, ThreadPoolTaskRunner(max_workers=2))
    with (
        LocalCluster(
            n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None
        ) as cluster,
        Client(cluster),
    ):
        on_dask = prefect_overhead_s(tasks, DaskTaskRunner(address=cluster.scheduler_address))
    print(f"Prefect overhead per task run ({tasks} trivial tasks, temporary API server):")
    print(f"  local thread pool: {1000 * threads:7.1f} ms")
    print(f"  Dask (1 worker):   {1000 * on_dask:7.1f} ms")
    times = task_work_s(store / "MH0-MH1", work / "one", params)
    print(
        f"task work on one archive (chunk_frames={params.chunk_frames}, "
        f"window_m={params.window_m}):"
    )
    for name, values in times.items():
        mean = statistics.fmean(values)
        print(
            f"  {name:15s} {len(values)} tasks, mean {mean:6.2f} s "
            f"(min {min(values):.2f}, max {max(values):.2f}); overhead "
            f"{100 * threads / mean:.1f} % (threads), {100 * on_dask / mean:.1f} % (Dask)"
        )


if __name__ == "__main__":
    main()
