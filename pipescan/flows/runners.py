"""Task runners for the flows: a local thread or process pool, or a Dask cluster."""

from __future__ import annotations

from prefect.task_runners import ProcessPoolTaskRunner, TaskRunner, ThreadPoolTaskRunner

RUNNER_KINDS = ("threads", "processes", "dask")


def make_task_runner(
    kind: str = "threads", workers: int = 2, dask_address: str | None = None
) -> TaskRunner:
    """A task runner by name.

    Parameters
    ----------
    kind
        ``threads`` (default; Open3D and NumPy release the GIL in their heavy loops),
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
