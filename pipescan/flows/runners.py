"""Task runners for the flows: a local thread or process pool, or a Dask cluster."""

from __future__ import annotations

import multiprocessing
import os

from prefect.context import FlowRunContext
from prefect.task_runners import ProcessPoolTaskRunner, TaskRunner, ThreadPoolTaskRunner

RUNNER_KINDS = ("threads", "processes", "dask")


def make_task_runner(
    kind: str = "threads", workers: int = 2, dask_address: str | None = None
) -> TaskRunner:
    """A task runner by name.

    Parameters
    ----------
    kind
        ``threads`` (default; NumPy and Open3D release the GIL in their heavy loops;
        small_gicp does not, so registration's own calls use the pool's cores instead:
        :func:`engine_threads`),
        ``processes`` (spawned workers: true parallelism, a few seconds to start) or ``dask``
        (the tasks run on the Dask cluster whose scheduler is at ``dask_address``).
    workers
        Threads or processes of a local pool (a Dask cluster has its own workers).
    dask_address
        The Dask scheduler, e.g. ``tcp://10.0.0.5:8786``; given alone, it selects ``dask``.

    Raises
    ------
    ValueError
        For an unknown kind, or ``dask`` without an address.
    """
    if dask_address:
        kind = "dask"
    if kind == "dask":
        if not dask_address:
            raise ValueError(
                "the dask task runner needs the scheduler's address, e.g. tcp://host:8786 "
                "(--dask ADDRESS or PIPESCAN_DASK_ADDRESS)"
            )
        from prefect_dask import DaskTaskRunner

        return DaskTaskRunner(address=dask_address)
    if kind == "processes":
        return ProcessPoolTaskRunner(max_workers=workers)
    if kind == "threads":
        return ThreadPoolTaskRunner(max_workers=workers)
    raise ValueError(f"unknown task runner {kind!r}: use one of {', '.join(RUNNER_KINDS)}")


def _thread_workers(runner: TaskRunner | None = None) -> int:
    """The thread-pool workers of ``runner`` (by default the running flow's), at most the
    machine's cores; 0 when it is not a thread pool."""
    if runner is None:
        context = FlowRunContext.get()
        runner = context.task_runner if context is not None else None
    if not isinstance(runner, ThreadPoolTaskRunner):
        return 0
    workers = getattr(runner, "_max_workers", 1) or 1
    return max(1, min(int(workers), os.cpu_count() or 1))


def engine_processes(enabled: bool = True, runner: TaskRunner | None = None) -> int:
    """Worker processes that register the chunks of a flow on ``runner`` (by default the
    running flow's; :mod:`pipescan.tasks.enginepool`), 0 for none.

    On a thread pool of two or more workers (and cores), as many as it has: two chunks then
    register at the same time, which threads cannot do (:func:`engine_threads`). Under a
    process pool or Dask each task already has its own process, and a daemonic process (a
    Dask worker running a whole inspection) may not start any: 0.
    """
    if multiprocessing.current_process().daemon:
        return 0  # a pool's worker (Dask's, a process pool's) may not start processes
    workers = _thread_workers(runner)
    return workers if enabled and workers >= 2 else 0


def engine_threads() -> int:
    """Threads a native engine may use within one task of the running flow.

    small_gicp holds the GIL for the whole of each call, so on a thread pool two chunks never
    register at the same time: each call then uses as many threads as the pool has workers,
    at most the machine's cores (docs/throughput.md, *The design*). Under a process pool or
    Dask every task has its own interpreter and core: 1.
    """
    return max(1, _thread_workers())


def limit_library_threads(threads: int) -> None:
    """Let the native libraries' own thread pools (NumPy's and SciPy's BLAS, OpenMP in Open3D
    and small_gicp) use at most ``threads`` threads, in this process and in the processes it
    starts from now on (the engine pool's, a process pool's). A thread count a call gives
    explicitly (small_gicp's ``num_threads``, :func:`engine_threads`) still applies.

    pipescan keeps the cores busy itself (task workers, the engine pool). The libraries would
    otherwise split large products and loops over every core and keep their threads spinning
    after them, on cores that other work needs: one thread costs less CPU for the same result
    to the bit (the figures: docs/throughput.md, *Library threads*).
    """
    from threadpoolctl import threadpool_limits

    # Read by OpenBLAS and OpenMP when a new process loads them; the limit below is this
    # process's.
    os.environ["OPENBLAS_NUM_THREADS"] = os.environ["OMP_NUM_THREADS"] = str(threads)
    threadpool_limits(limits=threads)
