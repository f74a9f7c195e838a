r"""Fine-scale detail transfer by Laplacian-coating rotation (Xu et al. 2014 §5.1, eq. 16, 5).

For every vertex and frame, the source coating change is rotated from the local frame ``F_t``
of the smoothed source ``S̄_t`` into the local frame ``F'_t`` of the smoothed target ``T̄_t``
(frames: normal + projected edge, :func:`~core.transfer._mesh.frame_vectors`):

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

Frames are processed in chunks; the Poisson solves share one factorisation
(:class:`~core.transfer.decompose.PoissonReconstructor`).
"""

from __future__ import annotations

import numpy as np

from ._mesh import first_neighbour, frame_vectors, incidence, to_local, to_world
from .decompose import FactoredSequence, PoissonReconstructor

__all__ = ["local_coating", "DetailTransfer"]


def local_coating(frames, coating: np.ndarray) -> np.ndarray:
    """World coating (..., V, 3) -> local coordinates ``F^T ξ`` (..., V, 3); ``frames`` is
    ``(t, b, n)`` from :func:`~core.transfer._mesh.frame_vectors`."""
    return to_local(frames, coating)


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
        self.inc = incidence(self.faces, V)
        self.gain = float(gain)
        self.rotate_reference = bool(rotate_reference)
        self.xi0 = np.asarray(source_coating_ref, dtype=np.float64)
        F0 = frame_vectors(np.asarray(source_smooth_ref, dtype=np.float64), self.faces, self.nb, self.inc)
        self.l0 = local_coating(F0, source_coating_ref)
        T0 = np.asarray(target_ref, dtype=np.float64)
        Tb0 = np.asarray(target_smooth_ref, dtype=np.float64)
        Ft0 = frame_vectors(Tb0, self.faces, self.nb, self.inc)
        self.That0 = np.asarray(poisson.L @ (T0 - Tb0))
        self.lt0 = local_coating(Ft0, self.That0)
        self.ref_displacement = T0 - Tb0
        self.mean = poisson.component_mean(T0 - Tb0)

    def coatings(self, source_smooth: np.ndarray, source_coating: np.ndarray, target_smooth: np.ndarray) -> np.ndarray:
        """Target coatings for (t, V, 3) chunks: ``T̂_0 + g F'_t F_t^T (ξ_t - ξ_0)`` (eq. 5, 16),
        or ``F'_t (F'^T_0 T̂_0 + g (F_t^T ξ_t - F_0^T ξ_0))`` with ``rotate_reference``."""
        # frames in float32: they only rotate (1e-7 relative); the Poisson solve is float64
        Fs = frame_vectors(np.asarray(source_smooth, dtype=np.float32), self.faces, self.nb, self.inc)
        Ft = frame_vectors(np.asarray(target_smooth, dtype=np.float32), self.faces, self.nb, self.inc)
        if not self.rotate_reference:
            change = np.asarray(source_coating, dtype=np.float32) - self.xi0.astype(np.float32)
            out = to_world(Ft, local_coating(Fs, change))
            out *= self.gain
            return out + self.That0
        local = local_coating(Fs, np.asarray(source_coating, dtype=np.float32))
        local -= self.l0
        local *= self.gain
        local += self.lt0
        return to_world(Ft, local)

    def displacements(self, source_smooth: FactoredSequence, source_coating: FactoredSequence,
                      target_smooth_frames, n_frames: int, chunk: int = 32, dtype=np.float32) -> np.ndarray:
        """Detail displacements ``y_t = T_t - T̄_t`` for all frames, (T, V, 3) ``dtype``.

        ``target_smooth_frames(idx)`` returns the (t, V, 3) smoothed target frames ``T̄_t``.
        """
        V = self.poisson.n
        out = np.empty((n_frames, V, 3), dtype=dtype)
        for s in range(0, n_frames, chunk):
            idx = slice(s, min(s + chunk, n_frames))
            c = self.coatings(source_smooth.frames(idx), source_coating.frames(idx), target_smooth_frames(idx))
            out[idx] = self.poisson.displacement(c, self.mean, self.ref_displacement)
        return out
