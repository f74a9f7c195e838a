"""Evaluate retargeting methods as an animator would look at them: ``face-retarget evaluate``.

For one source and rig pair, every chosen method runs through the pipeline (shared stages are
computed once) and is scored on

* what every take allows: marker error (mm, mean and p95 over frames), velocity error (Seol et
  al. 2012 Fig. 11: the per-frame change of the markers against the source's, mm per marker per
  frame), jitter (mean |second difference| of the weights), the weight range, how many shapes a
  frame uses (|w| > 0.05), and fold-overs (triangles of the target mesh whose normal turns by
  more than 90° against the neutral, on sampled frames);
* and, where a **ground truth** exists — a weight-curve source (e.g. Live Link Face) and a target
  whose shapes share the source channels' canonical ARKit names — the target rig driven by the
  same curves is the truth (:func:`ground_truth`): mean and p95 vertex error on the face (mm),
  vertex velocity error against the truth, and per-shape curve RMSE against the namesakes
  (``curve_rmse``: the mean over the target's shapes that have a namesake channel).

Frames without data (``synthesize["valid"]`` False) are left out of every number. The JSON
(:func:`evaluate_methods`) has the top level ``methods: {method: {metric: value}}``; the HTML
(:func:`write_html`) is self-contained (images inline, no CDN): the table, errors over time, the
curves of the best two methods against the truth, the best method's contact sheet
(:mod:`core.contact_sheet`) and renders of the worst frames (pyvista off screen).
"""

from __future__ import annotations

import base64
import html
import io
import json
import os
import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from .contact_sheet import contact_sheet
from .evaluate import ACTIVE, summarize
from .geometry import face_vertices, flipped_faces
from .metrics import vertex_errors
from .names import NameMap
from .pipeline import Pipeline, StageCache

#: fold-overs are counted on at most this many frames (evenly spaced)
FOLD_FRAMES = 60
#: the keys of :func:`core.evaluate.summarize` a method's row reports (same meaning, same value)
SUMMARY_KEYS = ("frames", "frames_without_data", "marker_mean_mm", "marker_p95_mm", "velocity_error_mm_per_frame",
                "jitter", "weight_min", "weight_max", "active_per_frame")


def readable(x, digits: int = 3, max_decimals: int = 6) -> str:
    """``x`` rounded for people: ``digits`` significant digits in plain decimal notation, never
    scientific (``4220``, ``0.0981``, ``0.000012``); at most ``max_decimals`` decimals (smaller
    magnitudes show as ``0``); ``""`` for None, ``"nan"``/``"inf"`` as Python spells them.

    Whole numbers keep every digit (``12345.6`` -> ``12346``): rounding 12346 to three
    significant digits would print a number that was never measured."""
    if x is None:
        return ""
    x = float(x)
    if not np.isfinite(x):
        return str(x)
    if x == 0:
        return "0"
    decimals = int(min(max(digits - 1 - np.floor(np.log10(abs(x))), 0), max_decimals))
    out = f"{x:.{decimals}f}"
    if decimals and abs(float(out)) >= 10 ** (digits - decimals):  # rounded up a decade: 0.099999 -> 0.100
        out = f"{x:.{decimals - 1}f}"
    return "0" if float(out) == 0 else out


def ground_truth(load: dict, frames: dict) -> Optional[dict]:
    """The target driven by the source's own curves through their canonical names, or None.

    ``weights`` (T, K_target) over the frame range (NaN where the source has no data), ``named``
    (K_target,) bool: target shapes with a namesake channel. None unless the source is weight
    curves and at least one target shape has a namesake.
    """

    src, rig = load["source"], load["target_rig"]
    if src.kind != "curves":
        return None
    nm = NameMap.automatic(src.names, rig.names)
    G = nm.matrix(src.names, rig.names)  # (K_target, C)
    named = np.abs(G).sum(1) > 0
    if not named.any():
        return None
    part = src.frames(frames["first"], frames["stop"])
    data = np.where(part.valid, part.data, np.nan)
    W = np.nan_to_num(data) @ G.T
    missing = (~part.valid).astype(float) @ (G != 0).T.astype(float) > 0
    W[missing] = np.nan
    return {"weights": W, "named": named}


def fold_overs(rig, W, frames_valid, n_frames: int = FOLD_FRAMES) -> float:
    """Mean count of triangles whose normal turns by more than 90° against the neutral's
    (:func:`core.geometry.flipped_faces`), on up to ``n_frames`` evenly spaced valid frames."""
    idx = np.flatnonzero(frames_valid)
    if not len(idx):
        return float("nan")
    idx = idx[np.linspace(0, len(idx) - 1, min(n_frames, len(idx))).round().astype(int)]
    P = rig.neutral[None] + np.einsum("tk,kvc->tvc", np.nan_to_num(W[idx]), rig.deltas)
    return float(flipped_faces(rig.neutral, P, rig.faces).sum(1).mean())


def method_metrics(pipe, truth: Optional[dict] = None, face=None) -> dict:
    """Run the pipeline's current method and score it (see the module docstring).

    The marker, velocity, jitter and weight numbers are :func:`core.evaluate.summarize`'s
    (:data:`SUMMARY_KEYS`, NaN where it has None); this adds ``seconds``, ``fold_overs`` and,
    with a ``truth``, the vertex and curve errors against it. ``face``: vertex ids scored
    (default: :func:`core.geometry.face_vertices` of the target rig)."""
    t0 = time.perf_counter()
    res = pipe.results(["load", "frames", "synthesize", "evaluate"])
    seconds = time.perf_counter() - t0
    syn, ev, rig = res["synthesize"], res["evaluate"], res["load"]["target_rig"]
    W, valid = np.asarray(syn["weights"]), np.asarray(syn["valid"]) & ev["frame_valid"]
    summary = summarize(ev, W, valid, rig.names, ACTIVE)
    out = {"seconds": seconds}
    out.update({k: float("nan") if summary[k] is None else summary[k] for k in SUMMARY_KEYS})
    out["fold_overs"] = fold_overs(rig, W, valid)
    if truth is not None:
        Wt = truth["weights"]
        tvalid = valid & np.isfinite(Wt).all(1)
        face = np.flatnonzero(face_vertices(rig.deltas)) if face is None else face
        mean, p95, vel = vertex_errors(rig.deltas, W, Wt, face, tvalid)
        named = truth["named"]
        per_shape = np.sqrt(np.nanmean((W[tvalid][:, named] - Wt[tvalid][:, named]) ** 2, axis=0))
        out.update({
            "mean_mm": float(np.nanmean(mean)), "p95_mm": p95, "vertex_velocity_error_mm_per_frame": float(np.nanmean(vel)),
            "curve_rmse": float(per_shape.mean()),
            "curve_rmse_per_shape": {n: float(v) for n, v in zip(np.asarray(rig.names)[named], per_shape)},
        })
        out["_per_frame_mm"] = mean
    else:
        out["mean_mm"] = out["p95_mm"] = out["curve_rmse"] = None
    out["_marker_per_frame_mm"] = ev["marker_error_mm"]
    out["_weights"] = W
    return out


def evaluate_methods(settings: dict, methods: Sequence[str], progress=None, cache=None) -> dict:
    """Score ``methods`` on one source + rig pair (``settings``: pipeline settings incl. files).

    Returns ``{"methods": {method: {metric: value}}, "ground_truth": bool, "inputs": {...},
    "settings": {...}}`` plus private per-frame arrays under ``_`` keys for the HTML (dropped
    by :func:`to_json`).
    """

    pipe = Pipeline(cache=cache if cache is not None else StageCache(), **settings)
    base = pipe.results(["load", "frames"])
    truth = ground_truth(base["load"], base["frames"])
    rig = base["load"]["target_rig"]
    face = np.flatnonzero(face_vertices(rig.deltas))
    out = {"methods": {}, "ground_truth": truth is not None,
           "inputs": {k: settings.get(k, "") for k in ("source", "source_rig", "target_rig")},
           "settings": {k: v for k, v in settings.items() if k not in ("source", "source_rig", "target_rig")},
           "_truth": truth, "_rig": rig, "_times": None}
    for i, m in enumerate(methods):
        if progress:
            progress(i / len(methods), m)
        pipe.configure(method=m)
        try:
            out["methods"][m] = method_metrics(pipe, truth, face)
        except Exception as e:  # noqa: BLE001 - one method failing is a row of the report, not the end of it
            out["methods"][m] = {"error": f"{type(e).__name__}: {e}"}
    out["_inputs"] = pipe.results(["load", "frames", "stabilize"])  # what the contact sheet draws
    st = out["_inputs"]["stabilize"]["source"]
    out["_times"] = st.times - st.times[0]
    out["face_vertices"] = int(len(face))
    if progress:
        progress(1.0, "done")
    return out


def to_json(report: dict) -> dict:
    """The report without its private arrays, JSON-able."""
    def clean(d):
        return {k: v for k, v in d.items() if not k.startswith("_")}

    out = clean(report)
    out["methods"] = {m: clean(v) for m, v in report["methods"].items()}
    return out


def write_json(report: dict, path) -> None:
    Path(path).write_text(json.dumps(to_json(report), indent=1, allow_nan=True) + "\n")


# -- HTML --------------------------------------------------------------------------------------
METRICS = [("mean_mm", "vertex error mean (mm)", "{:.3f}"), ("p95_mm", "p95 (mm)", "{:.3f}"),
           ("curve_rmse", "curve RMSE vs namesake", "{:.3f}"), ("marker_mean_mm", "marker error (mm)", "{:.3f}"),
           ("velocity_error_mm_per_frame", "velocity error (mm/frame)", "{:.4f}"), ("jitter", "jitter", "{:.4f}"),
           ("weight_min", "w min", "{:.2f}"), ("weight_max", "w max", "{:.2f}"),
           ("active_per_frame", "shapes > 0.05 / frame", "{:.1f}"), ("fold_overs", "fold-overs", "{:.1f}"),
           ("seconds", "seconds", "{:.2f}")]


#: weights an animator can key: a method whose curves leave this range is ranked after those that do not
KEYABLE = (-0.05, 1.05)


def ranking(report: dict) -> list:
    """Methods best first: those whose weights stay keyable (inside :data:`KEYABLE`) before those
    that do not, each by mean vertex error against the truth where there is one, else by marker
    error (an unregularised fit has the least marker error and weights of hundreds: it is not the
    best result); failed methods last."""
    ok = {m: r for m, r in report["methods"].items() if "error" not in r}
    key = "mean_mm" if report["ground_truth"] else "marker_mean_mm"

    def rank(m):
        r = ok[m]
        keyable = KEYABLE[0] <= r["weight_min"] and r["weight_max"] <= KEYABLE[1]
        return (not keyable, r[key] if r.get(key) is not None else float("inf"))

    return sorted(ok, key=rank) + [m for m in report["methods"] if m not in ok]


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


def _plots(report: dict) -> list:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = report["_times"]
    order = [m for m in ranking(report) if "error" not in report["methods"][m]]
    imgs = []
    fig, ax = plt.subplots(figsize=(10, 3))
    key = "_per_frame_mm" if report["ground_truth"] else "_marker_per_frame_mm"
    for m in order:
        ax.plot(t, report["methods"][m][key], lw=1, label=m)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("mean vertex error vs truth (mm)" if report["ground_truth"] else "marker error RMS (mm)")
    ax.legend(ncol=4, fontsize=8)
    imgs.append(("Error over time", _png(fig)))
    truth = report["_truth"]
    rig = report["_rig"]
    for m in order[:2]:
        W = report["methods"][m]["_weights"]
        if truth is not None:
            named = np.flatnonzero(truth["named"])
            act = np.nanmax(truth["weights"][:, named], axis=0) - np.nanmin(truth["weights"][:, named], axis=0)
            shapes = named[np.argsort(-np.nan_to_num(act))[:6]]
        else:
            shapes = np.argsort(-np.ptp(W, axis=0))[:6]
        fig, axes = plt.subplots(2, 3, figsize=(10, 4.4), sharex=True)
        for ax, k in zip(axes.ravel(), shapes):
            ax.plot(t, W[:, k], lw=1, label=m)
            if truth is not None:
                ax.plot(t, truth["weights"][:, k], lw=1, ls="--", color="k", label="truth")
            ax.set_title(rig.names[k], fontsize=8)
        axes[0, 0].legend(fontsize=7)
        imgs.append((f"Curves of {m}" + (" (dashed: the truth)" if truth is not None else ""), _png(fig)))
    return imgs


def _renders(report: dict, n: int = 2) -> list:
    """Off-screen renders of the best method's worst frames: result | truth, error coloured."""
    if not report["ground_truth"]:
        return []
    try:

        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
        import pyvista as pv
    except ImportError:  # pragma: no cover - pyvista is a dependency
        return []
    best = ranking(report)[0]
    r = report["methods"][best]
    rig, Wt = report["_rig"], report["_truth"]["weights"]
    per = np.nan_to_num(r["_per_frame_mm"], nan=-1)
    frames = np.argsort(-per)[:n]
    out = []
    faces = np.hstack([np.full((len(rig.faces), 1), 3), rig.faces]).ravel()
    for f in frames:
        P = rig.neutral + np.einsum("k,kvc->vc", np.nan_to_num(r["_weights"][f]), rig.deltas)
        Q = rig.neutral + np.einsum("k,kvc->vc", np.nan_to_num(Wt[f]), rig.deltas)
        err = np.linalg.norm(P - Q, axis=1) * 1e3
        p = pv.Plotter(off_screen=True, shape=(1, 2), window_size=(900, 450), border=False)
        for i, (X, title) in enumerate(((P, f"{best}, frame {f}"), (Q, "truth"))):
            p.subplot(0, i)
            mesh = pv.PolyData(X, faces)
            mesh["error mm"] = err
            p.add_mesh(mesh, scalars="error mm", cmap="inferno", clim=(0, max(2.0, float(np.percentile(err, 99)))),
                       show_scalar_bar=i == 0, smooth_shading=True)
            p.add_text(title, font_size=10)
            p.view_xy()
        p.link_views()
        img = p.screenshot(return_img=True)
        p.close()
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig = plt.figure(figsize=(9, 4.5))
        plt.imshow(img)
        plt.axis("off")
        out.append((f"Worst frame {f} of {best}: mean {per[f]:.2f} mm", _png(fig)))
    return out


def _contact_sheet(report: dict) -> list:
    """The best method's contact sheet (:mod:`core.contact_sheet`): source | target at its worst
    frame (by the mean vertex error against the truth where there is one, else the marker error RMS,
    as the page's), each caption saying which, and the frames farthest apart in the take's expression."""
    order = [m for m in ranking(report) if "error" not in report["methods"][m]]
    if not order or "_inputs" not in report:
        return []
    best = order[0]
    r = report["methods"][best]
    per = np.asarray(r["_per_frame_mm"] if report["ground_truth"] else r["_marker_per_frame_mm"], dtype=np.float64)
    worst = int(np.argmax(np.where(np.isfinite(per), per, -np.inf)))
    sheet = contact_sheet(report["_inputs"], r["_weights"], worst, error_mm=per,
                          error_label="vertex error (mean)" if report["ground_truth"] else "marker RMS")
    what = "mean vertex error against the truth" if report["ground_truth"] else "marker error RMS"
    return [(f"Contact sheet of {best}: source | target at the worst frame by {what} (red, frame {sheet.take_frames[0]}) "
             "and the frames farthest apart in the take's expression",
             "data:image/png;base64," + base64.b64encode(sheet.png()).decode())]


def write_html(report: dict, path) -> None:
    """The self-contained HTML report (see the module docstring)."""
    order = ranking(report)
    head = "".join(f"<th>{html.escape(label)}</th>" for _, label, _ in METRICS)
    rows = []
    for m in order:
        r = report["methods"][m]
        if "error" in r:
            rows.append(f"<tr><td>{html.escape(m)}</td><td colspan={len(METRICS)}>failed: {html.escape(r['error'])}</td></tr>")
            continue
        cells = "".join(f"<td>{'—' if r.get(k) is None else fmt.format(r[k])}</td>" for k, _, fmt in METRICS)
        rows.append(f"<tr><td><b>{html.escape(m)}</b></td>{cells}</tr>")
    imgs = _contact_sheet(report) + _plots(report) + _renders(report)
    inp = report["inputs"]
    truth = ("ground truth: the target rig driven by the source's own curves through their ARKit names"
             if report["ground_truth"] else "no ground truth (not a weight-curve source with namesake target shapes)")
    doc = f"""<!doctype html><html><head><meta charset="utf-8"><title>face-retarget evaluate</title>
<style>body{{font-family:sans-serif;margin:20px;max-width:1200px}}table{{border-collapse:collapse;font-size:13px}}
td,th{{border:1px solid #ccc;padding:4px 8px;text-align:right}}td:first-child{{text-align:left}}img{{max-width:100%}}</style>
</head><body><h1>Retargeting evaluation</h1>
<p>{html.escape(Path(inp['source']).name)} → {html.escape(Path(inp['target_rig']).name)}
{('(source rig ' + html.escape(Path(inp['source_rig']).name) + ')') if inp.get('source_rig') else ''};
{report['methods'][order[0]].get('frames', '?') if order else 0} frames; {report['face_vertices']} face vertices scored; {truth}.</p>
<table><tr><th>method</th>{head}</tr>{''.join(rows)}</table>
{''.join(f'<h2>{html.escape(t)}</h2><img src="{src}">' for t, src in imgs)}
</body></html>"""
    Path(path).write_text(doc, encoding="utf-8")
