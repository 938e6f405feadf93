"""Imports run one way: server -> schemas, server -> slam_core. slam_core is pure numerics."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

FORBIDDEN = {
    "slam_core": {
        "pydantic",
        "pydantic_settings",
        "sqlalchemy",
        "alembic",
        "fastapi",
        "starlette",
        "uvicorn",
        "asyncio",
        "httpx",
        "socket",
        "mcap",
        "server",
        "schemas",
        "migrations",
        "os",
        "time",
        "datetime",
        "pathlib",
    },
    "schemas": {"server", "slam_core", "sqlalchemy", "fastapi", "numpy", "numba", "migrations"},
}


def imported_roots(path: Path) -> set[str]:
    roots: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            roots.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            roots.add(node.module.split(".")[0])
    return roots


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_forbidden_imports(package: str) -> None:
    offenders = {}
    for path in sorted((ROOT / package).rglob("*.py")):
        bad = imported_roots(path) & FORBIDDEN[package]
        if bad:
            offenders[str(path.relative_to(ROOT))] = sorted(bad)
    assert offenders == {}, f"{package} must not import these: {offenders}"


def test_the_checker_sees_imports(tmp_path: Path) -> None:
    sample = tmp_path / "sample.py"
    sample.write_text("import os.path\nfrom sqlalchemy.orm import Session\nfrom . import sibling\n")
    assert imported_roots(sample) == {"os", "sqlalchemy"}


def test_cli_help_imports_nothing_heavy() -> None:
    code = (
        "import sys; from server.cli.main import build_parser; build_parser(); "
        "heavy = [m for m in ('numpy', 'numba', 'sqlalchemy', 'fastapi', 'pydantic') if m in sys.modules]; "
        "print(','.join(heavy))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.strip() == ""
