"""The house follows the data: imports run rig -> calib -> recon, and no module imports itself round.

Every ``import`` statement of the three packages counts, also the ones inside functions (a lazy
import still ties two modules together). See ``docs/architecture.md``.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: Lower floors first: a package may import its own floor and those below it.
FLOORS = ("recon", "calib", "rig")


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def modules() -> dict[str, Path]:
    return {module_name(p): p for floor in FLOORS for p in sorted((ROOT / floor).rglob("*.py"))}


def imports_of(name: str, path: Path, known: set[str]) -> set[str]:
    """The project modules ``path`` imports (``from a import b`` counts ``a.b`` when that is a module)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else base for alias in node.names]
        else:
            continue
        for target in targets:
            # the module itself, or the nearest enclosing package that is a project module
            while target and target not in known:
                target = target.rpartition(".")[0]
            if target and target != name:
                found.add(target)
    return found


def import_graph() -> dict[str, set[str]]:
    found = modules()
    known = set(found)
    return {name: imports_of(name, path, known) for name, path in found.items()}


def floor(name: str) -> int:
    return FLOORS.index(name.split(".")[0])


def test_every_package_is_scanned():
    graph = import_graph()
    assert {"recon.lf.capture", "calib.rectify", "rig.session", "rig.main"} <= set(graph)
    assert "recon.lf.capture" in graph["rig.session"]  # the walk sees real imports


def test_imports_run_with_the_data_flow():
    upward = sorted(f"{a} imports {b}" for a, targets in import_graph().items() for b in targets if floor(b) > floor(a))
    assert not upward, "imports against the data flow (rig -> calib -> recon):\n" + "\n".join(upward)


def test_no_import_cycles():
    graph = import_graph()
    # Tarjan's strongly connected components; a package importing its own submodules (its __init__
    # re-exporting them) is not a cycle of the code, so package -> own submodule edges are left out.
    def edges(name: str) -> set[str]:
        return {t for t in graph[name] if not t.startswith(name + ".")}

    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(edges(v)):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    assert not cycles, "import cycles: " + "; ".join(" <-> ".join(c) for c in cycles)


@pytest.mark.parametrize("name", ["recon", "calib"])
def test_lower_floors_import_without_the_upper_ones(name):
    """A fresh interpreter importing every module of a lower floor never loads an upper one."""
    import subprocess
    import sys

    names = [m for m in modules() if m.split(".")[0] in FLOORS[: FLOORS.index(name) + 1]]
    above = [f for f in FLOORS[FLOORS.index(name) + 1:]]
    code = ("import importlib, sys\n"
            f"for m in {names!r}: importlib.import_module(m)\n"
            f"bad = sorted(m for m in sys.modules if m.split('.')[0] in {above!r})\n"
            "print(bad); sys.exit(1 if bad else 0)\n")
    run = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stdout + run.stderr


def test_the_command_table_names_what_each_module_registers():
    """``rig.main`` builds a command's parser from the one module that adds it (``COMMAND_MODULES``):
    the table names every command each module registers, in its order."""
    import argparse
    import importlib

    from rig.main import COMMAND_MODULES, build_parser

    for name, commands in COMMAND_MODULES.items():
        subparsers = argparse.ArgumentParser().add_subparsers()
        importlib.import_module(name).register(subparsers)
        assert tuple(subparsers.choices) == commands, name
        for command in commands:
            assert command in build_parser([command, "--help"])._subparsers._group_actions[0].choices
    everything = build_parser([])._subparsers._group_actions[0].choices
    assert list(everything) == [c for commands in COMMAND_MODULES.values() for c in commands]
