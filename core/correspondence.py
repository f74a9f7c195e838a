"""Dense correspondence: many face points instead of 41 markers (Xu et al. 2014 §3 carried to
every method).

Forty-one markers cannot tell 50-175 shapes apart: an eye-look, a blink and a squint move the
same few markers. With ``correspondence = "dense"`` the solvers see N surface points instead
(default 1,000), placed and carried like this:

* **a source rig** (weight curves, or a mesh sequence in a rig's topology): the points are the
  farthest-point sample of the source's *face* — the vertices its shapes move (more than 1 % of
  the largest move), on the skin (the connected part that holds most layout markers: no
  eyeballs, teeth, tongue), inside the registration's crop — and each one's place on the target
  is where the rig pair's registration (landmarks + non-rigid ICP + closest point, the one dense
  transfer computes: the ``register`` stage) puts it. Every point is weighted by how well the
  registration fits there: ``w = 1 / (1 + (d / σ)²)`` with ``d`` its distance to the target
  surface after the non-rigid ICP and ``σ`` = 0.5 % of the target's size (1 mm on a 20 cm head).
* **a marker capture** (no source surface): the points are the farthest-point sample of the
  *target's* face, and their motion on the actor is the capture's marker motion interpolated by
  the RBF of the layout (the warp of :mod:`core.calibrate`: kernel ``‖x − c‖`` + linear
  polynomial), evaluated at each point's place in the actor's proportions. The points carry no
  more information than the markers — the interpolation is smooth — but they constrain every
  region of the face the markers span, so the solvers fit the face between the markers too.

The result is an ordinary pair of layouts (names ``d0000``…) with per-point weights, so every
method, the calibration and the segmentation use it unchanged.
"""

from __future__ import annotations

import numpy as np

from .calibrate import RBFWarp
from .geometry import closest_points, face_vertices, farthest_points, vertex_components
from .model import MarkerLayout, Performance, Rig

#: the registration-fit weight's scale, relative to the target's size
SIGMA_FRACTION = 0.005
#: the most points a dense correspondence ranks
MAX_POINTS = 20000


def skin(faces, n_vertices: int, anchors) -> np.ndarray:
    """(V,) bool: the connected part of the mesh that holds most of ``anchors`` (vertex ids,
    e.g. the layout's markers) — the skin, not the eyeballs, teeth or tongue."""
    _, labels = vertex_components(faces, n_vertices)
    best = np.bincount(labels[np.asarray(anchors, dtype=np.int64)]).argmax()
    return labels == best


def _names(n: int) -> list:
    return [f"d{i:04d}" for i in range(n)]


def rig_correspondence(source_rig: Rig, source_layout: MarkerLayout, welded, registration, target_rig: Rig,
                       n_points: int = 1000):
    """Dense layouts on both rigs from the rig pair's registration (see the module docstring).

    Parameters
    ----------
    source_rig, source_layout : the source rig and its marker layout (its markers find the skin)
    welded : core.transfer.WeldedSource of the source rig (the registration's vertex order)
    registration : core.transfer.correspond.Registration, or None for a same-topology pair
    target_rig : the target rig
    n_points : N

    Returns
    -------
    source layout, target layout (both N points, names ``d0000``...), weights (N,) in (0, 1]
    """
    V = source_rig.n_vertices
    cand = face_vertices(source_rig.deltas) & skin(source_rig.faces, V, source_layout.vertices.ravel())
    if registration is not None:
        w = welded.index
        cand &= registration.projected[w]
        if registration.crop is not None:
            cand &= registration.crop[w]
        on_target = registration.resampled[w]  # each source vertex's place on the target surface
        dist = registration.distance[w]
    else:  # same topology: the identity
        on_target, dist = target_rig.neutral, np.zeros(V)
    ids = np.flatnonzero(cand)
    if len(ids) < 4:
        raise ValueError(f"dense correspondence: only {len(ids)} source face vertices register onto {target_rig.name!r}")
    n = min(int(n_points), len(ids))
    P = source_rig.neutral[ids]
    start = int(np.argmax(P[:, 2]))  # the nose tip: the sample is the same on every run
    pick = ids[_farthest(P, n, start)]
    names = _names(n)
    src = MarkerLayout.from_vertices(names, pick, rig=source_rig.name, extras={"correspondence": "dense"})
    _, _, tri, bary = closest_points(on_target[pick], target_rig.neutral, target_rig.faces)
    tgt = MarkerLayout(names, target_rig.faces[tri], bary, rig=target_rig.name, extras={"correspondence": "dense"})
    sigma = SIGMA_FRACTION * target_rig.size
    return src, tgt, 1.0 / (1.0 + (dist[pick] / sigma) ** 2)


def _farthest(P, n, start):
    return farthest_points(P, n, start=start)


def capture_correspondence(source, target_rig: Rig, target_layout: MarkerLayout, n_points: int = 1000):
    """Dense virtual markers for a marker capture (see the module docstring).

    Parameters
    ----------
    source : Performance of kind markers (T, M, 3), its names matched to ``target_layout``'s
    target_rig, target_layout : the target and its marker layout
    n_points : N

    Returns
    -------
    a new markers Performance (T, N, 3) — the capture's marker motion interpolated at the points,
    missing where the frame misses a marker — and the target layout of the N points; the points'
    weights are all 1 (the interpolation is exact at the markers).
    """

    common = [n for n in target_layout.names if n in set(source.names)]
    if len(common) < 4:
        raise ValueError(f"dense correspondence: the capture shares only {len(common)} markers with the target layout")
    lay = target_layout.select(common)
    idx = [source.names.index(n) for n in common]
    X = np.asarray(source.data[:, idx], dtype=np.float64)  # (T, m, 3)
    ok = np.asarray(source.valid[:, idx]).all(1)
    if not ok.any():
        raise ValueError("dense correspondence: no frame of the capture has every shared marker")
    # the reference the points are placed at: the take's first complete frame (stabilisation later
    # measures every frame against its own neutral frame, so the choice does not matter beyond that)
    f0 = int(np.flatnonzero(ok)[0])
    cand = np.flatnonzero(face_vertices(target_rig.deltas) & skin(target_rig.faces, target_rig.n_vertices, lay.vertices.ravel()))
    n = min(int(n_points), len(cand))
    P = target_rig.neutral[cand]
    pick = cand[_farthest(P, n, int(np.argmax(P[:, 2])))]
    names = _names(n)
    tgt = MarkerLayout.from_vertices(names, pick, rig=target_rig.name, extras={"correspondence": "dense"})
    # the points' places in the actor's proportions: the target -> actor warp of the neutral markers
    to_actor = RBFWarp().fit(lay.points(target_rig.neutral), X[f0])
    rest = to_actor(target_rig.neutral[pick])
    # the capture's motion at those places: the RBF of each frame's marker displacements, with one
    # factorisation for all frames (the centres, the actor's neutral markers, do not move)
    disp = RBFWarp().fit(X[f0], np.where(ok[:, None, None], X - X[f0], 0.0).transpose(1, 0, 2).reshape(len(common), -1))
    D = disp(rest).reshape(n, len(X), 3).transpose(1, 0, 2)
    data = rest[None] + D
    valid = np.repeat(ok[:, None], n, axis=1)
    data[~valid] = np.nan
    return (Performance("markers", data, tuple(names), source.fps, valid, source.times, source.units, source.name,
                        dict(source.extras, correspondence="dense")), tgt)
