"""Carrying a transfer back to the target's own mesh (core.transfer.carry, the dense_output stage)."""

import numpy as np
import pytest

from core.transfer.carry import carry_back


def _sphere(sub=2):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=sub)
    return np.asarray(m.vertices), np.asarray(m.faces)


def test_target_on_the_source_surface_gets_the_transferred_displacements_exactly():
    """A target whose vertices are the source's (reordered) and edge midpoints (subdivided):
    every target vertex lies on the fitted source surface, so the carried displacement is the
    transferred one at its vertex / the linear interpolation at the midpoint (1e-12 of it)."""
    import trimesh

    S, F = _sphere()
    rng = np.random.default_rng(0)
    d = rng.normal(size=(3, len(S), 3)) * 0.01
    perm = rng.permutation(len(S))
    c = carry_back(S, F, S[perm])
    assert (c.weight == 1).all() and np.abs(c.distance).max() < 1e-12
    np.testing.assert_allclose(c.apply(d), d[:, perm], rtol=0, atol=1e-12 * np.abs(d).max())
    Vs, Fs = trimesh.remesh.subdivide(S, F)
    mid = np.arange(len(S), len(Vs))
    c = carry_back(S, F, Vs)
    E = trimesh.Trimesh(S, F, process=False).edges_unique
    # trimesh.remesh.subdivide appends one midpoint per unique edge, in edges_unique order
    want = 0.5 * (d[:, E[:, 0]] + d[:, E[:, 1]])
    np.testing.assert_allclose(c.apply(d)[:, mid], want, rtol=0, atol=1e-12 * np.abs(d).max())
    np.testing.assert_allclose(c.apply(d[0]), c.apply(d)[0])


def test_far_parts_keep_the_neutral_with_a_smooth_fall_off():
    """Target vertices beyond ``outer`` x its size from the fitted surface get exactly 0; the
    weight falls monotonically with the distance in between (continuous: no step)."""
    S, F = _sphere(3)
    dirs = S[:200] / np.linalg.norm(S[:200], axis=1, keepdims=True)
    size = np.linalg.norm(np.ptp(dirs, 0)) * 1.03
    r = np.linspace(0, 0.03, 200) * size  # from on the surface to 3 % of the size off it
    T = dirs * (1 + r)[:, None]
    size = np.linalg.norm(np.ptp(T, 0))  # the target's size: the fractions are of it
    c = carry_back(S, F, T, inner=0.005, outer=0.02)
    d = np.ones((len(S), 3))
    out = c.apply(d)
    dist = c.distance
    far = ~np.isfinite(dist) | (dist >= 0.02 * size)
    assert far.any() and (out[far] == 0).all() and (c.weight[far] == 0).all()
    assert (c.weight[dist <= 0.005 * size] == 1).all()
    order = np.argsort(np.where(np.isfinite(dist), dist, np.inf))
    w = c.weight[order]
    assert (np.diff(w) <= 1e-12).all()  # monotone in the distance
    assert np.abs(np.diff(w)).max() < 0.1  # 200 samples over 3 %: no jump


def test_untrusted_source_vertices_fade_out_over_rings():
    """Outside the fitted region (``trusted``) nothing moves; the weight ramps 1/3, 2/3, 1 over
    three rings inside it."""
    from core.geometry import vertex_adjacency

    S, F = _sphere(3)
    trusted = S[:, 2] > 0
    c = carry_back(S, F, S, trusted, rings=3)
    assert (c.weight[~trusted] == 0).all()
    A = vertex_adjacency(F, len(S))
    ring1 = trusted & (A @ (~trusted).astype(float) > 0)
    np.testing.assert_allclose(c.weight[ring1], 1 / 3)
    assert (c.weight[trusted & (S[:, 2] > 0.6)] == 1).all()
    with pytest.raises(ValueError, match="trusted"):
        carry_back(S, F, S, trusted[:-1])
    with pytest.raises(ValueError, match="inner, outer"):
        carry_back(S, F, S, inner=0.03, outer=0.02)


@pytest.fixture(scope="module")
def rocketbox_transfer(tmp_path_factory, rocketbox):
    """ICT -> a Rocketbox with UVs (written to a GLB with its layout), 30 frames, both outputs."""
    import json
    import shutil

    from core.cli import main
    from core.io.gltf import write_rig
    from core.model import Rig
    from datapaths import LAYOUTS, PERFORMANCES, RIGS

    d = tmp_path_factory.mktemp("carry")
    rb = rocketbox
    uv = (rb.neutral[:, :2] - rb.neutral[:, :2].min(0)) / np.ptp(rb.neutral[:, :2], 0)
    write_rig(d / "rb_uv.glb", Rig(rb.neutral, rb.faces, rb.deltas, rb.names, uv, "m", "rb_uv"))
    lay = json.loads((LAYOUTS / "rocketbox_female_adult_02.json").read_text())
    lay["rig"] = "rb_uv.glb"
    (d / "rb_uv.layout.json").write_text(json.dumps(lay))
    out = {}
    for mode in ("target", "source"):
        path = d / f"{mode}.glb"
        assert main(["retarget", "--method", "transfer", "--source", str(PERFORMANCES / "livelinkface_take_s07.csv"),
                     "--source-rig", str(RIGS / "ict_facekit.glb"), "--target-rig", str(d / "rb_uv.glb"),
                     "--target-layout", str(d / "rb_uv.layout.json"), "--last-frame", "29", "--transfer-output", mode,
                     "--no-transfer-icp", "--out", str(path), "--quiet"]) == 0
        out[mode] = path
    return out, uv


@pytest.mark.slow
def test_transfer_glb_is_the_targets_own_mesh(rocketbox_transfer, rocketbox, ict):
    """The GLB holds Rocketbox's vertices, faces and UVs and re-opens; its morph targets are
    the fitted-source ones carried back: on the part of the target the fitted source surface
    covers (within 0.5 % of the size) each carried delta is the interpolated transferred one,
    and a fitted source vertex lying on the target sees the carried deltas interpolate back to
    its own delta (interpolation error of the two samplings: median below 3 %, p95 below 15 %
    of each basis's largest delta); target vertices outside the face have exactly zero deltas."""
    from core.geometry import ClosestPoints
    from core.io.gltf import read_rig

    paths, uv = rocketbox_transfer
    tgt, src = read_rig(paths["target"]), read_rig(paths["source"])
    rb = rocketbox
    assert tgt.n_vertices == rb.n_vertices and np.array_equal(tgt.faces, rb.faces)
    np.testing.assert_allclose(tgt.neutral, rb.neutral, atol=1e-7)
    np.testing.assert_allclose(tgt.uvs, uv, atol=1e-7)
    assert src.n_vertices == ict.n_vertices and tgt.names == src.names and any(n.startswith("xu_detail") for n in tgt.names)
    from core.pipeline import Pipeline
    from datapaths import PERFORMANCES, RIGS

    pipe = Pipeline(source=str(PERFORMANCES / "livelinkface_take_s07.csv"), source_rig=str(RIGS / "ict_facekit.glb"),
                    target_rig=str(paths["target"].parent / "rb_uv.glb"), method="transfer", last_frame=29, transfer_icp=False,
                    target_layout=str(paths["target"].parent / "rb_uv.layout.json"))
    c = pipe.results(["dense_output"])["dense_output"]["carry"]
    top = np.abs(src.deltas).max()
    assert top > 1e-4
    # the GLB's morph targets are the carried ones (float32 in the file)
    np.testing.assert_allclose(tgt.deltas, c.apply(src.deltas), rtol=0, atol=1e-6 * top)
    outside = c.weight == 0
    assert outside.sum() > 100 and (tgt.deltas[:, outside] == 0).all()
    # the other way round: source vertices on the target, the target's carried deltas there
    _, dist, tri, bary = ClosestPoints(rb.neutral, rb.faces).query(src.neutral)
    on = dist < 1e-6 * rb.size
    inside = c.weight[rb.faces[tri]].min(1) == 1
    sel = on & inside
    assert sel.mean() > 0.15  # (the face crop is 37 % of ICT)
    bases = [i for i, n in enumerate(tgt.names) if n.startswith("xu_basis")]
    back = np.einsum("vj,svjc->svc", bary[sel], tgt.deltas[bases][:, rb.faces[tri[sel]]])
    want = src.deltas[bases][:, sel]
    rel = np.linalg.norm(back - want, axis=-1) / np.linalg.norm(src.deltas[bases], axis=-1).max(axis=1)[:, None]
    # measured (similarity-only registration, 7 bases up to 4.6 mm): median 1.4 %, p95 7.7 % of
    # each basis's largest delta (0.04 / 0.21 mm): the coarse Rocketbox triangles (5-10 mm)
    # interpolating ICT's finer field at the lips and lids
    assert np.median(rel) < 0.03 and np.percentile(rel, 95) < 0.15



@pytest.mark.slow
def test_switching_the_output_mesh_reruns_only_dense_output():
    from core.pipeline import Pipeline
    from datapaths import PERFORMANCES, RIGS

    pipe = Pipeline(source=str(PERFORMANCES / "livelinkface_take_s07.csv"), source_rig=str(RIGS / "ict_facekit.glb"),
                    target_rig=str(RIGS / "rocketbox_female_adult_02.glb"), method="transfer", last_frame=9, transfer_icp=False)
    a = pipe.results(["dense_output"])["dense_output"]
    before = dict(pipe.runs)
    pipe.configure(transfer_output="source")
    b = pipe.results(["dense_output"])["dense_output"]
    ran = {k for k, v in pipe.runs.items() if v > before.get(k, 0)}
    assert ran == {"dense_output"}
    assert a["mesh"] == "target" and a["rig"].n_vertices == 2458 and b["rig"].n_vertices == 14629
    assert a["rig"].names == b["rig"].names and np.array_equal(a["weights"], b["weights"])
