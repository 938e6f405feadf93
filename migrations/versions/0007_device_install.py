"""devices: the install their sequence numbers count in

A reinstalled phone starts its ``seq`` again; batches carry ``install_ms`` (when the app was installed) and a
device's last applied ``seq`` is counted within its latest install, so that the phone can post again with no
operator action while a batch of an earlier install, re-sent, is never applied.

Revision ID: 0007
Revises: 0006
Create Date: 2026-12-05 10:30:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op


revision: str = '0007'
down_revision: str | None = '0006'
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table('devices', schema=None) as batch_op:
        batch_op.add_column(sa.Column('install_ms', sa.BigInteger(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table('devices', schema=None) as batch_op:
        batch_op.drop_column('install_ms')
