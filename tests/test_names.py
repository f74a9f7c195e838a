"""ARKit name canonicalisation and name maps."""

from pathlib import Path

import numpy as np
import pytest

from core.names import ARKIT_NAMES, NameMap, canonical, split_base


@pytest.mark.parametrize("raw", ["eyeBlink_L", "AK_09_EyeBlinkLeft", "EyeBlinkLeft", "eyeBlinkLeft", "EYEBLINKLEFT"])
def test_canonical_spellings(raw):
    assert canonical(raw) == "eyeBlinkLeft"


def test_non_arkit_names_are_kept():
    for n in ["AU_01_InnerBrowRaiser", "smileLeft", "mouthOpen", "browInnerUp_L"]:
        assert canonical(n) == n
    assert split_base("browInnerUp_L") == "browInnerUp" and split_base("eyeBlink_L") is None


def test_arkit_list_is_complete():
    assert len(ARKIT_NAMES) == 52 and len(set(ARKIT_NAMES)) == 52


def test_real_rigs_cover_arkit(ict, rocketbox):
    assert sum(canonical(n) in ARKIT_NAMES for n in ict.names) == 49
    assert {canonical(n) for n in rocketbox.names} >= set(ARKIT_NAMES)


def test_automatic_map_handles_split_shapes(ict, rocketbox):
    nm = NameMap.automatic(rocketbox.names, ict.names)
    G = nm.matrix(rocketbox.names, ict.names)
    i = ict.names.index("browInnerUp_L")
    assert G[i, rocketbox.names.index("AK_03_BrowInnerUp")] == 1
    back = NameMap.automatic(ict.names, rocketbox.names).matrix(ict.names, rocketbox.names)
    j = rocketbox.names.index("AK_03_BrowInnerUp")
    np.testing.assert_allclose(back[j, [ict.names.index("browInnerUp_L"), ict.names.index("browInnerUp_R")]], [0.5, 0.5])
    assert "tongueOut" not in NameMap.automatic(ict.names, ["tongueOut"]).entries


def test_name_map_json_roundtrip_and_errors(tmp_path):
    nm = NameMap({"smileLeft": [("mouthSmileLeft", 1.0)], "mouthOpen": [("jawOpen", 0.8), ("mouthFunnel", 0.2)]})
    p = tmp_path / "map.json"
    nm.to_json(p)
    assert NameMap.from_json(p) == nm
    with pytest.raises(KeyError, match="does not have"):
        nm.matrix(["jawOpen"], ["mouthOpen"])
    p.write_text('{"map": {"x": [{"gain": 2}]}}')
    with pytest.raises(ValueError, match="source"):
        NameMap.from_json(p)
    p.write_text("{not json")
    with pytest.raises(ValueError, match="map.json"):
        NameMap.from_json(p)


# --- vocabularies -------------------------------------------------------------------------

from core.names import (Vocabulary, arkit_combination, load_vocabularies, name_key,  # noqa: E402
                        read_vocabulary, recognise)


@pytest.fixture(scope="module")
def vocabs():
    return load_vocabularies()


@pytest.mark.parametrize("raw", ["Mouth_Smile_Left", "mouthSmile_L", "MouthSmileLeft", "AK_44_MouthSmileLeft",
                                 "blendShape1.mouthSmile_L", "MOUTH_SMILE_LEFT"])
def test_name_key_ignores_case_separators_prefixes(raw):
    assert name_key(raw.replace("AK_44_", "")) == "mouthsmile|left"


def test_name_key_of_facs_is_the_au_number_and_side():
    assert name_key("AU_12_L_LipCornerPuller") == name_key("AU12_L") == name_key("AU12L") == "au12|left"
    assert name_key("AU_12_LipCornerPuller") == "au12|" and name_key("AU_61_EyesTurnLeft") == "au61|"


def _subset(rig, prefix):
    return [n for n in rig.names if n.startswith(prefix)]


@pytest.mark.parametrize("prefix, vocabulary, count", [("AK_", "arkit", 52), ("SR_", "sranipal", 42), ("AU_", "facs", 48),
                                                      ("AA_VI_", "oculus_visemes", 15), ("HB_", "rocketbox", 17)])
def test_rocketbox_vocabularies_are_recognised(rocketbox, vocabs, prefix, vocabulary, count):
    names = _subset(rocketbox, prefix)
    r = recognise(names, vocabs)
    assert (r.vocabulary, r.recognised, r.total) == (vocabulary, count, count)
    assert r.counts[0] == count


def test_whole_rocketbox_and_ict_are_recognised(rocketbox, ict, vocabs):
    r = recognise(rocketbox.names, vocabs)
    assert r.total == 175 and r.recognised == 175 and r.vocabularies[:3] == ("arkit", "facs", "sranipal")
    r = recognise(ict.names, vocabs)  # split shapes (browInnerUp_L) count as ARKit
    assert r.vocabulary == "arkit" and r.recognised == r.total == 53
    assert str(recognise(["jawOpen", "hat"], vocabs)).startswith("1 of 2 names recognised: arkit 1")


@pytest.mark.parametrize("names, vocabulary", [
    (["JawOpen", "MouthCornerPullLeft", "EyeSquintRight", "LipSuckUpperLeft", "BrowPinchLeft"], "unified_expressions"),
    (["JawDrop", "LipCornerPullerL", "EyesClosedL", "EYES_CLOSED_R", "LipFunnelerLB"], "meta_movement"),
    (["aa", "ih", "ou", "blink_l", "happy", "blinkLeft", "lookUp"], "vrm"),
    (["viseme_sil", "viseme_PP", "viseme_kk", "viseme_aa", "viseme_E"], "oculus_visemes"),
    (["Jaw_Open", "Mouth_Ape_Shape", "Mouth_Pout", "Eye_Left_squeeze", "Cheek_Suck"], "sranipal"),
])
def test_other_spellings_are_recognised(vocabs, names, vocabulary):
    r = recognise(names, vocabs)
    assert r.vocabulary == vocabulary and r.recognised == r.total


def test_vocabulary_rows_are_weighted_arkit_combinations(vocabs):
    assert arkit_combination("AU_12_LipCornerPuller", vocabs) == ("facs", (("mouthSmileLeft", 0.5), ("mouthSmileRight", 0.5)))
    assert arkit_combination("AU_12_L_LipCornerPuller", vocabs) == ("facs", (("mouthSmileLeft", 1.0),))
    assert arkit_combination("SR_08_Eye_Left_Right", vocabs) == ("sranipal", (("eyeLookInLeft", 1.0),))
    assert arkit_combination("EyesLookRightL", vocabs)[1] == (("eyeLookInLeft", 1.0),)
    # a sideless name of an ARKit left/right pair is their mean; a shape with no ARKit counterpart is ()
    assert arkit_combination("mouthSmile", vocabs) == ("arkit", (("mouthSmileLeft", 0.5), ("mouthSmileRight", 0.5)))
    assert arkit_combination("SR_03_Cheek_Suck", vocabs) == ("sranipal", ())
    assert arkit_combination("hat", vocabs) is None
    # a prefix ties a name to its vocabulary: SR_ names are not read as ARKit even when the words match
    assert arkit_combination("SR_21_Jaw_Open", vocabs)[0] == "sranipal"
    for v in vocabs:  # every bundled row is made of ARKit shapes
        assert all(a in ARKIT_NAMES for row in v.entries.values() for a, _ in row), v.name


def test_automatic_drives_vocabulary_shapes_from_arkit_curves(vocabs):
    src = list(ARKIT_NAMES)
    nm = NameMap.automatic(src, ["AU_12_LipCornerPuller", "SR_21_Jaw_Open", "AA_VI_14_U", "SR_03_Cheek_Suck"], vocabs)
    assert nm.entries["AU_12_LipCornerPuller"] == [("mouthSmileLeft", 0.5), ("mouthSmileRight", 0.5)]
    assert nm.entries["SR_21_Jaw_Open"] == [("jawOpen", 1.0)] and nm.entries["AA_VI_14_U"] == [("mouthPucker", 1.0)]
    assert nm.unmapped(["SR_03_Cheek_Suck"]) == ["SR_03_Cheek_Suck"]
    G = nm.matrix(src, list(nm.entries))
    x = np.random.default_rng(0).uniform(0, 1, len(src))
    np.testing.assert_allclose(G @ x, [0.5 * (x[src.index("mouthSmileLeft")] + x[src.index("mouthSmileRight")]),
                                       x[src.index("jawOpen")], x[src.index("mouthPucker")]])


def test_automatic_inverts_a_vocabulary_by_least_squares(vocabs):
    """Source curves in SRanipal and FACS made from ARKit weights x (eq. 1) give x back on the
    ARKit shapes they express."""
    source = ["SR_34_Mouth_Smile_Left", "SR_35_Mouth_Smile_Right", "AU_12_LipCornerPuller", "SR_21_Jaw_Open",
              "SR_05_Eye_Left_squeeze", "AU_07_L_LidTightener", "AU_06_L_CheekRaiser"]
    target = ["mouthSmileLeft", "mouthSmileRight", "jawOpen", "eyeSquintLeft", "cheekSquintLeft", "browDownLeft"]
    x = dict(zip(target, np.random.default_rng(1).uniform(0, 1, len(target))))
    s = np.array([sum(g * x[a] for a, g in arkit_combination(n, vocabs)[1]) for n in source])
    nm = NameMap.automatic(source, target, vocabs)
    assert set(nm.entries) == set(target)
    np.testing.assert_allclose(nm.matrix(source, target) @ s, [x[t] for t in target], atol=1e-9)
    assert any(g < 1 for _, g in nm.entries["mouthSmileLeft"])  # several channels carry it: a least-squares mix


def test_automatic_drives_each_arkit_shape_once(rocketbox, vocabs):
    src = list(ARKIT_NAMES)
    # a rig with ARKit shapes: the other vocabularies stay undriven (the evaluation's ground truth is unchanged)
    nm = NameMap.automatic(src, rocketbox.names, vocabs)
    assert {t for t in nm.entries} == set(_subset(rocketbox, "AK_"))
    # without them: one shape per ARKit shape, fewer-component and better-recognised vocabularies first
    rest = [n for n in rocketbox.names if not n.startswith("AK_")]
    nm = NameMap.automatic(src, rest, vocabs)
    driven = [a for t in nm.entries for a, _ in nm.entries[t]]
    assert len(driven) == len(set(driven)) and len(nm.entries) == 46
    assert "AU_12_L_LipCornerPuller" in nm.entries and "SR_34_Mouth_Smile_Left" not in nm.entries
    assert "AU_43_L_EyeClosed" in nm.entries and "AU_12_LipCornerPuller" not in nm.entries
    # the per-shape reading (the name prior) maps every shape that has an ARKit row
    loose = NameMap.automatic(src, rest, vocabs, exclusive=False)
    with_row = [n for n in rest if arkit_combination(n, vocabs)[1]]
    assert list(loose.entries) == with_row and loose.entries["SR_34_Mouth_Smile_Left"] == [("mouthSmileLeft", 1.0)]


def test_vocabulary_json_round_trip(tmp_path, vocabs):
    for v in vocabs:
        out = tmp_path / f"vocabulary_{v.name}.json"
        v.to_json(out)
        assert out.read_text() == Path(v.path).read_text()
        w = read_vocabulary(out)
        assert (w.name, w.entries, w.title, w.prefix, w.notes) == (v.name, v.entries, v.title, v.prefix, v.notes)


def test_an_edited_file_overrides_a_bundled_entry(tmp_path):
    edit = tmp_path / "vocabulary_sranipal.json"
    edit.write_text('{"vocabulary": "sranipal", "map": {"Mouth_Pout": [{"source": "mouthFunnel", "gain": 0.7}], '
                    '"Mouth_Smirk_Left": [{"source": "mouthSmile_L", "gain": 1}]}}')
    bundled = {v.name: v for v in load_vocabularies()}["sranipal"]
    given = load_vocabularies([edit])  # a file given ...
    for vocabs in (given, load_vocabularies([tmp_path])):  # ... or a folder of them
        sr = {v.name: v for v in vocabs}["sranipal"]
        assert sr.entries["Mouth_Pout"] == (("mouthFunnel", 0.7),)
        assert sr.entries["Mouth_Smirk_Left"] == (("mouthSmileLeft", 1.0),)  # sources in any ARKit spelling
        assert {k: r for k, r in sr.entries.items() if k not in ("Mouth_Pout", "Mouth_Smirk_Left")} == \
            {k: r for k, r in bundled.entries.items() if k != "Mouth_Pout"}
        assert sr.prefix == bundled.prefix
    assert NameMap.automatic(list(ARKIT_NAMES), ["SR_31_Mouth_Pout"], vocabularies=given).entries == \
        {"SR_31_Mouth_Pout": [("mouthFunnel", 0.7)]}


def test_bad_vocabulary_files_say_what_is_wrong(tmp_path):
    p = tmp_path / "vocabulary_x.json"
    cases = [("{not json", "cannot read"),
             ('{"map": {"a": [{"source": "jawOpen"}]}}', "field 'vocabulary'"),
             ('{"vocabulary": "x", "map": {"a": [{"source": "jawOpne"}]}}', "did you mean 'jawOpen'"),
             ('{"vocabulary": "x", "map": {"a": [{"source": "jawOpen", "gain": "big"}]}}', "gain must be a number"),
             ('{"vocabulary": "x", "prefix": "SR_(", "map": {}}', "not a regular expression"),
             ('{"vocabulary": "x", "source": "facs", "map": {}}', "field 'source'"),
             ('{"vocabulary": "x", "map": []}', "field 'map'")]
    for text, message in cases:
        p.write_text(text)
        with pytest.raises(ValueError, match=message) as e:
            read_vocabulary(p)
        assert "vocabulary_x.json" in str(e.value)
    with pytest.raises(ValueError, match="does not exist"):
        load_vocabularies([tmp_path / "missing.json"])
    assert isinstance(Vocabulary("v", {"a": ()}), Vocabulary)


def test_names_command_shows_vocabularies_and_pairs(tmp_path, capsys, rocketbox):
    from core.cli import main

    data = Path(__file__).resolve().parents[1] / "data"
    files = ["names", "--source", str(data / "performances" / "livelinkface_rom.csv"),
             "--target-rig", str(data / "rigs" / "rocketbox_female_adult_02.glb")]
    out = tmp_path / "map.json"
    assert main(files + ["--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "target rocketbox_female_adult_02: 175 of 175 names recognised: arkit 52, facs 48, sranipal 42" in text
    lines = {line.split()[0]: line for line in text.splitlines() if line.startswith("  ")}
    assert lines["AK_25_JawOpen"].endswith("<- jawOpen  [arkit]")
    assert "(no ARKit counterpart)  [oculus_visemes]" in lines["AA_VI_00_Sil"]
    assert "drive another shape" in lines["SR_21_Jaw_Open"]  # AK_25_JawOpen drives jawOpen already
    nm = NameMap.from_json(out)
    assert len(nm.entries) == 175 and nm.entries["SR_21_Jaw_Open"] == []
    # the non-ARKit shapes alone, with an edited vocabulary entry
    edit = tmp_path / "vocabulary_facs.json"  # AU 23 (lip tightener) has no bundled ARKit row
    edit.write_text('{"vocabulary": "facs", "map": {"AU23": [{"source": "mouthRollLower", "gain": 1}]}}')
    rest = ",".join(n for n in rocketbox.names if not n.startswith("AK_"))
    assert main(files + ["--target-shapes", rest, "--vocabulary", str(edit), "--mapped-only"]) == 0
    text = capsys.readouterr().out
    lines = {line.split()[0]: line for line in text.splitlines() if line.startswith("  ")}
    assert lines["AU_26_JawDrop"].endswith("<- jawOpen  [facs]") and "SR_21_Jaw_Open" not in lines  # one jaw
    assert lines["AU_12_L_LipCornerPuller"].endswith("<- mouthSmileLeft  [facs]") and "AA_VI_00_Sil" not in lines
    assert lines["AU_23_LipTightener"].endswith("<- mouthRollLower  [facs]") and "SR_26_Mouth_Lower_Inside" not in lines


def test_character_creator_arkit_names():
    """Reallusion Character Creator's ARKit set on CC_Base_Body is numbered A01_..A52_ with words
    split by '_' (``A01_Brow_Inner_Up``, ``A14_Eye_Blink_Left``), beside CC's own spellings of some
    of the same shapes (``Eye_Blink_L``). The numbered names are ARKit names; with ``exclusive`` one
    shape per ARKit name is driven, the ARKit-set one, so the eye does not blink twice over."""
    assert canonical("A01_Brow_Inner_Up") == "browInnerUp"
    assert canonical("A14_Eye_Blink_Left") == "eyeBlinkLeft"
    assert canonical("A52_Tongue_Out") == "tongueOut"
    assert canonical("A99_Not_A_Shape") == "A99_Not_A_Shape"
    cc = ["Eye_Blink_L", "A14_Eye_Blink_Left", "A01_Brow_Inner_Up", "Mouth_Smile_L", "Jaw_Open"]
    nm = NameMap.automatic(ARKIT_NAMES, cc)
    assert nm.entries == {"A14_Eye_Blink_Left": [("eyeBlinkLeft", 1.0)], "A01_Brow_Inner_Up": [("browInnerUp", 1.0)],
                          "Mouth_Smile_L": [("mouthSmileLeft", 1.0)], "Jaw_Open": [("jawOpen", 1.0)]}
    G = nm.matrix(ARKIT_NAMES, cc)
    assert (G.sum(axis=0) <= 1).all()  # every ARKit channel drives one shape at most
    both = NameMap.automatic(ARKIT_NAMES, cc, exclusive=False)  # a per-shape guess: both spellings
    assert both.entries["Eye_Blink_L"] == both.entries["A14_Eye_Blink_Left"] == [("eyeBlinkLeft", 1.0)]
    # the exact ARKit spelling wins over a prefixed one
    assert list(NameMap.automatic(ARKIT_NAMES, ["AK_09_EyeBlinkLeft", "eyeBlinkLeft"]).entries) == ["eyeBlinkLeft"]


def test_vroid_face_shapes_are_a_vocabulary():
    """A VRoid Studio avatar's morph targets are Fcl_* (the VRM presets only bind to them): the
    names of a real export (TalkingHead's vroid.glb) are all recognised, and the parts are driven,
    each ARKit channel at most once; whole-face emotions drive nothing."""
    fcl = ["Fcl_ALL_Neutral", "Fcl_ALL_Angry", "Fcl_ALL_Joy", "Fcl_BRW_Angry", "Fcl_BRW_Sorrow", "Fcl_EYE_Close",
           "Fcl_EYE_Close_R", "Fcl_EYE_Close_L", "Fcl_EYE_Joy", "Fcl_EYE_Surprised", "Fcl_EYE_Iris_Hide", "Fcl_MTH_Joy",
           "Fcl_MTH_A", "Fcl_MTH_I", "Fcl_MTH_U", "Fcl_MTH_E", "Fcl_MTH_O", "Fcl_HA_Fung1"]
    rec = recognise(fcl)
    assert rec.recognised == len(fcl) and rec.vocabularies[0] == "vroid"
    nm = NameMap.automatic(ARKIT_NAMES, fcl)
    assert nm.entries["Fcl_EYE_Close_L"] == [("eyeBlinkLeft", 1.0)]
    assert nm.entries["Fcl_MTH_A"] == [("jawOpen", 1.0)]
    assert nm.entries["Fcl_BRW_Angry"] == [("browDownLeft", 0.5), ("browDownRight", 0.5)]
    assert nm.entries["Fcl_MTH_Joy"] == [("mouthSmileLeft", 0.5), ("mouthSmileRight", 0.5)]
    assert not {"Fcl_ALL_Angry", "Fcl_ALL_Joy", "Fcl_EYE_Close", "Fcl_HA_Fung1"} & set(nm.entries)
    assert (nm.matrix(ARKIT_NAMES, fcl).sum(axis=0) <= 1 + 1e-12).all()
