"""batch_log: the batch bodies a restart may replay, in a table of their own

An accepted batch's id stays in ``batches`` for ``CROWDSLAM_BATCH_IDS_HOURS`` to answer retries; its body,
kept only until a tracker snapshot covers it, moves to ``batch_log``, whose rows are deleted whole. Bodies
written inline and later set to NULL had left most of the ``batches`` pages empty and unreusable.

Revision ID: 0010
Revises: 0009
Create Date: 2026-12-06 16:00:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op


revision: str = '0010'
down_revision: str | None = '0009'
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

_BIGINT_PK = sa.BigInteger().with_variant(sa.Integer(), 'sqlite')


def upgrade() -> None:
    # the logged bodies set aside first: rebuilding ``batches`` without its body (SQLite's batch mode copies
    # the table and drops the old one) would cascade into a ``batch_log`` already referring to it
    op.execute(
        'CREATE TABLE batch_log_moving AS SELECT id, building_id, applied_round, body FROM batches '
        'WHERE body IS NOT NULL AND applied_round IS NOT NULL'
    )
    with op.batch_alter_table('batches', schema=None) as batch_op:
        batch_op.drop_index(
            'ix_batches_logged',
            sqlite_where=sa.text('body IS NOT NULL'),
            postgresql_where=sa.text('body IS NOT NULL'),
        )
        batch_op.drop_column('body')
    op.create_table(
        'batch_log',
        sa.Column('batch_row_id', _BIGINT_PK, autoincrement=False, nullable=False),
        sa.Column('building_id', sa.String(length=64), nullable=False),
        sa.Column('applied_round', sa.BigInteger(), nullable=False),
        sa.Column('body', sa.LargeBinary(), nullable=False),
        sa.ForeignKeyConstraint(
            ['batch_row_id'], ['batches.id'], name=op.f('fk_batch_log_batch_row_id_batches'), ondelete='CASCADE'
        ),
        sa.ForeignKeyConstraint(
            ['building_id'], ['buildings.id'], name=op.f('fk_batch_log_building_id_buildings'), ondelete='CASCADE'
        ),
        sa.PrimaryKeyConstraint('batch_row_id', name=op.f('pk_batch_log')),
    )
    with op.batch_alter_table('batch_log', schema=None) as batch_op:
        batch_op.create_index('ix_batch_log_building_round', ['building_id', 'applied_round'], unique=False)
    op.execute(
        'INSERT INTO batch_log (batch_row_id, building_id, applied_round, body) '
        'SELECT id, building_id, applied_round, body FROM batch_log_moving'
    )
    op.drop_table('batch_log_moving')


def downgrade() -> None:
    with op.batch_alter_table('batches', schema=None) as batch_op:
        batch_op.add_column(sa.Column('body', sa.LargeBinary(), nullable=True))
    op.execute(
        'UPDATE batches SET body = (SELECT body FROM batch_log WHERE batch_log.batch_row_id = batches.id)'
    )
    with op.batch_alter_table('batches', schema=None) as batch_op:
        batch_op.create_index(
            'ix_batches_logged',
            ['building_id', 'applied_round'],
            unique=False,
            sqlite_where=sa.text('body IS NOT NULL'),
            postgresql_where=sa.text('body IS NOT NULL'),
        )
    with op.batch_alter_table('batch_log', schema=None) as batch_op:
        batch_op.drop_index('ix_batch_log_building_round')
    op.drop_table('batch_log')
