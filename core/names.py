"""Blendshape names: canonical ARKit names and user-editable maps between rigs.

Rigs spell the same ARKit shape many ways: ``eyeBlink_L`` (ICT), ``AK_09_EyeBlinkLeft``
(Rocketbox), ``EyeBlinkLeft`` (Live Link Face CSV). :func:`canonical` maps each to the ARKit
spelling ``eyeBlinkLeft``; a name that is not an ARKit shape keeps its spelling.

A :class:`NameMap` says which source channel drives which target shape, with a gain; it is
built automatically from canonical names (with the split-shape rule below) and can be
loaded from / saved to JSON so a user can edit it for non-ARKit rigs such as the Jeeliz animals.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

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
_PREFIX = re.compile(r"^(?:AK_\d+_|ARKit_|arkit[._])", re.IGNORECASE)
_SIDE = re.compile(r"^(?P<base>.+?)[_.\-]?(?P<side>L|R|Left|Right)$")


def _key(name: str) -> str:
    return re.sub(r"[^0-9a-z]", "", name.lower())


def canonical(name: str) -> str:
    """Canonical ARKit spelling of ``name``, or ``name`` unchanged when it is not ARKit.

    >>> canonical("eyeBlink_L"), canonical("AK_09_EyeBlinkLeft"), canonical("EyeBlinkLeft")
    ('eyeBlinkLeft', 'eyeBlinkLeft', 'eyeBlinkLeft')
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


@dataclass(frozen=True)
class NameMap:
    """Target shape -> list of (source channel, gain).

    ``target weight_k = sum_j gain_kj * source weight_j``.
    """

    entries: dict = field(default_factory=dict)

    @classmethod
    def automatic(cls, source: Sequence[str], target: Sequence[str]) -> "NameMap":
        """Pair shapes with the same canonical name; a target side-split shape
        (``browInnerUp_L``) is driven by the sideless source channel (``browInnerUp``),
        and a sideless target shape by the mean of a source's split pair."""
        src_by_canon = {}
        for s in source:
            src_by_canon.setdefault(canonical(s), s)
        split_src = {}
        for s in source:
            base = split_base(s)
            if base:
                split_src.setdefault(base, []).append(s)
        entries = {}
        for t in target:
            c = canonical(t)
            if c in src_by_canon:
                entries[t] = [(src_by_canon[c], 1.0)]
            elif split_base(t) and split_base(t) in src_by_canon:
                entries[t] = [(src_by_canon[split_base(t)], 1.0)]
            elif c in split_src:
                pair = split_src[c]
                entries[t] = [(s, 1.0 / len(pair)) for s in pair]
        return cls(entries)

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
