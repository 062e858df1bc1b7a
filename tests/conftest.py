"""Shared fixtures: every storage and trend test runs on SQLite and on a real PostgreSQL.

``db_url`` is parametrised over ``["sqlite", "postgresql"]``: a new SQLite file under the
test's tmp_path, or a new, empty schema on a PostgreSQL server (alone on the connections'
``search_path``, so a database of its own in all but name; dropped after the test). The
server is either the database named by ``PIPESCAN_TEST_POSTGRES_URL`` (its user needs CREATE
on it), or one the tests start themselves on loopback for the session
(``tests/pg_cluster.py``: Debian's ``initdb`` and ``pg_ctl``), stopped and deleted at the end.

Without PostgreSQL binaries, the PostgreSQL variants are skipped, or fail when ``CI`` is set:
CI must test both databases.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest
import sqlalchemy as sa

POSTGRES_URL_ENV = "PIPESCAN_TEST_POSTGRES_URL"
"""A PostgreSQL server to test on instead of starting one, e.g.
``postgresql+psycopg://postgres@127.0.0.1:5432/postgres``."""


def _in_ci() -> bool:
    return os.environ.get("CI", "").strip().lower() not in ("", "0", "false", "no")


@pytest.fixture(scope="session")
def postgres_server() -> Iterator[str]:
    """SQLAlchemy URL of a PostgreSQL server on which the tests may create databases."""
    url = os.environ.get(POSTGRES_URL_ENV)
    if url:
        yield url
        return
    from tests.pg_cluster import PostgresCluster, PostgresUnavailable

    try:
        cluster = PostgresCluster().start()
    except PostgresUnavailable as exc:
        message = f"no PostgreSQL server for the storage tests: {exc}"
        if _in_ci():
            pytest.fail(f"{message} (CI is set: CI must test PostgreSQL)", pytrace=False)
        pytest.skip(message)
    try:
        yield cluster.admin_url
    finally:
        cluster.stop()


@pytest.fixture
def sqlite_url(tmp_path: Path) -> str:
    """URL of a SQLite file under tmp_path that does not exist yet."""
    return f"sqlite:///{tmp_path / 'pipescan.db'}"


@pytest.fixture
def postgres_url(postgres_server: str) -> Iterator[str]:
    """URL of a new, empty PostgreSQL schema (in effect a database), dropped after the test."""
    from tests.pg_cluster import create_schema, drop_schema

    url = create_schema(postgres_server)
    try:
        yield url
    finally:
        drop_schema(postgres_server, url)


@pytest.fixture(params=["sqlite", "postgresql"])
def db_url(request: pytest.FixtureRequest) -> str:
    """An empty database, on SQLite and on PostgreSQL."""
    name = "sqlite_url" if request.param == "sqlite" else "postgres_url"
    return str(request.getfixturevalue(name))


def is_sqlite(url: str) -> bool:
    return url.startswith("sqlite")


@pytest.fixture
def engine(db_url: str) -> Iterator[sa.Engine]:
    """An engine on ``db_url`` at the newest schema revision.

    SQLite is migrated by ``connect`` on first use; PostgreSQL explicitly first, as an
    operator would with ``pipescan db upgrade``.
    """
    from pipescan.storage.database import db

    if not is_sqlite(db_url):
        db.upgrade(db_url)
    engine = db.connect(db_url)
    yield engine
    engine.dispose()


def pytest_unconfigure(config: pytest.Config) -> None:
    """Prefect stops its temporary API server at interpreter exit, after the tests, and logs
    that to a console whose stream pytest has already closed: logging then printed a
    "--- Logging error ---" traceback under the test summary. Nothing is wrong by then."""
    import logging

    logging.raiseExceptions = False
