r"""Large-scale editing of the transferred sequence (Xu et al. 2014 §4.3 eq. 12-15).

Large scale (:class:`LargeScaleEditor`)
    ``min λ_b E_b + λ_w E_w + λ_e E_e`` over the target bases ``b'`` and weights ``w' >= 0``
    (eq. 12), alternating (i) bases with weights fixed — a linear solve, and (ii) weights
    with bases fixed — non-negative least squares in the temporal window — until the
    energy drops by less than ``tol`` (5 % in the paper) between two rounds.

    * ``E_b = Σ_k E_{b'_k}`` is the deformation-transfer energy of eq. 9 (the factorised
      :class:`~core.transfer.deformation.DeformationTransfer` system ``A``; its minimiser is the
      unedited transfer ``Δ⁰``, so ``E_b = Σ_k (Δ_k - Δ⁰_k)^T A (Δ_k - Δ⁰_k)`` up to a constant);
    * ``E_w = Σ_{t=t_s-1}^{t_e} ||(w'_{t+1} - w'_t) - (w_{t+1} - w_t)||²`` (eq. 13, forward
      differences, frames outside the window fixed so the edit blends in);
    * ``E_e``: point constraints ``v'_t = v*`` (eq. 14) and distance constraints
      ``v'_i - v'_j = d*`` (eq. 15), with ``v'_t = T̄_0[v] + Σ_k w'_tk Δ_k[v]``.

    Step (i) is ``(λ_b I⊗A + λ_e C^T C) x = λ_b (I⊗A) x⁰ + λ_e C^T y`` with ``C`` a few rows
    (one per constraint): solved by the Woodbury identity with ``A^{-1}`` applied only to the
    constrained vertices' indicator vectors (one back-substitution per constrained vertex,
    reused across iterations). Step (ii) is a banded (block-tridiagonal in time) system,
    solved by an active-set NNLS on a sparse factorisation. ``λ_b = 0`` updates weights only,
    ``λ_w = 0`` bases only.

Fine-scale editing (§5.2, eq. 17-21) is :mod:`.detail_edit`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.optimize import lsq_linear

from ..geometry import weld_vertices
from ..io.gltf import read_rig
from .decompose import TaubinFilter, taubin_smooth
from ._cholesky import SparseCholesky
from .deformation import DeformationTransfer
from .detail_edit import _reference_propagation, propagate_details
from .features import line_edges
from .settings import TransferSettings
from .welded import weld_source

__all__ = ["PointConstraint", "DistanceConstraint", "LargeScaleEditor", "TransferEditor", "apply_transfer_edits", "benchmark"]


@dataclass(frozen=True)
class PointConstraint:
    """Vertex ``vertex`` at frame ``frame`` should be at ``position`` (eq. 14)."""

    frame: int
    vertex: int
    position: tuple


@dataclass(frozen=True)
class DistanceConstraint:
    """At ``frame``, ``v_i - v_j`` should keep its direction with length ``distance`` (eq. 15)."""

    frame: int
    i: int
    j: int
    distance: float


@dataclass
class EditResult:
    """Edited deltas (K, V, 3), weights (T, K), and the energy after each round."""

    deltas: np.ndarray
    weights: np.ndarray
    energies: list = field(default_factory=list)
    iterations: int = 0


class LargeScaleEditor:
    """Large-scale edit propagation (eq. 12-15) for a transferred blendshape sequence.

    Parameters
    ----------
    transfer : DeformationTransfer   the factorised eq. 9 system of the transfer
    target_smooth_ref : (V, 3)       ``T̄_0``
    deltas : (K, V, 3)               the transferred bases minus ``T̄_0`` (``Δ⁰``)
    weights : (T, K)                 the transferred weights (source weights ``w``)
    """

    def __init__(self, transfer: DeformationTransfer, target_smooth_ref, deltas, weights):
        self.dt = transfer
        self.T0 = np.asarray(target_smooth_ref, dtype=np.float64)
        self.D0 = np.asarray(deltas, dtype=np.float64)
        self.W0 = np.asarray(weights, dtype=np.float64)
        K, V, _ = self.D0.shape
        if self.W0.shape[1] != K or self.T0.shape != (V, 3) or transfer.V != V:
            raise ValueError(f"deltas (K, V, 3), weights (T, K), target_smooth_ref (V, 3) must agree; got "
                             f"{self.D0.shape}, {self.W0.shape}, {self.T0.shape}")
        self.K, self.V = K, V
        # A of eq. 9 as a matrix, for the energy E_b and Woodbury solves (A + mu I: the
        # translation of each basis is held by a weak tie to the unedited transfer)
        A = (transfer.Ga @ transfer.G).tocsr()
        if len(transfer.edges):
            Bm = sp.csr_matrix((np.r_[-np.ones(len(transfer.edges)), np.ones(len(transfer.edges))],
                                (np.r_[np.arange(len(transfer.edges)), np.arange(len(transfer.edges))],
                                 np.r_[transfer.edges[:, 0], transfer.edges[:, 1]])), shape=(len(transfer.edges), V))
            A = A + transfer.Bw @ Bm
        self.mu = 1e-6 * float(A.diagonal().mean())
        # E_b is dimensionless per triangle; E_e is in m²: divide it by the mean edge length²
        e = transfer.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
        self.h2 = float(np.mean(np.sum((self.T0[e[:, 0]] - self.T0[e[:, 1]]) ** 2, axis=1)))
        self.A = (A + self.mu * sp.identity(V)).tocsc()
        self._lu = None
        self._z = {}

    # -- energies -----------------------------------------------------------------------
    def _rows(self, constraints):
        """Constraint rows: (frame, {vertex: coefficient}, target (3,) relative to T̄_0)."""
        rows = []
        for c in constraints:
            if isinstance(c, PointConstraint):
                rows.append((int(c.frame), {int(c.vertex): 1.0}, np.asarray(c.position, dtype=np.float64) - self.T0[c.vertex]))
            elif isinstance(c, DistanceConstraint):
                cur = self.mesh(self.W0[c.frame], self.D0)
                d = cur[c.i] - cur[c.j]
                n = np.linalg.norm(d)
                if n == 0:
                    raise ValueError(f"DistanceConstraint at frame {c.frame}: vertices {c.i}, {c.j} coincide")
                want = d / n * float(c.distance)
                rows.append((int(c.frame), {int(c.i): 1.0, int(c.j): -1.0}, want - (self.T0[c.i] - self.T0[c.j])))
            else:
                raise TypeError(f"constraints: expected PointConstraint or DistanceConstraint, got {type(c).__name__}")
            if not 0 <= rows[-1][0] < len(self.W0):
                raise ValueError(f"constraint frame {rows[-1][0]} outside [0, {len(self.W0)})")
        return rows

    def mesh(self, w, deltas=None) -> np.ndarray:
        D = self.D0 if deltas is None else deltas
        return self.T0 + np.tensordot(np.asarray(w, dtype=np.float64), D, axes=1)

    def energy(self, deltas, weights, rows, lam_b, lam_w, lam_e, window) -> float:
        dD = (deltas - self.D0).transpose(1, 0, 2).reshape(self.V, -1)
        Eb = float(np.einsum("ij,ij->", dD, self.A @ dD))
        ts, te = window
        a, b = max(ts - 1, 0), min(te + 1, len(weights) - 1)
        Ew = float(((np.diff(weights[a:b + 1], axis=0) - np.diff(self.W0[a:b + 1], axis=0)) ** 2).sum())
        Ee = 0.0
        for t, g, y in rows:
            v = sum(c * np.tensordot(weights[t], deltas[:, i], axes=1) for i, c in g.items())
            Ee += float(((v - y) ** 2).sum())
        return lam_b * Eb + lam_w * Ew + lam_e * Ee

    # -- step (i): bases ------------------------------------------------------------------
    def _solve_A(self, vertex: int) -> np.ndarray:
        if vertex not in self._z:
            if self._lu is None:
                self._lu = spla.splu(self.A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                     options=dict(SymmetricMode=True))
            e = np.zeros(self.V)
            e[vertex] = 1.0
            self._z[vertex] = self._lu.solve(e)
        return self._z[vertex]

    def update_bases(self, deltas, weights, rows, lam_b, lam_e) -> np.ndarray:
        r"""Step (i): ``min λ_b Σ_k (Δ_k-Δ⁰_k)^T A (Δ_k-Δ⁰_k) + λ_e Σ_r (g_r^T Δ w_r - y_r)²``.

        With ``x = Δ - Δ⁰`` (per coordinate, V x K): ``(λ_b I⊗A + λ_e C^T C) x = λ_e C^T (y - C x⁰)``
        where row r of C is ``w_r ⊗ g_r``. Woodbury: ``x = H^{-1}C^T (I/λ_e + C H^{-1} C^T)^{-1} r``.
        """
        if not rows:
            return deltas.copy()
        R = len(rows)
        verts = sorted({v for _, g, _ in rows for v in g})
        Z = {v: self._solve_A(v) for v in verts}
        # H^{-1} C^T column r = (w_r ⊗ A^{-1} g_r) / λ_b ; C H^{-1} C^T [r, s] = (w_r.w_s)(g_r^T A^{-1} g_s)/λ_b
        Wr = np.stack([weights[t] for t, _, _ in rows])  # (R, K)
        AG = np.stack([sum(c * Z[v] for v, c in g.items()) for _, g, _ in rows], axis=1)  # (V, R)
        GAG = np.stack([sum(c * AG[v] for v, c in g.items()) for _, g, _ in rows])  # (R, R)
        M = np.eye(R) / lam_e + (Wr @ Wr.T) * GAG / lam_b
        # residual of the unedited bases at the constraints
        cur = np.stack([sum(c * np.tensordot(w, self.D0[:, v], axes=1) for v, c in g.items())
                        for w, (_, g, _) in zip(Wr, rows)])  # (R, 3)
        y = np.stack([yy for _, _, yy in rows]) - cur
        alpha = np.linalg.solve(M, y)  # (R, 3)
        # x (V, K, 3) = Σ_r AG[:, r] ⊗ w_r ⊗ alpha_r / λ_b
        x = np.einsum("vr,rk,rc->kvc", AG, Wr, alpha) / lam_b
        return self.D0 + x

    # -- step (ii): weights -----------------------------------------------------------------
    def update_weights(self, deltas, weights, rows, lam_w, lam_e, window) -> np.ndarray:
        """Step (ii): NNLS over the window's weights (eq. 13 + eq. 14/15), others fixed."""
        ts, te = window
        n, K = te - ts + 1, self.K
        T = len(weights)
        # E_w: forward differences over t in [ts-1, te], neighbours outside the window fixed
        D = sp.diags([-np.ones(n + 1), np.ones(n + 1)], [0, 1], shape=(n + 1, n + 2)).tocsr()
        inside = slice(1, n + 1)
        Wfull = np.zeros((n + 2, K))
        Wfull[1:n + 1] = 0.0
        left = weights[ts - 1] if ts > 0 else None
        right = weights[te + 1] if te + 1 < T else None
        keep_rows = np.ones(n + 1, dtype=bool)
        if left is None:
            keep_rows[0] = False
        if right is None:
            keep_rows[-1] = False
        D = D[keep_rows]
        src = np.zeros((n + 2, K))
        a = max(ts - 1, 0)
        src_vals = self.W0[a:min(te + 2, T)]
        off = 0 if ts > 0 else 1
        src[off:off + len(src_vals)] = src_vals
        dsrc = D @ src
        fixed = np.zeros((n + 2, K))
        if left is not None:
            fixed[0] = left
        if right is not None:
            fixed[-1] = right
        Dn = D[:, inside]  # acts on the unknown window rows
        rhs_w = dsrc - D @ fixed  # (rows, K)
        # quadratic form in vec(W_window) (row-major: t major, k minor)
        # + a 1e-8 λ_w ridge towards the source weights: E_w sees only velocities, so with no
        # fixed neighbour (window = whole sequence) the offsets would be undetermined
        ridge = 1e-8 * lam_w
        Q = lam_w * sp.kron(Dn.T @ Dn, sp.identity(K)) + ridge * sp.identity(n * K)
        q = lam_w * (Dn.T @ rhs_w).ravel() + ridge * self.W0[ts:te + 1].ravel()
        # constraint rows at frames inside the window: (g^T Δ) w_t = y  -> per coordinate c
        extra_rows, extra_cols, extra_vals = [], [], []
        cvec = []
        for t, g, y in rows:
            if not ts <= t <= te:
                continue
            P = sum(c * deltas[:, v] for v, c in g.items())  # (K, 3): row k = g^T Δ_k
            for c in range(3):
                extra_rows.append(len(cvec))
                cvec.append(y[c])
                extra_cols.append((t - ts) * K + np.arange(K))
                extra_vals.append(P[:, c])
        if cvec:
            Cm = sp.csr_matrix((np.concatenate(extra_vals), (np.repeat(extra_rows, K), np.concatenate(extra_cols))),
                               shape=(len(cvec), n * K))
            Q = Q + lam_e * (Cm.T @ Cm)
            q = q + lam_e * (Cm.T @ np.asarray(cvec))
        x = _nnls_sparse(Q.tocsc(), q, weights[ts:te + 1].ravel())
        out = weights.copy()
        out[ts:te + 1] = x.reshape(n, K)
        return out

    def edit(self, constraints, lam_b: float = 1.0, lam_w: float = 1.0, lam_e: float = 100.0, window=None,
             tol: float = 0.05, max_iter: int = 10) -> EditResult:
        """Propagate ``constraints`` (eq. 12) by alternating bases and weights.

        Parameters
        ----------
        constraints : list of PointConstraint / DistanceConstraint
        lam_b, lam_w, lam_e : weights of E_b, E_w, E_e (λ_b = 0: weights only; λ_w = 0: bases only);
            E_e is measured in units of the target's mean edge length, so λ_e = 100 weighs a
            one-edge miss like 100 fully distorted triangles of E_b
        window : (t_s, t_e) inclusive, default the whole sequence
        tol : stop when the energy drops by less than ``tol`` of its value (5 % in the paper)

        Raises
        ------
        ValueError
            Negative weights of the energy, both λ_b and λ_w zero, a bad window or constraint.
        """
        if min(lam_b, lam_w, lam_e) < 0 or (lam_b == 0 and lam_w == 0):
            raise ValueError(f"lam_b, lam_w, lam_e: expected >= 0 and not both lam_b and lam_w 0, got {lam_b}, {lam_w}, {lam_e}")
        T = len(self.W0)
        window = (0, T - 1) if window is None else (int(window[0]), int(window[1]))
        if not 0 <= window[0] <= window[1] < T:
            raise ValueError(f"window: expected 0 <= t_s <= t_e < {T}, got {window}")
        rows = self._rows(constraints)
        lam_e = lam_e / self.h2
        D, W = self.D0.copy(), self.W0.copy()
        E = [self.energy(D, W, rows, lam_b, lam_w, lam_e, window)]
        it = 0
        for it in range(1, max_iter + 1):
            if lam_b > 0:
                D = self.update_bases(D, W, rows, lam_b, lam_e)
            if lam_w > 0:
                W = self.update_weights(D, W, rows, lam_w, lam_e, window)
            E.append(self.energy(D, W, rows, lam_b, lam_w, lam_e, window))
            if E[-2] - E[-1] <= tol * E[-2] or E[-1] <= 1e-9 * E[0] or lam_b == 0 or lam_w == 0:
                break
        return EditResult(D, W, E, it)


class TransferEditor:
    """Large-scale edits (eq. 12-15) of a :class:`~core.transfer.TransferResult`, in the
    result's own vertex ids, from plain-data edit specs (what a shot stores).

    The eq. 9 system is the one the transfer was solved with: the result carries it
    (``result.system``, ``result.welded``). A result that does not (e.g. made by an older
    version) is rebuilt exactly as :func:`core.transfer.transfer_sequence` builds it — ``weld``
    of ``source_rig``, ``S̄_0`` = Taubin filter (``settings``) of the welded source neutral,
    ``T̄_0`` = the result's ``target_smooth_ref``, feature lines from ``settings`` —
    and :meth:`consistency` checks the rebuild (~1e-12 when it is the same system).

    The editor's mesh is ``reference + w Δ`` with the result's (shown) neutral as reference: it
    differs from the smoothed ``T̄_0 + w Δ`` by the reference details ``neutral - T̄_0``, a
    constant per vertex; E_b and E_w (eq. 9, 13) do not involve the reference, so point and
    distance constraints act on what the user sees.

    An edit spec is ``{"constraints": [...], "window": [a, b] or None, "lam_b", "lam_w",
    "lam_e"}`` with constraints ``{"kind": "point"|"fixed", "frame", "vertex", "target": [x, y,
    z]}`` or ``{"kind": "distance", "frame", "i", "j", "distance"}`` (metres, result vertex ids).

    Raises
    ------
    ValueError
        A result without its system and no ``source_rig`` of its topology to rebuild it from.
    """

    def __init__(self, result, source_rig=None, settings=None):

        self.result = result
        V = len(result.neutral)
        if result.system is not None and result.welded is not None:
            self.welded_index, self.rep = result.welded.index, result.welded.rep
            self.transfer = result.system
        else:
            if source_rig is None:
                raise ValueError("this transfer result does not carry its eq. 9 system: give the source rig to rebuild it")
            if source_rig.n_vertices != V or not np.array_equal(np.asarray(source_rig.faces), np.asarray(result.faces)):
                raise ValueError(f"source_rig {source_rig.name!r}: expected the topology of the transfer result "
                                 f"({V} vertices, {len(result.faces)} faces), got {source_rig.n_vertices} vertices")
            s = settings or TransferSettings()
            src = weld_source(source_rig.neutral, source_rig.faces)
            self.welded_index, self.rep = src.index, src.rep
            smooth_src = TaubinFilter(src.faces, src.n, s.iterations, s.lam, s.mu).apply(src.welded_neutral)
            edges = (line_edges([self.welded_index[np.asarray(ln, dtype=np.int64)] for ln in s.feature_lines], closed=True)
                     if s.feature_lines is not None else None)
            self.transfer = DeformationTransfer(smooth_src, np.asarray(result.target_smooth_ref)[self.rep], src.faces, edges,
                                                s.alpha, factor=SparseCholesky)  # as transfer_sequence's
        self.reference = np.asarray(result.neutral, dtype=np.float64)[self.rep]

    @property
    def n_frames(self) -> int:
        return len(self.result.weights)

    def consistency(self) -> float:
        """max |Δ_rebuilt - Δ_result| / max |Δ_result|: the system re-transfers the result's
        source bases; ~1e-12 when it is the one the transfer used."""
        r = self.result
        if not r.n_bases:
            return 0.0
        again = self.transfer.transfer(np.asarray(r.source_bases)[:, self.rep]) - np.asarray(r.target_smooth_ref)[self.rep]
        want = np.asarray(r.deltas)[:, self.rep]
        return float(np.abs(again - want).max() / max(np.abs(want).max(), 1e-300))

    def constraint(self, spec: dict):
        """A core constraint (welded ids) from a spec in result vertex ids (see the class docstring)."""
        w = self.welded_index
        kind = spec.get("kind")
        if kind in ("point", "fixed"):
            return PointConstraint(int(spec["frame"]), int(w[spec["vertex"]]), tuple(float(x) for x in spec["target"]))
        if kind == "distance":
            return DistanceConstraint(int(spec["frame"]), int(w[spec["i"]]), int(w[spec["j"]]), float(spec["distance"]))
        raise ValueError(f"constraint kind: expected 'point', 'fixed' or 'distance', got {kind!r}")

    def edit(self, deltas, weights, specs, lam_b: float, lam_w: float, lam_e: float, window=None):
        """Run :meth:`LargeScaleEditor.edit` from the state ``(deltas (K, V, 3), weights (T, K))``.

        Returns ``(deltas (K, V, 3), weights (T, K), EditResult)`` in the result's vertex ids.
        """
        D = np.asarray(deltas, dtype=np.float64)
        editor = LargeScaleEditor(self.transfer, self.reference, D[:, self.rep], weights)
        res = editor.edit([self.constraint(s) for s in specs], lam_b, lam_w, lam_e, window)
        return np.ascontiguousarray(res.deltas[:, self.welded_index]), res.weights, res

    def miss_mm(self, spec: dict, deltas, weights) -> float:
        """How far (mm) the state ``(deltas, weights)`` is from a constraint, on the shown mesh."""
        neutral = self.result.neutral
        f = int(spec["frame"])

        def at(v):
            return neutral[v] + weights[f] @ deltas[:, v]

        if spec["kind"] == "distance":
            return abs(float(np.linalg.norm(at(spec["i"]) - at(spec["j"]))) - float(spec["distance"])) * 1000
        return float(np.linalg.norm(at(spec["vertex"]) - np.asarray(spec["target"], dtype=float))) * 1000

    def apply(self, state: tuple, spec: dict) -> tuple:
        """One edit spec on the state ``(deltas, weights)``: ``(deltas, weights, report)`` where
        report holds the constraint misses before/after (mm), the rounds and the energies."""
        D, W = state
        cons = list(spec.get("constraints", []))
        if not cons:
            raise ValueError("a large-scale edit needs at least one constraint")
        win = spec.get("window")
        D2, W2, res = self.edit(D, W, cons, float(spec.get("lam_b", 1.0)), float(spec.get("lam_w", 1.0)),
                                float(spec.get("lam_e", 100.0)), tuple(win) if win else None)
        report = {"before_mm": [self.miss_mm(c, D, W) for c in cons], "after_mm": [self.miss_mm(c, D2, W2) for c in cons],
                  "iterations": res.iterations, "energies": [float(e) for e in res.energies]}
        return D2, W2, report


def apply_transfer_edits(editor: TransferEditor, specs) -> dict:
    """Every large-scale edit spec in order, from the transfer's own bases and weights:
    ``{"deltas", "weights", "reports": [...]}`` (the dense ``transfer_edit`` stage)."""
    r = editor.result
    state = (np.asarray(r.deltas, dtype=np.float64), np.asarray(r.weights, dtype=np.float64))
    reports = []
    for spec in specs:
        D, W, rep = editor.apply(state, spec)
        state = (D, W)
        reports.append(rep)
    return {"deltas": state[0], "weights": state[1], "reports": reports}


def _nnls_sparse(Q: sp.csc_matrix, q: np.ndarray, x0: np.ndarray, max_iter: int = 300) -> np.ndarray:
    """``min x^T Q x / 2 - q^T x`` s.t. ``x >= 0`` for sparse SPD ``Q``: Lawson–Hanson's
    active set on a sparse factorisation. Starts from the support of ``x0``, releases the
    variables whose gradient points inwards (all at once for the first rounds, then one at
    a time, which cannot cycle), and steps back to feasibility when the free solution turns
    negative. Exact at termination (KKT checked); RuntimeError after ``max_iter`` rounds."""
    n = len(q)
    scale = max(1.0, float(np.abs(q).max()))
    x = np.maximum(np.asarray(x0, dtype=np.float64), 0.0)
    free = x > 0
    rounds = 0
    for _ in range(max_iter):
        idx = np.flatnonzero(free)
        if len(idx):
            xf = spla.splu(Q[idx][:, idx].tocsc(), permc_spec="MMD_AT_PLUS_A").solve(q[idx])
        else:
            xf = np.zeros(0)
        if (xf >= 0).all():
            x = np.zeros(n)
            x[idx] = xf
            g = Q @ x - q  # at the optimum: g = 0 on free, g >= 0 on the active set
            cand = np.flatnonzero(~free & (g < -1e-12 * scale))
            if not len(cand):
                return x
            rounds += 1
            if rounds > 5:
                cand = cand[[int(np.argmin(g[cand]))]]
            free[cand] = True
        else:
            cur = x[idx]
            neg = xf < 0
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = np.where(neg, cur / (cur - xf), np.inf)
            s = float(np.clip(np.min(ratio), 0.0, 1.0))
            x = np.zeros(n)
            x[idx] = cur + s * (xf - cur)
            hit = idx[neg & (ratio <= s + 1e-12)]
            free[hit] = False
            x[hit] = 0.0
    raise RuntimeError("weights NNLS did not converge in max_iter active-set steps")


def benchmark(n_frames: int = 1300):
    """Print the ``xu_edit_large_1300f`` / ``xu_edit_fine_1300f`` BENCH lines (see benchmarks/)."""


    root = Path(__file__).resolve().parents[2]
    ict = read_rig(root / "data" / "rigs" / "ict_facekit.glb")
    wi, rep, F = weld_vertices(ict.neutral, ict.faces)
    S0 = ict.neutral[rep]
    Sb0 = taubin_smooth(S0, F)
    Tb0 = Sb0 * [1.1, 0.95, 1.0]
    rng = np.random.default_rng(0)
    K = 10
    bases = Sb0 + ict.deltas[rng.choice(ict.n_shapes, K, replace=False)][:, rep]
    dt = DeformationTransfer(Sb0, Tb0, F)
    D = dt.transfer(bases) - Tb0
    t = np.arange(n_frames)
    W = np.clip(0.5 + 0.5 * np.sin(t[:, None] / (20 + 7 * np.arange(K)) + np.arange(K)), 0, 1)
    ed = LargeScaleEditor(dt, Tb0, D, W)
    v = int(np.argmax(np.linalg.norm(D[0], axis=1)))
    f = n_frames // 2
    target = ed.mesh(W[f])[v] + np.array([0, 0.004, 0.002])
    cons = [PointConstraint(f, v, tuple(target))]
    ed._solve_A(v)  # the one back-substitution per constrained vertex is set-up, timed separately
    c0 = time.perf_counter()
    res = ed.edit(cons, 1.0, 1.0, 100.0)
    ours = time.perf_counter() - c0
    # reference: the weights step as one dense-free general bounded LS (scipy lsq_linear) on the
    # same objective, bases fixed (the edit's dominant cost), on the whole 1,300-frame window

    c0 = time.perf_counter()
    rows = ed._rows(cons)
    ref_w = _reference_weights(ed, res.deltas, W, rows, 1.0, 100.0, (0, n_frames - 1), lsq_linear)
    ref = time.perf_counter() - c0
    ours_w = ed.update_weights(res.deltas, W, rows, 1.0, 100.0, (0, n_frames - 1))
    e_ours = ed.energy(res.deltas, ours_w, rows, 0.0, 1.0, 100.0, (0, n_frames - 1))
    e_ref = ed.energy(res.deltas, ref_w, rows, 0.0, 1.0, 100.0, (0, n_frames - 1))
    print(f"BENCH xu_edit_large_1300f ours_s={ours:.3f} ref_s={ref:.3f} ratio={ref / ours:.2f} T={n_frames} K={K} "
          f"V={len(S0)} iterations={res.iterations} ref=lsq_linear_one_weights_step "
          f"weights_energy_ours={e_ours:.3e} weights_energy_ref={e_ref:.3e}", flush=True)

    # fine scale: a region of ~300 vertices around the same vertex, a key-frame scale edit
    region = np.argsort(np.linalg.norm(S0 - S0[v], axis=1))[:300]
    edit = 0.5 * rng.standard_normal((len(region), 3)) * 1e-4
    c0 = time.perf_counter()
    E = propagate_details(edit, F, len(S0), region, (0, n_frames - 1), f)
    ours = time.perf_counter() - c0
    c0 = time.perf_counter()
    Eref = _reference_propagation(edit, F, len(S0), region, (0, n_frames - 1), f)
    ref = time.perf_counter() - c0
    err = float(np.abs(E - Eref).max() / np.abs(Eref).max())
    print(f"BENCH xu_edit_fine_1300f ours_s={ours:.3f} ref_s={ref:.3f} ratio={ref / ours:.2f} T={n_frames} "
          f"region={len(region)} ref=sparse_direct_spacetime rel_maxdiff={err:.2e}", flush=True)


def _reference_weights(ed, deltas, weights, rows, lam_w, lam_e, window, lsq_linear):
    """Same objective as :meth:`LargeScaleEditor.update_weights` as a stacked LS, by lsq_linear."""
    ts, te = window
    n, K = te - ts + 1, ed.K
    blocks, rhs = [], []
    Dn = sp.diags([-np.ones(n - 1), np.ones(n - 1)], [0, 1], shape=(n - 1, n))
    blocks.append(np.sqrt(lam_w) * sp.kron(Dn, sp.identity(K)))
    rhs.append(np.sqrt(lam_w) * np.diff(ed.W0[ts:te + 1], axis=0).ravel())
    blocks.append(np.sqrt(1e-8 * lam_w) * sp.identity(n * K))
    rhs.append(np.sqrt(1e-8 * lam_w) * ed.W0[ts:te + 1].ravel())
    for t, g, y in rows:
        P = sum(c * deltas[:, v] for v, c in g.items())
        for c in range(3):
            row = sp.csr_matrix((P[:, c], (np.zeros(K, int), (t - ts) * K + np.arange(K))), shape=(1, n * K))
            blocks.append(np.sqrt(lam_e) * row)
            rhs.append(np.sqrt(lam_e) * np.array([y[c]]))
    A = sp.vstack(blocks).tocsr()
    b = np.concatenate(rhs)
    if n * K < 2000:  # small: the exact bounded-variable solver on the dense matrix
        x = lsq_linear(A.toarray(), b, bounds=(0, np.inf), method="bvls", tol=1e-12, max_iter=5000).x
    else:
        x = lsq_linear(A, b, bounds=(0, np.inf), method="trf", tol=1e-12, lsmr_tol="auto", max_iter=5000).x
    return x.reshape(n, K)
