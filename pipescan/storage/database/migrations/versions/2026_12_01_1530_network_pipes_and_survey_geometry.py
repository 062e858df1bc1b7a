"""Where the pipes are and which way they were surveyed: for the ISYBAU and GIS exports.

- ``network_pipes``: the pipes of a GIS layer imported with ``pipescan network import``, each
  with its GIS id, what names its asset (an asset id, its two nodes), its line, length and CRS.
- ``assets``: the nodes' positions and their CRS, from ``inspection.toml``.
- ``inspections``: the survey's direction and the chainage of its start. Inspections stored
  before keep NULL there (unknown), never a guess.

Revision ID: 3f8a6c2d9e17
Revises: 7d2b4e91c3a8
Create Date: 2026-12-01 15:30:00+00:00
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

# revision identifiers, used by Alembic.
revision: str = "3f8a6c2d9e17"
down_revision: str | None = "7d2b4e91c3a8"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "network_pipes",
        sa.Column("gis_id", sa.String(), nullable=False),
        sa.Column("asset_ref", sa.String(), nullable=False),
        sa.Column("from_node", sa.String(), nullable=True),
        sa.Column("to_node", sa.String(), nullable=True),
        sa.Column("crs", sa.String(), nullable=False),
        sa.Column("line_json", sa.Text(), nullable=False),
        sa.Column("length_m", sa.Float(), nullable=False),
        sa.Column("source", sa.String(), nullable=False),
        sa.Column("imported_at", sa.DateTime(timezone=True), nullable=False),
        sa.CheckConstraint("length_m > 0", name=op.f("ck_network_pipes__length_positive")),
        sa.PrimaryKeyConstraint("gis_id", name=op.f("pk_network_pipes")),
        sa.UniqueConstraint("asset_ref", name=op.f("uq_network_pipes__asset_ref")),
    )
    op.create_index(
        op.f("ix_network_pipes__from_node_to_node"),
        "network_pipes",
        ["from_node", "to_node"],
        unique=False,
    )
    # Plain ADD COLUMNs (nullable, no default): SQLite does not copy the tables.
    with op.batch_alter_table("assets") as batch_op:
        batch_op.add_column(sa.Column("upstream_node_xyz", sa.JSON(), nullable=True))
        batch_op.add_column(sa.Column("downstream_node_xyz", sa.JSON(), nullable=True))
        batch_op.add_column(sa.Column("crs", sa.String(), nullable=True))
    with op.batch_alter_table(
        "inspections", table_kwargs={"sqlite_autoincrement": True}
    ) as batch_op:
        batch_op.add_column(sa.Column("direction", sa.String(), nullable=True))
        batch_op.add_column(sa.Column("chainage_offset_m", sa.Float(), nullable=True))


def downgrade() -> None:
    # On SQLite the batch copies the table: keep AUTOINCREMENT, so ids are never reused.
    with op.batch_alter_table(
        "inspections", table_kwargs={"sqlite_autoincrement": True}
    ) as batch_op:
        batch_op.drop_column("chainage_offset_m")
        batch_op.drop_column("direction")
    with op.batch_alter_table("assets") as batch_op:
        batch_op.drop_column("crs")
        batch_op.drop_column("downstream_node_xyz")
        batch_op.drop_column("upstream_node_xyz")
    op.drop_index(op.f("ix_network_pipes__from_node_to_node"), table_name="network_pipes")
    op.drop_table("network_pipes")
