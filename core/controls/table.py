"""The controls table: per-shape bounds, gain, offset and on/off, symmetry and cancel pairs.

A table is plain data (JSON, :func:`validate_table` gives the format): what an animator edits.
:func:`default_table` gives a rig's defaults, :func:`merge_table` lays a user's table over
them, and :func:`resolve` turns it into :class:`Controls`, the arrays the solvers take:

=======================  ==================  ===============================================
control                  where               what
=======================  ==================  ===============================================
lower/upper per shape    inside the solve    :meth:`Controls.bounds` of range_pf, spacetime,
                                             local (box)
active set               inside the solve    off shapes held at 0: :meth:`Controls.zero`,
                                             the ``zero`` (K,) of every solver
symmetry pairs           inside the solve    :meth:`Controls.symmetry_matrix`, the solvers'
                                             ``quadratic`` (:mod:`core.controls.pairs`)
cancel pairs             around the solve    :func:`core.controls.pairs.cancel_pairs`
gain/offset              after the solve     :func:`remap` (:meth:`Controls.remap`), clamped
                                             to the bounds
=======================  ==================  ===============================================

Gain and offset are Audio2Face's per-shape multipliers and offsets [1] (Reallusion's per-morph
strength and limits): ``w'_tk = clip(g_k w_tk + o_k, lower_k, upper_k)``.

References
----------
.. [1] NVIDIA, Audio2Face-3D blendshape solver (MIT, 2025): ``FacsSolver`` with active poses,
       cancel pairs, symmetry pairs, L1/L2 and temporal terms.
"""

from __future__ import annotations

import copy
import difflib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Optional, Sequence

import numpy as np

from .inputs import as_names, as_weights, shape_index
from .pairs import symmetry_matrix, symmetry_pairs

__all__ = ["SHAPE_FIELDS", "FORMAT", "Controls", "default_table", "validate_table", "read_table", "write_table",
           "merge_table", "resolve", "remap"]


#: fields of one shape's entry in a controls table, with their defaults
SHAPE_FIELDS = {"lower": 0.0, "upper": 1.0, "gain": 1.0, "offset": 0.0, "active": True}
#: the ``format`` string of a controls table file
FORMAT = "face-retarget controls"
_TOP_KEYS = ("format", "version", "shapes", "symmetry", "cancel")


def _number(v, where: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
        raise ValueError(f"{where}: expected a finite number, got {v!r}")
    return float(v)


def _pairs_of(value, where: str) -> list:
    if not isinstance(value, (list, tuple)):
        raise ValueError(f"{where}: expected a list of [a, b] name pairs, got {type(value).__name__}")
    out = []
    for i, p in enumerate(value):
        if not isinstance(p, (list, tuple)) or len(p) != 2 or not all(isinstance(x, str) for x in p):
            raise ValueError(f"{where}[{i}]: expected a pair of two shape names [a, b], got {p!r}")
        if p[0] == p[1]:
            raise ValueError(f"{where}[{i}]: a pair needs two different shapes, got {p[0]!r} twice")
        out.append([p[0], p[1]])
    return out


def validate_table(table, names: Optional[Sequence[str]] = None, where: str = "controls") -> dict:
    """A checked, normalised copy of a controls table.

    The format (JSON)::

        {"format": "face-retarget controls", "version": 1,          (optional)
         "shapes": {name: {"lower": 0, "upper": 1, "gain": 1, "offset": 0, "active": true}, ...},
         "symmetry": [[left, right], ...],
         "cancel": [[a, b], ...]}

    Every key is optional; a shape's missing fields take :data:`SHAPE_FIELDS`' defaults when
    resolved. With ``names`` every shape and pair member must name one of them (exactly, or by
    canonical ARKit name when unique), and the table is rewritten in those spellings.

    Raises
    ------
    ValueError
        Naming ``where`` and the key: unknown keys (with "did you mean"), non-numbers, lower >
        upper, a pair of one shape, a shape named twice, unknown shape names.
    """
    if not isinstance(table, dict):
        raise ValueError(f"{where}: expected a JSON object with 'shapes', 'symmetry', 'cancel', got {type(table).__name__}")
    for k in table:
        if k not in _TOP_KEYS:
            close = difflib.get_close_matches(str(k), _TOP_KEYS, n=1)
            raise ValueError(f"{where}: unknown key {k!r}" + (f"; did you mean {close[0]!r}?" if close else "")
                             + f" (keys: {list(_TOP_KEYS)})")
    if "format" in table and table["format"] != FORMAT:
        raise ValueError(f"{where}.format: expected {FORMAT!r}, got {table['format']!r}")
    if "version" in table and table["version"] != 1:
        raise ValueError(f"{where}.version: this reader knows version 1, got {table['version']!r}")
    out = {"format": FORMAT, "version": 1}
    shapes = table.get("shapes", {})
    if not isinstance(shapes, dict):
        raise ValueError(f"{where}.shapes: expected an object {{name: {{lower, upper, gain, offset, active}}}}")
    norm = {}
    for name, entry in shapes.items():
        w = f"{where}.shapes[{name!r}]"
        if not isinstance(entry, dict):
            raise ValueError(f"{w}: expected an object with some of {list(SHAPE_FIELDS)}, got {entry!r}")
        e = {}
        for k, v in entry.items():
            if k not in SHAPE_FIELDS:
                close = difflib.get_close_matches(str(k), list(SHAPE_FIELDS), n=1)
                raise ValueError(f"{w}: unknown field {k!r}" + (f"; did you mean {close[0]!r}?" if close else "")
                                 + f" (fields: {list(SHAPE_FIELDS)})")
            if k == "active":
                if not isinstance(v, bool):
                    raise ValueError(f"{w}.active: expected true or false, got {v!r}")
                e[k] = v
            else:
                e[k] = _number(v, f"{w}.{k}")
        lo, hi = e.get("lower", SHAPE_FIELDS["lower"]), e.get("upper", SHAPE_FIELDS["upper"])
        if lo > hi:
            raise ValueError(f"{w}: lower {lo:g} > upper {hi:g}")
        key = str(name)
        if names is not None:
            key = names[shape_index(key, names, f"{where}.shapes")]
        if key in norm:
            raise ValueError(f"{where}.shapes: shape {key!r} is given twice (as {name!r})")
        norm[key] = e
    out["shapes"] = norm
    for part in ("symmetry", "cancel"):
        if part in table:
            pairs = _pairs_of(table[part], f"{where}.{part}")
            if names is not None:
                pairs = [[names[shape_index(a, names, f"{where}.{part}")], names[shape_index(b, names, f"{where}.{part}")]]
                         for a, b in pairs]
                for i, (a, b) in enumerate(pairs):
                    if a == b:
                        raise ValueError(f"{where}.{part}[{i}]: both names resolve to shape {a!r}")
            out[part] = pairs
    return out


def default_table(names: Sequence[str], lower: float = 0.0, upper: float = 1.0, symmetry: bool = True,
                  cancel: Iterable = ()) -> dict:
    """The defaults for a rig: every shape active with ``[lower, upper]``, gain 1, offset 0;
    ``symmetry`` = :func:`symmetry_pairs` (or none); ``cancel`` as given (none by default, see
    :func:`suggested_cancel_pairs`)."""
    names = as_names(names)
    t = {"format": FORMAT, "version": 1,
         "shapes": {n: dict(SHAPE_FIELDS, lower=float(lower), upper=float(upper)) for n in names},
         "symmetry": [list(p) for p in symmetry_pairs(names)] if symmetry else [],
         "cancel": [list(p) for p in cancel]}
    return validate_table(t, names, "default_table")


def merge_table(table, defaults) -> dict:
    """``defaults`` with ``table`` on top: per shape, the fields ``table`` gives replace the
    defaults' (shapes named in the defaults' spelling, or by canonical ARKit name);
    ``symmetry``/``cancel`` lists of ``table`` replace the defaults' when present (an empty list
    = no pairs). Both are validated; the result names the defaults' shapes."""
    d = validate_table(defaults, where="defaults")
    names = list(d["shapes"])
    t = validate_table(table, names, "controls")
    out = copy.deepcopy(d)
    for n, e in t["shapes"].items():
        out["shapes"].setdefault(n, {}).update(e)
        lo = out["shapes"][n].get("lower", SHAPE_FIELDS["lower"])
        hi = out["shapes"][n].get("upper", SHAPE_FIELDS["upper"])
        if lo > hi:
            raise ValueError(f"controls.shapes[{n!r}]: after merging with the defaults lower {lo:g} > upper {hi:g}")
    for part in ("symmetry", "cancel"):
        if part in t:
            out[part] = t[part]
    return out


def read_table(path, names: Optional[Sequence[str]] = None) -> dict:
    """Read and validate a controls table (JSON); errors name the file."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: no such controls table") from None
    try:
        raw = json.loads(text)
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: not JSON ({e.msg} at line {e.lineno}, column {e.colno})") from None
    return validate_table(raw, names, str(path))


def write_table(path, table) -> Path:
    """Write a (validated) controls table as JSON, one shape per line."""
    t = validate_table(table)
    path = Path(path)
    lines = ["{", f'  "format": {json.dumps(t["format"])},', f'  "version": {t["version"]},', '  "shapes": {']
    items = list(t["shapes"].items())
    for i, (n, e) in enumerate(items):
        lines.append(f"    {json.dumps(n)}: {json.dumps(e)}" + ("," if i < len(items) - 1 else ""))
    lines.append("  }" + ("," if "symmetry" in t or "cancel" in t else ""))
    rest = [k for k in ("symmetry", "cancel") if k in t]
    for i, k in enumerate(rest):
        lines.append(f'  "{k}": {json.dumps(t[k])}' + ("," if i < len(rest) - 1 else ""))
    lines.append("}")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


@dataclass(frozen=True, eq=False)
class Controls:
    """A controls table resolved against a list of shape names: arrays the solvers take.

    Attributes
    ----------
    names : tuple of K str
    lower, upper, gain, offset : (K,) float
    active : (K,) bool
    symmetry, cancel : (P, 2), (Q, 2) int index pairs into ``names``
    """

    names: tuple
    lower: np.ndarray
    upper: np.ndarray
    gain: np.ndarray
    offset: np.ndarray
    active: np.ndarray
    symmetry: np.ndarray
    cancel: np.ndarray

    @property
    def K(self) -> int:
        return len(self.names)

    def zero(self) -> np.ndarray:
        """(K,) bool: the off shapes, for the solvers' ``zero`` option."""
        return ~self.active

    def bounds(self):
        """``(lower, upper)`` (K,) with the off shapes pinned at ``clip(0, lower, upper)``."""
        z = np.clip(0.0, self.lower, self.upper)
        return np.where(self.active, self.lower, z), np.where(self.active, self.upper, z)

    def symmetry_matrix(self, weight: float = 1.0) -> np.ndarray:
        """:func:`symmetry_matrix` of the pairs whose two shapes are both active."""
        keep = self.active[self.symmetry].all(1) if len(self.symmetry) else np.zeros(0, bool)
        return symmetry_matrix(self.symmetry[keep], self.K, weight)

    def remap(self, W) -> np.ndarray:
        """:func:`remap` with the table's gain, offset and bounds; off shapes stay 0."""
        out = remap(W, self.gain, self.offset, self.lower, self.upper)
        out[:, ~self.active] = np.where(np.isnan(out[:, ~self.active]), np.nan, 0.0)
        return out

    def subset(self, names: Sequence[str]) -> "Controls":
        """The controls of some of the shapes (e.g. the solver's shapes of the rig); pairs with
        a shape outside ``names`` are dropped."""
        names = as_names(names)
        idx = np.array([self.names.index(n) if n in self.names else -1 for n in names])
        if (idx < 0).any():
            bad = [n for n, i in zip(names, idx) if i < 0]
            raise ValueError(f"Controls.subset: shapes {bad[:5]} are not in the controls' {self.K} shapes")
        where = np.full(self.K, -1)
        where[idx] = np.arange(len(idx))

        def sub(P):
            if not len(P):
                return np.zeros((0, 2), np.int64)
            Pm = where[P]
            return Pm[(Pm >= 0).all(1)]

        return Controls(names, self.lower[idx], self.upper[idx], self.gain[idx], self.offset[idx], self.active[idx],
                        sub(self.symmetry), sub(self.cancel))


def resolve(table, names: Sequence[str]) -> Controls:
    """:class:`Controls` for ``names`` from a table (missing shapes and fields take
    :data:`SHAPE_FIELDS`' defaults; missing ``symmetry`` = no pairs, merge with
    :func:`default_table` first for the automatic ones)."""
    names = as_names(names)
    t = validate_table(table, names)
    K = len(names)
    cols = {k: np.full(K, v, dtype=bool if k == "active" else np.float64) for k, v in SHAPE_FIELDS.items()}
    for n, e in t["shapes"].items():
        i = names.index(n)
        for k, v in e.items():
            cols[k][i] = v
    bad = np.flatnonzero(cols["lower"] > cols["upper"])
    if len(bad):
        raise ValueError(f"controls: lower > upper for shapes {[names[i] for i in bad[:5]]}")
    idx = {n: i for i, n in enumerate(names)}

    def ip(part):
        P = [[idx[a], idx[b]] for a, b in t.get(part, [])]
        return np.asarray(P, np.int64).reshape(-1, 2)

    return Controls(names, cols["lower"], cols["upper"], cols["gain"], cols["offset"], cols["active"],
                    ip("symmetry"), ip("cancel"))


def _per_shape(x, K: int, name: str, default=None) -> np.ndarray:
    if x is None:
        x = default
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 0:
        a = np.full(K, float(a))
    if a.shape != (K,):
        raise ValueError(f"{name}: expected a number or ({K},) per-shape values, got shape {a.shape}")
    if np.isnan(a).any():
        raise ValueError(f"{name}: contains NaN")
    return a


def remap(W, gain=1.0, offset=0.0, lower=None, upper=None) -> np.ndarray:
    """Per-shape gain and offset after the solve, clamped to the bounds:

        w'_tk = clip(g_k w_tk + o_k, lower_k, upper_k)

    (Audio2Face's per-shape multipliers and offsets [1], Reallusion's per-morph strength and
    limits). NaN (a gap) stays NaN.

    Parameters
    ----------
    W : (T, K) float
    gain, offset : float or (K,) float
    lower, upper : float or (K,) float, optional (None: no clamp on that side)

    Returns
    -------
    (T, K) float64, a new array.

    Raises
    ------
    ValueError
        Shapes that disagree, non-finite gain or offset, lower > upper.
    """
    W = as_weights(W)
    K = W.shape[1]
    g = _per_shape(gain, K, "gain")
    o = _per_shape(offset, K, "offset")
    if not (np.isfinite(g).all() and np.isfinite(o).all()):
        raise ValueError("gain, offset: must be finite")
    lo = _per_shape(lower, K, "lower", -np.inf)
    hi = _per_shape(upper, K, "upper", np.inf)
    if (lo > hi).any():
        raise ValueError(f"lower > upper for shapes {np.flatnonzero(lo > hi)[:5].tolist()}")
    with np.errstate(invalid="ignore"):
        return np.clip(W * g + o, lo, hi)
