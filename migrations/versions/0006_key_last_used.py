"""api keys: when each was last used

Operators list a building's keys with their last use (``GET /v1/buildings/{id}/keys``, ``crowdslam keys
list``) to find the ones to revoke. The server writes it in bulk when it revalidates its key cache, not on
every request.

Revision ID: 0006
Revises: 0005
Create Date: 2026-12-05 10:10:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op


revision: str = '0006'
down_revision: str | None = '0005'
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table('api_keys', schema=None) as batch_op:
        batch_op.add_column(sa.Column('last_used_at', sa.DateTime(timezone=True), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table('api_keys', schema=None) as batch_op:
        batch_op.drop_column('last_used_at')
