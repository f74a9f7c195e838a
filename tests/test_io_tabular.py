"""core.io.tabular: the helpers the readers share, and the one-way imports inside core.io."""

import ast
from pathlib import Path

import core.io.performance as performance
import core.io.tabular as tabular

IO = Path(tabular.__file__).parent


def _io_imports(path: Path) -> set:
    """The core.io modules ``path`` imports (top level or inside functions)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            base = ["core", "io"][: max(0, 3 - node.level)] if node.level else []
            mod = ".".join(base + [node.module])
            if mod == "core.io":
                out |= {f"core.io.{a.name}" for a in node.names}
            elif mod.startswith("core.io."):
                out.add(mod)
        elif isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.startswith("core.io.")}
    return out - {f"core.io.{path.stem}"}


def test_core_io_imports_have_no_cycle():
    graph = {f"core.io.{p.stem}": _io_imports(p) for p in IO.glob("*.py") if p.stem != "__init__"}
    assert graph.get("core.io.tabular") == set()
    for fmt in ("livelink", "markers", "gltf"):
        assert "core.io.performance" not in graph[f"core.io.{fmt}"], fmt
    seen, done = set(), set()

    def visit(m, path):
        assert m not in seen - done, f"import cycle: {' -> '.join(path + [m])}"
        if m in done:
            return
        seen.add(m)
        for d in graph.get(m, ()):
            visit(d, path + [m])
        done.add(m)

    for m in graph:
        visit(m, [])


def test_performance_reexports_the_shared_helpers():
    for name in ("DataQualityWarning", "estimate_fps", "parse_cells", "checked_rows", "summarize_rows",
                 "STANDARD_FPS", "FPS_SNAP_RTOL"):
        assert getattr(performance, name) is getattr(tabular, name)
        assert name in performance.__all__
