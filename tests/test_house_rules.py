"""The house's rules, read from the code's imports (every import counts: module level, inside functions and
under ``TYPE_CHECKING``):

- imports run one way: server -> schemas, server -> slam_core; slam_core is pure numerics;
- the packages of each root are layered (``LAYERS``, the one place the order is declared): a package imports
  its own modules and packages of lower layers only, never a package beside it or above it;
- no module imports itself back through others (no cycle).
"""

from __future__ import annotations

import ast
import re
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


LAYERS: dict[str, list[list[str]]] = {
    "slam_core": [
        ["geo", "background_call", "wifi", "zones"],
        ["filter"],
        ["sensing", "encounters"],
        ["crowd", "signalslam"],
        ["tracking"],
        ["sim"],
    ],
    "server": [
        [
            "settings",
            "errors",
            "gc_tuning",
            "process_lifetime",
            "storage",
            "rate_limit",
            "live",
            "data",
            "dashboard",
            "tls",
        ],
        ["store", "slam", "phone"],
        ["auth", "ingestion", "recordings", "webhooks"],
        ["buildings"],
        ["datasets", "simulation", "cluster"],
        ["signal_maps", "replay", "metrics"],
        ["state"],
        ["api"],
        ["app"],
        ["cli"],
    ],
}
"""Lowest first. A root's top-level module or package is a unit; ``slam_core.filter.kernels.motion`` is in
``filter``."""


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


def module_name(root: Path, path: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_graph(root: Path, packages: list[str]) -> dict[str, set[str]]:
    """Every module of ``packages`` (folders under ``root``) -> the modules of those packages it imports,
    wherever the import stands; ``from a import b`` counts module ``a.b`` when there is one, else ``a``."""
    files = {module_name(root, p): p for pkg in packages for p in sorted((root / pkg).rglob("*.py"))}
    graph: dict[str, set[str]] = {}
    for name, path in files.items():
        is_package = path.name == "__init__.py"
        targets: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                targets.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = name.split(".")[: len(name.split(".")) - node.level + (1 if is_package else 0)]
                    module = ".".join([*base, node.module] if node.module else base)
                else:
                    module = node.module or ""
                for alias in node.names:
                    child = f"{module}.{alias.name}"
                    targets.add(child if child in files else module)
        graph[name] = {t for t in targets if t in files and t != name}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm, iteratively)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def layer_violations(graph: dict[str, set[str]], layers: dict[str, list[list[str]]]) -> list[str]:
    """Imports from a unit (a root's top-level module or package) into a unit beside it or above it."""
    rank = {
        f"{root}.{unit}": k
        for root, order in layers.items()
        for k, units in enumerate(order)
        for unit in units
    }

    def unit_of(module: str) -> str | None:
        parts = module.split(".")
        return ".".join(parts[:2]) if len(parts) > 1 and parts[0] in layers else None

    unranked = sorted({u for m in graph if (u := unit_of(m)) is not None and u not in rank})
    bad = [f"{u}: not in LAYERS" for u in unranked]
    for module, targets in sorted(graph.items()):
        source = unit_of(module)
        for target in sorted(targets):
            dest = unit_of(target)
            if source is None or dest is None or source == dest or source.split(".")[0] != dest.split(".")[0]:
                continue
            if source in rank and dest in rank and rank[dest] >= rank[source]:
                bad.append(f"{module} imports {target} ({dest} is not below {source})")
    return bad


def test_no_import_cycles() -> None:
    assert cycles(import_graph(ROOT, ["slam_core", "server", "schemas"])) == []


def test_packages_import_only_lower_layers() -> None:
    assert layer_violations(import_graph(ROOT, ["slam_core", "server"]), LAYERS) == []


def test_the_checkers_see_a_planted_cycle_and_layer_violation(tmp_path: Path) -> None:
    """A temporary root with two layers: a cycle through a function-level import and one under
    TYPE_CHECKING, and a lower package importing a higher one."""
    pkg = tmp_path / "house"
    (pkg / "low").mkdir(parents=True)
    (pkg / "high").mkdir()
    for folder in (pkg, pkg / "low", pkg / "high"):
        (folder / "__init__.py").write_text("")
    (pkg / "low" / "a.py").write_text("def f():\n    from house.high import b  # a lower layer reaching up\n")
    (pkg / "high" / "b.py").write_text("from house.high import c\n")
    (pkg / "high" / "c.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from . import b\n"
    )
    graph = import_graph(tmp_path, ["house"])
    assert graph["house.low.a"] == {"house.high.b"}
    assert graph["house.high.c"] == {"house.high.b"}
    assert cycles(graph) == [["house.high.b", "house.high.c"]]
    layers = {"house": [["low"], ["high"]]}
    assert layer_violations(graph, layers) == [
        "house.low.a imports house.high.b (house.high is not below house.low)"
    ]
    assert layer_violations(graph, {"house": [["low", "high"]]}) == [
        "house.low.a imports house.high.b (house.high is not below house.low)"
    ]
    assert layer_violations(graph, {"house": [["high"]]}) == ["house.low: not in LAYERS"]


SHARED_PATH = re.compile(r"""["'](\.\./)?shared["'/]|/ ?["']shared["']""")
"""A path into ``../shared`` (the developers' copy of the data), which a clone of the repository lacks."""


def test_nothing_but_the_tests_locator_reaches_for_the_developers_shared_folder() -> None:
    """The product and its tests work on a clone alone: the package ships its scenario, the tests their
    sample of walks; only ``tests/conftest.py`` may prefer ``../shared`` for whole floors."""
    offenders = [
        str(path.relative_to(ROOT))
        for folder in ("server", "slam_core", "schemas", "migrations", "tests", "bench")
        for path in sorted((ROOT / folder).rglob("*.py"))
        if path not in (ROOT / "tests" / "conftest.py", Path(__file__))
        and SHARED_PATH.search(path.read_text())
    ]
    assert not offenders, offenders


WALK_LOCATORS = re.compile(r"\b(SAMPLE_FLOOR|SAMPLE_WALKS|whole_floor|public_walks|small_floor)\b")


def test_every_test_module_reading_walks_is_marked_so() -> None:
    """CI runs the ``walks`` tests once more as a clone without ``../shared`` would
    (``CROWDSLAM_TESTS_WITHOUT_SHARED``): a module that reads walks unmarked would escape that run."""
    unmarked = [
        str(path.relative_to(ROOT))
        for path in sorted((ROOT / "tests").rglob("test_*.py"))
        if WALK_LOCATORS.search(text := path.read_text()) and "pytestmark = pytest.mark.walks" not in text
    ]
    assert not unmarked, unmarked
    assert SHARED_PATH.search('SHARED = ROOT.parent / "shared" / "data"')
    assert SHARED_PATH.search("x = '../shared/data'")
    assert not SHARED_PATH.search("the crowd's shared anchor map")
