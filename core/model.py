"""The data model: rigs, performances and marker layouts.

All three are immutable: arrays are copied on construction and marked read-only, so a
cached stage result can never be changed behind the cache's back. Positions are in metres
inside the library (``units`` records what the file said); errors are reported in mm.

Shapes follow the house letters: T frames, V vertices, K shapes, M markers.
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np

#: metres per unit, for the units a file may declare
UNIT_SCALE = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254, "dm": 0.1}


def unit_scale(units: str) -> float:
    """Metres per one ``units``; raises ValueError naming the accepted units."""
    try:
        return UNIT_SCALE[units]
    except KeyError:
        raise ValueError(f"unknown units {units!r}; expected one of {sorted(UNIT_SCALE)}") from None


def _frozen(a, dtype, name: str, shape: tuple) -> np.ndarray:
    """Copy ``a`` to a read-only array of ``dtype`` and check its shape.

    ``shape`` holds ints or None (any size) per axis.
    """
    arr = np.array(a, dtype=dtype, copy=True)
    if arr.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, arr.shape)):
        want = "(" + ", ".join("?" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name}: expected shape {want}, got {arr.shape}")
    arr.setflags(write=False)
    return arr


def flatten(points: np.ndarray) -> np.ndarray:
    """Papers' stacked-coordinate view: (..., N, 3) -> (..., 3N) as x0 y0 z0 x1 ...

    The one helper that makes the 3n x m matrices of Seol 2012 eq. 1 from (K, M, 3)
    deltas (transpose the result for B) and 3n x f matrices from (T, M, 3) sequences.
    """
    points = np.asarray(points)
    return points.reshape(points.shape[:-2] + (points.shape[-2] * 3,))


def unflatten(vectors: np.ndarray) -> np.ndarray:
    """Inverse of :func:`flatten`: (..., 3N) -> (..., N, 3)."""
    vectors = np.asarray(vectors)
    return vectors.reshape(vectors.shape[:-1] + (vectors.shape[-1] // 3, 3))


@dataclass(frozen=True, eq=False)
class Rig:
    """A delta blendshape rig: ``mesh(w) = neutral + sum_k w_k deltas[k]``.

    Parameters
    ----------
    neutral : (V, 3) float
        Rest positions in metres.
    faces : (F, 3) int
        Triangles indexing ``neutral``.
    deltas : (K, V, 3) float
        Shape minus neutral, in metres.
    names : sequence of K str
        Shape names as the file has them (see :mod:`core.names` for canonical ARKit names).
    uvs : (V, 2) float, optional
        Texture coordinates.
    units : str
        Units the file declared (positions are already converted to metres).
    name : str
        A label, usually the file stem.
    """

    neutral: np.ndarray
    faces: np.ndarray
    deltas: np.ndarray
    names: tuple
    uvs: Optional[np.ndarray] = None
    units: str = "m"
    name: str = "rig"
    extras: dict = field(default_factory=dict)

    def __post_init__(self):
        neutral = _frozen(self.neutral, np.float64, f"rig {self.name!r} neutral", (None, 3))
        V = len(neutral)
        faces = _frozen(self.faces, np.int64, f"rig {self.name!r} faces", (None, 3))
        if faces.size and (faces.min() < 0 or faces.max() >= V):
            raise ValueError(
                f"rig {self.name!r} faces: indices must lie in [0, {V}), got [{faces.min()}, {faces.max()}]"
            )
        deltas = _frozen(self.deltas, np.float64, f"rig {self.name!r} deltas", (None, V, 3))
        names = tuple(str(n) for n in self.names)
        if len(names) != len(deltas):
            raise ValueError(f"rig {self.name!r}: {len(deltas)} deltas but {len(names)} names")
        if len(set(names)) != len(names):
            dup = sorted({n for n in names if names.count(n) > 1})
            raise ValueError(f"rig {self.name!r}: duplicate shape names {dup}")
        if not np.isfinite(neutral).all() or not np.isfinite(deltas).all():
            raise ValueError(f"rig {self.name!r}: neutral or deltas contain NaN/inf")
        uvs = None if self.uvs is None else _frozen(self.uvs, np.float64, f"rig {self.name!r} uvs", (V, 2))
        unit_scale(self.units)
        object.__setattr__(self, "neutral", neutral)
        object.__setattr__(self, "faces", faces)
        object.__setattr__(self, "deltas", deltas)
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "uvs", uvs)

    @property
    def n_vertices(self) -> int:
        return len(self.neutral)

    @property
    def n_shapes(self) -> int:
        return len(self.deltas)

    @property
    def size(self) -> float:
        """Bounding-box diagonal of the neutral (metres): the scale tolerances are relative to."""
        return float(np.linalg.norm(self.neutral.max(0) - self.neutral.min(0)))

    def evaluate(self, weights) -> np.ndarray:
        """Meshes for weights: (K,) -> (V, 3), (T, K) -> (T, V, 3).

        ``neutral + w @ deltas``; raises ValueError when the last axis is not K.
        """
        w = np.asarray(weights, dtype=np.float64)
        if w.shape[-1:] != (self.n_shapes,) or w.ndim > 2:
            raise ValueError(f"rig {self.name!r}: weights must be (K,) or (T, K) with K={self.n_shapes}, got {w.shape}")
        flat = self.deltas.reshape(self.n_shapes, -1)
        return self.neutral + (w @ flat).reshape(w.shape[:-1] + self.neutral.shape)

    def index(self, name: str) -> int:
        """Position of shape ``name``; KeyError with close matches when absent."""
        try:
            return self.names.index(name)
        except ValueError:
            close = difflib.get_close_matches(name, self.names, n=3)
            raise KeyError(f"rig {self.name!r} has no shape {name!r}" + (f"; did you mean {close}?" if close else "")) from None

    def subset(self, names: Sequence[str]) -> "Rig":
        """A rig with only the shapes ``names`` (in that order)."""
        idx = [self.index(n) for n in names]
        return Rig(self.neutral, self.faces, self.deltas[idx], [self.names[i] for i in idx], self.uvs, self.units, self.name, dict(self.extras))


@dataclass(frozen=True, eq=False)
class MarkerLayout:
    """Where each marker sits on a rig: a barycentric point on a triangle.

    A marker on a vertex ``v`` is stored as vertices ``(v, v, v)`` with weights ``(1, 0, 0)``.

    Parameters
    ----------
    names : sequence of M str
    vertices : (M, 3) int
        The three vertices each marker interpolates.
    weights : (M, 3) float
        Barycentric weights, non-negative, summing to 1 per row.
    rig : str
        The rig file name the layout was made for (e.g. ``"ict_facekit.glb"``).
    """

    names: tuple
    vertices: np.ndarray
    weights: np.ndarray
    rig: str = ""
    extras: dict = field(default_factory=dict)

    def __post_init__(self):
        names = tuple(str(n) for n in self.names)
        M = len(names)
        vertices = _frozen(self.vertices, np.int64, f"layout for {self.rig!r} vertices", (M, 3))
        weights = _frozen(self.weights, np.float64, f"layout for {self.rig!r} weights", (M, 3))
        if len(set(names)) != M:
            dup = sorted({n for n in names if names.count(n) > 1})
            raise ValueError(f"layout for {self.rig!r}: duplicate marker names {dup}")
        if M and (vertices.min() < 0):
            raise ValueError(f"layout for {self.rig!r}: negative vertex index")
        if M and (np.abs(weights.sum(1) - 1) > 1e-6).any() or (weights < -1e-9).any():
            bad = [names[i] for i in np.flatnonzero((np.abs(weights.sum(1) - 1) > 1e-6) | (weights < -1e-9).any(1))]
            raise ValueError(f"layout for {self.rig!r}: barycentric weights must be >= 0 and sum to 1 (markers {bad})")
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "vertices", vertices)
        object.__setattr__(self, "weights", weights)

    @classmethod
    def from_vertices(cls, names, vertex_index, rig: str = "", extras=None) -> "MarkerLayout":
        v = np.asarray(vertex_index, dtype=np.int64).reshape(-1, 1)
        w = np.zeros((len(v), 3))
        w[:, 0] = 1
        return cls(names, np.repeat(v, 3, axis=1), w, rig, dict(extras or {}))

    @property
    def n_markers(self) -> int:
        return len(self.names)

    def check(self, rig: Rig) -> None:
        """Raise ValueError when an index does not exist on ``rig``."""
        if self.n_markers and self.vertices.max() >= rig.n_vertices:
            bad = [self.names[i] for i in np.flatnonzero((self.vertices >= rig.n_vertices).any(1))]
            raise ValueError(
                f"layout for {self.rig!r}: markers {bad} index vertices >= {rig.n_vertices}, "
                f"the vertex count of rig {rig.name!r}; was the layout made for another rig?"
            )

    def points(self, positions: np.ndarray) -> np.ndarray:
        """Marker positions on meshes: (..., V, 3) -> (..., M, 3)."""
        positions = np.asarray(positions)
        return np.einsum("...mjc,mj->...mc", positions[..., self.vertices, :], self.weights)

    def on_rig(self, rig: Rig) -> tuple[np.ndarray, np.ndarray]:
        """(neutral markers (M, 3), marker deltas (K, M, 3)) of ``rig``."""
        self.check(rig)
        return self.points(rig.neutral), self.points(rig.deltas)

    def select(self, names: Sequence[str]) -> "MarkerLayout":
        idx = [self.names.index(n) for n in names]
        return MarkerLayout([self.names[i] for i in idx], self.vertices[idx], self.weights[idx], self.rig, dict(self.extras))


KINDS = ("markers", "curves", "meshes")


@dataclass(frozen=True, eq=False)
class Performance:
    """A captured performance: marker trajectories, weight curves, or a mesh sequence.

    Build one with :meth:`markers`, :meth:`curves` or :meth:`meshes`.

    Attributes
    ----------
    kind : {"markers", "curves", "meshes"}
    data : (T, M, 3) metres | (T, K) weights | (T, V, 3) metres
    names : tuple
        Marker names (M) or channel names (K); empty for meshes.
    fps : float
    valid : (T, M) or (T, K) or (T,) bool
        False where a sample is missing (tracking loss, NaN). Missing samples keep NaN in
        ``data``; they are never zeroed.
    times : (T,) float seconds from the first sample.
    units : str the file declared (data is in metres).
    extras : dict, e.g. ``{"head_rotation": (T, 3)}``; readers put what they know about the file
        here, e.g. Live Link Face's ``tracking_loss`` (T,) bool (frames the app lost the face;
        :meth:`frames` slices it with the data).
        A mesh sequence's topology lives in ``extras["faces"]`` (F, 3) int: one set of triangles
        shared by every frame (the mesh-sequence readers of :mod:`core.io.sequence` check that each
        frame has the same vertex count and faces, and put them here; :meth:`meshes` takes them as
        ``faces=``; :meth:`frames` never slices them). Without it a sequence needs the source rig
        whose topology it has.
    """

    kind: str
    data: np.ndarray
    names: tuple
    fps: float
    valid: np.ndarray
    times: np.ndarray
    units: str = "m"
    name: str = "performance"
    extras: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"performance kind must be one of {KINDS}, got {self.kind!r}")
        if not (np.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"performance {self.name!r}: fps must be positive, got {self.fps}")
        shape = {"markers": (None, len(self.names), 3), "curves": (None, len(self.names)), "meshes": (None, None, 3)}[self.kind]
        data = _frozen(self.data, np.float64, f"performance {self.name!r} data", shape)
        T = len(data)
        vshape = (T,) + data.shape[1:2] if self.kind != "meshes" else (T,)
        valid = _frozen(self.valid, bool, f"performance {self.name!r} valid", vshape)
        times = _frozen(self.times, np.float64, f"performance {self.name!r} times", (T,))
        names = tuple(str(n) for n in self.names)
        if len(set(names)) != len(names):
            dup = sorted({n for n in names if names.count(n) > 1})
            raise ValueError(f"performance {self.name!r}: duplicate names {dup}")
        finite = np.isfinite(data).all(axis=-1) if self.kind == "markers" else np.isfinite(data)
        if self.kind == "meshes":
            finite = finite.all(axis=(1, 2))
        if (valid & ~finite).any():
            raise ValueError(f"performance {self.name!r}: samples marked valid contain NaN/inf")
        unit_scale(self.units)
        object.__setattr__(self, "data", data)
        object.__setattr__(self, "valid", valid)
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "names", names)

    # -- constructors -------------------------------------------------------------------
    @classmethod
    def _build(cls, kind, data, names, fps, valid, times, units, name, extras):
        if not (np.isfinite(fps) and fps > 0):
            raise ValueError(f"performance {name!r}: fps must be positive, got {fps}")
        data = np.asarray(data, dtype=np.float64)
        if valid is None:
            valid = np.isfinite(data).all(axis=-1) if kind == "markers" else np.isfinite(data)
            if kind == "meshes":
                valid = valid.all(axis=(1, 2))
        else:
            valid = np.asarray(valid, dtype=bool)
            data = data.copy()
            data[~valid] = np.nan  # a masked sample must never look like a real zero
        if times is None:
            times = np.arange(len(data)) / float(fps)
        return cls(kind, data, tuple(names), float(fps), valid, times, units, name, dict(extras or {}))

    @classmethod
    def markers(cls, positions, names, fps, valid=None, times=None, units="m", name="markers", extras=None):
        """Marker trajectories (T, M, 3) in metres; NaN rows are masked."""
        return cls._build("markers", positions, names, fps, valid, times, units, name, extras)

    @classmethod
    def curves(cls, weights, names, fps, valid=None, times=None, name="curves", extras=None):
        """Blendshape weight curves (T, K)."""
        return cls._build("curves", weights, names, fps, valid, times, "m", name, extras)

    @classmethod
    def meshes(cls, positions, fps, faces=None, valid=None, times=None, units="m", name="meshes", extras=None):
        """Dense mesh sequence (T, V, 3) in metres, with optional ``faces``."""
        extras = dict(extras or {})
        if faces is not None:
            extras["faces"] = np.asarray(faces, dtype=np.int64)
        return cls._build("meshes", positions, (), fps, valid, times, units, name, extras)

    # -- queries ------------------------------------------------------------------------
    @property
    def n_frames(self) -> int:
        return len(self.data)

    @property
    def duration(self) -> float:
        return float(self.times[-1] - self.times[0]) if self.n_frames else 0.0

    def select(self, names: Sequence[str]) -> "Performance":
        """Only the markers/channels ``names`` (in that order)."""
        if self.kind == "meshes":
            raise ValueError("a mesh sequence has no named channels to select")
        missing = [n for n in names if n not in self.names]
        if missing:
            raise KeyError(f"performance {self.name!r} has no channels {missing}")
        idx = [self.names.index(n) for n in names]
        return Performance(self.kind, self.data[:, idx], tuple(names), self.fps, self.valid[:, idx], self.times, self.units, self.name, dict(self.extras))

    def frames(self, start: int = 0, stop: Optional[int] = None, step: int = 1) -> "Performance":
        """A frame range (Python slice semantics); extras with a frame axis are sliced too."""
        sl = slice(start, stop, step)
        T = self.n_frames
        extras = {k: (v[sl] if isinstance(v, np.ndarray) and v.ndim >= 1 and len(v) == T and k != "faces" else v) for k, v in self.extras.items()}
        return Performance(self.kind, self.data[sl], self.names, self.fps / step, self.valid[sl], self.times[sl], self.units, self.name, extras)
