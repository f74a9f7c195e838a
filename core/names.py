"""Blendshape names: canonical ARKit names, vocabularies of other naming schemes, and
user-editable maps between rigs.

Rigs spell the same ARKit shape many ways: ``eyeBlink_L`` (ICT), ``AK_09_EyeBlinkLeft``
(Rocketbox), ``EyeBlinkLeft`` (Live Link Face CSV). :func:`canonical` maps each to the ARKit
spelling ``eyeBlinkLeft``; a name that is not an ARKit shape keeps its spelling.

Other rigs use other vocabularies: SRanipal (``SR_21_Jaw_Open``), FACS action units
(``AU_12_L_LipCornerPuller``), Unified Expressions (``MouthCornerPullLeft``), Meta's face
expressions (``LipCornerPullerL``), visemes (``AA_VI_10_aa``, ``viseme_PP``, VRM ``aa``) ...
A :class:`Vocabulary` (bundled as ``data/namemaps/vocabulary_*.json``, editable, see
docs/names.md) writes each of its shapes as a weighted combination of ARKit shapes::

    w_shape ≈ Σ_j gain_j · w_ARKit_j                                   (1)

i.e. the shape's weight when the face makes the ARKit weights ``w_ARKit`` (a bilateral FACS AU12
is ``0.5 mouthSmileLeft + 0.5 mouthSmileRight``: 1 when both sides are 1). :func:`recognise`
says which vocabularies a list of names uses.

A :class:`NameMap` says which source channel drives which target shape, with a gain; it is
built automatically (:meth:`NameMap.automatic`: same canonical name first, then through the
vocabularies, eq. (1) forward for the target and by least squares for the source) and can be
loaded from / saved to JSON so a user can edit it, e.g. for the Jeeliz animals.
"""

from __future__ import annotations

import difflib
import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Optional, Sequence

import numpy as np

#: The 52 ARKit blendshape locations, in Apple's documented order.
ARKIT_NAMES = (
    "eyeBlinkLeft", "eyeLookDownLeft", "eyeLookInLeft", "eyeLookOutLeft", "eyeLookUpLeft",
    "eyeSquintLeft", "eyeWideLeft", "eyeBlinkRight", "eyeLookDownRight", "eyeLookInRight",
    "eyeLookOutRight", "eyeLookUpRight", "eyeSquintRight", "eyeWideRight", "jawForward",
    "jawLeft", "jawRight", "jawOpen", "mouthClose", "mouthFunnel", "mouthPucker", "mouthLeft",
    "mouthRight", "mouthSmileLeft", "mouthSmileRight", "mouthFrownLeft", "mouthFrownRight",
    "mouthDimpleLeft", "mouthDimpleRight", "mouthStretchLeft", "mouthStretchRight",
    "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper", "mouthPressLeft",
    "mouthPressRight", "mouthLowerDownLeft", "mouthLowerDownRight", "mouthUpperUpLeft",
    "mouthUpperUpRight", "browDownLeft", "browDownRight", "browInnerUp", "browOuterUpLeft",
    "browOuterUpRight", "cheekPuff", "cheekSquintLeft", "cheekSquintRight", "noseSneerLeft",
    "noseSneerRight", "tongueOut",
)
_BY_KEY = {n.lower(): n for n in ARKIT_NAMES}
#: ARKit names' own prefixes: Rocketbox ``AK_09_``, Reallusion Character Creator ``A14_`` (its ARKit
#: set ``A01_Brow_Inner_Up`` ... on ``CC_Base_Body``), ``ARKit_``
_PREFIX = re.compile(r"^(?:AK_\d+_|A\d{2}_|ARKit_|arkit[._])", re.IGNORECASE)
_SIDE = re.compile(r"^(?P<base>.+?)[_.\-]?(?P<side>L|R|Left|Right)$")


def _key(name: str) -> str:
    return re.sub(r"[^0-9a-z]", "", name.lower())


def canonical(name: str) -> str:
    """Canonical ARKit spelling of ``name``, or ``name`` unchanged when it is not ARKit.

    >>> canonical("eyeBlink_L"), canonical("AK_09_EyeBlinkLeft"), canonical("EyeBlinkLeft")
    ('eyeBlinkLeft', 'eyeBlinkLeft', 'eyeBlinkLeft')
    >>> canonical("A14_Eye_Blink_Left"), canonical("A01_Brow_Inner_Up")
    ('eyeBlinkLeft', 'browInnerUp')
    >>> canonical("AU_01_InnerBrowRaiser")
    'AU_01_InnerBrowRaiser'
    """
    stripped = _PREFIX.sub("", name)
    key = _key(stripped)
    if key in _BY_KEY:
        return _BY_KEY[key]
    m = _SIDE.match(stripped)
    if m:
        side = "left" if m.group("side").lower().startswith("l") else "right"
        key = _key(m.group("base")) + side
        if key in _BY_KEY:
            return _BY_KEY[key]
    return name


def split_base(name: str):
    """For a side-split shape of a sideless ARKit shape (ICT's ``browInnerUp_L``,
    ``cheekPuff_R``) return the ARKit name it splits (``browInnerUp``), else None."""
    m = _SIDE.match(_PREFIX.sub("", name))
    if m and _key(m.group("base")) in _BY_KEY and canonical(name) == name:
        return _BY_KEY[_key(m.group("base"))]
    return None


#: the bundled vocabularies: ``data/namemaps/vocabulary_*.json``, one file per vocabulary
NAMEMAPS = Path(__file__).resolve().parents[1] / "data" / "namemaps"

_ARKIT = frozenset(ARKIT_NAMES)
#: numbered prefixes such as Rocketbox's AK_25_, SR_21_, AA_VI_10_, HB_07_ (not FACS' AU_12_: its number is the name)
_NUMBERED = re.compile(r"^(?!AU_?\d)(?:[A-Za-z]{1,4}_){1,2}\d+_", re.IGNORECASE)
_FACS = re.compile(r"^AU[_ ]?0*(\d+)(?:[_ ]?([LR])(?=[_ ]|$))?", re.IGNORECASE)
_WORDS = re.compile(r"[A-Z]+(?![a-z])|[A-Z]?[a-z]+|\d+")
_SIDES = {"l": "left", "left": "left", "r": "right", "right": "right"}


def name_key(name: str) -> str:
    """The spelling-free key two names of one shape share: the words lower-cased and joined,
    side words (``L``, ``R``, ``Left``, ``Right`` as words of their own) behind a ``|``; text up
    to a last ``.`` is dropped (``blendShape1.jawOpen``); a FACS name keys on its AU number and side.

    >>> name_key("Mouth_Smile_Left"), name_key("mouthSmile_L"), name_key("MouthSmileLeft")
    ('mouthsmile|left', 'mouthsmile|left', 'mouthsmile|left')
    >>> name_key("AU_12_L_LipCornerPuller"), name_key("AU12"), name_key("AU_61_EyesTurnLeft")
    ('au12|left', 'au12|', 'au61|')
    """
    name = name.rsplit(".", 1)[-1]
    m = _FACS.match(name)
    if m:
        return f"au{int(m.group(1))}|" + (_SIDES[m.group(2).lower()] if m.group(2) else "")
    words, sides = [], []
    for w in _WORDS.findall(name):
        lw = w.lower()
        if lw in _SIDES:
            sides.append(_SIDES[lw])
        else:
            words.append(lw)
    return "".join(words) + "|" + "".join(sides)


@dataclass(frozen=True, eq=False)
class Vocabulary:
    """A naming scheme and each of its shapes as a weighted combination of ARKit shapes (eq. 1
    of the module docstring): ``entries[shape] = ((arkit_name, gain), ...)``; ``()`` for a shape
    of the vocabulary that no ARKit shape expresses (recognised, driven by nothing).

    ``prefix`` (a regular expression, may be empty): names that start with it belong to this
    vocabulary only (``SR_21_Jaw_Open`` is SRanipal's ``Jaw_Open``); the match is removed.
    """

    name: str
    entries: dict
    title: str = ""
    prefix: str = ""
    notes: str = ""
    path: str = ""

    def __post_init__(self):
        try:
            rx = re.compile(self.prefix) if self.prefix else None
        except re.error as e:
            raise ValueError(f"vocabulary {self.name!r}: prefix {self.prefix!r} is not a regular expression: {e}") from None
        object.__setattr__(self, "_prefix", rx)
        keys = {}
        for shape in self.entries:
            keys.setdefault(name_key(self._strip(shape, True)), shape)
        object.__setattr__(self, "_keys", keys)

    def _strip(self, name: str, owned: bool) -> str:
        name = name.rsplit(".", 1)[-1]
        if owned and self._prefix is not None:
            return self._prefix.sub("", name, count=1)
        return _NUMBERED.sub("", name)

    def owns(self, name: str) -> bool:
        """Whether ``name`` carries this vocabulary's prefix."""
        return self._prefix is not None and self._prefix.match(name.rsplit(".", 1)[-1]) is not None

    def shape(self, name: str, owned: bool = False) -> Optional[str]:
        """This vocabulary's spelling of ``name`` (any case, separators, numbered prefix), or None."""
        return self._keys.get(name_key(self._strip(name, owned)))

    def combination(self, name: str, owned: bool = False) -> Optional[tuple]:
        """``((arkit_name, gain), ...)`` of ``name`` in this vocabulary, or None when it is not one
        of its shapes. A side of a sideless shape (``browInnerUp_L``) takes the sideless row (the
        half is at 1 when the whole is); a sideless name of a left/right pair (``mouthSmile``) is
        their mean."""
        key = name_key(self._strip(name, owned))
        if key in self._keys:
            return self.entries[self._keys[key]]
        base, _, side = key.partition("|")
        if side in ("left", "right") and base + "|" in self._keys:
            return self.entries[self._keys[base + "|"]]
        if not side and f"{base}|left" in self._keys and f"{base}|right" in self._keys:
            mean = {}
            for s in ("left", "right"):
                for a, g in self.entries[self._keys[f"{base}|{s}"]]:
                    mean[a] = mean.get(a, 0.0) + 0.5 * g
            return tuple(mean.items())
        return None

    def to_json(self, path) -> None:
        """Write this vocabulary as :func:`read_vocabulary` reads it (one entry a line)."""
        head = {"format": "face-retarget name map", "version": 1, "vocabulary": self.name, "title": self.title}
        if self.prefix:
            head["prefix"] = self.prefix
        head["source"] = "arkit"
        if self.notes:
            head["notes"] = self.notes
        rows = [f"    {json.dumps(t)}: [" + ", ".join(json.dumps({"source": a, "gain": g}) for a, g in row) + "]"
                for t, row in self.entries.items()]
        Path(path).write_text(json.dumps(head, indent=2)[:-2] + ',\n  "map": {\n' + ",\n".join(rows) + "\n  }\n}\n")


@dataclass(frozen=True)
class Recognition:
    """Which vocabularies a list of names uses (:func:`recognise`)."""

    #: vocabularies recognising at least one name, most names first
    vocabularies: tuple
    #: names each of them recognises, same order
    counts: tuple
    #: names recognised by at least one vocabulary
    recognised: int
    #: names in the list
    total: int

    @property
    def vocabulary(self) -> Optional[str]:
        """The vocabulary recognising most names, or None."""
        return self.vocabularies[0] if self.vocabularies else None

    def __str__(self) -> str:
        per = ", ".join(f"{v} {n}" for v, n in zip(self.vocabularies, self.counts))
        return f"{self.recognised} of {self.total} names recognised" + (f": {per}" if per else "")


def _candidates(name: str, vocabularies: Sequence[Vocabulary]):
    """(vocabulary, owned) pairs to look ``name`` up in: the vocabularies whose prefix it has, else all."""
    owners = [v for v in vocabularies if v.owns(name)]
    return [(v, True) for v in owners] if owners else [(v, False) for v in vocabularies]


def recognise(names: Sequence[str], vocabularies: Optional[Sequence[Vocabulary]] = None) -> Recognition:
    """Which vocabularies ``names`` use and how many names each recognises.

    >>> r = recognise(["SR_21_Jaw_Open", "AU_12_L_LipCornerPuller", "AU_26_JawDrop", "hat"])
    >>> r.vocabulary, r.recognised, r.total
    ('facs', 3, 4)
    """
    vocabs = load_vocabularies() if vocabularies is None else tuple(vocabularies)
    counts = {v.name: 0 for v in vocabs}
    recognised = 0
    for n in names:
        hit = [v.name for v, owned in _candidates(n, vocabs) if v.combination(n, owned) is not None]
        for v in dict.fromkeys(hit):
            counts[v] += 1
        recognised += bool(hit)
    order = sorted((v for v in counts if counts[v]), key=lambda v: -counts[v])  # stable: file order on ties
    return Recognition(tuple(order), tuple(counts[v] for v in order), recognised, len(names))


def arkit_combination(name: str, vocabularies: Sequence[Vocabulary]):
    """``(vocabulary name, ((arkit_name, gain), ...))`` of ``name`` in the first of
    ``vocabularies`` that has it, or None."""
    for v, owned in _candidates(name, vocabularies):
        row = v.combination(name, owned)
        if row is not None:
            return v.name, row
    return None


def read_vocabulary(path) -> Vocabulary:
    """One vocabulary file: a name map (:meth:`NameMap.from_json`) whose sources are ARKit names,
    with a ``vocabulary`` field (its name) and optional ``title``, ``prefix`` and ``notes``.

    Raises ValueError naming the file and the field when it is not one.
    """
    path = Path(path)
    nm = NameMap.from_json(path)
    data = json.loads(path.read_text())
    name = data.get("vocabulary")
    if not isinstance(name, str) or not name.strip():
        raise ValueError(f"{path}: field 'vocabulary' (the vocabulary's name, e.g. \"sranipal\") is missing or empty; "
                         "a vocabulary file is a name map with a 'vocabulary' field (docs/names.md)")
    if data.get("source", "arkit") != "arkit":
        raise ValueError(f"{path}: field 'source' must be \"arkit\" (vocabularies are written in ARKit shapes), "
                         f"got {data['source']!r}")
    for f in ("title", "prefix", "notes"):
        if not isinstance(data.get(f, ""), str):
            raise ValueError(f"{path}: field {f!r} must be a string, got {data[f]!r}")
    entries = {}
    for shape, pairs in nm.entries.items():
        row = []
        for a, g in pairs:
            c = canonical(a)
            if c not in _ARKIT:
                close = difflib.get_close_matches(a, ARKIT_NAMES, n=1)
                raise ValueError(f"{path}: map[{shape!r}] source {a!r} is not an ARKit shape"
                                 + (f"; did you mean {close[0]!r}?" if close else " (core.names.ARKIT_NAMES)"))
            row.append((c, g))
        entries[shape] = tuple(row)
    try:
        return Vocabulary(name.strip(), entries, data.get("title", ""), data.get("prefix", ""), data.get("notes", ""), str(path))
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None


def bundled_vocabulary_files() -> list:
    """The bundled vocabulary files (what a cache key of their use hashes)."""
    return _vocabulary_files(NAMEMAPS)


def _vocabulary_files(folder: Path) -> list:
    files = sorted(folder.glob("vocabulary_*.json"))
    return sorted(files, key=lambda p: p.name != "vocabulary_arkit.json")  # ARKit first, then by name


def load_vocabularies(paths: Sequence = ()) -> tuple:
    """The bundled vocabularies (``data/namemaps/vocabulary_*.json``, ARKit first), then those of
    ``paths`` (files, or folders of ``vocabulary_*.json``; the pipeline's ``vocabularies`` setting).
    A later file of an existing vocabulary replaces its entries shape by shape (and its title or
    prefix when it gives one); a new vocabulary name adds a vocabulary.

    Raises ValueError for a path that does not exist or a file that is not a vocabulary.
    """
    files = _vocabulary_files(NAMEMAPS)
    for p in map(Path, paths):
        if p.is_dir():
            files += _vocabulary_files(p)
        elif p.is_file():
            files.append(p)
        else:
            raise ValueError(f"vocabulary path {str(p)!r} does not exist")
    merged = {}
    for f in files:
        v = read_vocabulary(f)
        old = merged.get(v.name)
        if old is not None:
            v = Vocabulary(v.name, {**old.entries, **v.entries}, v.title or old.title, v.prefix or old.prefix,
                           v.notes or old.notes, f"{old.path}, {v.path}")
        merged[v.name] = v
    return tuple(merged.values())


@dataclass(frozen=True)
class NameMap:
    """Target shape -> list of (source channel, gain).

    ``target weight_k = sum_j gain_kj * source weight_j``.
    """

    entries: dict = field(default_factory=dict)

    @classmethod
    def automatic(cls, source: Sequence[str], target: Sequence[str],
                  vocabularies: Optional[Sequence[Vocabulary]] = None, exclusive: bool = True) -> "NameMap":
        """Pair shapes by name.

        1. Same canonical name; a target side-split shape (``browInnerUp_L``) is driven by the
           sideless source channel (``browInnerUp``), and a sideless target shape by the mean of a
           source's split pair. With ``exclusive``, of several target shapes with one canonical
           ARKit name (``A14_Eye_Blink_Left`` and ``Eye_Blink_L``) only one is paired: the ARKit
           spelling, else an ARKit-prefixed one (``AK_``, ``A14_``), else the first.
        2. The target shapes left, through the vocabularies (:func:`load_vocabularies` when None):
           with ``A`` (C, 52) the ARKit rows (eq. 1) of the recognised source channels, the ARKit
           weights are estimated by least squares, ``x̂ = A⁺ s`` (exact for ARKit curves, the mean
           for a split pair), and a target shape with row ``b`` gets ``w = b · x̂``, i.e. gains
           ``b A⁺``. With ``exclusive`` (for driving a rig: the ``names`` method, the evaluation's
           ground truth) each ARKit shape drives at most one target shape: a shape whose ARKit
           shapes a step-1 pair or an earlier shape already drive is left unmapped, so a rig
           holding several vocabularies (Rocketbox: ARKit, SRanipal, FACS, visemes) is not driven
           twice over; shapes made of fewer ARKit shapes come first, then by vocabulary (the one
           recognising most target names first), then in target order. Without it (a per-shape
           guess such as the name prior) every recognised shape gets its own estimate.
        """
        src_by_canon = {}
        for s in source:
            src_by_canon.setdefault(canonical(s), s)
        split_src = {}
        for s in source:
            base = split_base(s)
            if base:
                split_src.setdefault(base, []).append(s)
        entries = {}
        # with exclusive, one target shape per ARKit name: a rig with two spellings of one shape
        # (Character Creator's CC_Base_Body has A14_Eye_Blink_Left and its own Eye_Blink_L) would
        # otherwise blink twice over. The ARKit spelling, then an ARKit-prefixed one, then the first.
        first = {}
        for i, t in sorted(enumerate(target), key=lambda it: (it[1] != canonical(it[1]), not _PREFIX.match(it[1]), it[0])):
            first.setdefault(canonical(t), t)
        for t in target:
            c = canonical(t)
            if c in src_by_canon and exclusive and c in _ARKIT and first[c] != t:
                continue
            if c in src_by_canon:
                entries[t] = [(src_by_canon[c], 1.0)]
            elif split_base(t) and split_base(t) in src_by_canon:
                entries[t] = [(src_by_canon[split_base(t)], 1.0)]
            elif c in split_src:
                pair = split_src[c]
                entries[t] = [(s, 1.0 / len(pair)) for s in pair]
        rest = [t for t in target if t not in entries]
        vocabs = (load_vocabularies() if vocabularies is None else tuple(vocabularies)) if rest else ()
        if not vocabs:
            return cls(entries)
        # step 2: the source's ARKit estimate
        src_vocabs = rank_vocabularies(vocabs, source)
        rows = [(s, arkit_combination(s, src_vocabs)) for s in source]
        rows = [(s, r[1]) for s, r in rows if r is not None and r[1]]
        if not rows:
            return cls(entries)
        col = {a: j for j, a in enumerate(ARKIT_NAMES)}
        A = np.zeros((len(rows), len(ARKIT_NAMES)))
        for i, (_, row) in enumerate(rows):
            for a, g in row:
                A[i, col[a]] += g
        P = np.linalg.pinv(A)  # (52, C): x̂ = P s
        available = {a for a in ARKIT_NAMES if np.any(A[:, col[a]] != 0)}
        claimed = {canonical(t) if canonical(t) in _ARKIT else split_base(t) for t in entries}
        tgt_vocabs = rank_vocabularies(vocabs, target)
        rank = {v.name: i for i, v in enumerate(tgt_vocabs)}
        candidates = []
        for i, t in enumerate(rest):
            hit = arkit_combination(t, tgt_vocabs)
            if hit and hit[1]:
                comps = {a for a, _ in hit[1]}
                candidates.append(((len(comps), rank[hit[0]], i), t, hit[1], comps))
        for _, t, row, comps in sorted(candidates, key=lambda c: c[0]):
            if not comps <= available or (exclusive and comps & claimed):
                continue
            claimed |= comps
            b = np.zeros(len(ARKIT_NAMES))
            for a, g in row:
                b[col[a]] += g
            gains = b @ P
            entries[t] = [(rows[j][0], round(float(gains[j]), 10)) for j in np.flatnonzero(np.abs(gains) > 1e-10)]
        return cls({t: entries[t] for t in target if t in entries})

    def matrix(self, source: Sequence[str], target: Sequence[str]) -> np.ndarray:
        """(K_target, K_source) matrix G with target = source @ G.T; names absent from
        ``source`` raise KeyError naming them."""
        col = {s: j for j, s in enumerate(source)}
        G = np.zeros((len(target), len(source)))
        missing = set()
        for i, t in enumerate(target):
            for s, gain in self.entries.get(t, ()):
                if s not in col:
                    missing.add(s)
                    continue
                G[i, col[s]] += gain
        if missing:
            raise KeyError(f"name map refers to source channels {sorted(missing)} that the source does not have")
        return G

    def unmapped(self, target: Iterable[str]) -> list:
        return [t for t in target if t not in self.entries]

    def to_json(self, path) -> None:
        data = {"format": "face-retarget name map", "version": 1,
                "map": {t: [{"source": s, "gain": g} for s, g in v] for t, v in self.entries.items()}}
        Path(path).write_text(json.dumps(data, indent=2) + "\n")

    @classmethod
    def from_json(cls, path) -> "NameMap":
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise ValueError(f"{path}: cannot read name map JSON: {e}") from None
        raw = data.get("map") if isinstance(data, dict) else None
        if not isinstance(raw, dict):
            raise ValueError(f"{path}: field 'map' must be an object {{target: [{{source, gain}}]}}")
        entries = {}
        for t, v in raw.items():
            if isinstance(v, str):
                v = [{"source": v, "gain": 1.0}]
            if not isinstance(v, list):
                raise ValueError(f"{path}: map[{t!r}] must be a list of {{source, gain}} or a source name")
            pairs = []
            for item in v:
                if isinstance(item, str):
                    item = {"source": item}
                if not isinstance(item, dict) or "source" not in item:
                    raise ValueError(f"{path}: map[{t!r}] entries need a 'source' field, got {item!r}")
                try:
                    pairs.append((str(item["source"]), float(item.get("gain", 1.0))))
                except (TypeError, ValueError):
                    raise ValueError(f"{path}: map[{t!r}] gain must be a number, got {item.get('gain')!r}") from None
            entries[str(t)] = pairs
        return cls(entries)


def rank_vocabularies(vocabularies: Sequence[Vocabulary], names: Sequence[str]) -> tuple:
    """``vocabularies`` with those recognising most of ``names`` first (file order on ties): the
    order :meth:`NameMap.automatic` looks names up in."""
    order = recognise(names, vocabularies).vocabularies
    by = {v.name: v for v in vocabularies}
    return tuple(by[n] for n in order) + tuple(v for v in vocabularies if v.name not in order)
