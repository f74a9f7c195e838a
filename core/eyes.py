"""The eyes as rigid parts: gaze mapped as the eyeballs' turn (issue 29, docs/evaluation.md "design E").

A rig's eyeballs are closed parts of its mesh, nearly spheres, that its gaze shapes turn about their
centres. A shape map fitted at face points (dense correspondence) sees only the lids, never the
eyeballs: on the sample (ICT -> Rocketbox, only Rocketbox's non-ARKit shapes) 35 % of the error was
on the eyeball vertices. :func:`gaze_rows` adds the eyeballs to the fit: each source shape's turn of
its eye part asks the target's eyeball on the same side to turn about the same axis.

Conventions: ``x`` across the face, the mid-plane ``x = `` the largest part's mid-x; a part is on the
side of the sign of its centre's ``x`` relative to it. Angles in radians (rotation vectors).

* :func:`eye_parts` finds, on each side, the largest part (not the whole mesh's largest) that some
  shape moves and a sphere fits within :data:`EYE_SPHERE_TOL` of its radius, its radius
  :data:`EYE_RADIUS` × the largest part's RMS radius. Both sides, or none.
* :func:`part_turns` fits each shape's motion of a part by a turn about the part's sphere centre
  (Kabsch, scipy's ``Rotation.align_vectors``) and says how much of that motion the turn explains
  (the *rigid share* ``1 − ‖R(p − c) − (p − c) − d‖² / ‖d‖²``, clipped to [0, 1]).
* :func:`gaze_rows`: the source's turn ``r_j`` counted by its rigid share ``ρ_j`` (a blink that drags
  the eye part non-rigidly turns it little), in the target's range: the gain
  ``g = max_k |q_k| / max_j |r_j|`` (the largest turn of the target's eyeball over its shapes over the
  largest of the source's eye part, per side — full range to full range, as ``motion_scale = rom``
  does for markers). The rows are the target eyeball's vertices ``p`` (with their shapes'
  displacements ``t_k(p)``) and, for the source, ``g ρ_j r_j × (p − c)``: the displacement of the
  target eyeball turned by the mapped angle (linearised), one row per vertex, each weighted as a
  face point.

Why not the same angle: ICT's eye parts turn about a fifth of the gaze the names mean
(``eyeLookOut_L`` 3.8° where Rocketbox's namesake turns its eyeball 19.6°) and deform with the lids;
turning the target's by the actor's angle measured B 0.420 -> 0.411 and C 0.314 -> 0.349.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial.transform import Rotation

#: a part is an eye when a sphere fits it within this fraction of its radius (RMS radial residual;
#: ICT's eye parts 1.7 %, Rocketbox's eyeballs 0.4 %)
EYE_SPHERE_TOL = 0.03
#: and its radius is within these fractions of the largest part's RMS radius (ICT 0.25, Rocketbox 0.14)
EYE_RADIUS = (0.05, 0.5)
#: parts with fewer vertices are left out (rivets, single quads)
EYE_MIN_VERTICES = 20
#: a rig whose shapes turn its eye parts by less than this (degrees) at most has no gaze to map:
#: the range gain would divide by almost nothing (ICT's largest 4.1°, Rocketbox's 30.2°)
EYE_MIN_TURN = 0.5


def mesh_parts(faces, n_vertices: int) -> np.ndarray:
    """(V,) int the connected part of each vertex (the triangles' edges; a vertex in no triangle is
    a part of its own)."""
    F = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    A = sp.coo_matrix((np.ones(F.size), (F.ravel(), np.roll(F, 1, 1).ravel())), (n_vertices, n_vertices))
    return connected_components(A, directed=False)[1]


def sphere_fit(points) -> tuple:
    """``(centre (3,), radius, RMS radial residual)`` of the algebraic least-squares sphere through
    ``points`` (N, 3), N >= 4: ``|p|² = 2 c·p + (r² − |c|²)`` solved for ``c`` and the constant."""
    P = np.asarray(points, dtype=np.float64)
    x = np.linalg.lstsq(np.c_[2 * P, np.ones(len(P))], (P ** 2).sum(1), rcond=None)[0]
    c = x[:3]
    radius = float(np.sqrt(max(x[3] + c @ c, 0.0)))
    return c, radius, float(np.linalg.norm(P - c, axis=1).std())


def eye_parts(rig) -> dict:
    """``{+1: (n,) int vertices, -1: (m,) int vertices}``: the rig's eye part on each side of the
    mid-plane (module docstring), or ``{}`` when a side has none."""
    P = np.asarray(rig.neutral, dtype=np.float64)
    lab = mesh_parts(rig.faces, len(P))
    sizes = np.bincount(lab)
    main = int(sizes.argmax())
    Pm = P[lab == main]
    mid = 0.5 * (Pm[:, 0].min() + Pm[:, 0].max())
    size = float(np.sqrt(((Pm - Pm.mean(0)) ** 2).sum(1).mean()))
    found = {}
    for part in np.flatnonzero(sizes >= EYE_MIN_VERTICES):
        sel = np.flatnonzero(lab == part)
        if part == main:
            continue
        centre, radius, resid = sphere_fit(P[sel])
        side = int(np.sign(centre[0] - mid))
        if (side and resid < EYE_SPHERE_TOL * radius and EYE_RADIUS[0] * size < radius < EYE_RADIUS[1] * size
                and (side not in found or len(sel) > len(found[side]))
                and len(rig.deltas) and np.abs(np.asarray(rig.deltas)[:, sel]).max() > 0):
            found[side] = sel
    return found if set(found) == {-1, 1} else {}


def part_turns(neutral, deltas) -> tuple:
    """``(rotation vectors (K, 3), rigid share (K,))`` of each shape's motion ``deltas`` (K, N, 3)
    of a part whose rest positions are ``neutral`` (N, 3): the turn about the part's sphere centre
    closest to it (Kabsch) and the share of its squared motion that turn explains (module
    docstring); zeros for a shape that does not move the part."""
    P = np.asarray(neutral, dtype=np.float64)
    D = np.asarray(deltas, dtype=np.float64)
    c = sphere_fit(P)[0]
    X = P - c
    rot, share = np.zeros((len(D), 3)), np.zeros(len(D))
    for k, d in enumerate(D):
        total = (d ** 2).sum()
        if not total > 0:
            continue
        R = Rotation.align_vectors(X + d, X)[0]
        rot[k] = R.as_rotvec()
        share[k] = max(0.0, 1.0 - ((R.apply(X) - X - d) ** 2).sum() / total)
    return rot, share


def _eye_turns(rig):
    """``{side: (vertices, rotation vectors (K, 3), rigid shares (K,))}`` of :func:`eye_parts` and
    :func:`part_turns`, or None without eye parts or when no shape turns them by :data:`EYE_MIN_TURN`."""
    parts = eye_parts(rig)
    out = {}
    for side, v in parts.items():
        rot, share = part_turns(np.asarray(rig.neutral)[v], np.asarray(rig.deltas)[:, v])
        if np.linalg.norm(rot, axis=1).max() < np.radians(EYE_MIN_TURN):
            return None
        out[side] = (v, rot, share)
    return out or None


def gaze_mapped(source_rig, target_rig) -> bool:
    """Whether :func:`gaze_rows` has rows for this pair (what auto's sentence says)."""
    return _eye_turns(source_rig) is not None and _eye_turns(target_rig) is not None


def gaze_rows(source_rig, target_rig, target_warp=None):
    """``(source (J, E, 3), target (K, E, 3))`` rows for a shape map (module docstring): the target
    eyeballs' E vertices, warped by ``target_warp`` (the calibrate stage's warp into the actor's
    proportions, as the face points; None: as they are), with the target's shapes' displacements
    there and each source shape's mapped turn ``g ρ_j r_j × (p − c)``; None unless both rigs have an
    eye part on each side that some shape turns by :data:`EYE_MIN_TURN` or more."""
    eyes_s, eyes_t = _eye_turns(source_rig), _eye_turns(target_rig)
    if eyes_s is None or eyes_t is None:
        return None
    S, T = [], []
    for side in (1, -1):
        (_, r, share), (vt, q, _) = eyes_s[side], eyes_t[side]
        top_s, top_t = np.linalg.norm(r, axis=1).max(), np.linalg.norm(q, axis=1).max()
        Q = np.asarray(target_rig.neutral, dtype=np.float64)[vt]
        dq = np.asarray(target_rig.deltas, dtype=np.float64)[:, vt]
        if target_warp is not None:
            Q, dq = target_warp(Q), target_warp(Q[None] + dq) - target_warp(Q)[None]
        c = sphere_fit(Q)[0]
        S.append((top_t / top_s) * np.cross((share[:, None] * r)[:, None, :], (Q - c)[None]))
        T.append(dq)
    return np.concatenate(S, 1), np.concatenate(T, 1)
