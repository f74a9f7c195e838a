"""Paths of the bundled data for tests (a uniquely named module: ``conftest`` is ambiguous
because tests/browser has its own)."""

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "data"
RIGS = DATA / "rigs"
PERFORMANCES = DATA / "performances"
LAYOUTS = DATA / "layouts"


def face_markers(rig, M=60):
    """Well-spread front-of-face vertices of the ICT rig (farthest-point sampling from the
    nose tip): virtual marker positions for tests that need more or other markers than the
    bundled layout."""
    import numpy as np

    from core.geometry import farthest_points, vertex_normals

    V = rig.neutral
    n = vertex_normals(V, rig.faces)
    cand = np.flatnonzero((V[:, 2] > 0.07) & (n[:, 2] > 0.4) & (V[:, 1] > -0.085) & (V[:, 1] < 0.09))
    P = V[cand]
    return cand[farthest_points(P, M, start=int(np.argmax(P[:, 2])))]
