#!/usr/bin/env python
"""The project's import graph, read from the code: package-to-package arrows, and what breaks the layers.

    python tools/import_graph.py            # the arrows between packages and any violation
    python tools/import_graph.py --check    # exit 1 on a violation (the test suite runs this)
    python tools/import_graph.py --modules  # every module-to-module arrow too

The layers, bottom up: ``lckit`` <- ``lcsim`` <- ``lcdata`` <- ``lcmodels`` <- ``lccli`` <- ``tools``, ``experiments``.
Every import counts, also one inside a function or under ``TYPE_CHECKING``. A violation is an arrow that
runs up a layer, a circle of modules that import each other, or a private name (``_x``) imported from
another package.
"""

from __future__ import annotations

import argparse
import ast
import collections
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
LAYERS = {"lckit": 0, "lcsim": 1, "lcdata": 2, "lcmodels": 3, "lccli": 4, "tools": 5, "experiments": 5}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def read_imports(root: Path = ROOT) -> tuple[dict[str, set[str]], list[str]]:
    """``(module -> project modules it imports, private names imported across packages)``."""
    files = [p for pkg in LAYERS for p in (root / pkg).rglob("*.py")
             if "test_" not in p.name and p.name != "conftest.py" and not p.name.endswith("_pb2.py")]  # fmt: skip
    modules = {module_name(p) for p in files}
    edges: dict[str, set[str]] = collections.defaultdict(set)
    private: list[str] = []
    for path in files:
        me = module_name(path)
        package = me.split(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            targets: list[tuple[str, list[str]]] = []
            if isinstance(node, ast.Import):
                targets = [(a.name, []) for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                targets = [(node.module, [a.name for a in node.names])]
            elif isinstance(node, ast.ImportFrom) and node.level > 0:  # relative: inside one package
                base = me.split(".")[: -node.level if path.name != "__init__.py" else len(me.split(".")) - node.level + 1]
                targets = [(".".join([*base, node.module] if node.module else base), [a.name for a in node.names])]
            for target, names in targets:
                if target.split(".")[0] not in LAYERS:
                    continue
                hit = max((m for m in modules if target == m or target.startswith(m + ".")), key=len, default=None)
                for name in names:  # `from pkg import module` names a module
                    if f"{target}.{name}" in modules:
                        hit = f"{target}.{name}"
                    elif name.startswith("_") and target.split(".")[0] != package:
                        private.append(f"{me} imports {target}.{name}")
                if hit is not None and hit != me:
                    edges[me].add(hit)
    return edges, private


def circles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected sets of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(edges.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                out.append(sorted(group))

    sys.setrecursionlimit(10_000)
    for v in sorted(set(edges) | {w for ws in edges.values() for w in ws}):
        if v not in index:
            visit(v)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="exit 1 when a layer is broken")
    ap.add_argument("--modules", action="store_true", help="print every module-to-module arrow")
    args = ap.parse_args(argv)
    edges, private = read_imports()
    packages: collections.Counter[tuple[str, str]] = collections.Counter()
    upward = []
    for a, targets in sorted(edges.items()):
        for b in sorted(targets):
            pa, pb = a.split(".")[0], b.split(".")[0]
            if pa != pb:
                packages[(pa, pb)] += 1
            if LAYERS[pb] > LAYERS[pa]:
                upward.append(f"{a} -> {b}")
            if args.modules:
                print(f"{a} -> {b}")
    print("package arrows (module imports):")
    for (pa, pb), n in sorted(packages.items(), key=lambda kv: (-LAYERS[kv[0][0]], kv[0])):
        print(f"  {pa:12s} -> {pb:10s} {n}")
    found = circles(edges)
    print(f"upward arrows: {len(upward)}" + "".join(f"\n  {u}" for u in upward))
    print(f"circles: {len(found)}" + "".join(f"\n  {' <-> '.join(c)}" for c in found))
    print(f"private names across packages: {len(private)}" + "".join(f"\n  {p}" for p in private))
    return 1 if args.check and (upward or found or private) else 0


if __name__ == "__main__":
    sys.exit(main())
