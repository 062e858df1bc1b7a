"""Settings, read only by the CLI and the flows (``PIPESCAN_`` environment variables or ``.env``).

Everything below the flows takes explicit arguments.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr
from pydantic_settings import BaseSettings, SettingsConfigDict

from pipescan.storage.input.limits import InputLimits

_LIMITS = InputLimits()


class Settings(BaseSettings):
    """pipescan's settings. Each field can be set as ``PIPESCAN_<FIELD>``."""

    model_config = SettingsConfigDict(env_prefix="PIPESCAN_", env_file=".env", extra="ignore")

    database_url: str = Field(
        "sqlite:///pipescan.db",
        description="SQLAlchemy URL; a SQLite file by default, postgresql+psycopg://... at scale",
    )
    work_dir: Path = Field(
        Path(".pipescan-work"), description="scratch space for extracted archives and buckets"
    )
    reports_dir: Path = Field(Path("reports"), description="where reports are written by default")
    contour_method: str = Field(
        "polar", description="a name in pipescan.core.contour.CONTOUR_METHODS (polar, grid)"
    )
    grid_k: int = Field(12, ge=3, description="grid method: neighbours in the angle-gap test")
    grid_s_threshold_rad: float = Field(
        0.55, gt=0, description="grid method: angle-gap standard deviation S of a boundary point"
    )
    registration_method: Literal["gicp", "point_to_plane", "point_to_point"] = Field(
        "gicp", description="gicp (default), point_to_plane, or the paper's point_to_point"
    )
    registration_engine: Literal["small_gicp", "open3d", "open3d_tensor"] = Field(
        "small_gicp", description="the library that runs the ICP (docs/registration.md)"
    )
    step_m: float = Field(0.1, gt=0, description="section length along the chainage")
    window_m: float = Field(2.0, gt=0, description="chainage window processed per task")
    chunk_frames: int = Field(60, ge=2, description="frames registered per task")
    workers: int = Field(2, ge=1, description="parallel task workers")
    task_runner: Literal["threads", "processes"] = "threads"
    threshold_table: str = "vsa-2023"
    pipe_class: Literal["auto", "rigid", "flexible"] = Field(
        "auto", description="BAA deformation rule: from the archive's material, or set for a run"
    )
    blockage_threshold_ratio: float = Field(0.10, ge=0, le=1)
    flag_grade: int = Field(2, ge=0, le=4)
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
    # --- input limits (docs/security.md): what one archive and its point files may cost ---
    archive_max_bytes: int = Field(_LIMITS.archive_max_bytes, gt=0, description="64 GiB")
    member_max_bytes: int = Field(_LIMITS.member_max_bytes, gt=0, description="32 GiB")
    compression_max_ratio: float = Field(_LIMITS.compression_max_ratio, gt=1)
    archive_max_members: int = Field(_LIMITS.archive_max_members, gt=0)
    line_max_bytes: int = Field(_LIMITS.line_max_bytes, gt=0, description="64 KiB")
    points_max_count: int = Field(_LIMITS.points_max_count, gt=0)
    metadata_max_bytes: int = Field(_LIMITS.metadata_max_bytes, gt=0, description="32 MiB")

    def input_limits(self) -> InputLimits:
        """The input limits these settings give, to pass down explicitly."""
        return InputLimits.from_settings(self)


def get_settings() -> Settings:
    return Settings()
