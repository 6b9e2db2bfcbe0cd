"""The package's import structure: core's subpackages in one order (ARCHITECTURE.md,
"Layers"), no import against it, no import cycle anywhere in the package, and no ROS in core.

Imports are read from the source with ``ast`` (every ``import`` and ``from ... import`` at any
depth, type-checking blocks included), so a lazy import inside a function counts too.
"""
from __future__ import annotations

import ast
import pathlib

import pytest

PACKAGE = "em_exploration_ros"
ROOT = pathlib.Path(__file__).resolve().parents[1] / PACKAGE

#: core's layers from the bottom up: a module may import its own layer and those below it.
#: ``base`` is the flat modules directly in core/ (geometry, params, ...).
CORE_ORDER = ["base", "records", "world", "links", "slam", "virtual_map", "planning", "agent",
              "evaluation", "sessions"]


def module_name(path: pathlib.Path) -> str:
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def package_modules() -> dict[str, pathlib.Path]:
    return {module_name(path): path for path in sorted(ROOT.rglob("*.py"))}


def imported_modules(path: pathlib.Path, known: set[str]) -> set[str]:
    """The package's modules that ``path`` imports (``from a.b import c`` counts as ``a.b.c``
    when that is a module, else ``a.b``)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [f"{node.module}.{alias.name}" for alias in node.names] + [node.module]
        else:
            continue
        for name in names:
            while name and name not in known:
                name = name.rpartition(".")[0]
            if name:
                found.add(name)
    return found


def import_graph() -> dict[str, set[str]]:
    modules = package_modules()
    known = set(modules)
    graph = {}
    for name, path in modules.items():
        targets = imported_modules(path, known)
        # A package's __init__ is imported with every module under it: not an edge to follow.
        graph[name] = {t for t in targets if t != name and not name.startswith(t + ".")}
    return graph


def core_layer(module: str) -> str | None:
    parts = module.split(".")
    if parts[:2] != [PACKAGE, "core"] or len(parts) < 3:
        return None
    return parts[2] if len(parts) > 3 or parts[2] in CORE_ORDER else "base"


def test_every_core_subpackage_has_a_place_in_the_order():
    subpackages = {p.name for p in (ROOT / "core").iterdir()
                   if p.is_dir() and (p / "__init__.py").exists()}
    assert subpackages == set(CORE_ORDER) - {"base"}


def test_core_imports_follow_the_order():
    against = []
    for module, targets in import_graph().items():
        layer = core_layer(module)
        if layer is None:
            continue
        for target in targets:
            target_layer = core_layer(target)
            assert target_layer is not None, f"{module} imports {target}, outside core"
            if CORE_ORDER.index(target_layer) > CORE_ORDER.index(layer):
                against.append(f"{module} ({layer}) -> {target} ({target_layer})")
    assert against == []


def test_core_imports_no_ros():
    for path in (ROOT / "core").rglob("*.py"):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            for name in names:
                top = name.split(".")[0]
                assert top not in {"rclpy", "rosidl_runtime_py", "em_exploration_msgs",
                                   "geometry_msgs", "nav_msgs", "std_msgs"}, (path, name)


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle of ``graph`` as a list of modules, or None (iterative DFS)."""
    state: dict[str, int] = {}
    for start in graph:
        if state.get(start):
            continue
        stack = [(start, iter(sorted(graph[start])))]
        path = [start]
        state[start] = 1
        while stack:
            node, children = stack[-1]
            child = next(children, None)
            if child is None:
                state[node] = 2
                stack.pop()
                path.pop()
            elif state.get(child) == 1:
                return path[path.index(child):] + [child]
            elif not state.get(child):
                state[child] = 1
                path.append(child)
                stack.append((child, iter(sorted(graph.get(child, ())))))
    return None


def test_no_import_cycle_in_the_package():
    assert find_cycle(import_graph()) is None


@pytest.mark.parametrize("graph, cycle", [
    ({"a": {"b"}, "b": {"c"}, "c": set()}, None),
    ({"a": {"b"}, "b": {"c"}, "c": {"a"}}, ["a", "b", "c", "a"]),
    ({"a": {"a2"}, "a2": set(), "b": {"c"}, "c": {"b"}}, ["b", "c", "b"]),
])
def test_the_cycle_finder_finds_cycles(graph, cycle):
    assert find_cycle(graph) == cycle
