"""Alembic environment of pipescan's database.

Run in two ways:

- by pipescan (``pipescan.storage.database.db.upgrade``), which passes a connection already
  inside the migration transaction in ``config.attributes["connection"]``;
- by a developer with ``alembic -c pipescan/storage/database/migrations/alembic.ini ...``,
  where the URL comes from ``-x url=...`` or the ini's ``sqlalchemy.url``.

``render_as_batch`` is always on: SQLite can only alter most things by copying the table
(Alembic's batch mode), and on PostgreSQL the same batch operations become plain ALTERs, so
one revision file serves both.
"""

from __future__ import annotations

from logging.config import fileConfig

from alembic import context
from sqlalchemy.engine import Connection

from pipescan.storage.database.db import (
    DEFAULT_DATABASE_URL,
    create_engine_for,
    migration_connection,
)
from pipescan.storage.database.models import Base

config = context.config
target_metadata = Base.metadata

if config.config_file_name is not None and config.file_config.has_section("loggers"):
    fileConfig(config.config_file_name, disable_existing_loggers=False)


def _database_url() -> str:
    url = context.get_x_argument(as_dictionary=True).get("url")
    return url or config.get_main_option("sqlalchemy.url") or DEFAULT_DATABASE_URL


def _run(connection: Connection) -> None:
    context.configure(
        connection=connection,
        target_metadata=target_metadata,
        render_as_batch=True,
        compare_type=True,
        # Also on SQLite: pipescan's engines issue BEGIN themselves (see storage/db.py), so
        # DDL there is transactional too, and a failed migration leaves nothing behind.
        transactional_ddl=True,
    )
    with context.begin_transaction():
        context.run_migrations()


def run_migrations_offline() -> None:
    """Print the SQL instead of running it (``alembic upgrade head --sql``)."""
    context.configure(
        url=_database_url(),
        target_metadata=target_metadata,
        literal_binds=True,
        dialect_opts={"paramstyle": "named"},
        render_as_batch=True,
    )
    with context.begin_transaction():
        context.run_migrations()


def run_migrations_online() -> None:
    """Run the migrations on a live database."""
    connection = config.attributes.get("connection")
    if connection is not None:
        _run(connection)
        return
    engine = create_engine_for(_database_url())
    try:
        with migration_connection(engine) as own_connection:
            _run(own_connection)
    finally:
        engine.dispose()


if context.is_offline_mode():
    run_migrations_offline()
else:
    run_migrations_online()
