r"""Fine-scale detail transfer by Laplacian-coating rotation (Xu et al. 2014 §5.1, eq. 16, 5).

For every vertex and frame, the source coating change is rotated from the local frame ``F_t``
of the smoothed source ``S̄_t`` into the local frame ``F'_t`` of the smoothed target ``T̄_t``
(frames: normal + projected edge, :func:`core.geometry.vertex_frames`):

.. math:: \hat D'_t = R_v(\xi_t - \xi_0),\quad R_v = F'_t F_t^T \qquad (16)

    T_t = L^{-1}(L \bar T_t + \hat T_0 + g \hat D'_t) \qquad (5)

with ``g`` the detail gain (default: the size ratio target / source, so a wrinkle keeps its
depth relative to the face). This is the paper's form (``rotate_reference=False``): where
the source does not move, ``ξ_t - ξ_0 = 0`` and nothing changes, however badly conditioned
the local frames of a resampled target are.

``rotate_reference=True`` is the fully rotation-covariant variant (Sorkine et al. 2004's
coating transfer): both the target's reference details and the source change are read in
the reference frames and written in the frames at ``t``,
``F'_t (F'^T_0 \hat T_0 + g (F_t^T ξ_t - F_0^T ξ_0))``; a rigidly rotated source then gives the
rigidly rotated target. It is exact for clean meshes but amplifies frame noise on a
resampled target whose reference details are large (a few degrees of frame jitter times
centimetre coatings, integrated by the Poisson solve), which is why it is not the default.

How it is computed (the result is eq. 5 exactly; only the order of the work differs)
-----------------------------------------------------------------------------------
* **One solve of the change only.** With ``y_0 = T_0 - T̄_0`` and ``T̂_0 = L y_0``, eq. 5 (and
  its screened form, :class:`~core.transfer.decompose.PoissonReconstructor`) is linear, so
  ``y_t = y_0 + L^{-1}(c_t - T̂_0)`` where ``c_t`` is the target coating: the constant part
  is known without a solve, and only the change ``c_t - T̂_0`` (``g R_v(ξ_t - ξ_0)`` in the
  paper's form) goes through the factorisation.
* **Component-major blocks.** A chunk of ``t`` frames is held as (3, V, t) arrays: every
  coordinate is one contiguous block for the per-frame arithmetic (the frames are one
  compiled pass, :func:`_frames_from_positions`, in a local vertex numbering,
  :func:`_local_numbering`), and the right-hand sides of all
  frames × coordinates of the chunk go to one sparse Cholesky factorisation as one (V, 3t)
  block, solved in place (:meth:`~core.transfer.decompose.PoissonReconstructor.solve`).
* **Positions from the factorisation, frames in float64.** For a factored sequence
  ``base + Σ a_j basis_j`` a chunk's positions are one float64 matrix product ``X [1, a_t]``
  (no per-frame gathers). Edges, normals and tangents are computed from them in float64 in one
  compiled pass and the frames rounded once to float32 (``_WORK``): within rounding of the unit
  vectors everywhere (float32 throughout, as before, was up to 1e-4 off where the tangent edge
  is near the normal), for ~10% more time than float32 arithmetic. The rotation and the
  screened Poisson solve run in float32 (a sparse Cholesky factor stored and solved in the
  working precision, :class:`~core.transfer._cholesky.SparseCholesky`; relative error ~1.5e-6
  on the screened operator, whose condition number is ~200; on the 56K-vertex benchmark the
  details moved by at most 4.4e-10 m against CHOLMOD's float64 solves, at 0.55 ms per column
  against 1.6).
  The tests check the algorithm in float64 against the per-frame formulas to 1e-9 and the
  float32 result to its precision.
* **Buffers reused.** Every chunk's arrays are views of a reused workspace
  (:class:`_Workspace`): fresh (3, V, t) temporaries for every chunk made 2 s of system time
  (page faults) of the 10 s the benchmark took.
* **Two cores.** A chunk's right-hand sides (for factored sequences one compiled call,
  :func:`_chunk_rhs`) and its solve run without the GIL, so with a second core two threads
  take the chunks in turn, each with its own workspace (made beforehand and paged in by
  :func:`detail_workspace` in :func:`core.transfer.transfer_sequence`). Each chunk's arithmetic
  is the same either way: the result is bit for bit that of one core (tested). (Before, with
  ``cholespy``'s solves holding the GIL, a worker solved while this thread formed the next
  chunk, and the stage waited on the solves: 3.3-4.1 s of the benchmark against ~1.4 s now.)
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Union

import numba
import numpy as np
from scipy.sparse.csgraph import reverse_cuthill_mckee

from ..geometry import first_neighbour, vertex_adjacency, vertex_face_incidence, vertex_frames
from ._mesh import to_local
from ..cores import free_cores
from .decompose import FactoredSequence, PoissonReconstructor

__all__ = ["local_coating", "DetailTransfer", "detail_morph_targets"]


def local_coating(frames, coating: np.ndarray) -> np.ndarray:
    """World coating (..., V, 3) -> local coordinates ``F^T ξ`` (..., V, 3); ``frames`` is
    ``(t, b, n)`` from :func:`core.geometry.vertex_frames`."""
    return to_local(frames, coating)


# -- component-major (3, V, t) kernels -------------------------------------------------------
# Hand-written rather than geometry.vertex_frames: that one works on (t, V, 3) sequences, whose
# per-vertex gathers copy 12-byte rows and whose component slices are 3-strided (2.3 ms per
# frame for the face cross products of a 112K-face mesh). Here a chunk of t frames is held
# as (3, V, t): every component is one contiguous block, the positions come out of one matrix
# product in this layout, and the nonlinear rest (edges, cross products, normal sums,
# normalisations, the tangent's projection) is one compiled pass (numba) over faces and
# vertices instead of ~30 numpy passes over (3, F, t) temporaries: 0.06 s of CPU per 32-frame
# chunk of the 56K-vertex benchmark. Tested equal to vertex_frames.


_WORK = np.float32  # precision of the stored frames, the rotation and the solve


#: a vertex whose normal is rounding noise, ``|Σ N_f| < NORMAL_CANCEL · Σ |e1_f| |e2_f|``, has
#: no frame (see :func:`_frames_from_positions`)
NORMAL_CANCEL = 1e-3


class _Workspace:
    """Named scratch arrays of one thread, reused from chunk to chunk of the detail stage.

    Fresh (3, V, t) arrays for every chunk cost more in page faults than the arithmetic they
    hold: on the 56K-vertex benchmark the ~360 MB of temporaries a chunk allocated made 2 s of
    the run's 10 s of CPU system time (zeroing new pages). ``work(name, shape, dtype)`` returns
    a C-ordered view of the first elements of one flat buffer per name (a smaller last chunk
    reuses it too)."""

    def __init__(self):
        self._bufs = {}

    def __call__(self, name: str, shape: tuple, dtype) -> np.ndarray:
        dtype = np.dtype(dtype)
        n = int(np.prod(shape))
        buf = self._bufs.get(name)
        if buf is None or buf.dtype != dtype or buf.size < n:
            buf = self._bufs[name] = np.empty(n, dtype=dtype)
        return buf[:n].reshape(shape)


def _frames_from_positions(x: np.ndarray, faces: np.ndarray, nbi: np.ndarray, flags: bool = False,
                           work: "_Workspace | None" = None, side: str = "") -> tuple:
    """Frames ``(t, b, n)`` of :func:`core.geometry.vertex_frames`, each (3, V, t) in the
    working precision ``_WORK``, from positions ``x`` (3, V, t) (float64: every edge is formed in
    float64 and rounded once, exact to rounding of the *edge*, not of the absolute position) of
    the triangles ``faces`` (F, 3), with tangent edges towards the neighbours ``nbi`` (V,).
    The arrays are views of ``work``'s buffers (named with the prefix ``side``): valid until
    the next call with the same names.

    With ``flags`` a fourth item, ``ok`` (V, t) bool, flags the vertices
    that have a frame: ``|Σ N_f| >=`` :data:`NORMAL_CANCEL` ``· Σ |e1_f| |e2_f|``. The
    rounding error of a computed cross product ``N_f = e1 × e2`` is of the order of
    ``eps |e1| |e2|`` (not of ``|N_f|``, and ``|N_f| <= |e1| |e2|``, so every vertex whose face
    normals cancel, ``|Σ N_f| ≪ Σ |N_f|``, is below the bound too). Below it the normal's
    direction is rounding noise, whether the face normals around the vertex cancel or the faces
    are needles (``|N_f| ≪ |e1| |e2|``). Both are what 40 Taubin iterations make of a thin
    closed part: the Jeeliz tiger's whiskers flatten to a double-sided sheet 1e-7 m thick, where
    the normals cancel (frames there turned at random between inputs that differ by 1e-9 m and
    moved the details by 10 mm), and collapse to needles 4 mm long and 5e-9 m across, where the
    float32 cross product of two long edges is off by a few percent (0.01-0.03 rad between a GLB
    and an OBJ of one take, 0.11 mm in the details). Such a vertex keeps its change unrotated."""
    work = work if work is not None else _Workspace()
    V, t = x.shape[1], x.shape[2]
    tg, b, n = (work(side + k, (3, V, t), _WORK) for k in "tbn")
    ok = work(side + "ok", (V, t), np.bool_)
    _frames_kernel(np.asarray(x, dtype=np.float64), faces, nbi, np.array([NORMAL_CANCEL, 1e-6, 0.9, 1.0]), tg, b, n, ok,
                   work("normal_sums", (3, V, t), np.float64), work("bound", (V, t), np.float64))
    return (tg, b, n, ok) if flags else (tg, b, n)


@numba.njit(cache=True, nogil=True)
def _frames_kernel(x, faces, nbi, consts, tg, b, n, ok, acc, bound):  # pragma: no cover - compiled
    """The arithmetic of :func:`_frames_from_positions` in one pass over the faces and two over
    the vertices, all in float64 (the face sums in increasing face order, as the CSR incidence
    product summed them; a face listing a vertex twice counts once), the frames rounded once to
    the dtype of ``tg``, ``b``, ``n`` when they are stored. Writes those and ``ok``; ``acc``
    (3, V, t) and ``bound`` (V, t) are float64 scratch."""
    V, t = x.shape[1], x.shape[2]
    tmax = _normals_pass(x, faces, nbi, consts, ok, acc, bound)
    for v in range(V):
        for j in range(t):
            t0, t1, t2, n0, n1, n2, b0, b1, b2 = _frame_at(x, nbi, acc, bound, tmax, consts, v, j)
            tg[0, v, j], tg[1, v, j], tg[2, v, j] = t0, t1, t2
            n[0, v, j], n[1, v, j], n[2, v, j] = n0, n1, n2
            b[0, v, j], b[1, v, j], b[2, v, j] = b0, b1, b2


@numba.njit(cache=True, nogil=True)
def _normals_pass(x, faces, nbi, consts, ok, acc, bound):  # pragma: no cover - compiled
    """The pass over the faces and the first over the vertices of :func:`_frames_kernel`:
    ``acc`` <- unit vertex normals, ``ok``, ``bound`` <- the projected tangent edge's length;
    returns its largest per frame (t,)."""
    nF = faces.shape[0]
    V, t = x.shape[1], x.shape[2]
    cancel = consts[0]
    for v in range(V):
        for j in range(t):
            acc[0, v, j] = 0.0
            acc[1, v, j] = 0.0
            acc[2, v, j] = 0.0
            bound[v, j] = 0.0  # Σ_f∋v |e1_f| |e2_f|
    nf = np.empty((4, t))  # one face's N_f (3 rows) and |e1_f| |e2_f|
    for f in range(nF):
        a0, a1, a2 = faces[f, 0], faces[f, 1], faces[f, 2]
        for j in range(t):
            x0 = x[0, a1, j] - x[0, a0, j]
            x1 = x[1, a1, j] - x[1, a0, j]
            x2 = x[2, a1, j] - x[2, a0, j]
            y0 = x[0, a2, j] - x[0, a0, j]
            y1 = x[1, a2, j] - x[1, a0, j]
            y2 = x[2, a2, j] - x[2, a0, j]
            nf[0, j] = x1 * y2 - x2 * y1
            nf[1, j] = x2 * y0 - x0 * y2
            nf[2, j] = x0 * y1 - x1 * y0
            nf[3, j] = np.sqrt((x0 * x0 + x1 * x1 + x2 * x2) * (y0 * y0 + y1 * y1 + y2 * y2))
        for k in range(3):
            v = faces[f, k]
            if (k == 1 and v == a0) or (k == 2 and (v == a0 or v == a1)):
                continue
            for j in range(t):
                acc[0, v, j] += nf[0, j]
                acc[1, v, j] += nf[1, j]
                acc[2, v, j] += nf[2, j]
                bound[v, j] += nf[3, j]
    tmax = np.zeros(t)
    for v in range(V):
        w = nbi[v]
        for j in range(t):
            n0, n1, n2 = acc[0, v, j], acc[1, v, j], acc[2, v, j]
            nl = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
            ok[v, j] = nl >= cancel * bound[v, j]
            if nl > 0:
                n0 /= nl
                n1 /= nl
                n2 /= nl
            acc[0, v, j], acc[1, v, j], acc[2, v, j] = n0, n1, n2
            e0 = x[0, w, j] - x[0, v, j]  # the tangent edge, projected
            e1 = x[1, w, j] - x[1, v, j]
            e2 = x[2, w, j] - x[2, v, j]
            d = e0 * n0 + e1 * n1 + e2 * n2
            e0 -= d * n0
            e1 -= d * n1
            e2 -= d * n2
            tn = np.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
            bound[v, j] = tn  # reused: the projected tangent's length
            if tn > tmax[j]:
                tmax[j] = tn
    return tmax


@numba.njit(cache=True, inline="always")
def _frame_at(x, nbi, acc, bound, tmax, consts, v, j):  # pragma: no cover - compiled
    """Vertex v's frame in frame j after :func:`_normals_pass` (the tangent again: cheaper than
    a float64 (3, V, t) array of it): ``(t0, t1, t2, n0, n1, n2, b0, b1, b2)`` in float64."""
    tiny, near, one = consts[1], consts[2], consts[3]
    w = nbi[v]
    n0, n1, n2 = acc[0, v, j], acc[1, v, j], acc[2, v, j]
    tn = bound[v, j]
    if tn <= tiny * tmax[j]:
        # as vertex_frames: an edge (nearly) along the normal falls back to an axis
        if abs(n0) < near:
            d = n0
            t0, t1, t2 = one - d * n0, -d * n1, -d * n2
        else:
            d = n1
            t0, t1, t2 = -d * n0, one - d * n1, -d * n2
        tn = np.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
    else:
        t0, t1, t2 = x[0, w, j] - x[0, v, j], x[1, w, j] - x[1, v, j], x[2, w, j] - x[2, v, j]
        d = t0 * n0 + t1 * n1 + t2 * n2
        t0 -= d * n0
        t1 -= d * n1
        t2 -= d * n2
    if tn > 0:
        t0 /= tn
        t1 /= tn
        t2 /= tn
    return t0, t1, t2, n0, n1, n2, n1 * t2 - n2 * t1, n2 * t0 - n0 * t2, n0 * t1 - n1 * t0


class _FramedSequence:
    """Per-vertex frames of the frames of a sequence, in (3, V, t) blocks.

    From a :class:`FactoredSequence` ``x(a) = base + Σ_j a_j basis_j`` the positions of a chunk
    are one float64 product ``X [1, a_t]`` (X: base and basis as (3V, m) columns, in the
    (3, V, t) layout, no per-frame gathers); from a callable ``idx -> (t, V, 3)`` they are
    copied into that layout. Edges, normals and everything after them are computed per frame
    (:func:`_frames_from_positions`). This replaced float32 edge matrices of base and basis
    (``E [1, a_t]`` for face and tangent edges, 5x the rows of the positions): their (3, F, t)
    products made 107 MB of temporaries a chunk, and the frames of both sides took 1.7 s of the
    56K-vertex benchmark against 0.8 s now, each edge now formed from float64 positions.
    """

    def __init__(self, seq: Union[FactoredSequence, Callable], faces: np.ndarray, nbi: np.ndarray, order=None):
        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
        self.nbi = np.ascontiguousarray(nbi, dtype=np.int64)
        self.seq = seq
        self.V = len(self.nbi)
        # ``order`` (V,): the frames' vertex i is the sequence's vertex order[i] (``faces`` and
        # ``nbi`` given in that numbering, see :func:`_local_numbering`)
        self.order = None if order is None else np.asarray(order, dtype=np.int64)
        if isinstance(seq, FactoredSequence):
            m = np.concatenate([seq.base[None], seq.basis])
            m = m if self.order is None else m[:, self.order]
            # (3V, m): row p V + i is coordinate p of vertex i; columns base, basis_1..r
            self.X = np.ascontiguousarray(m.transpose(2, 1, 0), dtype=np.float64).reshape(3 * self.V, -1)

    def positions(self, idx: slice, work: "_Workspace | None" = None) -> np.ndarray:
        """(3, V, t) float64 positions of the frames ``idx`` (a view of ``work``'s buffer
        ``"x"`` when given)."""
        V = self.V
        buf = (lambda t: np.empty((3, V, t))) if work is None else (lambda t: work("x", (3, V, t), np.float64))
        if isinstance(self.seq, FactoredSequence):
            c = np.atleast_2d(self.seq.coeffs[idx])
            a = np.empty((c.shape[1] + 1, len(c)))  # ã = [1, a_t] as columns
            a[0] = 1.0
            a[1:] = c.T
            x = buf(len(c))
            np.matmul(self.X, a, out=x.reshape(3 * V, len(c)))
            return x
        p = np.asarray(self.seq(idx), dtype=np.float64)
        p = p if self.order is None else p[:, self.order]
        x = buf(len(p))
        x[...] = p.transpose(2, 1, 0)
        return x

    def frames(self, idx: slice, flags: bool = False, work: "_Workspace | None" = None, side: str = "") -> tuple:
        """``(t, b, n)`` (each (3, V, t) ``_WORK``) of the frames ``idx``; with ``flags`` also
        ``ok`` (V, t): the vertices that have a frame (:func:`_frames_from_positions`). With
        ``work``, views of its buffers (prefix ``side``), overwritten by the next call."""
        work = work if work is not None else _Workspace()
        return _frames_from_positions(self.positions(idx, work), self.faces, self.nbi, flags, work, side)


@numba.njit(cache=True, nogil=True)
def _chunk_rhs(Xs, As, Xt, At, faces, nbi, consts, G, C, xi_base, scale, add, sub, sub2, rows, x, acc, bound,
               st, sb, sn, sok, tok, xi, B):  # pragma: no cover - compiled
    """The right-hand sides ``B`` (V, 3t) of a chunk of two factored sequences in one call
    without the GIL: positions ``X [1, a_t]`` of each side (``x``, (3V, t)), the source's frames
    (:func:`_frames_kernel`), the source coating change ``G c_t + xi_base`` (``xi``, (3V, t)),
    and the target's frames rotating it as they are made (:func:`_rotate_entry`, not stored: a
    (3, V, t) array less of each three, ~65 MB a thread on the 56K-vertex benchmark) -- the
    same arithmetic, rounded the same way, as :meth:`DetailTransfer.displacements` does call
    by call for other sequences."""
    V, t = st.shape[1], st.shape[2]
    x3 = x.reshape(3, V, t)
    np.dot(Xs, As, x)
    _frames_kernel(x3, faces, nbi, consts, st, sb, sn, sok, acc, bound)
    np.dot(G, C, xi)
    xi3 = xi.reshape(3, V, t)
    for p in range(3):
        for v in range(V):
            for j in range(t):
                xi3[p, v, j] += xi_base[p, v]
    np.dot(Xt, At, x)
    tmax = _normals_pass(x3, faces, nbi, consts, tok, acc, bound)
    g = scale[0]
    f = B.dtype.type  # the stored frames' precision: the target's frames are rounded to it
    for v in range(V):
        r = rows[v]
        for j in range(t):
            t0, t1, t2, n0, n1, n2, b0, b1, b2 = _frame_at(x3, nbi, acc, bound, tmax, consts, v, j)
            c0, c1, c2 = _rotate_entry(st, sb, sn, v, j, f(t0), f(t1), f(t2), f(b0), f(b1), f(b2), f(n0), f(n1), f(n2),
                                       xi3[0, v, j], xi3[1, v, j], xi3[2, v, j], sok[v, j] and tok[v, j], g, add, sub, sub2)
            B[r, j], B[r, t + j], B[r, 2 * t + j] = c0, c1, c2


@numba.njit(cache=True, nogil=True)
def _scatter_frames(y, rows, y0, out, start):  # pragma: no cover - compiled
    """``out[start + j, i, p] = y[rows[i], p t + j] + y0[i, p]`` for the (V, 3t) solution ``y``
    of a chunk of t frames, rounded to ``out``'s dtype."""
    t = y.shape[1] // 3
    for i in range(len(rows)):  # one row of y at a time (read once); t output rows stay cached
        r = rows[i]
        for p in range(3):
            for j in range(t):
                out[start + j, i, p] = y[r, p * t + j] + y0[i, p]


def _local_numbering(faces: np.ndarray, nbi: np.ndarray) -> tuple:
    """``(order, faces', nbi')``: the vertices renumbered by reverse Cuthill-McKee (vertex i is
    vertex order[i]), the faces in that numbering sorted by their smallest vertex (stable), and
    the first neighbours in it. The frames kernel gathers and scatters per face over (3, V, t)
    arrays far larger than the cache; with neighbours close in memory it ran 0.61-0.65 s
    against 0.75-0.76 s for the 12 chunks of one side on the 56K-vertex benchmark (a
    Loop-subdivided mesh numbers its new edge vertices after all the old ones). The face sums
    change order: the frames move by float64 rounding before they are rounded to float32."""
    V = len(nbi)
    order = reverse_cuthill_mckee(vertex_adjacency(faces, V), symmetric_mode=True).astype(np.int64)
    inv = np.empty_like(order)
    inv[order] = np.arange(V)
    f = inv[faces]
    f = np.ascontiguousarray(f[np.argsort(f.min(axis=1), kind="stable")])
    return order, f, np.ascontiguousarray(inv[nbi[order]])


def _rotate(Fs: tuple, Ft: tuple, x: np.ndarray, scale: float = 1.0, add_local=None, sub=None, ok=None,
            sub_frameless=None, out=None, rows=None) -> np.ndarray:
    """``F'_t (scale * F_t^T x + add_local) - sub`` for (3, V, t) blocks; ``scale * (x - sub_frameless)``
    where ``ok`` (V, t) is False (``add_local``, ``sub``, ``sub_frameless``: (V, 3) or None).

    Returns (3, V, t) in the frames' dtype, or writes ``out`` (V, 3t) (column ``p t + j`` is
    coordinate p of frame j: the right-hand sides of the Poisson solve) and returns it; with
    ``rows`` (V,), vertex v of the blocks goes to row ``rows[v]`` of ``out``."""
    V, t = x.shape[1], x.shape[2]
    z = np.zeros((V, 3), dtype=x.dtype)
    prm = lambda a: z if a is None else np.ascontiguousarray(a, dtype=x.dtype)
    okb = np.ones((V, t), dtype=np.bool_) if ok is None else ok
    res = np.empty((V, 3 * t), dtype=x.dtype) if out is None else out
    _rotate_kernel(Fs[0], Fs[1], Fs[2], Ft[0], Ft[1], Ft[2], x, np.array([scale], dtype=x.dtype), prm(add_local),
                   prm(sub), okb, prm(sub_frameless), res, np.arange(V) if rows is None else rows)
    return res.reshape(V, 3, t).transpose(1, 0, 2) if out is None else res


@numba.njit(cache=True, nogil=True)
def _rotate_kernel(s0, s1, s2, t0, t1, t2, x, scale, add, sub, ok, sub2, out, rows):  # pragma: no cover - compiled
    """The arithmetic of :func:`_rotate` per vertex and frame (:func:`_rotate_entry`); ``out``
    (V, 3t), vertex v in row ``rows[v]``."""
    V, t = x.shape[1], x.shape[2]
    g = scale[0]
    for v in range(V):
        r = rows[v]
        for j in range(t):
            c0, c1, c2 = _rotate_entry(s0, s1, s2, v, j, t0[0, v, j], t0[1, v, j], t0[2, v, j], t1[0, v, j], t1[1, v, j],
                                       t1[2, v, j], t2[0, v, j], t2[1, v, j], t2[2, v, j], x[0, v, j], x[1, v, j], x[2, v, j],
                                       ok[v, j], g, add, sub, sub2)
            out[r, j], out[r, t + j], out[r, 2 * t + j] = c0, c1, c2


@numba.njit(cache=True, inline="always")
def _rotate_entry(s0, s1, s2, v, j, a00, a01, a02, a10, a11, a12, a20, a21, a22, x0, x1, x2, ok, g, add, sub,
                  sub2):  # pragma: no cover - compiled
    """One vertex and frame of ``F'_t (g F_t^T x + add) - sub`` (``g (x - sub2)`` where not
    ``ok``): the source frame from ``s0, s1, s2`` (tangent, binormal, normal; (3, V, t)), the
    target's as scalars, ``a_pq`` component q of its tangent (p = 0), binormal (1), normal (2),
    in the order of the numpy version this replaced."""
    if ok:
        l0 = (s0[0, v, j] * x0 + s0[1, v, j] * x1 + s0[2, v, j] * x2) * g + add[v, 0]
        l1 = (s1[0, v, j] * x0 + s1[1, v, j] * x1 + s1[2, v, j] * x2) * g + add[v, 1]
        l2 = (s2[0, v, j] * x0 + s2[1, v, j] * x1 + s2[2, v, j] * x2) * g + add[v, 2]
        return (a00 * l0 + a10 * l1 + a20 * l2 - sub[v, 0], a01 * l0 + a11 * l1 + a21 * l2 - sub[v, 1],
                a02 * l0 + a12 * l1 + a22 * l2 - sub[v, 2])
    return g * (x0 - sub2[v, 0]), g * (x1 - sub2[v, 1]), g * (x2 - sub2[v, 2])


class DetailTransfer:
    """Transfer the fine-scale motion of a factored source sequence onto a target (eq. 16, 5).

    Parameters
    ----------
    faces : (F, 3) int, the shared topology
    poisson : PoissonReconstructor on that topology (its ``L`` defines the coating)
    source_smooth_ref : (V, 3)  ``S̄_0``
    source_coating_ref : (V, 3) ``ξ_0``
    target_ref, target_smooth_ref : (V, 3)  ``T_0`` and ``T̄_0``
    gain : float, the detail gain ``g``
    rotate_reference : bool, the rotation-covariant variant (see the module docstring)
    """

    def __init__(self, faces, poisson: PoissonReconstructor, source_smooth_ref, source_coating_ref,
                 target_ref, target_smooth_ref, gain: float = 1.0, rotate_reference: bool = False):
        self.faces = np.asarray(faces, dtype=np.int64)
        self.poisson = poisson
        V = poisson.n
        self.nb = first_neighbour(self.faces, V)
        self._nbi = np.where(self.nb < 0, np.arange(V), self.nb)
        self.inc = vertex_face_incidence(self.faces, V)
        self.gain = float(gain)
        self.rotate_reference = bool(rotate_reference)
        self.xi0 = np.asarray(source_coating_ref, dtype=np.float64)
        F0 = vertex_frames(np.asarray(source_smooth_ref, dtype=np.float64), self.faces, self.nb, self.inc)
        self.l0 = local_coating(F0, source_coating_ref)
        T0 = np.asarray(target_ref, dtype=np.float64)
        Tb0 = np.asarray(target_smooth_ref, dtype=np.float64)
        Ft0 = vertex_frames(Tb0, self.faces, self.nb, self.inc)
        self.That0 = np.asarray(poisson.L @ (T0 - Tb0))
        self.lt0 = local_coating(Ft0, self.That0)
        self.ref_displacement = T0 - Tb0
        self.mean = poisson.component_mean(T0 - Tb0)
        self._local = _local_numbering(self.faces, self._nbi)

    def coatings(self, source_smooth: np.ndarray, source_coating: np.ndarray, target_smooth: np.ndarray) -> np.ndarray:
        """Target coatings for (t, V, 3) chunks: ``T̂_0 + g F'_t F_t^T (ξ_t - ξ_0)`` (eq. 5, 16),
        or ``F'_t (F'^T_0 T̂_0 + g (F_t^T ξ_t - F_0^T ξ_0))`` with ``rotate_reference``.
        Returns (t, V, 3) float32."""
        Ss, Xi, Ts = (np.asarray(a, dtype=np.float64) for a in (source_smooth, source_coating, target_smooth))
        Fs = _FramedSequence(lambda idx: Ss[idx], self.faces, self._nbi).frames(slice(None), flags=True)
        Ft = _FramedSequence(lambda idx: Ts[idx], self.faces, self._nbi).frames(slice(None), flags=True)
        xi = (Xi - self.xi0) if not self.rotate_reference else Xi
        c = self._change(Fs, Ft, np.ascontiguousarray(xi.transpose(2, 1, 0), dtype=_WORK))
        c += self.That0.T.astype(_WORK)[:, :, None]
        return np.ascontiguousarray(c.transpose(2, 1, 0))

    def _change(self, Fs: tuple, Ft: tuple, xi: np.ndarray, out=None, order=None) -> np.ndarray:
        """``c_t - T̂_0`` (3, V, t) float32: ``g F'_t F_t^T (ξ_t - ξ_0)`` for ``xi = ξ_t - ξ_0``,
        or, with ``rotate_reference`` and ``xi = ξ_t``, ``F'_t(F'^T_0 T̂_0 + g(F_t^T ξ_t - F_0^T ξ_0)) - T̂_0``;
        with ``out`` (V, 3t), written there as the Poisson right-hand sides (see :func:`_rotate`).
        ``order``: the blocks' vertex i is vertex order[i] (its row in ``out``)."""
        ok = None
        if len(Fs) == 4:  # frames with flags: no rotation where either side has no frame
            ok = Fs[3] & Ft[3]
            Fs, Ft = Fs[:3], Ft[:3]
        if not self.rotate_reference:
            return _rotate(Fs, Ft, xi, self.gain, ok=ok, out=out, rows=order)
        # frameless: the change as is, the reference unrotated
        sel = (lambda a: a) if order is None else (lambda a: a[order])
        return _rotate(Fs, Ft, xi, self.gain, sel(self.lt0 - self.gain * self.l0), sel(self.That0), ok, sel(self.xi0),
                       out=out, rows=order)

    def displacements(self, source_smooth: FactoredSequence, source_coating: FactoredSequence,
                      target_smooth_frames, n_frames: int, chunk: int = 32, dtype=np.float32,
                      relative: bool = False, vertices=None, progress=None, out=None,
                      work: "_Workspace | None" = None) -> np.ndarray:
        """Detail displacements ``y_t = T_t - T̄_t`` for all frames, (T, V, 3) ``dtype``.

        Parameters
        ----------
        source_smooth, source_coating : FactoredSequence, ``S̄_t`` and ``ξ_t``
        target_smooth_frames : FactoredSequence or callable
            The smoothed target frames ``T̄_t``, factored (``T̄_0 + W_t Δ``: edges from the
            factorisation) or as ``idx -> (t, V, 3)``.
        n_frames : int
        chunk : int, frames per block
        dtype : output dtype
        relative : bool
            Return ``y_t - y_0`` (the detail motion relative to the target reference,
            ``y_0 = T_0 - T̄_0``) instead of ``y_t``; computed directly, without forming
            ``y_t`` first.
        vertices : (V',) int, optional
            Output rows (e.g. the unwelded vertex order): the result is (T, V', 3).
        progress : ``(fraction, message) -> None``, optional, called after every chunk
        out : (T, V', 3) ``dtype`` array to write into, optional (else a new one)
        work : the scratch of the stage's threads (one, or a list of one per thread), optional
            (else new ones; see :func:`detail_workspace`)
        """
        V = self.poisson.n
        rows = np.arange(V) if vertices is None else np.asarray(vertices, dtype=np.int64)
        if out is None:
            out = np.empty((n_frames, len(rows), 3), dtype=dtype)
        elif out.shape != (n_frames, len(rows), 3) or out.dtype != np.dtype(dtype):
            raise ValueError(f"out: expected {(n_frames, len(rows), 3)} {np.dtype(dtype)}, got {out.shape} {out.dtype}")
        # the per-chunk arithmetic runs in a local vertex numbering (_local_numbering); the
        # right-hand sides land in the original rows
        order, faces, nbi = self._local
        src = _FramedSequence(source_smooth, faces, nbi, order)
        tgt = _FramedSequence(target_smooth_frames, faces, nbi, order)
        # ξ_t - ξ_0 (or ξ_t) straight from the factorisation (float32 product: the change is
        # rotated in float32 anyway); (3V, r) so that the product lands in (3, V, t)
        G = source_coating.basis[:, order].transpose(2, 1, 0).reshape(3 * V, source_coating.rank).astype(_WORK)
        xi_base = ((source_coating.base - self.xi0) if not self.rotate_reference else source_coating.base)
        xi_base = xi_base[order].T.astype(_WORK)[:, :, None]
        y0 = np.zeros((len(rows), 3)) if relative else self.ref_displacement[rows]

        starts = list(range(0, n_frames, chunk))
        fused = isinstance(source_smooth, FactoredSequence) and isinstance(target_smooth_frames, FactoredSequence)
        if fused:  # the small per-chunk inputs, made before any thread runs (see below)
            coeff = lambda c: np.concatenate([np.ones((1, len(c))), c.T])  # ã = [1, a_t] as columns
            ends = [min(s + chunk, n_frames) for s in starts]
            parts = [(np.ascontiguousarray(coeff(np.atleast_2d(source_smooth.coeffs[s:e]))),
                      np.ascontiguousarray(coeff(np.atleast_2d(target_smooth_frames.coeffs[s:e]))),
                      np.ascontiguousarray(np.atleast_2d(source_coating.coeffs[s:e]).T, dtype=_WORK))
                     for s, e in zip(starts, ends)]
            z = np.zeros((V, 3), dtype=_WORK)
            if self.rotate_reference:
                prm = [np.ascontiguousarray(a[order], dtype=_WORK) for a in (self.lt0 - self.gain * self.l0, self.That0, self.xi0)]
            else:
                prm = [z, z, z]
            consts = np.array([NORMAL_CANCEL, 1e-6, 0.9, 1.0])
            xib = np.ascontiguousarray(xi_base[:, :, 0])

        def chunk_of(i: int, work: _Workspace):  # chunk i: right-hand sides, solve, into its frames of out
            idx = slice(starts[i], min(starts[i] + chunk, n_frames))
            t = idx.stop - idx.start
            B = work("B", (V, 3 * t), _WORK)
            if fused:
                As, At, C = parts[i]
                b = rhs_buffers(work, V, t)
                _chunk_rhs(src.X, As, tgt.X, At, faces, nbi, consts, G, C, xib, np.array([self.gain], dtype=_WORK),
                           prm[0], prm[1], prm[2], order, b["x"], b["normal_sums"], b["bound"], b["st"], b["sb"], b["sn"],
                           b["sok"], b["tok"], b["xi"], B)
            else:
                Fs, Ft = src.frames(idx, True, work, "s"), tgt.frames(idx, True, work, "t")
                xi = work("xi", (3, V, t), _WORK)
                np.matmul(G, np.atleast_2d(source_coating.coeffs[idx]).T.astype(_WORK), out=xi.reshape(3 * V, t))
                xi += xi_base
                self._change(Fs, Ft, xi, out=B, order=order)
            y = self.poisson.solve(B, dtype=_WORK, out=B)  # in place
            _scatter_frames(y, rows, y0, out, starts[i])

        # Every chunk's arithmetic is the same whichever thread runs it: the result is bit for
        # bit that of one core (tested). With a second core the two threads take chunks in
        # turn, each with its own scratch (~280 MB for 32 frames of a 56K-vertex mesh): the
        # right-hand sides of a factored chunk are one compiled call without the GIL
        # (_chunk_rhs), the solves too (SparseCholesky), so the threads wait on nothing but the
        # next chunk's number. Progress is reported from this thread.
        works = [w for w in (work if isinstance(work, (list, tuple)) else [work]) if w is not None] or [_Workspace()]
        n_threads = 1 if len(starts) <= 1 else min(2, free_cores())
        if n_threads == 1:
            for i in range(len(starts)):
                chunk_of(i, works[0])
                _report(progress, min(starts[i] + chunk, n_frames), n_frames)
            return out
        works += [_Workspace() for _ in range(n_threads - len(works))]
        lock = threading.Lock()
        state = {"next": 0, "stop": False, "reported": 0}
        finished = [False] * len(starts)

        def take() -> int:
            with lock:
                i = state["next"]
                state["next"] += 1
                return i if i < len(starts) and not state["stop"] else -1

        def report_done():  # every chunk of the finished prefix not yet reported, in order
            while True:
                with lock:
                    i = state["reported"]
                    if i >= len(starts) or not finished[i]:
                        return
                    state["reported"] += 1
                _report(progress, min(starts[i] + chunk, n_frames), n_frames)

        def run(work: _Workspace, reports: bool):
            try:
                while (i := take()) >= 0:
                    chunk_of(i, work)
                    finished[i] = True
                    if reports:
                        report_done()
            except BaseException:
                state["stop"] = True
                raise

        self.poisson.prepare(_WORK)  # once, before two threads ask for it
        with ThreadPoolExecutor(1) as pool:  # on an error either thread stops taking chunks
            other = pool.submit(run, works[1], False)
            run(works[0], True)
            other.result()
        report_done()
        return out


def rhs_buffers(work: _Workspace, V: int, t: int) -> dict:
    """The named scratch arrays of one chunk's right-hand sides (:func:`_chunk_rhs`) for ``V``
    vertices and ``t`` frames, views of ``work``'s buffers."""
    b = {"x": work("x", (3 * V, t), np.float64), "normal_sums": work("normal_sums", (3, V, t), np.float64),
         "bound": work("bound", (V, t), np.float64), "xi": work("xi", (3 * V, t), _WORK)}
    b.update({"s" + k: work("s" + k, (3, V, t), _WORK) for k in "tbn"})
    b["sok"], b["tok"] = work("sok", (V, t), np.bool_), work("tok", (V, t), np.bool_)
    return b


def detail_workspace(n_vertices: int, chunk: int, n_frames: int) -> _Workspace:
    """The scratch of one thread of :meth:`DetailTransfer.displacements` for ``n_vertices``
    and ``chunk`` frames of ``n_frames``, allocated and with every page mapped (a write per 4 KiB page):
    fresh memory costs more than the arithmetic done in it (~2 ms per MB on the benchmark's
    machines, where the host backs a page only when it is first touched), better spent in a
    second thread beside other work, as :func:`core.transfer.transfer_sequence` does."""
    work = _Workspace()
    t = min(chunk, n_frames)
    for a in [*rhs_buffers(work, n_vertices, t).values(), work("B", (n_vertices, 3 * t), _WORK)]:
        _touch_pages(a)
    return work


def paged_in(shape: tuple, dtype) -> np.ndarray:
    """An uninitialised array with every page already mapped (the stage's output: the first
    writes to a fresh 245 MB array cost ~0.4 s of page faults, better spent beside other work
    than in the stage's threads)."""
    a = np.empty(shape, dtype=dtype)
    _touch_pages(a)
    return a


def _touch_pages(a: np.ndarray) -> None:
    """One write per 4 KiB page of the contiguous array ``a`` (its values are not kept)."""
    a.reshape(-1).view(np.uint8)[::4096] = 0


def load_kernels() -> None:
    """Load this module's compiled kernels (numba, from its on-disk cache) by running them once
    on a triangle, with the argument types of the detail stage: the first call of each costs
    ~0.2 s in a new process, which :func:`core.transfer.transfer_sequence` spends in its
    second thread beside the decomposition instead of in the detail stage."""
    x = np.zeros((3, 3, 1))
    x[0, 1, 0] = x[1, 2, 0] = 1.0
    faces = np.array([[0, 1, 2]], dtype=np.int64)
    Fs = _frames_from_positions(x, faces, np.array([1, 2, 0], dtype=np.int64), True)
    B = _rotate(Fs[:3], Fs[:3], np.zeros((3, 3, 1), dtype=_WORK), 1.0, ok=Fs[3] & Fs[3], out=np.empty((3, 3), dtype=_WORK))
    _scatter_frames(B, np.arange(3, dtype=np.int64), np.zeros((3, 3)), np.empty((1, 3, 3), dtype=_WORK), 0)
    f3 = lambda: np.empty((3, 3, 1), dtype=_WORK)
    b2 = lambda: np.empty((3, 1), dtype=np.bool_)
    z = np.zeros((3, 3), dtype=_WORK)
    _chunk_rhs(x.reshape(9, 1), np.ones((1, 1)), x.reshape(9, 1), np.ones((1, 1)), faces, np.array([1, 2, 0], dtype=np.int64),
               np.array([NORMAL_CANCEL, 1e-6, 0.9, 1.0]), np.zeros((9, 1), dtype=_WORK), np.zeros((1, 1), dtype=_WORK), z,
               np.ones(1, dtype=_WORK), z, z, z, np.arange(3, dtype=np.int64), np.empty((9, 1)), np.empty((3, 3, 1)),
               np.empty((3, 1)), f3(), f3(), f3(), b2(), b2(), np.empty((9, 1), dtype=_WORK), np.empty((3, 3), dtype=_WORK))


def _report(progress, done: int, n_frames: int):
    if progress is not None:
        progress(done / n_frames, f"fine details: {done}/{n_frames} frames")


def detail_morph_targets(details, rtol: float = 0.05, max_rank: int = 64, ranks=(8, 16, 24, 32, 48, 64)):
    """Per-frame details ``D_t`` (T, V, 3) as ``r`` extra morph targets: ``D_t ≈ C_t B``.

    For playback: a viewer plays ``C`` (T, r) as weights of the shapes ``B`` (r, V, 3) like any
    blendshape, so the details move at full frame rate with nothing sent per frame.

    The truncated SVD of ``[D_t]`` (T, 3V), from the eigenvectors of its (T, T) Gram matrix;
    ``r`` is the first of ``ranks`` (capped at ``max_rank`` and T) whose largest vertex error in
    any frame is at most ``rtol`` × the largest detail (0.05: on ICT → Rocketbox, 300 frames,
    r = 24 and 0.044 mm for details up to 1.15 mm). The error is measured, not estimated:
    details live on a small part of the head, so an RMS over all vertices would hide them
    (on ICT → Rocketbox a rank with 0.014 mm RMS still missed a wrinkle by 0.9 mm).

    Returns
    -------
    coeffs (T, r), basis (r, V, 3), max_m (largest residual of any vertex in any frame, metres)
    """
    D = np.asarray(details)
    if D.ndim != 3 or D.shape[2] != 3 or len(D) == 0:
        raise ValueError(f"details: expected (T, V, 3), got {D.shape}")
    T, V, _ = D.shape
    X = D.reshape(T, 3 * V).astype(np.float64)
    top = float(np.sqrt((D.astype(np.float64) ** 2).sum(-1)).max())
    if top == 0:
        return np.zeros((T, 0)), np.zeros((0, V, 3)), 0.0
    ev, U = np.linalg.eigh(X @ X.T)
    order = np.argsort(ev)[::-1]
    ev, U = np.clip(ev[order], 0, None), U[:, order]
    cap = min(max_rank, T, int((ev > 1e-24 * ev[0]).sum()))
    worst = top
    for r in sorted({min(int(x), cap) for x in ranks} | {cap}):
        Q = U[:, :r].T @ X / np.sqrt(ev[:r])[:, None]  # orthonormal rows (r, 3V)
        C = X @ Q.T
        worst = 0.0
        for s in range(0, T, 64):
            res = (C[s:s + 64] @ Q - X[s:s + 64]).reshape(-1, V, 3)
            worst = max(worst, float(np.sqrt((res ** 2).sum(-1)).max()))
        if worst <= rtol * top:
            break
    return C, Q.reshape(r, V, 3), worst
