"""Shape-to-shape correspondence between two rigs, recovered from geometry alone.

Two rigs sculpted by different artists rarely share names, but a target shape that means the same
as a source shape moves the same part of the face by a similar amount, even where its direction
differs (ICT's ``jawOpen`` moves the chin back as much as down, Rocketbox's almost straight down).
Compared at the points both faces share (the markers or dense correspondence, the source's
motion in the character's range: ``motion_scale = rom``), the *affinity* of source shape ``j``
and target shape ``k`` is

    a_jk = mix · cos(s_j, t_k) + (1 − mix) · cos(|s_j|, |t_k|)                                   (1)

``s_j, t_k`` (M·3,) the shapes' displacements at the M points, ``|s_j|, |t_k|`` (M,) their
per-point magnitudes (the *pattern*: where the shape moves and how much, blind to direction);
``cos(x, y) = xᵀy / (‖x‖ ‖y‖)``, 0 for a shape that moves nothing. ``a_jk ∈ [−1, 1]``; the
magnitude term is in [0, 1].

:func:`match_shapes` pairs the shapes by the assignment of largest total affinity (Kuhn 1955;
``scipy.optimize.linear_sum_assignment``), one target shape per source shape at most, and calls a
pair *sure* when it is each side's best match (mutual) and ``a_jk >= min_affinity``. The gain
``g = ‖s_j‖ / ‖t_k‖`` says how much of the target shape a source shape's full weight means.
:func:`pseudo_names` turns the pairs into the per-shape "namesake" curves the name pull of the
spacetime solver takes (``name_target``, NaN = no namesake), each with its confidence.
:func:`shape_map` is the other design: each source shape fitted by the target's shapes within the
bounds, ``M[:, j] = argmin_{lower ≤ x ≤ upper} ‖Tᵀx − s_j‖² + ridge σ_max(T)² ‖x‖² + l1 ‖s_j‖² Σ_k x_k``
(the batched exact box QP of :func:`core.solvers.baselines.range_pf`, with the L1 term its unit-box
solver :func:`core.solvers.boxqp.solve_box_sequence` on the normal equations), a whole-take mapping
``W = clip(W_source Mᵀ, lower, upper)`` (:func:`mapped_weights`). The L1 term (``lower ≥ 0``, so
``Σ_k x_k = ‖x‖₁``) keeps each source shape to the few target shapes that carry it (:data:`SPARSE_L1`:
about 4 of 175 on the sample) instead of rebuilding the source's own sculpt out of many — compared
over dense correspondence, the whole face rather than 41 markers, it is what ``auto`` uses without
shared names (:func:`aligned_shape_map`; docs/evaluation.md, "Dense shape matching"). Per-shape L1
weights (``l1_scale``) let another source of meaning steer the fit; steered by the vocabularies it
measured no better (docs/evaluation.md, "Vocabulary-guided shape map").
:func:`restyled_motion` is the third: the source's motion re-sculpted in the character's style, each
sure pair's source shape moved part of the way towards its match, ``s'_j = (1 − β) s_j + β g t_k`` —
then an ordinary geometric solve fits it (the actor's jaw drop then asks for the character's jaw
drop, not for a chin pulled back by other shapes); kept to measure against (on top of the take-fitted
motion map, :func:`core.motion_alignment.matched_alignment`, it measured worse).

What was measured with them (issue 29, cases B and C): docs/evaluation.md, "Shape matching".

References
----------
1. H. W. Kuhn, "The Hungarian method for the assignment problem", Naval Research Logistics
   Quarterly 2, 1955.
2. Y. Seol, J. Seo, P. H. Kim, J. P. Lewis, J. Noh, "Weighted pose space editing for facial
   animation", The Visual Computer 28, 2012 — §7 Range PF, the per-shape fit of :func:`shape_map`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial.transform import Rotation

from .motion_alignment import apply_alignment, covariance_alignment
from .solvers.baselines import range_pf
from .solvers.boxqp import solve_box_sequence

#: a match is sure (it pulls) when both sides' best and at least this affine (eq. 1)
MIN_AFFINITY = 0.75
#: how far :func:`restyled_motion` moves a sure pair's source shape towards its match (β)
RESTYLE = 0.5
#: the L1 weight of the sparse :func:`shape_map` (relative to each source shape's squared size):
#: the best of 0, 0.1 … 4 on the sample over 2,000 dense points (docs/evaluation.md)
SPARSE_L1 = 0.3
#: :func:`jaw_rescaled_map`: a source shape is a jaw shape when the chin (the lowest
#: :data:`JAW_CHIN` of the points by height) moves on average at least :data:`JAW_MIN_CHIN` of the
#: shape's largest motion (on the sample: ICT's four jaw shapes 0.51–0.60, every other ≤ 0.25)
JAW_CHIN, JAW_MIN_CHIN = 0.1, 0.3
#: a jaw shape turning by at least this many degrees is mapped by its angle, else by its translation
JAW_MIN_DEGREES = 3.0
#: the points a rigid motion is fitted on: those moving more than this fraction of the largest motion
RIGID_MOVING = 0.3


def _deltas(x, name: str) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 3 or x.shape[2] != 3:
        raise ValueError(f"{name}: expected shape deltas (K, M, 3), got shape {x.shape}")
    return x


def _cosines(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(J, K) cosines of the rows of ``a`` (J, F) and ``b`` (K, F); 0 where a row is zero."""
    na, nb = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1)
    ua = a / np.where(na > 0, na, 1.0)[:, None]
    ub = b / np.where(nb > 0, nb, 1.0)[:, None]
    return ua @ ub.T


def motion_affinity(source, target, mix: float = 0.5) -> np.ndarray:
    """(J, K) affinity of every source shape with every target shape, eq. (1) of the module.

    Parameters
    ----------
    source : (J, M, 3) float
        The source shapes' displacements at the M shared points (in the character's range).
    target : (K, M, 3) float
        The target shapes' displacements at the same points.
    mix : float in [0, 1]
        Weight of the direction term; ``1 - mix`` that of the magnitude pattern.

    Raises
    ------
    ValueError
        Shapes that are not (K, M, 3), different M, or ``mix`` outside [0, 1].
    """
    s, t = _deltas(source, "source"), _deltas(target, "target")
    if s.shape[1] != t.shape[1]:
        raise ValueError(f"source and target: the same points are needed, got {s.shape[1]} and {t.shape[1]}")
    if not 0.0 <= mix <= 1.0:
        raise ValueError(f"mix: expected a weight in [0, 1], got {mix}")
    direction = _cosines(s.reshape(len(s), -1), t.reshape(len(t), -1))
    pattern = _cosines(np.linalg.norm(s, axis=2), np.linalg.norm(t, axis=2))
    return mix * direction + (1.0 - mix) * pattern


@dataclass(frozen=True)
class ShapeMatch:
    """Pairs of source and target shapes (:func:`match_shapes`).

    Attributes
    ----------
    source, target : (P,) int
        The pairs' source and target shape indices (each index at most once).
    affinity : (P,) float
        Their affinity, eq. (1).
    gain : (P,) float
        ``‖s_j‖ / ‖t_k‖``: the target weight a source weight of 1 means.
    mutual : (P,) bool
        The pair is each side's best match.
    confidence : (P,) float
        The affinity where the pair is sure (mutual and ``>= min_affinity``), else 0.
    """

    source: np.ndarray
    target: np.ndarray
    affinity: np.ndarray
    gain: np.ndarray
    mutual: np.ndarray
    confidence: np.ndarray

    @property
    def sure(self) -> np.ndarray:
        """(P,) bool: the pairs that pull."""
        return self.confidence > 0


def match_shapes(source, target, mix: float = 0.5, min_affinity: float = MIN_AFFINITY) -> ShapeMatch:
    """The assignment of largest total affinity between source and target shapes (Kuhn 1955).

    Parameters
    ----------
    source : (J, M, 3), target : (K, M, 3), mix : as :func:`motion_affinity`.
    min_affinity : float
        A mutual best pair with at least this affinity is sure (confidence = its affinity).

    Returns
    -------
    ShapeMatch with ``min(J, K)`` pairs, ordered by source shape.
    """
    A = motion_affinity(source, target, mix)
    rows, cols = linear_sum_assignment(-A)
    s = np.linalg.norm(_deltas(source, "source").reshape(A.shape[0], -1), axis=1)
    t = np.linalg.norm(_deltas(target, "target").reshape(A.shape[1], -1), axis=1)
    aff = A[rows, cols]
    mutual = (A.argmax(1)[rows] == cols) & (A.argmax(0)[cols] == rows)
    gain = s[rows] / np.where(t[cols] > 0, t[cols], 1.0)
    conf = np.where(mutual & (aff >= min_affinity), aff, 0.0)
    return ShapeMatch(rows, cols, aff, gain, mutual, conf)


def pseudo_names(match: ShapeMatch, source_weights, n_target: int, lower=0.0, upper=1.0) -> tuple:
    """The pairs as namesake curves: ``(W_named (T, K), confidence (K,))``.

    ``W_named[:, k] = clip(g · w_j, lower_k, upper_k)`` for each sure pair ``(j, k)`` (gain ``g``),
    NaN for the other target shapes (no namesake: no pull); ``confidence[k]`` the pair's
    confidence, 0 elsewhere — what :class:`core.solvers.spacetime.SpacetimeSolver` takes as
    ``name_target`` and, times a weight, ``name_weight``.

    Parameters
    ----------
    source_weights : (T, J) float
        The source's weight curves over the source rig's shapes.
    n_target : int
        K, the target shapes the solver uses.
    lower, upper : float or (K,) float
        The target's weight bounds.
    """
    W = np.asarray(source_weights, dtype=np.float64)
    if W.ndim != 2 or W.shape[1] <= (match.source.max() if len(match.source) else -1):
        raise ValueError(f"source_weights: expected (T, J) curves over the matched source shapes, got shape {W.shape}")
    lo = np.broadcast_to(np.asarray(lower, dtype=np.float64), (n_target,))
    hi = np.broadcast_to(np.asarray(upper, dtype=np.float64), (n_target,))
    named = np.full((len(W), n_target), np.nan)
    conf = np.zeros(n_target)
    sure = match.sure
    for j, k, g, c in zip(match.source[sure], match.target[sure], match.gain[sure], match.confidence[sure]):
        named[:, k] = np.clip(g * W[:, j], lo[k], hi[k])
        conf[k] = c
    return named, conf


def shape_map(source, target, lower=0.0, upper=1.0, ridge: float = 1e-2, l1: float = 0.0,
              l1_scale=None) -> np.ndarray:
    """(K, J) each source shape fitted by the target's shapes within the bounds (module docstring):

        M[:, j] = argmin_{lower ≤ x ≤ upper} ‖Tᵀx − s_j‖² + ridge σ_max(T)² ‖x‖² + l1 ‖s_j‖² Σ_k c_jk x_k,

    exact: :func:`core.solvers.baselines.range_pf` with the source shapes as its frames (``l1 = 0``),
    else the same exact box QP (:func:`core.solvers.boxqp.solve_box_sequence`) on the normal
    equations with the L1 term moved into the linear part (``½ xᵀ G x − (T s_j − ½ l1 ‖s_j‖² c_j)ᵀ x``, ``G = T Tᵀ + ρ I``; when ``ridge`` is
    0 a floor ``ρ = 1e-9 σ_max(T)²`` keeps ``G`` definite, as range_pf does).

    Parameters
    ----------
    source : (J, M, 3), target : (K, M, 3) float
        The shapes' displacements at the same M points.
    lower, upper : float or (K,) float
        The target's weight bounds.
    ridge : float >= 0
        Relative Tikhonov weight.
    l1 : float >= 0
        Sparsity weight relative to each source shape's squared size (scale-free); needs
        ``lower >= 0`` (then ``Σ_k x_k`` is the L1 norm).
    l1_scale : (K,) or (J, K) float >= 0, optional
        Each target shape's L1 weight as a multiple of ``l1`` (per source shape when (J, K)): the
        term becomes ``l1 ‖s_j‖² Σ_k c_jk x_k`` — a smaller weight for the shapes another source
        of meaning (a vocabulary) proposes for ``s_j``, a large one to leave a shape out
        (scripts/vocab_map_eval.py). None: ``c_jk = 1``.

    Raises
    ------
    ValueError
        Shapes that are not (K, M, 3) or differ in M; ``l1 < 0``; ``l1 > 0`` with a negative lower bound;
        ``l1_scale`` of another shape or with a negative weight.
    """
    s, t = _deltas(source, "source"), _deltas(target, "target")
    if s.shape[1] != t.shape[1]:
        raise ValueError(f"source and target: the same points are needed, got {s.shape[1]} and {t.shape[1]}")
    if l1 < 0:
        raise ValueError(f"l1: expected a weight >= 0, got {l1}")
    c = np.ones((len(s), len(t))) if l1_scale is None else np.asarray(l1_scale, dtype=np.float64)
    if c.shape not in ((len(t),), (len(s), len(t))):
        raise ValueError(f"l1_scale: expected shape ({len(t)},) or ({len(s)}, {len(t)}), got {c.shape}")
    if not np.all(c >= 0):
        raise ValueError(f"l1_scale: expected weights >= 0, got a minimum of {c.min()}")
    if l1 == 0:
        return range_pf(t, s, lower, upper, np.ones(s.shape[:2], bool), ridge=ridge).T
    if np.any(np.asarray(lower) < 0):
        raise ValueError(f"lower: the L1 term of shape_map needs lower >= 0 (the weights' sum is then their L1 norm), got {lower}")
    K = len(t)
    lo = np.broadcast_to(np.asarray(lower, dtype=np.float64), (K,))
    hi = np.broadcast_to(np.asarray(upper, dtype=np.float64), (K,))
    if not (hi > lo).all():
        raise ValueError(f"upper: the L1 term of shape_map needs lower < upper for every shape, got {lower}, {upper}")
    T = t.reshape(K, -1)  # (K, 3M)
    S = s.reshape(len(s), -1)  # (J, 3M)
    G = T @ T.T
    smax2 = float(np.linalg.eigvalsh(G)[-1]) if K else 0.0
    G[np.diag_indices_from(G)] += max(ridge, 1e-9) * smax2
    rhs = S @ T.T - 0.5 * l1 * (S ** 2).sum(1)[:, None] * np.broadcast_to(c, (len(S), K))
    # the unit box x = lo + d u, as range_pf: one Hessian, the source shapes its "frames"
    d = hi - lo
    u = solve_box_sequence((G * d[:, None] * d[None, :])[None], (lo @ G - rhs) * d)
    return np.clip(lo + u * d, lo, hi).T


def mapped_weights(shape_map_, source_weights, lower=0.0, upper=1.0) -> np.ndarray:
    """(T, K) the whole-take mapping ``clip(W_source Mᵀ, lower, upper)`` of the source's curves
    ``(T, J)`` through a (K, J) :func:`shape_map` (NaN frames stay NaN)."""
    M = np.asarray(shape_map_, dtype=np.float64)
    W = np.asarray(source_weights, dtype=np.float64)
    if W.ndim != 2 or W.shape[1] != M.shape[1]:
        raise ValueError(f"source_weights: expected (T, {M.shape[1]}) curves over the source shapes, got shape {W.shape}")
    return np.clip(W @ M.T, lower, upper)


def aligned_shape_map(source, target, lower=0.0, upper=1.0, l1: float = SPARSE_L1, extra=None) -> np.ndarray:
    """(K, J) the sparse :func:`shape_map` (``ridge = 0``, L1 ``l1``) of the source shapes mapped into
    the target's motion space point by point (:func:`core.motion_alignment.covariance_alignment`
    of the two sets of shapes): what ``auto`` maps a source rig's curves through when no name is
    shared (docs/evaluation.md, "Dense shape matching").

    Parameters
    ----------
    source : (J, M, 3), target : (K, M, 3) float
        The shapes' displacements at the same M points (dense correspondence: M in the thousands;
        the target's calibrated into the actor's proportions).
    lower, upper : float or (K,) float, ``lower >= 0``
    l1 : float > 0
    extra : ``(source (J, E, 3), target (K, E, 3))``, optional
        More points, already in the target's motion space, appended after the alignment (the
        eyeballs' turn: :func:`core.eyes.gaze_rows`).
    """
    s, t = _deltas(source, "source"), _deltas(target, "target")
    s = apply_alignment(covariance_alignment(s, t), s)
    if extra is not None:
        es, et = _deltas(extra[0], "extra source"), _deltas(extra[1], "extra target")
        if es.shape[:2] != (len(s), et.shape[1]) or len(et) != len(t):
            raise ValueError(f"extra: expected ({len(s)}, E, 3) and ({len(t)}, E, 3) rows, got {es.shape} and {et.shape}")
        s, t = np.concatenate([s, es], 1), np.concatenate([t, et], 1)
    return shape_map(s, t, lower, upper, ridge=0.0, l1=l1)


def restyled_motion(match: ShapeMatch, source, target, source_weights, beta: float = RESTYLE) -> np.ndarray:
    """(T, M, 3) what to add to the source's motion ``Σ_j w_j s_j`` to re-sculpt it in the target's
    style: ``Σ_j w_j β (g t_k − s_j)`` over the sure pairs ``(j, k)`` (gain ``g``), so each sure
    source shape ``s_j`` becomes ``(1 − β) s_j + β g t_k``; the other shapes keep their motion.

    Parameters
    ----------
    match : ShapeMatch of ``source`` and ``target``.
    source : (J, M, 3), target : (K, M, 3) as :func:`motion_affinity`.
    source_weights : (T, J) float, the source's weight curves (NaN: no data; the frame gets NaN).
    beta : float in [0, 1]

    Raises
    ------
    ValueError
        ``beta`` outside [0, 1], or curves that are not (T, J).
    """
    s, t = _deltas(source, "source"), _deltas(target, "target")
    W = np.asarray(source_weights, dtype=np.float64)
    if W.ndim != 2 or W.shape[1] != len(s):
        raise ValueError(f"source_weights: expected (T, {len(s)}) curves over the source shapes, got shape {W.shape}")
    if not 0.0 <= beta <= 1.0:
        raise ValueError(f"beta: expected a fraction in [0, 1], got {beta}")
    sure = match.sure
    j, k, g = match.source[sure], match.target[sure], match.gain[sure]
    change = beta * (g[:, None, None] * t[k] - s[j])  # (P, M, 3)
    return np.einsum("tp,pmc->tmc", W[:, j], change)


def rigid_motion(neutral, delta, moving: float = RIGID_MOVING) -> tuple:
    """``(rotation vector (3,) radians, translation (3,))`` of the rigid motion closest (least
    squares, Kabsch: scipy's ``Rotation.align_vectors``) to the displacement ``delta`` (M, 3) of the
    points ``neutral`` (M, 3), fitted on the points moving more than ``moving`` of its largest motion;
    the translation is that of those points' centroid. Zero for a shape that moves nothing."""
    P, d = np.asarray(neutral, dtype=np.float64), np.asarray(delta, dtype=np.float64)
    m = np.linalg.norm(d, axis=1)
    if not m.max() > 0:
        return np.zeros(3), np.zeros(3)
    sel = m > moving * m.max()
    X, Y = P[sel], P[sel] + d[sel]
    if sel.sum() < 3:
        return np.zeros(3), Y.mean(0) - X.mean(0)
    rot, _ = Rotation.align_vectors(Y - Y.mean(0), X - X.mean(0))
    return rot.as_rotvec(), Y.mean(0) - X.mean(0)


def jaw_shapes(neutral, source, chin: float = JAW_CHIN, min_chin: float = JAW_MIN_CHIN) -> np.ndarray:
    """(J,) bool: the source shapes that move the chin — the lowest ``chin`` of the points by height
    (``y``, the rigs' up axis) moving on average at least ``min_chin`` of the shape's largest motion."""
    P, s = np.asarray(neutral, dtype=np.float64), _deltas(source, "source")
    low = P[:, 1] <= np.quantile(P[:, 1], chin)
    m = np.linalg.norm(s, axis=2)  # (J, M)
    top = m.max(1)
    return (top > 0) & (m[:, low].mean(1) >= min_chin * np.where(top > 0, top, 1.0))


def jaw_rescaled_map(shape_map_, source_neutral, source, target_neutral, target, lower=0.0, upper=1.0) -> tuple:
    """The jaw mapped as a bone (issue 29, docs/evaluation.md "design S"): ``(M', scales (J,))``.

    A (K, J) :func:`shape_map` fits each source shape's *displacement*; a jaw that turns about
    another pivot (ICT's ``jawOpen`` moves the chin back as much as down, Rocketbox's almost straight
    down) is then rebuilt at the wrong amount (on the sample the map's jaw turns 12° where the actor's
    turns 8°). For each :func:`jaw_shapes` source shape ``j`` with a non-zero column, the rigid motions
    of the source shape and of the map's combination ``Σ_k M_kj t_k`` are fitted
    (:func:`rigid_motion`), and the column is scaled so the combination turns the jaw by the actor's
    angle (when the source shape turns by :data:`JAW_MIN_DEGREES` or more), else slides it by the
    actor's translation times the faces' size ratio (RMS radius of the points): the least-squares
    scale ``a·b / b·b``, the column then clipped to the bounds. The other columns are unchanged;
    ``scales`` is 1 for them (and for a jaw shape whose scale came out ≤ 0).

    Parameters
    ----------
    shape_map_ : (K, J) float
    source_neutral : (M, 3), source : (J, M, 3) float — the source rig at the M points (not aligned).
    target_neutral : (M, 3), target : (K, M, 3) float — the target's at the same points.
    lower, upper : float or (K,) float
    """
    M = np.array(shape_map_, dtype=np.float64)
    s, t = _deltas(source, "source"), _deltas(target, "target")
    if M.shape != (len(t), len(s)):
        raise ValueError(f"shape_map_: expected ({len(t)}, {len(s)}), got {M.shape}")
    Ps, Pt = np.asarray(source_neutral, dtype=np.float64), np.asarray(target_neutral, dtype=np.float64)
    ratio = np.sqrt(((Pt - Pt.mean(0)) ** 2).sum(1).mean() / ((Ps - Ps.mean(0)) ** 2).sum(1).mean())
    scales = np.ones(len(s))
    for j in np.flatnonzero(jaw_shapes(Ps, s)):
        if not M[:, j].any():
            continue
        rs, ts = rigid_motion(Ps, s[j])
        rc, tc = rigid_motion(Pt, np.einsum("k,kmc->mc", M[:, j], t))
        a, b = (rs, rc) if np.degrees(np.linalg.norm(rs)) >= JAW_MIN_DEGREES else (ratio * ts, tc)
        g = float(a @ b / (b @ b)) if b @ b > 0 else 0.0
        if g > 0:
            scales[j] = g
            M[:, j] = np.clip(M[:, j] * g, lower, upper)
    return M, scales
