"""batch log index

The batches that still hold their body (the write-ahead log a restart replays) get a partial index, so
that a restart finds them, and their bodies are cleared a chunk at a time once a snapshot covers them,
without scanning the building's whole batch history.

Revision ID: 0004
Revises: 0003
Create Date: 2026-12-03 18:40:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op


revision: str = '0004'
down_revision: str | None = '0003'
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table('batches', schema=None) as batch_op:
        batch_op.create_index(
            'ix_batches_logged',
            ['building_id', 'applied_round'],
            unique=False,
            sqlite_where=sa.text('body IS NOT NULL'),
            postgresql_where=sa.text('body IS NOT NULL'),
        )


def downgrade() -> None:
    with op.batch_alter_table('batches', schema=None) as batch_op:
        batch_op.drop_index('ix_batches_logged')
