"""Prefect tasks and helpers of a network run: finding the archives in a store, deciding which
errors are worth a retry, and looking up inspections already stored.

A store is a local directory or any fsspec URL (``s3://bucket/runs``, ``memory://...``)
holding many scan archives: directories with an ``inspection.toml``, or ``.zip``, ``.tar``,
``.tar.gz``/``.tgz`` files, at any depth.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import PurePosixPath

import sqlalchemy as sa
from prefect import task
from prefect.cache_policies import NO_CACHE

from pipescan.core.errors import (
    PipescanError,
)
from pipescan.core.model import Defect, SectionMeasures
from pipescan.core.sanitize import strip_credentials
from pipescan.storage.database.db import connect, session_scope
from pipescan.storage.database.models import Inspection
from pipescan.storage.database.repository import (
    InspectionRecord,
    find_inspection,
    get_inspection,
    list_defects,
    list_sections,
)
from pipescan.storage.input.metadata import INSPECTION_FILE
from pipescan.storage.input.urls import is_local, url_filesystem
from pipescan.tasks.retries import IO_RETRY_OPTIONS

ARCHIVE_SUFFIXES = (".tar.gz", ".tgz", ".zip", ".tar")
"""File names that are scan archives in a store (directories are recognised by content)."""


class StoreError(PipescanError):
    """A store of archives is missing, unreadable or holds no archive."""


class EmptyStoreError(StoreError):
    """The store exists but holds no archive (yet)."""


# --- the store --------------------------------------------------------------------------------


def archive_label(uri: str) -> str:
    """A short name for an archive: its file or folder name without the archive suffix.

    >>> archive_label("s3://bucket/2026-11/MH1042-MH1043.tar.gz")
    'MH1042-MH1043'
    """
    name = PurePosixPath(uri.rstrip("/").split("://", 1)[-1]).name
    for suffix in ARCHIVE_SUFFIXES:
        if name.lower().endswith(suffix) and len(name) > len(suffix):
            return name[: -len(suffix)]
    return name


def _natural_key(text: str) -> list:
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", text)]


def find_archives(store: str) -> list[str]:
    """Every scan archive in a store, in natural order of their paths.

    Parameters
    ----------
    store
        A local directory or an fsspec URL. Archives are found at any depth: a directory
        holding ``inspection.toml`` (not looked into further), or a file named ``*.zip``,
        ``*.tar``, ``*.tar.gz`` or ``*.tgz`` outside such a directory.

    Returns
    -------
    list of str
        Local paths for a local store, full URLs (with their protocol) otherwise, as
        :func:`pipescan.storage.input.archive.open_archive` takes them.

    Raises
    ------
    StoreError
        The store does not exist, is not a directory, or holds no archive. A failed listing
        (network, credentials) is raised as the ``OSError`` it is, so that it can be retried.
    """
    fs, root = url_filesystem(store, store, error=StoreError, what="the store")
    root = root.rstrip("/") or root
    if not fs.exists(root):
        raise StoreError("the store does not exist", archive=store, hint="check the path or URL")
    if not fs.isdir(root):
        raise StoreError(
            "the store is a file, not a folder of archives",
            archive=store,
            hint="to process one archive, use 'pipescan inspect'",
        )
    files = [p for p in fs.find(root) if not fs.isdir(p)]
    archive_dirs = {
        str(PurePosixPath(p).parent) for p in files if PurePosixPath(p).name == INSPECTION_FILE
    }

    def inside_archive_dir(path: str) -> bool:
        return any(str(parent) in archive_dirs for parent in PurePosixPath(path).parents)

    archive_files = [
        p
        for p in files
        if p.lower().endswith(ARCHIVE_SUFFIXES)
        and not PurePosixPath(p).name.startswith(".")
        and not inside_archive_dir(p)
    ]
    found = sorted(
        [d for d in archive_dirs if not inside_archive_dir(d)] + archive_files, key=_natural_key
    )
    if not found:
        raise EmptyStoreError(
            "the store holds no scan archive",
            archive=store,
            hint="a store holds folders with an inspection.toml, or .zip/.tar/.tar.gz files",
        )
    if is_local(fs):
        return found
    return [fs.unstrip_protocol(p) for p in found]


@task(name="discover-archives", cache_policy=NO_CACHE, **IO_RETRY_OPTIONS)
def discover_archives(store: str) -> list[str]:
    """List the scan archives of a store (see :func:`find_archives`)."""
    return find_archives(store)


# --- inspections already stored ----------------------------------------------------------------


@dataclass(frozen=True)
class StoredInspection:
    """An inspection read back from the database, to summarise a re-run that reused it."""

    record: InspectionRecord
    sections: list[SectionMeasures]
    defects: list[Defect]


def stored_inspection_id(
    database_url: str, asset_id: str, content_hash: str, params_hash: str
) -> int | None:
    """The id of the stored inspection of this archive content under these parameters, if any.

    ``(asset_id, content_hash, params_hash)`` is an inspection's identity: saving the same
    identity again replaces the earlier inspection, so there is at most one.
    """
    engine = connect(database_url)
    try:
        return find_inspection(engine, asset_id, content_hash, params_hash)
    finally:
        engine.dispose()


@task(name="find-stored-inspection", cache_policy=NO_CACHE, **IO_RETRY_OPTIONS)
def find_stored_inspection(
    database_url: str, asset_id: str, content_hash: str, params_hash: str
) -> int | None:
    """The id of this archive's inspection under these parameters if already stored, or None."""
    return stored_inspection_id(database_url, asset_id, content_hash, params_hash)


@task(name="load-stored-inspection", cache_policy=NO_CACHE, **IO_RETRY_OPTIONS)
def load_stored_inspection(database_url: str, inspection_id: int) -> StoredInspection:
    """Read a stored inspection with its sections and defects."""
    engine = connect(database_url)
    try:
        with session_scope(engine) as session:
            return StoredInspection(
                record=get_inspection(session, inspection_id),
                sections=list_sections(session, inspection_id),
                defects=list_defects(session, inspection_id),
            )
    finally:
        engine.dispose()


def stored_archive_uris(database_url: str) -> set[str]:
    """The archive URIs (without credentials) that stored inspections came from."""
    engine = connect(database_url)
    try:
        with session_scope(engine) as session:
            return set(session.scalars(sa.select(Inspection.archive_uri).distinct()))
    finally:
        engine.dispose()


@task(name="stored-archives", cache_policy=NO_CACHE, **IO_RETRY_OPTIONS)
def find_stored_archives(database_url: str) -> set[str]:
    """The archives with a stored inspection (see :func:`stored_archive_uris`)."""
    return stored_archive_uris(database_url)


def unstored_first(archives: list[str], stored: set[str]) -> list[str]:
    """The archives with no stored inspection first (those an earlier run left missing, and
    new ones), then the others, each group in store order.

    >>> unstored_first(["a", "b", "c"], {"a"})
    ['b', 'c', 'a']
    """
    missing = [a for a in archives if strip_credentials(a) not in stored]
    return missing + [a for a in archives if strip_credentials(a) in stored]
