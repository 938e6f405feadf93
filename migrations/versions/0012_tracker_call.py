"""tracker_call: the tracker call that applied a batch; anchor_observations dropped

``applied_round`` counted a building's calls of its tracker (a restart replays the batch log call by call),
not the rounds of events inside one call: it is ``tracker_call`` in the batches, the batch log and the
tracker snapshots. The ``anchor_observations`` table was never written: dropped.

Columns are renamed in place (SQLite 3.25 and PostgreSQL both rename a column without copying its table;
copying ``batches`` would cascade into the batch log that refers to it).

Revision ID: 0012
Revises: 0011
Create Date: 2026-12-07 12:00:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op


revision: str = '0012'
down_revision: str | None = '0011'
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

_TABLES = ('batches', 'batch_log', 'tracker_snapshots')
_BIGINT_PK = sa.BigInteger().with_variant(sa.Integer(), 'sqlite')


def _rename(old: str, new: str, index_old: str, index_new: str) -> None:
    op.drop_index(index_old, table_name='batch_log')
    for table in _TABLES:
        op.execute(f'ALTER TABLE {table} RENAME COLUMN {old} TO {new}')
    op.create_index(index_new, 'batch_log', ['building_id', new], unique=False)


def upgrade() -> None:
    _rename('applied_round', 'tracker_call', 'ix_batch_log_building_round', 'ix_batch_log_building_call')
    op.drop_index('ix_anchor_observations_anchor_id', table_name='anchor_observations')
    op.drop_table('anchor_observations')


def downgrade() -> None:
    op.create_table(
        'anchor_observations',
        sa.Column('id', _BIGINT_PK, autoincrement=True, nullable=False),
        sa.Column('anchor_id', _BIGINT_PK, nullable=False),
        sa.Column('user_id', sa.String(length=64), nullable=False),
        sa.Column('t_ms', sa.BigInteger(), nullable=False),
        sa.Column('detected_type', sa.String(length=32), nullable=False),
        sa.Column('x_m', sa.Float(), nullable=False),
        sa.Column('y_m', sa.Float(), nullable=False),
        sa.Column('cov_xx', sa.Float(), nullable=False),
        sa.Column('cov_xy', sa.Float(), nullable=False),
        sa.Column('cov_yy', sa.Float(), nullable=False),
        sa.ForeignKeyConstraint(
            ['anchor_id'], ['anchors.id'], name=op.f('fk_anchor_observations_anchor_id_anchors'), ondelete='CASCADE'
        ),
        sa.PrimaryKeyConstraint('id', name=op.f('pk_anchor_observations')),
    )
    op.create_index('ix_anchor_observations_anchor_id', 'anchor_observations', ['anchor_id'], unique=False)
    _rename('tracker_call', 'applied_round', 'ix_batch_log_building_call', 'ix_batch_log_building_round')
