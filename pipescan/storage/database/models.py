"""SQLAlchemy models of pipescan's database.

One row per pipe asset, per inspection of an asset, per 0.1 m section of an inspection, per
defect and per registered frame. Column names are the names used end to end (dataclass field,
column, CSV header), with the unit in the name.

Two representation choices matter to anyone querying the tables directly:

- Section chainages are **integer millimetres** (``chainage_start_mm``), so that the primary
  key ``(inspection_id, chainage_start_mm)`` compares exactly; the repository converts to and
  from metres. Defect chainages are plain floats in metres: they are never keys.
- Datetimes are stored in UTC. On PostgreSQL the columns are ``timestamp with time zone``; on
  SQLite, which has no such type, they are naive UTC and made aware again on reading
  (:class:`UTCDateTime`).

The migrations (``pipescan/storage/database/migrations/versions``) must build exactly these
models; a test compares the migrated schema with them through Alembic's autogenerate.
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any

import sqlalchemy as sa
from sqlalchemy.engine import Dialect
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship

from pipescan.core.errors import PipescanError

# Constraint and index names are fixed by convention so that migrations can name what they
# alter (SQLite's batch mode and PostgreSQL both need the name to drop a constraint).
NAMING_CONVENTION: dict[str, str] = {
    "ix": "ix_%(table_name)s__%(column_0_N_name)s",
    "uq": "uq_%(table_name)s__%(column_0_N_name)s",
    "ck": "ck_%(table_name)s__%(constraint_name)s",
    "fk": "fk_%(table_name)s__%(column_0_N_name)s__%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}


def utc_now() -> datetime:
    """The current time, timezone-aware, in UTC."""
    return datetime.now(UTC)


class UTCDateTime(sa.types.TypeDecorator[datetime]):
    """A timezone-aware datetime, stored in UTC.

    Binding a naive datetime raises, because its time zone would be a guess. Values read back
    are always aware and in UTC, on SQLite as on PostgreSQL.
    """

    impl = sa.DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None or value.utcoffset() is None:
            # Not StorageError (db.py imports this module); the repository checks first, so
            # only direct ORM use can get here.
            raise PipescanError(
                f"naive datetime {value.isoformat()} cannot be stored",
                hint="give it a time zone, e.g. value.replace(tzinfo=datetime.UTC)",
            )
        value = value.astimezone(UTC)
        if dialect.name == "sqlite":
            # SQLite's DATETIME has no offset: store naive UTC, re-attach UTC on reading.
            return value.replace(tzinfo=None)
        return value

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            return value.replace(tzinfo=UTC)
        return value.astimezone(UTC)


class Base(DeclarativeBase):
    """Declarative base of every pipescan table."""

    metadata = sa.MetaData(naming_convention=NAMING_CONVENTION)


class Asset(Base):
    """A pipe run between two nodes (manholes), identified by the utility's asset id.

    Its attributes are those of the most recently *saved* inspection; a value the newest
    metadata leaves out (None) does not erase one already known.
    """

    __tablename__ = "assets"

    asset_id: Mapped[str] = mapped_column(sa.String(), primary_key=True)
    upstream_node: Mapped[str | None] = mapped_column(sa.String())
    downstream_node: Mapped[str | None] = mapped_column(sa.String())
    # NULL for a non-circular pipe whose metadata gives no diameter.
    nominal_diameter_m: Mapped[float | None] = mapped_column(sa.Float())
    pipe_shape: Mapped[str] = mapped_column(sa.String())
    material: Mapped[str | None] = mapped_column(sa.String())
    # The nodes' positions, [x, y] or [x, y, z] in ``crs``, from the metadata (all or none).
    upstream_node_xyz: Mapped[list[float] | None] = mapped_column(sa.JSON(none_as_null=True))
    downstream_node_xyz: Mapped[list[float] | None] = mapped_column(sa.JSON(none_as_null=True))
    crs: Mapped[str | None] = mapped_column(sa.String())

    inspections: Mapped[list[Inspection]] = relationship(
        back_populates="asset", passive_deletes=True
    )


class Inspection(Base):
    """One processed scan archive of one asset, under one set of processing parameters.

    ``(asset_id, content_hash, params_hash)`` is unique: processing the same archive with the
    same parameters again replaces the earlier rows (see ``repository.save_inspection``).
    """

    __tablename__ = "inspections"
    __table_args__ = (
        sa.UniqueConstraint("asset_id", "content_hash", "params_hash"),
        # "How has this asset changed": the asset's inspections in time order, then each
        # inspection's section at a chainage through the sections' primary key.
        sa.Index(None, "asset_id", "inspected_at"),
        # Ids are never reused (SQLite would otherwise hand a replaced inspection's id to the
        # next insert), so an id quoted in an old report can never name a different inspection.
        {"sqlite_autoincrement": True},
    )

    id: Mapped[int] = mapped_column(sa.Integer(), primary_key=True, autoincrement=True)
    asset_id: Mapped[str] = mapped_column(
        sa.ForeignKey("assets.asset_id", ondelete="CASCADE", onupdate="CASCADE")
    )
    inspected_at: Mapped[datetime] = mapped_column(UTCDateTime())
    archive_uri: Mapped[str] = mapped_column(sa.String())
    content_hash: Mapped[str] = mapped_column(sa.String())
    params_hash: Mapped[str] = mapped_column(sa.String())
    params_json: Mapped[dict[str, Any]] = mapped_column(sa.JSON())
    software_version: Mapped[str] = mapped_column(sa.String())
    status: Mapped[str] = mapped_column(sa.String())
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utc_now)
    point_count: Mapped[int] = mapped_column(sa.Integer())
    frame_count: Mapped[int] = mapped_column(sa.Integer())
    scanned_length_m: Mapped[float] = mapped_column(sa.Float())
    registration_json: Mapped[dict[str, Any] | None] = mapped_column(sa.JSON())
    threshold_table: Mapped[str] = mapped_column(sa.String())
    # The survey's direction ("downstream" or "upstream") and the chainage of its start, from
    # the metadata; NULL for inspections stored before they were kept.
    direction: Mapped[str | None] = mapped_column(sa.String())
    chainage_offset_m: Mapped[float | None] = mapped_column(sa.Float())
    # Blockage summary of the inspection's *measured* sections (status ok, blockage known),
    # written with the sections, so that network-wide rankings (``trends.worst_assets``) read
    # one row per inspection instead of every section. NULL when no section was measured.
    measured_section_count: Mapped[int] = mapped_column(sa.Integer(), server_default="0")
    mean_blockage_ratio: Mapped[float | None] = mapped_column(sa.Float())
    peak_blockage_ratio: Mapped[float | None] = mapped_column(sa.Float())
    # Start of the section with the peak (the first one on a tie), in whole millimetres.
    peak_chainage_start_mm: Mapped[int | None] = mapped_column(sa.Integer())
    # Where the scan's start came from (pipescan.core.start.START_SOURCES); NULL for
    # inspections stored before it was recorded.
    start_source: Mapped[str | None] = mapped_column(sa.String())

    asset: Mapped[Asset] = relationship(back_populates="inspections")
    sections: Mapped[list[Section]] = relationship(
        back_populates="inspection", passive_deletes=True, cascade="all, delete-orphan"
    )
    defects: Mapped[list[DefectRow]] = relationship(
        back_populates="inspection", passive_deletes=True, cascade="all, delete-orphan"
    )
    frame_quality: Mapped[list[FrameQualityRow]] = relationship(
        back_populates="inspection", passive_deletes=True, cascade="all, delete-orphan"
    )


class Section(Base):
    """The measures of one section ``[chainage_start_mm, chainage_end_mm)`` of an inspection.

    The measured figures are NULL when they could not be computed (never 0). ``contour_json``
    is the inner contour as ``[[x_mm, y_mm], ...]`` integers, for report figures.
    """

    __tablename__ = "sections"
    __table_args__ = (
        sa.CheckConstraint("chainage_end_mm > chainage_start_mm", name="chainage_order"),
        sa.CheckConstraint("point_count >= 0", name="point_count_non_negative"),
        sa.CheckConstraint("coverage_ratio >= 0 AND coverage_ratio <= 1", name="coverage_range"),
    )

    inspection_id: Mapped[int] = mapped_column(
        sa.ForeignKey("inspections.id", ondelete="CASCADE"), primary_key=True
    )
    chainage_start_mm: Mapped[int] = mapped_column(sa.Integer(), primary_key=True)
    chainage_end_mm: Mapped[int] = mapped_column(sa.Integer())
    open_area_m2: Mapped[float | None] = mapped_column(sa.Float())
    # NULL when the nominal shape is unknown (non-circular pipe without dimensions).
    nominal_area_m2: Mapped[float | None] = mapped_column(sa.Float())
    blockage_ratio: Mapped[float | None] = mapped_column(sa.Float())
    ovality_ratio: Mapped[float | None] = mapped_column(sa.Float())
    deformation_ratio: Mapped[float | None] = mapped_column(sa.Float())
    deposit_height_ratio: Mapped[float | None] = mapped_column(sa.Float())
    coverage_ratio: Mapped[float] = mapped_column(sa.Float())
    point_count: Mapped[int] = mapped_column(sa.Integer())
    status: Mapped[str] = mapped_column(sa.String())
    grade: Mapped[int | None] = mapped_column(sa.Integer())
    contour_json: Mapped[str | None] = mapped_column(sa.Text())
    # The 95 % uncertainty (±) of each figure, and the water in the invert (docs/measures.md).
    blockage_uncertainty_ratio: Mapped[float | None] = mapped_column(sa.Float())
    ovality_uncertainty_ratio: Mapped[float | None] = mapped_column(sa.Float())
    deformation_uncertainty_ratio: Mapped[float | None] = mapped_column(sa.Float())
    deposit_height_uncertainty_ratio: Mapped[float | None] = mapped_column(sa.Float())
    water_depth_ratio: Mapped[float | None] = mapped_column(sa.Float())
    water_depth_uncertainty_ratio: Mapped[float | None] = mapped_column(sa.Float())
    # How far the section's true place may be from its chainage (registration's); NULL when
    # not known.
    chainage_uncertainty_m: Mapped[float | None] = mapped_column(sa.Float())

    inspection: Mapped[Inspection] = relationship(back_populates="sections")


class DefectRow(Base):
    """One coded feature along the pipe (``pipescan.core.model.Defect``); the clock positions
    and characterisation are NULL for defects stored before coding."""

    __tablename__ = "defects"

    id: Mapped[int] = mapped_column(sa.Integer(), primary_key=True, autoincrement=True)
    inspection_id: Mapped[int] = mapped_column(
        sa.ForeignKey("inspections.id", ondelete="CASCADE"), index=True
    )
    code: Mapped[str] = mapped_column(sa.String())
    measure: Mapped[str] = mapped_column(sa.String())
    chainage_start_m: Mapped[float] = mapped_column(sa.Float())
    chainage_end_m: Mapped[float] = mapped_column(sa.Float())
    peak_chainage_m: Mapped[float] = mapped_column(sa.Float())
    peak_value: Mapped[float] = mapped_column(sa.Float())
    peak_blockage_ratio: Mapped[float | None] = mapped_column(sa.Float())
    grade: Mapped[int | None] = mapped_column(sa.Integer())
    clock_from_h: Mapped[float | None] = mapped_column(sa.Float())
    clock_to_h: Mapped[float | None] = mapped_column(sa.Float())
    characterisation: Mapped[str | None] = mapped_column(sa.String())
    lower_bound: Mapped[bool | None] = mapped_column(sa.Boolean())
    """True where part of the feature stood in water that returned nothing: its figure and
    class are at least what they say. NULL for defects stored before it was recorded."""

    inspection: Mapped[Inspection] = relationship(back_populates="defects")


class NetworkPipe(Base):
    """One pipe of a network layer imported from a GIS (``pipescan network import``).

    ``gis_id`` is the layer's id of the pipe. It stands for the pipescan asset whose id is
    ``asset_ref`` or, failing that, whose upstream and downstream nodes are ``from_node`` and
    ``to_node`` (either way round): matched when read, so that a layer imported once serves
    the inspections stored after it too. ``line_json`` is the line's vertices
    ``[[x, y(, z)], ...]`` in ``crs``, in the layer's (digitised) order; ``length_m`` is its
    length along them, in the CRS's units (metres).
    """

    __tablename__ = "network_pipes"
    __table_args__ = (
        sa.CheckConstraint("length_m > 0", name="length_positive"),
        sa.Index(None, "from_node", "to_node"),
    )

    gis_id: Mapped[str] = mapped_column(sa.String(), primary_key=True)
    asset_ref: Mapped[str] = mapped_column(sa.String(), unique=True)
    from_node: Mapped[str | None] = mapped_column(sa.String())
    to_node: Mapped[str | None] = mapped_column(sa.String())
    crs: Mapped[str] = mapped_column(sa.String())
    line_json: Mapped[str] = mapped_column(sa.Text())
    length_m: Mapped[float] = mapped_column(sa.Float())
    source: Mapped[str] = mapped_column(sa.String())
    imported_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utc_now)


class FrameQualityRow(Base):
    """Registration quality of one frame (``pipescan.core.model.FrameQuality``)."""

    __tablename__ = "frame_quality"

    inspection_id: Mapped[int] = mapped_column(
        sa.ForeignKey("inspections.id", ondelete="CASCADE"), primary_key=True
    )
    frame_index: Mapped[int] = mapped_column(sa.Integer(), primary_key=True)
    fitness: Mapped[float] = mapped_column(sa.Float())
    rmse_m: Mapped[float] = mapped_column(sa.Float())
    degenerate: Mapped[bool] = mapped_column(sa.Boolean())

    inspection: Mapped[Inspection] = relationship(back_populates="frame_quality")
