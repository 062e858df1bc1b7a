"""A throwaway PostgreSQL server on loopback, for the tests and the database benchmark.

:class:`PostgresCluster` runs ``initdb`` and ``pg_ctl`` from Debian's ``postgresql`` package
(or any ``PIPESCAN_PG_BIN`` directory) on a data directory and unix socket under a temporary
directory, listening on a free TCP port of 127.0.0.1 with ``trust`` authentication, and
deletes it all on :meth:`stop`. PostgreSQL refuses to run as root: as root, the server runs
as the ``postgres`` system user (``runuser``), which owns the temporary directory.
"""

from __future__ import annotations

import glob
import os
import pwd
import shutil
import socket
import subprocess
import tempfile
import uuid
from pathlib import Path

import psycopg
from psycopg import sql
from sqlalchemy.engine import make_url

ENV_BIN = "PIPESCAN_PG_BIN"
"""Environment variable naming a directory with initdb and pg_ctl (overrides the search)."""


class PostgresUnavailable(RuntimeError):
    """The PostgreSQL server binaries are not installed, or the server did not start."""


def find_bin_dir() -> Path:
    """The directory holding ``initdb`` and ``pg_ctl``.

    Raises
    ------
    PostgresUnavailable
        If none is found.
    """
    if os.environ.get(ENV_BIN):
        candidates = [os.environ[ENV_BIN]]  # asked for: no other
    else:
        candidates = sorted(glob.glob("/usr/lib/postgresql/*/bin"), reverse=True)
        on_path = shutil.which("pg_ctl")
        if on_path:
            candidates.append(str(Path(on_path).parent))
    for candidate in candidates:
        path = Path(candidate)
        if (path / "initdb").is_file() and (path / "pg_ctl").is_file():
            return path
    raise PostgresUnavailable(
        "PostgreSQL server binaries (initdb, pg_ctl) not found in "
        f"{', '.join(candidates) or '/usr/lib/postgresql/*/bin or PATH'}: install the Debian "
        "package `postgresql` (scripts/bootstrap.sh does), set "
        f"{ENV_BIN}=/path/to/bin, or point PIPESCAN_TEST_POSTGRES_URL at a server"
    )


def free_port() -> int:
    """A TCP port of 127.0.0.1 that nothing listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


class PostgresCluster:
    """A PostgreSQL cluster in a temporary directory, started by :meth:`start`.

    Parameters
    ----------
    durable
        Keep PostgreSQL's default durability (fsync, synchronous commit). Off for tests,
        where a crash loses nothing of value and fsyncs only cost time; on for benchmarks.
    """

    def __init__(self, *, durable: bool = False) -> None:
        self.durable = durable
        self.bin_dir = find_bin_dir()
        self.port = 0
        self.root: Path | None = None
        self._run_as: str | None = "postgres" if os.geteuid() == 0 else None

    @property
    def admin_url(self) -> str:
        """SQLAlchemy URL of the ``postgres`` database, as the ``postgres`` superuser."""
        return f"postgresql+psycopg://postgres@127.0.0.1:{self.port}/postgres"

    def _command(self, *args: str) -> list[str]:
        if self._run_as is None:
            return list(args)
        return ["runuser", "-u", self._run_as, "--", *args]

    def start(self) -> PostgresCluster:
        """Create the cluster and start the server; returns self.

        Raises
        ------
        PostgresUnavailable
            If ``initdb`` or ``pg_ctl start`` fails (with their output).
        """
        self.root = Path(tempfile.mkdtemp(prefix="pipescan-pg-"))
        if self._run_as is not None:
            try:
                user = pwd.getpwnam(self._run_as)
            except KeyError as exc:
                raise PostgresUnavailable(
                    "running as root and there is no `postgres` user to run the server as"
                ) from exc
            os.chown(self.root, user.pw_uid, user.pw_gid)
        data = self.root / "data"
        self.port = free_port()
        self._run(
            str(self.bin_dir / "initdb"),
            "-D",
            str(data),
            "-U",
            "postgres",
            "-A",
            "trust",
            "-E",
            "UTF8",
            "--no-sync",
            "--locale=C",
        )
        options = [
            "-c listen_addresses=127.0.0.1",
            f"-p {self.port}",
            f"-k {self.root}",
            "-c max_connections=50",
        ]
        if not self.durable:
            options += ["-c fsync=off", "-c synchronous_commit=off", "-c full_page_writes=off"]
        self._run(
            str(self.bin_dir / "pg_ctl"),
            "-D",
            str(data),
            "-l",
            str(self.root / "server.log"),
            "-w",
            "-t",
            "60",
            "-o",
            " ".join(options),
            "start",
        )
        return self

    def _run(self, *args: str) -> None:
        result = subprocess.run(
            self._command(*args), capture_output=True, text=True, check=False, timeout=120
        )
        if result.returncode != 0:
            log = ""
            if self.root is not None and (self.root / "server.log").exists():
                log = (self.root / "server.log").read_text(errors="replace")[-2000:]
            raise PostgresUnavailable(
                f"{Path(args[0]).name} failed ({result.returncode}): "
                f"{result.stdout[-2000:]}{result.stderr[-2000:]}{log}"
            )

    def stop(self) -> None:
        """Stop the server (fast shutdown) and delete its directory."""
        if self.root is None:
            return
        try:
            if (self.root / "data" / "postmaster.pid").exists():
                subprocess.run(
                    self._command(
                        str(self.bin_dir / "pg_ctl"),
                        "-D",
                        str(self.root / "data"),
                        "-m",
                        "fast",
                        "-w",
                        "stop",
                    ),
                    capture_output=True,
                    check=False,
                    timeout=120,
                )
        finally:
            shutil.rmtree(self.root, ignore_errors=True)
            self.root = None


def create_schema(server_url: str, prefix: str = "pipescan_test") -> str:
    """Create an empty schema in the database of ``server_url``; returns a URL that uses it.

    The URL's connections have the schema alone on their ``search_path`` (so every table
    pipescan creates or reads is in it) and the schema's name as ``application_name`` (so
    :func:`drop_schema` can close any connection a test left open). A schema costs a
    millisecond where a database costs a checkpoint; the user of ``server_url`` needs only
    CREATE on its database.
    """
    name = f"{prefix}_{uuid.uuid4().hex[:12]}"
    with _admin_connection(server_url) as connection:
        connection.execute(sql.SQL("CREATE SCHEMA {}").format(sql.Identifier(name)))
    url = make_url(server_url).update_query_dict(
        {"options": f"-csearch_path={name}", "application_name": name}
    )
    return url.render_as_string(hide_password=False)


def drop_schema(server_url: str, schema_url: str) -> None:
    """Drop a schema made by :func:`create_schema` with everything in it."""
    name = make_url(schema_url).query["application_name"]
    assert isinstance(name, str)
    with _admin_connection(server_url) as connection:
        connection.execute(
            "SELECT pg_terminate_backend(pid) FROM pg_stat_activity "
            "WHERE application_name = %s AND pid <> pg_backend_pid()",
            (name,),
        )
        connection.execute(sql.SQL("DROP SCHEMA IF EXISTS {} CASCADE").format(sql.Identifier(name)))


def create_database(server_url: str, prefix: str = "pipescan_bench") -> str:
    """Create an empty database on the server of ``server_url``; returns its SQLAlchemy URL.

    The user of ``server_url`` needs the CREATEDB privilege.
    """
    url = make_url(server_url)
    name = f"{prefix}_{uuid.uuid4().hex[:12]}"
    with _admin_connection(server_url) as connection:
        connection.execute(
            sql.SQL("CREATE DATABASE {} TEMPLATE template0").format(sql.Identifier(name))
        )
    return url.set(database=name).render_as_string(hide_password=False)


def drop_database(server_url: str, database_url: str) -> None:
    """Drop a database made by :func:`create_database`, closing its remaining sessions."""
    name = make_url(database_url).database
    with _admin_connection(server_url) as connection:
        connection.execute(
            sql.SQL("DROP DATABASE IF EXISTS {} WITH (FORCE)").format(sql.Identifier(name))
        )


def _admin_connection(sqlalchemy_url: str) -> psycopg.Connection:
    url = make_url(sqlalchemy_url)
    url = url.difference_update_query(["options", "application_name"])
    conninfo = url.set(drivername="postgresql").render_as_string(hide_password=False)
    return psycopg.connect(conninfo, autocommit=True)
