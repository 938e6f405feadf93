"""Alembic migrations of the crowdslam store (run them with ``crowdslam migrate``)."""
