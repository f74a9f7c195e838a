"""The solvers' shared input checks (core/solvers/inputs.py) and the direction of the solver imports."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from core.solvers.baselines import range_pf
from core.solvers.inputs import as_bounds, as_coupling, as_zero_mask
from core.solvers.spacetime import SpacetimeSolver

ROOT = Path(__file__).resolve().parents[1]


def test_bounds_one_check_for_every_solver():
    lo, hi = as_bounds(None, 1.0, 3)
    assert np.array_equal(lo, [-np.inf] * 3) and np.array_equal(hi, [1.0] * 3)
    lo, hi = as_bounds([0.0, -0.5, 0.0], 2.0, 3, "range_pf", finite=True)
    assert np.array_equal(lo, [0.0, -0.5, 0.0]) and np.array_equal(hi, [2.0] * 3)
    with pytest.raises(ValueError, match=r"^range_pf: bounds must be finite"):
        as_bounds(None, 1.0, 3, "range_pf", finite=True)
    with pytest.raises(ValueError, match=r"^lower must be <= upper for every shape: shape 1 has lower=2 > upper=1"):
        as_bounds([0, 2, 0], 1.0, 3)
    with pytest.raises(ValueError, match=r"^lower: must not be NaN"):
        as_bounds(np.nan, 1.0, 3)
    with pytest.raises(ValueError, match=r"^range_pf: upper: expected a number or \(3,\)"):
        as_bounds(0.0, [1.0, 1.0], 3, "range_pf")
    # the same check behind both solvers that take bounds
    rng = np.random.default_rng(0)
    B, S = rng.normal(size=(3, 4, 3)), rng.normal(size=(5, 4, 3))
    with pytest.raises(ValueError, match=r"^range_pf: lower must be <= upper .* shape 2"):
        range_pf(B, S, lower=[0, 0, 1], upper=0.5)
    with pytest.raises(ValueError, match=r"^lower must be <= upper .* shape 2"):
        SpacetimeSolver(B, S, lower=[0, 0, 1], upper=0.5, known={0: np.zeros(3)})


def test_coupling_and_zero_mask():
    Q = np.array([[1.0, -1.0], [-1.0, 1.0]])
    assert np.array_equal(as_coupling(Q, 2, 3.0), 3.0 * Q)
    assert as_coupling(None, 2, 3.0) is None
    with pytest.raises(ValueError, match=r"^prior_pf: quadratic: must be symmetric"):
        as_coupling(np.array([[1.0, 0.5], [0.0, 1.0]]), 2, 1.0, "prior_pf")
    with pytest.raises(ValueError, match=r"^quadratic: must be positive semi-definite"):
        as_coupling(-np.eye(2), 2, 1.0)
    with pytest.raises(ValueError, match=r"^quadratic: expected a \(3, 3\) matrix"):
        as_coupling(Q, 3, 1.0)
    z = as_zero_mask(np.array([True, False]), 4, 2, "range_pf")
    assert z.shape == (4, 2) and z[:, 0].all() and not z[:, 1].any()
    assert as_zero_mask(np.zeros(2, bool), 4, 2) is None
    with pytest.raises(ValueError, match=r"^range_pf: zero must be a bool mask"):
        as_zero_mask(np.zeros(2), 4, 2, "range_pf")


@pytest.mark.parametrize("module, not_loaded", [
    ("core.solvers.bounded_spacetime", "core.solvers.spacetime"),  # the bounded solve works on any RangeSystem
    ("core.solvers.qp", "core.solvers.local"),  # the QP kernels know nothing of Liu's regions
    ("core.solvers.spacetime", "core.solvers.reference"),  # references are for tests and benchmarks only
    ("core.solvers.local", "core.solvers.reference"),
])
def test_solver_imports_point_one_way(module, not_loaded):
    """Importing a solver module on its own does not load the module above it (no arrow back up)."""
    code = f"import sys, {module}; print({not_loaded!r} in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True,
                         env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    assert out.stdout.strip() == "False", out.stderr
