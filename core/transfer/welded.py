"""The source reference welded at UV seams: every step of the dense transfer (Xu 2014) and its
editors work on one connected surface."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import weld_vertices
from ._mesh import check_faces, check_positions


@dataclass(frozen=True, eq=False)
class WeldedSource:
    """The source reference welded at UV-seam duplicates: Laplacians and gradients must see one
    connected surface. ``index`` (V,) maps every source vertex to its welded vertex, ``rep``
    (V_w,) each welded vertex to one source vertex; ``faces`` (F, 3) are the welded triangles."""

    neutral: np.ndarray
    source_faces: np.ndarray
    index: np.ndarray
    rep: np.ndarray
    faces: np.ndarray

    @property
    def n(self) -> int:
        return len(self.rep)

    @property
    def welded_neutral(self) -> np.ndarray:
        """(V_w, 3) the source reference's welded positions."""
        return self.neutral[self.rep]

    def unweld(self, a: np.ndarray) -> np.ndarray:
        """Welded (..., V_w, 3) -> source vertex order (..., V, 3)."""
        return np.ascontiguousarray(a[..., self.index, :])


def weld_source(source_ref, source_faces) -> WeldedSource:
    """Check and weld the source reference (see :class:`WeldedSource`)."""
    S0 = check_positions(source_ref, "source_ref")
    Fs = check_faces(source_faces, len(S0), "source_faces")
    wi, rep, Fw = weld_vertices(S0, Fs)
    return WeldedSource(S0, Fs, wi, rep, Fw)
