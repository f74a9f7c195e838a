"""Data model: validation, immutability, evaluation."""

import numpy as np
import pytest

from core.model import MarkerLayout, Performance, Rig, flatten, unflatten


def _tri_rig():
    neutral = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]])
    deltas = np.zeros((2, 3, 3))
    deltas[0, 0, 2] = 1
    deltas[1, 1, 1] = 2
    return Rig(neutral, [[0, 1, 2]], deltas, ["a", "b"], name="tri")


def test_rig_evaluate_single_and_batch():
    rig = _tri_rig()
    np.testing.assert_allclose(rig.evaluate([0.5, 0])[0], [0, 0, 0.5])
    seq = rig.evaluate(np.array([[0, 0], [1, 1]]))
    assert seq.shape == (2, 3, 3)
    np.testing.assert_allclose(seq[1, 1], [1, 2, 0])
    with pytest.raises(ValueError, match="K=2"):
        rig.evaluate([1, 2, 3])


def test_rig_is_immutable_and_copies_input():
    n = np.zeros((3, 3))
    rig = Rig(n, [[0, 1, 2]], np.zeros((1, 3, 3)), ["a"])
    n[0, 0] = 5
    assert rig.neutral[0, 0] == 0
    with pytest.raises(ValueError):
        rig.neutral[0, 0] = 1
    with pytest.raises(Exception):
        rig.names = ("b",)


@pytest.mark.parametrize("kw, msg", [
    (dict(faces=[[0, 1, 5]]), "faces"),
    (dict(deltas=np.zeros((1, 4, 3))), "deltas"),
    (dict(names=["a", "a"], deltas=np.zeros((2, 3, 3))), "duplicate"),
    (dict(names=["a", "b"]), "names"),
    (dict(units="furlong"), "units"),
])
def test_rig_validation_names_the_field(kw, msg):
    args = dict(neutral=np.zeros((3, 3)), faces=[[0, 1, 2]], deltas=np.zeros((1, 3, 3)), names=["a"])
    args.update(kw)
    with pytest.raises(ValueError, match=msg):
        Rig(**args)


def test_rig_index_suggests_close_names():
    with pytest.raises(KeyError, match="did you mean"):
        _tri_rig().index("aa")


def test_layout_barycentric_points_and_checks():
    rig = _tri_rig()
    lay = MarkerLayout(["m0", "m1"], [[0, 1, 2], [1, 1, 1]], [[1 / 3] * 3, [1, 0, 0]], rig="tri")
    n, d = lay.on_rig(rig)
    np.testing.assert_allclose(n[0], [1 / 3, 1 / 3, 0])
    np.testing.assert_allclose(d[1, 1], [0, 2, 0])
    with pytest.raises(ValueError, match="sum to 1"):
        MarkerLayout(["m"], [[0, 1, 2]], [[0.5, 0.5, 0.5]])
    big = MarkerLayout.from_vertices(["m"], [7], rig="other")
    with pytest.raises(ValueError, match="vertices >= 3"):
        big.on_rig(rig)


def test_performance_masks_never_zero():
    data = np.ones((4, 2, 3))
    data[1, 0] = np.nan
    p = Performance.markers(data, ["a", "b"], 60)
    assert not p.valid[1, 0] and p.valid[1, 1]
    valid = np.ones((4, 2), bool)
    valid[2, 1] = False
    q = Performance.markers(np.ones((4, 2, 3)), ["a", "b"], 60, valid=valid)
    assert np.isnan(q.data[2, 1]).all()
    with pytest.raises(ValueError, match="fps"):
        Performance.curves(np.zeros((3, 2)), ["a", "b"], 0)
    with pytest.raises(ValueError, match="shape"):
        Performance.curves(np.zeros((3, 2)), ["a"], 30)


def test_performance_select_and_frames():
    p = Performance.curves(np.arange(12.0).reshape(6, 2), ["a", "b"], 30, extras={"head_rotation": np.zeros((6, 3))})
    q = p.select(["b"]).frames(1, 5, 2)
    np.testing.assert_allclose(q.data[:, 0], [3, 7])
    assert q.fps == 15 and q.extras["head_rotation"].shape == (2, 3)
    with pytest.raises(KeyError, match="no channels"):
        p.select(["zz"])


def test_flatten_roundtrip_order():
    x = np.arange(24.0).reshape(2, 4, 3)
    f = flatten(x)
    assert f.shape == (2, 12) and f[0, 3] == x[0, 1, 0]
    np.testing.assert_array_equal(unflatten(f), x)


def test_real_rigs_load_with_expected_sizes(rigs):
    expect = {"ict_facekit": (14629, 53), "rocketbox_female_adult_02": (2458, 175), "jeeliz_tiger": (2100, 11), "jeeliz_triceratops": (3013, 11)}
    for stem, (V, K) in expect.items():
        r = rigs[stem]
        assert (r.n_vertices, r.n_shapes) == (V, K)
        assert 0.1 < r.size < 1.0  # metres: a head
        assert not r.deltas.flags.writeable
