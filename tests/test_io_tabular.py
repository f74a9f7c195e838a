"""core.io.tabular: the helpers the readers share, and the one-way imports inside core.io."""

import ast
from pathlib import Path

import numpy as np
import pytest

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


# -- estimate_fps -------------------------------------------------------------------------------
def test_estimate_fps_float32_long_take():
    """Two hours of float32 seconds: steps are quantised by ~0.4 %, the median step is off, the
    rate counted over the span is not (glTF stores float32; this is what read_animation sees)."""
    t = (np.arange(300_000) / 30.0).astype(np.float32).astype(np.float64)
    assert abs(1 / np.median(np.diff(t)) - 30) > 0.05  # the median alone is wrong
    assert tabular.estimate_fps(t) == 30.0
    gappy = np.delete(t, [5, 6, 7, 150_000])
    assert tabular.estimate_fps(gappy) == 30.0
    assert tabular.estimate_fps(np.round(np.arange(100_000) / 60.0, 5)) == 60.0  # 5 printed decimals


def test_estimate_fps_snap_modes():
    t15 = (np.arange(500) / 15.0).astype(np.float32).astype(np.float64)
    assert tabular.estimate_fps(t15, snap="whole") == 15.0
    assert tabular.estimate_fps(t15) != 15.0 and tabular.estimate_fps(t15) == pytest.approx(15.0, rel=1e-6)
    ntsc = np.arange(500) * 1001 / 30000
    for snap in ("standard", "whole"):
        assert tabular.estimate_fps(ntsc, snap=snap) == 30000 / 1001  # the same float either way
    assert tabular.estimate_fps(np.arange(500) * 1001 / 15000, snap="whole") == 15000 / 1001
    assert tabular.estimate_fps(np.arange(100) / 60.003, snap="none") == pytest.approx(60.003, rel=1e-9)
    assert tabular.estimate_fps(np.arange(100) / 60.003) == 60.0  # 5e-5 off: snapped
    with pytest.raises(ValueError, match=r"snap: expected one of \('standard', 'whole', 'none'\), got 'int'"):
        tabular.estimate_fps(t15, snap="int")


# -- runs of rows, for messages -----------------------------------------------------------------
def test_runs_and_line_runs():
    mask = np.array([0, 1, 1, 0, 1, 0, 0, 1], bool)
    np.testing.assert_array_equal(tabular.runs(mask), [[1, 3], [4, 5], [7, 8]])
    assert tabular.runs(np.zeros(4, bool)).shape == (0, 2)
    lines = np.array([2, 3, 5, 6, 7, 9, 10, 12])  # blank lines 4, 8, 11 between the rows
    pairs = tabular.line_runs(mask, lines)
    assert pairs == ((3, 5), (7, 7), (12, 12))
    assert tabular.summarize_runs(pairs) == "3-5, 7, 12"
    assert tabular.summarize_runs(pairs, limit=1) == "3-5, ... (and 2 more)"
