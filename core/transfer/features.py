"""Facial feature lines around the eyes and mouth (Xu et al. 2014 §3, Fig. 2d; used by eq. 11).

A feature line is an ordered chain of vertex ids (closed when it is a loop); eq. 11 uses its
edges. Sources of lines on a real rig:

* hole rims: :func:`core.geometry.boundary_loops` of the mesh, minus the outer rim;
* UV-seam rims: rigs like ICT-FaceKit split vertices where the face skin meets the mouth
  and eye-socket parts, so after welding the lip and eyelid rims are interior loops;
  :func:`seam_loops` finds them from the un-welded faces;
* markers: :func:`marker_loop` joins marker vertices (e.g. the four eye markers of a layout)
  by shortest edge paths.

:func:`loops_near` keeps the loops that pass near given points (layout markers).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

from ..geometry import boundary_loops, edges as mesh_edges, weld_vertices

__all__ = ["line_edges", "hole_loops", "seam_loops", "loops_near", "marker_loop", "feature_lines_near"]


def line_edges(lines, closed: bool = True) -> np.ndarray:
    """(E, 2) edges of feature lines given as a list of vertex-id chains; duplicates removed."""
    out = []
    for ln in lines:
        ln = np.asarray(ln, dtype=np.int64).ravel()
        if len(ln) < 2:
            continue
        nxt = np.roll(ln, -1) if closed and len(ln) > 2 else ln[1:]
        cur = ln if closed and len(ln) > 2 else ln[:-1]
        out.append(np.stack([cur, nxt], axis=1))
    if not out:
        return np.zeros((0, 2), np.int64)
    e = np.concatenate(out)
    e = e[e[:, 0] != e[:, 1]]
    key = np.sort(e, axis=1)
    _, idx = np.unique(key, axis=0, return_index=True)
    return e[np.sort(idx)]


def hole_loops(faces) -> list:
    """Boundary loops of ``faces`` except the longest (the outer rim / neck cut)."""
    return boundary_loops(faces)[1:]


def seam_loops(faces_unwelded, welded_index, welded_faces) -> list:
    """Rims of the un-welded mesh that are interior (not boundary) after welding.

    Parameters
    ----------
    faces_unwelded : (F, 3) int, faces on the original (split) vertices
    welded_index : (V,) int, welded id of every original vertex
    welded_faces : (F', 3) int

    Returns
    -------
    list of (m,) int arrays of *welded* ids, one per distinct seam loop.
    """
    welded_index = np.asarray(welded_index)
    wb = boundary_loops(welded_faces)
    on_boundary = set(np.concatenate(wb).tolist()) if wb else set()
    seen = set()
    out = []
    for loop in boundary_loops(faces_unwelded):
        w = welded_index[loop]
        # drop consecutive repeats (a seam corner collapsing)
        w = w[np.r_[True, w[1:] != w[:-1]]]
        if len(w) < 3 or any(int(v) in on_boundary for v in w):
            continue
        key = frozenset(w.tolist())
        if key in seen:
            continue
        seen.add(key)
        out.append(w)
    return out


def loops_near(loops, positions, points, radius: float) -> list:
    """Loops with at least one vertex within ``radius`` of one of ``points`` (M, 3)."""
    p = np.asarray(positions, dtype=np.float64)
    q = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    keep = []
    for ln in loops:
        d = np.linalg.norm(p[ln][:, None, :] - q[None, :, :], axis=-1)
        if d.min() <= radius:
            keep.append(ln)
    return keep


def marker_loop(positions, faces, vertices, closed: bool = True) -> np.ndarray:
    """Chain marker vertices by shortest edge paths (Dijkstra on edge lengths).

    Parameters
    ----------
    positions : (V, 3)
    faces : (F, 3) int
    vertices : (m,) int, the markers in order around the feature
    closed : bool, join the last marker back to the first

    Returns
    -------
    (n,) int, the vertex chain (first vertex not repeated when closed).
    """
    p = np.asarray(positions, dtype=np.float64)
    e = mesh_edges(faces)
    w = np.linalg.norm(p[e[:, 0]] - p[e[:, 1]], axis=1)
    n = len(p)
    G = sp.csr_matrix((np.r_[w, w], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n))
    vs = [int(v) for v in vertices]
    stops = vs + ([vs[0]] if closed else [])
    chain = [stops[0]]
    for a, b in zip(stops[:-1], stops[1:]):
        _, pred = dijkstra(G, indices=a, return_predecessors=True)
        path = [b]
        while path[-1] != a:
            nxt = pred[path[-1]]
            if nxt < 0:
                raise ValueError(f"vertices: no edge path from {a} to {b}")
            path.append(int(nxt))
        chain.extend(path[::-1][1:])
    if closed:
        chain = chain[:-1]
    return np.asarray(chain, dtype=np.int64)


def feature_lines_near(positions, faces, points, radius: float) -> list:
    """Eye and mouth lines of a rig: hole rims and UV-seam rims passing within ``radius`` of
    one of ``points`` (e.g. a layout's eye and mouth markers).

    Parameters
    ----------
    positions : (V, 3), faces : (F, 3) int  -- the rig as stored (seams split)
    points : (M, 3)
    radius : float, metres

    Returns
    -------
    list of (m,) int arrays of *input* vertex ids (one representative per welded vertex), the
    form ``TransferSettings.feature_lines`` takes.
    """

    p = np.asarray(positions, dtype=np.float64)
    wi, rep, wf = weld_vertices(p, faces)
    loops = seam_loops(faces, wi, wf) + hole_loops(wf)
    return [rep[ln] for ln in loops_near(loops, p[rep], points, radius)]
