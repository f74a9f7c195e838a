"""Example poses: a take-wide correspondence learned from a few frames the animator posed.

The practice of pose-based retargeters: the animator poses the target at a few frames, and
those poses teach the solver which target shape combination each source expression maps to —
for the whole take, not only around the posed frames as a spacetime edit does (Seol et al.
2012 §6, :meth:`core.solvers.spacetime.SpacetimeSolver.edit`). Where no pose speaks, the result
stays the geometric solution ``X`` (the method's own solve of the markers).

Notation: T frames, K target shapes, F source expression features, n poses at frames ``p``.
``X`` (T, K) is the method's solution, ``P`` (n, K) the posed weights, ``R = P - X_p`` the
residuals at the posed frames.

* :func:`suggest_poses` — which frames to pose: farthest-point sampling in the source's
  expression space, from the most expressive frame (Gonzalez 1985: a 2-approximation of the
  k-centre problem, so the n frames cover the take's expressions).
* :func:`linear_correction` — design (a): ``W = X (I + Δ)`` with ``Δ`` the ridge solution
  ``min_Δ ||X_p (I + Δ) - P||² + λ ||Δ||²``, i.e. ``Δ = (X_pᵀX_p + λI)⁻¹ X_pᵀ R``; with no pose
  ``Δ = 0`` (the identity: the geometric solution). What a pose says about a shape combination
  applies wherever the solver used that combination.
* :func:`pose_space_correction` — design (b), pose-space deformation (Lewis et al. 2000): a
  Gaussian RBF in the source feature space interpolating the residuals,
  ``W = X + Φ(F, F_p) (Φ(F_p, F_p) + εI)⁻¹ R``, ``Φ(a, b) = exp(-|a - b|² / 2σ²)``, σ the
  median distance between the posed frames' features; it vanishes far from every pose.
* :func:`learn_from_poses` — the recommended combination (``design="linear+rbf"``, measured in
  docs/evaluation.md §Example poses): the linear correction, then the RBF interpolation of what
  it leaves at the posed frames (so each pose is reproduced exactly), clipped into the bounds.

Design (c), the learned estimate as a pull target of the bounded spacetime solve
(``name_target`` / ``name_weight`` of :class:`core.solvers.spacetime.SpacetimeSolver`, so the
result stays a solve of the markers), was measured too (scripts/example_poses_eval.py): the
markers hold the result back towards the geometric solution the poses correct, and it never beat
the estimate it is pulled towards (docs/evaluation.md §Example poses).

Weights are unit-free (0 = neutral, 1 = the full shape), so ``ridge`` is in squared weights and
needs no scaling by the rig's size. Features are displacements from the neutral expression
(weight curves as they are; marker displacements in metres), zero = neutral.

References
----------
1. T. Gonzalez, "Clustering to minimize the maximum intercluster distance", Theor. Comput. Sci.
   38, 1985 (farthest-point sampling).
2. J. P. Lewis, M. Cordner, N. Fong, "Pose space deformation", SIGGRAPH 2000 (RBF on residuals).
3. Y. Seol et al., "Spacetime expression cloning for blendshapes", ACM TOG 31(2), 2012, §6.
"""

from __future__ import annotations

import difflib
from typing import Mapping, Sequence

import numpy as np
from scipy.interpolate import RBFInterpolator
from scipy.spatial.distance import pdist

from .gaps import fill_gaps
from .geometry import farthest_points

#: the designs :func:`learn_from_poses` knows
DESIGNS = ("linear", "rbf", "linear+rbf")
#: default ridge of the linear correction, in squared weights (measured on S07, docs/evaluation.md)
RIDGE = 1e-2
#: the RBF system's diagonal, relative to its largest entry (1): interpolation up to round-off
RBF_EPS = 1e-8


def _features(features) -> np.ndarray:
    F = np.asarray(features, dtype=np.float64)
    if F.ndim == 3:  # (T, M, 3) marker displacements
        F = F.reshape(len(F), -1)
    if F.ndim != 2:
        raise ValueError("features: expected (T, F) expression features or (T, M, 3) marker displacements, "
                         f"got shape {F.shape}")
    return F


def _has_data(F: np.ndarray) -> np.ndarray:
    return np.isfinite(F).all(1)


def suggest_poses(features, n: int, exclude: Sequence[int] = ()) -> np.ndarray:
    """The ``n`` frames to pose: far apart in expression.

    Farthest-point sampling (Gonzalez 1985) in feature space: the first frame is the most
    expressive (largest ``|f_t|``, features being displacements from the neutral), each next one
    the frame farthest (Euclidean) from all chosen so far. Frames without data (any non-finite
    feature) are never chosen; frames in ``exclude`` (already posed) count as chosen, so more
    suggestions extend an existing set.

    Parameters
    ----------
    features : (T, F) float, or (T, M, 3) marker displacements (flattened)
        The source's expression per frame: weight curves, or marker displacements from the neutral.
    n : int >= 0
        How many frames; fewer are returned when fewer distinct frames with data remain.
    exclude : sequence of int
        Frames already posed.

    Returns
    -------
    (n,) int64 : frame indices in the order chosen (the most informative first), distinct.

    Raises
    ------
    ValueError : ``n`` negative, features of the wrong shape, an ``exclude`` frame out of range.
    """
    F = _features(features)
    if int(n) != n or n < 0:
        raise ValueError(f"n: expected a whole number >= 0 of frames to suggest, got {n!r}")
    T = len(F)
    ex = np.asarray(list(exclude), dtype=np.int64)
    if ex.size and (ex.min() < 0 or ex.max() >= T):
        raise ValueError(f"exclude: frames must be in 0..{T - 1}, got {sorted(set(ex.tolist()))}")
    good = _has_data(F)
    idx = np.flatnonzero(good)
    if not len(idx) or n == 0:
        return np.zeros(0, dtype=np.int64)
    pos = np.cumsum(good) - 1  # frame -> row of the frames with data
    done = [int(pos[f]) for f in dict.fromkeys(ex.tolist()) if good[f]]  # already posed: rows, kept out
    start = done or [int(np.argmax(np.linalg.norm(F[idx], axis=1)))]
    rows = farthest_points(F[idx], min(len(done) + int(n), len(idx)), start=start)[len(done):]
    return idx[np.asarray(_distinct(rows, done), dtype=np.int64)].astype(np.int64)


def _distinct(rows, start) -> list:
    """``rows`` without repeats (farthest-point sampling repeats once every point is covered)."""
    seen, out = set(start), []
    for r in rows:
        if int(r) not in seen:
            seen.add(int(r))
            out.append(int(r))
    return out


def _poses(X: np.ndarray, poses: Mapping) -> tuple:
    """``(frames (n,), P (n, K))`` from ``{frame: (K,) weights}``, checked against ``X``."""
    T, K = X.shape
    poses = {int(f): w for f, w in poses.items()}
    frames = np.asarray(sorted(poses), dtype=np.int64)
    if frames.size and (frames.min() < 0 or frames.max() >= T):
        raise ValueError(f"poses: frames must be in 0..{T - 1}, got {frames.tolist()}")
    P = np.zeros((len(frames), K))
    for i, f in enumerate(frames):
        w = np.asarray(poses[int(f)], dtype=np.float64)
        if w.shape != (K,):
            raise ValueError(f"poses: the pose at frame {f} has shape {w.shape}; expected ({K},) weights, one per shape")
        if not np.isfinite(w).all():
            raise ValueError(f"poses: the pose at frame {f} has non-finite weights")
        P[i] = w
    return frames, P


def _solution(X) -> np.ndarray:
    X = np.asarray(X, dtype=np.float64)
    if X.ndim != 2:
        raise ValueError(f"X: expected the (T, K) solution weights, got shape {X.shape}")
    return np.nan_to_num(X)


def linear_correction(X, poses: Mapping, ridge: float = RIDGE) -> np.ndarray:
    """Design (a): ``W = X (I + Δ)``, ``Δ = argmin ||X_p (I + Δ) - P||² + ridge ||Δ||²``.

    ``Δ = (X_pᵀX_p + ridge I)⁻¹ X_pᵀ R`` (K×K), computed in its n×n form
    ``X Δ = X X_pᵀ (X_p X_pᵀ + ridge I)⁻¹ R`` (the push-through identity). Unbounded: see
    :func:`learn_from_poses` for the clipped result.

    Parameters
    ----------
    X : (T, K) float — the method's solution (NaN rows, frames without data, are taken as 0).
    poses : {frame: (K,) float} — the posed weights.
    ridge : float > 0 — in squared weights.

    Returns
    -------
    (T, K) float64; ``X`` (a copy) when there is no pose.

    Raises
    ------
    ValueError : a pose frame out of range, a pose of the wrong length, ridge <= 0.
    """
    X = _solution(X)
    if not ridge > 0:
        raise ValueError(f"ridge: expected > 0 (the pull of the correction towards the identity), got {ridge}")
    frames, P = _poses(X, poses)
    return _pushed_through(X, X, frames, P, ridge) if len(frames) else X.copy()


def _pushed_through(X, F, frames, P, ridge: float) -> np.ndarray:
    """``X + F F_pᵀ (F_p F_pᵀ + ridge I)⁻¹ (P − X_p)``: the ridge regression of the posed residuals
    on the features ``F`` (T, n) in its poses × poses form (the push-through identity), shared by
    :func:`linear_correction` (``F = X``) and :func:`source_correction` (the source's features)."""
    A = F[frames]
    return X + (F @ A.T) @ np.linalg.solve(A @ A.T + ridge * np.eye(len(frames)), P - X[frames])


def _rbf(F: np.ndarray, frames: np.ndarray, R: np.ndarray, width=None) -> np.ndarray:
    """``Φ(F, F_p) (Φ(F_p, F_p) + εI)⁻¹ R``, Gaussian ``Φ`` of width ``width`` (default: the
    median distance between the posed frames' features, 1 for a single pose), by
    :class:`scipy.interpolate.RBFInterpolator` (kernel ``exp(-(e r)²)`` with ``e = 1 / (√2 width)``,
    no polynomial, smoothing ε)."""
    Fp = F[frames]
    if width is None:
        d = pdist(Fp)
        d = d[d > 0]
        width = float(np.median(d)) if d.size else 1.0
    if not width > 0:
        raise ValueError(f"width: expected > 0 (feature units), got {width}")
    rbf = RBFInterpolator(Fp, R, kernel="gaussian", epsilon=1.0 / (np.sqrt(2.0) * width), degree=-1, smoothing=RBF_EPS)
    return rbf(F)


def _filled(features, T: int) -> np.ndarray:
    F = _features(features)
    if len(F) != T:
        raise ValueError(f"features: expected {T} frames like X, got {len(F)}")
    good = _has_data(F)
    if not good.any():
        raise ValueError("features: no frame has data")
    return F if good.all() else fill_gaps(F, good)


def pose_space_correction(X, features, poses: Mapping, width=None) -> np.ndarray:
    """Design (b), pose-space deformation (Lewis et al. 2000): ``W = X + Φ(F, F_p) (Φ(F_p, F_p) + εI)⁻¹ (P - X_p)``.

    Gaussian ``Φ(a, b) = exp(-|a - b|² / 2 width²)``; ``width`` defaults to the median distance
    between the posed frames' features; ``ε`` = :data:`RBF_EPS`. Interpolates the poses (up to
    round-off); frames without features take the features filled across the gap
    (:func:`core.gaps.fill_gaps`). Unbounded.

    Parameters
    ----------
    X : (T, K) float; features : (T, F) or (T, M, 3) float; poses : {frame: (K,) float};
    width : float > 0, optional — in feature units.

    Returns
    -------
    (T, K) float64; ``X`` (a copy) when there is no pose.

    Raises
    ------
    ValueError : shapes that disagree, a posed frame without features, a bad pose.
    """
    X = _solution(X)
    frames, P = _poses(X, poses)
    if not len(frames):
        return X.copy()
    raw = _features(features)
    if len(raw) == len(X) and not _has_data(raw)[frames].all():
        bad = frames[~_has_data(raw)[frames]].tolist()
        raise ValueError(f"poses: frames {bad} have no source data to learn from; pose frames with data")
    F = _filled(raw, len(X))
    return X + _rbf(F, frames, P - X[frames], width)


def learn_from_poses(X, features, poses: Mapping, design: str = "linear+rbf", ridge: float = RIDGE,
                     lower=0.0, upper=1.0, width=None) -> np.ndarray:
    """The whole take's weights learned from the example poses, inside ``lower…upper``.

    ``design``: ``"linear"`` (:func:`linear_correction`), ``"rbf"`` (:func:`pose_space_correction`
    on ``X``) or ``"linear+rbf"`` (the default: the RBF interpolation of the residuals the linear
    correction leaves, so poses inside the bounds are reproduced exactly), then clipped to
    ``lower <= w <= upper``. With no pose, ``X`` is returned unchanged (a copy, not clipped).

    Parameters
    ----------
    X : (T, K) float — the method's solution.
    features : (T, F) or (T, M, 3) float — the source's expression features (see the module docstring).
    poses : {frame: (K,) float} — posed weights (unposed shapes 0; see :func:`poses_from_items`).
    design : one of :data:`DESIGNS`.
    ridge : float > 0; lower, upper : float or (K,) float; width : float, optional.

    Returns
    -------
    (T, K) float64.

    Raises
    ------
    ValueError : an unknown design, shapes that disagree, a pose out of range or without data.
    """
    if design not in DESIGNS:
        raise ValueError(f"design: expected one of {DESIGNS}, got {design!r}")
    X = _solution(X)
    if not len(poses):
        return X.copy()
    if design == "linear":
        W = linear_correction(X, poses, ridge)
    elif design == "rbf":
        W = pose_space_correction(X, features, poses, width)
    else:
        W = pose_space_correction(linear_correction(X, poses, ridge), features, poses, width)
    return np.clip(W, lower, upper)


#: the ridges (relative to the posed source features' mean square) of :func:`source_correction`
#: that :func:`choose_by_loo` tries; the largest is "no correction" to 1e-4
SOURCE_RIDGES = (1e-3, 1e-2, 0.1, 1.0, 10.0, 100.0, 1e4)
#: half-width (frames) of the ease that keys each pose at its own frame (:func:`keyed`)
KEY_HALF = 3


def source_correction(X, features, poses: Mapping, ridge: float) -> np.ndarray:
    """The solution corrected by a ridge regression of the residuals on the source's features:
    ``W = X + F F_pᵀ (F_p F_pᵀ + ridge s² I)⁻¹ (P - X_p)``, ``s²`` the posed features' mean square
    (so ``ridge`` is relative: 1e-3 nearly interpolates the poses, 1e4 leaves ``X``). Where
    :func:`linear_correction` maps the solution's own combinations, this maps what the *source*
    does (the map's input), so it adds shapes the solution never used; the regularisation pulls
    it towards ``X``. Unbounded."""
    X = _solution(X)
    if not ridge > 0:
        raise ValueError(f"ridge: expected > 0, got {ridge}")
    frames, P = _poses(X, poses)
    if not len(frames):
        return X.copy()
    F = _filled(features, len(X))
    s2 = max(float((F[frames] ** 2).sum()) / len(frames), 1e-300)
    return _pushed_through(X, F, frames, P, ridge * s2)


def _candidates(X, features, lower, upper) -> dict:
    """``{label: poses -> (T, K) weights}``, ordered from the most regularised (``X`` itself) to
    the least: the source correction at decreasing ridge, then :func:`learn_from_poses`."""
    out = {"none": lambda poses: np.clip(X, lower, upper)}
    for r in SOURCE_RIDGES[::-1]:
        out[f"source-regressed correction, ridge {r:g}"] = (
            lambda r: lambda poses: np.clip(source_correction(X, features, poses, r), lower, upper))(r)
    out["linear + pose-space correction"] = lambda poses: learn_from_poses(X, features, poses, lower=lower, upper=upper)
    return out


def choose_by_loo(X, features, poses: Mapping, gram=None, lower=0.0, upper=1.0) -> tuple:
    """``(W (T, K), label, loo)``: the correction of ``X`` towards the poses that predicts held-out
    poses best, by leave-one-out over the poses themselves with the one-standard-error rule.

    Candidates (:func:`_candidates`, most regularised first): ``X`` unchanged, the
    :func:`source_correction` at each ridge of :data:`SOURCE_RIDGES` (largest first), and
    :func:`learn_from_poses`. Each predicts every pose from the others; its error is
    ``dᵀ gram d`` (``d`` the predicted minus the posed weights; ``gram = D Dᵀ`` of the rig's
    deltas makes it the squared vertex error, identity when None). The pick is the most
    regularised candidate whose mean error is within one standard error of the smallest
    (Hastie, Tibshirani & Friedman, *Elements of Statistical Learning* §7.10): with 2 poses one
    pose is all the evidence, so a correction must beat leaving ``X`` clearly to be used. Then
    each pose is keyed at its own frame (:func:`keyed`). Written here because the choice is
    over these designs, not one estimator's hyper-parameter (sklearn's CV needs an estimator).

    With no pose: ``(X clipped, "none", {})``; with one: nothing to hold out, the
    :func:`learn_from_poses` correction (the single pose's evidence, as before).
    ``loo``: ``{label: mean held-out error}``.
    """
    X = _solution(X)
    frames, P = _poses(X, poses)
    cands = _candidates(X, features, lower, upper)
    if not len(frames):
        return np.clip(X, lower, upper), "none", {}
    if len(frames) == 1:
        label = "linear + pose-space correction"
        return keyed(cands[label](poses), poses, lower, upper), label, {}
    G = np.eye(X.shape[1]) if gram is None else np.asarray(gram, dtype=np.float64)
    F = _filled(features, len(X))
    errs = {label: np.zeros(len(frames)) for label in cands}
    for h in range(len(frames)):
        # every candidate's prediction at a frame depends only on that frame and the posed ones:
        # fit on those rows alone (the held-out frame last), not the whole take
        rows = np.r_[np.delete(frames, h), frames[h]]
        rest = {i: P[j] for i, j in enumerate(np.delete(np.arange(len(frames)), h))}
        for label, fit in _candidates(X[rows], F[rows], lower, upper).items():
            d = fit(rest)[-1] - P[h]
            errs[label][h] = float(d @ G @ d)
    best = min(errs, key=lambda k: errs[k].mean())
    se = errs[best].std(ddof=1) / np.sqrt(len(frames))
    label = next(k for k in errs if errs[k].mean() <= errs[best].mean() + se)
    return keyed(cands[label](poses), poses, lower, upper), label, {k: float(v.mean()) for k, v in errs.items()}


def keyed(W, poses: Mapping, lower=0.0, upper=1.0, half: int = KEY_HALF) -> np.ndarray:
    """``W`` with each pose set exactly at its own frame and eased in and out over ``half``
    frames each side (a raised cosine of the pose's residual), clipped to the bounds; the posed
    frames themselves hold the pose (clipped)."""
    W = _solution(W).copy()
    frames, P = _poses(W, poses)
    T = len(W)
    R = P - W[frames]
    for f, r in zip(frames, R):
        t = np.arange(max(0, f - half), min(T, f + half + 1))
        W[t] += (0.5 * (1 + np.cos(np.pi * (t - f) / (half + 1))))[:, None] * r
    W[frames] = P
    return np.clip(W, lower, upper)


def poses_from_items(items, names: Sequence[str], n_frames: int) -> dict:
    """``{frame: (K,) weights}`` from the example-poses file's items
    ``[{"frame": F, "weights": {"<shape>": w, ...}}, ...]`` (shapes a pose does not list are 0).

    Raises
    ------
    ValueError : an item without ``frame``/``weights``, a frame out of ``0..n_frames-1`` or
        given twice, an unknown shape name (with "did you mean"), a non-finite weight.
    """
    names = list(names)
    index = {n: i for i, n in enumerate(names)}
    out: dict = {}
    for i, item in enumerate(items):
        if not isinstance(item, Mapping) or "frame" not in item or not isinstance(item.get("weights"), Mapping):
            raise ValueError(f"example pose {i}: expected {{'frame': F, 'weights': {{shape: w, ...}}}}, got {item!r}")
        f = item["frame"]
        if isinstance(f, bool) or int(f) != f or not 0 <= int(f) < n_frames:
            raise ValueError(f"example pose {i}: frame {f!r} is not a frame of the take (0..{n_frames - 1})")
        f = int(f)
        if f in out:
            raise ValueError(f"example pose {i}: frame {f} is posed twice")
        w = np.zeros(len(names))
        for name, v in item["weights"].items():
            if name not in index:
                hint = difflib.get_close_matches(str(name), names, n=3)
                raise ValueError(f"example pose {i} (frame {f}): no target shape {name!r}"
                                 + (f"; did you mean {hint}?" if hint else ""))
            if not np.isfinite(float(v)):
                raise ValueError(f"example pose {i} (frame {f}): weight of {name!r} is {v!r}")
            w[index[name]] = float(v)
        out[f] = w
    return out
