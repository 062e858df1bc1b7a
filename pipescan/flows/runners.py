"""Task runners for the flows: a local thread or process pool (Dask arrives with prefect-dask)."""

from __future__ import annotations

from prefect.task_runners import ProcessPoolTaskRunner, TaskRunner, ThreadPoolTaskRunner


def make_task_runner(kind: str = "threads", workers: int = 2) -> TaskRunner:
    """A task runner by name: ``threads`` (default; Open3D and NumPy release the GIL in their
    heavy loops) or ``processes`` (spawned workers: true parallelism, a few seconds to start)."""
    if kind == "processes":
        return ProcessPoolTaskRunner(max_workers=workers)
    if kind == "threads":
        return ThreadPoolTaskRunner(max_workers=workers)
    raise ValueError(f"unknown task runner {kind!r}: use 'threads' or 'processes'")
