"""SQL store: models, engine, migrations and repositories (all SQL of the project lives here)."""
