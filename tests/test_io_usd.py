"""USD in and out (core.io.usd): our UsdSkel layout read back by usd-core's own UsdSkel code and
passed by usdchecker's compliance checks; a file laid out the way a DCC writes it (Z-up,
centimetres, a transform, quads, offsets with and without pointIndices, an inbetween,
faceVarying UVs); time-sampled mesh sequences; the error without usd-core."""

import sys
import warnings

import numpy as np
import pytest

pxr = pytest.importorskip("pxr", reason="usd-core (pip install face-retarget[usd])")

from datapaths import RIGS  # noqa: E402

from core.io import usd  # noqa: E402
from core.io.gltf import read_rig as read_glb  # noqa: E402
from core.io.performance import read_performance  # noqa: E402
from core.io.rigs import load_rig  # noqa: E402
from core.model import Performance, Rig  # noqa: E402


@pytest.fixture(scope="module")
def tiger():
    return read_glb(RIGS / "jeeliz_tiger.glb")


def _weights(T, K, seed=0):
    return np.random.default_rng(seed).random((T, K))


def usdskel_points(path, t):
    """Points of the first skinned mesh at time code ``t`` as UsdSkel itself deforms them
    (UsdSkelBlendShapeQuery on the weights the AnimQuery gives): an independent reader."""
    from pxr import Usd, UsdGeom, UsdSkel

    stage = Usd.Stage.Open(str(path))
    cache = UsdSkel.Cache()
    root = UsdSkel.Root(stage.GetDefaultPrim())
    cache.Populate(root, Usd.TraverseInstanceProxies())
    binding = cache.ComputeSkelBindings(root, Usd.TraverseInstanceProxies())[0]
    skel = cache.GetSkelQuery(binding.GetSkeleton())
    target = binding.GetSkinningTargets()[0]
    shapes = UsdSkel.BlendShapeQuery(UsdSkel.BindingAPI(target.GetPrim()))
    w = skel.GetAnimQuery().ComputeBlendShapeWeights(Usd.TimeCode(t))
    mapper = target.GetBlendShapeMapper()
    w = w if mapper is None or mapper.IsNull() else mapper.Remap(w)
    sub, shape_idx, sub_idx = shapes.ComputeSubShapeWeights(w)
    pts = UsdGeom.Mesh(target.GetPrim()).GetPointsAttr().Get()
    shapes.ComputeDeformedPoints(sub, shape_idx, sub_idx, shapes.ComputeBlendShapePointIndices(),
                                 shapes.ComputeSubShapePointOffsets(), pts)
    return np.array(pts, dtype=np.float64)


@pytest.mark.parametrize("suffix", [".usda", ".usdc", ".usdz"])
def test_rig_and_animation_round_trip_pass_the_compliance_checker(tmp_path, tiger, suffix):
    W = _weights(25, tiger.n_shapes)
    path = usd.write_rig(tmp_path / f"tiger{suffix}", tiger, weights=W, fps=30.0)
    report = usd.check_usd(path)
    assert report["errors"] == [], report
    rig, anim = usd.read_rig(path), usd.read_animation(path)
    # float32 storage: the rig's values are float32 already (read from a GLB), so exact
    np.testing.assert_array_equal(rig.neutral, tiger.neutral)
    np.testing.assert_array_equal(rig.deltas, tiger.deltas)
    np.testing.assert_array_equal(rig.faces, tiger.faces)
    assert rig.names == tiger.names and anim.names == tiger.names
    np.testing.assert_array_equal(anim.data, W.astype(np.float32))
    assert anim.fps == 30.0 and anim.n_frames == 25
    np.testing.assert_allclose(anim.times, np.arange(25) / 30.0, rtol=0, atol=1e-12)
    # usd-core's own blend shape code plays the same meshes
    for t in (0, 7, 24):
        np.testing.assert_allclose(usdskel_points(path, t), tiger.evaluate(W[t].astype(np.float32)), rtol=0,
                                   atol=1e-6 * tiger.size)
    # the layout DCCs look for
    from pxr import Usd, UsdGeom, UsdSkel

    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(stage) == "Y" and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetTimeCodesPerSecond() == 30 and (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0, 24)
    mesh = next(p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh))
    binding = UsdSkel.BindingAPI(mesh)
    assert mesh.HasAPI(UsdSkel.BindingAPI) and len(binding.GetBlendShapeTargetsRel().GetTargets()) == tiger.n_shapes
    skel = binding.GetSkeleton()
    assert skel and list(skel.GetJointsAttr().Get()) == ["root"]
    assert UsdSkel.BindingAPI(skel.GetPrim()).GetAnimationSource()
    for k, tp in enumerate(binding.GetBlendShapeTargetsRel().GetTargets()):  # only the moving vertices
        idx = np.asarray(UsdSkel.BlendShape(stage.GetPrimAtPath(tp)).GetPointIndicesAttr().Get())
        moving = np.flatnonzero(np.abs(tiger.deltas[k]).max(1) > 0)
        np.testing.assert_array_equal(idx, moving if len(moving) else [0])


def test_uvs_normals_odd_names_and_an_empty_shape(tmp_path):
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.0]])
    F = np.array([[0, 1, 2], [1, 3, 2]])
    D = np.zeros((3, 4, 3))
    D[0, 3] = (0, 0, 0.5)
    D[2, 0] = (0.1, 0, 0)
    rig = Rig(V, F, D, ["jaw open", "empty", "1st.shape"], uvs=V[:, :2], name="quad head")
    path = usd.write_rig(tmp_path / "q.usda", rig, weights=np.eye(3), fps=24.0)
    assert usd.check_usd(path)["errors"] == []
    back = usd.read_rig(path)
    assert back.names == rig.names  # tokens keep any spelling; prims get valid identifiers
    np.testing.assert_array_equal(back.uvs, rig.uvs)
    np.testing.assert_array_equal(back.deltas, rig.deltas.astype(np.float32))  # the empty shape: one zero offset, still empty
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(path))
    mesh = UsdGeom.Mesh(next(p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)))
    np.testing.assert_allclose(np.asarray(mesh.GetNormalsAttr().Get()), [[0, 0, 1]] * 4, atol=1e-7)
    assert usd.read_animation(path).fps == 24.0


def _dcc_file(path):
    """A UsdSkel file as a DCC lays it out, written with plain usd-core calls: Z-up, centimetres,
    the mesh under a translated Xform, a quad, one BlendShape without pointIndices and one with
    them plus an inbetween, faceVarying UVs, an animation whose blendShapes are in another order
    and sampled every other time code at 60 time codes per second."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel, Vt

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    stage.SetTimeCodesPerSecond(60)
    root = UsdSkel.Root.Define(stage, "/Character")
    stage.SetDefaultPrim(root.GetPrim())
    xf = UsdGeom.Xform.Define(stage, "/Character/Geo")
    xf.AddTranslateOp().Set(Gf.Vec3d(0, 0, 100))  # 100 cm up (+Z)
    mesh = UsdGeom.Mesh.Define(stage, "/Character/Geo/Head")
    mesh.CreatePointsAttr(Vt.Vec3fArray([(0, 0, 0), (10, 0, 0), (10, 0, 10), (0, 0, 10), (5, -5, 5)]))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([4, 3]))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray([0, 1, 2, 3, 0, 4, 1]))
    st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying)
    st.Set(Vt.Vec2fArray([(0, 0), (1, 0), (1, 1), (0, 1), (0, 0), (0.5, 0.5), (1, 0)]))
    skel = UsdSkel.Skeleton.Define(stage, "/Character/Skel")
    skel.CreateJointsAttr(Vt.TokenArray(["Root"]))
    skel.CreateBindTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1)]))
    skel.CreateRestTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1)]))
    anim = UsdSkel.Animation.Define(stage, "/Character/Skel/Anim")
    UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([anim.GetPath()])
    b = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    b.CreateSkeletonRel().SetTargets([skel.GetPath()])
    full = UsdSkel.BlendShape.Define(stage, "/Character/Geo/Head/Raise")
    full.CreateOffsetsAttr(Vt.Vec3fArray([(0, 0, 1)] * 5))  # every point, no pointIndices
    smile = UsdSkel.BlendShape.Define(stage, "/Character/Geo/Head/Smile")
    smile.CreateOffsetsAttr(Vt.Vec3fArray([(2, 0, 0)]))
    smile.CreatePointIndicesAttr(Vt.IntArray([4]))
    half = smile.CreateInbetween("half")
    half.SetWeight(0.5)
    half.SetOffsets(Vt.Vec3fArray([(0.5, 0, 0)]))
    b.CreateBlendShapesAttr(Vt.TokenArray(["raise", "smile_L"]))
    b.CreateBlendShapeTargetsRel().SetTargets([full.GetPath(), smile.GetPath()])
    anim.CreateBlendShapesAttr(Vt.TokenArray(["smile_L", "raise"]))
    w = anim.CreateBlendShapeWeightsAttr()
    for i, t in enumerate(range(10, 30, 2)):
        w.Set(Vt.FloatArray([i / 10, 1 - i / 10]), Usd.TimeCode(t))
    stage.Save()


def test_reads_a_dcc_style_file(tmp_path):
    path = tmp_path / "dcc.usda"
    _dcc_file(path)
    with pytest.warns(usd.InbetweenIgnored, match="inbetween shapes of 1 blend shapes ignored .*smile_L"):
        rig = load_rig(path)  # dispatch by suffix
    assert rig.names == ("raise", "smile_L") and rig.units == "cm"
    # metres, +Y up: (x, y, z)_zup -> (x, z, -y), plus the 100 cm lift along +Z (-> +Y)
    np.testing.assert_allclose(rig.neutral[1], [0.1, 1.0, 0.0], atol=1e-7)
    np.testing.assert_allclose(rig.neutral[4], [0.05, 1.05, 0.05], atol=1e-7)
    np.testing.assert_allclose(rig.deltas[0], [[0, 0.01, 0]] * 5, atol=1e-9)  # offsets: linear part only
    np.testing.assert_allclose(rig.deltas[1, 4], [0.02, 0, 0], atol=1e-9)
    assert not rig.deltas[1, :4].any()
    np.testing.assert_array_equal(rig.faces, [[0, 1, 2], [0, 2, 3], [0, 4, 1]])  # the quad fanned
    np.testing.assert_allclose(rig.uvs[4], [0.5, 0.5])
    perf = read_performance(path)
    assert perf.kind == "curves" and perf.names == ("smile_L", "raise")
    assert perf.n_frames == 10 and perf.fps == 30.0  # every 2nd of 60 time codes per second
    np.testing.assert_allclose(perf.times, np.arange(10) / 30.0)
    np.testing.assert_allclose(perf.data[3], [0.3, 0.7], atol=1e-7)
    # the same file as a dense sequence: the rig played by its animation
    with pytest.warns(usd.InbetweenIgnored):
        seq = read_performance(path, kind="meshes")
    assert seq.kind == "meshes" and seq.data.shape == (10, 5, 3)
    np.testing.assert_allclose(seq.data[3], rig.evaluate([0.7, 0.3]), atol=1e-9)


def test_mesh_sequence_round_trip_and_a_changing_vertex_count_is_named(tmp_path, tiger):
    T = 6
    frames = tiger.evaluate(_weights(T, tiger.n_shapes, seed=3))
    perf = Performance.meshes(frames, 25.0, faces=tiger.faces, name="take")
    path = usd.write_mesh_sequence(tmp_path / "seq.usdc", perf)
    assert usd.check_usd(path)["errors"] == []
    back = read_performance(path)  # no SkelAnimation: the time-sampled mesh
    assert back.kind == "meshes" and back.fps == 25.0
    np.testing.assert_array_equal(back.extras["faces"], tiger.faces)
    np.testing.assert_allclose(back.data, frames, rtol=0, atol=1e-7 * tiger.size * 10)
    assert read_performance(path, fps=50).fps == 50

    from pxr import Usd, UsdGeom, Vt

    stage = Usd.Stage.Open(str(path))
    pts = UsdGeom.Mesh(next(p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh))).GetPointsAttr()
    pts.Set(Vt.Vec3fArray.FromNumpy(frames[4, :-1].astype(np.float32)), Usd.TimeCode(4))
    stage.GetRootLayer().Export(str(tmp_path / "bad.usda"))
    with pytest.raises(usd.UsdError, match=r"bad\.usda: .*points at time code 4 has 2099 vertices.*time code 0\) has 2100"):
        read_performance(tmp_path / "bad.usda")


def test_bad_files_name_the_problem(tmp_path, tiger):
    with pytest.raises(FileNotFoundError, match="nope.usda"):
        usd.read_rig(tmp_path / "nope.usda")
    (tmp_path / "junk.usda").write_text("#usda 1.0\ndef Mesh \"M\" {\n")
    with pytest.raises(usd.UsdError, match=r"junk\.usda: not a readable USD file"):
        usd.read_rig(tmp_path / "junk.usda")
    path = usd.write_mesh_sequence(tmp_path / "seq.usda", Performance.meshes(tiger.evaluate(np.zeros((2, 11))), 30, faces=tiger.faces))
    with pytest.raises(usd.UsdError, match=r"no Mesh with skel:blendShapeTargets.*mesh sequence"):
        usd.read_rig(path)
    with pytest.raises(usd.UsdError, match="no SkelAnimation with blendShapeWeights"):
        usd.read_animation(path)
    with pytest.raises(ValueError, match=r"must end in one of \.usd, \.usda, \.usdc, \.usdz"):
        usd.write_rig(tmp_path / "x.fbx", tiger)


def test_without_usd_core_the_error_names_the_extra(tmp_path, monkeypatch, tiger):
    monkeypatch.setitem(sys.modules, "pxr", None)  # import pxr now raises ImportError
    with pytest.raises(ImportError, match=r"face-retarget\[usd\]"):
        usd.write_rig(tmp_path / "x.usda", tiger)
    with pytest.raises(ImportError, match=r"face-retarget\[usd\]"):
        (tmp_path / "y.usda").write_text("#usda 1.0\n")
        load_rig(tmp_path / "y.usda")


def test_ict_with_uvs_round_trips(tmp_path, ict):
    path = usd.write_rig(tmp_path / "ict.usdc", ict, normals=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        back = usd.read_rig(path)
    np.testing.assert_array_equal(back.neutral, ict.neutral)
    np.testing.assert_array_equal(back.deltas, ict.deltas)
    np.testing.assert_array_equal(back.uvs, ict.uvs.astype(np.float32))
    assert back.names == ict.names


def test_the_checker_reports_a_noncompliant_file(tmp_path):
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.CreateNew(str(tmp_path / "bare.usda"))  # no defaultPrim, upAxis, metersPerUnit
    UsdGeom.Mesh.Define(stage, "/M")
    stage.Save()
    report = usd.check_usd(tmp_path / "bare.usda")
    assert report["errors"] and any("defaultPrim" in e or "default prim" in e.lower() for e in report["errors"])
