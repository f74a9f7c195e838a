"""Weight curves as a plain CSV: ``time_s,frame,valid`` then one column per shape, in rig order
(and reduced keys in a long format, one row per key: :func:`write_keys_csv`).

The format every spreadsheet, DCC script and pandas reads. ``valid`` is 1 where the frame had
data and 0 for a gap (tracking loss): a gap's weights are the filled values that are played
(see :mod:`core.gaps`), so the curves stay continuous and the flag says which frames are real.
A NaN weight is written as an empty cell and read back as a masked sample.

:func:`read_curves_csv` also reads the older ``time_s,<shape>...`` layout.
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Optional, Union

import numpy as np

from ..controls import Keys
from ..model import Performance
from .tabular import estimate_fps

#: the columns before the shapes
LEAD = ("time_s", "frame", "valid")


def _formatter(precision: Union[int, str, None]):
    if precision in (None, "full"):  # shortest text that reads back to the same float64
        return repr
    fmt = f"{{:.{int(precision)}f}}"
    return fmt.format


def write_curves_csv(path, times, weights, names, precision: Union[int, str, None] = 6, valid=None,
                     frames=None) -> None:
    """Write (T,) times and (T, K) weights with header ``time_s,frame,valid,<name>...``.

    Parameters
    ----------
    precision : decimals of the weights, or ``"full"`` (round-trip exact float64 text)
    valid : (T,) bool, optional — frames with data (default: frames whose weights are finite)
    frames : (T,) int, optional — the take's frame numbers (default: 0 .. T-1)
    """
    times = np.asarray(times, dtype=np.float64)
    W = np.asarray(weights, dtype=np.float64)
    if W.ndim != 2 or W.shape != (len(times), len(names)):
        raise ValueError(f"weights must be (T, K) = ({len(times)}, {len(names)}), got {W.shape}")
    valid = np.isfinite(W).all(1) if valid is None else np.asarray(valid, dtype=bool)
    frames = np.arange(len(times)) if frames is None else np.asarray(frames, dtype=np.int64)
    if valid.shape != (len(times),) or frames.shape != (len(times),):
        raise ValueError(f"valid, frames: expected ({len(times)},), got {valid.shape}, {frames.shape}")
    fmt = _formatter(precision)
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow([*LEAD, *names])
        for t, n, ok, row in zip(times, frames, valid, W):
            w.writerow([f"{t:.6f}", int(n), int(bool(ok))] + ["" if not np.isfinite(v) else fmt(float(v)) for v in row])


def read_curves_csv(path, name: Optional[str] = None) -> Performance:
    """Read a file written by :func:`write_curves_csv` (fps from the times,
    :func:`core.io.tabular.estimate_fps`; 30 for a single row); a ``valid`` 0 row reads as a
    frame whose samples are all missing."""
    path = Path(path)
    with open(path, newline="", encoding="utf-8-sig") as f:
        rows = list(csv.reader(f))
    if not rows or not rows[0] or rows[0][0] != "time_s":
        raise ValueError(f"{path}: first column must be 'time_s' (a weight-curve CSV), got {rows[0][:1] if rows else 'an empty file'}")
    lead = 3 if tuple(rows[0][:3]) == LEAD else 1
    names = rows[0][lead:]
    body = rows[1:]
    bad = [i + 2 for i, r in enumerate(body) if len(r) != len(names) + lead]
    if bad:
        raise ValueError(f"{path}: rows {bad[:5]} have the wrong number of cells (expected {len(names) + lead})")
    try:
        data = np.array([[float(c) if c.strip() else np.nan for c in r] for r in body]).reshape(len(body), len(names) + lead)
    except ValueError as e:
        raise ValueError(f"{path}: non-numeric cell ({e})") from None
    times = data[:, 0]
    W = data[:, lead:]
    valid = np.isfinite(W)
    if lead == 3:
        valid &= (data[:, 2] != 0)[:, None]
    fps = estimate_fps(times, f"{path}: column time_s") if len(times) > 1 else 30.0
    return Performance.curves(np.where(valid, W, np.nan), names, fps, valid=valid, times=times - times[0], name=name or path.stem)


#: columns of the long (one row per key) format
KEY_COLUMNS = ("shape", "frame", "time_s", "value", "interpolation", "in_tangent", "out_tangent")


def write_keys_csv(path, keys, names=None, precision: Union[int, str, None] = "full") -> dict:
    """Reduced keys (:func:`core.controls.reduce_keys`) as a long CSV, one row per key:
    ``shape,frame,time_s,value,interpolation,in_tangent,out_tangent`` (tangents in weight per
    second, empty for LINEAR), curves in order, keys in time order within each curve.

    Each curve keeps its own keys (unlike glTF, whose sampler shares one time grid): the layout a
    DCC script or spreadsheet turns into hand-editable keys.

    Parameters
    ----------
    keys : core.controls.Keys
    names : K shape names (default ``keys.names``)
    precision : decimals of values and tangents, or ``"full"`` (round-trip exact, the default:
        a rounded value could leave the tolerance the keys were reduced to)

    Returns
    -------
    dict ``{"keys": total rows, "dense": T * K samples of the dense curves}``
    """
    names = keys.names if names is None else tuple(str(n) for n in names)
    if names is None or len(names) != len(keys.frames):
        raise ValueError(f"names: expected {len(keys.frames)} shape names (keys.names is not set)")
    fmt = _formatter(precision)
    cubic = keys.interpolation == "CUBICSPLINE"
    n = 0
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(KEY_COLUMNS)
        for c, name in enumerate(names):
            for i, (fr, v) in enumerate(zip(keys.frames[c], keys.values[c])):
                a = fmt(float(keys.in_tangents[c][i])) if cubic else ""
                b = fmt(float(keys.out_tangents[c][i])) if cubic else ""
                w.writerow([name, int(fr), f"{fr / keys.fps:.6f}", fmt(float(v)), keys.interpolation, a, b])
                n += 1
    return {"keys": n, "dense": int(keys.n_frames * len(names))}


def read_keys_csv(path, fps: Optional[float] = None, n_frames: Optional[int] = None, tolerance: float = float("nan")):
    """Read a file of :func:`write_keys_csv` back into :class:`core.controls.Keys`.

    ``fps`` defaults to ``frame / time_s`` of the keys (frames are integers, times rounded to
    microseconds); ``n_frames`` to the last key frame + 1.
    """
    path = Path(path)
    with open(path, newline="", encoding="utf-8-sig") as f:
        rows = list(csv.reader(f))
    if not rows or tuple(rows[0]) != KEY_COLUMNS:
        raise ValueError(f"{path}: expected the header {','.join(KEY_COLUMNS)} (a keys CSV), got {rows[0] if rows else 'nothing'}")
    order, per = [], {}
    interp = None
    for ln, r in enumerate(rows[1:], start=2):
        if len(r) != len(KEY_COLUMNS):
            raise ValueError(f"{path}: line {ln} has {len(r)} cells, expected {len(KEY_COLUMNS)}")
        name, fr, t, v, it, a, b = r
        if interp is None:
            interp = it
        elif it != interp:
            raise ValueError(f"{path}: line {ln}: interpolation {it!r} differs from the file's {interp!r}")
        if name not in per:
            order.append(name)
            per[name] = []
        try:
            per[name].append((int(fr), float(t), float(v), float(a) if a else 0.0, float(b) if b else 0.0))
        except ValueError as e:
            raise ValueError(f"{path}: line {ln}: {e}") from None
    if not order:
        raise ValueError(f"{path}: no keys")
    if fps is None:
        ratios = [fr / t for k in per.values() for fr, t, *_ in k if t > 0]
        if not ratios:
            raise ValueError(f"{path}: cannot tell the frame rate from keys at time 0 only; pass fps")
        fps = float(np.median(ratios))
        snapped = round(fps * 1000) / 1000
        fps = snapped if abs(snapped - fps) < 1e-3 else fps
    frames, values, ins, outs = [], [], [], []
    for name in order:
        k = sorted(per[name])
        fr = np.array([x[0] for x in k], np.int64)
        if (np.diff(fr) <= 0).any():
            raise ValueError(f"{path}: shape {name!r} has two keys at one frame")
        frames.append(fr)
        values.append(np.array([x[2] for x in k]))
        ins.append(np.array([x[3] for x in k]))
        outs.append(np.array([x[4] for x in k]))
    T = int(max(f[-1] for f in frames)) + 1 if n_frames is None else int(n_frames)
    cubic = interp == "CUBICSPLINE"
    return Keys(tuple(frames), tuple(values), tuple(ins) if cubic else None, tuple(outs) if cubic else None,
                float(fps), T, interp, float(tolerance), tuple(order))
