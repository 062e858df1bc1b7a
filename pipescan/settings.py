"""Settings, read only by the CLI and the flows (``PIPESCAN_`` environment variables or ``.env``).

Everything below the flows takes explicit arguments.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict


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
    contour_method: Literal["polar", "grid"] = "polar"
    registration_method: Literal["point_to_plane", "point_to_point"] = "point_to_plane"
    step_m: float = Field(0.1, gt=0, description="section length along the chainage")
    window_m: float = Field(2.0, gt=0, description="chainage window processed per task")
    chunk_frames: int = Field(60, ge=2, description="frames registered per task")
    workers: int = Field(2, ge=1, description="parallel task workers")
    task_runner: Literal["threads", "processes"] = "threads"
    threshold_table: str = "vsa-2023"
    pipe_class: Literal["rigid", "flexible"] = "rigid"
    blockage_threshold_ratio: float = Field(0.10, ge=0, le=1)
    flag_grade: int = Field(2, ge=0, le=4)


def get_settings() -> Settings:
    return Settings()
