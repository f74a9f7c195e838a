"""One shot's output files: the rig with its animation (GLB/glTF, or USD by suffix), the weight
CSV and the Live Link Face CSV.

:func:`write_outputs` runs what a pipeline needs for them and writes them; ``face-retarget
retarget`` and ``face-retarget batch`` (:mod:`core.batch`) both call it, so a shot gives the
same bytes whichever way it is run. It returns the stage results it used (the batch reads the
``evaluate`` metrics from them) and the human summary the CLI prints.

Two kinds of result:

* marker methods (every method but ``transfer``): the target rig with its weight animation;
  with ``--method local`` also ``<csv stem>_regions.csv``, the per-region curves (Liu 2011 §6.4);
  optionally the target's ARKit-named shapes as a Live Link Face CSV;
* dense transfer (Xu 2014): a rig of transferred bases (+ the fine details as extra morph
  targets) with their weights (no Live Link output: the bases have no ARKit names), on the
  target's own mesh by default (``transfer_output``, :class:`core.stages.dense.DenseOutput`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from .controls.keys import reduce_keys
from .gaps import fill_gaps
from .io.curves_csv import write_curves_csv, write_keys_csv
from .io.gltf import write_rig
from .io.livelink import arkit_curves, write_livelink
from .progress import ProgressFn
from .solvers.local import region_curves
from .stages.methods import METHODS

#: the stages a marker method's outputs read
MARKER_STAGES = ("load", "frames", "stabilize", "calibrate", "solve", "synthesize", "evaluate")


@dataclass
class ShotOutputs:
    """What :func:`write_outputs` computed and wrote.

    Attributes
    ----------
    dense : True for dense transfer (no ``evaluate`` result then)
    results : stage name -> result, for the stages the outputs read
    weights : (T, K) the written weights, ``names`` (K,) their shapes, ``valid`` (T,) frames with data
    summary : the human summary (what was retargeted, errors, stage timings)
    written : one ``wrote <path>`` line per file written
    paths : the files written, in order
    """

    dense: bool
    results: dict
    weights: np.ndarray
    names: list
    valid: np.ndarray
    summary: str
    written: list = field(default_factory=list)
    paths: list = field(default_factory=list)

    @property
    def evaluation(self) -> Optional[dict]:
        """The pipeline's ``evaluate`` result (None for dense transfer)."""
        return self.results.get("evaluate")

    def text(self, extra=()) -> str:
        """The summary followed by the ``wrote`` lines (and any ``extra`` lines)."""
        return self.summary + "".join("\n" + line for line in [*self.written, *extra])


def write_outputs(pipe, out=None, weights_csv=None, csv_precision=6, progress: Optional[ProgressFn] = None,
                  livelink_csv=None, keys: Optional[str] = None, keys_tolerance: float = 0.005) -> ShotOutputs:
    """Compute ``pipe``'s result and write its rig with animation (``out``), weight CSV
    (``weights_csv``) and Live Link Face CSV (``livelink_csv``).

    Parameters
    ----------
    pipe : core.pipeline.Pipeline
    out : path to write, or None: ``.glb``/``.gltf`` (morph targets + weight animation) or a USD
        suffix (UsdSkel, :mod:`core.io.usd`)
    weights_csv : path of the CSV to write, or None (``time_s, frame, valid``, one column per shape)
    csv_precision : decimals of the CSV weights, or ``"full"`` (round-trip exact)
    progress : ``progress(fraction, message)`` for the pipeline run
    livelink_csv : path of a Live Link Face CSV of the target's ARKit-named shapes, or None
    keys : None (every frame a key), "linear" or "cubic": keyframe reduction of the GLB's animation
        (:func:`core.controls.reduce_keys`, within ``keys_tolerance`` weight at every frame) and a
        ``<csv stem>_keys.csv`` of each curve's own keys beside the weights CSV

    Raises
    ------
    ValueError
        ``livelink_csv`` with dense transfer; and whatever the pipeline raises for bad inputs
        (ValueError / FileNotFoundError naming the file).
    """

    if METHODS[pipe.solve.method].dense:
        if livelink_csv:
            raise ValueError("--livelink-csv: dense transfer makes a new rig of bases (xu_basis_*), which has no ARKit "
                             "shapes to write; use a marker method (bounded, spacetime, ...) for Live Link output")
        return _write_transfer(pipe, out, weights_csv, csv_precision, progress)
    return _write_markers(pipe, out, weights_csv, csv_precision, progress, livelink_csv, keys, keys_tolerance)


def write_animation(path, rig, weights, times, fps: float) -> None:
    """``rig`` with a weight animation: GLB/glTF (morph targets) or USD (UsdSkel, core.io.usd) by suffix."""
    from .io.usd import SUFFIXES as USD_SUFFIXES

    if Path(path).suffix.lower() in USD_SUFFIXES:
        from .io.usd import write_rig as write_usd

        write_usd(path, rig, weights=weights, times=times, fps=fps)
    else:

        write_rig(path, rig, weights=weights, times=times)


def _write_livelink(path, rig, weights, times, fps: float) -> str:
    """The target's ARKit-named shapes as a Live Link Face CSV; returns the ``wrote`` line."""

    perf, missing = arkit_curves(weights, rig.names, fps, times=times, name=rig.name)
    write_livelink(path, perf, timecode_rate=60 if fps <= 60 else 120)
    return f"wrote {path}" + (f" ({len(missing)} ARKit channels the target lacks written as 0: "
                              f"{', '.join(missing[:6])}{' ...' if len(missing) > 6 else ''})" if missing else "")


def _write_markers(pipe, out, weights_csv, csv_precision, progress, livelink_csv=None, keys=None,
                   keys_tolerance=0.005) -> ShotOutputs:

    t0 = time.perf_counter()
    res = pipe.results(list(MARKER_STAGES), progress=progress)
    ld, st, ev = res["load"], res["stabilize"]["source"], res["evaluate"]
    syn = res["synthesize"]
    W, valid = syn["weights"], syn["valid"]
    rig = ld["target_rig"]
    times = st.times - st.times[0]
    frames = res["frames"]["first"] + np.arange(len(times))
    written, paths = [], []
    reduced = None
    if keys:

        reduced = reduce_keys(W, st.fps, keys_tolerance, {"linear": "LINEAR", "cubic": "CUBICSPLINE"}[keys],
                              names=rig.names)
        written.append(f"keys: {int(reduced.counts.sum())} of {W.size} samples ({100 * reduced.counts.sum() / W.size:.1f} %), "
                       f"every frame within {keys_tolerance:g} of the dense curves")
    if out:
        if reduced is not None and str(out).lower().endswith((".glb", ".gltf")):

            F, t_keys, V, A, Bt = reduced.grid()
            write_rig(out, rig, weights=V, times=t_keys, interpolation=reduced.interpolation,
                      tangents=None if A is None else (A, Bt))
        else:
            write_animation(out, rig, W, times, st.fps)
        written.append(f"wrote {out}")
        paths.append(Path(out))
    if livelink_csv:
        written.append(_write_livelink(livelink_csv, rig, W, times, st.fps))
        paths.append(Path(livelink_csv))
    if weights_csv:
        write_curves_csv(weights_csv, times, W, rig.names, csv_precision, valid=valid, frames=frames)
        written.append(f"wrote {weights_csv}")
        paths.append(Path(weights_csv))
        if reduced is not None:

            kpath = Path(weights_csv).with_name(Path(weights_csv).stem + "_keys.csv")
            write_keys_csv(kpath, reduced, rig.names)
            written.append(f"wrote {kpath} (each curve's own keys)")
            paths.append(kpath)
        U = res["solve"]["info"].get("region_weights")
        if U is not None:  # Liu 2011 §6.4: the regional curves an animator edits

            # U holds the shapes the solver used (--target-shapes, minus shapes no marker sees)
            curves = region_curves(fill_gaps(U, valid), res["calibrate"]["rig"].names)
            path = Path(weights_csv).with_name(Path(weights_csv).stem + "_regions.csv")
            write_curves_csv(path, times, np.column_stack(list(curves.values())), list(curves), csv_precision,
                             valid=valid, frames=frames)
            written.append(f"wrote {path} (per-region curves <shape>@r<k>; {weights_csv} holds their mask-area blend)")
            paths.append(path)
    gaps = int((~valid).sum())
    timings = " ".join(f"{k}={v * 1e3:.0f}ms" for k, v in pipe.timings.items() if v)
    summary = (
        f"retargeted {len(W)} frames at {st.fps:g} fps, {len(st.names)} markers -> {rig.name} ({rig.n_shapes} shapes) "
        f"with {pipe.solve.method} in {time.perf_counter() - t0:.1f}s\n"
        f"marker error: median {np.nanmedian(ev['marker_error_mm']):.2f} mm, max {np.nanmax(ev['marker_error_mm']):.2f} mm; "
        f"weights in [{np.nanmin(W):.3f}, {np.nanmax(W):.3f}]"
        + (f"; {gaps} frames without data (tracking loss) filled from their neighbours, flagged valid=0" if gaps else "")
        + f"\nstage timings: {timings}"
    )
    chose = res["solve"]["info"].get("auto")
    if chose:
        summary = f"{chose}\n{summary}"
    return ShotOutputs(False, res, W, list(rig.names), valid, summary, written, paths)


def _write_transfer(pipe, out, weights_csv, csv_precision, progress) -> ShotOutputs:
    """``--method transfer``: dense transfer (Xu 2014) to a rig of new morph targets."""

    t0 = time.perf_counter()
    # target_face in the same run: a second run would reset pipe.timings to its own stages
    res = pipe.results(["target_face", "transfer", "transfer_edit", "detail_morphs", "dense_output"], progress=progress)
    tr, do = res["transfer"], res["dense_output"]
    r = tr["result"]
    target = res["target_face"]["target_rig"]
    rig, weights = do["rig"], do["weights"]
    detail_note = (f"; details as {do['n_details']} morph targets (largest error {do['detail_error'] * 1000:.3f} mm)"
                   if do["n_details"] else "")
    if do["mesh"] == "target":
        c = do["carry"]
        mesh_note = (f"the target's own mesh" + ("" if c is None else
                     f", carried back from the source topology: {int((c.weight > 0).sum())} of {rig.n_vertices} vertices move, "
                     f"{int((c.weight == 1).sum())} fully"))
    else:
        mesh_note = "source topology fitted to the target"
    times = tr["times"]
    frames = tr["first"] + np.arange(len(times))
    written, paths = [], []
    if out:
        write_animation(out, rig, weights, times, tr["fps"])
        written.append(f"wrote {out}")
        paths.append(Path(out))
    if weights_csv:
        write_curves_csv(weights_csv, times, weights, rig.names, csv_precision, valid=tr["valid"], frames=frames)
        written.append(f"wrote {weights_csv}")
        paths.append(Path(weights_csv))
    stages = " ".join(f"{k}={v:.1f}s" for k, v in pipe.timings.items() if v > 0.05)
    summary = (f"transferred {len(weights)} frames to {target.name}: {r.n_bases} bases on {rig.n_vertices} vertices "
               f"({mesh_note}){detail_note} in {time.perf_counter() - t0:.1f}s; stages: {stages}")
    return ShotOutputs(True, res, weights, list(rig.names), np.asarray(tr["valid"], dtype=bool), summary, written, paths)
