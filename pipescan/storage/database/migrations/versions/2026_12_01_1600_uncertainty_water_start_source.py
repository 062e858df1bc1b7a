"""Uncertainty of each figure and water depth on sections; where the scan started, on
inspections.

Adds to ``sections`` the 95 % uncertainty (±, a ratio like the figure) of the blockage,
ovality, deformation and deposit height, and ``water_depth_ratio`` (water in the invert over
the nominal diameter); and to ``inspections`` ``start_source``, which of the rules placed the
scan's start (docs/archive.md). All nullable: sections and inspections stored before have
none (the figures were measured without them), and are left as they were.

Revision ID: a61c0e5d2b94
Revises: 3f8a6c2d9e17
Create Date: 2026-12-01 16:00:00+00:00
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

# revision identifiers, used by Alembic.
revision: str = "a61c0e5d2b94"
down_revision: str | None = "3f8a6c2d9e17"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

_SECTION_COLUMNS = (
    "blockage_uncertainty_ratio",
    "ovality_uncertainty_ratio",
    "deformation_uncertainty_ratio",
    "deposit_height_uncertainty_ratio",
    "water_depth_ratio",
)


def upgrade() -> None:
    # Nullable columns without defaults: plain ADD COLUMNs, on SQLite too (no table copy).
    with op.batch_alter_table("sections") as batch_op:
        for name in _SECTION_COLUMNS:
            batch_op.add_column(sa.Column(name, sa.Float(), nullable=True))
    with op.batch_alter_table(
        "inspections", table_kwargs={"sqlite_autoincrement": True}
    ) as batch_op:
        batch_op.add_column(sa.Column("start_source", sa.String(), nullable=True))


def downgrade() -> None:
    # On SQLite the batch copies the table: keep AUTOINCREMENT, so ids are never reused.
    with op.batch_alter_table(
        "inspections", table_kwargs={"sqlite_autoincrement": True}
    ) as batch_op:
        batch_op.drop_column("start_source")
    with op.batch_alter_table("sections") as batch_op:
        for name in reversed(_SECTION_COLUMNS):
            batch_op.drop_column(name)
