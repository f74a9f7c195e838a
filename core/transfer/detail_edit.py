r"""Fine-scale detail editing of a transferred sequence (Xu et al. 2014 §5.2, eq. 17-21).

The transferred details are the per-frame displacements ``D_t`` of
:attr:`core.transfer.TransferResult.details` (``T_t = neutral + w_t Δ + D_t``). Their Laplacian
coating is ``ξ_t = A D_t`` with ``A = L + εI`` the operator whose inverse reconstructs them
(:class:`~core.transfer.decompose.PoissonReconstructor`, screened as in the transfer), so an
edit of the coating maps back to the displacements exactly: ``ΔD_t = A^{-1} Δξ_t``.

1. **Selection** (§5.2 "dynamic facial detail selection"): paint (vertices within a brush
   radius of picked vertices, :meth:`DetailEditor.select_paint`) or a curve along a wrinkle
   with a distance threshold (:meth:`DetailEditor.select_curve`, :func:`region_near_curve`);
   the frames ``[t_s, t_e]`` where the selection's details are active: the coating ratio
   ``Σ|ξ_t| / Σ|ξ_{t_k}| >= μ`` (0.23) around the key frame (:func:`detail_window`). The
   coating measured is that of the *dynamic* details (``D_t`` is relative to the neutral, so
   the target's static skin detail does not count as activity).
2. **Key-frame edits** (each a :class:`KeyEdit`: a coating change ``Δ*`` on some vertices at
   ``t_k``): scale (enhance, diminish, remove; a linear fall-off band at the border,
   :meth:`DetailEditor.scale`), copy-paste (the selected details moved by a similarity —
   anchor vertex, rotation about the normal, scale — and pasted by closest points with the
   coating rotated to the local normals, :meth:`DetailEditor.copy_paste`), wrinkle reshape
   (eq. 17: the wrinkle region deformed so its curve follows a drawn curve, matched by arc
   length, with the Laplacian term λ_l = 0.2; the details are removed from the old region
   and pasted on the deformed one, :meth:`DetailEditor.reshape`).
3. **Propagation** (eq. 18-21, :func:`propagate_details`, :meth:`DetailEditor.apply`): the
   change ``E_t`` over the window with λ_e, λ_t, λ_s = 1, 0.1, 1. In the eigenbasis of the
   region's spatial Laplacian the space-time system splits into one tridiagonal time system
   per mode; the temporal responses of the modes form a numerically low-rank matrix, so the
   displacement change of every frame is a combination of ``r`` (typically 10-30) fields,
   each one Poisson back-substitution — not one solve per frame.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.spatial import cKDTree

from ..geometry import uniform_laplacian, vertex_adjacency, vertex_normals, weld_vertices
from ..io.gltf import read_rig
from .decompose import PoissonReconstructor, taubin_smooth
from .settings import TransferSettings

__all__ = ["region_near_curve", "region_near_points", "detail_window", "scale_details", "propagate_details",
           "KeyEdit", "DetailEditResult", "DetailEditor"]


def region_near_curve(positions, curve, radius: float) -> np.ndarray:
    """Vertices within ``radius`` of a polyline ``curve`` (m, 3) (§5.2 wrinkle selection)."""
    p = np.asarray(positions, dtype=np.float64)
    c = np.asarray(curve, dtype=np.float64)
    if c.ndim != 2 or c.shape[1] != 3 or len(c) < 1:
        raise ValueError(f"curve: expected (m, 3) points, got {c.shape}")
    best = np.full(len(p), np.inf)
    segs = [(c[i], c[i + 1]) for i in range(len(c) - 1)] or [(c[0], c[0])]
    for a, b in segs:
        ab = b - a
        den = float(ab @ ab)
        u = np.clip(((p - a) @ ab) / den, 0, 1) if den > 0 else np.zeros(len(p))
        best = np.minimum(best, np.linalg.norm(p - (a + u[:, None] * ab), axis=1))
    return np.flatnonzero(best <= radius)


def detail_window(coating_norms, region, key_frame: int, mu: float = 0.23) -> tuple[int, int]:
    r"""Frames ``[t_s, t_e]`` around ``key_frame`` where the region's details are active (§5.2):

    .. math:: \frac{\sum_{v \in P} |\xi^v_t|}{\sum_{v \in P} |\xi^v_{t_k}|} \ge \mu

    Parameters
    ----------
    coating_norms : (T, V) magnitudes of the (transferred) detail coating per frame
    region : (m,) int vertex ids
    key_frame : int
    mu : float, the threshold (0.23 in the paper)
    """
    s = np.asarray(coating_norms, dtype=np.float64)[:, np.asarray(region)].sum(1)
    if s[key_frame] <= 0:
        return key_frame, key_frame
    ok = s / s[key_frame] >= mu
    ts = key_frame
    while ts > 0 and ok[ts - 1]:
        ts -= 1
    te = key_frame
    while te < len(s) - 1 and ok[te + 1]:
        te += 1
    return ts, te


def falloff(faces, n_vertices: int, region, band: int = 2, adjacency=None) -> tuple[np.ndarray, np.ndarray]:
    """Vertices of ``region`` and of ``band`` edge rings around it, with the ring of each:
    ``(ids (m,), ring (m,))``, ring 0 inside the region. ``adjacency``: the mesh's
    :func:`~core.geometry.vertex_adjacency`, when the caller keeps one."""
    A = vertex_adjacency(np.asarray(faces), n_vertices) if adjacency is None else adjacency
    ring = np.full(n_vertices, -1)
    cur = np.zeros(n_vertices, dtype=bool)
    cur[np.asarray(region, dtype=np.int64)] = True
    ring[cur] = 0
    for r in range(1, band + 1):
        nxt = (A @ cur.astype(np.float64)) > 0
        ring[nxt & (ring < 0)] = r
        cur = cur | nxt
    ids = np.flatnonzero(ring >= 0)
    return ids, ring[ids]


def scale_details(details, faces, region, factor: float, band: int = 2) -> np.ndarray:
    """Key-frame edit: details (V, 3) scaled by ``factor`` in ``region`` (0 removes them, >1
    enhances), blending linearly to 1 over ``band`` rings outside it (§5.2: "linear
    interpolations between the edited and original coating values")."""
    d = np.asarray(details, dtype=np.float64)
    ids, ring = falloff(faces, len(d), region, band)
    s = np.ones(len(d))
    s[ids] = factor + (1 - factor) * ring / (band + 1)
    return d * s[:, None]


def _thomas_many(lower, diag, upper, rhs):
    """Solve tridiagonal systems with shared off-diagonals and per-system diagonals.

    diag : (m, n) (one diagonal per system), lower/upper : (n-1,), rhs : (m, n)."""
    m, n = diag.shape
    c = np.zeros((m, n))
    d = np.zeros((m, n))
    b0 = diag[:, 0]
    c[:, 0] = (upper[0] / b0) if n > 1 else 0
    d[:, 0] = rhs[:, 0] / b0
    for i in range(1, n):
        den = diag[:, i] - lower[i - 1] * c[:, i - 1]
        if i < n - 1:
            c[:, i] = upper[i] / den
        d[:, i] = (rhs[:, i] - lower[i - 1] * d[:, i - 1]) / den
    x = np.zeros((m, n))
    x[:, -1] = d[:, -1]
    for i in range(n - 2, -1, -1):
        x[:, i] = d[:, i] - c[:, i] * x[:, i + 1]
    return x


def _modal_response(faces, n_vertices: int, region, window, key_frame: int, lam_e: float, lam_t: float,
                    lam_s: float) -> tuple[np.ndarray, np.ndarray]:
    r"""Eigenbasis ``Φ`` (m, m) of the region Laplacian and the temporal response ``H`` (m, n)
    of each mode to a unit key-frame edit: the eq. 18-21 solution for an edit ``Δ*`` is
    ``E_t = Φ diag(H[:, t]) Φ^T Δ*``."""
    region = np.asarray(region, dtype=np.int64)
    ts, te = int(window[0]), int(window[1])
    if not ts <= key_frame <= te:
        raise ValueError(f"key_frame {key_frame} outside window {window}")
    n = te - ts + 1
    L = uniform_laplacian(np.asarray(faces), n_vertices)
    Ls = L[region][:, region].toarray()  # Dirichlet: degrees count edges leaving the region
    mu, Phi = np.linalg.eigh(Ls)
    # time operator: λ_t * path Laplacian + λ_e at key frame + λ_s at both ends
    main = np.zeros(n)
    if n > 1:
        main[:-1] += 1
        main[1:] += 1
    main *= lam_t
    main[key_frame - ts] += lam_e
    main[0] += lam_s
    main[-1] += lam_s
    off = -lam_t * np.ones(max(n - 1, 0))
    diag = main[None, :] + lam_t * mu[:, None]  # (m modes, n)
    rhs = np.zeros((len(region), n))
    rhs[:, key_frame - ts] = lam_e
    return Phi, _thomas_many(off, diag, off, rhs)


def propagate_details(edit, faces, n_vertices: int, region, window, key_frame: int,
                      lam_e: float = 1.0, lam_t: float = 0.1, lam_s: float = 1.0) -> np.ndarray:
    r"""Propagate a key-frame detail edit over the window (Xu et al. 2014 eq. 18-21).

    With ``E_t = D'_t - R(D_t)`` the change of the transferred details (zero outside the
    region and the window), eq. 18 becomes

    .. math:: \lambda_e\|E_{t_k} - \Delta^*\|^2 + \lambda_t\sum_t (\|d_t E\|^2 + \|d_s E\|^2)
              + \lambda_s(\|E_{t_s}\|^2 + \|E_{t_e}\|^2)

    with ``Δ* = D*_{t_k} - R(D_{t_k})`` the key-frame edit, ``d_t`` forward differences in time
    and ``d_s`` differences along mesh edges (edges leaving the region count, with the
    outside held at zero). The normal matrix is ``T_op ⊗ I + λ_t I ⊗ L_s``; in the eigenbasis
    of the region Laplacian ``L_s`` it splits into one tridiagonal time system per mode.

    Parameters
    ----------
    edit : (m, 3) ``Δ*`` on the region's vertices (in ``region`` order)
    faces : (F, 3) int, n_vertices : int
    region : (m,) int
    window : (t_s, t_e) inclusive, containing ``key_frame``
    lam_e, lam_t, lam_s : 1, 0.1, 1 in the paper

    Returns
    -------
    (t_e - t_s + 1, m, 3) the change ``E_t`` to add to the details in the window.

    Raises
    ------
    ValueError
        ``key_frame`` outside the window or ``edit`` not (m, 3).
    """
    m = len(np.asarray(region))
    e = np.asarray(edit, dtype=np.float64)
    if e.shape != (m, 3):
        raise ValueError(f"edit: expected ({m}, 3), got {e.shape}")
    Phi, H = _modal_response(faces, n_vertices, region, window, key_frame, lam_e, lam_t, lam_s)
    coef = Phi.T @ e  # (m, 3)
    out = np.empty((H.shape[1], m, 3))
    for c in range(3):  # one (m, m) x (m, n) product per coordinate
        out[:, :, c] = (Phi @ (coef[:, c, None] * H)).T
    return out


# -- the editor ---------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class KeyEdit:
    """A key-frame change of the detail coating: ``Δ* = D*_{t_k} - R(D_{t_k})`` of eq. 19.

    Attributes
    ----------
    frame : key frame ``t_k``
    vertices : (m,) editor (welded) vertex ids the change lives on
    delta : (m, 3) coating change
    selection : (s,) the selected vertices whose detail activity sets the window (§5.2 μ rule)
    kind : "scale" | "copy_paste" | "reshape"
    info : dict, what the edit did (for reports)
    at_frame : the same spatial operation at another frame: ``t -> (m, 3)`` coating change on
        ``vertices`` (used by ``apply(..., propagation="per_frame")``)
    """

    frame: int
    vertices: np.ndarray
    delta: np.ndarray
    selection: np.ndarray
    kind: str
    info: dict = field(default_factory=dict)
    at_frame: Optional[Callable] = None


@dataclass(frozen=True, eq=False)
class DetailEditResult:
    """The edited details (T, V, 3) float32 in the rig's vertex order, and how they were made."""

    details: np.ndarray
    window: tuple
    edit: KeyEdit
    rank: int
    max_change_mm: float
    seconds: dict


def _unit(x: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(x, axis=-1, keepdims=True)
    return np.divide(x, n, out=np.zeros_like(x), where=n > 0)


def _rotate_between(a: np.ndarray, b: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Rotate vectors ``x`` (n, 3) by the smallest rotations taking unit ``a`` onto unit ``b``
    (Rodrigues; antiparallel pairs are left unrotated: there is no preferred axis)."""
    a, b = _unit(np.atleast_2d(a)), _unit(np.atleast_2d(b))
    v = np.cross(a, b)
    c = np.einsum("ij,ij->i", a, b)
    s2 = np.einsum("ij,ij->i", v, v)
    k = np.divide(1.0, 1.0 + c, out=np.zeros_like(c), where=1.0 + c > 1e-12)
    vx = np.cross(v, x)
    return x + vx + k[:, None] * np.cross(v, vx) * (s2 > 0)[:, None]


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    k = _unit(np.asarray(axis, dtype=np.float64))
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def _arc_length(points: np.ndarray) -> np.ndarray:
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(seg)]
    return s / s[-1] if s[-1] > 0 else np.linspace(0, 1, len(points))


def region_near_points(positions, vertices, radius: float) -> np.ndarray:
    """Vertices within ``radius`` of any of the picked ``vertices`` (a paint brush, §5.2)."""

    p = np.asarray(positions, dtype=np.float64)
    ids = np.asarray(vertices, dtype=np.int64).ravel()
    if ids.size == 0:
        raise ValueError("vertices: paint at least one vertex")
    if ids.min() < 0 or ids.max() >= len(p):
        raise ValueError(f"vertices: ids must lie in [0, {len(p)})")
    hits = cKDTree(p).query_ball_point(p[ids], r=float(radius))
    return np.unique(np.concatenate([np.asarray(h, dtype=np.int64) for h in hits] + [ids]))


class DetailEditor:
    """Fine-scale editing of transferred details (Xu et al. 2014 §5.2).

    All vertex ids are the editor's (seam-welded) ids: :meth:`to_editor` maps rig vertex ids
    (what a viewer picks) to them, :meth:`to_rig` back. Nothing is modified in place:
    :meth:`apply` returns new details.

    Parameters
    ----------
    faces : (F, 3) int, neutral : (V, 3)    the transfer's topology and target neutral
    details : (T, V, 3)                      per-frame detail displacements (``TransferResult.details``)
    deltas : (K, V, 3), weights : (T, K)     the large-scale rig (for the surface the edits are drawn on)
    screening : the detail reconstruction's screened-Poisson weight (``TransferSettings.detail_screening``)
    laplacian : "uniform" | "cotangent" (``TransferSettings.laplacian``)
    """

    def __init__(self, faces, neutral, details, deltas=None, weights=None, screening: float = 0.01,
                 laplacian: str = "uniform"):
        self.neutral = np.asarray(neutral, dtype=np.float64)
        d = np.asarray(details)
        V = len(self.neutral)
        if d.ndim != 3 or d.shape[1:] != (V, 3) or len(d) == 0:
            raise ValueError(f"details: expected (T, {V}, 3), got {d.shape}")
        self.details = d
        self.wi, self.rep, self.faces = weld_vertices(self.neutral, faces)
        n = len(self.rep)
        self.poisson = PoissonReconstructor(self.faces, n, laplacian, self.neutral[self.rep] if laplacian == "cotangent" else None,
                                            screening)
        L = self.poisson.L
        # vertex adjacency of the welded mesh: built once here, so editors made by rebase share it
        self.adjacency = vertex_adjacency(self.faces, n)
        self.A = (L + self.poisson.eps * sp.identity(n)).tocsr() if screening > 0 else sp.csr_matrix(L)
        K = 0 if deltas is None else len(deltas)
        self.deltas = np.zeros((0, V, 3)) if deltas is None else np.asarray(deltas, dtype=np.float64)
        self.weights = np.zeros((len(d), 0)) if weights is None else np.asarray(weights, dtype=np.float64)
        if self.deltas.shape != (K, V, 3) or self.weights.shape != (len(d), K):
            raise ValueError(f"deltas, weights: expected ({K}, {V}, 3) and ({len(d)}, {K}), got {self.deltas.shape}, "
                             f"{self.weights.shape}")

    @classmethod
    def from_result(cls, result, settings=None, deltas=None, weights=None, details=None) -> "DetailEditor":
        """An editor of a :class:`~core.transfer.TransferResult` (with its ``settings``, default
        :class:`~core.transfer.TransferSettings`); ``deltas``/``weights``/``details`` override the
        result's (e.g. after large-scale or earlier detail edits)."""

        s = settings or TransferSettings()
        det = result.details if details is None else details
        if det is None:
            raise ValueError("the transfer has no details (it ran with details=False)")
        return cls(result.faces, result.neutral, det, result.deltas if deltas is None else deltas,
                   result.weights if weights is None else weights, s.detail_screening, s.laplacian)

    def rebase(self, details=None, deltas=None, weights=None) -> "DetailEditor":
        """The same editor (factorisation shared, nothing recomputed) on other details and/or
        another large-scale state — after an edit of either."""

        new = copy.copy(self)
        if details is not None:
            d = np.asarray(details)
            if d.shape != self.details.shape:
                raise ValueError(f"details: expected {self.details.shape}, got {d.shape}")
            new.details = d
        if deltas is not None or weights is not None:
            D = self.deltas if deltas is None else np.asarray(deltas, dtype=np.float64)
            W = self.weights if weights is None else np.asarray(weights, dtype=np.float64)
            if D.shape[1:] != self.deltas.shape[1:] or W.shape != (self.n_frames, len(D)):
                raise ValueError(f"deltas, weights: expected (K, {len(self.neutral)}, 3) and ({self.n_frames}, K), got "
                                 f"{D.shape}, {W.shape}")
            new.deltas, new.weights = D, W
        return new

    # -- ids and geometry ---------------------------------------------------------------------
    @property
    def n_frames(self) -> int:
        return len(self.details)

    @property
    def n_vertices(self) -> int:
        """Editor (welded) vertex count."""
        return len(self.rep)

    def to_editor(self, rig_ids) -> np.ndarray:
        """Rig vertex ids -> editor ids, order kept, repeats in a row dropped (a curve stays a chain)."""
        ids = np.asarray(rig_ids, dtype=np.int64).ravel()
        if ids.size and (ids.min() < 0 or ids.max() >= len(self.wi)):
            raise ValueError(f"vertex ids must lie in [0, {len(self.wi)})")
        w = self.wi[ids]
        return w[np.r_[True, w[1:] != w[:-1]]] if w.size else w

    def to_rig(self, editor_ids) -> np.ndarray:
        """Editor ids -> every rig vertex that welds to them (seam duplicates included)."""
        mask = np.zeros(self.n_vertices, dtype=bool)
        mask[np.asarray(editor_ids, dtype=np.int64)] = True
        return np.flatnonzero(mask[self.wi])

    def _frame(self, frame: int) -> int:
        f = int(frame)
        if not 0 <= f < self.n_frames:
            raise ValueError(f"frame {frame}: expected 0 <= frame < {self.n_frames}")
        return f

    def surface(self, frame: int) -> np.ndarray:
        """(n, 3) the large-scale surface ``neutral + w_t Δ`` at ``frame`` (editor ids)."""
        f = self._frame(frame)
        r = self.rep
        return self.neutral[r] + np.einsum("k,kvc->vc", self.weights[f], self.deltas[:, r])

    def normals(self, frame: int) -> np.ndarray:
        return vertex_normals(self.surface(frame), self.faces)

    def coating(self, frame: int) -> np.ndarray:
        """(n, 3) the detail coating ``ξ_t = A D_t`` at ``frame``."""
        f = self._frame(frame)
        return np.asarray(self.A @ np.asarray(self.details[f], dtype=np.float64)[self.rep])

    def activity(self, vertices) -> np.ndarray:
        """(T,) ``Σ_{v ∈ vertices} |ξ_t^v|`` for every frame (only the rows needed are formed)."""
        v = np.asarray(vertices, dtype=np.int64)
        Ar = self.A[v]
        cols = np.unique(Ar.indices)
        Ar = Ar[:, cols]
        d = np.asarray(self.details[:, self.rep[cols]], dtype=np.float64)  # (T, c, 3)
        T = len(d)
        X = (Ar @ d.transpose(1, 0, 2).reshape(len(cols), 3 * T)).reshape(len(v), T, 3)
        return np.linalg.norm(X, axis=2).sum(0)

    def window(self, vertices, key_frame: int, mu: float = 0.23) -> tuple[int, int]:
        """``[t_s, t_e]`` by the coating ratio μ on ``vertices`` (:func:`detail_window`)."""
        return detail_window(self.activity(vertices)[:, None], [0], self._frame(key_frame), mu)

    def mean_edge(self, vertices=None, positions=None) -> float:
        """Mean edge length (m) of the surface at frame 0, or among ``vertices`` of ``positions``."""
        X = self.surface(0) if positions is None else positions
        e = np.concatenate([self.faces[:, [0, 1]], self.faces[:, [1, 2]], self.faces[:, [2, 0]]])
        if vertices is not None:
            inside = np.zeros(self.n_vertices, dtype=bool)
            inside[np.asarray(vertices, dtype=np.int64)] = True
            sel = inside[e].all(1)
            if sel.any():
                e = e[sel]
        return float(np.linalg.norm(X[e[:, 0]] - X[e[:, 1]], axis=1).mean())

    # -- selection ----------------------------------------------------------------------------
    def select_paint(self, vertices, radius: float, frame: int = 0) -> np.ndarray:
        """Editor ids within ``radius`` (m) of the painted editor ids ``vertices`` at ``frame``."""
        return region_near_points(self.surface(frame), vertices, radius)

    def select_curve(self, curve, radius: float, frame: int = 0) -> np.ndarray:
        """Editor ids within ``radius`` (m) of the polyline through the editor ids ``curve``
        (a wrinkle sketched vertex by vertex) at ``frame``; the curve's vertices included."""
        X = self.surface(frame)
        c = np.asarray(curve, dtype=np.int64)
        if c.size == 0:
            raise ValueError("curve: pick at least one vertex")
        return np.union1d(region_near_curve(X, X[c], radius), c)

    # -- key-frame edits ------------------------------------------------------------------------
    def scale(self, region, frame: int, factor: float, band: int = 2) -> KeyEdit:
        """Scale the details of ``region`` at ``frame`` (0 removes, < 1 diminishes, > 1 enhances),
        fading to unchanged over ``band`` edge rings (§5.2 "scaling the Laplacian coating")."""
        f = self._frame(frame)
        region = np.unique(np.asarray(region, dtype=np.int64))
        if region.size == 0:
            raise ValueError("region: select at least one vertex")
        ids, ring = falloff(self.faces, self.n_vertices, region, band, self.adjacency)
        s = float(factor) + (1 - float(factor)) * ring / (band + 1)
        Ar = self.A[ids]

        def at(t):
            return (s - 1)[:, None] * np.asarray(Ar @ np.asarray(self.details[t], dtype=np.float64)[self.rep])

        return KeyEdit(f, ids, at(f), region, "scale", {"factor": float(factor), "band": band}, at)

    def _paste(self, X, N, Y, nY, h, R=None):
        """Surface vertices within ``h`` of the moved points ``Y`` (facing like ``nY``) and the
        nearest moved point of each: ``(dst (m,), j (m,), rot)`` with ``rot(vectors (m, 3))``
        the rotation by ``R`` and then onto each destination's normal."""

        hits = cKDTree(X).query_ball_point(Y, r=h)
        cand = np.unique(np.concatenate([np.asarray(t, dtype=np.int64) for t in hits]))
        if cand.size == 0:
            return cand, cand, None
        dist, j = cKDTree(Y).query(X[cand])
        keep = (dist <= h) & (np.einsum("ij,ij->i", N[cand], nY[j]) > 0.3)
        dst, j = cand[keep], j[keep]
        a, b = nY[j], N[dst]

        def rot(vec):
            return _rotate_between(a, b, vec if R is None else vec @ R.T)

        return dst, j, rot

    def _key_edit(self, frame, change, touched, selection, kind, info) -> KeyEdit:
        """The coating change ``A Δy`` of the displacement change ``Δy = change(t)`` (n, 3), which
        is zero outside the vertices ``touched``; the edit lives on their A-neighbourhood."""
        ids = np.unique(self.A[np.asarray(touched, dtype=np.int64)].indices)
        Ar = self.A[ids]

        def at(t):
            return np.asarray(Ar @ change(t))

        dy = change(frame)
        info = dict(info, displacement=dy)
        return KeyEdit(frame, ids, at(frame), np.asarray(selection, dtype=np.int64), kind, info, at)

    def copy_paste(self, region, frame: int, anchor: int, angle: float = 0.0, scale: float = 1.0,
                   mode: str = "replace", spacing: Optional[float] = None, band: int = 2,
                   mirror: bool = False) -> KeyEdit:
        """Copy the details of ``region`` and paste them around the vertex ``anchor`` at ``frame``.

        The region is moved by a similarity: its central vertex onto ``anchor``, its mean normal
        onto the anchor's normal, then ``angle`` (radians) about that normal and ``scale`` about
        the anchor. Every surface vertex within ``spacing`` (default: 0.75 × the region's mean
        edge length × ``scale``, about the farthest a vertex can be from a moved vertex inside
        the footprint), facing the same way, takes the detail of the closest moved vertex,
        rotated with the similarity and then onto its own normal (the coating transfer of
        §5.1). ``mode="replace"`` swaps the details there, ``"add"`` adds them.

        What is pasted is the detail *displacement* of the region and of ``band`` edge rings
        around it, feathered linearly to zero across the band; the key-frame edit is the
        coating of that change (``A Δy``). Pasting the region's raw coating instead cuts a
        wrinkle's coating at the brush's edge, and a cut coating is not the Laplacian of a
        local bump: on ICT → Rocketbox a 16-vertex paste raised the whole cheek by 2.6 mm.
        ``info["displacement"]`` holds ``Δy`` (editor ids).

        ``mirror``: reflect the region (positions and detail vectors) across the plane through
        the anchor spanned by its normal and the mesh's up axis (+y) before pasting — a
        wrinkle copied to the other side of the face keeps its mirror-image slant.
        """
        f = self._frame(frame)
        if mode not in ("replace", "add"):
            raise ValueError(f"mode: expected 'replace' or 'add', got {mode!r}")
        if not scale > 0:
            raise ValueError(f"scale: expected > 0, got {scale}")
        S = np.unique(np.asarray(region, dtype=np.int64))
        if S.size == 0:
            raise ValueError("region: select at least one vertex")
        a = int(anchor)
        if not 0 <= a < self.n_vertices:
            raise ValueError(f"anchor: expected an editor vertex id in [0, {self.n_vertices})")
        X = self.surface(f)
        N = vertex_normals(X, self.faces)
        ext, ring = falloff(self.faces, self.n_vertices, S, band, self.adjacency)
        w = 1.0 - ring / (band + 1.0)
        c_idx = S[np.argmin(np.linalg.norm(X[S] - X[S].mean(0), axis=1))]
        n_s = _unit(N[S].sum(0))
        R = _axis_angle(N[a], angle) @ _rotate_between(n_s[None], N[a][None], np.eye(3)).T
        if mirror:
            side = np.cross(N[a], [0.0, 1.0, 0.0])
            if np.linalg.norm(side) < 1e-6:  # the anchor faces up: mirror across x instead
                side = np.array([1.0, 0.0, 0.0])
            side = _unit(side)
            R = (np.eye(3) - 2 * np.outer(side, side)) @ R
        Y = X[a] + scale * (X[ext] - X[c_idx]) @ R.T
        h = float(spacing) if spacing is not None else 0.75 * scale * self.mean_edge(S, X)
        dst, j, rot = self._paste(X, N, Y, N[ext] @ R.T, h, R)
        if dst.size == 0:
            raise ValueError("copy_paste: no surface vertex under the moved region (anchor on another part?)")
        wd = w[j][:, None]

        def change(t):
            D = np.asarray(self.details[t], dtype=np.float64)[self.rep]
            dy = np.zeros((self.n_vertices, 3))
            vals = rot(D[ext[j]])
            dy[dst] = wd * (vals - D[dst] if mode == "replace" else vals)
            return dy

        return self._key_edit(f, change, dst, S, "copy_paste",
                              {"anchor": a, "angle": float(angle), "scale": float(scale), "mode": mode, "spacing": h,
                               "pasted_vertices": int(dst.size), "mirror": bool(mirror)})

    def reshape(self, curve, target, frame: int, radius: float, lam_l: float = 0.2,
                spacing: Optional[float] = None, band: int = 2) -> KeyEdit:
        r"""Deform a wrinkle so its curve follows ``target`` (eq. 17), then move its details there.

        ``curve``: editor ids along the wrinkle (in order); ``target``: (p, 3) points of the
        drawn curve (p >= 2). The region ``P`` is every vertex within ``radius`` of the curve;

        .. math:: \min_{x} \sum_{c} \|x_c - v^*_c\|^2 + \lambda_l \sum_{i \in P} \|L_P x_i - L_P x^0_i\|^2

        with ``v*_c`` the target curve at the arc-length fraction of curve vertex ``c`` and
        ``L_P`` the uniform Laplacian of ``P``'s own edges. Then, as in the paper, the details
        of ``P`` are removed and pasted on the deformed region (closest points within
        ``spacing``, default 0.75 × the region's mean edge length), both feathered over ``band``
        rings as in :meth:`copy_paste` (the band follows its nearest region vertex).
        """
        f = self._frame(frame)
        C = np.asarray(curve, dtype=np.int64)
        Q = np.asarray(target, dtype=np.float64)
        if len(C) < 2 or Q.ndim != 2 or Q.shape[1] != 3 or len(Q) < 2:
            raise ValueError(f"reshape: need a curve of >= 2 vertices and a target of >= 2 points, got {len(C)} "
                             f"and {Q.shape}")

        X = self.surface(f)
        P = self.select_curve(C, radius, f)
        x = self.deform_region(P, C, Q, X, lam_l)
        N = vertex_normals(X, self.faces)
        ext, ring = falloff(self.faces, self.n_vertices, P, band, self.adjacency)
        w = 1.0 - ring / (band + 1.0)
        move = x - X[P]
        _, near = cKDTree(X[P]).query(X[ext])
        moved = X[ext] + move[near]
        h = float(spacing) if spacing is not None else 0.75 * self.mean_edge(P, X)
        dst, j, rot = self._paste(X, N, moved, N[ext], h)
        wd = w[j][:, None]

        def change(t):
            D = np.asarray(self.details[t], dtype=np.float64)[self.rep]
            dy = np.zeros((self.n_vertices, 3))
            dy[ext] -= w[:, None] * D[ext]
            dy[dst] += wd * rot(D[ext[j]])
            return dy

        return self._key_edit(f, change, np.union1d(ext, dst), P, "reshape", {"region": int(P.size), "lam_l": float(lam_l),
                                                   "max_move_mm": float(np.linalg.norm(move, axis=1).max()) * 1000,
                                                   "deformed": x})

    def deform_region(self, region, curve, target, positions, lam_l: float = 0.2) -> np.ndarray:
        """The eq. 17 least-squares deformation of ``region`` (editor ids) at ``positions``;
        returns (len(region), 3) new positions (region in sorted order)."""
        P = np.unique(np.asarray(region, dtype=np.int64))
        C = np.asarray(curve, dtype=np.int64)
        if not np.isin(C, P).all():
            raise ValueError("reshape: the curve's vertices must lie in the region")
        X = np.asarray(positions, dtype=np.float64)
        Ad = self.adjacency[P][:, P]
        LP = (sp.diags(np.asarray(Ad.sum(1)).ravel()) - Ad).tocsr()
        Q = np.asarray(target, dtype=np.float64)
        sc, sq = _arc_length(X[C]), _arc_length(Q)
        q = np.stack([np.interp(sc, sq, Q[:, k]) for k in range(3)], axis=1)
        rows = np.searchsorted(P, C)
        S = sp.csr_matrix((np.ones(len(C)), (np.arange(len(C)), rows)), shape=(len(C), len(P)))
        LtL = (LP.T @ LP).tocsc()
        M = (S.T @ S + lam_l * LtL).tocsc()
        # L_P's null space is the constants per component of P: a component without a curve
        # vertex would be singular; a 1e-12 ridge keeps it where it is
        M = M + 1e-12 * max(M.diagonal().max(), 1.0) * sp.identity(len(P), format="csc")
        rhs = S.T @ q + lam_l * (LtL @ X[P]) + 1e-12 * max(M.diagonal().max(), 1.0) * X[P]
        return spla.splu(M).solve(rhs)

    # -- propagation ----------------------------------------------------------------------------
    def _taper(self, window, taper: int) -> np.ndarray:
        ts, te = window
        t = np.arange(ts, te + 1)
        return np.minimum(1.0, np.minimum(t - ts + 1, te - t + 1) / (taper + 1.0))

    def apply(self, edit: KeyEdit, window: Optional[tuple] = None, mu: float = 0.23, lam_e: float = 1.0,
              lam_t: float = 0.1, lam_s: float = 1.0, propagation: str = "eq18", taper: int = 3,
              rtol: float = 1e-10, chunk: int = 128) -> DetailEditResult:
        """Propagate ``edit`` over ``window`` (default: the μ window of its selection) and return
        the new details (float32, rig vertex order).

        ``propagation="eq18"``: the paper's eq. 18-21 with λ_e, λ_t, λ_s. Its spatial term
        penalises the *change* between neighbouring vertices in every frame, so a change with
        fine spatial structure (a wrinkle's) decays within a few frames of ``t_k``
        (docs/transfer.md, "Fine-scale editing"). ``propagation="per_frame"``: the same spatial
        operation (scale, paste, reshape — ``edit.at_frame``) applied to every frame of the
        window, faded in and out over ``taper`` frames at its ends: the edit follows the
        details' own motion (a pasted wrinkle comes and goes with its source).

        Both are reconstructed exactly through a low-rank factorisation of the per-frame
        coating changes (``rtol``: singular values below ``rtol`` of the largest are dropped;
        the result equals the per-frame solve of :meth:`apply_reference` to ~``rtol``).
        """
        t0 = time.perf_counter()
        k = edit.frame
        ts, te = window if window is not None else self.window(edit.selection, k, mu)
        ts, te = int(ts), int(te)
        if not 0 <= ts <= k <= te < self.n_frames:
            raise ValueError(f"window ({ts}, {te}): expected 0 <= t_s <= key frame {k} <= t_e < {self.n_frames}")
        m = len(edit.vertices)
        if propagation == "eq18":
            Phi, H = _modal_response(self.faces, self.n_vertices, edit.vertices, (ts, te), k, lam_e, lam_t, lam_s)
            coef = Phi.T @ edit.delta  # (m, 3)
            U, S, Vt = np.linalg.svd(H.T, full_matrices=False)  # H^T = U S Vt: (n, r)(r)(r, m)
            fields = lambda r: np.einsum("vi,ji,ic->jvc", Phi, S[:r, None] * Vt[:r], coef, optimize=True)  # noqa: E731
        elif propagation == "per_frame":
            if edit.at_frame is None:
                raise ValueError("propagation='per_frame' needs an edit made by this editor (edit.at_frame)")
            tau = self._taper((ts, te), taper)
            G = np.stack([tau[i] * edit.at_frame(t).ravel() for i, t in enumerate(range(ts, te + 1))])  # (n, 3m)
            U, S, Vt = np.linalg.svd(G, full_matrices=False)
            fields = lambda r: (S[:r, None] * Vt[:r]).reshape(r, m, 3)  # noqa: E731
        else:
            raise ValueError(f"propagation: expected 'eq18' or 'per_frame', got {propagation!r}")
        r = max(1, int((S > rtol * S[0]).sum())) if S.size and S[0] > 0 else 0
        t1 = time.perf_counter()
        n = self.n_vertices
        out = np.array(self.details, dtype=np.float32, copy=True)
        biggest = 0.0
        if r:
            # spatial fields Z_j scattered onto the mesh, one Poisson solve each
            B = np.zeros((n, r, 3))
            B[edit.vertices] = fields(r).transpose(1, 0, 2)
            Y = self.poisson.solve(B.reshape(n, 3 * r)).reshape(n, r, 3)[self.wi]  # rig order
            Yf = Y.transpose(1, 0, 2).reshape(r, -1)
            for a in range(ts, te + 1, chunk):
                b = min(a + chunk, te + 1)
                change = (U[a - ts:b - ts, :r] @ Yf).reshape(b - a, len(self.wi), 3)
                out[a:b] += change.astype(np.float32)
                biggest = max(biggest, float(np.abs(change).max()))
        t2 = time.perf_counter()
        return DetailEditResult(out, (ts, te), edit, r, biggest * 1000,
                                {"propagation": t1 - t0, "reconstruction": t2 - t1, "total": t2 - t0})

    # -- plain-data edits (what a shot stores) ---------------------------------------------------
    def select(self, selection: dict, frame: int) -> np.ndarray:
        """Editor ids of a selection spec ``{"mode": "paint"|"curve", "picks": [rig ids],
        "strokes": [[rig id, rig id], ...], "radius": metres}`` at ``frame``: *paint* takes every
        vertex within the radius of a pick or of a stroke's path, *curve* every vertex within it
        of the polyline through the picks (empty when nothing is picked)."""
        picks = [int(v) for v in selection.get("picks", [])]
        if not picks:
            return np.zeros(0, dtype=np.int64)
        ids = self.to_editor(picks)
        r = float(selection.get("radius", 0.0))
        if selection.get("mode", "paint") == "curve":
            return self.select_curve(ids, r, frame)
        parts = [self.select_paint(ids, r, frame)]
        parts += [self.select_curve(self.to_editor([a, b]), r, frame) for a, b in selection.get("strokes", []) if a != b]
        return np.unique(np.concatenate(parts))

    def key_edit(self, spec: dict) -> tuple:
        """The key-frame edit of a spec: ``(KeyEdit, description)``.

        ``spec``: ``{"op": "scale"|"copy_paste"|"reshape", "frame", "selection"}`` (see
        :meth:`select`) and per operation ``factor``; ``anchor`` (rig id), ``angle_deg``,
        ``scale``, ``mode`` ("replace"|"add"), ``mirror``; ``targets`` ((n, 3) metres), ``lam_l``.

        Raises
        ------
        ValueError
            Nothing selected, a missing anchor or target curve, or a selection without details
            at the key frame — each said in words a user can act on.
        """
        op, k = spec.get("op", "scale"), int(spec["frame"])
        sel = spec.get("selection", {})
        if not sel.get("picks"):
            raise ValueError("nothing selected: click on the mesh to select the details to edit")
        if op == "scale":
            edit = self.scale(self.select(sel, k), k, float(spec.get("factor", 0.0)))
            what = f"scale ×{float(spec.get('factor', 0.0)):g}"
        elif op == "copy_paste":
            if spec.get("anchor") is None:
                raise ValueError("copy-paste: choose where the details go (the paste anchor)")
            edit = self.copy_paste(self.select(sel, k), k, int(self.to_editor([int(spec["anchor"])])[0]),
                                   math.radians(float(spec.get("angle_deg", 0.0))), float(spec.get("scale", 1.0)),
                                   spec.get("mode", "replace"), mirror=bool(spec.get("mirror", False)))
            what = f"copy-paste to vertex {spec['anchor']} ({edit.info['pasted_vertices']} vertices)"
        elif op == "reshape":
            if sel.get("mode") != "curve" or len(sel.get("picks", [])) < 2:
                raise ValueError("reshape: select the wrinkle as a curve (two or more clicks along it)")
            targets = np.asarray(spec.get("targets", []), dtype=np.float64).reshape(-1, 3)
            if len(targets) < 2:
                raise ValueError("reshape: give the new curve (two or more wrinkle target points)")
            edit = self.reshape(self.to_editor(sel["picks"]), targets, k, float(sel.get("radius", 0.0)),
                                float(spec.get("lam_l", 0.2)))
            what = f"reshape wrinkle ({edit.info['region']} vertices, moved ≤ {edit.info['max_move_mm']:.1f} mm)"
        else:
            raise ValueError(f"detail edit op: expected 'scale', 'copy_paste' or 'reshape', got {op!r}")
        if self.activity(edit.selection)[k] <= 0:
            raise ValueError(f"the selection has no fine details at frame {k}: nothing to edit there")
        return edit, what

    def apply_spec(self, spec: dict) -> tuple:
        """Make and propagate a spec's edit: ``(DetailEditResult, report dict)``; the spec's
        ``mu``, ``lam_e``, ``lam_t``, ``lam_s`` and ``propagation`` ("per_frame" | "eq18")."""
        edit, what = self.key_edit(spec)
        res = self.apply(edit, mu=float(spec.get("mu", 0.23)), lam_e=float(spec.get("lam_e", 1.0)),
                         lam_t=float(spec.get("lam_t", 0.1)), lam_s=float(spec.get("lam_s", 1.0)),
                         propagation=spec.get("propagation", "per_frame"))
        ts, te = res.window
        return res, {"what": what, "frame": int(spec["frame"]), "window": [int(ts), int(te)],
                     "max_change_mm": float(res.max_change_mm), "seconds": float(res.seconds["total"])}

    def apply_reference(self, edit: KeyEdit, window: tuple, lam_e: float = 1.0, lam_t: float = 0.1,
                        lam_s: float = 1.0, propagation: str = "eq18", taper: int = 3) -> np.ndarray:
        """Slow, obviously-correct :meth:`apply`: eq. 18-21 assembled as one sparse space-time
        system and solved directly (or the per-frame changes formed one by one), then one
        direct Poisson solve per frame (float64)."""
        ts, te = window
        if propagation == "eq18":
            E = _reference_propagation(edit.delta, self.faces, self.n_vertices, edit.vertices, (ts, te), edit.frame,
                                       lam_e, lam_t, lam_s)
        else:
            tau = self._taper((ts, te), taper)
            E = [tau[i] * edit.at_frame(t) for i, t in enumerate(range(ts, te + 1))]
        out = np.array(self.details, dtype=np.float64, copy=True)
        lu = spla.splu(self.A.tocsc()) if self.poisson.screening > 0 else None
        for t in range(ts, te + 1):
            b = np.zeros((self.n_vertices, 3))
            b[edit.vertices] = E[t - ts]
            y = lu.solve(b) if lu is not None else self.poisson.solve(b)
            out[t] += y[self.wi]
        return out



def _reference_propagation(edit, faces, n_vertices, region, window, key_frame, lam_e=1.0, lam_t=0.1, lam_s=1.0):
    """Eq. 18-21 assembled as one sparse space-time system and solved directly."""
    ts, te = window
    n, m = te - ts + 1, len(region)
    L = uniform_laplacian(np.asarray(faces), n_vertices)
    Ls = L[region][:, region]
    Lt = sp.diags([np.r_[1, 2 * np.ones(n - 2), 1], -np.ones(n - 1), -np.ones(n - 1)], [0, -1, 1])
    Dt = np.zeros(n)
    Dt[key_frame - ts] += lam_e
    Dt[0] += lam_s
    Dt[-1] += lam_s
    M = (sp.kron(lam_t * Lt + sp.diags(Dt), sp.identity(m)) + lam_t * sp.kron(sp.identity(n), Ls)).tocsc()
    rhs = np.zeros((n * m, 3))
    rhs[(key_frame - ts) * m:(key_frame - ts + 1) * m] = lam_e * edit
    return spla.splu(M).solve(rhs).reshape(n, m, 3)


def benchmark(n_frames: int = 1300):
    """Print the ``xu_detail_edit_1300f`` BENCH line: a key-frame detail edit propagated and
    reconstructed over ``n_frames`` frames of the 14K-vertex ICT head (see benchmarks/)."""


    root = Path(__file__).resolve().parents[2]
    ict = read_rig(root / "data" / "rigs" / "ict_facekit.glb")
    wi, rep, F = weld_vertices(ict.neutral, ict.faces)
    # details: the high-pass part (shape minus its Taubin smoothing) of three real ICT shapes,
    # each with its own temporal profile — the content does not change the cost, the sizes do
    names = [n for n in ("browInnerUp_L", "noseSneer_L", "eyeSquint_R") if n in ict.names]
    if not names:
        raise RuntimeError("benchmark: the ICT rig lacks the shapes it uses")
    t = np.arange(n_frames)
    D = np.zeros((n_frames, ict.n_vertices, 3), dtype=np.float32)
    profiles = np.clip(np.sin(t[:, None] / (40.0 + 17 * np.arange(len(names)))), 0, None)
    for i, name in enumerate(names):
        d = ict.deltas[ict.names.index(name)][rep]
        hp = (d - taubin_smooth(ict.neutral[rep] + d, F) + taubin_smooth(ict.neutral[rep], F))[wi]
        D += (profiles[:, i, None, None] * hp[None]).astype(np.float32)
    ed = DetailEditor(ict.faces, ict.neutral, D)
    key = int(np.argmax(profiles.sum(1)))
    busiest = int(np.argmax(np.linalg.norm(ed.coating(key), axis=1)))
    region = ed.select_paint([busiest], 0.01, key)
    e = ed.scale(region, key, 0.0)
    window = (0, n_frames - 1)
    c0 = time.perf_counter()
    res = ed.apply(e, window=window)
    ours = time.perf_counter() - c0
    c0 = time.perf_counter()
    ref = ed.apply_reference(e, window)
    ref_s = time.perf_counter() - c0
    ch, chr_ = res.details - D, ref - D
    err = float(np.abs(ch - chr_).max() / max(np.abs(chr_).max(), 1e-300))
    print(f"BENCH xu_detail_edit_1300f ours_s={ours:.3f} ref_s={ref_s:.3f} ratio={ref_s / ours:.2f} T={n_frames} "
          f"V={len(rep)} edit_vertices={len(e.vertices)} rank={res.rank} propagation_s={res.seconds['propagation']:.3f} "
          f"reconstruction_s={res.seconds['reconstruction']:.3f} window={res.window[0]}-{res.window[1]} "
          f"max_change_mm={res.max_change_mm:.3f} ref=sparse_spacetime+per_frame_poisson rel_maxdiff={err:.1e}",
          flush=True)


def apply_detail_edits(editor: DetailEditor, specs) -> dict:
    """Every detail edit spec in order (:meth:`DetailEditor.apply_spec`), each on the details the
    previous one left: ``{"details": (T, V, 3) float32, "reports": [...]}`` (the dense
    ``detail_edit`` stage)."""
    ed, reports = editor, []
    for spec in specs:
        res, rep = ed.apply_spec(spec)
        reports.append(rep)
        ed = ed.rebase(details=res.details)
    return {"details": ed.details, "reports": reports}
