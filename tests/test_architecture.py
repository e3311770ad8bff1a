"""The import graph: one namespace, layers that only import downward, no cycle, small files.

Layers, bottom to top (README "Architecture"):

    core -> io -> stages (reconstruction -> mapping -> detection -> evaluation; simulation
    alone) -> pipeline -> cli / viewer

A short AST pass over every module of the installed package (symlinked stage folders
included) reads every import, lazy imports inside functions and ``TYPE_CHECKING`` blocks too,
so a lazy import cannot hide an arrow that points up.
"""

from __future__ import annotations

import ast
import os
from collections import defaultdict
from pathlib import Path

import pytest

import roadsurf

PKG_DIR = Path(roadsurf.__file__).parent
REPO = Path(__file__).resolve().parents[1]

# what each part of the package may import (besides itself); anything else is an upward arrow
ALLOWED: dict[str, set[str]] = {
    "core": set(),
    "io": {"core"},
    "reconstruction": {"core", "io"},
    "simulation": {"core", "io"},
    "mapping": {"core", "io", "reconstruction"},
    "detection": {"core", "io", "reconstruction", "mapping"},
    "evaluation": {"core", "io", "reconstruction", "mapping", "detection", "simulation"},
    "pipeline": {"core", "io", "reconstruction", "mapping", "detection", "evaluation"},
    "viewer": {"core", "io", "reconstruction", "mapping", "detection", "evaluation", "pipeline"},
    "cli": {
        "core",
        "io",
        "reconstruction",
        "mapping",
        "detection",
        "evaluation",
        "simulation",
        "pipeline",
        "viewer",
    },  # fmt: skip
    "": {"cli"},  # roadsurf/__init__.py, __main__.py
}
# generic top-level names the stage folders had before they moved under roadsurf
STRAY_TOP_LEVEL = {"reconstruction", "mapping", "detection", "simulation", "viewer", "evaluation"}
MAX_LINES = 500


def _modules() -> dict[str, Path]:
    """Dotted module name -> file, following the stage-folder symlinks like the importer does."""
    out: dict[str, Path] = {}
    for dirpath, _dirs, files in os.walk(PKG_DIR, followlinks=True):
        rel = Path(dirpath).relative_to(PKG_DIR)
        if "__pycache__" in rel.parts:
            continue
        for f in files:
            if not f.endswith(".py"):
                continue
            parts = ["roadsurf", *rel.parts]
            if f != "__init__.py":
                parts.append(f[:-3])
            out[".".join(parts)] = Path(dirpath) / f
    return out


def _imports(path: Path, module: str, is_pkg: bool) -> list[tuple[str, int]]:
    """Every imported name (dotted) with its line, relative imports resolved."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    found: list[tuple[str, int]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                pkg = module.split(".") if is_pkg else module.split(".")[:-1]
                pkg = pkg[: len(pkg) - (node.level - 1)]
                base = ".".join([*pkg, base] if base else pkg)
            found.append((base, node.lineno))
            found += [(f"{base}.{a.name}", node.lineno) for a in node.names if a.name != "*"]
    return found


def _graph() -> tuple[dict[str, set[str]], list[str]]:
    mods = _modules()
    edges: dict[str, set[str]] = defaultdict(set)
    stray: list[str] = []
    for mod, path in mods.items():
        for name, line in _imports(path, mod, path.name == "__init__.py"):
            top = name.split(".")[0]
            if top in STRAY_TOP_LEVEL:
                stray.append(f"{path}:{line} imports {name} (use roadsurf.{name})")
            if top == "benchmarks":
                stray.append(
                    f"{path}:{line} imports {name} (benchmarks are not part of the package)"
                )
            if top != "roadsurf":
                continue
            # longest prefix that is a module: `from roadsurf.x import y` may name module x.y
            while name and name not in mods:
                name = name.rpartition(".")[0]
            if name and name != mod:
                edges[mod].add(name)
    return edges, stray


def _part(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in ALLOWED else ""


def test_no_generic_top_level_imports() -> None:
    _, stray = _graph()
    assert not stray, "\n".join(stray)


def test_layers_only_import_downward() -> None:
    edges, _ = _graph()
    bad = []
    for src, dsts in sorted(edges.items()):
        ps = _part(src)
        for dst in sorted(dsts):
            pd = _part(dst)
            if pd != ps and pd not in ALLOWED[ps]:
                bad.append(
                    f"{src} -> {dst}  ({ps or 'roadsurf'} may not import {pd or 'roadsurf'})"
                )
    assert not bad, "upward or sideways imports:\n" + "\n".join(bad)


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = 0
    nodes = set(edges) | {d for ds in edges.values() for d in ds}
    for root in sorted(nodes):
        if root in index:
            continue
        work = [(root, iter(sorted(edges.get(root, ()))))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on.add(root)
        while work:
            node, it = work[-1]
            nxt = next(it, None)
            if nxt is not None:
                if nxt not in index:
                    index[nxt] = low[nxt] = counter
                    counter += 1
                    stack.append(nxt)
                    on.add(nxt)
                    work.append((nxt, iter(sorted(edges.get(nxt, ())))))
                elif nxt in on:
                    low[node] = min(low[node], index[nxt])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                comp = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.append(w)
                    if w == node:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


def test_no_import_cycles() -> None:
    edges, _ = _graph()
    cycles = _cycles(edges)
    assert not cycles, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_cycle_finder_finds_a_cycle() -> None:
    """The checks above can fail: a planted cycle and an upward arrow are reported."""
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert "mapping" not in ALLOWED["reconstruction"]


def test_stage_packages_live_in_the_design_card_folders() -> None:
    for name in ("reconstruction", "mapping", "detection", "viewer"):
        assert (REPO / name / "__init__.py").is_file(), name
        assert (PKG_DIR / name).resolve() == (REPO / name).resolve(), name


@pytest.mark.parametrize("top", ["roadsurf", "benchmarks"])
def test_no_source_file_over_the_line_limit(top: str) -> None:
    files = _modules().values() if top == "roadsurf" else (REPO / top).rglob("*.py")
    long = []
    for p in sorted(files):
        n = len(p.read_text(encoding="utf-8").splitlines())
        if n > MAX_LINES:
            long.append(f"{p}: {n} lines")
    assert not long, f"files over {MAX_LINES} lines (split them by responsibility):\n" + "\n".join(
        long
    )
