"""Chainage uncertainty of each section.

Adds ``sections.chainage_uncertainty_m``: how far the section's true place along the pipe may
be from its chainage, from registration (the travel held to the odometer before it, times the
odometer's stated error). NULL for sections stored before it was recorded, and for scans that
were not registered (one registered cloud).

Revision ID: 3f8a61c2d7e4
Revises: a61c0e5d2b94
Create Date: 2026-12-01 17:00:00+00:00
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

# revision identifiers, used by Alembic.
revision: str = "3f8a61c2d7e4"
down_revision: str | None = "a61c0e5d2b94"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("sections") as batch_op:
        batch_op.add_column(sa.Column("chainage_uncertainty_m", sa.Float(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("sections") as batch_op:
        batch_op.drop_column("chainage_uncertainty_m")
