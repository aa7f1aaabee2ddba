"""The house's layers (docs/architecture.md): the import graph of the non-test code has no
circles, the kernels import no converter, the core imports nothing of ``converters``, nothing
below the edge imports it, and the short public paths of ``converters.MOVED`` give the very
modules that hold them."""

from __future__ import annotations

import ast
import importlib
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _modules() -> dict[str, Path]:
    mods = {}
    for pkg in ("lidarscan", "converters"):
        for path in (ROOT / pkg).rglob("*.py"):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            mods[".".join(parts)] = path
    return mods


def _graph() -> dict[str, set[str]]:
    """module -> the project modules it imports (anywhere in the file, type-checking imports
    included). ``from pkg import name`` imports ``pkg.name`` when that is a module, else
    ``pkg``."""
    mods = _modules()

    def resolve(name: str) -> str | None:
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    edges: dict[str, set[str]] = {m: set() for m in mods}
    for mod, path in mods.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = mod.split(".")
                    if path.name != "__init__.py":
                        parts.pop()
                    parts = parts[:len(parts) - node.level + 1]
                    base = ".".join(parts + ([node.module] if node.module else []))
                subs = [f"{base}.{alias.name}" for alias in node.names]
                targets = [s for s in subs if s in mods] or [base]
            else:
                continue
            for target in targets:
                found = resolve(target)
                if found and found != mod:
                    edges[mod].add(found)
    return edges


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for root in edges:
        if root in index:
            continue
        work = [(root, iter(sorted(edges[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(edges[child]))))
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


def test_cycle_finder_finds_a_cycle() -> None:
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_circles() -> None:
    assert _cycles(_graph()) == []


def test_layers_point_one_way() -> None:
    edges = _graph()
    for mod, targets in edges.items():
        if mod.startswith("lidarscan"):
            assert not [t for t in targets if t.startswith("converters")], mod
        if mod.startswith("converters._kernels"):
            below = ("converters._kernels", "converters.slices.spec", "converters.slices.holes",
                     "lidarscan")
            assert all(t.startswith(below) for t in targets), (mod, sorted(targets))
        if not mod.startswith("converters.edge"):
            assert not [t for t in targets if t.startswith("converters.edge")], mod
        if mod.startswith(("converters.shared", "converters.sources")):
            above = ("converters.pointcloud2", "converters.slices", "converters.merger")
            assert not [t for t in targets if t.startswith(above)], mod


@pytest.mark.parametrize("short", sorted(importlib.import_module("converters").MOVED))
def test_short_public_paths_are_the_real_modules(short: str) -> None:
    import converters
    assert importlib.import_module(short) is importlib.import_module(converters.MOVED[short])


def test_short_path_of_a_submodule_is_not_a_second_copy() -> None:
    code = ("import converters.velodyne.calibration as a, converters.sources.velodyne.calibration"
            " as b, sys; assert a is b, (a, b); assert a.__spec__.name == b.__name__; "
            "assert 'rclpy' not in sys.modules; print('ok')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert out.stdout.strip() == "ok", out.stderr
