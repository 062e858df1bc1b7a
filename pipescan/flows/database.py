"""The database a flow run writes to: from the settings of the process it runs in.

No database URL is a flow parameter: Prefect stores a run's parameters (and copies them to its
sub-flows) where its UI and API show them, and a URL may hold a password. A flow reads
``PIPESCAN_DATABASE_URL`` (and, if named, the password in a Prefect ``Secret`` block) where it
runs: a deployment's runs on the worker that runs them, ``pipescan inspect --db`` through
:func:`pipescan.settings.use_settings`.
"""

from __future__ import annotations

from pathlib import Path

from sqlalchemy.engine import make_url

from pipescan.settings import Settings, database_url, get_settings
from pipescan.storage.database.db import (
    StorageError,
    check_database,
    parse_database_url,
    refuse_unencoded_password,
)

WORKER_HINT = (
    "set PIPESCAN_DATABASE_URL (an absolute SQLite path or postgresql+psycopg://...) in the "
    "environment of the Prefect worker, see docs/operations.md"
)


def absolute_database_url(url: str) -> str:
    """A SQLite URL with a relative file made absolute; any other URL unchanged.

    Raises
    ------
    StorageError
        When ``url`` cannot be parsed.
    """
    parsed = parse_database_url(url)
    if not is_relative_sqlite(url):
        return url
    return parsed.set(database=str(Path(parsed.database or "").resolve())).render_as_string(
        hide_password=False
    )


def is_relative_sqlite(url: str) -> bool:
    parsed = parse_database_url(url)
    database = parsed.database or ""
    return not (
        parsed.get_backend_name() != "sqlite"
        or database in ("", ":memory:")
        or database.startswith("file:")
        or Path(database).is_absolute()
    )


def in_deployment() -> bool:
    """True inside a run of a Prefect deployment (started by a worker)."""
    from prefect.runtime import deployment

    return deployment.id is not None


def run_database_url(settings: Settings | None = None) -> str:
    """The database of this run, with a relative SQLite file made absolute.

    Raises
    ------
    StorageError
        In a deployment's run, when the worker's settings name no database or a relative SQLite
        file: the worker runs each flow in a temporary folder, where such a file would be
        created and lost.
    PipescanError
        The password's ``Secret`` block cannot be loaded.
    """
    settings = settings or get_settings()
    refuse_unencoded_password(settings.database_url)
    url = database_url(settings)
    if in_deployment():
        if "database_url" not in settings.model_fields_set:
            raise StorageError(
                "no database for this scheduled run: the worker's settings name none",
                field="PIPESCAN_DATABASE_URL",
                hint=WORKER_HINT,
            )
        if is_relative_sqlite(url):
            raise StorageError(
                f"the worker's database {make_url(url)!r} is a relative SQLite path, which a "
                "scheduled run would resolve in its temporary folder",
                field="PIPESCAN_DATABASE_URL",
                hint=WORKER_HINT,
            )
    return absolute_database_url(url)


def checked_database_url(settings: Settings | None = None) -> str:
    """:func:`run_database_url`, checked once: reachable, migrated and writable.

    Raises
    ------
    StorageError
        What is wrong with the database, in one line.
    """
    url = run_database_url(settings)
    refuse_memory_database(url)
    check_database(url)
    return url


def refuse_memory_database(url: str) -> None:
    """Refuse an in-memory SQLite database (``sqlite://``, ``sqlite:///:memory:``, a
    ``mode=memory`` URI) for a run: what it stores is gone when the process ends, and the run
    would report an inspection that nothing keeps.

    Raises
    ------
    StorageError
        Naming the URL and what to give instead.
    """
    parsed = parse_database_url(url)
    database = parsed.database or ""
    memory = (
        database in ("", ":memory:")
        or "mode=memory" in database
        or (str(parsed.query.get("mode", "")) == "memory")
    )
    if parsed.get_backend_name() == "sqlite" and memory:
        raise StorageError(
            f"database {url} is an in-memory SQLite database: what a run stores in it is gone "
            "when the run ends",
            hint="give a database file, e.g. --db inspections.db or sqlite:////data/pipescan.db",
        )


def migration_steps(before: str | None, after: str | None) -> list[str]:
    """The schema migrations between two revisions, one line each, in the order they ran: the
    revision, what it did, and what it means for rows stored before (from the migration's
    docstring), e.g. ``3f6c2d8a1b47 Clock positions and characterisation of each defect
    (NULL for defects stored before: they were not coded)``. Migrations undone by a downgrade
    start with ``undone``."""
    import re

    from alembic.script import ScriptDirectory

    from pipescan.storage.database.db import alembic_config

    if before == after:
        return []
    script = ScriptDirectory.from_config(alembic_config())
    try:
        revisions = list(reversed(list(script.iterate_revisions(after, before or "base"))))
        undone = ""
    except Exception:  # a downgrade: ``after`` is below ``before``
        revisions = list(script.iterate_revisions(before, after or "base"))
        undone = "undone "
    lines = []
    for revision in revisions:
        text = " ".join((revision.longdoc or revision.doc or "").split())
        what = " ".join((revision.doc or "").split())
        before_note = next(
            (
                sentence.strip()
                for sentence in re.split(r"(?<=[.:])\s+(?=[A-Z])", text)
                if "before" in sentence and ("NULL" in sentence or "none" in sentence)
            ),
            None,
        )
        note = f" {before_note.rstrip('.')}." if before_note and not undone else ""
        lines.append(f"{undone}{revision.revision} {what}{note}")
    return lines
