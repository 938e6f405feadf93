"""zones and zone_visits: areas operators draw on a floor, and each user's stays in them

Revision ID: 0013
Revises: 0012
Create Date: 2026-12-07 21:00:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op


revision: str = '0013'
down_revision: str | None = '0012'
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

_BIGINT_PK = sa.BigInteger().with_variant(sa.Integer(), 'sqlite')


def upgrade() -> None:
    op.create_table(
        'zones',
        sa.Column('building_id', sa.String(length=64), nullable=False),
        sa.Column('id', sa.String(length=64), nullable=False),
        sa.Column('floor', sa.Integer(), nullable=False),
        sa.Column('name', sa.String(length=128), nullable=False),
        sa.Column('ring', sa.Text(), nullable=False),
        sa.Column('dwell_s', sa.Float(), nullable=True),
        sa.Column('updated_at', sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ['building_id'], ['buildings.id'], name=op.f('fk_zones_building_id_buildings'), ondelete='CASCADE'
        ),
        sa.PrimaryKeyConstraint('building_id', 'id', name=op.f('pk_zones')),
    )
    op.create_table(
        'zone_visits',
        sa.Column('id', _BIGINT_PK, autoincrement=True, nullable=False),
        sa.Column('building_id', sa.String(length=64), nullable=False),
        sa.Column('zone_id', sa.String(length=64), nullable=False),
        sa.Column('user_id', sa.String(length=64), nullable=False),
        sa.Column('entered_ms', sa.BigInteger(), nullable=False),
        sa.Column('entered_probability', sa.Float(), nullable=False),
        sa.Column('left_ms', sa.BigInteger(), nullable=True),
        sa.Column('left_probability', sa.Float(), nullable=True),
        sa.Column('dwelled_ms', sa.BigInteger(), nullable=True),
        sa.Column('stored_at_ms', sa.BigInteger(), nullable=False),
        sa.ForeignKeyConstraint(
            ['building_id', 'zone_id'],
            ['zones.building_id', 'zones.id'],
            name=op.f('fk_zone_visits_building_id_zones'),
            ondelete='CASCADE',
        ),
        sa.PrimaryKeyConstraint('id', name=op.f('pk_zone_visits')),
    )
    op.create_index('ix_zone_visits_zone_entered', 'zone_visits', ['building_id', 'zone_id', 'entered_ms'])
    op.create_index('ix_zone_visits_user', 'zone_visits', ['building_id', 'user_id', 'zone_id'])
    op.create_index('ix_zone_visits_building_stored', 'zone_visits', ['building_id', 'stored_at_ms'])


def downgrade() -> None:
    op.drop_index('ix_zone_visits_building_stored', table_name='zone_visits')
    op.drop_index('ix_zone_visits_user', table_name='zone_visits')
    op.drop_index('ix_zone_visits_zone_entered', table_name='zone_visits')
    op.drop_table('zone_visits')
    op.drop_table('zones')
