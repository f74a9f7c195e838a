"""Range-of-motion alignment: actor-specific sparse blendshapes (Ribera et al. 2017, §4).

Given an actor's range-of-motion (ROM) take as marker deltas ``Δa_f`` (T, M, 3), an
initial guess ``Δg_k`` (K, M, 3) of the actor's blendshapes (the target rig's marker
blendshapes warped into the actor's proportions by the RBF calibration, Seol 2012 §3.2) and
the actor's neutral markers, find personalised actor blendshapes ``Δp_k`` that match the
actor's own range of motion while keeping the local shape of ``Δg_k`` and the relations
between shapes:

    E_Align(Δp) = E_Match + β E_Mesh + γ E_CEG                                 (eq. 4)
    E_Match = 1/F Σ_f Σ_k c̃_kf ‖Δp_k − diag(u_k) Δa_f‖²                          (eq. 10)
    E_Mesh  = 1/M Σ_k ‖L_M (Δp_k − Δg_k)‖²                                      (eq. 11)
    E_CEG   = 1/M Σ_k ‖Λ(Δp_k) − Λ(Δs_k)‖²,  Λ(x_k) = Σ_l c_kl (x_l − x_k) / Σ_l |c_kl|  (eq. 12, 13)

with β = 0.01, γ = 0.1, f running over the F key expressions (§4.2), c̃ the
contrast-enhanced similarity (eq. 5–8), u_k the local-support masks (§4.3), L_M the
cotangent Laplacian of a triangulation of the actor's neutral markers plus eyelid/lip contact
edges (§4.4) and Λ the signed cross-expression graph Laplacian (§4.5).

The energy is separable in x/y/z and the system matrix is the same for the three
coordinates (§4.6). The paper factorises the sparse (MK × MK) matrix; its fill is dense in K
(E_CEG couples every pair of shapes), so SuperLU takes seconds. With the paper's eq. 10 the
matrix is a Kronecker sum, (diag C_k/F + γ/M GᵀG) ⊗ I_M + I_K ⊗ β/M L_MᵀL_M, solved exactly
through two small eigendecompositions instead (:meth:`AlignmentProblem.solve`; ``"splu"``
and ``"dense"`` remain as references).

Extensions (off by default; docs/geometric.md has the numbers): ``mask="residual"``
weights E_Match's residual by u_k instead of scaling the actor's motion by it,
``exclusive=True`` lets each key frame pull only its most similar shape, and
``peak_power=q`` weights frames by how far along the shape they are (:func:`amplitude`).
On a mixed ARKit range-of-motion take the paper's settings shrink the blendshapes (the
correlation of eq. 5 is blind to amplitude; §6.3 notes the under-estimation).

Choices the paper leaves open (each also said where it is made):

* ``Δs_k`` (the rig's own sparse blendshapes, used for the similarities, the trust values,
  the masks and E_CEG) defaults to the initial guess ``Δg_k``: correlations are invariant to
  the uniform scale, and the RBF warp only re-proportions the rig, so the two give nearly the
  same numbers while ``Δg_k`` lives in the actor's frame like ``Δa_f``. Pass ``rig_deltas`` to
  use the rig's own.
* Contact edges are not triangle edges, so they carry no cotangent weight; they enter L_M as
  graph-Laplacian edges weighted by the mean |cotangent weight| of the triangulation.
* A ridge ``ε‖Δp − Δg‖²`` with ε = 1e-9 × (largest diagonal entry) keeps the system
  non-singular when a shape is never matched (then E_Mesh and E_CEG fix it only up to a
  translation); it changes the solution by a relative ~1e-9.
* Frames with a missing marker are left out of the similarity (c = 0) and the key frames.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np
import scipy.sparse as sp
from scipy.ndimage import gaussian_filter1d
from scipy.signal import find_peaks
from scipy.sparse.linalg import LinearOperator, cg, splu
from scipy.special import expit

from core import geometry
from core.geometry import marker_triangulation  # noqa: F401  (Ribera §4.4: part of this module's API)

#: Ribera 2017 defaults (§4, eq. 4 and eq. 7)
BETA = 0.01
GAMMA = 0.1
STEEPNESS = 15.0


# -- validation --------------------------------------------------------------------------

def _points(a, name, shape):
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, arr.shape)):
        want = "(" + ", ".join("?" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name}: expected shape {want}, got {arr.shape}")
    return arr


# -- §4.1 facial motion similarity ------------------------------------------------------

def motion_similarity(actor_deltas, rig_deltas):
    r"""Correlation of every rig shape with every actor frame, in delta form.

    .. math:: c_{kf} = \frac{\Delta a_f \cdot \Delta s_k}{\|\Delta a_f\|\,\|\Delta s_k\|}

    (Ribera et al. 2017, eq. 5: Pearson's coefficient with the neutral face as the mean).

    Parameters
    ----------
    actor_deltas : (T, M, 3) float
        Marker displacements from the neutral, one row per frame.
    rig_deltas : (K, M, 3) float
        Sparse delta blendshapes on the same markers.

    Returns
    -------
    c : (K, T) float64 in [-1, 1]; 0 where either displacement is zero or not finite.

    Raises
    ------
    ValueError
        Shapes disagree.
    """
    a = _points(actor_deltas, "actor_deltas", (None, None, 3))
    s = _points(rig_deltas, "rig_deltas", (None, a.shape[1], 3))
    A = a.reshape(len(a), -1)
    S = s.reshape(len(s), -1)
    good = np.isfinite(A).all(axis=1)
    A = np.where(good[:, None], A, 0.0)
    na = np.linalg.norm(A, axis=1)
    ns = np.linalg.norm(S, axis=1)
    num = S @ A.T
    den = np.outer(ns, na)
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
    return np.clip(c, -1.0, 1.0)


def trust(rig_deltas):
    r"""Trust value of every shape: unique and strongly moving shapes are trusted most.

    Shapes are ordered by total displacement :math:`d_k = \|\Delta s_k\|`, largest first;
    with :math:`c^+_{kl} = \max(0, c_{kl})` the between-shape correlation (eq. 5 applied to
    two shapes) and the sums over the strictly lower triangle in that order,

    .. math:: t_k = 1 - \frac{\sum_{l<k} c^+_{kl}}{\max_{k'} \sum_{l<k'} c^+_{k'l}}

    (Ribera et al. 2017, eq. 6). The largest shape gets t = 1. When no shape correlates
    positively with a larger one every t is 1.

    Parameters
    ----------
    rig_deltas : (K, M, 3) float

    Returns
    -------
    t : (K,) float64 in [0, 1], in the input order of the shapes.
    """
    s = _points(rig_deltas, "rig_deltas", (None, None, 3))
    K = len(s)
    d = np.linalg.norm(s.reshape(K, -1), axis=1)
    order = np.argsort(-d, kind="stable")
    C = motion_similarity(s[order], s[order])  # (K, K), C[i, j] between order[i] and order[j]
    rows = np.tril(np.maximum(C, 0.0), k=-1).sum(axis=1)
    top = rows.max() if K else 0.0
    t_sorted = 1.0 - rows / top if top > 0 else np.ones(K)
    t = np.empty(K)
    t[order] = t_sorted
    return t


def contrast(c, r=STEEPNESS):
    r"""Contrast enhancement of correlations (Ribera et al. 2017, eq. 7).

    .. math:: b(c) = \frac{e^{rc}}{e^{r/2} + e^{rc}} = \frac{1}{1 + e^{-r(c - 1/2)}}

    A logistic step centred at c = 1/2 with steepness ``r`` (15 in the paper); evaluated as
    :func:`scipy.special.expit` so large ``r`` does not overflow.
    """
    return expit(float(r) * (np.asarray(c, dtype=np.float64) - 0.5))


def blended_similarity(actor_deltas, rig_deltas, r=STEEPNESS, trust_values=None):
    r"""Contrast-enhanced similarity :math:`\tilde c_{kf}` (Ribera et al. 2017, eq. 8).

    .. math:: \tilde c_{kf} = (1 - t_k)\, c^+_{kf} + t_k\, b(c^+_{kf})

    with :math:`c^+ = \max(0, c)` from :func:`motion_similarity`, :math:`t_k` from :func:`trust` and
    b from :func:`contrast`.

    Parameters
    ----------
    actor_deltas : (T, M, 3)
    rig_deltas : (K, M, 3)
    r : float
        Steepness of b.
    trust_values : (K,) float, optional
        Precomputed :func:`trust` of ``rig_deltas``.

    Returns
    -------
    (K, T) float64 in [0, 1]
    """
    cp = np.maximum(motion_similarity(actor_deltas, rig_deltas), 0.0)
    t = trust(rig_deltas) if trust_values is None else np.asarray(trust_values, dtype=np.float64)
    if t.shape != (len(cp),):
        raise ValueError(f"trust_values: expected shape ({len(cp)},), got {t.shape}")
    return (1.0 - t)[:, None] * cp + t[:, None] * contrast(cp, r)


def amplitude(actor_deltas, rig_deltas):
    r"""How far along each shape every frame is, relative to the take's furthest frame.

    .. math:: \alpha_{kf} = \frac{\max(0, \omega_{kf})}{\max_{f'} \omega_{kf'}},\quad
              \omega_{kf} = \frac{\Delta a_f \cdot \Delta s_k}{\|\Delta s_k\|^2}

    (:math:`\omega_{kf}` is the weight of shape k alone that fits frame f best). Not in
    Ribera et al. 2017: the correlation of eq. 5 is blind to amplitude, so a ramp towards an
    expression correlates as much as its peak, and E_Match (eq. 10) then averages the ramp
    into the blendshape, shrinking it (the under-estimation the paper notes in §6.3).
    ``personalize(peak_power=q)`` multiplies c̃_kf by :math:`\alpha_{kf}^q` in E_Match.

    Returns
    -------
    (K, T) float64 in [0, 1]; 0 for non-finite frames and for shapes no frame moves along.
    """
    a = _points(actor_deltas, "actor_deltas", (None, None, 3))
    s = _points(rig_deltas, "rig_deltas", (None, a.shape[1], 3))
    A = a.reshape(len(a), -1)
    A = np.where(np.isfinite(A).all(axis=1)[:, None], A, 0.0)
    S = s.reshape(len(s), -1)
    n2 = np.einsum("ij,ij->i", S, S)
    w = np.maximum(np.divide(S @ A.T, n2[:, None], out=np.zeros((len(S), len(A))), where=n2[:, None] > 0), 0.0)
    top = w.max(axis=1, keepdims=True) if w.size else w
    return np.divide(w, top, out=np.zeros_like(w), where=top > 0)


# -- §4.2 key expressions ----------------------------------------------------------------

def key_expressions(sim, valid=None, sigma=1.0, distance=1, prominence=None):
    """Frames where the actor's expression is most similar to the rig's shapes (§4.2).

    Every row of ``sim`` (one shape over the take) is low-pass filtered with a 3-frame
    Gaussian (``sigma`` 1 frame, radius 1), the rows are summed per frame, and the local
    maxima of that cumulative curve are the key frames (Ribera et al. 2017 §4.2, Fig. 8,
    after Coleman et al. 2008).

    Parameters
    ----------
    sim : (K, T) float
        :func:`blended_similarity`.
    valid : (T,) bool, optional
        Frames that may be chosen (e.g. no missing marker).
    sigma : float
        Gaussian width in frames; the kernel is truncated to radius ``max(1, round(sigma))``,
        i.e. three taps for the paper's setting.
    distance, prominence
        Passed to :func:`scipy.signal.find_peaks` to thin the peaks; the defaults keep every
        strict local maximum as the paper does.

    Returns
    -------
    frames : (F,) int64, increasing.
    cumulative : (T,) float64, the summed filtered similarity (Fig. 8).

    Raises
    ------
    ValueError
        ``sim`` not 2-D or ``valid`` of the wrong length.
    """
    sim = np.asarray(sim, dtype=np.float64)
    if sim.ndim != 2:
        raise ValueError(f"sim: expected (K, T) similarities, got shape {sim.shape}")
    T = sim.shape[1]
    radius = max(1, int(round(sigma)))
    filtered = gaussian_filter1d(sim, sigma, axis=1, mode="nearest", truncate=radius / sigma) if sigma > 0 else sim
    cumulative = filtered.sum(axis=0)
    frames, _ = find_peaks(cumulative, distance=distance, prominence=prominence)
    if valid is not None:
        valid = np.asarray(valid, dtype=bool)
        if valid.shape != (T,):
            raise ValueError(f"valid: expected shape ({T},), got {valid.shape}")
        frames = frames[valid[frames]]
    return frames.astype(np.int64), cumulative


# -- §4.3 local support ----------------------------------------------------------------

def support_masks(rig_deltas):
    r"""Soft local-support mask of every shape (Ribera et al. 2017 §4.3, eq. 10).

    .. math:: u_k^m = \|\Delta s_k^m\| / \max_{m'} \|\Delta s_k^{m'}\|

    Returns
    -------
    (K, M) float64 in [0, 1]; a zero row for a shape that moves no marker.
    """
    s = _points(rig_deltas, "rig_deltas", (None, None, 3))
    n = np.linalg.norm(s, axis=2)
    top = n.max(axis=1, keepdims=True) if n.size else n
    return np.divide(n, top, out=np.zeros_like(n), where=top > 0)


# -- §4.4 marker mesh ----------------------------------------------------------------------

_CONTACT_PART = re.compile(r"eye|lid|mouth|lip", re.IGNORECASE)
_CONTACT_SIDE = re.compile(r"(Upper|Lower|Up|Down|Top|Bottom|Bot)", re.IGNORECASE)


def contact_edges(names):
    """Upper/lower eyelid and lip marker pairs found by name (Ribera et al. 2017 §4.4).

    Markers of an eye, lid, mouth or lip (not brow) pair up when their names agree after
    replacing Up/Upper/Top by Down/Lower/Bottom and dropping trailing digits, e.g. the AnimFace
    names ``Leye_Up``–``Leye_Down``, ``Mouth_Up``–``Mouth_Down``, ``Mouth_UpL1``–``Mouth_DownL``.

    Parameters
    ----------
    names : sequence of M str

    Returns
    -------
    (E, 2) int64 marker index pairs (upper, lower).
    """
    names = [str(n) for n in names]

    def key(n):
        if not _CONTACT_PART.search(n) or re.search("brow", n, re.IGNORECASE):
            return None
        m = _CONTACT_SIDE.search(n)
        if not m:
            return None
        side = "up" if m.group(1).lower() in ("upper", "up", "top") else "down"
        rest = (n[: m.start()] + "*" + n[m.end():]).rstrip("0123456789").lower()
        return side, rest

    ups, downs = {}, {}
    for i, n in enumerate(names):
        k = key(n)
        if k:
            (ups if k[0] == "up" else downs).setdefault(k[1], i)
    pairs = [(ups[k], downs[k]) for k in sorted(ups) if k in downs]
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


def marker_laplacian(points, faces, contacts=None, contact_weight=None):
    """Laplacian of the marker mesh for E_Mesh (Ribera et al. 2017 eq. 11).

    ``L = cotangent_laplacian(points, faces) + w_c · (D − A)_contacts`` — the cotangent
    Laplacian of the triangulation (positive semi-definite, rows summing to 0; see
    :mod:`core.geometry`) plus the graph Laplacian of the contact edges weighted by
    ``contact_weight`` (default: mean |off-diagonal cotangent weight|).

    Parameters
    ----------
    points : (M, 3)
    faces : (F, 3) int
    contacts : (E, 2) int, optional
    contact_weight : float, optional

    Returns
    -------
    (M, M) scipy.sparse.csr_matrix
    """
    P = _points(points, "points", (None, 3))
    M = len(P)
    L = geometry.cotangent_laplacian(P, faces)
    if contacts is None or len(contacts) == 0:
        return L
    E = np.asarray(contacts, dtype=np.int64).reshape(-1, 2)
    if E.min() < 0 or E.max() >= M:
        raise ValueError(f"contacts: marker indices must lie in [0, {M}), got [{E.min()}, {E.max()}]")
    if contact_weight is None:
        off = L - sp.diags(L.diagonal())
        contact_weight = float(np.abs(off.data).mean()) if off.nnz else 1.0
    A = sp.coo_matrix((np.full(len(E), float(contact_weight)), (E[:, 0], E[:, 1])), shape=(M, M)).tocsr()
    A = A + A.T
    return (L + sp.diags(np.asarray(A.sum(axis=1)).ravel()) - A).tocsr()


# -- §4.5 cross-expression graph -------------------------------------------------------

def cross_expression_laplacian(rig_deltas):
    r"""Signed, normalised graph Laplacian of the cross-expression graph (eq. 12).

    .. math:: \Lambda(x)_k = \frac{1}{\sum_{l\ne k} |c_{kl}|} \sum_{l\ne k} c_{kl}\,(x_l - x_k)

    with :math:`c_{kl}` the signed between-shape correlation (eq. 5). As a matrix acting on
    the stacked shapes (rows k): ``G[k, l] = c_kl / n_k`` for l ≠ k and
    ``G[k, k] = -Σ_{l≠k} c_kl / n_k``, ``n_k = Σ_{l≠k} |c_kl|``; a row is zero when shape k
    correlates with nothing. ``G @ 1 = 0``: a common change of all shapes costs nothing.

    Parameters
    ----------
    rig_deltas : (K, M, 3)

    Returns
    -------
    G : (K, K) float64 (dense: the graph is complete).
    """
    s = _points(rig_deltas, "rig_deltas", (None, None, 3))
    C = motion_similarity(s, s)
    np.fill_diagonal(C, 0.0)
    n = np.abs(C).sum(axis=1)
    G = np.divide(C, n[:, None], out=np.zeros_like(C), where=n[:, None] > 0)
    G[np.diag_indices_from(G)] = -G.sum(axis=1)
    return G


# -- the alignment problem -------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class AlignmentProblem:
    """E_Align of Ribera et al. 2017 eq. 4 with all its ingredients fixed.

    Attributes
    ----------
    weights : (K, F) c̃_kf on the key frames
    targets : (F, M, 3) actor marker deltas Δa_f on the key frames
    masks : (K, M) u_k
    initial : (K, M, 3) Δg_k
    reference : (K, M, 3) Δs_k (for E_CEG)
    mesh_laplacian : (M, M) sparse L_M
    graph_laplacian : (K, K) Λ as a matrix G
    beta, gamma : float
    ridge : float, absolute ε of the ‖Δp − Δg‖² safeguard
    mask : {"target", "residual"}
        Where u_k enters E_Match: ``"target"`` is eq. 10 as printed,
        ‖Δp_k − diag(u_k) Δa_f‖²; ``"residual"`` weights the residual instead,
        ‖diag(u_k)(Δp_k − Δa_f)‖², so a marker's motion is not scaled down by its mask
        (see :func:`personalize`).
    """

    weights: np.ndarray
    targets: np.ndarray
    masks: np.ndarray
    initial: np.ndarray
    reference: np.ndarray
    mesh_laplacian: sp.csr_matrix
    graph_laplacian: np.ndarray
    beta: float = BETA
    gamma: float = GAMMA
    ridge: float = 0.0
    mask: str = "target"

    def __post_init__(self):
        if self.mask not in ("target", "residual"):
            raise ValueError(f"mask: expected 'target' or 'residual', got {self.mask!r}")

    @property
    def shape(self):
        return self.initial.shape

    def energies(self, p):
        """``{"match", "mesh", "ceg", "total"}`` of eq. 10, 11, 13 and 4 at ``p`` (K, M, 3).

        ``total`` = match + β mesh + γ ceg (the ridge is not included).
        """
        p = _points(p, "p", self.shape)
        K, M, _ = self.shape
        F = max(self.weights.shape[1], 1)
        # E_Match: sum_f sum_k c_kf ||p_k - u_k * a_f||^2 / F  (or ||u_k * (p_k - a_f)||^2)
        u = self.masks[:, None, :, None]
        if self.mask == "target":
            r = p[:, None] - u * self.targets[None]  # (K, F, M, 3)
        else:
            r = u * (p[:, None] - self.targets[None])
        match = float(np.einsum("kf,kfmc,kfmc->", self.weights, r, r)) / F
        d = (p - self.initial).transpose(1, 0, 2).reshape(M, -1)
        Ld = self.mesh_laplacian @ d
        mesh = float(np.sum(Ld * Ld)) / M
        e = (p - self.reference).reshape(K, -1)
        Ge = self.graph_laplacian @ e
        ceg = float(np.sum(Ge * Ge)) / M
        return {"match": match, "mesh": mesh, "ceg": ceg, "total": match + self.beta * mesh + self.gamma * ceg}

    def parts(self):
        """The pieces of the normal equations: ``(d, B, C, b)``.

        Half the gradient of E_Align + ε‖Δp − Δg‖² set to zero gives, for each coordinate c
        with unknown ``X_c = Δp[:, :, c]`` (K, M),

            d ∘ X_c + X_c B + C X_c = b_c,
            d_km = C_k h_km / F + ε,   B = β/M · L_MᵀL_M,   C = γ/M · GᵀG,
            b_c = 1/F · (u_k ∘ Σ_f c̃_kf Δa_f,c) + g_c B + C s_c + ε g_c

        with C_k = Σ_f c̃_kf, h_km = 1 for ``mask="target"``; for ``mask="residual"``
        h_km = u_km² and the first term of b_c has u_k² in place of u_k.

        Returns
        -------
        d : (K, M); B : (M, M) dense; C : (K, K); b : (K, M, 3).
        """
        K, M, _ = self.shape
        F = max(self.weights.shape[1], 1)
        L = self.mesh_laplacian
        B = (self.beta / M) * (L.T @ L).toarray()
        C = (self.gamma / M) * (self.graph_laplacian.T @ self.graph_laplacian)
        h = np.ones((K, M)) if self.mask == "target" else self.masks ** 2
        d = self.weights.sum(axis=1)[:, None] / F * h + self.ridge
        um = self.masks if self.mask == "target" else self.masks ** 2
        pulled = np.einsum("kf,fmc->kmc", self.weights, self.targets) * um[:, :, None] / F
        g = self.initial
        mesh_rhs = np.einsum("kmc,mn->knc", g, B)
        ceg_rhs = np.einsum("kl,lmc->kmc", C, self.reference)
        b = pulled + mesh_rhs + ceg_rhs + self.ridge * g
        return d, B, C, b

    def system(self):
        """Normal equations ``A x_c = b_c`` as one sparse (MK × MK) matrix (§4.6).

        Unknown ``x_c = Δp[:, :, c].ravel()`` (k-major, length MK);
        ``A = diag(vec d) + I_K ⊗ B + C ⊗ I_M`` with d, B, C from :meth:`parts`.

        Returns
        -------
        A : (MK, MK) scipy.sparse.csc_matrix, symmetric positive (semi-)definite.
        b : (MK, 3) float64.
        """
        d, B, C, b = self.parts()
        K, M = d.shape
        A = (sp.diags(d.ravel())
             + sp.kron(sp.identity(K, format="csr"), sp.csr_matrix(B))
             + sp.kron(sp.csr_matrix(C), sp.identity(M, format="csr"))).tocsc()
        return A, b.reshape(K * M, 3)

    def solve(self, method: str = "auto", rtol: float = 1e-12):
        """Minimiser of E_Align (+ ridge): (K, M, 3).

        Methods
        -------
        ``"kron"``
            Exact when d_km does not depend on m (``mask="target"``, the paper's eq. 10):
            then A = (diag d_k + C) ⊗ I_M + I_K ⊗ B is a Kronecker sum, and with
            eigendecompositions diag d + C = U Λ Uᵀ, B = V Σ Vᵀ,
            X_c = U [(Uᵀ b_c V) / (λ_i + σ_j)] Vᵀ: O(K³ + M³ + KM(K + M)) instead of a
            sparse factorisation whose fill is dense in K (hand-written: no library solves
            Sylvester-type Kronecker sums with a diagonal term; scipy.linalg.solve_sylvester
            would do it for the paper's case but not with the residual masks).
        ``"pcg"``
            Conjugate gradients on A, preconditioned by its exact per-shape diagonal blocks
            diag(d_k) + B + C_kk I (block Jacobi: K dense (M × M) inverses), started from the
            Kronecker-sum solve with the per-shape mean of d (``mask="residual"``).
        ``"splu"``
            scipy.sparse.linalg.splu of :meth:`system`, factorised once, three back-substitutions
            (the paper's §4.6 route; slow: fill is dense in K).
        ``"dense"``
            numpy.linalg.solve of the dense matrix (the reference).
        ``"auto"``
            ``"kron"`` when exact, else ``"pcg"``.

        Raises
        ------
        ValueError
            Unknown method.
        """
        if method not in ("auto", "kron", "pcg", "splu", "dense"):
            raise ValueError(f"method: expected 'auto', 'kron', 'pcg', 'splu' or 'dense', got {method!r}")
        K, M, _ = self.shape
        if method in ("splu", "dense"):
            A, b = self.system()
            if method == "splu":
                x = splu(A, permc_spec="MMD_ATA").solve(b)
            else:
                x = np.linalg.solve(A.toarray(), b)
            return x.reshape(K, M, 3).copy()
        d, B, C, b = self.parts()
        separable = np.ptp(d, axis=1).max() <= 1e-12 * max(np.abs(d).max(), 1e-300) if d.size else True
        if method == "auto":
            method = "kron" if separable else "pcg"
        if method == "kron" and not separable:
            raise ValueError("method='kron' needs d_km independent of m (mask='target'); use 'pcg'")
        lam, U = np.linalg.eigh(np.diag(d.mean(axis=1)) + C)
        sig, Vb = np.linalg.eigh(B)
        denom = lam[:, None] + sig[None, :]

        def kron_solve(R):  # R (K, M) -> X (K, M)
            return U @ ((U.T @ R @ Vb) / denom) @ Vb.T

        if method == "kron":
            return np.stack([kron_solve(b[:, :, c]) for c in range(3)], axis=-1)
        n = K * M
        op = LinearOperator((n, n), matvec=lambda x: (d * x.reshape(K, M) + x.reshape(K, M) @ B + C @ x.reshape(K, M)).ravel(),
                            dtype=np.float64)
        blocks = B[None] + (d[:, :, None] + np.diag(C)[:, None, None]) * np.eye(M)[None]
        inv = np.linalg.inv(blocks)  # (K, M, M), symmetric positive definite blocks
        pre = LinearOperator((n, n), matvec=lambda x: np.einsum("kmn,kn->km", inv, x.reshape(K, M)).ravel(),
                             dtype=np.float64)
        out = np.empty((K, M, 3))
        for c in range(3):
            x0 = kron_solve(b[:, :, c]).ravel()
            x, info = cg(op, b[:, :, c].ravel(), x0=x0, M=pre, rtol=rtol, atol=0.0, maxiter=20 * n)
            if info != 0:  # not converged: fall back on the exact sparse factorisation
                return self.solve("splu")
            out[:, :, c] = x.reshape(K, M)
        return out


@dataclass(frozen=True, eq=False)
class Personalization:
    """Result of :func:`personalize`.

    Attributes
    ----------
    deltas : (K, M, 3) personalised actor blendshapes Δp_k.
    blended_similarity : (K, T) c̃_kf over the whole take (Fig. 7, :func:`blended_similarity`).
    trust : (K,) t_k.
    key_frames : (F,) frame indices used in E_Match.
    cumulative : (T,) the summed filtered similarity the key frames are peaks of (Fig. 8).
    masks : (K, M) u_k.
    faces : (F_M, 3) marker triangulation; contacts (E, 2) contact edges.
    energies : {"initial": {...}, "aligned": {...}} from :meth:`AlignmentProblem.energies`.
    problem : the :class:`AlignmentProblem` that was solved.
    """

    deltas: np.ndarray
    blended_similarity: np.ndarray
    trust: np.ndarray
    key_frames: np.ndarray
    cumulative: np.ndarray
    masks: np.ndarray
    faces: np.ndarray
    contacts: np.ndarray
    energies: dict
    problem: AlignmentProblem
    extras: dict = field(default_factory=dict)


def personalize(actor_deltas, initial_guess, neutral, *, names: Optional[Sequence[str]] = None,
                rig_deltas=None, valid=None, faces=None, contacts=None, key_frames=None,
                beta: float = BETA, gamma: float = GAMMA, r: float = STEEPNESS,
                mask: str = "target", peak_power: float = 0.0, exclusive: bool = False,
                up=(0.0, 1.0, 0.0), forward=(0.0, 0.0, 1.0), ridge: float = 1e-9) -> Personalization:
    """Actor-specific sparse blendshapes by range-of-motion alignment (Ribera et al. 2017 §4).

    Minimises E_Align = E_Match + β E_Mesh + γ E_CEG (eq. 4, 10, 11, 13; see the module
    docstring) over the personalised marker blendshapes Δp (K, M, 3).

    Parameters
    ----------
    actor_deltas : (T, M, 3) float
        The actor's ROM take as stabilised marker displacements from the neutral (metres).
        NaN marks a missing marker.
    initial_guess : (K, M, 3) float
        Δg_k: the target rig's marker blendshapes in the actor's proportions (RBF
        calibration, e.g. ``core.calibrate.calibrate_deltas``).
    neutral : (M, 3) float
        The actor's neutral markers (triangulated for E_Mesh).
    names : sequence of M str, optional
        Marker names; used to find eyelid/lip contact edges (:func:`contact_edges`) when
        ``contacts`` is not given.
    rig_deltas : (K, M, 3) float, optional
        Δs_k, the rig's own sparse blendshapes, for similarity, trust, masks and E_CEG;
        default ``initial_guess``.
    valid : (T,) or (T, M) bool, optional
        False where a marker is missing; default: finite entries of ``actor_deltas``.
    faces : (F, 3) int, optional
        Marker triangulation; default :func:`marker_triangulation` of ``neutral``.
    contacts : (E, 2) int, optional
        Contact edges; default ``contact_edges(names)`` (none without names).
    key_frames : (F,) int, optional
        Frames for E_Match; default :func:`key_expressions` of the similarity.
    beta, gamma : float
        Weights of E_Mesh and E_CEG (paper: 0.01, 0.1).
    r : float
        Contrast steepness (paper: 15).
    mask : {"target", "residual"}
        ``"target"`` (default, eq. 10 as printed) pulls Δp_k towards diag(u_k) Δa_f, which
        also scales a marker's motion down by its mask value; ``"residual"`` weights the
        residual by u_k instead (markers outside the shape's support are left to E_Mesh,
        motion inside it is not shrunk). An extension; see docs/geometric.md for numbers.
    peak_power : float
        q >= 0; E_Match weights become c̃_kf · α_kf^q with α from :func:`amplitude`, so
        frames at the peak of an expression count more than the ramp towards it. 0 (the
        default) is the paper. An extension; see docs/geometric.md.
    exclusive : bool
        When True every key frame counts in E_Match only for the shape most similar to it
        (largest c̃_kf), so a frame of one expression does not also pull every correlated
        shape towards it. False (the default) is the paper. An extension.
    up, forward : (3,) float
        Head frame for the triangulation.
    ridge : float
        ε relative to the largest diagonal entry of the system (see module docstring).

    Returns
    -------
    Personalization

    Raises
    ------
    ValueError
        Inconsistent shapes, fewer than 3 markers, no usable frame, or key frames out of range.
    """
    a = _points(actor_deltas, "actor_deltas", (None, None, 3))
    T, M, _ = a.shape
    g = _points(initial_guess, "initial_guess", (None, M, 3))
    K = len(g)
    P0 = _points(neutral, "neutral", (M, 3))
    if not np.isfinite(g).all() or not np.isfinite(P0).all():
        raise ValueError("initial_guess and neutral must be finite")
    s = g if rig_deltas is None else _points(rig_deltas, "rig_deltas", (K, M, 3))
    if names is not None and len(names) != M:
        raise ValueError(f"names: expected {M} marker names, got {len(names)}")
    if valid is None:
        frame_ok = np.isfinite(a).all(axis=(1, 2))
    else:
        v = np.asarray(valid, dtype=bool)
        if v.shape == (T, M):
            v = v.all(axis=1)
        if v.shape != (T,):
            raise ValueError(f"valid: expected shape ({T},) or ({T}, {M}), got {np.asarray(valid).shape}")
        frame_ok = v & np.isfinite(a).all(axis=(1, 2))
    if not frame_ok.any():
        raise ValueError("actor_deltas: no frame has all markers; cannot measure similarity")
    a_clean = np.where(frame_ok[:, None, None], a, 0.0)

    t = trust(s)
    sim = blended_similarity(a_clean, s, r=r, trust_values=t)
    sim[:, ~frame_ok] = 0.0
    if key_frames is None:
        kf, cumulative = key_expressions(sim, valid=frame_ok)
    else:
        kf = np.asarray(key_frames, dtype=np.int64).ravel()
        if kf.size and (kf.min() < 0 or kf.max() >= T):
            raise ValueError(f"key_frames: indices must lie in [0, {T}), got [{kf.min()}, {kf.max()}]")
        if kf.size and not frame_ok[kf].all():
            raise ValueError(f"key_frames: frames {kf[~frame_ok[kf]].tolist()} have missing markers")
        cumulative = sim.sum(axis=0)
    if faces is None:
        faces = marker_triangulation(P0, up=up, forward=forward)
    faces = np.asarray(faces, dtype=np.int64)
    if contacts is None:
        contacts = contact_edges(names) if names is not None else np.zeros((0, 2), np.int64)
    contacts = np.asarray(contacts, dtype=np.int64).reshape(-1, 2)
    L = marker_laplacian(P0, faces, contacts)
    G = cross_expression_laplacian(s)
    u = support_masks(s)
    W = sim[:, kf]
    if exclusive and W.size:
        win = W.argmax(axis=0)
        Z = np.zeros_like(W)
        Z[win, np.arange(W.shape[1])] = W[win, np.arange(W.shape[1])]
        W = Z
    if peak_power < 0:
        raise ValueError(f"peak_power: expected q >= 0, got {peak_power}")
    if peak_power:
        W = W * amplitude(a_clean, s)[:, kf] ** float(peak_power)
    eps = 0.0
    if ridge:  # relative to the largest diagonal entry of the system (see system())
        F = max(len(kf), 1)
        LtL_diag = np.asarray(L.multiply(L).sum(axis=0)).ravel()
        top = W.sum(axis=1).max() / F + beta / M * LtL_diag.max() + gamma / M * (G * G).sum(axis=0).max()
        eps = float(ridge) * float(top)
    problem = AlignmentProblem(W, a_clean[kf], u, g, s, L, G, float(beta), float(gamma), eps, mask)
    p = problem.solve()
    energies = {"initial": problem.energies(g), "aligned": problem.energies(p)}
    return Personalization(p, sim, t, kf, cumulative, u, faces, contacts, energies, problem,
                           {"n_invalid_frames": int((~frame_ok).sum())})
