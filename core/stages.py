"""The pipeline's stage functions: ``run(inputs, settings, progress) -> result``.

Each is pure: it reads its upstream results (``inputs[stage name]``) and its settings and
returns a new dict; the pipeline caches and freezes it. Method modules are imported inside
the functions that use them, so a missing optional piece fails only the method that needs it.
"""

from __future__ import annotations

import warnings

import numpy as np

from .model import Performance
from .progress import report
from .retarget import common_markers, source_markers, target_markers

#: methods that use the PCA prior stage
PRIOR_METHODS = ("prior_pf", "spacetime")  # edits use it too, see EditSettings


def run_load(inputs, s, progress=None):
    from .io.performance import read_performance
    from .io.rigs import load_rig, read_layout_for
    from .names import NameMap

    if not s.source:
        raise ValueError("no source performance chosen (--source)")
    if not s.target_rig:
        raise ValueError("no target rig chosen (--target-rig)")
    report(progress, 0.1, "reading source")
    source = read_performance(s.source)
    source_rig = load_rig(s.source_rig) if s.source_rig else None
    if source.kind == "curves" and source_rig is None:
        raise ValueError(f"{s.source}: weight curves need the rig they drive (--source-rig)")
    report(progress, 0.4, "reading target rig")
    target_rig = load_rig(s.target_rig)
    source_layout = read_layout_for(s.source_layout, s.source_rig, source_rig) if source_rig is not None else None
    target_layout = read_layout_for(s.target_layout, s.target_rig, target_rig)
    name_map = NameMap.from_json(s.name_map) if s.name_map else None
    return {"source": source, "source_rig": source_rig, "source_layout": source_layout,
            "target_rig": target_rig, "target_layout": target_layout, "name_map": name_map}


def run_stabilize(inputs, s, progress=None):
    ld = inputs["load"]
    src: Performance = ld["source"]
    last = src.n_frames if s.last_frame < 0 else min(s.last_frame + 1, src.n_frames)
    if not 0 <= s.first_frame < last:
        raise ValueError(f"frame range [{s.first_frame}, {s.last_frame}] is empty for {src.n_frames} frames")
    if s.first_frame or last != src.n_frames:
        src = src.frames(s.first_frame, last)
    sm = source_markers(src, ld["source_rig"], ld["source_layout"], ld["name_map"], s.head_motion,
                        min(s.neutral_frame, src.n_frames - 1))
    names = common_markers(sm.names, ld["target_layout"])
    idx = [sm.names.index(n) for n in names]
    from dataclasses import replace

    sm = replace(sm, deltas=sm.deltas[:, idx], valid=sm.valid[:, idx], neutral=sm.neutral[idx], names=tuple(names))
    return {"source": sm, "names": tuple(names)}


def run_calibrate(inputs, s, progress=None):
    ld, st = inputs["load"], inputs["stabilize"]
    tm = target_markers(ld["target_rig"], ld["target_layout"], st["names"], st["source"].neutral, s.calibrate, s.rbf_smoothing)
    return {"target": tm, "deltas": tm.calibrated}


def run_personalize(inputs, s, progress=None):
    cal = inputs["calibrate"]
    if not s.personalize:
        return {"deltas": cal["deltas"], "personalized": False}
    from .personalize import personalize_markers  # Ribera 2017 §4

    st = inputs["stabilize"]
    out = personalize_markers(st["source"], cal["deltas"], st["names"], beta=s.align_beta, gamma=s.align_gamma,
                              rom=s.rom or None, progress=progress)
    return {"deltas": out["deltas"], "personalized": True, "diagnostics": out}


def run_segment(inputs, s, progress=None):
    from .segment import segment_rig  # Liu 2011 §3.2.1

    ld = inputs["load"]
    return segment_rig(ld["target_rig"], ld["target_layout"].select(inputs["calibrate"]["target"].names),
                       n_regions=s.regions, min_size=s.min_region_size, smooth_iters=s.mask_smoothing)


def run_prior(inputs, s, progress=None):
    from .prior import PCAPrior  # Seol 2012 §5

    deltas = inputs["personalize"]["deltas"]
    return {"prior": PCAPrior().fit(deltas)}


def _prior(inputs):
    return inputs["prior"]["prior"] if inputs.get("prior") else None


def run_solve(inputs, s, progress=None):
    from .solvers import baselines

    st = inputs["stabilize"]["source"]
    B = inputs["personalize"]["deltas"]
    S, valid = st.deltas, st.valid
    m = s.method
    info = {}
    if m == "lsq":
        W = baselines.no_const(B, S, valid)
    elif m == "bounded":
        W = baselines.range_pf(B, S, s.lower, s.upper, valid)
    elif m == "range_pf":
        W = baselines.range_pf(B, S, valid=valid)  # the paper's -0.5 <= w <= 1.5
    elif m == "prior_pf":
        W = baselines.prior_pf(B, S, s.alpha, _prior(inputs), valid)
    elif m == "spacetime":
        from .solvers.spacetime import SpacetimeSolver

        known = None
        if s.boundary == "perframe":
            ends = baselines.prior_pf(B, S[[0, -1]], s.alpha, _prior(inputs), valid[[0, -1]])
            known = {0: ends[0], len(S) - 1: ends[1]}
        solver = SpacetimeSolver(B, S, alpha=s.alpha, beta=s.beta, prior=_prior(inputs), known=known,
                                 boundary="none" if s.boundary == "none" else "neutral", valid=valid)
        W = solver.solve()
        info = {"path": solver.method_}
    elif m == "local":
        from .solvers.local import solve_local

        out = solve_local(B, S, inputs["segment"], valid=valid, sigma=s.sigma, progress=progress)
        W, info = out["weights"], out
    elif m == "geometric":
        from .solvers.geometric import solve_geometric

        W = solve_geometric(B, S, inputs["load"]["target_rig"], mu=s.mu, lam=s.lam, valid=valid)
    else:  # pragma: no cover - param.Selector guards this
        raise ValueError(f"unknown method {m!r}")
    W = np.asarray(W, dtype=np.float64)
    # the prior/Sobolev weights later edits propagate with: this method's own when it has them
    alpha = s.alpha if m in PRIOR_METHODS else s.param.alpha.default
    beta = s.beta if m == "spacetime" else 0.0
    return {"weights": W, "method": m, "info": info, "alpha": alpha, "beta": beta}


def run_edit(inputs, s, progress=None):
    """Spacetime edits (Seol 2012 §6) on top of any method's solution."""
    W = inputs["solve"]["weights"]
    if not s.edits:
        return {"weights": W, "edits": []}
    from .solvers.spacetime import Edit, SpacetimeSolver

    st = inputs["stabilize"]["source"]
    edits = []
    for e in s.edits:
        win = e.get("window")
        shapes = list(e["weights"]) if isinstance(e["weights"], dict) else e.get("shapes")
        values = list(e["weights"].values()) if isinstance(e["weights"], dict) else e["weights"]
        edits.append(Edit(int(e["frame"]), np.asarray(values, float), shapes, tuple(win) if win else None))
    sol = inputs["solve"]
    solver = SpacetimeSolver(inputs["personalize"]["deltas"], st.deltas, alpha=sol["alpha"], beta=sol["beta"], prior=_prior(inputs),
                             known={0: W[0], len(W) - 1: W[-1]}, valid=st.valid, names=inputs["load"]["target_rig"].names)
    return {"weights": solver.edit(W, edits=edits), "edits": list(s.edits)}


def run_synthesize(inputs, s, progress=None):
    tm = inputs["calibrate"]["target"]
    W = np.nan_to_num(inputs["edit"]["weights"])
    markers = tm.neutral[None] + (W @ tm.deltas.reshape(len(tm.deltas), -1)).reshape((len(W),) + tm.neutral.shape)
    return {"target_markers": markers, "weights": inputs["edit"]["weights"]}


def run_evaluate(inputs, s, progress=None):
    from .evaluate import evaluate

    st = inputs["stabilize"]["source"]
    return evaluate(inputs["personalize"]["deltas"], inputs["edit"]["weights"], st.deltas, st.valid, step=s.jitter_window)
