"""Settings, read only by the CLI and the flows (``PIPESCAN_`` environment variables or ``.env``).

Everything below the flows takes explicit arguments. The flows read the settings of the process
they run in (a deployment's runs: the worker's), so that no database URL or secret travels as a
flow parameter; :func:`use_settings` sets some for the code it wraps (the CLI's ``--db``).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from pipescan.core import defaults
from pipescan.core.flags import DEFAULT_TABLE, FlagRule
from pipescan.storage.input.limits import InputLimits
from pipescan.storage.input.network_layer import LayerLimits

_LIMITS = InputLimits()
_LAYER_LIMITS = LayerLimits()


class Settings(BaseSettings):
    """pipescan's settings. Each field can be set as ``PIPESCAN_<FIELD>``."""

    model_config = SettingsConfigDict(env_prefix="PIPESCAN_", env_file=".env", extra="ignore")

    database_url: str = Field(
        "sqlite:///pipescan.db",
        description="SQLAlchemy URL, or the path of a SQLite file; a SQLite file by default, "
        "postgresql+psycopg://... at scale",
    )
    database_password_block: str | None = Field(
        None,
        description="name of a Prefect Secret block holding the database password, which "
        "replaces any password in database_url (docs/operations.md)",
    )
    work_dir: Path = Field(
        Path(".pipescan-work"), description="scratch space for extracted archives and buckets"
    )
    reports_dir: Path = Field(Path("reports"), description="where reports are written by default")
    contour_method: str = Field(
        defaults.CONTOUR_METHOD,
        description="a name in pipescan.core.contour.CONTOUR_METHODS (polar, grid)",
    )
    grid_k: int = Field(
        defaults.GRID_K, ge=3, description="grid method: neighbours in the angle-gap test"
    )
    grid_s_threshold_rad: float = Field(
        defaults.GRID_S_THRESHOLD_RAD,
        gt=0,
        description="grid method: angle-gap standard deviation S of a boundary point",
    )
    registration_method: Literal["gicp", "point_to_plane", "point_to_point"] = Field(
        "gicp", description="gicp (default), point_to_plane, or the paper's point_to_point"
    )
    registration_engine: Literal["small_gicp", "open3d", "open3d_tensor"] = Field(
        "small_gicp", description="the library that runs the ICP (docs/registration.md)"
    )
    step_m: float = Field(
        defaults.SECTION_STEP_M, gt=0, description="section length along the chainage"
    )
    window_m: float = Field(
        defaults.WINDOW_M, gt=0, description="chainage window processed per task"
    )
    chunk_frames: int = Field(defaults.CHUNK_FRAMES, ge=2, description="frames registered per task")
    frame_stride: int | None = Field(
        None,
        ge=1,
        description="register every k-th frame and track the others (1: all); every frame is "
        "placed either way; none: the largest k the local map allows (docs/throughput.md)",
    )
    placed_share: float | None = Field(
        None,
        gt=0,
        le=1,
        description="share of each frame's points placed in the sections (1: every point); "
        "none: twice what an inner section keeps, from the scan (docs/throughput.md)",
    )
    workers: int = Field(2, ge=1, description="parallel task workers")
    task_runner: Literal["threads", "processes"] = "threads"
    engine_processes: bool = Field(
        True,
        description="on threads, register chunks in lean worker processes, one per worker "
        "(docs/throughput.md); false: in the flow's own process",
    )
    library_threads: int = Field(
        1,
        ge=1,
        description="threads the native libraries' own pools (BLAS, OpenMP) may use in each "
        "process of a run; pipescan runs its own work in parallel, and more only spin on the "
        "same cores (docs/throughput.md)",
    )
    threshold_table: str = DEFAULT_TABLE
    pipe_class: Literal["auto", "rigid", "flexible"] = Field(
        defaults.PIPE_CLASS,
        description="BAA deformation rule: from the archive's material, or set for a run",
    )
    blockage_threshold_ratio: float = Field(FlagRule.blockage_threshold_ratio, ge=0, le=1)
    flag_grade: int = Field(FlagRule.flag_grade, ge=0, le=4)
    dask_address: str | None = Field(
        None, description="Dask scheduler (tcp://host:8786) that runs the tasks; none: local pool"
    )
    network_concurrency: int | None = Field(
        None,
        ge=1,
        description="archives a network run processes at once; none: 2, on Dask its threads",
    )
    # --- report delivery (docs/reports.md) ---
    reports_location: str | None = Field(
        None,
        description="where delivered reports are written: a directory or an fsspec URL "
        "(s3://bucket/reports); default: reports_dir",
    )
    recipients_file: Path | None = Field(
        None, description="TOML file: asset id or glob pattern -> addresses, and network = [...]"
    )
    smtp_host: str | None = Field(None, description="SMTP server; unset disables e-mail")
    smtp_port: int = Field(25, ge=1, le=65535)
    smtp_sender: str = Field("pipescan@localhost", description="From: address of report e-mails")
    smtp_username: str | None = None
    smtp_password: SecretStr | None = None
    smtp_security: Literal["none", "starttls", "ssl"] = "none"
    smtp_allow_plaintext_login: bool = Field(
        False, description="send the SMTP password without TLS (smtp_security = none)"
    )
    smtp_alert_to: str | None = Field(
        None,
        description="comma-separated addresses e-mailed when a network run ends Failed "
        "(archives missing or failed, or no start); unset: no e-mail alert "
        "(docs/operations.md)",
    )
    # --- input limits (docs/security.md): what one archive and its point files may cost ---
    archive_max_bytes: int = Field(_LIMITS.archive_max_bytes, gt=0, description="64 GiB")
    member_max_bytes: int = Field(_LIMITS.member_max_bytes, gt=0, description="32 GiB")
    compression_max_ratio: float = Field(_LIMITS.compression_max_ratio, gt=1)
    archive_max_members: int = Field(_LIMITS.archive_max_members, gt=0)
    line_max_bytes: int = Field(_LIMITS.line_max_bytes, gt=0, description="64 KiB")
    points_max_count: int = Field(_LIMITS.points_max_count, gt=0)
    metadata_max_bytes: int = Field(_LIMITS.metadata_max_bytes, gt=0, description="32 MiB")
    # --- network layers (docs/security.md): what `network import` may read ---
    layer_max_bytes: int = Field(_LAYER_LIMITS.layer_max_bytes, gt=0, description="2 GiB")
    layer_max_features: int = Field(_LAYER_LIMITS.layer_max_features, gt=0)
    layer_max_vertices: int = Field(_LAYER_LIMITS.layer_max_vertices, gt=0)

    @field_validator("database_url")
    @classmethod
    def _path_is_sqlite(cls, value: str) -> str:
        return as_database_url(value)

    def input_limits(self) -> InputLimits:
        """The input limits these settings give, to pass down explicitly."""
        return InputLimits.from_settings(self)


def as_database_url(value: str) -> str:
    """A database URL as given, or a file's path (no ``scheme://``) as that SQLite file's URL.

    >>> as_database_url("surveys/pipescan.db"), as_database_url("/data/p.db")
    ('sqlite:///surveys/pipescan.db', 'sqlite:////data/p.db')
    >>> as_database_url("postgresql+psycopg://pipescan@db/pipescan")
    'postgresql+psycopg://pipescan@db/pipescan'
    """
    if not value.strip() or "://" in value or value.startswith("sqlite:"):
        return value
    return "sqlite:///" + str(Path(value).expanduser())


_OVERRIDES: ContextVar[dict[str, Any] | None] = ContextVar("pipescan_settings", default=None)


def get_settings() -> Settings:
    """The settings: ``PIPESCAN_*`` variables and ``.env``, under any :func:`use_settings`."""
    return Settings(**(_OVERRIDES.get() or {}))


@contextmanager
def use_settings(**values: Any) -> Iterator[None]:
    """Within the block (and the flows, sub-flows and thread-pool tasks it starts), these
    settings replace the environment's; ``None`` values are left out.

    >>> with use_settings(database_url="sqlite:////tmp/x.db"):
    ...     get_settings().database_url
    'sqlite:////tmp/x.db'
    """
    given = {k: v for k, v in values.items() if v is not None}
    token = _OVERRIDES.set((_OVERRIDES.get() or {}) | given)
    try:
        yield
    finally:
        _OVERRIDES.reset(token)


def database_url(settings: Settings | None = None) -> str:
    """The database URL of these settings, with the password of the Prefect ``Secret`` block
    named by ``database_password_block`` (loaded from the Prefect API) if one is named.

    Raises
    ------
    PipescanError
        The block cannot be loaded (no such block, no Prefect API).
    """
    settings = settings or get_settings()
    if not settings.database_password_block:
        return settings.database_url
    from sqlalchemy.engine import make_url

    from pipescan.core.errors import PipescanError

    name = settings.database_password_block
    try:
        from prefect.blocks.system import Secret

        password = str(Secret.load(name).get())  # type: ignore[union-attr]
    except Exception as exc:  # a missing block is a ValueError; no API, an httpx error
        raise PipescanError(
            f"cannot load the database password from the Prefect Secret block {name!r}: {exc}",
            field="PIPESCAN_DATABASE_PASSWORD_BLOCK",
            hint=f"create it with: prefect block create secret (name {name!r}), or unset it",
        ) from exc
    url = make_url(settings.database_url).set(password=password)
    return url.render_as_string(hide_password=False)
