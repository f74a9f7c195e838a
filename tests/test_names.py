"""ARKit name canonicalisation and name maps."""

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
