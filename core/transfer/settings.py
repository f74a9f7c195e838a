"""The settings of Xu et al. 2014's dense transfer (:func:`core.transfer.transfer_sequence`), in
a module of their own: the editors (:mod:`.edit`, :mod:`.detail_edit`) take them too."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence, Union

import numpy as np


@dataclass(frozen=True)
class TransferSettings:
    """Settings of :func:`transfer_sequence` (defaults follow the paper where it gives a value).

    Attributes
    ----------
    iterations : Taubin iterations ("about 40", §3)
    lam, mu : Taubin λ, μ
    laplacian : "uniform" | "cotangent", the operator L of eq. 1-2
    eps : relative residual energy that ends basis selection (eq. 7's ε)
    max_bases, min_bases : bounds on K (deltas, not counting the neutral b_1 = S̄_0)
    candidates : frames tried per greedy step (the worst-fitted ones)
    alpha : feature-line weight of eq. 9 (100 in the paper)
    feature_lines : list of vertex-id chains on the source (closed loops), or None
    details : transfer fine-scale details (§5.1); False gives the large-scale result only
    detail_gain : scale of the transferred coating; None = size(target) / size(source)
    rotate_reference_details : the rotation-covariant detail variant (see :mod:`.details`)
    detail_screening : screened-Poisson weight of the detail reconstruction (0 = eq. 5 as is;
        see :class:`.decompose.PoissonReconstructor`)
    rank_rtol : relative RMS tolerance of the sequence factorisation
    chunk : frames per block in the detail stage
    landmarks : (source vertex ids (M,), target points (M, 3)) for a target with its own topology
    icp_steps, max_distance, icp : registration settings (see :func:`.correspond.register`);
        ``icp=False`` stops at the landmark similarity + closest-point resampling
    crop : which source vertices the registration fits to the target (:func:`.correspond.register`):
        "auto" (default: the face crop when the target lacks the rest of the source head, as the
        Jeeliz animals do; the whole head for a human target), "face", "none", or a (V,) bool
        mask / vertex ids of ``source_ref``
    """

    iterations: int = 40
    lam: float = 0.5
    mu: float = -0.53
    laplacian: str = "uniform"
    eps: float = 1e-3
    max_bases: int = 30
    min_bases: int = 0
    candidates: int = 8
    alpha: float = 100.0
    feature_lines: Optional[Sequence] = None
    details: bool = True
    detail_gain: Optional[float] = None
    rotate_reference_details: bool = False
    detail_screening: float = 0.01
    rank_rtol: float = 1e-6
    chunk: int = 32
    landmarks: Optional[tuple] = None
    icp_steps: Optional[list] = None
    max_distance: Optional[float] = None
    icp: bool = True
    crop: Union[str, None, np.ndarray, Sequence[int]] = "auto"

    def __post_init__(self):
        if self.laplacian not in ("uniform", "cotangent"):
            raise ValueError(f"laplacian: expected 'uniform' or 'cotangent', got {self.laplacian!r}")
        for name in ("iterations", "max_bases", "min_bases", "candidates", "chunk"):
            v = getattr(self, name)
            if int(v) != v or v < (1 if name in ("candidates", "chunk") else 0):
                raise ValueError(f"{name}: expected a non-negative integer, got {v!r}")
        if self.eps < 0 or self.alpha < 0 or self.rank_rtol <= 0:
            raise ValueError(f"eps >= 0, alpha >= 0, rank_rtol > 0 expected; got {self.eps}, {self.alpha}, {self.rank_rtol}")
        if isinstance(self.crop, str) and self.crop not in ("auto", "face", "none"):
            raise ValueError(f"crop: expected 'auto', 'face', 'none', a bool mask or vertex ids; got {self.crop!r}")
