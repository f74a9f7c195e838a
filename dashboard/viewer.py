"""3D playback of blendshape rigs in the browser: three.js morph targets in a Panel JSComponent.

What travels, and when (measured numbers in ``docs/viewer.md``):

* once per session: ``neutral`` (V, 3) float32, ``faces`` (F, 3) uint32, ``deltas`` (K, V, 3)
  float32 and the weight ``track`` (T, K) float32 — on our server each as one blob by URL
  (:mod:`dashboard.payloads`, fetched once and shared by every page showing it; a new track
  is a new URL), elsewhere as binary websocket frames (bokeh ndarray buffers, no base64) —
  and the marker layout or marker track;
* while playing: nothing per frame. The browser plays the track at ``fps`` on a clock shared
  by all viewers with the same ``sync_group``; the group's first viewer writes ``frame`` back
  to Python at most every ``sync_interval`` seconds (0: only when playback stops);
* scrubbing from Python: ``frame`` (one int), or ``weights`` (K floats) to show a pose that is
  not on the track (a solver preview);
* a texture-space normal map (optional): ``uvs`` (V, 2) float32 once, ``normal_map`` (H, W, 3)
  uint8 whenever it changes (H*W*3 bytes, binary), e.g. Liu et al. 2011 §5's per-frame blended
  map on a decimated mesh (``dashboard.normalmap_view``);
* per-vertex offsets (optional): ``offsets`` (V, 3) float32 whenever they change (V*3*4 bytes,
  binary, nothing else with them), e.g. the fine-scale detail (wrinkles) of a dense transfer
  that the blendshape rig does not hold.

The browser computes, per frame, ``mesh = neutral + sum_k w_k deltas[k] (+ offsets)``: on the GPU as three.js
morph targets (``morphAttributes.position`` with ``morphTargetsRelative``; WebGL2 keeps all K
targets in a texture, so there is no 8-target limit), or in JS over the non-zero weights when
the WebGL is software (``blend="auto"``: SwiftShader runs the vertex shader on the CPU, and the
generic morph shader fetches all K targets per vertex). Normals are blended the same way from
per-shape normal deltas the browser computes on load; markers are the layout's barycentric
points on the morphed mesh. With offsets set, the mesh is blended in JS (also when ``blend`` is
gpu) and its normals are the exact vertex normals of the offset mesh, so the offsets show in the
shading. With a normal map, the fragment normal is read from the map
instead (``MeshStandardMaterial.normalMap``, object or tangent space). Python only packs arrays here.
"""

from __future__ import annotations

import base64
import weakref
from pathlib import Path

import numpy as np
import panel as pn
import param
from panel.io.state import state

from core.normalmap import encode_normal_map  # noqa: F401  (re-exported for views and tests)

from . import assets, payloads

_STATIC = Path(__file__).parent / "static"


# float32 copies of read-only arrays, shared by every viewer (every page) showing them: a rig's
# deltas are the bulk of a session's memory, and the pipeline's results are frozen, so the copy
# of one is the copy for all. Keyed by the source array's id, checked by a weak reference (numpy
# arrays are not hashable), dropped with it.
_SHARED_F32: dict = {}


def _f32(a, what: str, shape: tuple) -> np.ndarray:
    """C-contiguous float32 copy of ``a``, checked against ``shape`` (None = any) and finite;
    for a read-only ``a`` the same (read-only) copy every time."""
    if isinstance(a, np.ndarray) and not a.flags.writeable:
        hit = _SHARED_F32.get(id(a))
        if hit is not None and hit[0]() is a and hit[2] == (what, shape):
            return hit[1]
        out = _f32_copy(a, what, shape)
        out.flags.writeable = False
        key = id(a)
        try:
            ref = weakref.ref(a, lambda r, key=key: _SHARED_F32.pop(key, None))
        except TypeError:  # a view of a buffer that takes no weak reference: not shared
            return out
        _SHARED_F32[key] = (ref, out, (what, shape))
        return out
    return _f32_copy(a, what, shape)


def _u32(a) -> np.ndarray:
    """C-contiguous uint32 ``a`` (triangles), shared like :func:`_f32` for a read-only ``a``."""
    if isinstance(a, np.ndarray) and not a.flags.writeable:
        hit = _SHARED_F32.get(id(a))
        if hit is not None and hit[0]() is a and hit[2] == "u32":
            return hit[1]
        out = np.ascontiguousarray(a, dtype=np.uint32)
        out.flags.writeable = False
        key = id(a)
        _SHARED_F32[key] = (weakref.ref(a, lambda r, key=key: _SHARED_F32.pop(key, None)), out, "u32")
        return out
    return np.ascontiguousarray(a, dtype=np.uint32)


def _f32_copy(a, what: str, shape: tuple) -> np.ndarray:
    arr = np.ascontiguousarray(np.asarray(a, dtype=np.float64))
    if arr.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, arr.shape)):
        want = "(" + ", ".join("?" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{what}: expected shape {want}, got {arr.shape}")
    if not np.isfinite(arr).all():
        bad = np.flatnonzero(~np.isfinite(arr).reshape(len(arr), -1).all(axis=1))[:10].tolist()
        raise ValueError(
            f"{what}: contains NaN/inf (first rows {bad}); fill or drop missing samples before "
            "display, the viewer does not guess them"
        )
    return arr.astype(np.float32)


class MeshViewer(pn.custom.JSComponent):
    """A blendshape rig played back with three.js morph targets.

    ``mesh(t) = neutral + sum_k track[t, k] * deltas[k] + offsets`` is evaluated in the browser
    for the frame ``frame`` (or for ``weights`` when those are set; ``offsets`` only when set,
    see :meth:`set_offsets`); markers, when given, are
    barycentric points of the morphed mesh ``p_m = sum_j b_mj mesh[v_mj]`` (the
    :class:`core.model.MarkerLayout` convention) or positions from ``marker_track``.

    Build one with :meth:`from_rig`. Two viewers with the same ``sync_group`` share one
    playback clock and one orbit camera in the browser, so they stay frame-locked without a
    round trip through Python; link one of them to a frame slider.

    Direct manipulation (``pick_mode="vertex"``): the browser raycasts the mesh as shown (the
    blended positions of the shown frame) and takes the hit triangle's vertex nearest to the
    hit; a click sets :attr:`picked`, a drag sets :attr:`dragged` whose ``end`` is the start
    point moved in the camera plane through it. :attr:`highlight` marks vertices. Vertex ids
    are the rig's (unwelded) ids.

    Diagnostics for tests: ``window.__faceRetargetStats.viewers[label]`` counts renders and
    shown/skipped frames; ``window.__faceRetarget.viewers[label]`` offers ``probe(weights)``,
    ``pixels()``, ``pickAt(x, y)``, ``vertexPositions(ids)`` and ``camera()`` (see ``docs/viewer.md``).
    """

    # the mesh is kept here and reaches the browser packed into one blob (dashboard.payloads):
    # by URL on our server, inside the document otherwise (see _rename)
    neutral = param.Array(default=None, precedence=-1, doc="(V, 3) float32 rest positions, metres.")
    faces = param.Array(default=None, precedence=-1, doc="(F, 3) uint32 triangles.")
    deltas = param.Array(default=None, precedence=-1, doc="(K, V, 3) float32 shape deltas, metres.")
    geometry_url = param.String(
        default="", doc="Set from neutral/faces/deltas: the path (from the server root) of their packed blob "
                        "(dashboard.payloads), which the browser fetches once and caches; empty when the blob "
                        "travels inline in `geometry`.")
    geometry = param.Array(
        default=None, doc="Set from neutral/faces/deltas when the server has no mesh route (a notebook, "
                          "`panel serve` without dashboard.assets.serve) or `inline_geometry` is on: the packed "
                          "blob as uint8, sent in the document (binary).")
    inline_geometry = param.Boolean(
        default=False, precedence=-1,
        doc="Send the mesh and the track inside the document even when the server serves them by URL.")
    shape_names = param.List(default=[], item_type=str, doc="K shape names.")
    track = param.Array(
        default=None, doc="(T, K) float32 weight track played in the browser (set it with set_track). Sent inside "
                          "the document only when `track_url` is empty.")
    track_url = param.String(
        default="", doc="Set with the track: the path (from the server root) of its packed blob "
                        "(dashboard.payloads), fetched by the browser; empty when the track travels in `track`.")
    weights = param.List(default=[], doc="K floats shown instead of the track while non-empty.")
    frame = param.Integer(default=0, bounds=(0, None), doc="Frame of the track shown.")
    gaps = param.List(default=[], doc="[first, last] frame ranges without captured data (tracking loss): the "
                                      "view's label says so at those frames (their weights are filled in).")
    playing = param.Boolean(default=False, doc="Play the track in the browser.")
    fps = param.Number(default=30.0, bounds=(0, None), inclusive_bounds=(False, True), doc="Playback rate.")
    loop = param.Boolean(default=True, doc="Wrap around at the end instead of stopping.")
    sync_group = param.String(default="", doc="Viewers with the same non-empty group share clock and camera.")
    sync_interval = param.Number(
        default=0.5, bounds=(0, None),
        doc="While playing, the sync group's first viewer writes `frame` back to Python at most "
            "this often (s); 0: only when playback stops (then every viewer writes it).")
    marker_vertices = param.Array(default=None, doc="(M, 3) uint32 layout triangles' vertices.")
    marker_weights = param.Array(default=None, doc="(M, 3) float32 barycentric weights.")
    marker_track = param.Array(default=None, doc="(T, M, 3) float32 marker positions (instead of a layout).")
    marker_radius = param.Number(default=0.006, bounds=(0, None), doc="Marker sphere radius / rig size.")
    marker_color = param.Color(default="#19d3ff")
    show_markers = param.Boolean(default=True)
    colors = param.Array(default=None, doc="(V, 3) float32 per-vertex RGB in [0, 1] (e.g. an error map).")
    offsets = param.Array(
        default=None,
        doc="(V, 3) float32 per-vertex displacement (metres) added to the shown mesh on top of the blend "
            "(e.g. a dense transfer's wrinkles, which the rig does not hold), or None. One displacement, not "
            "a track: set it again when the frame changes. Sent alone whenever it changes (V*3*4 bytes); the "
            "geometry is not resent or rebuilt. While set, the browser blends this mesh in JS even when "
            "`blend` is gpu (morph targets are swapped out, and back in when cleared), normals are the exact "
            "area-weighted vertex normals of the displaced mesh (so the offsets show in the shading), and "
            "picking, highlights and layout markers use the displaced positions. None: the plain blend again, "
            "exactly as before. Set it with `set_offsets` (validated).")
    mesh_color = param.Color(default="#d8b49c")
    background_color = param.Color(default="#2b2f36")
    margin_factor = param.Number(default=1.12, bounds=(0.2, 10), doc="Camera framing: 1 = bbox touches the edges.")
    frame_bounds = param.List(
        default=[], doc="[xmin, ymin, zmin, xmax, ymax, zmax] (metres) to frame the camera on instead of the "
                        "neutral's bounding box, so views of different meshes of one head line up pixel for pixel.")
    label = param.String(default="", doc="Overlay text and key of the browser-side stats.")
    blend = param.Selector(
        default="auto", objects=["auto", "gpu", "cpu"],
        doc="gpu: three.js morph targets; cpu: the weighted sum in JS over non-zero weights; "
            "auto: cpu on a software WebGL (SwiftShader/llvmpipe), gpu otherwise. Read once on render.")
    shading = param.Selector(
        default="auto", objects=["auto", "standard", "fast"],
        doc="standard: per-pixel PBR (MeshStandardMaterial), both sides; fast: per-vertex "
            "Lambert, front faces only; auto: fast on a software WebGL. Read once on render.")
    pick_mode = param.Selector(
        default="off", objects=["off", "vertex"],
        doc="vertex: a left click on the mesh sets `picked`, a left drag that starts on the mesh "
            "sets `dragged`; orbit then with a left drag off the mesh, alt + left drag or a "
            "middle-button drag (right/shift drag pans, wheel zooms, as always). off: the "
            "default controls, nothing is picked.")
    picked = param.Dict(
        default={}, doc="Set by the browser on a click in pick mode: {'vertex': int, 'frame': int, "
                        "'position': [x, y, z] (metres, the vertex as shown), 'count': int}.")
    dragged = param.Dict(
        default={}, doc="Set by the browser when a drag in pick mode ends: {'vertex', 'frame', "
                        "'start': [x, y, z] (the vertex as shown at mouse-down), 'end': [x, y, z] "
                        "(the start moved in the camera plane through it), 'count'}.")
    highlight = param.List(default=[], item_type=int, doc="Vertex ids drawn as small spheres on the morphed mesh.")
    highlight_radius = param.Number(default=0.012, bounds=(0, None), doc="Highlight sphere radius / rig size.")
    highlight_color = param.Color(default="#ffd400")
    uvs = param.Array(
        default=None,
        doc="(V, 2) float32 texture coordinates of `normal_map`, in [0, 1] of the image: u along "
            "columns, v along rows, (0, 0) the top-left corner = first row of the array (glTF's "
            "convention; the texture is uploaded with flipY = false). Sent once.")
    normal_map = param.Array(
        default=None,
        doc="(H, W, 3) uint8 RGB normal map, n = 2 rgb / 255 - 1 (see `encode_normal_map`); None: "
            "the blended vertex normals. Needs `uvs`. Forces per-pixel standard shading (the "
            "per-vertex 'fast' shader has no per-pixel normal). Sent whenever it changes.")
    normal_map_space = param.Selector(
        default="object", objects=["object", "tangent"],
        doc="object: the map holds normals in the mesh's own frame (three.js ObjectSpaceNormalMap), "
            "what core.normalmap bakes; tangent: a tangent-space map (frame from screen-space "
            "derivatives of the UVs).")

    _esm = _STATIC / "viewer.js"
    # on a server the module is one URL (Panel's component route, cached by the browser), not its
    # 58 KB source inside every viewer model of every page (2 per page: ~0.25 MB of server memory
    # a page, and again in each document sent); elsewhere (a saved page, a notebook) it is inlined
    _bundle = _esm

    # kept in Python only: the mesh reaches the browser packed (geometry_url / geometry)
    _rename = {"neutral": None, "faces": None, "deltas": None, "inline_geometry": None}

    # three.js is imported from our own server (dashboard.assets), never a CDN
    _importmap = {"imports": {"three": assets.three_url(".")}}

    @classmethod
    def _process_importmap(cls):
        prefix = state.rel_path or "."
        return {"imports": {"three": assets.three_url(prefix)}}

    # -- construction --------------------------------------------------------------------
    @classmethod
    def from_rig(cls, rig, track=None, fps: float = 30.0, layout=None, marker_track=None, colors=None,
                 uvs=None, normal_map=None, offsets=None, **params) -> "MeshViewer":
        """A viewer for ``rig`` playing ``track``.

        Parameters
        ----------
        rig : core.model.Rig
            neutral (V, 3), faces (F, 3), deltas (K, V, 3), K names.
        track : (T, K) array_like, optional
            Weights per frame, columns in ``rig.names`` order. Must be finite.
        fps : float
            Playback rate of ``track``.
        layout : core.model.MarkerLayout, optional
            Markers drawn on the morphed mesh (computed in the browser).
        marker_track : (T, M, 3) array_like, optional
            Marker positions per frame in metres (e.g. captured markers), instead of ``layout``.
        colors : (V, 3) array_like, optional
            Per-vertex RGB in [0, 1].
        uvs : (V, 2) array_like, optional
            Texture coordinates of ``normal_map`` in [0, 1] of the image (see :attr:`uvs`);
            not ``rig.uvs``, whose UDIM range need not be [0, 1].
        normal_map : (H, W, 3) uint8, optional
            RGB-encoded normals (:func:`encode_normal_map`); needs ``uvs``.
        offsets : (V, 3) array_like, optional
            Per-vertex displacement in metres added after the blend (see :attr:`offsets`).
        **params
            Any other parameter (``label``, ``sync_group``, ``height`` ...).

        Raises
        ------
        ValueError
            naming the argument whose shape does not match the rig, or which holds NaN.
        """
        name = getattr(rig, "name", "rig")
        V, K = rig.n_vertices, rig.n_shapes
        faces = np.asarray(rig.faces)
        if faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"rig {name!r} faces: expected shape (F, 3), got {faces.shape}")
        values = dict(
            neutral=_f32(rig.neutral, f"rig {name!r} neutral", (V, 3)),
            faces=_u32(faces),
            deltas=_f32(rig.deltas, f"rig {name!r} deltas", (K, V, 3)),
            shape_names=list(rig.names),
            fps=float(fps),
        )
        values.setdefault("label", name)
        values.update(cls._track_values(track, K, "track", params.get("inline_geometry", False)))
        values.update(cls._geometry_values(values["neutral"], values["faces"], values["deltas"],
                                           params.get("inline_geometry", False)))
        if layout is not None and marker_track is not None:
            raise ValueError("give either layout (markers on the mesh) or marker_track (positions), not both")
        if layout is not None:
            layout.check(rig)
            values["marker_vertices"] = np.ascontiguousarray(layout.vertices, dtype=np.uint32)
            values["marker_weights"] = _f32(layout.weights, "layout weights", (layout.n_markers, 3))
        if marker_track is not None:
            values["marker_track"] = _f32(marker_track, "marker_track", (None, None, 3))
        if colors is not None:
            values["colors"] = cls._colors(colors, V)
        if uvs is not None:
            values["uvs"] = cls._uvs(uvs, V)
        if normal_map is not None:
            if uvs is None:
                raise ValueError("normal_map: needs uvs (V, 2), the texture coordinates to read it with")
            values["normal_map"] = cls._normal_map(normal_map)
        if offsets is not None:
            values["offsets"] = _f32(offsets, "offsets", (V, 3))
        values.update(params)
        return cls(**values)

    def __init__(self, **params):
        payload = params.pop("_payload", None)
        track_payload = params.pop("_track_payload", None)
        super().__init__(**params)
        # the registry only refers to a blob while a viewer holds it
        self._payload, self._track_payload = payload, track_payload
        if self.neutral is not None and not self.geometry_url and self.geometry is None:
            self._set_geometry()
        if self.track is not None and not self.track_url and payloads.enabled() and not self.inline_geometry:
            self.set_track(self.track)
        self.param.watch(lambda *e: self._set_geometry(), ["neutral", "faces", "deltas", "inline_geometry"])
        self.param.watch(lambda *e: self.track is not None and self.set_track(self.track), ["inline_geometry"])

    def _process_param_change(self, params):
        if self.track_url and "track" in params:  # the browser fetches it (dashboard.payloads)
            params = {k: v for k, v in params.items() if k != "track"}
        return super()._process_param_change(params)

    @staticmethod
    def _geometry_values(neutral, faces, deltas, inline: bool = False) -> dict:
        """``geometry_url`` / ``geometry`` for these arrays (see :mod:`dashboard.payloads`), and
        under ``_payload`` the :class:`~dashboard.payloads.Payload` the viewer must hold (or None)."""
        if neutral is None:
            return {"geometry_url": "", "geometry": None, "_payload": None}
        faces = np.zeros((0, 3), np.uint32) if faces is None else faces
        deltas = np.zeros((0, len(neutral), 3), np.float32) if deltas is None else deltas
        if payloads.enabled() and not inline:
            p = payloads.register(neutral, faces, deltas)
            return {"geometry_url": p.url, "geometry": None, "_payload": p}
        blob = np.frombuffer(payloads.pack(neutral, faces, deltas), dtype=np.uint8)
        return {"geometry_url": "", "geometry": blob, "_payload": None}

    def _set_geometry(self, **more) -> None:
        # after a direct assignment (``viewer.deltas = ...``), or with the setters' other changes
        values = self._geometry_values(self.neutral, self.faces, self.deltas, self.inline_geometry)
        self._payload = values.pop("_payload")
        self.param.update(**values, **more)

    @staticmethod
    def _track_values(track, K: int, what: str, inline: bool = False) -> dict:
        """``track`` checked as float32, its ``track_url`` and under ``_track_payload`` the
        :class:`~dashboard.payloads.Payload` to hold (by URL on our server unless ``inline``)."""
        if track is None:
            return {"track": None, "track_url": "", "_track_payload": None}
        arr = _f32(track, what, (None, K))
        if not len(arr):
            raise ValueError(f"{what}: expected at least one frame, got shape {arr.shape}")
        p = payloads.register_track(arr) if payloads.enabled() and not inline else None
        return {"track": arr, "track_url": p.url if p is not None else "", "_track_payload": p}

    @staticmethod
    def _colors(colors, V: int) -> np.ndarray:
        c = _f32(colors, "colors", (V, 3))
        if c.min() < 0 or c.max() > 1:
            raise ValueError(f"colors: expected RGB in [0, 1], got range [{c.min():.3g}, {c.max():.3g}]")
        return c

    @staticmethod
    def _uvs(uvs, V: int) -> np.ndarray:
        return _f32(uvs, "uvs", (V, 2))

    @staticmethod
    def _normal_map(image) -> np.ndarray:
        img = np.asarray(image)
        if img.ndim != 3 or img.shape[2] != 3 or min(img.shape[:2]) < 1:
            raise ValueError(f"normal_map: expected an (H, W, 3) RGB image, got shape {img.shape}")
        if img.dtype != np.uint8:
            raise ValueError(f"normal_map: expected uint8 RGB (encode unit normals with encode_normal_map), got {img.dtype}")
        if max(img.shape[:2]) > 8192:
            raise ValueError(f"normal_map: {img.shape[1]}x{img.shape[0]} exceeds 8192 texels per side, more than WebGL "
                             "guarantees; bake at a lower resolution")
        return np.ascontiguousarray(img)

    @property
    def n_shapes(self) -> int:
        return 0 if self.deltas is None else int(self.deltas.shape[0])

    @property
    def n_frames(self) -> int:
        """Frames of the track (or of the marker track), at least 1."""
        t = 0 if self.track is None else len(self.track)
        m = 0 if self.marker_track is None else len(self.marker_track)
        return max(t, m, 1)

    # -- updates ---------------------------------------------------------------------------
    def set_track(self, track, fps: float | None = None) -> None:
        """Replace the (T, K) weight track (sent once, as float32); clamps ``frame``.

        Raises ValueError when the track is not (T, K) for this rig's K or holds NaN.
        """
        values = self._track_values(track, self.n_shapes, "track", self.inline_geometry)
        self._track_payload = values.pop("_track_payload")
        T = 1 if values["track"] is None else len(values["track"])
        values["frame"] = min(self.frame, T - 1)
        if fps is not None:
            values["fps"] = float(fps)
        inline_again = not values["track_url"] and self.track_url and values["track"] is self.track
        self.param.update(**values)
        if inline_again:  # the same array, now inside the document: param saw no change of it
            self.param.trigger("track")

    def set_weights(self, weights) -> None:
        """Show ``weights`` (K,) instead of the track; ``None`` or ``[]`` goes back to the track.

        Sent as K decimal numbers rounded to 1e-6 (far below a visible difference), i.e. a
        few hundred bytes per update. Raises ValueError for a wrong length or NaN.
        """
        if weights is None or (not isinstance(weights, np.ndarray) and len(weights) == 0):
            self.weights = []
            return
        w = _f32(np.reshape(weights, -1), "weights", (self.n_shapes,))
        self.weights = [round(float(x), 6) for x in w]

    def stream_weights(self, weights) -> None:
        """Show ``weights`` (K,) now, sent as a message rather than a model change (no property
        patch and no echo: the cheapest update, for a live stream at 60 Hz): ``{"w32": the K
        float32 little-endian, base64}``, one string (a list of K floats cost Bokeh's serializer
        a call per element, ~2 ms a message); the next :meth:`set_weights` or track replaces
        them. Raises ValueError for a wrong length or NaN."""
        w = _f32(np.reshape(weights, -1), "weights", (self.n_shapes,))
        self._send_msg({"w32": base64.b64encode(w.astype("<f4").tobytes()).decode("ascii")})

    def set_colors(self, colors) -> None:
        """Per-vertex RGB (V, 3) in [0, 1], or None for the plain material."""
        V = 0 if self.neutral is None else len(self.neutral)
        self.colors = None if colors is None else self._colors(colors, V)

    def set_deltas(self, deltas) -> None:
        """Replace the (K, V, 3) shape deltas (same K and V; sent once as float32, the browser
        recomputes its normals). Raises ValueError for another shape or NaN."""
        K = self.n_shapes
        V = 0 if self.neutral is None else len(self.neutral)
        d = _f32(deltas, "deltas", (K, V, 3))
        with param.discard_events(self):
            self.deltas = d
        self._set_geometry()

    def set_shapes(self, deltas, track, shape_names=None) -> None:
        """Replace the shapes and their track together; unlike :meth:`set_deltas` the shape count
        K may change (e.g. detail morph targets appended to a rig). The browser rebuilds the
        geometry once (normals of every shape). Raises ValueError for another V, a track that
        is not (T, K) for the new K, names of another length, or NaN."""
        V = 0 if self.neutral is None else len(self.neutral)
        d = np.asarray(deltas)
        if d.ndim != 3:
            raise ValueError(f"deltas: expected (K, {V}, 3), got {d.shape}")
        K = len(d)
        values = {"deltas": _f32(d, "deltas", (K, V, 3))}
        names = [f"shape_{k:02d}" for k in range(K)] if shape_names is None else [str(n) for n in shape_names]
        if len(names) != K:
            raise ValueError(f"shape_names: expected {K} names, got {len(names)}")
        values["shape_names"] = names
        values.update(self._track_values(track, K, "track", self.inline_geometry))
        self._track_payload = values.pop("_track_payload")
        T = 1 if values["track"] is None else len(values["track"])
        values["frame"] = min(self.frame, T - 1)
        with param.discard_events(self):
            self.deltas = values.pop("deltas")
        self._set_geometry(**values)

    def set_highlight(self, vertices) -> None:
        """Mark ``vertices`` (ids of this rig) with spheres; raises ValueError for ids outside [0, V)."""
        V = 0 if self.neutral is None else len(self.neutral)
        ids = [int(v) for v in np.reshape(np.asarray(vertices if vertices is not None else [], dtype=np.int64), -1)]
        bad = [v for v in ids if not 0 <= v < V]
        if bad:
            raise ValueError(f"highlight: vertex ids must lie in [0, {V}), got {bad[:10]}")
        self.highlight = ids

    def set_offsets(self, offsets) -> None:
        """Show ``mesh = neutral + sum_k w_k deltas[k] + offsets`` with a (V, 3) per-vertex
        displacement in metres (e.g. the fine-scale detail of a dense transfer); None clears it
        and the viewer shows the plain blend exactly as before.

        Only the offsets travel (V*3 float32, binary); the browser recomputes the normals of the
        displaced mesh, so the offsets show in the shading (see :attr:`offsets`). The input is
        copied, never modified. Raises ValueError for another shape than (V, 3) or NaN/inf.
        """
        if offsets is None:
            self.offsets = None
            return
        V = 0 if self.neutral is None else len(self.neutral)
        self.offsets = _f32(offsets, "offsets", (V, 3))

    def set_uvs(self, uvs) -> None:
        """Texture coordinates (V, 2) of the normal map in [0, 1] of the image, or None.
        Raises ValueError for another V or NaN."""
        V = 0 if self.neutral is None else len(self.neutral)
        self.uvs = None if uvs is None else self._uvs(uvs, V)

    def set_normal_map(self, image) -> None:
        """Show an (H, W, 3) uint8 RGB normal map (n = 2 rgb/255 - 1), or None for the vertex
        normals. Only the image travels (H·W·3 bytes, binary). Raises ValueError for another
        shape or dtype, or when :attr:`uvs` is not set."""
        if image is None:
            self.normal_map = None
            return
        if self.uvs is None:
            raise ValueError("normal_map: set uvs (V, 2) first, the texture coordinates to read it with")
        self.normal_map = self._normal_map(image)

    def payload_bytes(self) -> dict:
        """Bytes of each array sent on load (float32/uint32/uint8 buffers), and their total;
        ``offsets`` travel again (alone) whenever they change."""
        out = {}
        for k in ("neutral", "faces", "deltas", "track", "marker_vertices", "marker_weights", "marker_track", "colors",
                  "uvs", "normal_map", "offsets"):
            v = getattr(self, k)
            out[k] = 0 if v is None else int(v.nbytes)
        out["total"] = sum(out.values())
        return out


def error_colors(values, vmax: float | None = None) -> np.ndarray:
    """Per-vertex heat-map colours for :attr:`MeshViewer.colors`: (V,) values -> (V, 3) RGB.

    ``t = clip(values / vmax, 0, 1)`` mapped from a light grey (0) through orange to red (1);
    ``vmax`` defaults to the largest finite value. NaN values are shown in blue so missing data
    is visible, not painted as zero error. Raises ValueError for a non-1-D input.
    """
    v = np.asarray(values, dtype=np.float64)
    if v.ndim != 1:
        raise ValueError(f"values: expected shape (V,), got {v.shape}")
    finite = np.isfinite(v)
    top = float(np.max(v[finite])) if vmax is None and finite.any() else float(vmax or 0.0)
    t = np.clip(np.where(finite, v, 0.0) / top, 0, 1) if top > 0 else np.zeros_like(v)
    stops = np.array([[0.85, 0.82, 0.80], [1.0, 0.6, 0.1], [0.85, 0.05, 0.05]])
    x = t * 2
    lo = np.minimum(x.astype(int), 1)
    frac = (x - lo)[:, None]
    rgb = stops[lo] * (1 - frac) + stops[lo + 1] * frac
    rgb[~finite] = (0.2, 0.35, 0.9)
    return rgb.astype(np.float32)
