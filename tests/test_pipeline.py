"""The stage pipeline: exactly the stale stages re-run; reverting is a cache hit; results
are read-only; CLI flags and widgets come from one definition."""

import numpy as np
import pytest

from core.pipeline import Pipeline, StageCache, add_cli_arguments, cli_flags, content_key
from datapaths import PERFORMANCES, RIGS

FILES = dict(source=str(PERFORMANCES / "livelinkface_take_s07.csv"), source_rig=str(RIGS / "ict_facekit.glb"),
             target_rig=str(RIGS / "rocketbox_female_adult_02.glb"))


@pytest.fixture
def pipe():
    return Pipeline(cache=StageCache(), first_frame=0, last_frame=119, method="lsq", **FILES)


def test_first_run_runs_every_active_stage_once(pipe):
    pipe.run()
    assert pipe.runs["load"] == pipe.runs["calibrate"] == pipe.runs["solve"] == pipe.runs["evaluate"] == 1
    assert pipe.runs["segment"] == 0  # inactive unless the method is local
    pipe.run()
    assert pipe.runs["solve"] == 1  # nothing stale: all hits


def test_solver_setting_reruns_solve_and_below_only(pipe):
    pipe.configure(method="bounded")
    pipe.run()
    before = dict(pipe.runs)
    pipe.configure(upper=0.8)
    pipe.run()
    ran = {k for k in pipe.runs if pipe.runs[k] != before.get(k, 0)}
    assert ran == {"solve", "edit", "synthesize", "evaluate"}
    W = pipe.results(["solve"])["solve"]["weights"]
    assert W.max() <= 0.8 + 1e-9
    # reverting is a cache hit: no stage runs
    pipe.configure(upper=1.0)
    snapshot = dict(pipe.runs)
    pipe.run()
    assert dict(pipe.runs) == snapshot


def test_irrelevant_settings_are_cache_hits(pipe):
    pipe.run()
    snapshot = dict(pipe.runs)
    pipe.configure(alpha=0.5, mu=1.0, regions=3)  # not used by lsq
    pipe.run()
    assert dict(pipe.runs) == snapshot


def test_upstream_setting_invalidates_downstream(pipe):
    pipe.run()
    pipe.configure(rbf_smoothing=0.01)
    pipe.run()
    assert pipe.runs["load"] == 1 and pipe.runs["stabilize"] == 1
    assert pipe.runs["calibrate"] == 2 and pipe.runs["solve"] == 2


def test_cached_results_are_read_only(pipe):
    W = pipe.results(["solve"])["solve"]["weights"]
    with pytest.raises(ValueError):
        W[0, 0] = 1.0


def test_shared_cache_between_sessions(pipe):
    pipe.run()
    other = Pipeline(cache=pipe.cache, first_frame=0, last_frame=119, method="lsq", **FILES)
    other.run()
    assert sum(other.runs.values()) == 0


def test_unknown_setting_suggests():
    with pytest.raises(KeyError, match="alpha"):
        Pipeline(alpah=1)


def test_content_key_hashes_whole_arrays():
    a = np.zeros((52, 5000, 3))
    k0 = content_key(a)
    a[17, 4321, 2] = 1e-12  # a one-element change pandas-style samplers miss
    assert content_key(a) != k0


def test_cli_flags_come_from_settings():
    import argparse

    flags = {f for f, *_ in cli_flags()}
    assert {"--alpha", "--beta", "--regions", "--mu", "--lam", "--method", "--source", "--target-rig"} <= flags
    p = argparse.ArgumentParser()
    add_cli_arguments(p)
    ns = p.parse_args(["--alpha", "0.02", "--regions", "6", "--no-calibrate"])
    assert ns.alpha == 0.02 and ns.regions == 6 and ns.calibrate is False
    with pytest.raises(SystemExit):
        p.parse_args(["--method", "magic"])


def test_target_shape_subset_and_unseen_shapes_stay_zero():
    from core.names import ARKIT_NAMES, canonical

    pipe = Pipeline(cache=StageCache(), last_frame=299, method="spacetime", target_shapes="arkit", **FILES)
    with pytest.warns(UserWarning, match="move no marker"):
        res = pipe.results(["calibrate", "synthesize"])
    names = pipe.results(["load"])["load"]["target_rig"].names
    W = res["synthesize"]["weights"]
    assert W.shape == (300, 175)
    non_arkit = [i for i, n in enumerate(names) if canonical(n) not in ARKIT_NAMES]
    assert np.all(W[:, non_arkit] == 0)
    assert res["calibrate"]["unseen"] == ["AK_52_TongueOut"]
    assert np.all(W[:, names.index("AK_52_TongueOut")] == 0)
    # the relative ridge keeps nearly invisible combinations (eye wide/look up/blink) in range
    assert np.abs(W).max() < 2
    pipe.configure(ridge=0.0)
    assert np.abs(pipe.results(["synthesize"])["synthesize"]["weights"]).max() > np.abs(W).max()


@pytest.mark.parametrize("method", ["lsq", "bounded", "range_pf", "prior_pf", "spacetime", "local", "geometric"])
def test_every_method_runs_through_every_stage(method):
    """Each stage reads only what its declared dependencies give it (a missing dependency is a
    KeyError here), and every method yields finite weights for all target shapes."""
    pipe = Pipeline(cache=StageCache(), source=FILES["source"], source_rig=FILES["source_rig"],
                    target_rig=str(RIGS / "jeeliz_tiger.glb"), method=method, last_frame=59, regions=3,
                    edits=[{"frame": 30, "weights": {"mouthOpen": 0.5}, "window": [20, 40]}])
    res = pipe.results()
    W = res["synthesize"]["weights"]
    assert W.shape == (60, 11) and np.isfinite(W).all()
    assert abs(W[30, pipe.results(["load"])["load"]["target_rig"].names.index("mouthOpen")] - 0.5) < 1e-9
    assert np.isfinite(res["evaluate"]["marker_error_mm"]).all()


# -- exact invalidation: one test per case of the "one shot, one pipeline" issue ------------------
def _ran(pipe, before):
    return {k for k in pipe.runs if pipe.runs[k] != before.get(k, 0)}


def test_an_edited_default_layout_file_changes_the_result(tmp_path):
    """A rig's default layout (here its sidecar <rig>.layout.json) is an input: editing it
    re-keys the target rig and everything below, and changes the weights."""
    import json
    import shutil

    rig = tmp_path / "my_tiger.glb"
    shutil.copy(RIGS / "jeeliz_tiger.glb", rig)
    layout = json.loads((RIGS.parent / "layouts" / "jeeliz_tiger.json").read_text())
    layout["rig"] = rig.name
    side = tmp_path / "my_tiger.layout.json"
    side.write_text(json.dumps(layout))
    pipe = Pipeline(cache=StageCache(), source=FILES["source"], source_rig=FILES["source_rig"], target_rig=str(rig),
                    method="lsq", last_frame=59)
    pipe.run()
    W0 = pipe.results(["synthesize"])["synthesize"]["weights"].copy()
    before = dict(pipe.runs)
    pipe.run()
    assert _ran(pipe, before) == set()  # nothing changed: all hits
    # move the mouth-corner marker to a neighbouring vertex
    layout["markers"]["Mouth_Lend"] = {"vertex": int(layout["markers"]["Mouth_Lend"]["vertex"]) + 1}
    side.write_text(json.dumps(layout))
    pipe.run()
    assert {"target_face", "load", "shapes", "stabilize", "calibrate", "solve"} <= _ran(pipe, before)
    assert "take" not in _ran(pipe, before) and "source_face" not in _ran(pipe, before)
    assert not np.array_equal(pipe.results(["synthesize"])["synthesize"]["weights"], W0)


def test_frame_range_does_not_resegment(pipe):
    pipe.configure(method="local", regions=4)
    pipe.run()
    before = dict(pipe.runs)
    pipe.configure(first_frame=10, last_frame=99)
    pipe.run()
    ran = _ran(pipe, before)
    assert "segment" not in ran and "shapes" not in ran and "load" not in ran
    assert {"frames", "stabilize", "calibrate", "solve", "evaluate"} <= ran


@pytest.mark.parametrize("switch,off_setting,value", [
    ({"personalize": False}, "align_beta", 0.5),
    ({"personalize": False}, "rom", str(PERFORMANCES / "livelinkface_rom.csv")),
    ({"calibrate": False}, "rbf_smoothing", 0.05),
])
def test_settings_of_a_disabled_stage_rerun_nothing(pipe, switch, off_setting, value):
    pipe.configure(**switch)
    pipe.run()
    before = dict(pipe.runs)
    pipe.configure(**{off_setting: value})
    pipe.run()
    assert _ran(pipe, before) == set()


def test_prior_shapes_builds_the_subset_prior_of_seol_fig13(pipe):
    """prior_shapes is in the prior's key and used: a prior of the mouth shapes only changes
    the spacetime result (Seol 2012 Fig. 13 b)."""
    pipe.configure(method="spacetime", target_shapes="arkit")
    W_all = pipe.results(["solve"])["solve"]["weights"].copy()
    before = dict(pipe.runs)
    names = pipe.results(["shapes"])["shapes"]["rig"].names
    mouth = [n for n in names if "Mouth" in n or "Jaw" in n]
    pipe.configure(prior_shapes=",".join(mouth))
    res = pipe.results(["prior", "solve"])
    assert _ran(pipe, before) >= {"prior", "solve"} and "personalize" not in _ran(pipe, before)
    assert len(res["prior"]["subset"]) == len(mouth) and res["prior"]["prior"].n_samples_ == len(mouth)
    assert not np.allclose(res["solve"]["weights"], W_all)
    with pytest.raises(KeyError, match="NoSuchShape"):
        pipe.configure(prior_shapes="NoSuchShape")
        pipe.results(["prior"])


def test_results_survive_an_evicting_cache():
    """results() returns what it computed even when the LRU is too small to keep it."""
    pipe = Pipeline(cache=StageCache(max_entries=2), last_frame=29, method="lsq", **FILES)
    res = pipe.results(["load", "stabilize", "solve", "synthesize"])
    assert all(res[k] is not None for k in res)
    assert res["synthesize"]["weights"].shape == (30, 175)


def test_a_run_reads_one_snapshot_of_the_settings(pipe):
    """A setting changed while a stage runs belongs to the next run (the key and the run read
    the same snapshot)."""
    seen = {}
    solve = pipe.stages["solve"]
    original = type(solve).run

    def spy(self, inputs, s, progress=None, **hint):
        pipe.configure(upper=0.5)  # a widget moved during the solve
        seen["upper"] = s.upper
        return original(self, inputs, s, progress, **hint)

    pipe.configure(method="bounded", upper=0.9)
    type(solve).run = spy
    try:
        W = pipe.results(["solve"])["solve"]["weights"]
    finally:
        type(solve).run = original
    assert seen["upper"] == 0.9 and W.max() <= 0.9 + 1e-9
    assert pipe.solve.upper == 0.5
    assert pipe.results(["solve"])["solve"]["weights"].max() <= 0.5 + 1e-9


def test_method_registry_is_the_one_source_of_method_knowledge():
    from core.pipeline import METHOD_PARAMS, METHODS
    from core.stages import PRIOR_METHODS
    from core.stages.methods import METHODS as REGISTRY

    assert METHODS == tuple(REGISTRY) and list(Pipeline().solve.param.method.objects) == list(REGISTRY)
    assert METHOD_PARAMS["spacetime"] == REGISTRY["spacetime"].params
    assert set(PRIOR_METHODS) == {n for n, m in REGISTRY.items() if "prior" in m.needs}
    pipe = Pipeline(method="local")
    assert pipe.segment.active(pipe.config()) and not pipe.prior.active(pipe.config())


def test_an_edit_stays_inside_the_methods_bounds_and_its_window():
    """The issue's own case: "Set pose at this frame" with AK_25_JawOpen = 1.39 at frame 437
    (half-window 12) on the bounded result turned 0..1 into -29.2..75.5; now the edit is solved
    under the method's bounds and regularisers: every weight stays in [0, 1] and the other
    shapes change only inside the window."""
    pipe = Pipeline(cache=StageCache(), method="bounded", last_frame=599, target_shapes="arkit", **FILES)
    before = pipe.results(["synthesize"])["synthesize"]["weights"].copy()
    names = pipe.results(["load"])["load"]["target_rig"].names
    jaw = names.index("AK_25_JawOpen")
    with pytest.warns(UserWarning, match="clipped"):
        pipe.add_edit("spacetime", {"frame": 437, "weights": {"AK_25_JawOpen": 1.39}, "window": [425, 449]})
        after = pipe.results(["synthesize"])["synthesize"]["weights"]
    assert after.min() >= -1e-9 and after.max() <= 1 + 1e-9
    outside = np.r_[0:425, 450:600]
    np.testing.assert_array_equal(after[outside], before[outside])
    assert after[437, jaw] == pytest.approx(1.0)  # the pose, clipped to the shape's bound
    for method in ("spacetime", "local"):
        pipe.configure(method=method)
        W = pipe.results(["synthesize"])["synthesize"]["weights"]
        assert W.min() >= -1e-9 and W.max() <= 1 + 1e-9, method


def test_a_pose_edit_propagates_over_its_window_without_popping():
    """Issue 33 item 2, the issue's own case: jawOpen = 1 at frame 419, half-window 12, spacetime.
    It popped (0.12 -> 1.00 -> 0.11 at 418-420, other mouth shapes dropping at 419 to cancel it).
    Seol 2012 §6: the change propagates smoothly and the window's ends stay continuous. Every
    curve's step from frame to frame, inside the window, at its ends and around the edit, stays
    within the edit's change spread over the half-window (twice that at most, a tent's slope is
    once) plus the curves' own 99.9th-percentile step; the frame's other weights keep their values."""
    pipe = Pipeline(cache=StageCache(), method="spacetime", last_frame=599, **FILES)
    before = pipe.results(["edit"])["edit"]["weights"].copy()
    names = pipe.results(["shapes"])["shapes"]["rig"].names
    jaw = names.index("AK_25_JawOpen")
    pipe.add_edit("spacetime", {"frame": 419, "weights": {"AK_25_JawOpen": 1.0}, "window": [407, 431]})
    after = pipe.results(["edit"])["edit"]["weights"]
    assert after[419, jaw] == pytest.approx(1.0)
    others = np.arange(len(names)) != jaw
    np.testing.assert_allclose(after[419, others], before[419, others], atol=1e-9)
    outside = np.r_[0:407, 432:600]
    np.testing.assert_array_equal(after[outside], before[outside])
    normal = np.percentile(np.abs(np.diff(before, axis=0)), 99.9)
    slope = (1.0 - before[419, jaw]) / 12
    step = np.abs(np.diff(after, axis=0)).max(axis=1)  # step[t]: frame t -> t + 1, the largest over the curves
    assert step[405:432].max() <= 2 * slope + normal, (step[405:432].round(3), slope, normal)
    assert step[[406, 407, 430, 431]].max() <= slope + normal, (step[[406, 407, 430, 431]], slope, normal)
    assert step[417:421].max() <= 2 * slope + normal  # around the edit: no pop


def test_cache_shares_work_in_flight():
    """Two pipelines asking for one key at once compute it once; when the computing thread fails,
    the waiting one computes it itself (and a later call is a hit)."""
    import threading
    import time as _time

    from core.pipeline import StageCache

    cache, calls, out = StageCache(), [], []

    def slow():
        calls.append(1)
        _time.sleep(0.3)
        return 42

    ts = [threading.Thread(target=lambda: out.append(cache.compute("k", slow))) for _ in range(4)]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    assert len(calls) == 1 and sorted(out) == [(False, 42)] + [(True, 42)] * 3

    def fails():
        _time.sleep(0.2)
        raise RuntimeError("boom")

    res = []
    t = threading.Thread(target=lambda: res.append(pytest.raises(RuntimeError, cache.compute, "j", fails)))
    t.start()
    _time.sleep(0.05)
    assert cache.compute("j", lambda: 7) == (False, 7)  # waited for the failure, then computed
    t.join()
    assert cache.compute("j", lambda: 8) == (True, 7)


def test_lowest_and_highest_weight_share_one_scale():
    """Issue 33.7: the Lowest/Highest weight sliders ran over -1..0 and 1..2, so the lowest (0)
    sat at its right end and the highest (1) at its left: they looked swapped. One scale now,
    on which the lowest's default is left of the highest's."""
    p = Pipeline().solve.param
    assert p.lower.softbounds == p.upper.softbounds
    lo, hi = p.lower.softbounds
    assert lo < p.lower.default < p.upper.default < hi


def test_alpha_change_reuses_the_data_gram_and_gives_a_fresh_pipelines_result(pipe):
    """prior_pf's products with the whole take (the ``gram`` stage) depend on the take and the rig,
    not on alpha: a change of alpha re-solves without them, to the numbers a fresh pipeline gives."""
    pipe.configure(method="prior_pf", ridge=1e-3)
    pipe.run()
    before = dict(pipe.runs)
    pipe.configure(alpha=0.2)
    W = pipe.results(["solve"])["solve"]["weights"]
    assert "gram" not in _ran(pipe, before) and "solve" in _ran(pipe, before)
    fresh = Pipeline(cache=StageCache(disk=False), first_frame=0, last_frame=119, method="prior_pf", ridge=1e-3,
                     alpha=0.2, **FILES)
    assert np.array_equal(W, fresh.results(["solve"])["solve"]["weights"])


def test_a_spacetime_alpha_change_reuses_the_motion_gram_and_gives_a_fresh_pipelines_result():
    """The spacetime solver's products with the take (the ``motion_gram`` stage) depend on the take
    and the rig, not on alpha or the bounds: a change re-solves without them (dense correspondence
    too), to the numbers a fresh pipeline gives (the disk cache keeps only the rig pair's
    registration, as in every dense test)."""
    for extra in ({}, {"correspondence": "dense", "dense_points": 200}):
        kw = dict(first_frame=0, last_frame=59, method="spacetime", **extra, **FILES)
        pipe = Pipeline(cache=StageCache(), **kw)
        pipe.run()
        before = dict(pipe.runs)
        pipe.configure(alpha=0.05, upper=0.9)
        W = pipe.results(["solve"])["solve"]["weights"]
        assert "motion_gram" not in _ran(pipe, before) and "solve" in _ran(pipe, before)
        fresh = Pipeline(cache=StageCache(), alpha=0.05, upper=0.9, **kw)
        np.testing.assert_allclose(W, fresh.results(["solve"])["solve"]["weights"], rtol=0, atol=1e-9)


def test_spacetime_end_frames_from_the_motion_gram_are_the_direct_prior_pf():
    """boundary = perframe: the end frames' prior_pf at every alpha is made from the motion_gram
    stage's products (B^T Gamma B, (Gamma S_t) B, the largest eigenvalue of B^T Gamma B for the
    relative ridge), not from the weighted marker rows and their SVD: the same ends, with marker
    weights (dense correspondence) and without."""
    from core.stage import SettingsView
    from core.stages import methods

    for extra in ({}, {"correspondence": "dense", "dense_points": 200}):
        pipe = Pipeline(cache=StageCache(), first_frame=0, last_frame=59, method="spacetime", boundary="perframe",
                        **extra, **FILES)
        inputs = pipe.results(list(pipe.solve.reads(pipe.config())))
        assert (methods._marker_weights(inputs) is not None) == bool(extra)
        T = len(methods._markers(inputs)[1])
        assert methods._frames_gram(inputs, [0, T - 1]) is not None
        # (the default ridge and more: without one, B^T Gamma B + alpha P of 165 shapes seen by 41
        # markers is singular to working precision (condition 1e19) and any two ways of rounding it
        # give other ends)
        for ridge in (1e-3, 1e-2):
            s = SettingsView("solve", {"alpha": 0.1, "ridge": ridge, "quadratic": None, "zero": None})
            ends = methods._prior_pf_frames(inputs, s, [0, T - 1])
            direct = methods._prior_pf_frames({k: v for k, v in inputs.items() if k != "motion_gram"}, s, [0, T - 1])
            assert np.abs(direct).max() > 1e-3  # the ends move: the comparison is not of zeros
            np.testing.assert_allclose(ends, direct, rtol=0, atol=1e-10 * np.abs(direct).max())


def test_a_spacetime_change_starts_from_the_last_result_and_gives_a_fresh_pipelines_numbers(monkeypatch):
    """The solve stage's warm start (its last result) is a hint: in no key, and the result is the
    one a fresh pipeline computes cold (issue 30 item 3)."""
    import core.solvers.spacetime as st

    runs = []

    def spy(*args, **kw):
        W, info = solve_bounded(*args, **kw)
        runs.append(info)
        return W, info

    solve_bounded = st.solve_bounded
    monkeypatch.setattr(st, "solve_bounded", spy)
    kw = dict(first_frame=0, last_frame=119, method="spacetime", **FILES)
    pipe = Pipeline(cache=StageCache(disk=False), **kw)
    pipe.results(["solve"])
    pipe.configure(alpha=0.0105)
    got = pipe.results(["solve"])["solve"]
    assert runs[-1]["warm"] is True
    fresh = Pipeline(cache=StageCache(disk=False), alpha=0.0105, **kw)
    assert fresh.key("solve") == pipe.key("solve")
    want = fresh.results(["solve"])["solve"]
    assert "warm" not in runs[-1]
    assert np.abs(got["weights"] - want["weights"]).max() <= 1e-9
    g, w = got["info"]["bounded"], want["info"]["bounded"]
    assert (g["active"], g["converged"]) == (w["active"], w["converged"]) and abs(g["kkt"] - w["kkt"]) <= 1e-12


def test_evaluate_from_the_error_products_is_the_residuals_and_survives_an_alpha_change():
    """The ``evaluate`` stage sums the errors in weight space from the take's products (the
    ``error_products`` stage: made once per take and rig, not re-run by an alpha change): the
    numbers of :func:`core.evaluate.evaluate` from the (T, 3M) residual to 1e-10 relative, on the
    sample with dense correspondence (its take's low-rank factors used) and on its markers (whose products the stage skips: 3M <=
    2K; scored here through them all the same), and a change in place gives a fresh pipeline's."""
    from core.evaluate import evaluate
    from core.metrics import error_products

    for extra in ({"correspondence": "dense", "dense_points": 200}, {}):
        kw = dict(first_frame=0, last_frame=399, method="spacetime", **extra, **FILES)
        pipe = Pipeline(cache=StageCache(), **kw)
        pipe.run()
        before = dict(pipe.runs)
        pipe.configure(alpha=0.05)
        res = pipe.results(["calibrate", "personalize", "edit", "synthesize", "evaluate", "error_products"])
        assert "error_products" not in _ran(pipe, before) and "evaluate" in _ran(pipe, before)
        st, B = res["calibrate"]["source"], res["personalize"]["deltas"]
        products = res["error_products"]["products"]
        assert (products is not None) == bool(extra)
        # the face points: the source rig's shapes driven by the take's curves, scored through S = A V
        assert not extra or products.low_rank is not None and products.low_rank[0].shape[1] < 60
        args = (B, res["edit"]["weights"], st.deltas, st.valid)
        ref = evaluate(*args, frame_valid=res["synthesize"]["valid"])
        assert ref["marker_rms_mm"] > 0.1 and np.nanmax(ref["velocity_error_mm2"]) > 0  # not a comparison of zeros
        for ev in (res["evaluate"], evaluate(*args, frame_valid=res["synthesize"]["valid"],
                                             products=error_products(B, st.deltas, st.valid))):
            assert ev.keys() == ref.keys()
            for k in ref:
                np.testing.assert_allclose(np.asarray(ev[k], float), np.asarray(ref[k], float), rtol=1e-10, atol=0,
                                           err_msg=k)
        fresh = Pipeline(cache=StageCache(), alpha=0.05, **kw).results(["evaluate"])["evaluate"]
        for k in ref:
            np.testing.assert_allclose(np.asarray(fresh[k], float), np.asarray(res["evaluate"][k], float), rtol=1e-10,
                                       atol=0, err_msg=k)
