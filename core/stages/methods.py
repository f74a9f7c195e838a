"""The solve methods: each registers itself with the settings it reads and the stages it needs.

``@solve_method(name, params=..., needs=...)`` puts a method into :data:`METHODS`; the solve
stage's ``method`` choices, its cache key (``relevant``), the CLI's ``--method`` choices, which
optional stages run (``prior``, ``segment``) and which widgets the dashboard shows all derive
from these declarations — nothing else lists the methods.

A method's function takes the solve stage's inputs (``load``, ``frames``, ``stabilize``,
``personalize``, ``shapes``, ``segment``, ``prior``) and its frozen settings ``s`` and returns
``{"weights": (T, K), "info": {...}, "edit": {...}}`` for the solver's K shapes; ``edit`` holds
the options a later spacetime edit (Seol 2012 §6) is solved with — the method's own bounds and
regularisers (:func:`edit_options`), so an edit of a bounded result stays inside its bounds. ``dense`` methods (Xu 2014 transfer) do not solve for the
target's shapes at all: the dense stages (:mod:`core.stages.dense`) compute a new rig instead.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np
import scipy.linalg

from ..eyes import gaze_mapped, gaze_rows
from ..gaps import fill_gaps
from ..model import flatten
from ..motion_alignment import apply_alignment
from ..examples import choose_by_loo, learn_from_poses, poses_from_items, suggest_poses
from ..names import NameMap, recognise
from ..prior import prior_quadratic
from ..shape_matching import (SPARSE_L1, aligned_shape_map, jaw_rescaled_map, mapped_weights, match_shapes,
                              restyled_motion)
from ..solvers import baselines
from ..solvers.geometric import GeometricSolver
from ..solvers.local import blend_weights, local_precompute, local_spacetime, reconstruct_markers, smooth_weights
from ..solvers.spacetime import SpacetimeSolver

#: method name -> Method, in registration order
METHODS: dict = {}


#: what a method may honour of the production controls (:mod:`core.controls`), besides the
#: per-shape gain and offset every method's result gets after the solve (:class:`~.retarget.Synthesize`)
CAPABILITIES = {
    "bounds": "solves within each shape's lower…upper (the controls' table over lowest…highest)",
    "active": "holds the shapes switched off at zero while solving",
    "symmetry": "takes the symmetry pairs' term (symmetry_weight)",
    "cancel": "re-solves with the weaker shape of a cancel pair held at zero (cancel_threshold)",
    "filter": "is a per-frame result the jitter filter (weights_filter) smooths",
}


@dataclass(frozen=True)
class Method:
    """A registered solve method (see the module docstring).

    ``params`` are the solve stage's settings the method reads; ``honours`` which of
    :data:`CAPABILITIES` it implements. The two are the whole declaration: the solve stage's key
    and what its ``run`` may read derive from them (:meth:`core.stages.retarget.Solve.relevant`),
    so no other place lists methods by name."""

    name: str
    run: Callable
    params: tuple = ()
    needs: tuple = ()
    dense: bool = False
    doc: str = ""
    label: str = ""
    honours: frozenset = frozenset()
    #: the method chooses its own configuration from the pair and the take (``auto``): the stages
    #: before the solve derive their settings for it (``Stage.derived``: the range-of-motion match)
    chooses: bool = False
    #: ``run`` takes ``warm=``: the (T, K) weights of the solve stage's last result, where an
    #: iterative solve may start (the result must not depend on it)
    warm: bool = False


def solve_method(name: str, params=(), needs=(), dense: bool = False, label: str = "", honours=(), chooses: bool = False,
                 warm: bool = False):
    """Decorator: register ``fn(inputs, s) -> {"weights", "info", "edit"}`` as method ``name``;
    ``label`` is what a person reads in the method list (plain words first, the paper after);
    ``honours`` names the :data:`CAPABILITIES` it implements; ``warm``: ``fn`` also takes ``warm=``
    (see :attr:`Method.warm`)."""

    def deco(fn):
        if name in METHODS:
            raise ValueError(f"solve method {name!r} registered twice")
        unknown = set(honours) - set(CAPABILITIES)
        if unknown:
            raise ValueError(f"solve method {name!r}: unknown capabilities {sorted(unknown)}; known: {sorted(CAPABILITIES)}")
        METHODS[name] = Method(name, fn, tuple(params), tuple(needs), dense, (fn.__doc__ or "").strip(), label or name,
                               frozenset(honours), chooses, warm)
        return fn

    return deco


def method_of(cfg) -> Method:
    """The method a settings snapshot chooses."""
    return METHODS[cfg.solve.method]


def edit_options(s, alpha=None, lower=None, upper=None, l1=0.0, name_weight=0.0, beta=0.0) -> dict:
    """The spacetime options an edit of this method's result is solved with: its prior weight
    (the default alpha for methods without one), Sobolev weight, ridge, bounds (None: unbounded;
    scalars or per shape), L1, name weight, and the symmetry pairs' quadratic (the controls')."""
    return {"alpha": float(s.alpha if alpha is None else alpha), "beta": float(beta),
            "ridge": float(s.ridge) if s.ridge > 0 else "auto", "lower": lower, "upper": upper,
            "l1": float(l1), "name_weight": float(name_weight), "quadratic": getattr(s, "quadratic", None)}


def named_target(inputs, exclusive: bool = False) -> "np.ndarray | None":
    """``W_named`` (T, K_solver): each solver shape's estimate from the source curves through its
    name (:meth:`core.names.NameMap.automatic` with the ``vocabulary`` stage's vocabularies: the
    same canonical ARKit name, or a vocabulary's combination of ARKit shapes), NaN for shapes
    without one; gaps (tracking loss) filled as everywhere (:mod:`core.gaps`). None unless the
    source is weight curves with a namesake. ``exclusive``: each ARKit channel drives one shape at
    most (driving a rig, the ``names`` method); off, every recognised shape gets its own estimate
    (a per-shape pull, the name prior)."""
    src = inputs["load"]["source"]
    if src.kind != "curves":
        return None
    rig = inputs["shapes"]["rig"]
    G = NameMap.automatic(src.names, rig.names, vocabularies=inputs["vocabulary"]["vocabularies"],
                          exclusive=exclusive).matrix(src.names, rig.names)  # (K, C)
    named = np.abs(G).sum(1) > 0
    if not named.any():
        return None
    fr = inputs["frames"]
    part = src.frames(fr["first"], fr["stop"])
    valid = part.valid.all(1)
    W = fill_gaps(np.where(part.valid, part.data, 0.0) @ G.T, valid)
    W[:, ~named] = np.nan
    return W


def _prior(inputs):
    return inputs["prior"]["prior"] if inputs.get("prior") else None


def _markers(inputs):
    """``(B (K, M, 3), S (T, M, 3), valid (T, M))`` the solvers fit (the source's motion as the
    calibrate stage passes it on: range-of-motion scaled or not)."""
    st = inputs["calibrate"]["source"]
    return inputs["personalize"]["deltas"], st.deltas, st.valid


def _marker_weights(inputs):
    """(M,) per-point weights of dense correspondence (how well the registration fits there), or None."""
    return inputs["shapes"].get("weights")


def weighted_markers(inputs, frames=slice(None), take: bool = True):
    """``_markers`` with each point's rows scaled by the square root of its weight: the weighted
    least-squares data term ``Σ_m w_m ||B_m x - s_m||²`` for the solvers that take plain rows.
    ``frames``: the take's frames to return; ``take=False``: the take's rows are left unscaled, for
    a solver that reads none of them (prior_pf on a ``gram`` of every frame: spares a copy)."""
    B, S, valid = _markers(inputs)
    S, valid = S[frames], valid[frames]
    w = _marker_weights(inputs)
    if w is None:
        return B, S, valid
    r = np.sqrt(w)[:, None]
    return B * r[None], (S * r[None] if take else S), valid


#: what ``auto`` runs (measured on the sample, S07 -> Rocketbox: scripts/quality_cases.py,
#: docs/evaluation.md). The solves run on the markers with the actor's motion space aligned to the
#: character's (``motion_scale = matched``, a 3x3 map per marker refitted on the take from the
#: rigs' nearest shapes, :mod:`core.motion_alignment`, derived by the calibrate stage: 0.53 -> 0.415
#: mm on the renamed rig against ``rom``'s scale, 0.47 with the covariance map alone), a ridge of 1e-2:
#: * the target has the take's own ARKit names: the whole take at once (bounded spacetime, Sobolev
#:   beta 10) pulled towards each shape's namesake curve — 0.02-0.1 mm where the per-frame solve
#:   gives 0.4-0.6, in seconds (dense correspondence: the same error after a registration);
#: * otherwise, when the take is a source rig's curves, the rig pair's dense correspondence
#:   (registration cached per rig pair) compares the two rigs' shapes over the face's first
#:   :data:`AUTO_DENSE_POINTS` points and each source shape is carried by the few target shapes that
#:   rebuild it (the sparse shape map, :func:`core.shape_matching.aligned_shape_map`): the curves are
#:   mapped through it, no per-frame solve, the jaw's columns scaled to the actor's jaw angle (names hidden
#:   0.465 -> 0.355 -> 0.314 mm, non-ARKit shapes 0.519 -> 0.466 -> 0.420; docs/evaluation.md "Dense shape
#:   matching", "design S");
#: * otherwise (a capture, example poses, no dense correspondence, or a negative lower bound) the
#:   per-frame bounded solve (a pull through the vocabularies' approximate combinations did not beat
#:   geometry alone: 0.556 at best; re-sculpting the source's motion towards the shapes it matches,
#:   :func:`restyled_inputs`, helped on the covariance map but measured worse on the matched one,
#:   before its cap: B 0.474 -> 0.487, C 0.420 -> 0.430 mm).
AUTO_RIDGE = 1e-2
AUTO_MOTION_SCALE = "matched"
#: ... but with example poses, which carry the meaning, the solve goes back to the covariance map
#: (:func:`covariance_inputs`; under the matched one the poses measured worse on the renamed rig:
#: 2 poses 0.362 -> 0.418 mm, 8 poses 0.081 -> 0.086)
AUTO_NAMED = {"alpha": 0.01, "beta": 10.0, "boundary": "perframe", "spacetime_bounds": True, "l1": 0.0,
              "name_weight": 30.0, "ridge": AUTO_RIDGE}
AUTO_UNNAMED = {"ridge": AUTO_RIDGE}
#: names are trusted when at least this fraction of the solver's shapes has a namesake channel
#: (a quarter: Rocketbox's 52 ARKit shapes are 0.297 of its 175, and the files-only check that spares
#: the registration, ``core.stages.retarget.auto_maps_shapes``, counts before the shapes no marker
#: sees are dropped, so it must agree with this on such a rig)
AUTO_MIN_NAMED = 0.25


def names_carry(named: int, shapes: int) -> bool:
    """Whether ``named`` namesakes among ``shapes`` solver shapes are enough for auto to go by
    names (:data:`AUTO_MIN_NAMED`): one rule for :func:`auto_choice` on the loaded data and for the
    files-only check that spares the registration (``core.stages.retarget.auto_maps_shapes``)."""
    return named >= max(1, AUTO_MIN_NAMED * shapes)
#: the dense correspondence points (a prefix of the farthest-point order) auto's shape map compares
#: the rigs' shapes at: 1,000 gave 0.355 / 0.466 mm (names hidden / non-ARKit), 2,000 0.399 / 0.495,
#: 5,000 0.383 / 0.481 — the fewest is the best and the cheapest
AUTO_DENSE_POINTS = 1000


def _exact_names(inputs) -> np.ndarray:
    """(K_solver,) bool: the solver shapes with a namesake channel in the take (the same canonical
    ARKit name, not a vocabulary's approximate combination)."""
    named = named_target({**inputs, "vocabulary": {"vocabularies": ()}}, exclusive=True)
    if named is None:
        return np.zeros(inputs["shapes"]["rig"].n_shapes, bool)
    return np.isfinite(named).all(0)


def _alignment_phrase(inputs) -> str:
    """How the calibrate stage matched the actor's motion to the character's, in words."""
    cal = inputs.get("calibrate") or {}
    if cal.get("source_map") is None:
        return "the actor's motion as captured"
    if cal.get("alignment") == "matched":
        return ("the actor's motion space aligned to the character's (a 3×3 map per point, fitted on the take "
                "to the character's nearest shapes)")
    if cal.get("source_scale") is None:
        return "the actor's motion space aligned to the character's (a 3×3 map per point)"
    return "the actor's range of motion matched to the character's"


def shape_map_phrase(n_points: int, eyes: bool = False) -> str:
    """What auto's shape map (:func:`_shape_mapped`) does, in words: one text for auto's sentence and
    for live's, which maps each packet through the same map (``core.live``); ``eyes``: the eyeballs
    are in the fit (:func:`core.eyes.gaze_rows`)."""
    gaze = ", the eyeballs turned about the actor's gaze axes in the character's range" if eyes else ""
    return (f"mapped shape by shape, each source shape carried by the few target shapes that rebuild it over "
            f"{n_points} face points (dense correspondence), the jaw's turned by the actor's angle{gaze}, within the bounds")


def auto_choice(inputs, zero=None, posed: bool = False) -> tuple:
    """``(method function, settings, sentence)``: what ``auto`` runs on these inputs and why.
    ``zero``: the shapes the controls hold at zero already ((K,) bool or None); ``posed``: example
    poses will be learned from: when the shape map does not apply, their base is the per-frame solve
    on the covariance map (measured better than the matched one under poses, docs/evaluation.md);
    the shape map, where it applies, is their base as it is without poses (*The posed path*)."""
    src, rig = inputs["load"]["source"], inputs["shapes"]["rig"]
    named = _exact_names(inputs) if src.kind == "curves" else np.zeros(rig.n_shapes, bool)
    n = int(named.sum())
    where = (f"dense correspondence ({len(inputs['shapes']['weights'])} face points)"
             if inputs["shapes"].get("weights") is not None else f"the {len(inputs['shapes']['names'])} markers")
    if names_carry(n, rig.n_shapes):
        # the rig's other shapes (another vocabulary's smile, a viseme) would add the same
        # expressions a second time: the namesakes carry the take
        held = ~named if zero is None else (~named | np.asarray(zero, bool))
        rest = f"; its {int((~named).sum())} other shapes stay at zero" if (~named).any() else ""
        return _spacetime, {**AUTO_NAMED, "zero": held if held.any() else zero}, (
            f"auto: the whole take at once on {where}, {_alignment_phrase(inputs)}, "
            f"each shape pulled towards its namesake curve — {n} of the {rig.n_shapes} target shapes have the "
            f"take's own ARKit names{rest}")
    recognised = recognise(rig.names, inputs["vocabulary"]["vocabularies"])
    why = ("the take is markers, not named curves" if src.kind != "curves" else
           f"the target's shapes are not the take's ARKit names ({', '.join(recognised.vocabularies[:3])}: "
           "the vocabularies' combinations are approximate)" if recognised.recognised else
           "the target's shapes share no names with the take's curves")
    restyle = src.kind == "curves" and inputs["load"]["source_rig"] is not None
    if restyle and inputs.get("dense_correspondence") is not None:
        n_points = min(AUTO_DENSE_POINTS, len(inputs["dense_correspondence"]["weights"]))
        eyes = gaze_mapped(inputs["load"]["source_rig"], rig)
        return _shape_mapped, AUTO_UNNAMED, f"auto: the take's curves {shape_map_phrase(n_points, eyes)} — {why}"
    return _bounded, AUTO_UNNAMED, (f"auto: frame by frame within the bounds on {where}, {_alignment_phrase(inputs)}, "
                                    f"by geometry alone — {why}")


def restyled_inputs(inputs) -> tuple:
    """The re-sculpt design of issue 29 (docs/evaluation.md, *Shape matching*), which ``auto`` ran
    before the take-fitted map replaced it (on top of that map it measured worse); kept to measure
    against. ``(inputs, match)``: the solve's inputs with the source's motion (the calibrate stage's, in the
    character's range) re-sculpted in the character's style (:func:`core.shape_matching.restyled_motion`
    over :func:`~core.shape_matching.match_shapes` of the source rig's shapes and the solver's, at the
    same points); ``(inputs, None)`` unchanged unless the source is weight curves on a source rig."""
    cal, rig = inputs["calibrate"], inputs["load"]["source_rig"]
    st, layout = cal["source"], inputs["correspond"]["source_layout"]
    if st.source_weights is None or rig is None or layout is None:
        return inputs, None
    Ds = layout.select(list(inputs["stabilize"]["names"])).points(rig.deltas)
    if cal.get("source_map") is not None:  # the source rig's shapes in the character's motion space, as the take
        Ds = apply_alignment(cal["source_map"], Ds)
    B = np.asarray(inputs["personalize"]["deltas"], dtype=np.float64)
    match = match_shapes(Ds, B)
    add = restyled_motion(match, Ds, B, np.nan_to_num(np.asarray(st.source_weights, dtype=np.float64)))
    return {**inputs, "calibrate": {**cal, "source": replace(st, deltas=st.deltas + add)}}, match


def dense_shape_map(inputs, lower=0.0, upper=1.0) -> tuple:
    """``(M, eyes)``: ``M`` (K_solver, J) the :func:`core.shape_matching.aligned_shape_map` of the source rig's shapes and the
    solver's at the first :data:`AUTO_DENSE_POINTS` points of the rig pair's dense correspondence
    (the ``dense_correspondence`` stage), the target's warped into the actor's proportions by the
    calibrate stage's warp (Seol 2012 §3.2, fitted at the markers; none when calibration is off),
    then the jaw mapped as a bone (:func:`core.shape_matching.jaw_rescaled_map`: the columns of the
    source shapes that move the chin scaled so the character's jaw turns by the actor's angle; names
    hidden 0.355 -> 0.314 mm, non-ARKit shapes 0.466 -> 0.420, docs/evaluation.md "design S"), with
    the eyeballs in the fit when both rigs have them (:func:`core.eyes.gaze_rows`: the target's
    turned about the actor's axis, in the target's range; design E); ``eyes``: whether they were."""
    dc, ld = inputs["dense_correspondence"], inputs["load"]
    names = list(dc["source_layout"].names[:AUTO_DENSE_POINTS])
    source_points = dc["source_layout"].select(names)
    Ds, Ns = source_points.points(ld["source_rig"].deltas), source_points.points(ld["source_rig"].neutral)
    n, d = dc["target_layout"].select(names).on_rig(inputs["shapes"]["rig"])
    warp = inputs["calibrate"]["target"].warp
    T, Nt = (d, n) if warp is None else (warp(n[None] + d) - warp(n)[None], warp(n))
    eyes = gaze_rows(ld["source_rig"], inputs["shapes"]["rig"], warp)
    M = aligned_shape_map(Ds, T, lower, upper, l1=SPARSE_L1, extra=eyes)
    return jaw_rescaled_map(M, Ns, Ds, Nt, T, lower, upper)[0], eyes is not None


def _shape_mapped(inputs, s):
    """The source rig's curves mapped through :func:`dense_shape_map` within the bounds
    (``clip(W_source Mᵀ, lower, upper)``); shapes held at zero are left out of the map (per frame:
    set to zero). A negative lower bound (the L1 term needs ``lower >= 0``): the per-frame bounded
    solve instead."""
    lo, hi = s.lower, s.upper
    if np.any(np.asarray(lo) < 0):
        return _bounded(inputs, s)
    rig, src = inputs["shapes"]["rig"], inputs["load"]["source_rig"]
    K = rig.n_shapes
    keep = np.ones(K, bool) if s.zero is None or np.ndim(s.zero) != 1 else ~np.asarray(s.zero, bool)
    lo_k, hi_k = np.broadcast_to(np.asarray(lo, float), (K,)), np.broadcast_to(np.asarray(hi, float), (K,))
    free = keep & (hi_k > lo_k)
    M = np.zeros((K, src.n_shapes))
    eyes = False  # the eyeballs in the map (info["gaze"]: auto's and live's sentences)
    if free.any():
        sub = {**inputs, "shapes": {**inputs["shapes"], "rig": rig.subset([rig.names[k] for k in np.flatnonzero(free)])}}
        M[free], eyes = dense_shape_map(sub, lo_k[free], hi_k[free])
    Ws = np.nan_to_num(np.asarray(inputs["calibrate"]["source"].source_weights, dtype=np.float64))
    W = mapped_weights(M, Ws, lo_k, hi_k)
    W[:, ~free] = np.clip(0.0, lo_k, hi_k)[~free]
    if s.zero is not None and np.ndim(s.zero) == 2:
        W = np.where(s.zero, np.clip(0.0, lo_k, hi_k)[None], W)
    top = M.argmax(0)
    matches = {src.names[j]: rig.names[top[j]] for j in range(src.n_shapes) if M[top[j], j] > 0.05}
    # the map itself: the live retargeter maps each packet through it (core.live), from the cached result
    return {"weights": W, "info": {"shape_matches": matches, "shape_map": M, "gaze": eyes, "dense_points": min(AUTO_DENSE_POINTS, len(
        inputs["dense_correspondence"]["weights"]))}, "edit": edit_options(s, alpha=0.01, lower=lo, upper=hi)}



def covariance_inputs(inputs) -> dict:
    """The solve's inputs with the source's motion mapped by the calibrate stage's covariance map
    instead of its matched one (:func:`core.motion_alignment.matched_alignment`); unchanged under
    any other alignment."""
    cal = inputs["calibrate"]
    if cal.get("alignment") != "matched":
        return inputs
    st = inputs["stabilize"]["source"]
    src = replace(cal["source"], deltas=apply_alignment(cal["covariance_map"], st.deltas))
    return {**inputs, "calibrate": {**cal, "source": src, "source_map": cal["covariance_map"], "alignment": "covariance"}}


def pose_features(inputs) -> np.ndarray:
    """(T, F) the source's expression per frame, what example poses are learned over: the take's
    weight curves, or its marker displacements (captures, mesh sequences)."""
    st = inputs["stabilize"]["source"]
    if st.source_weights is not None:
        return np.asarray(st.source_weights, dtype=np.float64)
    return np.asarray(st.deltas, dtype=np.float64).reshape(len(st.deltas), -1)


def suggested_frames(inputs, n: int, posed=()) -> list:
    """Take frames to pose next (:func:`core.examples.suggest_poses` over :func:`pose_features`):
    far apart in expression; the example poses ``posed`` already set count as chosen."""
    first, stop = inputs["frames"]["first"], inputs["frames"]["stop"]
    exclude = [p["frame"] - first for p in posed if first <= p["frame"] < stop]
    return [int(first + f) for f in suggest_poses(pose_features(inputs), n, exclude=exclude)]


def example_poses(inputs, items) -> dict:
    """``{solve frame: (K_solver,) weights}`` of the example poses ``items`` (take frames, target
    shape names; shapes the solver does not use are left out, poses outside the frame range skipped)."""
    rig, full = inputs["shapes"]["rig"], inputs["load"]["target_rig"]
    fr = inputs["frames"]
    poses = poses_from_items(items, full.names, fr["n_frames"])
    keep = [list(full.names).index(n) for n in rig.names]
    outside = sorted(f for f in poses if not fr["first"] <= f < fr["stop"])
    if outside:
        warnings.warn(f"example poses at frames {outside[:6]} are outside the frame range "
                      f"{fr['first']}..{fr['stop'] - 1}: not used")
    return {f - fr["first"]: w[keep] for f, w in poses.items() if fr["first"] <= f < fr["stop"]}


@solve_method("auto", params=("example_poses",), needs=("prior",),
              honours=("bounds", "active", "symmetry", "cancel", "filter"), chooses=True, warm=True,
              label="auto — the best this pair and take allow (says what it chose)")
def _auto(inputs, s, warm=None):
    """The default: looks at the pair and the take and runs what serves best (:func:`auto_choice`),
    then corrects it towards the example poses, if any, for the whole take. On the shape map: the
    correction that predicts held-out poses best by leave-one-out over the poses, the most
    regularised within one standard error (:func:`core.examples.choose_by_loo`: none, a correction
    regressed on the source's features, or a linear map plus a pose-space RBF), each pose keyed at
    its own frame; on the per-frame solve, :func:`core.examples.learn_from_poses`.
    Says what it chose and why (``info["auto"]``)."""
    poses = example_poses(inputs, s.example_poses) if s.example_poses else {}
    run, chosen, sentence = auto_choice(inputs, s.zero, posed=bool(poses))
    if poses and run is not _shape_mapped:
        inputs = covariance_inputs(inputs)
        run, chosen, sentence = auto_choice(inputs, s.zero, posed=True)
    out = run(inputs, s.with_values(**chosen), **({"warm": warm} if run is _spacetime else {}))
    if poses and run is _shape_mapped:
        # the map is strong (C 0.254 mm alone): a correction must beat it on held-out poses
        rig = inputs["shapes"]["rig"]
        D = np.asarray(rig.deltas, dtype=np.float64).reshape(rig.n_shapes, -1)
        lo = np.broadcast_to(np.asarray(s.lower, float), (rig.n_shapes,))
        hi = np.broadcast_to(np.asarray(s.upper, float), (rig.n_shapes,))
        out["weights"], label, loo = choose_by_loo(np.asarray(out["weights"]), pose_features(inputs), poses,
                                                   gram=D @ D.T, lower=lo, upper=hi)
        many = "s" if len(poses) > 1 else ""
        how = ("leave-one-out kept the map, no correction predicting the held-out poses clearly better"
               if label == "none" else f"the {label}" + (", chosen by leave-one-out over the poses" if loo else ""))
        sentence += f"; then learned from {len(poses)} example pose{many} ({how}), each keyed at its own frame"
        out.setdefault("info", {})["pose_choice"] = {"design": label, "loo": loo}
    elif poses:
        # the per-frame solve is geometry alone (C 0.57 mm): the poses' linear + RBF correction, which
        # measured better there than the leave-one-out choice (2 poses C 0.362 against 0.468)
        out["weights"] = learn_from_poses(np.asarray(out["weights"]), pose_features(inputs), poses,
                                          lower=s.lower, upper=s.upper)
        sentence += f"; then learned from {len(poses)} example pose{'s' if len(poses) > 1 else ''}"
    out.setdefault("info", {})
    out["info"]["auto"] = sentence
    out["info"]["chosen"] = {"method": run.__name__.lstrip("_"), **{k: v for k, v in chosen.items() if k != "zero"},
                             "example_poses": len(poses)}
    return out


@solve_method("lsq", params=("ridge",), honours=("filter",), label='lsq — unregularised diagnostic (weights can explode)')
def _lsq(inputs, s):
    """Per-frame least squares, unbounded (a diagnostic: no regulariser keeps it in range)."""

    B, S, valid = weighted_markers(inputs)
    return {"weights": baselines.no_const(B, S, valid), "edit": edit_options(s, alpha=0.01)}


@solve_method("bounded", params=("lower", "upper", "ridge"), honours=("bounds", "active", "symmetry", "cancel", "filter"),
              label='bounded — per frame, within lowest…highest')
def _bounded(inputs, s):
    """Per-frame least squares with ``lower <= w <= upper`` (batched exact active set)."""

    B, S, valid = weighted_markers(inputs)
    return {"weights": baselines.range_pf(B, S, s.lower, s.upper, valid, ridge=s.ridge, quadratic=s.quadratic, zero=s.zero),
            "edit": edit_options(s, alpha=0.01, lower=s.lower, upper=s.upper)}


@solve_method("range_pf", params=("ridge",), honours=("active", "symmetry", "cancel", "filter"), label='range_pf — per frame, −0.5…1.5 (Seol §7)')
def _range_pf(inputs, s):
    """Seol 2012 §7 Range PF: per frame, -0.5 <= w <= 1.5."""

    B, S, valid = weighted_markers(inputs)
    return {"weights": baselines.range_pf(B, S, valid=valid, ridge=s.ridge, quadratic=s.quadratic, zero=s.zero),
            "edit": edit_options(s, alpha=0.01, lower=-0.5, upper=1.5)}


def _frames_gram(inputs, frames):
    """:func:`baselines.data_gram` of the weighted markers on a few ``frames`` of the take, from the
    ``motion_gram`` stage's products (``G = B^T Gamma B`` is the weighted rows' ``B_w^T B_w``,
    ``(Gamma S_t) B`` their ``S_w,t B_w``, ``sigma_max(B_w)^2`` the largest eigenvalue of ``G``),
    or None when it did not run on this take or a frame lacks a marker. The end frames of the
    spacetime solve (``boundary = perframe``) are a prior_pf of two frames at every alpha: from
    the products it reads no (3M, K) matrix (with 1,000 dense points the SVD of the weighted
    rows alone was 12 ms of every setting change). The same ends to rounding (1e-12 relative at the
    default ridge; with ridge 0 the two frames' ``G + alpha P`` of 165 shapes is singular to working
    precision, condition 1e19, and its ends are rounding's whichever way they are made)."""
    pr = _products(inputs, _markers(inputs)[1])
    if pr is None or not pr.valid[frames].all():
        return None
    K = pr.G.shape[0]
    smax2 = float(scipy.linalg.eigvalsh(pr.G, subset_by_index=[K - 1, K - 1])[0]) if K else 0.0
    return {"frames": np.arange(len(frames)), "H": pr.G, "rhs": pr.SGB[frames], "smax2": smax2}


def _prior_pf_frames(inputs, s, frames):
    """Prior PF (the weighted data term, the unweighted markers' prior) on a few frames (all of
    them: with the ``gram`` stage's products of the data term, when it ran; a list of frames:
    with the ``motion_gram`` stage's, when it ran, :func:`_frames_gram`)."""

    whole = isinstance(frames, slice) and frames == slice(None)
    gram = inputs.get("gram") if whole else (None if isinstance(frames, slice) else _frames_gram(inputs, frames))
    n_frames = len(_markers(inputs)[1][frames])
    # with a gram of every frame prior_pf reads no frame of the take
    B, S, valid = weighted_markers(inputs, frames, take=gram is None or len(gram["frames"]) != n_frames)
    prior = _prior(inputs)
    if _marker_weights(inputs) is not None and prior is not None:
        B0 = _markers(inputs)[0]
        P, q, _ = prior_quadratic(prior, flatten(B0).T, len(B0))
        prior = (P, q)
    zero = s.zero if s.zero is None or np.ndim(s.zero) == 1 else np.asarray(s.zero)[frames]
    return baselines.prior_pf(B, S, s.alpha, prior, valid, ridge=s.ridge, quadratic=s.quadratic, zero=zero,
                              gram=gram)


@solve_method("prior_pf", params=("alpha", "ridge"), needs=("prior", "gram"), honours=("active", "symmetry", "cancel", "filter"),
              label="prior_pf — per frame with the rig's prior (Seol §7)")
def _prior_pf(inputs, s):
    """Seol 2012 §7 Prior PF: per frame with the PCA prior."""
    return {"weights": _prior_pf_frames(inputs, s, slice(None)), "edit": edit_options(s)}


def _products(inputs, S):
    """The ``motion_gram`` stage's products when it ran on this very take (``S`` the array the
    solver gets: not a re-sculpted copy of the inputs), else None (the solver makes them)."""
    pr = (inputs.get("motion_gram") or {}).get("products")
    return pr if pr is not None and pr.S3 is S else None


@solve_method("spacetime", params=("alpha", "beta", "boundary", "ridge", "spacetime_bounds", "lower", "upper", "l1",
                                   "name_weight"), needs=("prior", "motion_gram"), honours=("bounds", "active", "symmetry", "cancel"),
              warm=True, label='spacetime — the whole take at once (Seol 2012)')
def _spacetime(inputs, s, warm=None):
    """Seol 2012 movement matching + PCA prior (+ Sobolev), the whole take at once; by default
    within ``lower <= w <= upper`` (exact bounded solve), optionally with L1 sparsity and a pull
    towards the namesake source curves (``name_weight``)."""

    B, S, valid = _markers(inputs)
    mw = _marker_weights(inputs)
    lo, hi = (s.lower, s.upper) if s.spacetime_bounds else (None, None)
    named = named_target(inputs) if s.name_weight > 0 else None
    known = None
    if s.boundary == "perframe":
        ends = _prior_pf_frames(inputs, s, [0, len(S) - 1])
        if lo is not None:  # the end frames are known values: inside the bounds too
            ends = np.clip(ends, lo, hi)
        known = {0: ends[0], len(S) - 1: ends[1]}
    solver = SpacetimeSolver(B, S, alpha=s.alpha, beta=s.beta, prior=_prior(inputs), known=known,
                             boundary="none" if s.boundary == "none" else "neutral", valid=valid,
                             ridge=s.ridge if s.ridge > 0 else "auto", lower=lo, upper=hi, l1=s.l1, marker_weights=mw,
                             name_target=named, name_weight=s.name_weight if named is not None else 0.0,
                             quadratic=s.quadratic, products=_products(inputs, S))
    W = solver.solve(zero=s.zero, warm=warm)  # the bounded solve starts there (same result)
    info = {"path": solver.method_}
    if getattr(solver, "info_", None):
        # the answer's certificate; how it was reached (active-set steps, iterations, the warm
        # start) depends on the stage's last result and stays with the solver (its info_)
        info["bounded"] = {k: solver.info_[k] for k in ("kkt", "active", "converged")}
    return {"weights": W, "info": info,
            "edit": edit_options(s, lower=lo, upper=hi, l1=s.l1, name_weight=s.name_weight if named is not None else 0.0,
                                 beta=s.beta)}


@solve_method("local", params=("constraint", "local_temporal", "alpha", "beta", "sigma", "ridge"), needs=("segment",),
              honours=("bounds", "active", "symmetry", "cancel"), label='local — face regions (Liu 2011)')
def _local(inputs, s):
    """Liu 2011: per-region constrained QP (eq. 2), blended by the region masks (eq. 3)."""

    B, S, valid = _markers(inputs)
    st = inputs["calibrate"]["source"]
    seg = inputs["segment"]
    mw = seg["marker_weights"] if _marker_weights(inputs) is None else seg["marker_weights"] * _marker_weights(inputs)[None]
    box = {"lower": s.lower, "upper": s.upper} if s.constraint == "box" else {}
    problem = local_precompute(np.zeros_like(st.neutral), B, mw, constraint=s.constraint, quadratic=s.quadratic, **box)
    has = valid.any(1)  # frames without a marker sample (tracking loss) are gaps: filled, flagged by synthesize
    U = np.empty((len(S), len(seg["masks"]), len(B)))
    zero = s.zero if s.zero is None or np.ndim(s.zero) == 1 else np.asarray(s.zero)[has]
    U[has] = problem.solve(S[has], valid[has], zero=zero)  # (T, R, K) regional weights, eq. 2
    if not has.all():
        U = fill_gaps(U, has)
    if s.local_temporal == "spacetime":  # movement matching per region, ends from the QP
        U = local_spacetime(B, S, mw, U, s.alpha, s.beta, valid, quadratic=s.quadratic)
    if s.sigma > 0:
        U = smooth_weights(U, s.sigma)
    W = blend_weights(U, seg["masks"])
    # eq. 3 at the markers: what the mask-blended meshes show (the blended curves are a summary)
    predicted = reconstruct_markers(np.zeros_like(st.neutral), B, U, seg["marker_masks"])
    return {"weights": W, "info": {"region_weights": U, "masks": seg["masks"], "predicted": predicted},
            "edit": edit_options(s, lower=0.0, upper=1.0, beta=s.beta)}


@solve_method("geometric", params=("geometric_prior", "mu", "lam", "ridge"), needs=("prior",),
              honours=("bounds", "active", "symmetry", "cancel", "filter"), label='geometric — smooth mesh, few shapes (Ribera 2017)')
def _geometric(inputs, s):
    """Ribera 2017: cotangent-Laplacian (or PCA / L2) prior + L1 sparsity, within ``lower <= w <= upper``
    (exact batched box QP; ``GeometricSolver(lower=None, upper=None)`` is the paper's unbounded IRLS)."""

    B, S, valid = weighted_markers(inputs)
    kw = {"rig": inputs["shapes"]["rig"]} if s.geometric_prior == "geometric" else {}
    if s.geometric_prior == "pca":
        B0 = _markers(inputs)[0]  # the prior is the unweighted markers'
        P, q, _ = prior_quadratic(_prior(inputs), flatten(B0).T, len(B0))
        kw = {"gram": P, "linear": -q}
    frames = S
    if not valid.all():  # the L1 solver needs complete frames: fill gaps with the No Const fit
        fill = np.einsum("tk,kmc->tmc", baselines.no_const(B, S, valid), B)
        frames = np.where(valid[..., None], S, fill)
        warnings.warn(f"geometric: {int((~valid).sum())} missing marker samples filled by the per-frame fit")
    sol = GeometricSolver(B, s.geometric_prior, mu=s.mu, lam=s.lam, quadratic=s.quadratic, lower=s.lower, upper=s.upper,
                          **kw).solve(frames, zero=s.zero)
    return {"weights": sol.weights, "info": {"iterations": sol.iterations, "kkt": sol.extras.get("kkt")},
            "edit": edit_options(s, alpha=0.01, lower=s.lower, upper=s.upper)}


@solve_method("names", params=("ridge",), honours=("active",), label='names — copy curves by ARKit name')
def _names(inputs, s):
    """Copy by canonical name: each target shape plays its namesake source curve (weight-curve
    sources only; shapes without a namesake stay at zero). The baseline a solver must beat where
    names do not match."""
    W = named_target(inputs, exclusive=True)
    if W is None:
        src = inputs["load"]["source"]
        raise ValueError(f"the names method copies weight curves by name: {src.name!r} is "
                         + ("markers" if src.kind == "markers" else "curves whose channels share no name with the target's shapes"))
    named = int(np.isfinite(W).all(0).sum())
    W = np.nan_to_num(W)
    if s.zero is not None:  # shapes switched off stay at zero
        W[:, np.asarray(s.zero, bool)] = 0.0
    return {"weights": W, "info": {"named": named},
            "edit": edit_options(s, alpha=0.01, lower=0.0, upper=1.0)}


@solve_method("transfer", dense=True, label='transfer — dense, a new rig (Xu 2014)')
def _transfer(inputs, s):  # pragma: no cover - the solve stage is inactive for dense methods
    """Xu 2014 dense transfer: a new rig of transferred bases (+ details), see core.stages.dense."""
    raise RuntimeError("transfer is computed by the dense stages, not by the solve stage")
