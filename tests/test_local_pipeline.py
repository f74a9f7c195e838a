"""The local method inside the pipeline: errors come from eq. 3's reconstruction, and local
spacetime keeps the per-frame regional solution at the ends."""

import numpy as np
import pytest

from core.pipeline import Pipeline, StageCache
from core.solvers.local import local_spacetime, reconstruct_markers
from datapaths import PERFORMANCES, RIGS


@pytest.fixture(scope="module")
def pipe():
    return Pipeline(cache=StageCache(), source=str(PERFORMANCES / "livelinkface_take_s07.csv"), source_rig=str(RIGS / "ict_facekit.glb"),
                    target_rig=str(RIGS / "jeeliz_tiger.glb"), method="local", regions=4, last_frame=89)


def test_local_error_is_measured_on_the_mask_blended_reconstruction(pipe):
    r = pipe.results(["stabilize", "personalize", "segment", "solve", "evaluate"])
    U = r["solve"]["info"]["region_weights"]
    P = reconstruct_markers(np.zeros_like(r["stabilize"]["source"].neutral), r["personalize"]["deltas"], U,
                            r["segment"]["marker_masks"])
    S = r["stabilize"]["source"].deltas
    rms = np.sqrt(((P - S) ** 2).sum(-1).mean(1)) * 1e3
    np.testing.assert_allclose(r["evaluate"]["marker_error_mm"], rms, rtol=1e-9)
    assert U.shape == (90, 4, 11) and U.min() >= -1e-12 and U.sum(2).max() <= 1 + 1e-9  # the paper's simplex


def test_local_spacetime_keeps_ends_and_changes_the_middle(pipe):
    r = pipe.results(["stabilize", "personalize", "segment", "solve"])
    U = r["solve"]["info"]["region_weights"]
    st = r["stabilize"]["source"]
    V = local_spacetime(r["personalize"]["deltas"], st.deltas, r["segment"]["marker_weights"], U, alpha=0.01)
    np.testing.assert_allclose(V[[0, -1]], U[[0, -1]], atol=1e-10)
    assert np.abs(V - U).max() > 1e-4
    pipe.configure(local_temporal="spacetime")
    W = pipe.results(["solve"])["solve"]["info"]["region_weights"]
    np.testing.assert_allclose(W, V, atol=1e-10)
    pipe.configure(local_temporal="perframe")
