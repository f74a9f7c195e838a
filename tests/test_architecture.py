"""The shape of the package: no import circle among core's modules, counting imports made inside
functions too (they hide a circle, they do not remove it), and core never imports the dashboard
or Panel at import time."""

from __future__ import annotations

import ast
from pathlib import Path

import networkx as nx

from datapaths import ROOT

CORE = ROOT / "core"


def _module(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path):
    """``(module imported, at module level)`` for every import of ``path``, relative ones resolved."""
    mod = _module(path)
    package = mod if path.name == "__init__.py" else mod.rsplit(".", 1)[0]
    tree = ast.parse(path.read_text())
    top = set(map(id, tree.body))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield a.name, id(node) in top
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")
                up = up[:len(up) - node.level + 1]
                base = ".".join(up + ([base] if base else []))
            for a in node.names:  # `from . import x` may name a module
                yield f"{base}.{a.name}", id(node) in top
            yield base, id(node) in top


def _graph():
    modules = {_module(p): p for p in CORE.rglob("*.py")}
    g = nx.DiGraph()
    g.add_nodes_from(modules)
    for mod, path in modules.items():
        for target, _ in _imports(path):
            while target and target not in modules:  # core.solvers.local.masks_at -> core.solvers.local
                target = target.rpartition(".")[0]
            if target and target != mod and not mod.startswith(target + "."):  # a package's own __init__
                g.add_edge(mod, target)
    return g


def test_no_import_circle_in_core():
    circles = [sorted(c) for c in nx.strongly_connected_components(_graph()) if len(c) > 1]
    assert not circles, f"import circles among core's modules: {circles}"


def test_the_graph_sees_imports_inside_functions():
    """The check can fail: an import inside a function is an arrow like any other."""
    g = _graph()
    assert g.has_edge("core.cli", "core.pipeline") and g.has_edge("core.stages.methods", "core.solvers.spacetime")


def test_core_never_imports_the_dashboard_at_import_time():
    for path in CORE.rglob("*.py"):
        for target, at_top in _imports(path):
            if at_top:
                assert not target.split(".")[0] in ("panel", "dashboard", "bokeh"), f"{path}: imports {target}"
