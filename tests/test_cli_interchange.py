"""Studio interchange through the command line: USD out (--out .usda/.usdc/.usdz), Live Link
Face CSV out (--livelink-csv), and dense mesh-sequence sources (a GLB, a USD and an OBJ folder
of the same take) through a marker method and dense transfer, without a source rig."""

import numpy as np
import pytest

from datapaths import LAYOUTS, PERFORMANCES, RIGS
from dense_case import tiger_files, tiger_weights

from core.cli import main
from core.io.curves_csv import read_curves_csv
from core.io.gltf import read_rig
from core.io.livelink import read_livelink
from core.model import Performance

pytest.importorskip("pxr", reason="usd-core (pip install face-retarget[usd])")

from core.io import usd  # noqa: E402


def test_usd_and_livelink_out_match_the_weights_csv(tmp_path, capsys):
    out, csv, ll = tmp_path / "r.usdc", tmp_path / "r.csv", tmp_path / "ll.csv"
    code = main(["retarget", "--source", str(PERFORMANCES / "livelinkface_take_s07.csv"), "--source-rig", str(RIGS / "ict_facekit.glb"),
                 "--target-rig", str(RIGS / "rocketbox_female_adult_02.glb"), "--method", "bounded", "--last-frame", "59",
                 "--out", str(out), "--weights-csv", str(csv), "--csv-precision", "full", "--livelink-csv", str(ll), "--quiet"])
    assert code == 0
    printed = capsys.readouterr().out
    assert f"wrote {out}" in printed and f"wrote {ll}" in printed
    assert usd.check_usd(out)["errors"] == []
    W = read_curves_csv(csv)
    anim, rig = usd.read_animation(out), usd.read_rig(out)
    assert anim.names == W.names == rig.names and anim.fps == W.fps == 30
    np.testing.assert_array_equal(anim.data, W.data.astype(np.float32))
    np.testing.assert_allclose(anim.times, W.times, atol=1e-6)
    np.testing.assert_array_equal(rig.deltas, read_rig(RIGS / "rocketbox_female_adult_02.glb").deltas)
    # Live Link: Rocketbox's AK_25_JawOpen drives jawOpen, at Live Link's 10 printed decimals
    lf = read_livelink(ll)
    assert lf.n_frames == 60 and lf.fps == 30 and lf.valid.all()
    np.testing.assert_allclose(lf.data[:, lf.names.index("jawOpen")], W.data[:, W.names.index("AK_25_JawOpen")], atol=1e-10)
    np.testing.assert_allclose(lf.data[:, lf.names.index("eyeBlinkLeft")], W.data[:, W.names.index("AK_09_EyeBlinkLeft")], atol=1e-10)


def test_livelink_out_of_a_transfer_is_refused(tmp_path, capsys):
    files = tiger_files(tmp_path)
    code = main(["retarget", "--method", "transfer", "--source", files["source"], "--source-rig", files["source_rig"],
                 "--target-rig", files["target_rig"], "--livelink-csv", str(tmp_path / "x.csv"), "--quiet"])
    assert code == 2 and "no ARKit shapes" in capsys.readouterr().err


@pytest.fixture(scope="module")
def sequences(tmp_path_factory):
    """The tiger take (a neutral first frame, then the dense case's curves) as three containers."""
    from core.io.sequence import write_mesh_sequence

    d = tmp_path_factory.mktemp("sequences")
    files = tiger_files(d)
    rig = read_rig(RIGS / "jeeliz_tiger.glb")
    W = np.vstack([np.zeros((1, rig.n_shapes)), tiger_weights(rig.n_shapes, 29)])
    perf = Performance.meshes(rig.evaluate(W), 30.0, faces=rig.faces, name="tiger_take")
    paths = {"glb": write_mesh_sequence(d / "take.glb", perf), "usd": write_mesh_sequence(d / "take.usdc", perf),
             "obj": write_mesh_sequence(d / "take_obj", perf)}
    return d, files["target_rig"], paths


def _run(d, target, source, method, tag, extra=()):
    csv, out = d / f"{method}_{tag}.csv", d / f"{method}_{tag}.glb"
    kind = ["--source-kind", "meshes"] if str(source).endswith(".glb") else []
    code = main(["retarget", "--source", str(source), *kind, "--source-layout", str(LAYOUTS / "jeeliz_tiger.json"),
                 "--target-rig", str(target), "--method", method, "--weights-csv", str(csv), "--csv-precision", "full",
                 "--out", str(out), "--quiet", *extra])
    assert code == 0
    return read_curves_csv(csv), out


@pytest.mark.parametrize("method", ["bounded", "transfer"])
def test_glb_usd_and_obj_sequences_of_one_take_give_the_same_weights(sequences, method, capsys):
    d, target, paths = sequences
    extra = ("--transfer-details", "none") if method == "transfer" else ()
    runs = {tag: _run(d, target, p, method, tag, extra) for tag, p in paths.items()}
    ref, ref_out = runs["obj"]
    if method == "bounded":
        assert ref.data.max() > 0.5  # the take really moves the target
    for tag in ("glb", "usd"):
        W, out = runs[tag]
        assert W.names == ref.names and W.n_frames == 30
        # float32 geometry in the GLB and USD, 17 digits in the OBJ: the same weights to float32 precision
        np.testing.assert_allclose(W.data, ref.data, rtol=0, atol=1e-5)
        if method == "transfer":  # and the same transferred bases
            a, b = read_rig(out), read_rig(ref_out)
            np.testing.assert_allclose(a.deltas, b.deltas, rtol=0, atol=1e-6 * b.size)
    capsys.readouterr()


def test_detail_transfer_is_stable_to_float32_input(sequences, capsys):
    """The GLB (float32) and OBJ (17 digits) containers of one take give the same transfer with
    fine details. The tiger's whiskers, smoothed, collapse to needles whose float32 normals are
    noise: they have no frame (core.transfer.details.NORMAL_CANCEL; 0.11 mm apart before)."""
    d, target, paths = sequences
    (W, a), (V, b) = _run(d, target, paths["glb"], "transfer", "d_glb"), _run(d, target, paths["obj"], "transfer", "d_obj")
    ra, rb = read_rig(a), read_rig(b)
    np.testing.assert_allclose(ra.evaluate(W.data), rb.evaluate(V.data), rtol=0, atol=1e-5 * rb.size)


def test_transfer_writes_usdz_that_passes_the_checker(sequences):
    d, target, paths = sequences
    W, _ = _run(d, target, paths["usd"], "transfer", "usdz_src")
    out = d / "xu.usdz"
    assert main(["retarget", "--source", str(paths["usd"]), "--source-layout", str(LAYOUTS / "jeeliz_tiger.json"),
                 "--target-rig", str(target), "--method", "transfer", "--out", str(out), "--quiet"]) == 0
    assert usd.check_usd(out)["errors"] == []
    rig, anim = usd.read_rig(out), usd.read_animation(out)
    assert anim.names == rig.names == W.names
    np.testing.assert_allclose(anim.data, W.data.astype(np.float32), atol=1e-6)


def test_layout_for_a_sequence_and_the_rig_path_agree(sequences, tmp_path, capsys):
    """``face-retarget layout --rig <sequence>`` puts a layout on the sequence's first frame; the
    sequence through it retargets as the curves through the source rig do (same take, same markers)."""
    d, target, paths = sequences
    lay = tmp_path / "seq.layout.json"
    assert main(["layout", "--from", str(LAYOUTS / "jeeliz_tiger.json"), "--rig", str(paths["usd"]), "--out", str(lay)]) == 0
    seq_csv, rig_csv = tmp_path / "seq.csv", tmp_path / "rig.csv"
    assert main(["retarget", "--source", str(paths["usd"]), "--source-layout", str(lay), "--target-rig", str(target),
                 "--method", "bounded", "--weights-csv", str(seq_csv), "--csv-precision", "full", "--quiet"]) == 0
    rig = read_rig(RIGS / "jeeliz_tiger.glb")
    from core.io.gltf import write_rig

    W = np.vstack([np.zeros((1, rig.n_shapes)), tiger_weights(rig.n_shapes, 29)])
    write_rig(tmp_path / "curves.glb", rig, weights=W, fps=30.0)
    assert main(["retarget", "--source", str(tmp_path / "curves.glb"), "--source-rig", str(RIGS / "jeeliz_tiger.glb"),
                 "--target-rig", str(target), "--method", "bounded", "--weights-csv", str(rig_csv), "--csv-precision", "full",
                 "--quiet"]) == 0
    np.testing.assert_allclose(read_curves_csv(seq_csv).data, read_curves_csv(rig_csv).data, rtol=0, atol=1e-5)
    capsys.readouterr()
