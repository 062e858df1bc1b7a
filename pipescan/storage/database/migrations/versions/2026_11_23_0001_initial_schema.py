"""Initial schema: assets, inspections, sections, defects, frame quality.

Written to match ``pipescan/storage/database/models.py`` exactly; ``tests/test_db.py`` checks
it with Alembic's autogenerate comparison. Types are spelled with plain SQLAlchemy types (not the
models' ``UTCDateTime`` decorator) so that this file never changes when the models do.

Revision ID: c5e1a9f40b21
Revises:
Create Date: 2026-11-23 00:01:00+00:00
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

# revision identifiers, used by Alembic.
revision: str = "c5e1a9f40b21"
down_revision: str | None = None
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "assets",
        sa.Column("asset_id", sa.String(), nullable=False),
        sa.Column("upstream_node", sa.String(), nullable=True),
        sa.Column("downstream_node", sa.String(), nullable=True),
        sa.Column("nominal_diameter_m", sa.Float(), nullable=True),
        sa.Column("pipe_shape", sa.String(), nullable=False),
        sa.Column("material", sa.String(), nullable=True),
        sa.PrimaryKeyConstraint("asset_id", name=op.f("pk_assets")),
    )
    op.create_table(
        "inspections",
        sa.Column("id", sa.Integer(), autoincrement=True, nullable=False),
        sa.Column("asset_id", sa.String(), nullable=False),
        # Stored in UTC: timestamptz on PostgreSQL, naive UTC on SQLite.
        sa.Column("inspected_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("archive_uri", sa.String(), nullable=False),
        sa.Column("content_hash", sa.String(), nullable=False),
        sa.Column("params_hash", sa.String(), nullable=False),
        sa.Column("params_json", sa.JSON(), nullable=False),
        sa.Column("software_version", sa.String(), nullable=False),
        sa.Column("status", sa.String(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("point_count", sa.Integer(), nullable=False),
        sa.Column("frame_count", sa.Integer(), nullable=False),
        sa.Column("scanned_length_m", sa.Float(), nullable=False),
        sa.Column("registration_json", sa.JSON(), nullable=True),
        sa.Column("threshold_table", sa.String(), nullable=False),
        sa.ForeignKeyConstraint(
            ["asset_id"],
            ["assets.asset_id"],
            name=op.f("fk_inspections__asset_id__assets"),
            onupdate="CASCADE",
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_inspections")),
        sa.UniqueConstraint(
            "asset_id",
            "content_hash",
            "params_hash",
            name=op.f("uq_inspections__asset_id_content_hash_params_hash"),
        ),
        sqlite_autoincrement=True,
    )
    with op.batch_alter_table("inspections") as batch_op:
        batch_op.create_index(
            batch_op.f("ix_inspections__asset_id_inspected_at"),
            ["asset_id", "inspected_at"],
            unique=False,
        )

    op.create_table(
        "sections",
        sa.Column("inspection_id", sa.Integer(), nullable=False),
        sa.Column("chainage_start_mm", sa.Integer(), nullable=False),
        sa.Column("chainage_end_mm", sa.Integer(), nullable=False),
        sa.Column("open_area_m2", sa.Float(), nullable=True),
        sa.Column("nominal_area_m2", sa.Float(), nullable=True),
        sa.Column("blockage_ratio", sa.Float(), nullable=True),
        sa.Column("ovality_ratio", sa.Float(), nullable=True),
        sa.Column("deformation_ratio", sa.Float(), nullable=True),
        sa.Column("deposit_height_ratio", sa.Float(), nullable=True),
        sa.Column("coverage_ratio", sa.Float(), nullable=False),
        sa.Column("point_count", sa.Integer(), nullable=False),
        sa.Column("status", sa.String(), nullable=False),
        sa.Column("grade", sa.Integer(), nullable=True),
        sa.Column("contour_json", sa.Text(), nullable=True),
        sa.CheckConstraint(
            "chainage_end_mm > chainage_start_mm", name=op.f("ck_sections__chainage_order")
        ),
        sa.CheckConstraint("point_count >= 0", name=op.f("ck_sections__point_count_non_negative")),
        sa.CheckConstraint(
            "coverage_ratio >= 0 AND coverage_ratio <= 1",
            name=op.f("ck_sections__coverage_range"),
        ),
        sa.ForeignKeyConstraint(
            ["inspection_id"],
            ["inspections.id"],
            name=op.f("fk_sections__inspection_id__inspections"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("inspection_id", "chainage_start_mm", name=op.f("pk_sections")),
    )

    op.create_table(
        "defects",
        sa.Column("id", sa.Integer(), autoincrement=True, nullable=False),
        sa.Column("inspection_id", sa.Integer(), nullable=False),
        sa.Column("code", sa.String(), nullable=False),
        sa.Column("measure", sa.String(), nullable=False),
        sa.Column("chainage_start_m", sa.Float(), nullable=False),
        sa.Column("chainage_end_m", sa.Float(), nullable=False),
        sa.Column("peak_chainage_m", sa.Float(), nullable=False),
        sa.Column("peak_value", sa.Float(), nullable=False),
        sa.Column("peak_blockage_ratio", sa.Float(), nullable=True),
        sa.Column("grade", sa.Integer(), nullable=True),
        sa.ForeignKeyConstraint(
            ["inspection_id"],
            ["inspections.id"],
            name=op.f("fk_defects__inspection_id__inspections"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_defects")),
    )
    with op.batch_alter_table("defects") as batch_op:
        batch_op.create_index(
            batch_op.f("ix_defects__inspection_id"), ["inspection_id"], unique=False
        )

    op.create_table(
        "frame_quality",
        sa.Column("inspection_id", sa.Integer(), nullable=False),
        sa.Column("frame_index", sa.Integer(), nullable=False),
        sa.Column("fitness", sa.Float(), nullable=False),
        sa.Column("rmse_m", sa.Float(), nullable=False),
        sa.Column("degenerate", sa.Boolean(), nullable=False),
        sa.ForeignKeyConstraint(
            ["inspection_id"],
            ["inspections.id"],
            name=op.f("fk_frame_quality__inspection_id__inspections"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("inspection_id", "frame_index", name=op.f("pk_frame_quality")),
    )


def downgrade() -> None:
    # Children first, so that no drop has to cascade.
    op.drop_table("frame_quality")
    with op.batch_alter_table("defects") as batch_op:
        batch_op.drop_index(batch_op.f("ix_defects__inspection_id"))
    op.drop_table("defects")
    op.drop_table("sections")
    with op.batch_alter_table("inspections") as batch_op:
        batch_op.drop_index(batch_op.f("ix_inspections__asset_id_inspected_at"))
    op.drop_table("inspections")
    op.drop_table("assets")
