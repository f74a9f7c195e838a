"""Controllable high-fidelity transfer of dense mesh sequences (Xu et al. 2014).

Pipeline (:func:`transfer_sequence`):

1. preprocessing (§3, :mod:`.correspond`): when the target has its own topology, register the
   source reference onto it (landmarks + non-rigid ICP) and resample it in the source topology;
2. decomposition (eq. 1-4, :mod:`.decompose`): Taubin smoothing + Laplacian coating;
3. basis selection (eq. 6-7, :mod:`.bases`): greedy frames with non-negative weights;
4. feature-preserving deformation transfer of the bases (eq. 9-11, :mod:`.deformation`);
5. fine-scale detail transfer (eq. 16, 5, :mod:`.details`).

Editing (eq. 12-15 and 17-21) lives in :mod:`.edit`.
"""

from __future__ import annotations

import dataclasses
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ..cores import free_cores
from ..geometry import weld_vertices
from ..model import Rig
from ..progress import ProgressFn, report
from ._mesh import bbox_size, check_faces, check_positions
from .bases import BasisSelection, gram_from_factored, nnls_gram, select_bases
from .correspond import Registration, landmarks_from_shapes, register
from .decompose import (
    FactoredSequence, PoissonReconstructor, TaubinFilter, factor_sequence, laplacian_coating, laplacian_operator,
    taubin_smooth)
from .deformation import DeformationTransfer, deformation_gradients, deformation_transfer, line_gradients
from ._cholesky import SparseCholesky
from .details import _WORK, DetailTransfer, detail_workspace, load_kernels, paged_in
from .edit import TransferEditor
from .features import feature_lines_near, hole_loops, line_edges, loops_near, marker_loop, seam_loops
from .settings import TransferSettings
from .welded import WeldedSource, weld_source

__all__ = [
    "TransferSettings", "TransferResult", "transfer_sequence", "naive_transfer",
    "WeldedSource", "weld_source", "register_target", "Decomposition", "decompose_sequence", "select_sequence_bases",
    "BasisTransfer", "transfer_bases", "transfer_details", "assemble_result", "decomposition_operators", "transfer_system", "detail_transfer",
    "TaubinFilter", "taubin_smooth", "laplacian_operator", "laplacian_coating", "PoissonReconstructor",
    "FactoredSequence", "factor_sequence", "nnls_gram", "select_bases", "BasisSelection",
    "DeformationTransfer", "deformation_transfer", "deformation_gradients", "line_gradients",
    "DetailTransfer", "register", "Registration", "landmarks_from_shapes",
    "line_edges", "hole_loops", "seam_loops", "loops_near", "marker_loop", "feature_lines_near",
]


@dataclass(frozen=True, eq=False)
class TransferResult:
    """Transferred sequence as a blendshape rig plus per-frame details.

    ``mesh_t = neutral + weights[t] @ deltas + details[t]`` in the source topology
    (``faces``). ``neutral`` is the target reference resampled in that topology.

    Attributes
    ----------
    faces : (F, 3) int
    neutral : (V, 3)
    deltas : (K, V, 3)        target bases b'_k minus the smoothed target reference
    weights : (T, K)          non-negative (eq. 6)
    details : (T, V, 3) float32 or None   fine-scale motion (eq. 16) as displacements
    frames : (K,) int         source frame each basis was taken from
    selection_errors : (K+1,) relative residual energy after 0..K bases
    source_bases : (K, V, 3)  the smoothed source bases b_k
    target_smooth_ref : (V, 3) T̄_0
    registration : Registration or None
    factor_residual_mm : RMS error of the sequence factorisation
    timings : dict stage -> seconds
    welded : WeldedSource or None   the seam welding the eq. 9 system was solved on
    system : DeformationTransfer or None   the factorised eq. 9 system (welded ids), for editing
    """

    faces: np.ndarray
    neutral: np.ndarray
    deltas: np.ndarray
    weights: np.ndarray
    details: Optional[np.ndarray]
    frames: np.ndarray
    selection_errors: np.ndarray
    source_bases: np.ndarray
    target_smooth_ref: np.ndarray
    registration: Optional[Registration] = None
    factor_residual_mm: float = 0.0
    timings: dict = field(default_factory=dict)
    welded: Optional["WeldedSource"] = None
    system: Optional[DeformationTransfer] = None

    @property
    def n_bases(self) -> int:
        return len(self.deltas)

    def large_scale(self, idx=slice(None)) -> np.ndarray:
        """Smoothed target frames ``T̄_t`` (t, V, 3) (eq. 8)."""
        w = np.atleast_2d(self.weights[idx])
        K, V = self.deltas.shape[:2]
        return self.target_smooth_ref + (w @ self.deltas.reshape(K, 3 * V)).reshape(len(w), V, 3)

    def sequence(self, idx=slice(None)) -> np.ndarray:
        """Full target frames ``T_t`` (t, V, 3) (eq. 5)."""
        w = np.atleast_2d(self.weights[idx])
        K, V = self.deltas.shape[:2]
        out = self.neutral + (w @ self.deltas.reshape(K, 3 * V)).reshape(len(w), V, 3)
        if self.details is not None:
            d = self.details[idx]
            out += d.reshape(out.shape) if d.ndim == 3 else d[None]
        return out

    def to_rig(self, name: str = "transfer", prefix: str = "xu_basis_"):
        """A :class:`core.model.Rig` (neutral + K deltas); details are not part of a rig."""

        names = [f"{prefix}{k:02d}_f{int(f)}" for k, f in enumerate(self.frames)]
        return Rig(self.neutral, self.faces, self.deltas, names, None, "m", name)

    def editor(self, source_rig=None, settings: Optional[TransferSettings] = None):
        """A :class:`~core.transfer.edit.TransferEditor` for large-scale edits (eq. 12-15) of this
        result: the factorised eq. 9 system it was solved with (rebuilt from ``source_rig`` and
        ``settings`` for a result that does not carry it)."""

        return TransferEditor(self, source_rig, settings)


# -- the steps of transfer_sequence (each a pure function; the pipeline caches each one) ----------
def register_target(src: WeldedSource, target_ref, target_faces, settings: TransferSettings,
                    progress: Optional[ProgressFn] = None) -> tuple:
    """§3 preprocessing: the target reference in the welded source topology, ``(T_w0 (V_w, 3),
    Registration or None)``. Same topology: the target as is; else landmarks + non-rigid ICP
    (:func:`.correspond.register`), which needs ``settings.landmarks``. ``progress(fraction,
    message)`` hears every ICP iteration, with a time estimate."""
    T0in = check_positions(target_ref, "target_ref")
    Ft_in = check_faces(target_faces, len(T0in), "target_faces")
    Vs = len(src.neutral)
    if len(T0in) == Vs and Ft_in.shape == src.source_faces.shape and np.array_equal(Ft_in, src.source_faces):
        return T0in[src.rep], None
    if settings.landmarks is None:
        raise ValueError("target_ref has another topology than source_ref: settings.landmarks = "
                         "(source vertex ids, target points) is required for the registration (§3)")
    src_lm, tgt_pts = settings.landmarks
    src_lm = np.asarray(src_lm, dtype=np.int64)
    if src_lm.size and (src_lm.min() < 0 or src_lm.max() >= Vs):
        raise ValueError(f"settings.landmarks: source vertex ids must lie in [0, {Vs})")
    report(progress, 0.0, "registration (landmarks + non-rigid ICP)")
    reg = register(src.welded_neutral, src.faces, T0in, Ft_in, src.index[src_lm], tgt_pts, settings.icp_steps,
                   settings.max_distance, settings.icp, crop=settings.crop, crop_index=src.index, progress=progress)
    report(progress, 1.0, "registration done")
    return reg.resampled, reg


@dataclass(frozen=True, eq=False)
class Decomposition:
    """Eq. 1-4 of the source sequence, factored: ``frames`` S_t, ``smooth`` S̄_t = P S_t (Taubin)
    and ``coating`` ξ_t = L (S_t - S̄_t), all in the welded topology, with the ``filter`` P and
    the Poisson ``reconstructor`` of L the details are rebuilt with."""

    frames: FactoredSequence
    smooth: FactoredSequence
    coating: FactoredSequence
    filter: TaubinFilter
    reconstructor: PoissonReconstructor


def decompose_sequence(src: WeldedSource, source_seq, settings: TransferSettings, filt: Optional[TaubinFilter] = None,
                       poisson: Optional[PoissonReconstructor] = None) -> Decomposition:
    """Multi-scale decomposition (eq. 1-4) of a (T, V, 3) source sequence in the topology of
    ``src``: one low-rank factorisation, the (linear) filter and coating applied to its basis.
    ``filt`` and ``poisson``, when given, are the filter and reconstructor this step would build
    (:func:`decomposition_operators`, e.g. built beside it in another thread)."""
    V = src.n
    seq = np.asarray(source_seq)
    if seq.ndim != 3 or seq.shape[1:] != (len(src.neutral), 3) or len(seq) == 0:
        raise ValueError(f"source_seq: expected (T, {len(src.neutral)}, 3) frames in the topology of source_ref, got {seq.shape}")
    # factor the frames as given and weld the (linear) basis: no welded copy of the sequence
    fac = factor_sequence(seq, settings.rank_rtol, base=src.neutral)
    fac = FactoredSequence(fac.base[src.rep], fac.coeffs, fac.basis[:, src.rep], fac.residual_rms)
    if filt is None or poisson is None:
        f, p = decomposition_operators(src, settings, filt is None)
        filt, poisson = filt or f, poisson or p
    # S̄_t = P S_t with P linear: one filter pass over base and basis together
    r = fac.rank
    block = np.concatenate([fac.base[:, :, None], fac.basis.transpose(1, 2, 0)], axis=2)
    block = filt.apply(block.reshape(V, 3 * (r + 1))).reshape(V, 3, r + 1)
    smooth = FactoredSequence(block[:, :, 0].copy(), fac.coeffs, block[:, :, 1:].transpose(2, 0, 1).copy(), fac.residual_rms)
    # eq. 1 on base and basis: ξ = L (S - S̄), linear, one sparse product for the whole block
    detail = np.concatenate([(fac.base - smooth.base)[None], fac.basis - smooth.basis])  # (r+1, V, 3)
    lap = np.asarray(poisson.L @ detail.transpose(1, 2, 0).reshape(V, 3 * (r + 1))).reshape(V, 3, r + 1)
    coat = FactoredSequence(np.ascontiguousarray(lap[:, :, 0]), fac.coeffs,
                            np.ascontiguousarray(lap[:, :, 1:].transpose(2, 0, 1)), fac.residual_rms)
    return Decomposition(fac, smooth, coat, filt, poisson)


def decomposition_operators(src: WeldedSource, settings: TransferSettings, taubin: bool = True) -> tuple:
    """``(TaubinFilter or None, PoissonReconstructor)`` of the welded topology: the linear
    operators of eq. 1-4, which depend on the mesh and the settings only."""
    V = src.n
    filt = TaubinFilter(src.faces, V, settings.iterations, settings.lam, settings.mu) if taubin else None
    poisson = PoissonReconstructor(src.faces, V, settings.laplacian, src.welded_neutral if settings.laplacian == "cotangent" else None,
                                   settings.detail_screening)
    return filt, poisson


def select_sequence_bases(dec: Decomposition, settings: TransferSettings) -> tuple:
    """Greedy basis selection with non-negative weights (eq. 6-7) on the smoothed frames:
    ``(BasisSelection, source bases b_k (K, V_w, 3))``."""
    sm = dec.smooth
    V = sm.base.shape[0]
    Qb = sm.basis.reshape(sm.rank, 3 * V)
    gram = gram_from_factored(dec.frames.coeffs, Qb @ Qb.T)
    sel = select_bases(gram, settings.eps, settings.max_bases, settings.candidates, settings.min_bases)
    return sel, (sm.frames(sel.frames) if sel.n_bases else np.zeros((0, V, 3)))


@dataclass(frozen=True, eq=False)
class BasisTransfer:
    """Eq. 9-11: the smoothed target reference ``T̄_0`` (V_w, 3), the factorised ``system``, and
    the transferred bases as ``deltas`` b'_k - T̄_0 (K, V_w, 3)."""

    target_smooth_ref: np.ndarray
    system: DeformationTransfer
    deltas: np.ndarray


def transfer_bases(src: WeldedSource, dec: Decomposition, source_bases, target_welded, settings: TransferSettings,
                   system: Optional[DeformationTransfer] = None) -> BasisTransfer:
    """Feature-preserving deformation transfer of the source bases (eq. 9-11). ``system``, when
    given, is :func:`transfer_system`'s (built beside the decomposition in another thread);
    used only if its references are exactly this decomposition's."""
    if system is not None and np.array_equal(system.S0, dec.smooth.base):
        dt, Tb0 = system, system.T0
    else:
        Tb0 = dec.filter.apply(np.asarray(target_welded, dtype=np.float64))
        dt = DeformationTransfer(dec.smooth.base, Tb0, src.faces, _feature_edges(settings, src.index, src.n), settings.alpha,
                                 factor=SparseCholesky)
    K = len(source_bases)
    deltas = (dt.transfer(source_bases) - Tb0) if K else np.zeros((0, src.n, 3))
    return BasisTransfer(Tb0, dt, deltas)


def transfer_system(src: WeldedSource, filt: TaubinFilter, target_welded, settings: TransferSettings) -> DeformationTransfer:
    """The factorised eq. 9 system of :func:`transfer_bases`, from the meshes alone: its
    references are the smoothed source and target references ``S̄_0 = P S_0`` and ``T̄_0``
    (the filter is linear and column by column, so ``P S_0`` is bit for bit the base of the
    decomposition's smoothed sequence). Factorised by :class:`._cholesky.SparseCholesky`, without
    the GIL (beside the sequence factorisation in :func:`transfer_sequence`)."""
    refs = filt.apply(np.concatenate([src.welded_neutral, np.asarray(target_welded, dtype=np.float64)], axis=1))
    return DeformationTransfer(refs[:, :3].copy(), refs[:, 3:].copy(), src.faces, _feature_edges(settings, src.index, src.n),
                               settings.alpha, factor=SparseCholesky)


def detail_transfer(src: WeldedSource, dec: Decomposition, target_welded, target_smooth_ref,
                    settings: TransferSettings) -> DetailTransfer:
    """The :class:`DetailTransfer` of :func:`transfer_details` (reference frames and coatings of
    both sides), from the decomposition and the smoothed target reference ``T̄_0``."""
    Tw0 = np.asarray(target_welded, dtype=np.float64)
    gain = settings.detail_gain if settings.detail_gain is not None else bbox_size(Tw0) / max(bbox_size(src.welded_neutral), 1e-300)
    return DetailTransfer(src.faces, dec.reconstructor, dec.smooth.base, dec.coating.base, Tw0, target_smooth_ref, gain,
                          settings.rotate_reference_details)


def transfer_details(src: WeldedSource, dec: Decomposition, sel: BasisSelection, target_welded, bt: BasisTransfer,
                     settings: TransferSettings, progress: Optional[ProgressFn] = None, out=None,
                     det: Optional[DetailTransfer] = None, work=None) -> Optional[np.ndarray]:
    """Fine-scale detail transfer (eq. 16, 5): (T, V, 3) float32 displacements relative to the
    target neutral, in the source vertex order; None when ``settings.details`` is off. ``out``:
    an array of that shape and dtype to write them into (e.g. allocated and paged in
    beforehand); ``det``: :func:`detail_transfer`'s object for these inputs, if built already;
    ``work``: the stage's scratch (:func:`.details.detail_workspace`), if made already."""
    if not settings.details:
        return None
    det = det or detail_transfer(src, dec, target_welded, bt.target_smooth_ref, settings)
    # T̄_t = T̄_0 + W_t Δ (eq. 8) as a factored sequence; details relative to the neutral
    # T_0, written straight in the unwelded vertex order
    target_smooth = FactoredSequence(bt.target_smooth_ref, sel.weights, bt.deltas, 0.0)
    return det.displacements(dec.smooth, dec.coating, target_smooth, dec.frames.n_frames, settings.chunk, relative=True,
                             vertices=src.index, progress=progress, out=out, work=work)


def assemble_result(src: WeldedSource, target_welded, dec: Decomposition, sel: BasisSelection, source_bases,
                    bt: BasisTransfer, details, registration=None, timings=None) -> TransferResult:
    """The :class:`TransferResult` of the steps, in the source vertex order."""
    return TransferResult(
        faces=src.source_faces, neutral=src.unweld(np.asarray(target_welded)), deltas=src.unweld(bt.deltas),
        weights=sel.weights, details=details, frames=sel.frames, selection_errors=sel.errors,
        source_bases=src.unweld(source_bases), target_smooth_ref=src.unweld(bt.target_smooth_ref),
        registration=registration, factor_residual_mm=dec.frames.residual_rms * 1000.0, timings=dict(timings or {}),
        welded=src, system=bt.system)


def _feature_edges(settings, welded_index, n):
    if settings.feature_lines is None:
        return np.zeros((0, 2), np.int64)
    lines = [welded_index[np.asarray(ln, dtype=np.int64)] for ln in settings.feature_lines]
    for ln in settings.feature_lines:
        ln = np.asarray(ln)
        if ln.size and (ln.min() < 0 or ln.max() >= len(welded_index)):
            raise ValueError(f"settings.feature_lines: vertex ids must lie in [0, {len(welded_index)})")
    return line_edges(lines, closed=True)


def transfer_sequence(source_ref, source_faces, source_seq, target_ref, target_faces,
                      settings: Optional[TransferSettings] = None, progress: Optional[ProgressFn] = None,
                      **overrides) -> TransferResult:
    """Transfer a dense source sequence onto a target face (Xu et al. 2014 §3-5).

    The composition of the steps :func:`weld_source`, :func:`register_target`,
    :func:`decompose_sequence`, :func:`select_sequence_bases`, :func:`transfer_bases`,
    :func:`transfer_details` and :func:`assemble_result` (the pipeline's dense stages run the
    same steps, each cached on its own). With a second core free, what depends on the meshes
    alone (:func:`transfer_system`, the detail kernels, :func:`detail_transfer`, the
    output's pages) is made ready in a second thread beside the
    decomposition, basis selection and transfer; the result is the same either way.

    Parameters
    ----------
    source_ref : (V, 3)        source reference expression ``S_0`` (metres)
    source_faces : (F, 3) int
    source_seq : (T, V, 3)     source frames ``S_1..S_T`` in the topology of ``source_ref``
    target_ref : (V', 3)       target reference expression ``T_0``
    target_faces : (F', 3) int; when the target topology differs from the source's,
                               ``settings.landmarks`` is required and §3 preprocessing runs
    settings : TransferSettings; keyword ``overrides`` replace single fields
    progress : ``(fraction, message) -> None``, optional: called at each stage, after every
        iteration of the registration's non-rigid ICP (with a time estimate) and after every
        chunk of the detail stage

    Returns
    -------
    TransferResult in the source topology (``source_faces``).

    Raises
    ------
    ValueError
        Bad shapes, non-finite input, a target of another topology without landmarks.
    """

    settings = settings or TransferSettings()
    if overrides:
        settings = dataclasses.replace(settings, **overrides)
    timings = {}
    t0 = time.perf_counter()
    src = weld_source(source_ref, source_faces)
    seq = np.asarray(source_seq)
    if seq.ndim != 3 or seq.shape[1:] != (len(src.neutral), 3) or len(seq) == 0:
        raise ValueError(f"source_seq: expected (T, {len(src.neutral)}, 3) frames in the topology of source_ref, got {seq.shape}")
    Tw0, registration = register_target(src, target_ref, target_faces, settings,
                                        None if progress is None else (lambda f, m: progress(0.4 * f, m)))
    timings["preprocessing"] = time.perf_counter() - t0

    # What depends on the meshes alone -- the eq. 9 system on the smoothed references, the
    # detail stage's compiled kernels, reference frames and the pages of its 363 x 56K x 3
    # output on the benchmark -- is made ready by a second thread while the sequence is
    # factored and smoothed and the bases selected and transferred (BLAS and page faults run
    # without the GIL). The same objects either way: the result does not depend on it (tested).
    filt, poisson = decomposition_operators(src, settings)
    side = ThreadPoolExecutor(1) if free_cores() > 1 else None
    try:
        system = out = det = work = None
        if side is not None:  # beside the sequence factorisation (~1.1 s on the benchmark)
            # in this order: what the main thread needs first first. The eq. 9 system and the
            # detail stage's factorisation are compiled without the GIL; the pages of the output
            # and of the detail stage's scratch (~800 MB on the benchmark: 0.1-2 s of page
            # faults, by how long ago the memory was last used) fill the rest of the time
            if settings.details:
                side.submit(load_kernels)
            system = side.submit(transfer_system, src, filt, Tw0, settings)
            if settings.details:
                side.submit(poisson.prepare, _WORK)
                out = side.submit(paged_in, (len(seq), len(src.neutral), 3), _WORK)
                work = [side.submit(detail_workspace, src.n, settings.chunk, len(seq)) for _ in range(2)]

        report(progress, 0.4, "decomposition (smoothing + Laplacian coating)")
        t = time.perf_counter()
        dec = decompose_sequence(src, seq, settings, filt, poisson)
        timings["decomposition"] = time.perf_counter() - t
        if side is not None and settings.details:  # beside the basis selection and transfer
            det = side.submit(lambda: detail_transfer(src, dec, Tw0, system.result().T0, settings))

        report(progress, 0.45, "basis selection")
        t = time.perf_counter()
        sel, src_bases = select_sequence_bases(dec, settings)
        timings["basis_selection"] = time.perf_counter() - t

        report(progress, 0.5, f"deformation transfer of {sel.n_bases} bases")
        t = time.perf_counter()
        bt = transfer_bases(src, dec, src_bases, Tw0, settings, None if system is None else system.result())
        timings["transfer"] = time.perf_counter() - t

        t = time.perf_counter()
        # what the second thread has not started yet is made here instead (it is behind: the
        # page faults of cold memory can take seconds)
        det = _made(det)
        if system is None or bt.system is not system.result():
            det = None  # made for another system's references
        details = transfer_details(src, dec, sel, Tw0, bt, settings,
                                   None if progress is None else (lambda f, m: progress(0.55 + 0.45 * f, m)),
                                   _made(out), det, None if work is None else [w for w in map(_made, work) if w is not None])
        timings["details"] = time.perf_counter() - t
    finally:
        if side is not None:
            side.shutdown(wait=True, cancel_futures=True)

    report(progress, 1.0, f"{len(seq)} frames, {sel.n_bases} bases")
    return assemble_result(src, Tw0, dec, sel, src_bases, bt, details, registration, timings)


def _made(future):
    """The result of a second thread's task, or None when it had not started (then cancelled:
    the caller makes it itself)."""
    if future is None or future.cancel():
        return None
    return future.result()


def naive_transfer(source_ref, target_ref, faces, frames, feature_edges=None, alpha: float = 100.0,
                   factorised: Optional[DeformationTransfer] = None) -> np.ndarray:
    """Reference: per-frame deformation transfer of every frame (Sumner & Popović 2004).

    The "naive method that transfers the motions of all frames" of Xu et al. 2014 §6: no
    smoothing, no bases, no details; one shared factorisation, one solve per frame.
    Welds seam duplicates like :func:`transfer_sequence`. Returns (T, V, 3).
    """
    S0 = check_positions(source_ref, "source_ref")
    Fs = check_faces(faces, len(S0))
    wi, rep, Fw = weld_vertices(S0, Fs)
    dt = factorised or DeformationTransfer(S0[rep], np.asarray(target_ref, dtype=np.float64)[rep], Fw, feature_edges, alpha)
    fr = np.asarray(frames, dtype=np.float64)
    out = np.empty(fr.shape)
    for t in range(len(fr)):
        out[t] = dt.transfer(fr[t][rep])[wi]
    return out
