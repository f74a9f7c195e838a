"""Production solver controls: what animators tune in the tools they already use.

Every control is a pure function of arrays and names (validated here, at the boundary) or an
option of the solvers (``quadratic``, ``zero``, per-shape ``lower``/``upper``), off by default so
that every method solves exactly as before. Where each acts:

=======================  ==================  ===============================================
control                  where               what
=======================  ==================  ===============================================
lower/upper per shape    inside the solve    bounds of range_pf, spacetime, local (box)
active set               inside the solve    off shapes held at 0: ``zero`` (K,) of every
                                             solver (:meth:`Controls.zero`)
symmetry pairs           inside the solve    ``quadratic = symmetry_matrix(pairs, K, mu_s)``
cancel pairs             around the solve    :func:`cancel_pairs`: second pass(es) with the
                                             weaker of each firing pair held at 0
gain/offset              after the solve     :func:`remap`, clamped to the bounds
temporal filter          after the solve     :func:`filter_weights` (One Euro, Gaussian)
keyframe reduction       on export           :func:`reduce_keys` -> GLB / CSV writers
mirror                   on data             :func:`mirror_weights`, :func:`mirror_markers`,
                                             :func:`mirror_performance`, :func:`mirror_edit`
=======================  ==================  ===============================================

Symmetry (soft)
---------------
For pairs ``(L, R)`` the energy gains ``mu_s sum_pairs (w_L - w_R)^2 = mu_s w^T Q w`` per frame
with ``Q = sum (e_L - e_R)(e_L - e_R)^T`` (the graph Laplacian of the pairs, PSD). The solvers
take ``Q`` relative to ``sigma_max(B)^2`` (like their ridge): ``mu_s = 1`` makes a unit L/R
difference cost as much as a unit move along the most visible shape combination. It is the
"symmetry pairs" term of NVIDIA's Audio2Face-3D blendshape solver [1] (there an absolute
``A += symmetry * scale * S^T S`` with ``S`` rows ``e_a - e_b``). Because ``Q`` is the same
matrix in every frame it joins the per-frame Gram matrix (per-frame solvers) or the spacetime
solver's ``C`` (exact, fast path kept).

Cancel pairs (hard)
-------------------
``w_a w_b = 0`` (two shapes that must not fire together: blink vs wide, jawOpen vs
mouthClose) is a complementarity constraint: the feasible set is not convex. We use the
Audio2Face-style *second pass* [1]: solve; in every frame (and region) where both weights of a
pair exceed ``threshold`` hold the weaker one at 0 and re-solve the others with it held; repeat
while a re-solve makes another pair fire (each pass only adds held entries, so it ends). The
result is the optimum of the convex problem with those entries fixed, not the optimum of the
non-convex one (which would need a branch per pair and frame). Its marker-error cost is
measured in ``docs/controls.md``.

Temporal filters (post-solve, per-frame methods)
------------------------------------------------
* One Euro (Casiez, Roussel, Vogel 2012 [2]): a first-order low-pass
  ``y_n = a x_n + (1 - a) y_{n-1}``, ``a = 1 / (1 + fps / (2 pi f_c))``, whose cutoff follows the
  low-passed speed: ``f_c = min_cutoff + beta |dx/dt|``. For a fixed ``f_c`` the magnitude
  response at frequency ``f`` (``omega = 2 pi f / fps``) is::

      |H(f)|^2 = a^2 / (1 - 2 (1 - a) cos(omega) + (1 - a)^2)                          (R1)

  (:func:`lowpass_response`), -3 dB at ``cos omega_c = 1 - a^2 / (2 (1 - a))`` (about ``f_c``
  for ``f_c << fps``), delay ``(1 - a) / a`` frames = ``1 / (2 pi f_c)`` seconds at low
  frequencies. With ``beta = 0`` the One Euro filter *is* this low-pass at ``min_cutoff``.

  Cutoff against speed (``beta > 0``). The filter's speed estimate is ``(x_n - y_{n-1}) fps``,
  taken against its own lagging output. On a ramp ``x = v t`` the low-pass settles to a
  constant lag ``L = (1 - a) v / (a fps)`` (from ``y_n = a x_n + (1 - a) y_{n-1}`` with
  ``y_n = x_n - L``), so the estimate is ``v T_e + L`` per frame = ``v / a``: the filter sees
  ``1/a`` times the true speed. The cutoff is therefore the fixed point
  ``f_c = min_cutoff + beta v / a(f_c)``; with ``a = r / (1 + r)``, ``r = 2 pi f_c / fps`` this is
  the quadratic ``kappa f_c^2 - kappa (min_cutoff + beta v) f_c - beta v = 0``, ``kappa = 2 pi / fps``::

      f_c(v) = ((min_cutoff + beta v) + sqrt((min_cutoff + beta v)^2 + 4 beta v / kappa)) / 2       (R2)

  (:func:`one_euro_cutoff`), about ``sqrt(beta v fps / (2 pi))`` for fast motion, and the lag
  behind a ramp is ``L(v) = v (1 - a) / (a fps)`` ~ ``v / (2 pi f_c(v))``: it grows like
  ``sqrt(v)``, not like ``v`` as for a fixed cutoff. On a sine the cutoff swings with the speed
  and the filter is no longer linear; its attenuation is never below (R1) at ``min_cutoff`` and
  lies well above it (measured table in ``docs/controls.md``): fast motion is followed, slow
  jitter is removed.
* Gaussian (zero phase, whole take): :func:`core.solvers.local.smooth_weights` (one
  implementation), ``H(f) = sum_k g_k cos(omega k)`` ~ ``exp(-(sigma omega)^2 / 2)``
  (:func:`gaussian_response`), -3 dB at ``f = fps sqrt(ln 2) / (2 pi sigma)`` = 0.1325 fps /
  sigma (sigma in frames).

Both are convex combinations of input samples (non-negative taps summing to 1), so weights stay
inside any box the solver imposed.

Keyframe reduction (export)
---------------------------
:func:`reduce_keys` finds per curve the keys (a subset of the frames, with the dense values)
that reproduce the dense curve within ``tolerance`` at every frame: LINEAR by an *optimal*
dynamic program over segments (Imai and Iri's segment graph [3] with the sliding-wedge validity
test: fewest keys among all subsets of frames), CUBICSPLINE (glTF's cubic Hermite, separate
in- and out-tangents per key) greedily, each segment as long as a least-squares tangent fit (or
the chord) stays within tolerance. Both errors are measured at the frames; for LINEAR the
difference of two piecewise-linear curves with breakpoints at frames is largest at a frame, so
the tolerance holds at every time in between too.

References
----------
.. [1] NVIDIA, Audio2Face-3D blendshape solver (MIT, 2025): ``FacsSolver`` with active poses,
       cancel pairs, symmetry pairs, L1/L2 and temporal terms.
.. [2] G. Casiez, N. Roussel, D. Vogel, "1 Euro Filter: A Simple Speed-based Low-pass Filter for
       Noisy Input in Interactive Systems", CHI 2012, pp. 2527-2530.
.. [3] H. Imai, M. Iri, "Polygonal approximations of a curve -- formulations and algorithms",
       in Computational Morphology, 1988, pp. 71-86.
"""

from __future__ import annotations

import copy
import difflib
import json
import re
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Iterable, Optional, Sequence

import numpy as np

from .names import canonical

__all__ = [
    "SHAPE_FIELDS", "FORMAT", "Controls", "default_table", "validate_table", "read_table", "write_table",
    "merge_table", "resolve", "remap", "mirror_map", "mirror_pairs", "symmetry_pairs", "suggested_cancel_pairs",
    "pair_indices", "symmetry_matrix", "cancel_conflicts", "cancel_pairs", "cancel_clamp", "lowpass_alpha",
    "lowpass_response", "one_euro_cutoff", "gaussian_response", "one_euro", "filter_weights", "FILTERS", "Keys", "reduce_keys",
    "evaluate_sampler", "mirror_weights", "mirror_markers", "mirror_performance", "mirror_edit",
]

#: fields of one shape's entry in a controls table, with their defaults
SHAPE_FIELDS = {"lower": 0.0, "upper": 1.0, "gain": 1.0, "offset": 0.0, "active": True}
#: the ``format`` string of a controls table file
FORMAT = "face-retarget controls"
_TOP_KEYS = ("format", "version", "shapes", "symmetry", "cancel")


# =============================================================================================
# left / right names
# =============================================================================================
#: a leading code such as Rocketbox's ``AK_09_``, ``AU_02_``, ``SR_05_`` (numbers differ between
#: the two sides of a pair: ``SR_01_Cheek_Puff_Left`` / ``SR_02_Cheek_Puff_Right``)
_CODE = re.compile(r"^[A-Za-z]{2}_\d+_")
#: side words: ``Left``/``Right`` anywhere (camel case), ``left``/``right`` at a word start
_WORD = re.compile(r"Left|Right|(?<![A-Za-z])(?:left|right)")
#: side letters: an upper-case L or R not preceded by an upper-case letter (``_L``, ``L_``,
#: ``Leye``, ``UpL1``, ``DownR``)
_LETTER = re.compile(r"(?<![A-Z])[LR]")
_SWAP = {"Left": "Right", "Right": "Left", "left": "right", "right": "left", "L": "R", "R": "L"}
#: words after which a side token names a direction, not a face half (``jawLeft`` moves the jaw
#: to the left: its mirror is ``jawRight``, but a symmetry pair would forbid sideways motion)
_DIRECTIONAL_END = ("jaw", "mouth", "tongue", "lower", "upper", "eyesturn", "eyeslook")
_DIRECTIONAL_ARKIT = ("jawLeft", "jawRight", "mouthLeft", "mouthRight")


def _side_tokens(s: str):
    """Side words and side letters of ``s``: lists of (start, end) spans."""
    words = [m.span() for m in _WORD.finditer(s)]
    inside = {i for a, b in words for i in range(a, b)}
    letters = [m.span() for m in _LETTER.finditer(s) if m.start() not in inside]
    return words, letters


def _swapped(s: str, spans) -> str:
    out, last = [], 0
    for a, b in sorted(spans):
        out.append(s[last:a])
        out.append(_SWAP[s[a:b]])
        last = b
    out.append(s[last:])
    return "".join(out)


def _partner(name: str, lookup: dict):
    """``(mirror name, number of side tokens swapped)`` of ``name`` among ``lookup`` (stripped
    key -> names), or None. Candidates in order: every side word swapped; each side letter
    alone; every side letter."""
    code = _CODE.match(name)
    s = name[code.end():] if code else name
    words, letters = _side_tokens(s)
    cands = []
    if words:
        cands.append(words)
    cands += [[sp] for sp in letters]
    if len(letters) > 1:
        cands.append(letters)
    for spans in cands:
        key = _swapped(s, spans)
        hits = [n for n in lookup.get(key, ()) if n != name]
        if len(hits) > 1 and code:  # the same code family (AK_ with AK_) decides
            fam = code.group(0).split("_")[0]
            hits = [n for n in hits if n.split("_")[0] == fam]
        if len(hits) == 1:
            return hits[0], len(spans)
    return None


def _lookup(names: Sequence[str]) -> dict:
    lk = {}
    for n in names:
        code = _CODE.match(n)
        lk.setdefault(n[code.end():] if code else n, []).append(n)
    return lk


def _check_names(names, what="names") -> tuple:
    names = tuple(str(n) for n in names)
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise ValueError(f"{what}: duplicate names {dup[:5]}")
    return names


def mirror_map(names: Sequence[str]) -> np.ndarray:
    """Index of each name's left/right mirror (itself when it has none), (K,) int.

    Pairs are found from the names alone: side words ``Left``/``Right`` (ARKit
    ``eyeBlinkLeft``, Jeeliz ``eyeBrowLeftDown``), side letters ``_L``/``_R`` (ICT
    ``eyeBlink_L``), ``L_``/``R_`` infixes (Rocketbox ``AU_02_L_OuterBrowRaiser``), glued letters
    (the layouts' markers ``Leye_Up``, ``Mouth_UpL1``, ``Chin_R2``), with a leading code such as
    ``AK_09_`` or ``SR_05_`` ignored (its number differs between the sides). Every side token is
    swapped at once, so ``SR_07_Eye_Left_Left`` (left eye looks left) mirrors to
    ``SR_15_Eye_Right_Right``. A pair is kept only when each is the other's mirror.

    Parameters
    ----------
    names : sequence of K str

    Returns
    -------
    (K,) int: ``names[m[k]]`` is the mirror of ``names[k]``; ``m[m[k]] == k``.

    Raises
    ------
    ValueError
        Duplicate names.
    """
    names = _check_names(names)
    lk = _lookup(names)
    idx = {n: i for i, n in enumerate(names)}
    part = [_partner(n, lk) for n in names]
    m = np.arange(len(names))
    for i, p in enumerate(part):
        if p is None:
            continue
        j = idx[p[0]]
        q = part[j]
        if q is not None and q[0] == names[i]:
            m[i] = j
    return m


def mirror_pairs(names: Sequence[str]) -> list:
    """All left/right mirror pairs of ``names`` as ``[(left_or_first, other), ...]`` (name
    pairs, each once, in the order of ``names``), see :func:`mirror_map`."""
    names = _check_names(names)
    m = mirror_map(names)
    return [(names[i], names[j]) for i, j in enumerate(m) if i < j]


def _directional(name: str, partner: str) -> bool:
    """A pair whose side token is a direction (``jawLeft``), not a face half (``eyeBlinkLeft``)."""
    c = canonical(name)
    if c in _DIRECTIONAL_ARKIT or c.startswith(("eyeLookIn", "eyeLookOut")):
        return True  # horizontal gaze is conjugate (in-left with out-right), not mirrored
    code = _CODE.match(name)
    s = name[code.end():] if code else name
    words, letters = _side_tokens(s)
    lk = _lookup([partner])
    spans = None
    cands = ([words] if words else []) + [[sp] for sp in letters] + ([letters] if len(letters) > 1 else [])
    for sp in cands:
        if _swapped(s, sp) in lk:
            spans = sp
            break
    if spans is None:
        return False
    if len(spans) >= 2:
        return True  # Eye_Left_Left: the second side is a direction
    a, b = spans[0]
    rest = re.sub(r"[^0-9a-z]", "", (s[:a] + s[b:]).lower())  # the name without its side token
    return rest.endswith(_DIRECTIONAL_END)


def symmetry_pairs(names: Sequence[str]) -> list:
    """The default symmetry pairs: :func:`mirror_pairs` minus directional shapes.

    A symmetry pair ties the two sides of one expression (``eyeBlinkLeft``/``eyeBlinkRight``,
    ``AU_12_L_LipCornerPuller``/``AU_12_R_...``). Left out: pairs whose side token is a
    direction, whose mirror is the opposite motion (``jawLeft``/``jawRight``,
    ``mouthLeft``/``mouthRight``, ``SR_20_Jaw_Left``, ``HB_10_L_Tongue``, ``SR_27_Mouth_Lower_Left``,
    ``AU_61_EyesTurnLeft``), names with two side tokens (``SR_07_Eye_Left_Left``: gaze), and ARKit's
    horizontal gaze (``eyeLookIn*``/``eyeLookOut*``: the eyes turn together, in-left with
    out-right). Vertical gaze (``eyeLookUp*``) stays tied. Edit the table's ``symmetry`` list to
    change it.
    """
    return [(a, b) for a, b in mirror_pairs(names) if not _directional(a, b)]


#: suggested cancel pairs, by canonical ARKit name (blink vs wide per eye; jaw open vs mouth
#: close is a candidate for rigs whose mouthClose is a standalone lip press)
_SUGGESTED_CANCEL = (("eyeBlinkLeft", "eyeWideLeft"), ("eyeBlinkRight", "eyeWideRight"), ("jawOpen", "mouthClose"))


def suggested_cancel_pairs(names: Sequence[str]) -> list:
    """Cancel pairs worth trying on a rig with ARKit shapes: blink vs wide per eye and jaw
    open vs mouth close, as ``[(a, b), ...]`` in the rig's spelling (pairs whose shapes the rig
    lacks are left out). Not a default: a cancel pair costs marker error (docs/controls.md), and
    ARKit's own mouthClose is meant to be used *with* jawOpen."""
    names = _check_names(names)
    by = {}
    for n in names:
        by.setdefault(canonical(n), []).append(n)
    return [(by[a][0], by[b][0]) for a, b in _SUGGESTED_CANCEL if a in by and b in by]


# =============================================================================================
# the controls table (plain data, JSON)
# =============================================================================================
def _match(name: str, names: Sequence[str], where: str) -> int:
    """Index of ``name`` in ``names``: exact, else by canonical ARKit name when unique."""
    names = list(names)
    if name in names:
        return names.index(name)
    c = canonical(name)
    hits = [i for i, n in enumerate(names) if canonical(n) == c]
    if len(hits) == 1:
        return hits[0]
    if len(hits) > 1:
        raise ValueError(f"{where}: {name!r} matches several shapes by ARKit name: {[names[i] for i in hits]}; "
                         "use the exact shape name")
    close = difflib.get_close_matches(name, names, n=3)
    raise ValueError(f"{where}: no shape {name!r}" + (f"; did you mean {close}?" if close else ""))


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
            key = names[_match(key, names, f"{where}.shapes")]
        if key in norm:
            raise ValueError(f"{where}.shapes: shape {key!r} is given twice (as {name!r})")
        norm[key] = e
    out["shapes"] = norm
    for part in ("symmetry", "cancel"):
        if part in table:
            pairs = _pairs_of(table[part], f"{where}.{part}")
            if names is not None:
                pairs = [[names[_match(a, names, f"{where}.{part}")], names[_match(b, names, f"{where}.{part}")]]
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
    names = _check_names(names)
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
        names = _check_names(names)
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
    names = _check_names(names)
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


# =============================================================================================
# per-shape: gain and offset
# =============================================================================================
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


def _weights(W, name: str = "W") -> np.ndarray:
    W = np.asarray(W, dtype=np.float64)
    if W.ndim != 2:
        raise ValueError(f"{name}: expected (T, K) weights, got shape {W.shape}")
    return W


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
    W = _weights(W)
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


# =============================================================================================
# symmetry and cancel pairs
# =============================================================================================
def pair_indices(pairs, names: Sequence[str], where: str = "pairs") -> np.ndarray:
    """``[(a, b), ...]`` of names (exact or canonical ARKit names) or indices -> (P, 2) int."""
    names = _check_names(names)
    out = []
    for i, p in enumerate(pairs):
        if len(p) != 2:
            raise ValueError(f"{where}[{i}]: expected a pair, got {p!r}")
        row = [x if isinstance(x, (int, np.integer)) else _match(str(x), names, f"{where}[{i}]") for x in p]
        for x in row:
            if not 0 <= int(x) < len(names):
                raise ValueError(f"{where}[{i}]: index {x} is outside [0, {len(names)})")
        if row[0] == row[1]:
            raise ValueError(f"{where}[{i}]: a pair needs two different shapes")
        out.append([int(row[0]), int(row[1])])
    return np.asarray(out, np.int64).reshape(-1, 2)


def _index_pairs(pairs, K: int, name: str) -> np.ndarray:
    P = np.asarray(pairs if len(pairs) else np.zeros((0, 2)), dtype=np.int64).reshape(-1, 2)
    if P.size and (P.min() < 0 or P.max() >= K):
        raise ValueError(f"{name}: indices must be in [0, {K}), got {P.min()}..{P.max()}")
    if (P[:, 0] == P[:, 1]).any():
        raise ValueError(f"{name}: a pair needs two different shapes")
    return P


def symmetry_matrix(pairs, K: int, weight: float = 1.0) -> np.ndarray:
    """``Q`` with ``w^T Q w = weight * sum_pairs (w_a - w_b)^2`` (the pairs' graph Laplacian).

    Pass it as the ``quadratic`` option of :func:`core.solvers.baselines.range_pf`,
    :func:`~core.solvers.baselines.prior_pf`, :class:`~core.solvers.spacetime.SpacetimeSolver`,
    :func:`~core.solvers.local.local_precompute` and
    :class:`~core.solvers.geometric.GeometricSolver`, which scale it by their data term's
    ``sigma_max^2`` (module docstring).

    Parameters
    ----------
    pairs : (P, 2) int (see :func:`pair_indices` for names)
    K : int
    weight : float >= 0, the relative ``mu_s``

    Returns
    -------
    (K, K) float, symmetric positive semi-definite.
    """
    w = float(weight)
    if not (np.isfinite(w) and w >= 0):
        raise ValueError(f"weight: expected a finite number >= 0, got {weight}")
    P = _index_pairs(pairs, K, "pairs")
    Q = np.zeros((K, K))
    np.add.at(Q, (P[:, 0], P[:, 0]), w)
    np.add.at(Q, (P[:, 1], P[:, 1]), w)
    np.add.at(Q, (P[:, 0], P[:, 1]), -w)
    np.add.at(Q, (P[:, 1], P[:, 0]), -w)
    return Q


def cancel_conflicts(W, pairs, threshold: float = 0.0) -> np.ndarray:
    """(N, P) bool: rows where both weights of a cancel pair exceed ``threshold``."""
    W = _weights(W)
    P = _index_pairs(pairs, W.shape[1], "pairs")
    with np.errstate(invalid="ignore"):
        return (W[:, P[:, 0]] > threshold) & (W[:, P[:, 1]] > threshold)


def _weaker(W, P, conflict):
    """(rows, shapes) of the weaker weight of each conflicting pair (ties: the second)."""
    r, p = np.nonzero(conflict)
    a, b = P[p, 0], P[p, 1]
    k = np.where(W[r, a] >= W[r, b], b, a)
    return r, k


def cancel_clamp(W, pairs, threshold: float = 0.0) -> np.ndarray:
    """The cheap alternative to :func:`cancel_pairs`: the weaker weight of every firing pair
    set to 0 without re-solving (the marker error it costs is larger, docs/controls.md)."""
    W = _weights(W).copy()
    P = _index_pairs(pairs, W.shape[1], "pairs")
    for _ in range(len(P) + 1):
        c = cancel_conflicts(W, P, threshold)
        if not c.any():
            break
        r, k = _weaker(W, P, c)
        W[r, k] = 0.0
    return W


def cancel_pairs(solve: Callable, W, pairs, threshold: float = 0.0, max_passes: int = 8):
    """Cancel pairs by re-solving with the weaker shape held at 0 (Audio2Face's second pass [1]).

    ``w_a w_b = 0`` is not convex. Pass ``n``: find the rows (frames, or frame-region problems)
    where both weights of a pair exceed ``threshold``; hold the weaker at 0 there (for good:
    the held set only grows); re-solve everything with ``solve(zero)``. Stop when no pair fires.
    A re-solve can make another pair fire (the freed marker residual goes somewhere), hence the
    passes; each adds held entries, so the loop ends. After ``max_passes`` the remaining firing
    pairs are clamped (``info["clamped"]``, 0 in every case measured).

    Parameters
    ----------
    solve : callable ``zero (N, K) bool -> (N, K) weights``
        The method's solve with those weights held at 0, e.g.
        ``lambda z: range_pf(B, S, lo, hi, valid, ridge, zero=z)``,
        ``lambda z: SpacetimeSolver(...).solve(zero=z)``,
        ``lambda z: problem.solve(S, valid, zero=z.reshape(T, R, K)).reshape(T * R, K)`` (local,
        per region), ``lambda z: GeometricSolver(...).solve(frames, zero=z).weights``.
    W : (N, K) float
        The first pass (the method's result without cancel pairs).
    pairs : (P, 2) int
    threshold : float >= 0
        "Fires": above this weight (0: any positive weight, the complementarity ``w_a w_b = 0``).
    max_passes : int

    Returns
    -------
    W : (N, K) float, no pair with both weights above ``threshold``
    info : dict ``passes``, ``held`` (N, K) bool, ``rows`` (rows that changed), ``clamped``

    Raises
    ------
    ValueError
        ``threshold < 0``; a held weight the solve did not bring to ``<= threshold`` (its lower
        bound is above the threshold: the pair cannot be cancelled).
    """
    W = _weights(W).copy()
    N, K = W.shape
    P = _index_pairs(pairs, K, "pairs")
    thr = float(threshold)
    if not (np.isfinite(thr) and thr >= 0):
        raise ValueError(f"threshold: expected a finite number >= 0, got {threshold}")
    held = np.zeros((N, K), bool)
    info = {"passes": 0, "held": held, "rows": 0, "clamped": 0}
    if not len(P):
        return W, info
    touched = np.zeros(N, bool)
    for _ in range(int(max_passes)):
        c = cancel_conflicts(W, P, thr)
        if not c.any():
            break
        r, k = _weaker(W, P, c)
        if held[r, k].any():
            i = int(np.flatnonzero(held[r, k])[0])
            raise ValueError(f"cancel pairs: shape {int(k[i])} is held at 0 in row {int(r[i])} but the solve gave "
                             f"{W[r[i], k[i]]:g} > threshold {thr:g} (its lower bound?); a cancel pair needs shapes "
                             "that can reach 0")
        held[r, k] = True
        touched[r] = True
        W = _weights(solve(held.copy()), "solve(zero)").copy()
        if W.shape != (N, K):
            raise ValueError(f"solve(zero) returned {W.shape}, expected ({N}, {K})")
        info["passes"] += 1
    c = cancel_conflicts(W, P, thr)
    if c.any():
        r, k = _weaker(W, P, c)
        W[r, k] = 0.0
        info["clamped"] = int(len(r))
    info["rows"] = int(touched.sum())
    return W, info


# =============================================================================================
# temporal filters
# =============================================================================================
FILTERS = ("none", "gaussian", "one_euro")


def _fps(fps) -> float:
    f = float(fps)
    if not (np.isfinite(f) and f > 0):
        raise ValueError(f"fps: expected a positive frame rate, got {fps}")
    return f


def lowpass_alpha(cutoff, fps) -> np.ndarray:
    """Smoothing factor of the first-order low-pass at ``cutoff`` Hz:
    ``a = 1 / (1 + tau / T_e)``, ``tau = 1 / (2 pi f_c)``, ``T_e = 1 / fps`` (Casiez et al. 2012 [2])."""
    r = 2.0 * np.pi * np.asarray(cutoff, dtype=np.float64) / _fps(fps)
    return r / (1.0 + r)


def lowpass_response(freq, fps, cutoff) -> np.ndarray:
    """Magnitude response (R1) of the One Euro filter's first-order low-pass at a fixed cutoff:
    ``|H| = a / sqrt(1 - 2 (1 - a) cos(2 pi f / fps) + (1 - a)^2)`` (module docstring)."""
    a = lowpass_alpha(cutoff, fps)
    w = 2.0 * np.pi * np.asarray(freq, dtype=np.float64) / _fps(fps)
    return a / np.sqrt(1.0 - 2.0 * (1.0 - a) * np.cos(w) + (1.0 - a) ** 2)


def one_euro_cutoff(speed, fps, min_cutoff: float = 1.0, beta: float = 0.0):
    """Steady-state cutoff (Hz) and lag of the One Euro filter on a ramp of ``speed``: (R2) of
    the module docstring. Returns ``(f_c, lag)`` (lag in the signal's units: ``v (1 - a) / (a fps)``)."""
    v = np.abs(np.asarray(speed, dtype=np.float64))
    kappa = 2.0 * np.pi / _fps(fps)
    b = min_cutoff + beta * v
    fc = 0.5 * (b + np.sqrt(b * b + 4.0 * beta * v / kappa))
    a = lowpass_alpha(fc, fps)
    return fc, v * (1.0 - a) / (a * _fps(fps))


def gaussian_response(freq, fps, sigma: float, truncate: float = 4.0) -> np.ndarray:
    """Frequency response of the zero-phase Gaussian of :func:`core.solvers.local.smooth_weights`
    (``scipy.ndimage.gaussian_filter1d``, kernel truncated at ``truncate * sigma`` frames):
    ``H(f) = sum_k g_k cos(2 pi f k / fps)``, real (no phase), ~ ``exp(-2 (pi sigma f / fps)^2)``."""
    s = float(sigma)
    w = 2.0 * np.pi * np.asarray(freq, dtype=np.float64) / _fps(fps)
    if s == 0:
        return np.ones_like(w)
    r = int(truncate * s + 0.5)
    k = np.arange(-r, r + 1)
    g = np.exp(-0.5 * (k / s) ** 2)
    g /= g.sum()
    return np.tensordot(np.cos(np.multiply.outer(w, k)), g, axes=([-1], [0]))


def one_euro(W, fps, min_cutoff: float = 1.0, beta: float = 0.0, d_cutoff: float = 1.0) -> np.ndarray:
    """The One Euro filter (Casiez, Roussel, Vogel 2012 [2]) on every column of ``W``, causal.

    Per sample n (period ``T_e = 1 / fps``)::

        dx_n  = (x_n - y_{n-1}) / T_e                 speed against the previous output
        ed_n  = LP(dx_n; d_cutoff)                    its first-order low-pass
        f_n   = min_cutoff + beta |ed_n|              cutoff that follows the speed
        y_n   = LP(x_n; f_n)                          y_n = a x_n + (1 - a) y_{n-1}

    with ``a = lowpass_alpha(f, fps)``; ``y_0 = x_0``, ``ed_0 = 0``. Response: module docstring.

    Parameters
    ----------
    W : (T, K) float, finite (fill gaps first, :func:`core.gaps.fill_gaps`)
    fps : float > 0
    min_cutoff : float > 0, Hz (jitter at rest)
    beta : float >= 0, speed coefficient (lag during fast motion)
    d_cutoff : float > 0, Hz (the derivative's low-pass)

    Returns
    -------
    (T, K) float64
    """
    W = _weights(W)
    f = _fps(fps)
    for name, v, lo in (("min_cutoff", min_cutoff, 0.0), ("d_cutoff", d_cutoff, 0.0)):
        if not (np.isfinite(v) and v > lo):
            raise ValueError(f"{name}: expected a positive frequency in Hz, got {v}")
    if not (np.isfinite(beta) and beta >= 0):
        raise ValueError(f"beta: expected a finite number >= 0, got {beta}")
    if not np.isfinite(W).all():
        raise ValueError("W: contains NaN/inf; fill the gaps first (core.gaps.fill_gaps)")
    out = np.empty_like(W)
    if not len(W):
        return out
    ad = lowpass_alpha(d_cutoff, f)
    y = W[0].copy()
    ed = np.zeros(W.shape[1])
    out[0] = y
    two_pi_te = 2.0 * np.pi / f
    for n in range(1, len(W)):
        x = W[n]
        ed = ad * ((x - y) * f) + (1.0 - ad) * ed
        r = two_pi_te * (min_cutoff + beta * np.abs(ed))
        a = r / (1.0 + r)
        y = a * x + (1.0 - a) * y
        out[n] = y
    # each output is a convex combination of inputs: within their range but for rounding
    return np.clip(out, W.min(axis=0), W.max(axis=0), out=out)


def filter_weights(W, fps, kind: str = "one_euro", *, sigma: float = 1.0, min_cutoff: float = 1.0,
                   beta: float = 0.0, d_cutoff: float = 1.0) -> np.ndarray:
    """Post-solve temporal filter of weight curves, one entry point for every per-frame method.

    Parameters
    ----------
    W : (T, K) float, finite
    fps : float > 0
    kind : {"none", "gaussian", "one_euro"}
        ``"gaussian"``: zero-phase Gaussian of ``sigma`` frames over the whole take
        (:func:`core.solvers.local.smooth_weights`, response :func:`gaussian_response`);
        ``"one_euro"``: causal One Euro (:func:`one_euro`); ``"none"``: a copy.
    sigma, min_cutoff, beta, d_cutoff
        The filters' settings (module docstring for their responses).

    Returns
    -------
    (T, K) float64. Both filters average input samples with non-negative weights summing to 1,
    so any box bounds of the solve still hold.
    """
    if kind not in FILTERS:
        close = difflib.get_close_matches(str(kind), FILTERS, n=1)
        raise ValueError(f"kind: expected one of {FILTERS}, got {kind!r}" + (f"; did you mean {close[0]!r}?" if close else ""))
    W = _weights(W)
    if kind == "none":
        return W.copy()
    if kind == "gaussian":
        from .solvers.local import smooth_weights

        if not np.isfinite(W).all():
            raise ValueError("W: contains NaN/inf; fill the gaps first (core.gaps.fill_gaps)")
        _fps(fps)
        return smooth_weights(W, sigma)
    return one_euro(W, fps, min_cutoff, beta, d_cutoff)


# =============================================================================================
# keyframe reduction
# =============================================================================================
INTERPOLATIONS = ("LINEAR", "CUBICSPLINE")


def _hermite(s):
    """Cubic Hermite basis (h00, h10, h01, h11) at s in [0, 1]."""
    s2, s3 = s * s, s * s * s
    return 2 * s3 - 3 * s2 + 1, s3 - 2 * s2 + s, -2 * s3 + 3 * s2, s3 - s2


def evaluate_sampler(times, values, t, interpolation: str = "LINEAR", in_tangents=None, out_tangents=None):
    """A glTF 2.0 animation sampler evaluated at times ``t`` (glTF 2.0 Appendix C).

    ``LINEAR``: linear between keys; ``CUBICSPLINE``: on ``[t_k, t_{k+1}]`` with ``d = t_{k+1} -
    t_k`` and ``s = (t - t_k) / d``, ``v = h00(s) v_k + d h10(s) b_k + h01(s) v_{k+1} + d h11(s)
    a_{k+1}`` (``b_k`` the out-tangent of key k, ``a_{k+1}`` the in-tangent of key k+1, per
    second); held at the end values outside the keys.

    Parameters
    ----------
    times : (n,) increasing; values, in_tangents, out_tangents : (n, K); t : (m,)

    Returns
    -------
    (m, K) float64
    """
    times = np.asarray(times, dtype=np.float64)
    V = np.asarray(values, dtype=np.float64)
    V = V[:, None] if V.ndim == 1 else V
    t = np.asarray(t, dtype=np.float64)
    if interpolation not in INTERPOLATIONS:
        raise ValueError(f"interpolation: expected one of {INTERPOLATIONS}, got {interpolation!r}")
    if len(times) == 1:
        return np.repeat(V[:1], len(t), axis=0)
    tc = np.clip(t, times[0], times[-1])
    k = np.clip(np.searchsorted(times, tc, side="right") - 1, 0, len(times) - 2)
    d = times[k + 1] - times[k]
    s = ((tc - times[k]) / d)[:, None]
    if interpolation == "LINEAR":
        return V[k] * (1 - s) + V[k + 1] * s
    a = np.asarray(in_tangents, dtype=np.float64).reshape(V.shape)
    b = np.asarray(out_tangents, dtype=np.float64).reshape(V.shape)
    h00, h10, h01, h11 = _hermite(s)
    return h00 * V[k] + d[:, None] * h10 * b[k] + h01 * V[k + 1] + d[:, None] * h11 * a[k + 1]


@dataclass(frozen=True, eq=False)
class Keys:
    """Reduced keys of K curves (:func:`reduce_keys`).

    Attributes
    ----------
    frames : tuple of K (n_k,) int arrays, increasing, first 0 and last T-1
    values : tuple of K (n_k,) float arrays (the dense curve's values at those frames)
    in_tangents, out_tangents : tuple of K (n_k,) float arrays (weight per second), CUBICSPLINE only
    fps : float
    n_frames : int (T of the dense curves)
    interpolation : "LINEAR" or "CUBICSPLINE"
    tolerance : float, the largest allowed |reduced - dense| at a frame
    names : tuple of K str, optional
    """

    frames: tuple
    values: tuple
    in_tangents: Optional[tuple]
    out_tangents: Optional[tuple]
    fps: float
    n_frames: int
    interpolation: str
    tolerance: float
    names: Optional[tuple] = None

    @property
    def counts(self) -> np.ndarray:
        """(K,) keys per curve."""
        return np.array([len(f) for f in self.frames], dtype=np.int64)

    def evaluate(self, t=None) -> np.ndarray:
        """The reduced curves at times ``t`` seconds (default: every frame), (m, K)."""
        t = np.arange(self.n_frames) / self.fps if t is None else np.asarray(t, dtype=np.float64)
        out = np.empty((len(t), len(self.frames)))
        for c, (f, v) in enumerate(zip(self.frames, self.values)):
            if self.interpolation == "LINEAR":
                out[:, c] = evaluate_sampler(f / self.fps, v, t)[:, 0]
            else:
                out[:, c] = evaluate_sampler(f / self.fps, v, t, "CUBICSPLINE", self.in_tangents[c],
                                             self.out_tangents[c])[:, 0]
        return out

    def grid(self):
        """The curves on the union of their key frames: what one glTF sampler stores.

        glTF animates all morph weights of a node through one sampler (one time grid, one
        interpolation); each curve is therefore written at every key frame of every curve. The
        extra keys lie on the curve's own interpolant: a LINEAR curve gets collinear points, a
        CUBICSPLINE curve is split at the new time with value and derivative of its Hermite
        segment (in-tangent = out-tangent), which reproduces the same cubic pieces exactly.

        Returns
        -------
        frames : (n,) int; times : (n,) float seconds; values : (n, K);
        in_tangents, out_tangents : (n, K) (CUBICSPLINE) or None
        """
        F = np.unique(np.concatenate(self.frames))
        t = F / self.fps
        V = self.evaluate(t)
        if self.interpolation == "LINEAR":
            return F, t, V, None, None
        A = np.empty_like(V)
        Bt = np.empty_like(V)
        for c, (f, v) in enumerate(zip(self.frames, self.values)):
            a, b = self.in_tangents[c], self.out_tangents[c]
            tk = f / self.fps
            k = np.clip(np.searchsorted(tk, t, side="right") - 1, 0, len(tk) - 2)
            d = tk[k + 1] - tk[k]
            s = (t - tk[k]) / d
            # derivative of the Hermite segment, per second
            dh00, dh10, dh01, dh11 = 6 * s**2 - 6 * s, 3 * s**2 - 4 * s + 1, -6 * s**2 + 6 * s, 3 * s**2 - 2 * s
            der = (dh00 * v[k] + dh01 * v[k + 1]) / d + dh10 * b[k] + dh11 * a[k + 1]
            A[:, c] = der
            Bt[:, c] = der
            own = np.searchsorted(F, f)
            A[own, c] = a
            Bt[own, c] = b
        return F, t, V, A, Bt


def _linear_dp(Y, tol):
    """Optimal LINEAR keys for every column of Y (T, K): fewest keys (subset of frames, dense
    values) with |chord - y| <= tol at every frame. Imai-Iri segment graph: segment (i, j) is
    valid iff its slope lies in the wedge of slopes through (k, y_k +- tol) for i < k < j; the
    shortest path from frame 0 to T-1 in the graph of valid segments (a DP in frame order).
    Work: the sum over starts of the wedge's length, vectorised over the curves."""
    T, K = Y.shape
    cost = np.full((K, T), np.iinfo(np.int64).max // 2, dtype=np.int64)
    parent = np.zeros((K, T), dtype=np.int64)
    cost[:, 0] = 1
    # curves the chord from the first to the last frame already fits (constant curves: shapes the
    # solve never used) need two keys; leaving them out of the DP saves its O(T^2) worst case
    s = np.arange(T) / max(T - 1, 1)
    whole = (np.abs(Y[0] + (Y[-1] - Y[0]) * s[:, None] - Y) <= tol).all(0)
    cost[whole, -1] = 2
    kk = np.flatnonzero(~whole)
    for i in range(T - 1):
        rows = kk
        j0 = i + 1
        lo_run = np.full(K, -np.inf)
        hi_run = np.full(K, np.inf)
        yi = Y[i]
        ci = cost[:, i] + 1
        chunk = 32
        while len(rows) and j0 < T:
            j1 = min(T, j0 + chunk)
            js = np.arange(j0, j1)
            dt = (js - i).astype(np.float64)
            Yr = Y[j0:j1][:, rows].T  # (n_rows, n)
            base = yi[rows][:, None]
            slope = (Yr - base) / dt
            lo_k = (Yr - tol - base) / dt
            hi_k = (Yr + tol - base) / dt
            # wedge over the interior points i < k < j: running max/min of the previous columns
            lo_prev = np.maximum.accumulate(np.concatenate([lo_run[rows][:, None], lo_k], axis=1), axis=1)[:, :-1]
            hi_prev = np.minimum.accumulate(np.concatenate([hi_run[rows][:, None], hi_k], axis=1), axis=1)[:, :-1]
            ok = (slope >= lo_prev) & (slope <= hi_prev)
            better = ok & (ci[rows][:, None] < cost[rows][:, j0:j1])
            if better.any():
                r, c = np.nonzero(better)
                cost[rows[r], j0 + c] = ci[rows[r]]
                parent[rows[r], j0 + c] = i
            lo_run[rows] = np.maximum(lo_prev[:, -1], lo_k[:, -1])
            hi_run[rows] = np.minimum(hi_prev[:, -1], hi_k[:, -1])
            keep = lo_run[rows] <= hi_run[rows]  # the wedge is still open: longer segments may be valid
            rows = rows[keep]
            j0 = j1
            chunk *= 2
    frames = []
    for c in range(K):
        path = [T - 1]
        while path[-1] > 0:
            path.append(int(parent[c, path[-1]]))
        frames.append(np.asarray(path[::-1], dtype=np.int64))
    return frames


def _linear_dp_shared(Y, tol):
    """Optimal LINEAR keys shared by all columns of Y: a segment is valid when it is valid for
    every curve (the same DP as :func:`_linear_dp` on the intersection of the segment graphs)."""
    T, K = Y.shape
    live = np.flatnonzero(np.ptp(Y, axis=0) > 0)  # constant curves fit every chord exactly
    Y = Y[:, live]
    cost = np.full(T, np.iinfo(np.int64).max // 2, dtype=np.int64)
    parent = np.zeros(T, dtype=np.int64)
    cost[0] = 1
    for i in range(T - 1):
        j0 = i + 1
        lo_run = np.full(len(live), -np.inf)
        hi_run = np.full(len(live), np.inf)
        yi = Y[i][:, None]
        chunk = 32
        while j0 < T:
            j1 = min(T, j0 + chunk)
            dt = np.arange(j0 - i, j1 - i, dtype=np.float64)
            Yr = Y[j0:j1].T
            slope = (Yr - yi) / dt
            lo_k = (Yr - tol - yi) / dt
            hi_k = (Yr + tol - yi) / dt
            lo_prev = np.maximum.accumulate(np.concatenate([lo_run[:, None], lo_k], axis=1), axis=1)[:, :-1]
            hi_prev = np.minimum.accumulate(np.concatenate([hi_run[:, None], hi_k], axis=1), axis=1)[:, :-1]
            ok = ((slope >= lo_prev) & (slope <= hi_prev)).all(0)
            better = ok & (cost[i] + 1 < cost[j0:j1])
            cost[j0:j1][better] = cost[i] + 1
            parent[j0:j1][better] = i
            lo_run = np.maximum(lo_prev[:, -1], lo_k[:, -1])
            hi_run = np.minimum(hi_prev[:, -1], hi_k[:, -1])
            if (lo_run > hi_run).any():
                break  # some curve's wedge closed: no longer segment from i is valid
            j0 = j1
            chunk *= 2
    path = [T - 1]
    while path[-1] > 0:
        path.append(int(parent[path[-1]]))
    return np.asarray(path[::-1], dtype=np.int64)


def _cubic_fit(y, i, j, tol):
    """Best cubic Hermite segment from frame i to j with end values y_i, y_j for curves y (K', T)
    rows: least-squares unit-interval tangents (m0, m1) over the interior frames (biased to
    the chord's by a tiny ridge), accepted when within tol, else the chord if that is.
    Returns ok (K',), m0, m1 (K',)."""
    n = j - i  # (K',) segment lengths
    L = int(n.max()) - 1
    Kc = len(y)
    lin = y[np.arange(Kc), j] - y[np.arange(Kc), i]
    if L <= 0:
        return np.ones(Kc, bool), lin, lin
    off = np.arange(1, L + 1)[None]
    mask = off < n[:, None]
    k = np.minimum(i[:, None] + off, y.shape[1] - 1)
    s = off / n[:, None]
    h00, h10, h01, h11 = _hermite(s)
    yi, yj = y[np.arange(Kc), i][:, None], y[np.arange(Kc), j][:, None]
    yk = y[np.arange(Kc)[:, None], k]
    base = h00 * yi + h01 * yj
    chord = yi + (yj - yi) * s
    r = np.where(mask, yk - base - (h10 + h11) * lin[:, None], 0.0)  # residual after the chord's tangents
    a11 = np.where(mask, h10 * h10, 0).sum(1)
    a12 = np.where(mask, h10 * h11, 0).sum(1)
    a22 = np.where(mask, h11 * h11, 0).sum(1)
    b1 = (np.where(mask, h10, 0) * r).sum(1)
    b2 = (np.where(mask, h11, 0) * r).sum(1)
    eps = 1e-9 * (a11 + a22) + 1e-300
    a11, a22 = a11 + eps, a22 + eps
    det = a11 * a22 - a12 * a12
    d0 = (a22 * b1 - a12 * b2) / det
    d1 = (a11 * b2 - a12 * b1) / det
    m0, m1 = lin + d0, lin + d1
    fit = base + h10 * m0[:, None] + h11 * m1[:, None]
    err_c = np.where(mask, np.abs(fit - yk), 0).max(1)
    err_l = np.where(mask, np.abs(chord - yk), 0).max(1)
    ok_c = err_c <= tol
    ok_l = err_l <= tol
    m0 = np.where(ok_c, m0, lin)
    m1 = np.where(ok_c, m1, lin)
    return ok_c | ok_l, m0, m1


def _cubic_greedy(Y, tol):
    """CUBICSPLINE keys per column of Y (T, K): from each key, the farthest next key whose
    segment fits (galloping 1, 2, 4, ... frames, then bisection), all curves in lock-step.
    Not optimal (validity is not monotone in the length); every accepted segment is checked."""
    T, K = Y.shape
    y = Y.T.copy()
    keys = [[0] for _ in range(K)]
    tin = [[0.0] for _ in range(K)]  # unit-interval tangents, converted at the end
    tout = [[] for _ in range(K)]
    i = np.zeros(K, np.int64)
    good = np.minimum(i + 1, T - 1)
    gm0 = y[np.arange(K), good] - y[np.arange(K), i]
    gm1 = gm0.copy()
    bad = np.full(K, -1)
    step = np.full(K, 2)
    live = np.flatnonzero(i < T - 1)
    while len(live):
        # candidate per live curve: gallop (bad < 0) or bisect
        gallop = bad[live] < 0
        cand = np.where(gallop, np.minimum(i[live] + step[live], T - 1), (good[live] + bad[live]) // 2)
        test = cand > good[live]
        if test.any():
            rows = live[test]
            ok, m0, m1 = _cubic_fit(y[rows], i[rows], cand[test], tol)
            rr, cc = rows[ok], cand[test][ok]
            good[rr], gm0[rr], gm1[rr] = cc, m0[ok], m1[ok]
            fail = rows[~ok]
            bad[fail] = cand[test][~ok]
            step[rr] *= 2
        # a curve is done searching when its gallop reached the end or bisection closed
        done = (good[live] == T - 1) | ((bad[live] >= 0) & (bad[live] - good[live] <= 1))
        for c in live[done]:
            j = int(good[c])
            d = (j - int(i[c])) / 1.0
            tout[c].append(gm0[c] / d)
            tin[c].append(gm1[c] / d)
            keys[c].append(j)
            i[c] = j
            if j < T - 1:
                good[c] = j + 1
                gm0[c] = gm1[c] = y[c, j + 1] - y[c, j]
                bad[c] = -1
                step[c] = 2
        live = np.flatnonzero(i < T - 1)
    frames, ins, outs = [], [], []
    for c in range(K):
        frames.append(np.asarray(keys[c], np.int64))
        ins.append(np.asarray(tin[c], np.float64))  # per frame; the first key's in-tangent is unused
        outs.append(np.asarray(tout[c] + [0.0], np.float64))  # the last key's out-tangent is unused
    return frames, ins, outs


def _cubic_greedy_shared(Y, tol):
    """CUBICSPLINE keys shared by all columns: :func:`_cubic_greedy`'s search, a segment
    accepted when every curve fits it (tangents per curve)."""
    T, K = Y.shape
    y = Y.T.copy()
    ar = np.arange(K)
    keys, tin, tout = [0], [np.zeros(K)], []
    i = 0
    while i < T - 1:
        good = i + 1
        gm0 = gm1 = y[:, good] - y[:, i]
        bad, step = -1, 2
        while True:
            cand = min(i + step, T - 1) if bad < 0 else (good + bad) // 2
            if cand > good:
                ok, m0, m1 = _cubic_fit(y, np.full(K, i), np.full(K, cand), tol)
                if ok.all():
                    good, gm0, gm1 = cand, m0, m1
                    step *= 2
                else:
                    bad = cand
            if good == T - 1 or (bad >= 0 and bad - good <= 1):
                break
        d = float(good - i)
        tout.append(gm0 / d)
        tin.append(gm1 / d)
        keys.append(good)
        i = good
    tout.append(np.zeros(K))
    fr = np.asarray(keys, np.int64)
    A, B = np.asarray(tin), np.asarray(tout)
    return [fr] * K, [A[:, c] for c in ar], [B[:, c] for c in ar]


def reduce_keys(W, fps, tolerance: float = 0.005, interpolation: str = "LINEAR", names=None,
                shared: bool = False) -> Keys:
    """Per curve, few keys that reproduce the dense curve within ``tolerance`` at every frame.

    Keys sit on frames and take the dense values there (an animator's keys lie on the curve);
    the first and last frames are always keys.

    * ``"LINEAR"``: the fewest such keys, exactly (module docstring: Imai-Iri's segment graph
      with the wedge test, a dynamic program in frame order). Linear interpolation between
      frames of both curves means the bound holds at every time, not only at frames.
    * ``"CUBICSPLINE"``: glTF's cubic Hermite with separate in- and out-tangents per key (so
      each segment has two free tangents); segments are grown greedily from each key as long as
      the least-squares tangents (or the chord) keep every frame within tolerance. Not
      provably fewest; never worse per segment than the chord.

    Parameters
    ----------
    W : (T, K) float, finite
    fps : float > 0
    tolerance : float > 0 (weight units; default 0.005)
    interpolation : {"LINEAR", "CUBICSPLINE"}
    names : sequence of K str, optional (kept on the result for the writers)
    shared : bool
        One key set for all curves (a segment must fit every curve): the fewest keys of a glTF
        sampler, which shares its times across all morph targets (LINEAR: optimal, the same DP
        on the intersection of the curves' segment graphs). Default: keys per curve.

    Returns
    -------
    Keys (``counts`` per curve; ``evaluate()`` the reduced curves at every frame; ``grid()`` the
    one-sampler layout for glTF).

    Raises
    ------
    ValueError
        Non-finite weights, tolerance <= 0, unknown interpolation, names of the wrong length.
    """
    W = _weights(W)
    f = _fps(fps)
    tol = float(tolerance)
    if not (np.isfinite(tol) and tol > 0):
        raise ValueError(f"tolerance: expected a positive weight difference, got {tolerance}")
    if interpolation not in INTERPOLATIONS:
        raise ValueError(f"interpolation: expected one of {INTERPOLATIONS}, got {interpolation!r}")
    if not np.isfinite(W).all():
        raise ValueError("W: contains NaN/inf; fill the gaps first (core.gaps.fill_gaps)")
    T, K = W.shape
    if T == 0:
        raise ValueError("W: needs at least one frame")
    if names is not None:
        names = _check_names(names)
        if len(names) != K:
            raise ValueError(f"names: expected {K} names, got {len(names)}")
    # the acceptance tests compare with <=; shave a hair off so float rounding in the test and in
    # evaluation (a few ulps of the values) cannot push a frame past the tolerance
    t_eff = tol * (1.0 - 1e-9) - 8 * np.finfo(float).eps * max(1.0, float(np.abs(W).max(initial=0.0)))
    if T == 1:
        fr = [np.zeros(1, np.int64) for _ in range(K)]
        vals = tuple(W[0, c:c + 1].copy() for c in range(K))
        tan = tuple(np.zeros(1) for _ in range(K)) if interpolation == "CUBICSPLINE" else None
        return Keys(tuple(fr), vals, tan, tan, f, T, interpolation, tol, names)
    if interpolation == "LINEAR":
        frames = [_linear_dp_shared(W, t_eff)] * K if shared else _linear_dp(W, t_eff)
        return Keys(tuple(frames), tuple(W[fr_, c].copy() for c, fr_ in enumerate(frames)), None, None, f, T,
                    interpolation, tol, names)
    frames, ins, outs = (_cubic_greedy_shared if shared else _cubic_greedy)(W, t_eff)
    # unit-interval tangents -> per second: the segment's tangent m over d frames is m / (d / fps)
    tin, tout = [], []
    for fr_, a, b in zip(frames, ins, outs):
        tin.append(a * f)
        tout.append(b * f)
    return Keys(tuple(frames), tuple(W[fr_, c].copy() for c, fr_ in enumerate(frames)), tuple(tin), tuple(tout), f, T,
                interpolation, tol, names)


# =============================================================================================
# mirror
# =============================================================================================
def mirror_weights(W, names: Sequence[str], pairs=None) -> np.ndarray:
    """Left/right swapped weight curves: ``W'[:, k] = W[:, m[k]]`` (:func:`mirror_map`, or the
    given name ``pairs``); shapes without a mirror (jawOpen) keep their curve."""
    W = _weights(W)
    names = _check_names(names)
    if W.shape[1] != len(names):
        raise ValueError(f"W: expected {len(names)} columns (one per name), got {W.shape[1]}")
    m = _perm(names, pairs)
    return W[:, m].copy()


def _perm(names, pairs):
    if pairs is None:
        return mirror_map(names)
    m = np.arange(len(names))
    for a, b in pair_indices(pairs, names):
        if m[a] != a or m[b] != b:
            raise ValueError(f"pairs: shape {names[a] if m[a] != a else names[b]!r} is in two mirror pairs")
        m[a], m[b] = b, a
    return m


def mirror_markers(positions, names: Sequence[str], center: Optional[float] = None, axis: int = 0) -> np.ndarray:
    """Marker trajectories mirrored left/right: each marker takes its mirror's trajectory
    (names paired by :func:`mirror_map`, as the bundled layouts name them: ``Leye_Up`` /
    ``Reye_Up``, ``Mouth_UpL1`` / ``Mouth_UpR1``, ``Chin_L2`` / ``Chin_R2``), reflected in the
    plane ``x[axis] = center``.

    The faces look down +Z with +Y up, so left/right is ``axis = 0`` (x). Mirror stabilised
    markers (head frame), or captures whose head faces +Z.

    Parameters
    ----------
    positions : (T, M, 3) or (M, 3) float, NaN = missing (stays missing)
    names : M marker names
    center : float, optional
        The mirror plane; default the mean ``x[axis]`` of the markers without a mirror (the
        midline: ``ForeHead_M``, ``NoseTop``, ``Chin``), over all valid samples, else of all markers.
    axis : int

    Returns
    -------
    Same shape as ``positions``.
    """
    P = np.asarray(positions, dtype=np.float64)
    one = P.ndim == 2
    if one:
        P = P[None]
    names = _check_names(names)
    if P.ndim != 3 or P.shape[1:] != (len(names), 3):
        raise ValueError(f"positions: expected (T, {len(names)}, 3) or ({len(names)}, 3), got {np.shape(positions)}")
    if axis not in (0, 1, 2):
        raise ValueError(f"axis: expected 0, 1 or 2, got {axis}")
    m = mirror_map(names)
    if center is None:
        mid = m == np.arange(len(names))
        x = P[:, mid, axis] if mid.any() else P[:, :, axis]
        if not np.isfinite(x).any():
            x = P[:, :, axis]
        center = float(np.nanmean(x)) if np.isfinite(x).any() else 0.0
    out = P[:, m].copy()
    out[..., axis] = 2.0 * float(center) - out[..., axis]
    return out[0] if one else out


#: Live Link Face rotation extras (yaw, pitch, roll): mirrored, yaw and roll change sign
_ROT_SWAP = {"eye_rotation_left": "eye_rotation_right", "eye_rotation_right": "eye_rotation_left"}


def mirror_performance(perf, center: Optional[float] = None):
    """A :class:`core.model.Performance` mirrored left/right.

    Curves: :func:`mirror_weights` by channel name (and Live Link Face's rotation extras: left
    and right eye swapped, yaw and roll negated, pitch kept: a reflection in the x = 0 plane
    reverses rotations about y and z). Markers: :func:`mirror_markers`. Mesh sequences are refused
    (they need a vertex correspondence of the mesh with its mirror image).
    """
    from .model import Performance

    if not isinstance(perf, Performance):
        raise TypeError(f"perf: expected a core.model.Performance, got {type(perf).__name__}")
    if perf.kind == "meshes":
        raise ValueError(f"{perf.name}: mirroring a mesh sequence needs the mesh's left/right vertex map; "
                         "mirror the weight curves or markers instead")
    m = mirror_map(perf.names)
    extras = dict(perf.extras)
    if perf.kind == "curves":
        data = perf.data[:, m]
        for key in ("head_rotation", "eye_rotation_left", "eye_rotation_right"):
            if key in perf.extras:
                r = np.asarray(perf.extras[_ROT_SWAP.get(key, key)], dtype=np.float64).copy()
                if r.ndim == 2 and r.shape[1] == 3:
                    r[:, 0] *= -1.0
                    r[:, 2] *= -1.0
                r.setflags(write=False)
                extras[key] = r
    else:
        data = mirror_markers(perf.data, perf.names, center)
    return replace(perf, data=data, valid=perf.valid[:, m], extras=extras, name=f"{perf.name}_mirrored")


def mirror_edit(edit: dict, names: Sequence[str], keep: bool = False) -> dict:
    """A spacetime edit ``{frame, weights: {shape: value}, window}`` moved to the other side.

    ``keep=False``: every shape is replaced by its mirror (an edit of ``eyeBlinkLeft`` becomes
    one of ``eyeBlinkRight``; midline shapes keep theirs). ``keep=True``: the edit plus its
    mirror (both eyes), the edit's own values winning where it sets both sides.

    Raises
    ------
    ValueError
        Not an edit dict, or a shape name not in ``names`` (with "did you mean").
    """
    if not isinstance(edit, dict) or "frame" not in edit or not isinstance(edit.get("weights"), dict):
        raise ValueError(f"edit: expected {{'frame': int, 'weights': {{shape: value}}, 'window': [a, b] or None}}, got {edit!r}")
    names = _check_names(names)
    m = mirror_map(names)
    out = {}
    for shape, v in edit["weights"].items():
        k = _match(str(shape), names, "edit.weights")
        out[names[m[k]]] = v
    if keep:
        mine = {names[_match(str(s), names, "edit.weights")]: v for s, v in edit["weights"].items()}
        out.update(mine)
    res = copy.deepcopy(edit)
    res["weights"] = out
    return res
