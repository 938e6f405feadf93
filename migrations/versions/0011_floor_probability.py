"""floor_probability: how sure the filter was of an estimate's floor

Every estimate carries the floor the filter believes its user is on and the belief's probability; the
position history and the latest positions keep both. Rows written before hold floor 0 in a one-floor
building, where the filter is sure: 1.

Revision ID: 0011
Revises: 0010
Create Date: 2026-12-06 18:00:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op


revision: str = '0011'
down_revision: str | None = '0010'
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

_TABLES = ('position_snapshots', 'latest_positions')


def upgrade() -> None:
    for table in _TABLES:
        with op.batch_alter_table(table) as batch:
            batch.add_column(
                sa.Column('floor_probability', sa.Float(), nullable=False, server_default=sa.text('1.0'))
            )


def downgrade() -> None:
    for table in _TABLES:
        with op.batch_alter_table(table) as batch:
            batch.drop_column('floor_probability')
