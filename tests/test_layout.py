"""The package's layering: every module imports on its own, and no chain of imports (at module
level or inside functions) leads from a module back to itself."""

from __future__ import annotations

import ast
import importlib
import pkgutil
import sys
from pathlib import Path

import pytest

import hipode_pipeline

PACKAGE = "hipode_pipeline"
PACKAGE_DIR = Path(hipode_pipeline.__file__).parent


def package_modules() -> list[str]:
    return sorted(
        info.name for info in pkgutil.walk_packages([str(PACKAGE_DIR)], prefix=f"{PACKAGE}.")
    )


def module_file(name: str) -> Path:
    relative = Path(*name.split(".")[1:])
    package_init = PACKAGE_DIR / relative / "__init__.py"
    return package_init if package_init.is_file() else PACKAGE_DIR / relative.with_suffix(".py")


def imported_modules(name: str, known: set[str]) -> set[str]:
    """Package modules `name` imports anywhere in its file (lazy imports count too)."""
    tree = ast.parse(module_file(name).read_text())
    is_package = module_file(name).name == "__init__.py"
    found: set[str] = set()
    for node in ast.walk(tree):
        targets: list[str] = []
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = name.split(".") if is_package else name.split(".")[:-1]
                anchor = anchor[: len(anchor) - node.level + 1]
                base = ".".join([*anchor, *([base] if base else [])])
            # `from pkg import module` imports the module; `from module import name` the module
            submodules = [f"{base}.{a.name}" for a in node.names if f"{base}.{a.name}" in known]
            targets = submodules or [base]
        for target in targets:
            # `from hipode_pipeline import console` imports the module hipode_pipeline.console
            while target and target not in known:
                target = target.rpartition(".")[0]
            # a module's own parent packages are loaded first by Python, not a layer above it
            if target and target != name and not name.startswith(f"{target}."):
                found.add(target)
    return found


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle as a path [a, b, ..., a], or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt) :] + [nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (cycle := visit(node)):
            return cycle
    return None


def test_no_import_cycle_anywhere_in_the_package():
    modules = set(package_modules())
    # a subpackage's __init__ that re-exports its modules is a facade, not a layer
    graph = {name: imported_modules(name, modules) - {PACKAGE} for name in modules}
    assert find_cycle(graph) is None, " -> ".join(find_cycle(graph))


def test_the_cycle_finder_finds_a_planted_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert find_cycle(graph) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_layers_point_one_way():
    modules = set(package_modules())
    imports = {name: imported_modules(name, modules) for name in modules}
    for name, targets in imports.items():
        if name.startswith(f"{PACKAGE}.data") or name == f"{PACKAGE}.replay":
            assert not {t for t in targets if t.startswith(f"{PACKAGE}.learners")}, name
        if name.startswith(f"{PACKAGE}.learners"):
            assert f"{PACKAGE}.train" not in targets, name
        if name == f"{PACKAGE}.generate":
            # Algorithm 1 does no file I/O: no artifact writer, no run folder, no loader
            assert not targets & {f"{PACKAGE}.artifact", f"{PACKAGE}.files", f"{PACKAGE}.data.load"}


@pytest.mark.parametrize("name", package_modules())
def test_every_module_imports_on_its_own(name):
    loaded = {key: module for key, module in sys.modules.items() if key.startswith(PACKAGE)}
    try:
        for key in loaded:
            del sys.modules[key]
        importlib.import_module(name)
    finally:
        for key in [key for key in sys.modules if key.startswith(PACKAGE)]:
            del sys.modules[key]
        sys.modules.update(loaded)
