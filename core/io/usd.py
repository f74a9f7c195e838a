"""USD: UsdSkel blendshape rigs and weight animations, and time-sampled mesh sequences.

Studios move facial animation as USD: NVIDIA Audio2Face exports UsdSkel blendshape animation,
and Omniverse, Maya (mayaUSD), Houdini (Solaris), Blender and Unreal read it. Reading and
writing go through Pixar's ``usd-core`` (``pip install face-retarget[usd]``), imported inside the
functions that need it; without it they raise an ImportError naming the extra.

What :func:`write_rig` writes (``.usda`` text, ``.usdc`` crate, ``.usdz`` package of a ``.usdc``),
laid out as the UsdSkel schema documentation's blendshape example and the importers of Blender
(``io/usd/intern/usd_skel_convert.cc``) and Unreal expect::

    #usda 1.0
    (defaultPrim = "<rig>", upAxis = "Y", metersPerUnit = 1,
     timeCodesPerSecond = fps, framesPerSecond = fps, startTimeCode = 0, endTimeCode = T - 1)

    def SkelRoot "<rig>"
        def Skeleton "Skeleton" (apiSchemas = ["SkelBindingAPI"])
            uniform token[] joints = ["root"]            # one joint: DCCs build an armature
            uniform matrix4d[] bindTransforms / restTransforms = [identity]
            rel skel:animationSource = </<rig>/Animation>
        def SkelAnimation "Animation"                    # only with weights
            uniform token[] joints = ["root"]; translations, rotations, scales: the identity
            uniform token[] blendShapes = [<shape names>]
            float[] blendShapeWeights.timeSamples = {0: [...], 1: [...], ...}
        def Mesh "<rig>_mesh" (apiSchemas = ["SkelBindingAPI"])
            point3f[] points; int[] faceVertexCounts (all 3); int[] faceVertexIndices; extent
            normal3f[] normals (vertex); texCoord2f[] primvars:st (vertex, when the rig has UVs)
            primvars:skel:jointIndices = [0], primvars:skel:jointWeights = [1] (constant: rigid on root)
            matrix4d primvars:skel:geomBindTransform = identity
            uniform token[] skel:blendShapes = [<shape names>]
            rel skel:blendShapeTargets = [<one BlendShape prim per shape>]
            rel skel:skeleton = </<rig>/Skeleton>
            def BlendShape "<shape>"
                uniform vector3f[] offsets          # the delta of each moving vertex
                uniform int[] pointIndices          # the moving vertices only
                uniform vector3f[] normalOffsets    # normal change at those vertices

Shape names are the ``skel:blendShapes`` / ``blendShapes`` tokens (any spelling is kept); the
BlendShape prims get valid, unique identifiers made from them. A shape that moves no vertex is
written with one zero offset at vertex 0 (Blender drops a BlendShape whose offsets are empty, and
with it the shape key its curve drives). Positions, offsets and weights are float32; time code
``i`` is frame ``i`` of the take (``t_i * fps``), so a DCC puts the keys on its frames.

What the readers take from any UsdSkel file (ours, a DCC's, Audio2Face's):

* :func:`read_rig` — the first Mesh with ``skel:blendShapeTargets`` (or ``mesh=``): points at
  the default time (else the first sample), polygons fan-triangulated (``leftHanded`` winding
  flipped), the mesh's local-to-world transform, ``metersPerUnit`` (to metres) and
  ``upAxis = "Z"`` (rotated to +Y up, the house frame) applied; offsets with or without
  ``pointIndices``; inbetween shapes ignored with a warning (a Rig is linear); UVs from
  ``primvars:st`` (vertex, or faceVarying when every corner of a vertex agrees).
* :func:`read_animation` — a SkelAnimation's ``blendShapeWeights`` samples as a curves
  Performance (channels = its ``blendShapes`` tokens), times ``(t - t_0) / timeCodesPerSecond``.
* :func:`read_mesh_sequence` — a Mesh with time-sampled ``points`` as a meshes Performance
  (T, V, 3) with ``extras["faces"]``; every sample must have the same vertex count and topology
  (the error names the file and the time code that differ). ``kind="meshes"`` on a UsdSkel file
  evaluates the rig with its animation instead.

:func:`check_usd` runs the compliance checks ``usdchecker`` runs.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import warnings
from pathlib import Path
from types import SimpleNamespace
from typing import Optional

import numpy as np

from ..model import UNIT_SCALE, Performance, Rig
from .gltf import _animation_inputs, vertex_normals
from .tabular import DataQualityWarning, estimate_fps

#: suffixes read and written as USD
SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")

#: the one joint of the written Skeleton
ROOT_JOINT = "root"


class UsdError(ValueError):
    """A USD file that cannot be read as a rig, animation or mesh sequence; the message names the
    file, the prim and what is wrong."""


class InbetweenIgnored(UserWarning):
    """A BlendShape had inbetween shapes; a linear Rig keeps only the full shape."""


def _pxr():
    """The pxr modules, or an ImportError that names the extra to install."""
    try:
        from pxr import Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, UsdUtils, Vt
    except ImportError as e:
        raise ImportError(
            f"USD files need Pixar's usd-core: pip install 'face-retarget[usd]' (or pip install usd-core); ({e})"
        ) from None
    return Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, UsdUtils, Vt


def _check_suffix(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise ValueError(f"path: {path} must end in one of {', '.join(SUFFIXES)}")
    return suffix


# ---------------------------------------------------------------------------------------
# writing
# ---------------------------------------------------------------------------------------


def _identifiers(names, Tf) -> list:
    """Valid, unique prim names for ``names`` (``Tf.MakeValidIdentifier``, ``_2``... on clashes)."""
    out, seen = [], set()
    for n in names:
        base = Tf.MakeValidIdentifier(str(n)) or "shape"
        ident, k = base, 2
        while ident in seen:
            ident, k = f"{base}_{k}", k + 1
        seen.add(ident)
        out.append(ident)
    return out


def _time_codes(times: np.ndarray, fps: float) -> np.ndarray:
    """Time codes ``t * fps``, snapped to whole frames where within 1e-4 of one."""
    tc = np.asarray(times, dtype=np.float64) * fps
    near = np.rint(tc)
    return np.where(np.abs(tc - near) < 1e-4, near, tc)


def _stage_metadata(stage, root_path: str, fps: float, tc: Optional[np.ndarray], UsdGeom):
    stage.SetDefaultPrim(stage.GetPrimAtPath(root_path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetTimeCodesPerSecond(float(fps))
    stage.SetFramesPerSecond(float(fps))
    if tc is not None and len(tc):
        stage.SetStartTimeCode(float(tc[0]))
        stage.SetEndTimeCode(float(tc[-1]))


def _define_mesh(stage, path: str, rig_like, normals: bool, UsdGeom, Vt, Gf, points: bool = True):
    """A Mesh prim with ``rig_like``'s triangles, and (``points``) its neutral as the points' default
    value with normals and UVs; returns it."""
    mesh = UsdGeom.Mesh.Define(stage, path)
    neutral = np.asarray(rig_like.neutral, dtype=np.float64)
    faces = np.asarray(rig_like.faces, dtype=np.int64)
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)  # a face scan is a polygon mesh, not a cage
    mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, dtype=np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.reshape(-1).astype(np.int32)))
    if points:
        p32 = neutral.astype(np.float32)
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(p32))
        lo, hi = (p32.min(0), p32.max(0)) if len(p32) else (np.zeros(3, np.float32),) * 2
        mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]))
    if normals and points and len(faces):
        n = vertex_normals(neutral, faces).astype(np.float32)
        mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(n))
        mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    uvs = getattr(rig_like, "uvs", None)
    if uvs is not None:
        pv = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", _sdf().ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex)
        pv.Set(Vt.Vec2fArray.FromNumpy(np.asarray(uvs, dtype=np.float32)))
    return mesh


def _sdf():
    from pxr import Sdf

    return Sdf


def _save(stage_layer, path: Path, suffix: str, UsdUtils, Sdf) -> None:
    """Export the layer to ``path`` through a temporary file (``.usdz``: a package of a ``.usdc``)."""
    tmpdir = Path(tempfile.mkdtemp(prefix=".usd-", dir=path.parent))
    try:
        if suffix == ".usdz":
            inner = tmpdir / (path.stem + ".usdc")
            if not stage_layer.Export(str(inner)):
                raise OSError(f"{path}: usd-core could not write {inner.name}")
            tmp = tmpdir / path.name
            if not UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(inner)), str(tmp)):
                raise OSError(f"{path}: usd-core could not write the usdz package")
        else:
            tmp = tmpdir / path.name
            if not stage_layer.Export(str(tmp)):
                raise OSError(f"{path}: usd-core could not write the file")
        os.replace(tmp, path)
    finally:
        shutil.rmtree(tmpdir, ignore_errors=True)


def write_rig(path, rig: Rig, weights=None, fps: float = 30.0, times=None, *, normals: bool = True) -> Path:
    """Write ``rig`` (and optionally its weight animation) as a UsdSkel blendshape asset.

    The mesh is ``points + sum_k w_k offsets_k`` at ``pointIndices_k`` (UsdSkel's blend shape
    model, the same delta model as :class:`core.model.Rig`); the layout is in the module docstring.

    Parameters
    ----------
    path : str or Path
        ``.usda`` (text), ``.usdc`` / ``.usd`` (crate), ``.usdz`` (package). Written to a
        temporary file and moved into place.
    rig : Rig
    weights : (T, K) array or Performance of kind "curves", optional
        Weights per frame in ``rig.names`` order (a Performance is matched by channel name and
        its times used, shifted to start at 0). Adds the SkelAnimation with
        ``blendShapeWeights`` sampled at time codes ``t * fps``.
    fps : float
        ``timeCodesPerSecond`` / ``framesPerSecond`` of the stage, and the default times
        ``arange(T) / fps``.
    times : (T,) float, optional
        Key times in seconds, >= 0 and strictly increasing.
    normals : bool
        Write vertex normals and each shape's ``normalOffsets`` at its moving vertices.

    Returns
    -------
    Path written.

    Raises
    ------
    ImportError
        usd-core is not installed (names the ``[usd]`` extra).
    ValueError
        Unknown suffix, weights not (T, K) or not finite, times not increasing.
    """
    path = Path(path)
    suffix = _check_suffix(path)
    if not isinstance(rig, Rig):
        raise TypeError(f"rig: expected a core.model.Rig, got {type(rig).__name__}")
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps: must be positive, got {fps}")
    anim = None if weights is None else _animation_inputs(rig, weights, fps, times)
    Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, UsdUtils, Vt = _pxr()

    layer = Sdf.Layer.CreateAnonymous("face-retarget.usda")
    stage = Usd.Stage.Open(layer)
    root_name = Tf.MakeValidIdentifier(rig.name) or "rig"
    root = f"/{root_name}"
    UsdSkel.Root.Define(stage, root)
    tc = None if anim is None else _time_codes(anim[1].astype(np.float64), fps)
    _stage_metadata(stage, root, fps, tc, UsdGeom)
    stage.GetRootLayer().customLayerData = {"creator": "face-retarget core.io.usd"}

    identity = Gf.Matrix4d(1.0)
    skel = UsdSkel.Skeleton.Define(stage, f"{root}/Skeleton")
    skel.CreateJointsAttr(Vt.TokenArray([ROOT_JOINT]))
    skel.CreateBindTransformsAttr(Vt.Matrix4dArray([identity]))
    skel.CreateRestTransformsAttr(Vt.Matrix4dArray([identity]))

    mesh = _define_mesh(stage, f"{root}/{root_name}_mesh", rig, normals, UsdGeom, Vt, Gf)
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
    binding.CreateJointIndicesPrimvar(constant=True, elementSize=1).Set(Vt.IntArray([0]))
    binding.CreateJointWeightsPrimvar(constant=True, elementSize=1).Set(Vt.FloatArray([1.0]))
    binding.CreateGeomBindTransformAttr(identity)

    if rig.n_shapes:
        vn = None
        if normals and len(rig.faces):
            vn = vertex_normals(np.concatenate([rig.neutral[None], rig.neutral + rig.deltas]), rig.faces)
        idents = _identifiers(rig.names, Tf)
        targets = []
        for k, ident in enumerate(idents):
            bs = UsdSkel.BlendShape.Define(stage, mesh.GetPath().AppendChild(ident))
            d32 = rig.deltas[k].astype(np.float32)
            moving = np.flatnonzero((d32 != 0).any(axis=1))
            if not len(moving):
                moving = np.array([0])  # one zero offset: DCCs drop a BlendShape without offsets
            bs.CreateOffsetsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(d32[moving])))
            bs.CreatePointIndicesAttr(Vt.IntArray.FromNumpy(moving.astype(np.int32)))
            if vn is not None:
                dn = (vn[k + 1] - vn[0])[moving].astype(np.float32)
                bs.CreateNormalOffsetsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(dn)))
            targets.append(bs.GetPath())
        binding.CreateBlendShapesAttr(Vt.TokenArray(list(rig.names)))
        binding.CreateBlendShapeTargetsRel().SetTargets(targets)

    if anim is not None:
        w32, _ = anim
        a = UsdSkel.Animation.Define(stage, f"{root}/Animation")
        a.CreateJointsAttr(Vt.TokenArray([ROOT_JOINT]))
        a.CreateTranslationsAttr(Vt.Vec3fArray([Gf.Vec3f(0, 0, 0)]))
        a.CreateRotationsAttr(Vt.QuatfArray([Gf.Quatf(1, 0, 0, 0)]))
        a.CreateScalesAttr(Vt.Vec3hArray([Gf.Vec3h(1, 1, 1)]))
        a.CreateBlendShapesAttr(Vt.TokenArray(list(rig.names)))
        attr = a.CreateBlendShapeWeightsAttr()
        for t, row in zip(tc.tolist(), w32):
            attr.Set(Vt.FloatArray.FromNumpy(row), Usd.TimeCode(t))
        UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([a.GetPath()])
    _save(stage.GetRootLayer(), path, suffix, UsdUtils, Sdf)
    return path


def write_mesh_sequence(path, perf: Performance, *, normals: bool = False) -> Path:
    """Write a meshes Performance as a Mesh whose ``points`` are sampled at time codes
    ``t * fps`` (what Alembic-to-USD and 4D-capture exports hold); topology from
    ``perf.extras["faces"]``. Invalid frames are not written (no sample at their time code).

    Raises
    ------
    ValueError
        Not a meshes Performance, or it has no ``extras["faces"]``.
    """
    path = Path(path)
    suffix = _check_suffix(path)
    if not isinstance(perf, Performance) or perf.kind != "meshes":
        raise ValueError(f"perf: expected a meshes Performance, got {getattr(perf, 'kind', type(perf).__name__)!r}")
    faces = perf.extras.get("faces")
    if faces is None:
        raise ValueError(f"perf {perf.name!r}: a mesh sequence needs extras['faces'] to be written")
    Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, UsdUtils, Vt = _pxr()
    layer = Sdf.Layer.CreateAnonymous("face-retarget.usda")
    stage = Usd.Stage.Open(layer)
    name = Tf.MakeValidIdentifier(perf.name) or "sequence"
    UsdGeom.Xform.Define(stage, f"/{name}")
    tc = _time_codes(perf.times - perf.times[0], perf.fps)
    _stage_metadata(stage, f"/{name}", perf.fps, tc, UsdGeom)
    first = int(np.flatnonzero(perf.valid)[0]) if perf.valid.any() else 0

    topo = SimpleNamespace(neutral=perf.data[first], faces=np.asarray(faces), uvs=None)
    mesh = _define_mesh(stage, f"/{name}/{name}_mesh", topo, False, UsdGeom, Vt, Gf, points=False)
    pts, ext = mesh.CreatePointsAttr(), mesh.CreateExtentAttr()
    for t, frame, ok in zip(tc.tolist(), perf.data.astype(np.float32), perf.valid.tolist()):
        if not ok:
            continue
        pts.Set(Vt.Vec3fArray.FromNumpy(frame), Usd.TimeCode(t))
        lo, hi = frame.min(0), frame.max(0)
        ext.Set(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]), Usd.TimeCode(t))
    _save(stage.GetRootLayer(), path, suffix, UsdUtils, Sdf)
    return path


# ---------------------------------------------------------------------------------------
# reading
# ---------------------------------------------------------------------------------------


def _open(path):
    """(stage, pxr modules) of ``path``; FileNotFoundError / UsdError naming it."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    if path.is_dir():
        raise UsdError(f"{path}: is a folder, expected a {'/'.join(SUFFIXES)} file")
    _check_suffix(path)
    mods = _pxr()
    Sdf, Usd = mods[1], mods[3]
    layer = Sdf.Layer.Find(str(path))
    if layer:  # a layer still open from an earlier read would hide a rewritten file
        layer.Reload(force=True)
    try:
        stage = Usd.Stage.Open(str(path))
    except Exception as e:  # pxr raises Tf.ErrorException with the parser's message
        raise UsdError(f"{path}: not a readable USD file ({str(e).strip().splitlines()[-1] if str(e).strip() else e})") from None
    if stage is None:
        raise UsdError(f"{path}: not a readable USD file")
    return stage, mods


def _frame_transform(stage, prim, UsdGeom, Usd, time=None) -> tuple[np.ndarray, float, str]:
    """(4x4 row-vector local-to-world incl. the Z-up -> Y-up turn, scale to metres, units name).

    USD matrices act on row vectors (``p' = p M``); metres = ``metersPerUnit`` * units.
    """
    tc = Usd.TimeCode.Default() if time is None else Usd.TimeCode(time)
    M = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(tc), dtype=np.float64) \
        if prim.IsA(UsdGeom.Xformable) else np.eye(4)
    if UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z:  # (x, y, z) -> (x, z, -y): +Z up to +Y up
        M = M @ np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=np.float64)
    mpu = float(UsdGeom.GetStageMetersPerUnit(stage))
    units = next((u for u, s in UNIT_SCALE.items() if abs(s - mpu) <= 1e-9 * s), "m")
    return M, mpu, units


def _apply(M: np.ndarray, mpu: float, points: np.ndarray, linear_only: bool = False) -> np.ndarray:
    out = points @ M[:3, :3]
    if not linear_only:
        out = out + M[3, :3]
    return out * mpu


def _triangles(path, prim, counts: np.ndarray, indices: np.ndarray, V: int, left_handed: bool) -> np.ndarray:
    """Fan triangulation of polygons (``faceVertexCounts`` / ``faceVertexIndices``)."""
    where = f"{path}: {prim.GetPath()}"
    if counts.size and counts.min() < 3:
        bad = int(np.flatnonzero(counts < 3)[0])
        raise UsdError(f"{where}.faceVertexCounts[{bad}] is {counts[bad]}; a face needs at least 3 vertices")
    if counts.sum() != indices.size:
        raise UsdError(f"{where}: faceVertexCounts sum to {counts.sum()} but faceVertexIndices has {indices.size} entries")
    if indices.size and (indices.min() < 0 or indices.max() >= V):
        raise UsdError(f"{where}.faceVertexIndices: indices must lie in [0, {V}), got [{indices.min()}, {indices.max()}]")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    n_tri = counts - 2
    face_of = np.repeat(np.arange(len(counts)), n_tri)
    k = np.arange(n_tri.sum()) - np.repeat(np.cumsum(n_tri) - n_tri, n_tri)  # 0..n-3 within each polygon
    s = starts[face_of]
    tri = np.stack([indices[s], indices[s + k + 1], indices[s + k + 2]], axis=1).astype(np.int64)
    return tri[:, ::-1].copy() if left_handed else tri


def _topology(path, mesh_prim, UsdGeom, time=None):
    """(faces (F, 3), corner vertex ids (sum counts,)) of a Mesh at ``time`` (default: default/first)."""
    from pxr import Usd

    mesh = UsdGeom.Mesh(mesh_prim)
    tc = Usd.TimeCode.Default() if time is None else Usd.TimeCode(time)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(tc) or [], dtype=np.int64)
    indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(tc) or [], dtype=np.int64)
    pts = mesh.GetPointsAttr().Get(tc)
    if pts is None:
        samples = mesh.GetPointsAttr().GetTimeSamples()
        pts = mesh.GetPointsAttr().Get(Usd.TimeCode(samples[0])) if samples else []
    left = mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded
    return _triangles(path, mesh_prim, counts, indices, len(pts), left), counts, indices


def _points(path, mesh_prim, UsdGeom, Usd) -> np.ndarray:
    attr = UsdGeom.Mesh(mesh_prim).GetPointsAttr()
    pts = attr.Get(Usd.TimeCode.Default())
    if pts is None:
        samples = attr.GetTimeSamples()
        if not samples:
            raise UsdError(f"{path}: {mesh_prim.GetPath()}.points has no value")
        pts = attr.Get(Usd.TimeCode(samples[0]))
    return np.asarray(pts, dtype=np.float64).reshape(-1, 3)


def _uvs(path, mesh_prim, counts, indices, V: int, UsdGeom) -> Optional[np.ndarray]:
    """Per-vertex UVs from ``primvars:st`` (or the first texCoord2f primvar), or None."""
    api = UsdGeom.PrimvarsAPI(mesh_prim)
    pv = api.GetPrimvar("st")
    if not pv or not pv.HasValue():
        pv = next((p for p in api.GetPrimvars() if p.HasValue() and str(p.GetTypeName()).startswith("texCoord2")), None)
    if pv is None:
        return None
    vals = pv.ComputeFlattened()
    if vals is None:
        return None
    uv = np.asarray(vals, dtype=np.float64).reshape(-1, 2)
    interp = pv.GetInterpolation()
    if interp in (UsdGeom.Tokens.vertex, UsdGeom.Tokens.varying) and len(uv) == V:
        return uv
    if interp == UsdGeom.Tokens.faceVarying and len(uv) == len(indices):
        per = np.zeros((V, 2))
        per[indices] = uv
        if np.abs(per[indices] - uv).max(initial=0) > 0:
            warnings.warn(f"{path}: {mesh_prim.GetPath()} {pv.GetName()}: vertices have several UVs (seams); "
                          f"a Rig holds one UV per vertex, so the UVs are dropped", stacklevel=3)
            return None
        return per
    return None


def _blendshape_meshes(stage, UsdGeom, UsdSkel) -> list:
    return [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh) and UsdSkel.BindingAPI(p).GetBlendShapeTargetsRel().GetTargets()]


def _pick(path, prims: list, which: Optional[str], what: str):
    if which is not None:
        hit = [p for p in prims if str(p.GetPath()) == str(which) or p.GetName() == str(which)]
        if not hit:
            raise UsdError(f"{path}: no {what} {which!r}; the file has {[str(p.GetPath()) for p in prims]}")
        return hit[0]
    return prims[0]


def has_blendshapes(path) -> bool:
    """Whether a USD file holds a Mesh with UsdSkel blend shapes (a rig :func:`read_rig` reads)."""
    stage, (Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, UsdUtils, Vt) = _open(path)
    return bool(_blendshape_meshes(stage, UsdGeom, UsdSkel))


def read_rig(path, mesh: Optional[str] = None) -> Rig:
    """Read a blendshape rig from a UsdSkel file (see the module docstring for what is read).

    ``deltas[k]`` is BlendShape ``k``'s ``offsets`` scattered to its ``pointIndices`` (all
    points when absent), in ``skel:blendShapes`` order and named by those tokens.

    Parameters
    ----------
    path : str or Path
    mesh : str, optional
        Prim path or name of the mesh (default: the first mesh with blend shape targets).

    Returns
    -------
    Rig in metres, +Y up; ``units`` from ``metersPerUnit`` ("m" when it is no named unit);
    ``extras["usd_mesh"]`` the prim path read.

    Raises
    ------
    ImportError (no usd-core), FileNotFoundError, UsdError naming the file and prim: no mesh
    with blend shapes, blendShapes / blendShapeTargets counts differ, a target that is no
    BlendShape, offsets and pointIndices of different lengths or out of range.
    """
    path = Path(path)
    stage, (Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, UsdUtils, Vt) = _open(path)
    meshes = _blendshape_meshes(stage, UsdGeom, UsdSkel)
    if not meshes:
        n = sum(1 for p in stage.Traverse() if p.IsA(UsdGeom.Mesh))
        raise UsdError(f"{path}: no Mesh with skel:blendShapeTargets (UsdSkelBindingAPI blend shapes); the file has "
                       f"{n} meshes. A mesh with time-sampled points is a mesh sequence: read it with read_mesh_sequence")
    prim = _pick(path, meshes, mesh, "mesh with blend shapes")
    where = f"{path}: {prim.GetPath()}"
    binding = UsdSkel.BindingAPI(prim)
    names = list(binding.GetBlendShapesAttr().Get() or [])
    targets = binding.GetBlendShapeTargetsRel().GetTargets()
    if len(names) != len(targets):
        raise UsdError(f"{where}: skel:blendShapes has {len(names)} names but skel:blendShapeTargets {len(targets)} targets")
    neutral_local = _points(path, prim, UsdGeom, Usd)
    V = len(neutral_local)
    faces, counts, indices = _topology(path, prim, UsdGeom)
    deltas = np.zeros((len(names), V, 3))
    skipped = []
    for k, (name, tp) in enumerate(zip(names, targets)):
        bs = UsdSkel.BlendShape(stage.GetPrimAtPath(tp))
        if not bs:
            raise UsdError(f"{where}: skel:blendShapeTargets[{k}] {tp} is not a BlendShape prim")
        off = np.asarray(bs.GetOffsetsAttr().Get() or [], dtype=np.float64).reshape(-1, 3)
        idx = bs.GetPointIndicesAttr().Get()
        if idx is None or not bs.GetPointIndicesAttr().HasAuthoredValue():
            if len(off) != V:
                raise UsdError(f"{path}: {tp}.offsets has {len(off)} entries and no pointIndices; expected one per point ({V})")
            deltas[k] = off
        else:
            idx = np.asarray(idx, dtype=np.int64)
            if len(idx) != len(off):
                raise UsdError(f"{path}: {tp}: {len(off)} offsets but {len(idx)} pointIndices")
            if idx.size and (idx.min() < 0 or idx.max() >= V):
                raise UsdError(f"{path}: {tp}.pointIndices must lie in [0, {V}), got [{idx.min()}, {idx.max()}]")
            np.add.at(deltas[k], idx, off)
        if bs.GetAuthoredInbetweens():
            skipped.append(str(name))
    if skipped:
        warnings.warn(f"{where}: inbetween shapes of {len(skipped)} blend shapes ignored ({', '.join(skipped[:6])}"
                      f"{' ...' if len(skipped) > 6 else ''}): a Rig is linear in each weight", InbetweenIgnored, stacklevel=2)
    M, mpu, units = _frame_transform(stage, prim, UsdGeom, Usd)
    uvs = _uvs(path, prim, counts, indices, V, UsdGeom)
    neutral = _apply(M, mpu, neutral_local)
    deltas = _apply(M, mpu, deltas, linear_only=True)
    if np.linalg.det(M[:3, :3]) < 0:  # a mirroring transform turns the winding
        faces = faces[:, ::-1].copy()
    root = stage.GetDefaultPrim()
    label = root.GetName() if root else path.stem
    try:
        return Rig(neutral, faces, deltas, [str(n) for n in names], uvs, units, label, {"usd_mesh": str(prim.GetPath())})
    except ValueError as e:
        raise UsdError(f"{where}: {e}") from None


def _animations(stage, UsdSkel) -> list:
    return [p for p in stage.Traverse() if p.IsA(UsdSkel.Animation)]


def _bound_animation(stage, UsdSkel, mesh_prim):
    """The SkelAnimation the mesh's skeleton (``skel:skeleton``, inherited) binds, or None."""
    skel = UsdSkel.BindingAPI(mesh_prim).GetInheritedSkeleton()
    if not skel:
        return None
    b = UsdSkel.BindingAPI(skel.GetPrim())
    src = b.GetInheritedAnimationSource()
    if not src:
        targets = b.GetAnimationSourceRel().GetTargets() if b.GetAnimationSourceRel() else []
        src = stage.GetPrimAtPath(targets[0]) if targets else None
    return src if src and src.IsA(UsdSkel.Animation) else None


def _sample_times(attr) -> list:
    return list(attr.GetTimeSamples())


def _fps_of(stage, tc: np.ndarray, where: str) -> float:
    tcps = float(stage.GetTimeCodesPerSecond())
    if len(tc) < 2:
        return tcps
    step = np.diff(tc)
    if np.allclose(step, step[0], rtol=0, atol=1e-6):
        return tcps / float(step[0])
    return estimate_fps((tc - tc[0]) / tcps, where, snap="whole")


def read_animation(path, animation: Optional[str] = None) -> Performance:
    """Read a SkelAnimation's blend shape weights as curves.

    The animation is ``animation`` (prim path or name), else the one bound (through the
    skeleton's ``skel:animationSource``) to the first mesh with blend shapes, else the first
    SkelAnimation with ``blendShapeWeights``. Each time sample is a frame; ``times`` are
    ``(t - t_0) / timeCodesPerSecond`` seconds; ``fps`` is ``timeCodesPerSecond / step`` for
    evenly spaced samples, else estimated (:func:`core.io.tabular.estimate_fps`, ``"whole"``).
    A value with no time samples is a single frame.

    Returns
    -------
    Performance, kind "curves", channels = the animation's ``blendShapes`` tokens,
    ``extras["time_codes"]`` (T,) and ``extras["usd_animation"]`` the prim path.

    Raises
    ------
    ImportError, FileNotFoundError; UsdError naming file and prim: no SkelAnimation with
    blendShapeWeights, a sample whose length is not the number of blendShapes.
    """
    path = Path(path)
    stage, (Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, UsdUtils, Vt) = _open(path)
    anims = [p for p in _animations(stage, UsdSkel) if UsdSkel.Animation(p).GetBlendShapeWeightsAttr().HasValue()]
    if not anims:
        raise UsdError(f"{path}: no SkelAnimation with blendShapeWeights (a UsdSkel blend shape animation)")
    if animation is None:
        meshes = _blendshape_meshes(stage, UsdGeom, UsdSkel)
        bound = _bound_animation(stage, UsdSkel, meshes[0]) if meshes else None
        prim = bound if bound is not None and bound in anims else anims[0]
    else:
        prim = _pick(path, anims, animation, "SkelAnimation with blendShapeWeights")
    a = UsdSkel.Animation(prim)
    where = f"{path}: {prim.GetPath()}"
    names = [str(n) for n in (a.GetBlendShapesAttr().Get() or [])]
    attr = a.GetBlendShapeWeightsAttr()
    tcs = _sample_times(attr)
    if not tcs:
        rows = [attr.Get(Usd.TimeCode.Default())]
        tcs = [0.0]
    else:
        rows = [attr.Get(Usd.TimeCode(t)) for t in tcs]
    data = np.empty((len(rows), len(names)))
    for i, (t, r) in enumerate(zip(tcs, rows)):
        r = np.asarray(r if r is not None else [], dtype=np.float64)
        if r.shape != (len(names),):
            raise UsdError(f"{where}.blendShapeWeights at time code {t:g} has {r.size} weights for {len(names)} blendShapes")
        data[i] = r
    tc = np.asarray(tcs, dtype=np.float64)
    fps = _fps_of(stage, tc, f"{where}.blendShapeWeights time codes")
    times = (tc - tc[0]) / float(stage.GetTimeCodesPerSecond())
    try:
        return Performance.curves(data, names, fps, times=times, name=prim.GetName() if animation else path.stem,
                                  extras={"time_codes": tc, "usd_animation": str(prim.GetPath())})
    except ValueError as e:
        raise UsdError(f"{where}: {e}") from None


def read_mesh_sequence(path, mesh: Optional[str] = None, fps: Optional[float] = None) -> Performance:
    """Read a Mesh with time-sampled ``points`` as a mesh sequence (T, V, 3).

    The mesh is ``mesh`` (prim path or name), else the first Mesh whose points have more than
    one time sample. A UsdSkel file without such a mesh (blend shapes + a SkelAnimation) is
    evaluated instead: ``neutral + w_t @ deltas`` per animation sample, as
    :func:`read_rig` and :func:`read_animation` read them. Positions are in metres, +Y up, with
    the mesh's transform at each sample.

    Parameters
    ----------
    fps : float, optional
        Overrides the rate derived from the time codes.

    Returns
    -------
    Performance of kind "meshes", ``extras["faces"]`` (F, 3) the shared topology,
    ``extras["time_codes"]`` (T,).

    Raises
    ------
    UsdError naming the file, prim and time code: a sample with another vertex count, a
    time-sampled topology that changes, no mesh sequence and no blend shape animation.
    """
    path = Path(path)
    stage, (Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, UsdUtils, Vt) = _open(path)
    sampled = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh) and UsdGeom.Mesh(p).GetPointsAttr().GetNumTimeSamples() > 1]
    if not sampled and mesh is None and _blendshape_meshes(stage, UsdGeom, UsdSkel) and _animations(stage, UsdSkel):
        rig, curves = read_rig(path), read_animation(path)
        missing = [n for n in rig.names if n not in curves.names]
        W = np.zeros((curves.n_frames, rig.n_shapes))
        for k, n in enumerate(rig.names):
            if n in curves.names:
                W[:, k] = curves.data[:, curves.names.index(n)]
        if missing:
            warnings.warn(f"{path}: blend shapes {missing[:6]} have no animated weight; held at 0", DataQualityWarning, stacklevel=2)
        return Performance.meshes(rig.evaluate(W), fps or curves.fps, faces=rig.faces, times=curves.times,
                                  units=rig.units, name=path.stem, extras={"time_codes": curves.extras["time_codes"]})
    if not sampled:
        raise UsdError(f"{path}: no Mesh with time-sampled points (a mesh sequence) and no blend shape animation")
    prim = _pick(path, sampled, mesh, "mesh with time-sampled points")
    where = f"{path}: {prim.GetPath()}"
    m = UsdGeom.Mesh(prim)
    tcs = list(m.GetPointsAttr().GetTimeSamples())
    faces, counts, indices = _topology(path, prim, UsdGeom, tcs[0])
    topo_samples = set(m.GetFaceVertexIndicesAttr().GetTimeSamples()) | set(m.GetFaceVertexCountsAttr().GetTimeSamples())
    V = None
    frames = []
    xform_sampled = prim.IsA(UsdGeom.Xformable) and UsdGeom.Xformable(prim).TransformMightBeTimeVarying()
    M, mpu, units = _frame_transform(stage, prim, UsdGeom, Usd, tcs[0])
    for t in tcs:
        p = np.asarray(m.GetPointsAttr().Get(Usd.TimeCode(t)), dtype=np.float64).reshape(-1, 3)
        if V is None:
            V = len(p)
        elif len(p) != V:
            raise UsdError(f"{where}.points at time code {t:g} has {len(p)} vertices, the first sample "
                           f"(time code {tcs[0]:g}) has {V}; a mesh sequence needs the same vertices in every frame")
        if topo_samples:
            c = np.asarray(m.GetFaceVertexCountsAttr().Get(Usd.TimeCode(t)), dtype=np.int64)
            ix = np.asarray(m.GetFaceVertexIndicesAttr().Get(Usd.TimeCode(t)), dtype=np.int64)
            if not (np.array_equal(c, counts) and np.array_equal(ix, indices)):
                raise UsdError(f"{where}: the faces at time code {t:g} differ from the first sample's "
                               f"(time code {tcs[0]:g}); a mesh sequence needs one topology")
        if xform_sampled:
            M, _, _ = _frame_transform(stage, prim, UsdGeom, Usd, t)
        frames.append(_apply(M, mpu, p))
    if np.linalg.det(M[:3, :3]) < 0:
        faces = faces[:, ::-1].copy()
    tc = np.asarray(tcs, dtype=np.float64)
    rate = fps or _fps_of(stage, tc, f"{where}.points time codes")
    times = (tc - tc[0]) / float(stage.GetTimeCodesPerSecond())
    try:
        return Performance.meshes(np.stack(frames), rate, faces=faces, times=times, units=units, name=path.stem,
                                  extras={"time_codes": tc, "usd_mesh": str(prim.GetPath())})
    except ValueError as e:
        raise UsdError(f"{where}: {e}") from None


def read_performance(path, kind: str = "auto", fps: Optional[float] = None) -> Performance:
    """A performance from a USD file: ``kind="auto"`` reads a blend shape animation as curves
    (:func:`read_animation`) when the file has one, else a mesh with time-sampled points
    (:func:`read_mesh_sequence`); ``"curves"`` / ``"meshes"`` force either (``"meshes"`` on a
    UsdSkel file evaluates its rig with its animation). ``fps`` overrides the file's rate."""
    if kind not in ("auto", "curves", "meshes"):
        raise ValueError(f"kind: expected 'auto', 'curves' or 'meshes' for a USD file, got {kind!r}")
    if kind == "meshes":
        return read_mesh_sequence(path, fps=fps)
    if kind == "auto":
        stage, (Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, UsdUtils, Vt) = _open(path)
        has_anim = any(UsdSkel.Animation(p).GetBlendShapeWeightsAttr().HasValue() for p in _animations(stage, UsdSkel))
        del stage
        if not has_anim:
            return read_mesh_sequence(path, fps=fps)
    perf = read_animation(path)
    if fps:
        perf = Performance.curves(perf.data, perf.names, fps, valid=perf.valid, times=perf.times, name=perf.name,
                                  extras=perf.extras)
    return perf


# ---------------------------------------------------------------------------------------
# compliance
# ---------------------------------------------------------------------------------------


def check_usd(path, arkit: bool = False) -> dict:
    """Run the compliance checks ``usdchecker`` runs on ``path``.

    With a usd-core that has ``UsdUtils.ComplianceChecker`` (up to 25.x) that checker, as
    ``usdchecker`` calls it (``assetLevelChecks``, variants, ``arkit``); with newer usd-core
    (26.x, where usdchecker is built on the validation framework) every registered validator
    but the ``UsdzValidators`` (unless ``arkit``) and the root-package one, as ``usdchecker``
    selects them, plus the usdz package validator for a ``.usdz``.

    Returns
    -------
    dict with ``errors`` and ``warnings`` (lists of the checker's messages), ``checker`` (which
    one ran) and ``usd_version``.
    """
    Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, UsdUtils, Vt = _pxr()
    path = Path(path)
    version = ".".join(map(str, Usd.GetVersion()))
    if hasattr(UsdUtils, "ComplianceChecker"):
        c = UsdUtils.ComplianceChecker(arkit=arkit, skipARKitRootLayerCheck=False, rootPackageOnly=False,
                                       skipVariants=False, verbose=False, assetLevelChecks=True)
        c.CheckCompliance(str(path))
        return {"errors": list(c.GetErrors()) + list(c.GetFailedChecks()), "warnings": list(c.GetWarnings()),
                "checker": "UsdUtils.ComplianceChecker", "usd_version": version}
    from pxr import UsdValidation

    reg = UsdValidation.ValidationRegistry()
    names = []
    for md in reg.GetAllValidatorMetadata():
        kw = list(md.GetKeywords())
        if md.name.endswith(":RootPackageValidator"):
            continue
        if "UsdzValidators" in kw and not arkit and not (path.suffix.lower() == ".usdz" and md.name.endswith(":UsdzPackageValidator")):
            continue
        names.append(md.name)
    ctx = UsdValidation.ValidationContext(reg.GetOrLoadValidatorsByName(sorted(names)))
    stage = Usd.Stage.Open(str(path))
    errors, warns = [], []
    for e in ctx.Validate(stage):
        t = e.GetType()
        if t == UsdValidation.ValidationErrorType.Error:
            errors.append(e.GetErrorAsString())
        elif t == UsdValidation.ValidationErrorType.Warn:
            warns.append(e.GetErrorAsString())
    return {"errors": errors, "warnings": warns, "checker": f"UsdValidation ({len(names)} validators)", "usd_version": version}
