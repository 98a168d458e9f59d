"""The house rules, checked on the source: no import circles among project modules, no module
over 500 lines and no function over 60 lines in ``bsms/`` and ``datagen/``, and at most 12
modules directly in ``bsms/`` (the rest lives in its sub-packages: training, evaluate, infer,
rollouts, physics, graph, models, datasets).

Imports are read with ``ast`` from every module, at module level and inside functions alike
(a function-level import that dodges a circle is still a circle). ``from pkg import name``
depends on ``pkg.name`` when that is a module and on ``pkg`` otherwise; importing a
submodule does not count as depending on its package's ``__init__``.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
from scipy.sparse import csgraph, csr_matrix

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("bsms", "datagen")
MAX_MODULE_LINES = 500
MAX_FUNCTION_LINES = 60
MAX_TOP_LEVEL_MODULES = 12  # files directly in bsms/, __init__.py included


def project_modules(root: Path = ROOT) -> dict[str, Path]:
    """Dotted module name -> file, for every module of the project's packages under ``root``."""
    modules = {}
    for package in PACKAGES:
        for path in sorted((root / package).rglob("*.py")):
            parts = path.relative_to(root).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            modules[name] = path
    return modules


def _imported(module: str, path: Path, node: ast.AST, modules: dict) -> list[str]:
    """Project modules that one import statement of ``module`` depends on."""
    if isinstance(node, ast.Import):
        targets = [alias.name for alias in node.names]
    else:
        base = node.module or ""
        if node.level:
            package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
            package = package[: len(package) - node.level + 1]
            base = ".".join(package + ([node.module] if node.module else []))
        submodules = [f"{base}.{alias.name}" for alias in node.names if f"{base}.{alias.name}" in modules]
        targets = submodules + ([base] if len(submodules) < len(node.names) else [])
    found = []
    for target in targets:
        while target and target not in modules:  # 'pkg.mod.attr' -> 'pkg.mod'
            target = target.rpartition(".")[0]
        if target and target != module:
            found.append(target)
    return found


def import_graph(modules: dict[str, Path]) -> dict[str, set[str]]:
    """module -> the project modules it imports anywhere in its source."""
    graph = {}
    for module, path in modules.items():
        tree = ast.parse(path.read_text(), filename=str(path))
        graph[module] = {
            target
            for node in ast.walk(tree) if isinstance(node, (ast.Import, ast.ImportFrom))
            for target in _imported(module, path, node, modules)
        }
    return graph


def import_circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (each one is a circle)."""
    names = sorted(graph)
    index = {name: k for k, name in enumerate(names)}
    rows = [index[a] for a in names for b in graph[a]]
    cols = [index[b] for a in names for b in graph[a]]
    adjacency = csr_matrix(([1] * len(rows), (rows, cols)), shape=(len(names), len(names)))
    _, labels = csgraph.connected_components(adjacency, directed=True, connection="strong")
    groups: dict[int, list[str]] = {}
    for name, label in zip(names, labels, strict=True):
        groups.setdefault(int(label), []).append(name)
    return sorted(group for group in groups.values() if len(group) > 1)


def test_no_import_circles():
    circles = import_circles(import_graph(project_modules()))
    assert circles == [], "project modules import each other in a circle: " + "; ".join(
        " <-> ".join(c) for c in circles)


def test_the_circle_check_finds_function_level_circles(tmp_path):
    """The checker itself: a circle closed by an import inside a function is found."""
    for package in PACKAGES:
        (tmp_path / package).mkdir()
        (tmp_path / package / "__init__.py").write_text("")
    (tmp_path / "bsms" / "a.py").write_text("from bsms.b import f\n")
    (tmp_path / "bsms" / "b.py").write_text("def f():\n    from . import a\n    return a\n")
    (tmp_path / "datagen" / "c.py").write_text("from datagen import d\n")
    (tmp_path / "datagen" / "d.py").write_text("import numpy\n")
    graph = import_graph(project_modules(tmp_path))
    assert graph["datagen.c"] == {"datagen.d"} and graph["datagen.d"] == set()
    assert import_circles(graph) == [["bsms.a", "bsms.b"]]


@pytest.mark.parametrize("package", PACKAGES)
def test_modules_and_functions_stay_small(package):
    too_long = []
    for path in sorted((ROOT / package).rglob("*.py")):
        source = path.read_text()
        lines = source.count("\n")
        if lines > MAX_MODULE_LINES:
            too_long.append(f"{path.relative_to(ROOT)}: {lines} lines")
        for node in ast.walk(ast.parse(source)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                if length > MAX_FUNCTION_LINES:
                    too_long.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name}() {length} lines")
    assert too_long == [], f"over {MAX_MODULE_LINES} lines a module or {MAX_FUNCTION_LINES} a function"


def test_the_learned_side_keeps_a_small_top_level():
    top = sorted(path.name for path in (ROOT / "bsms").glob("*.py"))
    assert len(top) <= MAX_TOP_LEVEL_MODULES, (
        f"bsms/ holds {len(top)} modules directly ({', '.join(top)}); at most {MAX_TOP_LEVEL_MODULES}: "
        "put a new one in the sub-package of its job")
