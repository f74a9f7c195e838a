r"""Carry a transfer from the source topology back to the target's own mesh.

The transfer (Xu et al. 2014 §3-5) runs in the source's topology: the target reference is
resampled as the fitted source surface (:mod:`.correspond`), and the bases and details are
displacements of its vertices. A user's character is the target's own mesh (its vertex order,
UVs, materials and skinning), so the result is carried back through the registration:

.. math:: d'_j = w_j \sum_{k=1}^{3} b_{jk}\, d_{f_j(k)}, \qquad
          w_j = t(c_j)\, s\!\left(\frac{\delta_j - r_0}{r_1 - r_0}\right)

for every target vertex ``j``: ``c_j`` is its closest point on the fitted source surface, in
triangle ``f_j`` with barycentric coordinates ``b_j``, at distance ``δ_j`` (among the source
triangles facing the target vertex's way, when the target's faces are given); ``d`` a
displacement of the source vertices (a basis delta, a detail morph target). The weight fades
the motion out where the source surface does not describe the target:

* ``s`` is the smoothstep ``3x² - 2x³`` clamped to [0, 1], reversed (1 below ``r_0``, 0 beyond
  ``r_1``): target parts the fitted face does not reach (eyeballs under the lids, a body)
  keep their neutral, with a continuous fall-off in between;
* ``t`` is the source's trust interpolated at ``c_j``: 1 on the source's face skin (the face
  crop, :func:`.correspond.face_crop`, which a cropped registration fitted and a whole-head one
  fitted among the rest), 0 elsewhere (back of head, neck, and the mouth bag and eye sockets
  that a whole-head registration lays onto the target's lips and lids too), ramped over
  ``rings`` vertex rings inside the face, so its border fades out instead of stepping. Only
  the face's triangles are searched for ``c_j``.

``w = 0`` gives a displacement of exactly 0: those target vertices keep the neutral to the
bit. The map is linear, one sparse (V', V) matrix for every basis and detail target.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import scipy.sparse as sp

from ..geometry import ClosestPoints, vertex_adjacency, vertex_normals
from ._mesh import bbox_size, check_faces, check_positions

__all__ = ["CarryBack", "carry_back", "INNER", "OUTER", "RINGS"]

#: distances (fractions of the target's bounding-box diagonal) where the fall-off starts / ends
INNER = 0.005
OUTER = 0.02
#: vertex rings over which the trust ramps up inside the fitted region
RINGS = 3


@dataclass(frozen=True, eq=False)
class CarryBack:
    """The map from source-topology displacements to the target's vertices (see the module).

    Attributes
    ----------
    matrix : (V', V) scipy.sparse.csr_matrix, the weights ``w_j b_jk`` (rows of zeros where w = 0)
    weight : (V',) w in [0, 1]
    distance : (V',) δ, target vertex -> fitted source surface
    triangle : (V',) int, barycentric : (V', 3)  the closest points on the source faces
    """

    matrix: sp.csr_matrix
    weight: np.ndarray
    distance: np.ndarray
    triangle: np.ndarray
    barycentric: np.ndarray

    def apply(self, values) -> np.ndarray:
        """Carry (V, c) or (K, V, c) per-source-vertex values to (V', c) / (K, V', c)."""
        v = np.asarray(values, dtype=np.float64)
        if v.ndim == 2:
            return np.asarray(self.matrix @ v)
        if v.ndim != 3 or v.shape[1] != self.matrix.shape[1]:
            raise ValueError(f"values: expected ({self.matrix.shape[1]}, c) or (K, {self.matrix.shape[1]}, c), got {v.shape}")
        K, V, c = v.shape
        out = self.matrix @ v.transpose(1, 0, 2).reshape(V, K * c)
        return np.ascontiguousarray(np.asarray(out).reshape(-1, K, c).transpose(1, 0, 2))


def _smoothstep_down(x):
    x = np.clip(x, 0.0, 1.0)
    return 1.0 - x * x * (3.0 - 2.0 * x)


def carry_back(fitted, faces, target_positions, trusted: Optional[np.ndarray] = None, inner: float = INNER,
               outer: float = OUTER, rings: int = RINGS, target_faces=None) -> CarryBack:
    """The :class:`CarryBack` of target vertices onto the fitted source surface.

    Parameters
    ----------
    fitted : (V, 3)  the fitted source surface (the target resampled in the source topology,
        :attr:`.correspond.Registration.resampled` / ``TransferResult.neutral``)
    faces : (F, 3) int, the source topology
    target_positions : (V', 3), the target's own neutral
    trusted : (V,) bool, optional
        Source vertices fitted to the target (the registration's crop); default all.
    inner, outer : float, 0 <= inner < outer, fractions of the target's bounding-box diagonal
    rings : int >= 0, vertex rings of the trust ramp inside ``trusted``
    target_faces : (F', 3) int, optional
        The target's triangles: with them a target vertex is located only on source triangles
        facing its way (normals less than 90° apart), so the upper lip takes the upper lip's
        motion where the lips touch; without, the plain closest point.

    Raises
    ------
    ValueError
        Bad shapes, ``trusted`` not (V,) bool, ``inner``/``outer`` out of order.
    """

    S = check_positions(fitted, "fitted")
    F = check_faces(faces, len(S), "faces")
    T = check_positions(target_positions, "target_positions")
    if not 0 <= inner < outer:
        raise ValueError(f"inner, outer: expected 0 <= inner < outer (fractions of the target's size), got {inner}, {outer}")
    if int(rings) != rings or rings < 0:
        raise ValueError(f"rings: expected a non-negative integer, got {rings!r}")
    trust = np.ones(len(S))
    if trusted is not None:
        m = np.asarray(trusted)
        if m.shape != (len(S),) or m.dtype != bool:
            raise ValueError(f"trusted: expected a ({len(S)},) bool mask of the source vertices, got {m.shape} {m.dtype}")
        trust = m.astype(np.float64)
        if rings and not m.all():
            # distance in rings from the untrusted vertices, capped: 0 outside, k/rings k rings in
            A = vertex_adjacency(F, len(S))
            level = np.where(m, rings, 0)
            front = ~m
            for k in range(1, rings):
                front = (A @ front.astype(np.float64) > 0) & (level == rings)
                level[front] = k
            trust = level / rings
    size = bbox_size(T)
    # the closest point on the sheet facing the same way as the target vertex (dot >= 0): upper
    # and lower lips (or lids) in contact are two sheets a plain closest point mixes up
    Tf = check_faces(target_faces, len(T), "target_faces") if target_faces is not None else None
    nq = None if Tf is None else vertex_normals(T, Tf, fallback=None)
    # only the fitted region's triangles are searched: where the registration laid other parts of
    # the source onto the target too (a mouth bag projected onto the lips), they are not found
    fit = np.flatnonzero(trust[F].min(axis=1) > 0) if trusted is not None else np.arange(len(F))
    if len(fit) == 0:
        raise ValueError("trusted: no source triangle lies wholly in the trusted region")
    _, dist, tri, bary = ClosestPoints(S, F[fit]).query(T, max_distance=outer * size, normals=nq, min_dot=0.0)
    near = tri >= 0
    tri = np.where(near, fit[np.maximum(tri, 0)], -1)
    w = np.zeros(len(T))
    corners = F[np.maximum(tri, 0)]
    w[near] = (np.einsum("jk,jk->j", bary[near], trust[corners[near]])
               * _smoothstep_down((dist[near] - inner * size) / ((outer - inner) * size)))
    rows = np.repeat(np.arange(len(T)), 3)
    vals = (w[:, None] * bary).ravel()
    keep = vals != 0
    M = sp.csr_matrix((vals[keep], (rows[keep], corners.ravel()[keep])), shape=(len(T), len(S)))
    return CarryBack(M, w, np.where(near, dist, np.inf), np.where(near, tri, -1), bary)
