"""Database engines, schema migrations and sessions.

The embedded default is a SQLite file (:data:`DEFAULT_DATABASE_URL`); at scale the same
models and migrations run on PostgreSQL. :func:`connect` is the one entry point for code that
wants a ready database: it migrates a new or outdated SQLite file on first use and refuses a
PostgreSQL database that is not at the current revision (migrating a shared server is an
explicit operator step: ``pipescan db upgrade``).

SQLite is set up for several processes writing one file (Prefect fans work out over
processes): write-ahead logging, so readers never block the writer (with ``synchronous =
NORMAL``, its recommended companion: no flush per commit); a 30 s busy timeout, so a
writer waits for the lock instead of failing with "database is locked"; and writes that take
the lock when their transaction begins (``BEGIN IMMEDIATE``), because in WAL mode a
transaction that read first and then tries to write after another process committed fails at
once, whatever the timeout. WAL needs a local file system (not NFS or SMB).
"""

from __future__ import annotations

import sqlite3
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import sqlalchemy as sa
from alembic import command
from alembic.config import Config
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
from alembic.util import CommandError
from sqlalchemy import event
from sqlalchemy.engine import URL, Connection, Engine, make_url
from sqlalchemy.orm import Session

from pipescan import __version__
from pipescan.core.errors import PipescanError

DEFAULT_DATABASE_URL = "sqlite:///pipescan.db"
"""A SQLite file in the working directory."""

SQLITE_BUSY_TIMEOUT_S = 30.0
"""How long a SQLite writer waits for another writer's lock before giving up, in seconds."""

MIGRATIONS_DIR = Path(__file__).resolve().parent / "migrations"
"""The Alembic script directory shipped inside the package."""

# Connection execution option read by the SQLite "begin" listener.
_BEGIN_IMMEDIATE = "pipescan_sqlite_begin_immediate"

# Date-prefixed revision files, e.g. versions/2026_11_23_0001_initial_schema.py.
_FILE_TEMPLATE = "%(year)d_%(month).2d_%(day).2d_%(hour).2d%(minute).2d_%(slug)s"


class StorageError(PipescanError):
    """The database is unreachable, at the wrong schema revision, or refused a write."""


UNENCODED_PASSWORD_HINT = (
    "percent-encode it in the URL (@ as %40, : as %3A, / as %2F, % as %25), or keep the "
    "password out of the URL in a Prefect Secret block (PIPESCAN_DATABASE_PASSWORD_BLOCK, "
    "docs/operations.md)"
)


def refuse_unencoded_password(url: str) -> None:
    """Refuse a URL whose password holds an unencoded ``@``, before it is parsed or used:
    the URL parser ends the password at its first ``@`` and takes the rest of it for the
    host, which a connection error would then print.

    Raises
    ------
    StorageError
        In one line that names no part of the URL but its scheme.
    """
    scheme, sep, rest = url.partition("://")
    if not sep or rest.count("@") < 2:
        return
    try:
        parsed = make_url(url)
        unencoded = "@" in (parsed.host or "")
    except (sa.exc.ArgumentError, ValueError):  # e.g. the password's tail read as a port
        unencoded = True
    if unencoded:
        raise StorageError(
            f"the {scheme}:// database URL holds an unencoded '@' in its password, which would "
            "be read as part of the host (the URL is not shown: it holds the password)",
            hint=UNENCODED_PASSWORD_HINT,
        )


def parse_database_url(url: str | URL) -> URL:
    """``url`` parsed (SQLAlchemy's ``make_url``).

    Raises
    ------
    StorageError
        It cannot be parsed (also a port that is not a number), or its password holds an
        unencoded ``@`` (:func:`refuse_unencoded_password`), in one line.
    """
    if isinstance(url, URL):
        return url
    refuse_unencoded_password(url)
    try:
        return make_url(url)
    except (sa.exc.ArgumentError, ValueError) as exc:  # a port that is not a number
        raise StorageError(
            f"cannot parse database URL {url!r}",
            hint="give a SQLite file's path, or a URL such as sqlite:///pipescan.db or "
            "postgresql+psycopg://user@host/db",
        ) from exc


def _is_sqlite(url: URL) -> bool:
    return url.get_backend_name() == "sqlite"


def _display_url(url: URL) -> str:
    return url.render_as_string(hide_password=True)


def create_engine_for(url: str | URL) -> Engine:
    """Create an engine for a database URL, set up for pipescan.

    Parameters
    ----------
    url
        A SQLAlchemy URL, e.g. ``sqlite:///pipescan.db`` (relative to the working directory),
        ``sqlite:////abs/path/pipescan.db`` or ``postgresql+psycopg://user@host/pipescan``.

    Returns
    -------
    Engine
        For SQLite: foreign keys enforced, WAL journal, a busy timeout of
        :data:`SQLITE_BUSY_TIMEOUT_S`, and the parent directory of the file created if
        missing. For other databases: a pooled engine that checks connections before use.

    Raises
    ------
    StorageError
        If the URL cannot be parsed or names a driver that is not installed.
    """
    parsed = parse_database_url(url)
    try:
        if _is_sqlite(parsed):
            _ensure_sqlite_parent_dir(parsed)
            engine = sa.create_engine(parsed, connect_args={"timeout": SQLITE_BUSY_TIMEOUT_S})
            _install_sqlite_listeners(engine)
            return engine
        return sa.create_engine(parsed, pool_pre_ping=True)
    except (ImportError, sa.exc.NoSuchModuleError) as exc:
        hint = "install the driver named in the URL, e.g. pip install 'psycopg[binary]'"
        if parsed.drivername == "postgresql":  # SQLAlchemy's default is psycopg2, not psycopg 3
            hint = "pipescan uses psycopg 3: write the URL as postgresql+psycopg://..."
        raise StorageError(
            f"no database driver for {_display_url(parsed)}: {exc}", hint=hint
        ) from exc


def _ensure_sqlite_parent_dir(url: URL) -> None:
    database = url.database or ""
    if database in ("", ":memory:") or database.startswith("file:") or url.query.get("uri"):
        return
    Path(database).expanduser().parent.mkdir(parents=True, exist_ok=True)


def _switch_to_wal(cursor: Any) -> None:
    """``PRAGMA journal_mode = WAL``, retried while another connection holds the lock.

    Switching a brand-new file to WAL needs an exclusive lock, and SQLite answers "database is
    locked" at once, without the busy handler, when a concurrent first connection is doing the
    same (measured: 5 of 40 trials with three threads opening a new file together). So wait
    here, up to the busy timeout, as every other statement does.
    """
    deadline = time.monotonic() + SQLITE_BUSY_TIMEOUT_S
    delay_s = 0.005
    while True:
        try:
            cursor.execute("PRAGMA journal_mode = WAL")
            return
        except sqlite3.OperationalError as exc:
            if "locked" not in str(exc) or time.monotonic() + delay_s > deadline:
                raise
            time.sleep(delay_s)
            delay_s = min(2.0 * delay_s, 0.2)


def _install_sqlite_listeners(engine: Engine) -> None:
    busy_timeout_ms = int(SQLITE_BUSY_TIMEOUT_S * 1000)

    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_connection: Any, _record: Any) -> None:
        # Take transaction control away from the sqlite3 module, which would otherwise begin
        # a transaction lazily before the first INSERT; the "begin" listener below emits
        # BEGIN itself (SQLAlchemy's documented recipe for pysqlite).
        dbapi_connection.isolation_level = None
        cursor = dbapi_connection.cursor()
        try:
            cursor.execute(f"PRAGMA busy_timeout = {busy_timeout_ms}")
            _switch_to_wal(cursor)
            # With WAL, NORMAL syncs the log at checkpoints instead of at every commit: the
            # database cannot be corrupted by a crash, but a power cut may undo the last
            # commits (SQLite's recommended pairing). A lost save is redone by re-running its
            # inspection, which replaces it; it is not worth a disk flush per inspection.
            cursor.execute("PRAGMA synchronous = NORMAL")
            cursor.execute("PRAGMA foreign_keys = ON")
        finally:
            cursor.close()

    @event.listens_for(engine, "begin")
    def _on_begin(connection: Connection) -> None:
        immediate = connection.get_execution_options().get(_BEGIN_IMMEDIATE, False)
        connection.exec_driver_sql("BEGIN IMMEDIATE" if immediate else "BEGIN")


@contextmanager
def session_scope(engine: Engine, *, write: bool = False) -> Iterator[Session]:
    """A session that commits when the block ends and rolls back if it raises.

    Parameters
    ----------
    engine
        From :func:`create_engine_for` or :func:`connect`.
    write
        The block writes. On SQLite its transaction then takes the write lock when it begins,
        so that concurrent writers queue (up to the busy timeout) rather than fail.

    Yields
    ------
    Session
        With ``expire_on_commit=False``, so values read in the block stay readable after it.
    """
    bind = engine.execution_options(**{_BEGIN_IMMEDIATE: True}) if write else engine
    session = Session(bind=bind, expire_on_commit=False)
    try:
        yield session
        session.commit()
    except BaseException:
        session.rollback()
        raise
    finally:
        session.close()


Reader = Engine | Session
"""What a read takes: an engine (the read opens its own session) or the session of a caller
that makes several reads, which then see one state of the database over one connection."""


@contextmanager
def reading(source: Reader) -> Iterator[Session]:
    """A session to read in: ``source`` itself, or a new one on the engine
    (:func:`session_scope`)."""
    if isinstance(source, Session):
        yield source
    else:
        with session_scope(source) as session:
            yield session


def _set_sqlite_foreign_keys(connection: Connection, *, on: bool) -> None:
    # The pragma only takes effect outside a transaction, so it goes straight to the driver
    # (through SQLAlchemy it would autobegin one first).
    driver_connection = connection.connection.driver_connection
    if driver_connection is None:  # pragma: no cover - only after the connection is closed
        raise StorageError("the SQLite connection is closed")
    driver_connection.execute(f"PRAGMA foreign_keys = {'ON' if on else 'OFF'}")


@contextmanager
def migration_connection(engine: Engine) -> Iterator[Connection]:
    """A connection inside one transaction to run schema migrations in.

    On SQLite, the transaction holds the write lock from the start (two processes migrating
    the same new file run one after the other, and the second finds nothing to do), and
    foreign keys are off while it runs: a batch migration copies a table, drops the original
    and renames the copy, and with foreign keys on that drop would cascade-delete the rows of
    every child table. The foreign keys are checked before committing instead.

    Yields
    ------
    Connection
        Already in a transaction; it is committed when the block ends without error.

    Raises
    ------
    StorageError
        If the database cannot be reached, or, on SQLite, the migrated data violates a
        foreign key.
    """
    try:
        opened = engine.connect()  # connects now: a refusal is reported as such
    except sa.exc.DBAPIError as exc:
        raise _cannot_open(engine, exc) from exc
    with opened as connection:
        sqlite = connection.dialect.name == "sqlite"
        if sqlite:
            _set_sqlite_foreign_keys(connection, on=False)
            connection.execution_options(**{_BEGIN_IMMEDIATE: True})
        try:
            with connection.begin():
                yield connection
                if sqlite:
                    violations = connection.exec_driver_sql("PRAGMA foreign_key_check").all()
                    if violations:
                        raise StorageError(
                            f"the migration left {len(violations)} rows that violate a foreign "
                            f"key, e.g. {tuple(violations[0])} (table, rowid, parent, fk id)",
                            hint="the migration was rolled back; report this as a bug",
                        )
        finally:
            if sqlite:
                _set_sqlite_foreign_keys(connection, on=True)


def alembic_config() -> Config:
    """An Alembic configuration pointing at the package's migrations, with no ini file."""
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    config.set_main_option("path_separator", "os")
    # ConfigParser interpolation: % must be doubled.
    config.set_main_option("file_template", _FILE_TEMPLATE.replace("%", "%%"))
    return config


def head_revision() -> str:
    """The newest schema revision this version of pipescan ships."""
    head = ScriptDirectory.from_config(alembic_config()).get_current_head()
    if head is None:  # pragma: no cover - the package always ships a revision
        raise StorageError(f"no migrations found in {MIGRATIONS_DIR}")
    return head


@contextmanager
def _engine_from(url_or_engine: str | URL | Engine) -> Iterator[Engine]:
    if isinstance(url_or_engine, Engine):
        yield url_or_engine
        return
    engine = create_engine_for(url_or_engine)
    try:
        yield engine
    finally:
        engine.dispose()


def _one_line(exc: BaseException | None) -> str:
    """A driver's message on one line (psycopg's span several)."""
    return " ".join(str(exc).split())


def _cannot_open(engine: Engine, exc: sa.exc.DBAPIError) -> StorageError:
    return StorageError(
        f"cannot open database {_display_url(engine.url)}: {_one_line(exc.orig)}",
        hint="check the URL, that the server is running and that you may connect",
    )


def _run_alembic(url_or_engine: str | URL | Engine, fn: Any, revision: str) -> None:
    with _engine_from(url_or_engine) as engine, migration_connection(engine) as connection:
        config = alembic_config()
        # env.py runs on this connection (and inside its transaction) instead of its own.
        config.attributes["connection"] = connection
        try:
            fn(config, revision)
        except CommandError as exc:
            raise StorageError(
                f"cannot migrate {_display_url(engine.url)} to {revision!r}: {exc}",
                hint="give 'head', 'base', a step such as '-1' or a pipescan revision id",
            ) from exc


def upgrade(url_or_engine: str | URL | Engine, revision: str = "head") -> None:
    """Migrate a database up to ``revision`` (default: the newest), in one transaction.

    Parameters
    ----------
    url_or_engine
        A database URL or an engine from :func:`create_engine_for`. An engine built here
        from a URL is disposed of afterwards.
    revision
        An Alembic revision id, ``"head"`` or a relative step such as ``"+1"``.

    Raises
    ------
    StorageError
        If the revision is unknown or the migrated data violates a foreign key. Nothing is
        changed in that case.
    """
    _run_alembic(url_or_engine, command.upgrade, revision)


def downgrade(url_or_engine: str | URL | Engine, revision: str = "-1") -> None:
    """Migrate a database down to ``revision`` (default: one step), in one transaction.

    ``"base"`` drops every pipescan table and its data.

    Raises
    ------
    StorageError
        If the revision is unknown; nothing is changed in that case.
    """
    _run_alembic(url_or_engine, command.downgrade, revision)


def current_revision(engine: Engine) -> str | None:
    """The database's schema revision, or None for a database that was never migrated.

    Raises
    ------
    StorageError
        If the database cannot be reached.
    """
    try:
        with engine.connect() as connection:
            return MigrationContext.configure(connection).get_current_revision()
    except sa.exc.DBAPIError as exc:
        raise _cannot_open(engine, exc) from exc


def connect(url: str | URL = DEFAULT_DATABASE_URL) -> Engine:
    """An engine on a database at the current schema revision.

    A new or outdated SQLite database is migrated to the newest revision here, on first use.
    A PostgreSQL (or other) database is only checked: migrating a shared server is left to
    the operator.

    Parameters
    ----------
    url
        A SQLAlchemy database URL.

    Returns
    -------
    Engine
        Ready for the functions of ``pipescan.storage.database.repository``.

    Raises
    ------
    StorageError
        If the database is unreachable, was migrated by a newer pipescan, or (not SQLite) is
        not at the newest revision.
    """
    engine = create_engine_for(url)
    try:
        _ensure_at_head(engine)
    except BaseException:
        engine.dispose()
        raise
    return engine


def _ensure_at_head(engine: Engine) -> None:
    where = _display_url(engine.url)
    current = current_revision(engine)
    head = head_revision()
    if current == head:
        return
    if current is not None:
        try:
            ScriptDirectory.from_config(alembic_config()).get_revision(current)
        except CommandError as exc:
            raise StorageError(
                f"database {where} is at schema revision {current}, which pipescan "
                f"{__version__} does not know",
                hint="it was migrated by a newer pipescan; upgrade pipescan",
            ) from exc
    if engine.dialect.name == "sqlite":
        upgrade(engine)
        return
    raise StorageError(
        f"database {where} is at schema revision {current or 'none (empty database)'}, "
        f"pipescan {__version__} needs {head}",
        hint="run `pipescan db upgrade` on this database (back it up first)",
    )


def check_database(url: str | URL) -> None:
    """Check that a database is reachable, at the current schema revision and writable, as
    one check before a run starts work (a new SQLite file is created and migrated here).

    Writability is probed with a no-op update of the schema revision, rolled back: it fails on
    a read-only file, a read-only transaction or replica, and a user without write rights.

    Raises
    ------
    StorageError
        Naming the database (without its password) and what to do.
    """
    engine = connect(url)
    try:
        with engine.connect() as connection, connection.begin() as transaction:
            connection.execute(sa.text("UPDATE alembic_version SET version_num = version_num"))
            transaction.rollback()
    except sa.exc.DBAPIError as exc:
        raise StorageError(
            f"database {_display_url(engine.url)} refuses writes: {_one_line(exc.orig)}",
            hint="check the file's or the user's write permissions, and that it is no replica",
        ) from exc
    finally:
        engine.dispose()
