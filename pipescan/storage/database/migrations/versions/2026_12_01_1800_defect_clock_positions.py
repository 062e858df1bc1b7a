"""Clock positions and characterisation of each defect.

Adds to ``defects`` the arc of wall each defect displaces, as clock positions in hours
(``clock_from_h``, ``clock_to_h``: 12 at the crown, 3 on the right looking in the survey's
direction, the arc running clockwise), and its EN 13508-2 characterisation where the geometry
tells it (``characterisation``: A vertical or B horizontal for a deformation). All three are
NULL for defects stored before: they were not coded.

Revision ID: 3f6c2d8a1b47
Revises: 3f8a61c2d7e4
Create Date: 2026-12-01 18:00:00+00:00
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

# revision identifiers, used by Alembic.
revision: str = "3f6c2d8a1b47"
down_revision: str | None = "3f8a61c2d7e4"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    # Nullable columns without a default: plain ADD COLUMNs on SQLite and PostgreSQL alike.
    with op.batch_alter_table("defects") as batch_op:
        batch_op.add_column(sa.Column("clock_from_h", sa.Float(), nullable=True))
        batch_op.add_column(sa.Column("clock_to_h", sa.Float(), nullable=True))
        batch_op.add_column(sa.Column("characterisation", sa.String(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("defects") as batch_op:
        batch_op.drop_column("characterisation")
        batch_op.drop_column("clock_to_h")
        batch_op.drop_column("clock_from_h")
