"""Left and right in shape and marker names: which name is the mirror of which.

Rigs and marker layouts spell the two halves of the face in many ways: side words
(ARKit ``eyeBlinkLeft``, Jeeliz ``eyeBrowLeftDown``), side letters (ICT ``eyeBlink_L``),
``L_``/``R_`` infixes (Rocketbox ``AU_02_L_OuterBrowRaiser``), letters glued to a word (the
layouts' markers ``Leye_Up``, ``Mouth_UpL1``, ``Chin_R2``), behind a leading code whose number
differs between the sides (``SR_01_Cheek_Puff_Left`` / ``SR_02_Cheek_Puff_Right``).
:func:`mirror_map` pairs names from their spelling alone; a pair is kept only when each is the
other's mirror. :func:`is_directional` tells a side token that names a direction (``jawLeft``:
the jaw moves to the left) from one that names a face half (``eyeBlinkLeft``).

Used by the symmetry pairs (:mod:`core.controls.pairs`) and by mirroring a take
(:mod:`core.controls.mirror`).
"""

from __future__ import annotations

import re
from typing import Sequence

import numpy as np

from ..names import canonical
from .inputs import as_names

__all__ = ["mirror_map", "mirror_pairs", "is_directional"]


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
    names = as_names(names)
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
    names = as_names(names)
    m = mirror_map(names)
    return [(names[i], names[j]) for i, j in enumerate(m) if i < j]


def is_directional(name: str, partner: str) -> bool:
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
