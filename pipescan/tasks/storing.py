"""Prefect tasks at the edges of a run: staging the archive and storing the results."""

from __future__ import annotations

from pathlib import Path

from prefect import task
from prefect.cache_policies import NO_CACHE

from pipescan.storage.database.db import connect
from pipescan.storage.database.repository import InspectionToSave, save_inspection
from pipescan.storage.input.archive import open_archive
from pipescan.storage.input.limits import DEFAULT_LIMITS, InputLimits
from pipescan.tasks import enginepool
from pipescan.tasks.retries import IO_RETRY_OPTIONS
from pipescan.tasks.staged import StagedArchive


@task(name="stage-archive", cache_policy=NO_CACHE, **IO_RETRY_OPTIONS)
def stage_archive(
    archive: str,
    run_dir: Path,
    limits: InputLimits = DEFAULT_LIMITS,
    engine_processes: int = 0,
) -> StagedArchive:
    """Open and validate an archive; unpack a file archive into the run's scratch directory.

    A local directory archive (a path or a ``file://`` URL) is used in place and never moved:
    only what :func:`open_archive` extracted into ``run_dir`` is. Later tasks reopen ``root``
    as a directory, under the same ``limits``. With ``engine_processes``, an archive of
    frames starts the engine pool's workers as soon as it is open, so that their imports
    overlap hashing its content (a registered cloud needs none).
    """
    with open_archive(archive, workdir=run_dir, limits=limits) as arc:
        if arc.frame_count:
            enginepool.import_here_ahead()
        if engine_processes and arc.frame_count:
            enginepool.prestart(engine_processes)
        # Hash while the extracted files are still where the archive object expects them.
        content_hash = arc.content_hash
        root = arc.detach_extraction(run_dir / "archive")
        return StagedArchive(
            name=arc.name,
            root=root,
            meta=arc.meta,
            content_hash=content_hash,
            frame_count=arc.frame_count,
            cloud_member=arc.cloud_member,
            limits=limits,
            bag=arc.bag,
        )


@task(name="save-results", cache_policy=NO_CACHE, **IO_RETRY_OPTIONS)
def save_results(database_url: str, inspection: InspectionToSave) -> int:
    """Write the inspection and all its rows in one transaction; returns its id."""
    engine = connect(database_url)
    try:
        return save_inspection(engine, inspection)
    finally:
        engine.dispose()
