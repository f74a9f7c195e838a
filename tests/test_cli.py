"""The command line end to end on the bundled data (short frame ranges to stay fast)."""

import csv

import numpy as np
import pytest

from datapaths import LAYOUTS, PERFORMANCES, RIGS
from core.cli import main
from core.io.gltf import read_animation, read_rig


def test_retarget_curves_through_source_rig_writes_glb_and_csv(tmp_path, capsys):
    out, wcsv = tmp_path / "r.glb", tmp_path / "r.csv"
    code = main(["retarget", "--source", str(PERFORMANCES / "livelinkface_take_s07.csv"),
                 "--source-rig", str(RIGS / "ict_facekit.glb"), "--target-rig", str(RIGS / "rocketbox_female_adult_02.glb"),
                 "--method", "bounded", "--last-frame", "59", "--out", str(out), "--weights-csv", str(wcsv)])
    assert code == 0
    text = capsys.readouterr().out
    assert "retargeted 60 frames" in text and "marker error" in text
    rig, anim = read_rig(out), read_animation(out)
    assert rig.n_shapes == 175 and anim.n_frames == 60 and anim.fps == pytest.approx(30, rel=1e-3)  # real timecode steps
    assert anim.names == rig.names
    assert anim.data.min() >= -1e-6 and anim.data.max() <= 1 + 1e-6  # bounded
    rows = list(csv.reader(open(wcsv)))
    assert rows[0][:3] == ["time_s", "frame", "valid"] and rows[0][3:] == list(rig.names) and len(rows) == 61
    body = np.array(rows[1:], float)
    assert np.array_equal(body[:, 1], np.arange(60)) and np.all(body[:, 2] == 1)  # every frame of this take has data
    np.testing.assert_allclose(body[:, 3:], anim.data, atol=2e-6)


@pytest.mark.parametrize("rig", ["ict_facekit", "jeeliz_tiger"])
def test_retarget_marker_capture_onto_rigs(tmp_path, capsys, rig):
    out = tmp_path / "m.glb"
    code = main(["retarget", "--source", str(PERFORMANCES / "animface_markers_jaw_60hz.csv"), "--target-rig", str(RIGS / f"{rig}.glb"),
                 "--method", "spacetime", "--last-frame", "199", "--out", str(out), "--quiet"])
    assert code == 0
    anim = read_animation(out)
    assert anim.n_frames == 200 and anim.fps == pytest.approx(60)
    # the jaw take opens the mouth: some shape must move substantially
    assert np.ptp(anim.data, axis=0).max() > 0.1


def test_bad_inputs_give_readable_errors(tmp_path, capsys):
    assert main(["retarget", "--source", str(tmp_path / "nope.csv"), "--target-rig", str(RIGS / "jeeliz_tiger.glb")]) == 2
    err = capsys.readouterr().err
    assert "nope.csv" in err and "Traceback" not in err
    bad = tmp_path / "bad.csv"
    bad.write_text("Timecode,BlendShapeCount,EyeBlinkLeft\n00:00:00:00.000,1,0.5\n")
    assert main(["retarget", "--source", str(bad), "--source-rig", str(RIGS / "ict_facekit.glb"),
                 "--target-rig", str(RIGS / "jeeliz_tiger.glb")]) == 2
    err = capsys.readouterr().err
    assert "bad.csv" in err
    # curves without the rig they drive
    assert main(["retarget", "--source", str(PERFORMANCES / "livelinkface_rom.csv"), "--target-rig", str(RIGS / "jeeliz_tiger.glb")]) == 2
    assert "--source-rig" in capsys.readouterr().err


def test_layout_without_default_explains_how_to_make_one(tmp_path, capsys, tiger):
    from core.io.gltf import write_rig

    rig = tmp_path / "new_head.glb"
    write_rig(rig, tiger)
    # without the flag the markers are placed automatically (tests/test_cli_markers.py)
    assert main(["retarget", "--source", str(PERFORMANCES / "animface_markers_jaw_60hz.csv"), "--target-rig", str(rig),
                 "--no-auto-markers"]) == 2
    assert "face-retarget layout" in capsys.readouterr().err


def test_info_describes_files(capsys):
    assert main(["info", str(RIGS / "jeeliz_tiger.glb"), str(PERFORMANCES / "livelinkface_rom.csv")]) == 0
    out = capsys.readouterr().out
    assert "2100 vertices" in out and "11 shapes" in out and "4030 frames at 30 fps" in out


@pytest.mark.slow
def test_layout_command_transfers_to_another_rig(tmp_path, capsys):
    out = tmp_path / "rb.json"
    assert main(["layout", "--from", str(LAYOUTS / "ict_facekit.json"), "--rig", str(RIGS / "rocketbox_female_adult_02.glb"),
                 "--out", str(out)]) == 0
    from core.io.layout import read_layout

    lay = read_layout(out)
    assert lay.n_markers == 41 and "wrote" in capsys.readouterr().out


@pytest.mark.slow
def test_dense_transfer_method_writes_a_rig_of_transferred_bases(tmp_path, capsys):
    out = tmp_path / "xu.glb"
    code = main(["retarget", "--method", "transfer", "--source", str(PERFORMANCES / "livelinkface_take_s07.csv"),
                 "--source-rig", str(RIGS / "ict_facekit.glb"), "--target-rig", str(RIGS / "rocketbox_female_adult_02.glb"),
                 "--last-frame", "39", "--out", str(out), "--quiet"])
    assert code == 0
    rig, anim = read_rig(out), read_animation(out)
    assert anim.n_frames == 40 and anim.names == rig.names and rig.n_shapes >= 1
    # the fitted neutral lies on the Rocketbox head, not on ICT (which sits ~1.5 m lower)
    assert 1.3 < np.median(rig.neutral[:, 1]) < 1.8
    # the details ride along as morph targets after the bases; --transfer-details none drops them
    n_detail = sum(n.startswith("xu_detail_") for n in rig.names)
    assert n_detail >= 1 and all(n.startswith("xu_basis_") for n in rig.names[:rig.n_shapes - n_detail])
    assert "morph targets (largest error" in capsys.readouterr().out
    bare = tmp_path / "bare.glb"
    assert main(["retarget", "--method", "transfer", "--source", str(PERFORMANCES / "livelinkface_take_s07.csv"),
                 "--source-rig", str(RIGS / "ict_facekit.glb"), "--target-rig", str(RIGS / "rocketbox_female_adult_02.glb"),
                 "--last-frame", "39", "--out", str(bare), "--quiet", "--transfer-details", "none",
                 "--transfer-max-bases", "3", "--no-transfer-feature-lines"]) == 0
    names = read_rig(bare).names
    assert len(names) == min(3, rig.n_shapes - n_detail) and all(n.startswith("xu_basis_") for n in names)


@pytest.mark.slow
def test_transfer_refuses_marker_sources(capsys):
    code = main(["retarget", "--method", "transfer", "--source", str(PERFORMANCES / "animface_markers_jaw_60hz.csv"),
                 "--source-rig", str(RIGS / "ict_facekit.glb"), "--target-rig", str(RIGS / "jeeliz_tiger.glb")])
    assert code == 2 and "dense source" in capsys.readouterr().err


def test_names_writes_an_editable_map_and_bundled_jeeliz_map_drives_the_tiger(tmp_path, capsys):
    from core.names import NameMap

    out = tmp_path / "map.json"
    assert main(["names", "--source", str(PERFORMANCES / "livelinkface_rom.csv"), "--target-rig", str(RIGS / "jeeliz_tiger.glb"),
                 "--out", str(out)]) == 0
    nm = NameMap.from_json(out)
    assert set(nm.entries) == {"smileRight", "smileLeft", "eyeBrowLeftDown", "eyeBrowRightDown", "eyeBrowLeftUp", "eyeBrowRightUp",
                               "mouthOpen", "mouthRound", "eyeRightClose", "eyeLeftClose", "mouthNasty"}
    assert all(v == [] for v in nm.entries.values()) and "unmapped" in capsys.readouterr().out
    # the bundled map lets Live Link curves drive the tiger as a source rig
    code = main(["retarget", "--source", str(PERFORMANCES / "livelinkface_take_s07.csv"), "--source-rig", str(RIGS / "jeeliz_tiger.glb"),
                 "--name-map", str(RIGS.parent / "namemaps" / "arkit_to_jeeliz.json"), "--target-rig", str(RIGS / "ict_facekit.glb"),
                 "--method", "lsq", "--last-frame", "59", "--quiet"])
    assert code == 0 and "retargeted 60 frames" in capsys.readouterr().out


def test_evaluate_help_says_what_it_does_with_an_example(capsys):
    from core.cli import main

    with pytest.raises(SystemExit):
        main(["evaluate", "--help"])
    out = capsys.readouterr().out
    assert "score each as an animator would look" in out and "example:\n  face-retarget evaluate --source" in out
