"""Blockage summary on inspections, for network-wide rankings.

Adds to ``inspections`` the count of measured sections (status ``ok`` with a blockage ratio),
their mean and peak blockage ratio and the start chainage of the peak section, and fills them
in from the stored sections, so that ``pipescan worst`` reads one row per inspection instead of
every section. ``repository.save_inspection`` writes them together with the sections.

Revision ID: 7d2b4e91c3a8
Revises: c5e1a9f40b21
Create Date: 2026-11-23 16:20:00+00:00
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

# revision identifiers, used by Alembic.
revision: str = "7d2b4e91c3a8"
down_revision: str | None = "c5e1a9f40b21"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

# The measured sections of the inspection being updated; the same rule as the repository's.
_MEASURED = (
    "FROM sections WHERE sections.inspection_id = inspections.id "
    "AND sections.status = 'ok' AND sections.blockage_ratio IS NOT NULL"
)


def upgrade() -> None:
    # Plain ADD COLUMNs on SQLite too: a literal (string) server default does not make the
    # batch copy the table. If it ever must, AUTOINCREMENT is kept (ids are never reused).
    with op.batch_alter_table(
        "inspections", table_kwargs={"sqlite_autoincrement": True}
    ) as batch_op:
        batch_op.add_column(
            sa.Column(
                "measured_section_count",
                sa.Integer(),
                server_default="0",
                nullable=False,
            )
        )
        batch_op.add_column(sa.Column("mean_blockage_ratio", sa.Float(), nullable=True))
        batch_op.add_column(sa.Column("peak_blockage_ratio", sa.Float(), nullable=True))
        batch_op.add_column(sa.Column("peak_chainage_start_mm", sa.Integer(), nullable=True))

    # Plain SQL with correlated subqueries: the same statement runs on SQLite and PostgreSQL.
    op.execute(
        "UPDATE inspections SET "
        f"measured_section_count = (SELECT count(*) {_MEASURED}), "
        f"mean_blockage_ratio = (SELECT avg(blockage_ratio) {_MEASURED}), "
        f"peak_blockage_ratio = (SELECT max(blockage_ratio) {_MEASURED}), "
        f"peak_chainage_start_mm = (SELECT chainage_start_mm {_MEASURED} "
        "ORDER BY blockage_ratio DESC, chainage_start_mm LIMIT 1)"
    )


def downgrade() -> None:
    # On SQLite the batch copies the table: keep AUTOINCREMENT, so ids are never reused.
    with op.batch_alter_table(
        "inspections", table_kwargs={"sqlite_autoincrement": True}
    ) as batch_op:
        batch_op.drop_column("peak_chainage_start_mm")
        batch_op.drop_column("peak_blockage_ratio")
        batch_op.drop_column("mean_blockage_ratio")
        batch_op.drop_column("measured_section_count")
