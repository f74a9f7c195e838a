"""``face-retarget evaluate``'s row per method (core/report.py): the numbers a batch summary also
reports come from ``core.evaluate.summarize`` and mean the same; the rest (fold-overs, errors
against the ground truth) is checked against a direct computation."""

import numpy as np
import pytest

from core.evaluate import ACTIVE
from core.pipeline import Pipeline, StageCache
from core.report import SUMMARY_KEYS, fold_overs, ground_truth, method_metrics
from datapaths import PERFORMANCES, RIGS

FILES = dict(source=str(PERFORMANCES / "livelinkface_take_s07.csv"), source_rig=str(RIGS / "ict_facekit.glb"),
             target_rig=str(RIGS / "rocketbox_female_adult_02.glb"))


@pytest.fixture(scope="module")
def scored():
    pipe = Pipeline(cache=StageCache(), last_frame=59, method="lsq", **FILES)
    base = pipe.results(["load", "frames"])
    truth = ground_truth(base["load"], base["frames"])
    assert truth is not None  # Live Link curves on a rig with ARKit names: the truth exists
    return pipe, truth, method_metrics(pipe, truth)


def test_method_metrics_equal_a_direct_computation(scored):
    pipe, truth, m = scored
    res = pipe.results(["load", "synthesize", "evaluate"])
    syn, ev, rig = res["synthesize"], res["evaluate"], res["load"]["target_rig"]
    W = np.asarray(syn["weights"])
    valid = np.asarray(syn["valid"]) & ev["frame_valid"]
    Wv = W[valid]
    me = ev["marker_error_mm"][valid]
    assert set(SUMMARY_KEYS) <= set(m)
    assert m["frames"] == len(W) and m["frames_without_data"] == int((~valid).sum())
    assert m["marker_mean_mm"] == pytest.approx(np.nanmean(me), rel=1e-12)
    assert m["marker_p95_mm"] == pytest.approx(np.nanpercentile(me, 95), rel=1e-12)
    assert m["velocity_error_mm_per_frame"] == pytest.approx(np.nanmean(ev["velocity_error_mm_per_frame"][valid]), rel=1e-12)
    assert m["jitter"] == pytest.approx(np.nanmean(ev["jitter"]), rel=1e-12)
    assert m["weight_min"] == Wv.min() and m["weight_max"] == Wv.max()
    assert m["active_per_frame"] == pytest.approx((np.abs(Wv) > ACTIVE).sum(1).mean(), rel=1e-12)
    assert "velocity_error" not in m and "vertex_velocity_error_mm_per_frame" in m


def test_velocity_error_is_in_mm_per_frame(scored):
    """The name says the unit: the per-frame RMS per marker of Seol 2012 eq. 2 (whose per-frame
    sum of squares is in mm²), in mm per frame."""
    pipe, _, m = scored
    ev = pipe.results(["evaluate"])["evaluate"]
    M = len(ev["marker_error_per_marker_mm"])
    np.testing.assert_allclose(ev["velocity_error_mm_per_frame"], np.sqrt(ev["velocity_error_mm2"] / M), rtol=1e-12)
    assert ev["velocity_error_total_mm2"] == pytest.approx(np.nansum(ev["velocity_error_mm2"]), rel=1e-9)
    assert 0 < m["velocity_error_mm_per_frame"] < 5  # mm per frame at 60 fps, not mm²


def test_fold_overs_against_np_cross(scored):
    """Mean count of triangles whose normal turns by more than 90° against the neutral's, against
    np.cross on every frame; extreme weights fold many, the neutral none."""
    pipe, _, m = scored
    res = pipe.results(["load", "synthesize", "evaluate"])
    rig = res["load"]["target_rig"]
    F = rig.faces

    def reference(W):
        P = rig.neutral[None] + np.einsum("tk,kvc->tvc", W, rig.deltas)
        n = np.cross(P[:, F[:, 1]] - P[:, F[:, 0]], P[:, F[:, 2]] - P[:, F[:, 0]])
        n0 = np.cross(rig.neutral[F[:, 1]] - rig.neutral[F[:, 0]], rig.neutral[F[:, 2]] - rig.neutral[F[:, 0]])
        return float(((n * n0).sum(-1) < 0).sum(1).mean())

    W = np.random.default_rng(0).uniform(-3, 3, (6, rig.n_shapes))
    assert reference(W) > 10 and fold_overs(rig, W, np.ones(6, bool)) == reference(W)
    assert fold_overs(rig, np.zeros((3, rig.n_shapes)), np.ones(3, bool)) == 0.0
    Wm = np.asarray(res["synthesize"]["weights"])
    valid = np.asarray(res["synthesize"]["valid"]) & res["evaluate"]["frame_valid"]
    assert valid.sum() <= 60  # every valid frame is sampled
    assert m["fold_overs"] == reference(np.nan_to_num(Wm[valid]))


def test_numbers_for_people_are_never_scientific():
    """Issue 32 item 5: the numbers a page or report shows are rounded for people, in plain
    decimals (the batch summary printed 1.235e+04 seconds and the ROM tab 1.2e-05)."""
    from core.report import readable

    cases = {4220.3: "4220", 12345.6: "12346", 0.0981234: "0.0981", 1.2e-5: "0.000012", 0.099999: "0.100",
             -0.5: "-0.500", 3.0: "3.00", 1e-9: "0", 0.0: "0", None: "", float("nan"): "nan"}
    for x, want in cases.items():
        assert readable(x) == want, (x, readable(x))
    for x in np.geomspace(1e-6, 1e7, 200):
        out = readable(x, digits=4)
        assert "e" not in out and abs(float(out) - x) <= max(0.0005 * x, 1e-6), (x, out)
