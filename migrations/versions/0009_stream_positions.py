"""stream_positions: the last batch-stream sequence each building's worker applied

Cluster mode's workers read a building's batches from the stream after this sequence, which they write in
the same transaction as the batches.

Revision ID: 0009
Revises: 0008
Create Date: 2026-12-05 16:30:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op


revision: str = '0009'
down_revision: str | None = '0008'
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        'stream_positions',
        sa.Column('building_id', sa.String(length=64), nullable=False),
        sa.Column('sequence', sa.BigInteger(), nullable=False),
        sa.Column('updated_at', sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ['building_id'],
            ['buildings.id'],
            name=op.f('fk_stream_positions_building_id_buildings'),
            ondelete='CASCADE',
        ),
        sa.PrimaryKeyConstraint('building_id', name=op.f('pk_stream_positions')),
    )


def downgrade() -> None:
    op.drop_table('stream_positions')
