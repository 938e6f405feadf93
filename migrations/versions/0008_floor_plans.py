"""floor_plans: a floor's plan as GeoJSON in the building's local frame

Operators upload a floor's walkable area, obstacles and walls (``PUT /v1/buildings/{id}/floors/{level}/plan``);
the tracker weighs each particle's step by it.

Revision ID: 0008
Revises: 0007
Create Date: 2026-12-05 12:00:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op


revision: str = '0008'
down_revision: str | None = '0007'
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        'floor_plans',
        sa.Column('building_id', sa.String(length=64), nullable=False),
        sa.Column('level', sa.Integer(), nullable=False),
        sa.Column('geojson', sa.Text(), nullable=False),
        sa.Column('updated_at', sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ['building_id', 'level'],
            ['floors.building_id', 'floors.level'],
            name=op.f('fk_floor_plans_building_id_floors'),
            ondelete='CASCADE',
        ),
        sa.PrimaryKeyConstraint('building_id', 'level', name=op.f('pk_floor_plans')),
    )


def downgrade() -> None:
    op.drop_table('floor_plans')
