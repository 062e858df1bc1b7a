"""The 95 % uncertainty of each section's water depth.

Adds ``sections.water_depth_uncertainty_ratio``: the ± of ``water_depth_ratio``, over the
nominal diameter (docs/measures.md, "Water"). NULL for sections stored before: their water
depth was read without a stated ±, and from the axis rather than the wall's own circle.

Revision ID: 5d2e8b7c4a16
Revises: 8b1e4c7d2a90
Create Date: 2026-12-07 23:00:00+00:00
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

# revision identifiers, used by Alembic.
revision: str = "5d2e8b7c4a16"
down_revision: str | None = "8b1e4c7d2a90"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    # A nullable column without a default: a plain ADD COLUMN on SQLite and PostgreSQL alike.
    with op.batch_alter_table("sections") as batch_op:
        batch_op.add_column(sa.Column("water_depth_uncertainty_ratio", sa.Float(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("sections") as batch_op:
        batch_op.drop_column("water_depth_uncertainty_ratio")
