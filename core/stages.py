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
PRIOR_METHODS = ("prior_pf", "spacetime", "geometric")
#: a shape whose largest marker displacement is below this fraction of the largest shape's
#: is invisible to the markers
INVISIBLE = 1e-3  # edits use it too, see EditSettings


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


def solver_shapes(rig, spec: str) -> list:
    """Indices of the target shapes the solvers may use: ``""`` all; ``"arkit"`` the shapes
    with a canonical ARKit name (all shapes when the rig has none); else comma-separated names."""
    from .names import ARKIT_NAMES, canonical

    spec = (spec or "").strip()
    if not spec:
        return list(range(rig.n_shapes))
    if spec.lower() == "arkit":
        idx = [i for i, n in enumerate(rig.names) if canonical(n) in ARKIT_NAMES]
        return idx or list(range(rig.n_shapes))
    return [rig.index(n.strip()) for n in spec.split(",") if n.strip()]


def run_calibrate(inputs, s, progress=None):
    ld, st = inputs["load"], inputs["stabilize"]
    rig = ld["target_rig"]
    idx = solver_shapes(rig, s.target_shapes)
    # shapes that move no marker (tongue, eyeball-only, empty shapes) cannot be determined from
    # markers: solving for them only injects noise (weights of 1e3 through near-null modes)
    layout = ld["target_layout"].select(st["names"])
    reach = np.linalg.norm(layout.points(rig.deltas), axis=2).max(1)
    unseen = [i for i in idx if reach[i] <= INVISIBLE * reach.max()]
    if unseen:
        warnings.warn(f"{len(unseen)} target shapes move no marker and stay at zero: "
                      + ", ".join(rig.names[i] for i in unseen[:8]) + (" ..." if len(unseen) > 8 else ""))
        idx = [i for i in idx if i not in set(unseen)]
    if len(idx) < rig.n_shapes:
        rig = rig.subset([rig.names[i] for i in idx])
    tm = target_markers(rig, ld["target_layout"], st["names"], st["source"].neutral, s.calibrate, s.rbf_smoothing)
    return {"target": tm, "deltas": tm.calibrated, "shape_index": np.asarray(idx), "rig": rig,
            "unseen": [ld["target_rig"].names[i] for i in unseen]}


def run_personalize(inputs, s, progress=None):
    """Actor-specific marker blendshapes by range-of-motion alignment (Ribera 2017 §4).

    The ROM take is the source itself unless ``rom`` names another capture of the same
    actor (its markers are matched by name and stabilised the same way).
    """
    cal = inputs["calibrate"]
    if not s.personalize:
        return {"deltas": cal["deltas"], "personalized": False}
    from .personalize import personalize

    st = inputs["stabilize"]
    src = st["source"]
    rom_deltas, rom_valid = src.deltas, src.valid
    if s.rom:
        from .io.performance import read_performance

        ld = inputs["load"]
        rom = source_markers(read_performance(s.rom), ld["source_rig"], ld["source_layout"], ld["name_map"])
        missing = [n for n in st["names"] if n not in rom.names]
        if missing:
            raise ValueError(f"{s.rom}: the range-of-motion take lacks markers {missing}")
        idx = [rom.names.index(n) for n in st["names"]]
        rom_deltas, rom_valid = rom.deltas[:, idx], rom.valid[:, idx]
    out = personalize(rom_deltas, cal["deltas"], src.neutral, names=st["names"], rig_deltas=cal["target"].deltas,
                      valid=rom_valid, beta=s.align_beta, gamma=s.align_gamma)
    return {"deltas": out.deltas, "personalized": True, "diagnostics": out}


def run_segment(inputs, s, progress=None):
    """Regions of the target rig and per-region marker weights (Liu 2011 §3.2.1–3.2.2)."""
    from .segment import marker_weights, segment

    rig = inputs["calibrate"]["rig"]
    layout = inputs["load"]["target_layout"].select(inputs["calibrate"]["target"].names)
    seg = segment(rig, n_regions=s.regions, min_size=max(1, int(round(s.min_region_size * rig.n_vertices))),
                  smooth_iters=s.mask_smoothing)
    report(progress, 0.8, "marker weights")
    from .solvers.local import masks_at

    return {"labels": seg.labels, "masks": seg.masks, "marker_weights": marker_weights(rig, layout, seg.masks),
            "marker_masks": masks_at(layout, seg.masks), "info": dict(seg.info)}


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
        W = baselines.range_pf(B, S, s.lower, s.upper, valid, ridge=s.ridge)
    elif m == "range_pf":
        W = baselines.range_pf(B, S, valid=valid, ridge=s.ridge)  # the paper's -0.5 <= w <= 1.5
    elif m == "prior_pf":
        W = baselines.prior_pf(B, S, s.alpha, _prior(inputs), valid, ridge=s.ridge)
    elif m == "spacetime":
        from .solvers.spacetime import SpacetimeSolver

        known = None
        if s.boundary == "perframe":
            ends = baselines.prior_pf(B, S[[0, -1]], s.alpha, _prior(inputs), valid[[0, -1]], ridge=s.ridge)
            known = {0: ends[0], len(S) - 1: ends[1]}
        solver = SpacetimeSolver(B, S, alpha=s.alpha, beta=s.beta, prior=_prior(inputs), known=known,
                                 boundary="none" if s.boundary == "none" else "neutral", valid=valid,
                                 ridge=s.ridge if s.ridge > 0 else "auto")
        W = solver.solve()
        info = {"path": solver.method_}
    elif m == "local":
        from .solvers.local import blend_weights, local_precompute, smooth_weights

        seg = inputs["segment"]
        problem = local_precompute(np.zeros_like(st.neutral), B, seg["marker_weights"], constraint=s.constraint)
        U = problem.solve(S, valid)  # (T, R, K) regional weights, eq. 2
        if s.local_temporal == "spacetime":  # movement matching per region, ends from the QP
            from .solvers.local import local_spacetime

            U = local_spacetime(B, S, seg["marker_weights"], U, s.alpha, s.beta, valid)
        if s.sigma > 0:
            U = smooth_weights(U, s.sigma)
        W = blend_weights(U, seg["masks"])
        from .solvers.local import reconstruct_markers

        # eq. 3 at the markers: what the mask-blended meshes show (the blended curves are a summary)
        predicted = reconstruct_markers(np.zeros_like(st.neutral), B, U, seg["marker_masks"])
        info = {"region_weights": U, "masks": seg["masks"], "predicted": predicted}
    elif m == "geometric":
        from .solvers.geometric import GeometricSolver

        kw = {"rig": inputs["calibrate"]["rig"]} if s.geometric_prior == "geometric" else {}
        if s.geometric_prior == "pca":
            from .solvers.spacetime import _prior_quadratic
            from .model import flatten

            P, q, _ = _prior_quadratic(_prior(inputs), flatten(B).T, len(B))
            kw = {"gram": P, "linear": -q}
        frames = S
        if not valid.all():  # the L1 solver needs complete frames: fill gaps with the No Const fit
            fill = np.einsum("tk,kmc->tmc", baselines.no_const(B, S, valid), B)
            frames = np.where(valid[..., None], S, fill)
            warnings.warn(f"geometric: {int((~valid).sum())} missing marker samples filled by the per-frame fit")
        sol = GeometricSolver(B, s.geometric_prior, mu=s.mu, lam=s.lam, **kw).solve(frames)
        W = sol.weights
        info = {"iterations": sol.iterations}
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
                             known={0: W[0], len(W) - 1: W[-1]}, valid=st.valid, names=inputs["calibrate"]["rig"].names)
    return {"weights": solver.edit(W, edits=edits), "edits": list(s.edits)}


def run_synthesize(inputs, s, progress=None):
    """Target markers, and the weights for every shape of the target rig (shapes the solver
    did not use, see ``target_shapes``, stay at zero)."""
    cal = inputs["calibrate"]
    tm = cal["target"]
    Wsub = inputs["edit"]["weights"]
    W = np.nan_to_num(Wsub)
    markers = tm.neutral[None] + (W @ tm.deltas.reshape(len(tm.deltas), -1)).reshape((len(W),) + tm.neutral.shape)
    full = np.zeros((len(Wsub), inputs["load"]["target_rig"].n_shapes))
    full[:, cal["shape_index"]] = Wsub
    return {"target_markers": markers, "weights": full}


def run_evaluate(inputs, s, progress=None):
    from .evaluate import evaluate

    st = inputs["stabilize"]["source"]
    predicted = inputs["solve"]["info"].get("predicted") if not inputs["edit"]["edits"] else None
    return evaluate(inputs["personalize"]["deltas"], inputs["edit"]["weights"], st.deltas, st.valid, step=s.jitter_window,
                    predicted=predicted)
