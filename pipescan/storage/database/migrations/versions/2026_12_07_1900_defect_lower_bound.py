"""Whether each defect's figure is a lower bound.

Adds ``lower_bound`` to ``defects``: true where part of the feature stood in water that
returned nothing, so that the feature is at least its figure and its class at least as bad.
NULL for defects stored before: sections with water in the invert were not coded then, so none
of them is a lower bound.

Revision ID: 8b1e4c7d2a90
Revises: 3f6c2d8a1b47
Create Date: 2026-12-07 19:00:00+00:00
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

# revision identifiers, used by Alembic.
revision: str = "8b1e4c7d2a90"
down_revision: str | None = "3f6c2d8a1b47"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    # A nullable column without a default: a plain ADD COLUMN on SQLite and PostgreSQL alike.
    with op.batch_alter_table("defects") as batch_op:
        batch_op.add_column(sa.Column("lower_bound", sa.Boolean(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("defects") as batch_op:
        batch_op.drop_column("lower_bound")
