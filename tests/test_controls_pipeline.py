"""The production controls through the pipeline and the CLI (core/controls/ wired into the
solve, synthesize and take stages, and the exports)."""

import csv
import json

import numpy as np
import pytest

from core.cli import main
from core.pipeline import Pipeline, StageCache
from datapaths import PERFORMANCES, RIGS

FILES = dict(source=str(PERFORMANCES / "livelinkface_take_s07.csv"), source_rig=str(RIGS / "ict_facekit.glb"),
             target_rig=str(RIGS / "rocketbox_female_adult_02.glb"))


@pytest.fixture(scope="module")
def pipe():
    return Pipeline(cache=StageCache(), method="bounded", target_shapes="arkit", last_frame=599, **FILES)


def _w(pipe, name):
    res = pipe.results(["load", "synthesize"])
    return res["synthesize"]["weights"][:, res["load"]["target_rig"].names.index(name)]


def test_gain_doubles_a_curve_up_to_its_bound_and_off_shapes_stay_zero(pipe):
    pipe.configure(controls={})
    jaw = _w(pipe, "AK_25_JawOpen").copy()
    pipe.configure(controls={"shapes": {"jawOpen": {"gain": 2.0}}})  # a canonical ARKit name finds AK_25_JawOpen
    np.testing.assert_allclose(_w(pipe, "AK_25_JawOpen"), np.minimum(2 * jaw, 1.0), atol=1e-12)
    pipe.configure(controls={"shapes": {"AK_44_MouthSmileLeft": {"active": False}}})
    assert np.all(_w(pipe, "AK_44_MouthSmileLeft") == 0)
    pipe.configure(controls={})


def test_per_shape_bounds_hold_in_the_solve(pipe):
    pipe.configure(controls={"shapes": {"AK_25_JawOpen": {"upper": 0.3}}})
    assert _w(pipe, "AK_25_JawOpen").max() <= 0.3 + 1e-9
    pipe.configure(controls={})


def test_symmetry_weight_brings_left_and_right_blinks_together(pipe):
    pipe.configure(symmetry_weight=0.0)
    d0 = np.sqrt(np.mean((_w(pipe, "AK_09_EyeBlinkLeft") - _w(pipe, "AK_10_EyeBlinkRight")) ** 2))
    pipe.configure(symmetry_weight=0.1)
    d1 = np.sqrt(np.mean((_w(pipe, "AK_09_EyeBlinkLeft") - _w(pipe, "AK_10_EyeBlinkRight")) ** 2))
    pipe.configure(symmetry_weight=0.0)
    assert d1 < 0.5 * d0, (d0, d1)


def test_a_cancel_pair_never_fires_together(pipe):
    pipe.configure(controls={"cancel": [["AK_09_EyeBlinkLeft", "AK_21_EyeWideLeft"]]}, cancel_threshold=0.02)
    a, b = _w(pipe, "AK_09_EyeBlinkLeft"), _w(pipe, "AK_21_EyeWideLeft")
    assert not np.any((a > 0.02) & (b > 0.02))
    assert "cancel" in pipe.results(["solve"])["solve"]["info"]
    pipe.configure(controls={}, cancel_threshold=0.0)


def test_one_euro_filter_reduces_jitter_of_a_per_frame_method(pipe):
    pipe.configure(weights_filter="none")
    j0 = np.nanmean(pipe.results(["evaluate"])["evaluate"]["jitter"])
    pipe.configure(weights_filter="one_euro", filter_min_cutoff=1.0)
    j1 = np.nanmean(pipe.results(["evaluate"])["evaluate"]["jitter"])
    pipe.configure(weights_filter="none")
    assert j1 < 0.5 * j0, (j0, j1)


def test_mirror_source_swaps_left_and_right(pipe):
    left = _w(pipe, "AK_44_MouthSmileLeft").copy()
    pipe.configure(mirror_source=True)
    right = _w(pipe, "AK_45_MouthSmileRight").copy()
    pipe.configure(mirror_source=False)
    assert np.corrcoef(left, right)[0, 1] > 0.9


def test_cli_controls_file_and_keyframe_reduction(tmp_path, capsys):
    table = tmp_path / "controls.json"
    table.write_text(json.dumps({"shapes": {"jawOpen": {"gain": 1.5}}}))
    out, w = tmp_path / "r.glb", tmp_path / "r.csv"
    args = ["retarget", *sum(([f"--{k.replace('_', '-')}", v] for k, v in FILES.items()), []), "--method", "bounded",
            "--target-shapes", "arkit", "--last-frame", "299", "--controls", str(table), "--keys", "linear",
            "--out", str(out), "--weights-csv", str(w), "--quiet"]
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "keys:" in text and (tmp_path / "r_keys.csv").exists()
    from core.io.gltf import read_animation

    anim = read_animation(out)
    rows = list(csv.reader(open(w)))
    dense = np.array([[float(c) for c in r[3:]] for r in rows[1:]])
    # the reduced animation, resampled at the frames, stays within the tolerance of the dense curves
    t = np.arange(len(dense)) / 30.0
    got = np.stack([np.interp(t, anim.times, anim.data[:, k]) for k in range(anim.data.shape[1])], axis=1)
    assert anim.n_frames < len(dense) and np.abs(got - dense).max() <= 0.005 + 1e-5
