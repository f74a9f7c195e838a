"""``face-retarget``: the command line.

    face-retarget retarget --source take.csv --source-rig ict.glb --target-rig other.glb --out r.glb
    face-retarget evaluate --source take.csv --source-rig ict.glb --target-rig other.glb --json r.json --html r.html
    face-retarget batch shots/ --out results/ [--template shot.json] [--workers N] [--scheduler tcp://host:8786]
    face-retarget layout --from data/layouts/ict_facekit.json --rig new.glb --out new.json
    face-retarget serve [--port N] [--address A] [--show]
    face-retarget live --listen 0.0.0.0:11111 --shot shot.json --osc 127.0.0.1:9000 [--livelink-out HOST:PORT]
    face-retarget info FILE...
    face-retarget bench

Solver flags (``--alpha``, ``--regions``, ``--mu`` ...) are generated from the pipeline's
settings objects, the same ones that generate the dashboard's widgets.
"""

from __future__ import annotations

import argparse
import json
import os
import runpy
import signal
import sys
import tempfile
import threading
import time
import warnings
from pathlib import Path

from .batch import collect_shots, run_batch, zip_results
from .controls.table import read_table
from .io.livelink import write_livelink
from .io.performance import read_performance
from .live import LiveLinkOut, LiveRetargeter, LiveSession, OscOut, listen, neutral_take, parse_address
from .io.rigs import load_rig
from .names import NameMap, arkit_combination, load_vocabularies, rank_vocabularies, recognise
from .outputs import write_outputs
from .pipeline import Pipeline, StageCache, add_cli_arguments
from .progress import StderrBar
from .registration import layout_command, place_missing_layouts
from .report import evaluate_methods, ranking, write_html, write_json
from .stages.methods import METHODS as REGISTRY, suggested_frames

ROOT = Path(__file__).resolve().parents[1]

# The solvers factor many small matrices; BLAS threads only add contention on small
# machines (measured 10-50x slowdowns on 2 loaded cores). Users can still override.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


#: one stage cache per process: several runs in one process (tests, scripts calling main())
#: share the rigs they load and the segmentations they compute
_CACHE = None
#: CLI options that are not pipeline settings
OUTPUT_OPTIONS = ("func", "out", "weights_csv", "livelink_csv", "quiet", "command", "shot", "save_shot", "csv_precision",
                  "controls_file", "keys", "keys_tolerance", "example_poses_file", "n", "no_auto_markers", "listen", "osc", "livelink_out",
                  "record", "duration", "stats")


def _cache():
    global _CACHE

    if _CACHE is None:
        _CACHE = StageCache(max_entries=64)
    return _CACHE


def read_example_poses(path) -> list:
    """The example poses of ``--example-poses FILE.json``: ``[{"frame": F, "weights": {shape: w}}, ...]``
    (frames of the take, target shape names; checked against the rig when the solve reads them)."""
    path = Path(path)
    try:
        items = json.loads(path.read_text(encoding="utf-8-sig"))
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: no such example-poses file") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: not an example-poses file (JSON expected: {e})") from None
    if isinstance(items, dict) and isinstance(items.get("example_poses"), list):
        items = items["example_poses"]  # what `suggest-poses --out` writes
    if not isinstance(items, list) or not all(isinstance(i, dict) and "frame" in i and isinstance(i.get("weights"), dict)
                                              for i in items):
        raise ValueError(f"{path}: expected a list of {{\"frame\": F, \"weights\": {{\"<target shape>\": w, ...}}}}")
    return items


def _settings(args) -> dict:
    """The pipeline settings of a command's flags; ``--controls FILE`` reads the per-shape table,
    ``--example-poses FILE`` the example poses."""
    settings = {k: v for k, v in vars(args).items() if k not in OUTPUT_OPTIONS}
    if getattr(args, "controls_file", None):
        settings["controls"] = read_table(args.controls_file)
    if getattr(args, "example_poses_file", None):
        settings["example_poses"] = read_example_poses(args.example_poses_file)
    return settings


def _suggest_poses(args) -> int:
    """The frames to pose: far apart in expression (core.examples.suggest_poses)."""
    pipe = _pipeline(args)
    res = pipe.results(["load", "frames", "stabilize", "synthesize"])
    first, rig, W = res["frames"]["first"], res["load"]["target_rig"], res["synthesize"]["weights"]
    frames = suggested_frames(res, args.n, pipe.solve.example_poses)  # a shot's poses count as chosen
    items = [{"frame": f, "weights": {n: round(float(W[f - first, k]), 4) for k, n in enumerate(rig.names)
                                      if W[f - first, k] > 0.01}} for f in frames]
    print(f"pose these {len(items)} frames (far apart in expression): " + ", ".join(str(i["frame"]) for i in items))
    if args.out:
        Path(args.out).write_text(json.dumps(items, indent=1) + "\n")
        print(f"wrote {args.out}: the current result at each frame, to correct and pass back with --example-poses")
    return 0


def _auto_markers(settings: dict, args) -> dict:
    """The layouts to add for the rigs (and a mesh-sequence source) that have none: placed
    automatically as the page does (:func:`core.registration.place_missing_layouts`), with the
    page's report of the markers that landed badly; ``--no-auto-markers`` refuses instead."""

    quiet = getattr(args, "quiet", False)
    updates, reports = place_missing_layouts(settings, place=not getattr(args, "no_auto_markers", False),
                                             progress=None if quiet else StderrBar("markers"))
    for what, path, report in reports:
        print(f"{report['message']}\nwrote {path} (the {what.replace('_', ' ')} from now on: edit it to move a marker, "
              f"or pass --{what.replace('_', '-')})")
    return updates


def _pipeline(args):
    """The pipeline of a ``retarget`` run: the shot (``--shot``) with the flags given on top; markers
    placed on a rig that has no layout (``--no-auto-markers``: refused)."""

    settings = _settings(args)
    if getattr(args, "shot", None):
        pipe = Pipeline.from_shot(args.shot, cache=_cache(), **settings)
    else:
        pipe = Pipeline(cache=_cache(), **settings)
    cfg = pipe.config()
    updates = _auto_markers({**vars(cfg.take), **vars(cfg.source_face), **vars(cfg.target_face)}, args)
    if updates:
        pipe.configure(**updates)
    if getattr(args, "save_shot", None):
        pipe.shot().to_json(args.save_shot)
    return pipe


def _retarget(args) -> int:

    pipe = _pipeline(args)
    label = "transfer" if REGISTRY[pipe.solve.method].dense else "retarget"
    out = write_outputs(pipe, args.out, args.weights_csv, args.csv_precision, livelink_csv=args.livelink_csv,
                        progress=None if args.quiet else StderrBar(label), keys=args.keys, keys_tolerance=args.keys_tolerance)
    print(out.text([f"wrote {args.save_shot}"] if args.save_shot else []))
    return 0


def _evaluate(args) -> int:
    """``face-retarget evaluate``: score methods on one source + rig pair (core.report)."""

    methods = [m.strip() for m in args.methods.split(",")] if args.methods else [n for n, m in REGISTRY.items() if not m.dense]
    unknown = [m for m in methods if m not in REGISTRY or REGISTRY[m].dense]
    if unknown:
        raise ValueError(f"--methods: unknown or dense methods {unknown}; choose from "
                         f"{[n for n, m in REGISTRY.items() if not m.dense]}")
    settings = {k: v for k, v in _settings(args).items() if k not in ("methods", "json", "html", "method")}
    if getattr(args, "shot", None):

        base = Pipeline.from_shot(args.shot, **settings).shot()
        settings = {**{k: v for st in base.settings.values() for k, v in st.items()},
                    **{k: base.resolve(k) for k in base.files}}
        settings.pop("method", None)
    settings.update(_auto_markers(settings, args))
    report = evaluate_methods(settings, methods, progress=None if args.quiet else StderrBar("evaluate"), cache=_cache())
    if args.json:
        write_json(report, args.json)
    if args.html:
        write_html(report, args.html)
    cols = ("mean_mm", "p95_mm", "curve_rmse", "marker_mean_mm", "velocity_error_mm_per_frame", "weight_min", "weight_max",
            "active_per_frame", "seconds")
    print(f"{'method':10s} " + " ".join(f"{c:>15s}" for c in cols))
    for m in ranking(report):
        r = report["methods"][m]
        if "error" in r:
            print(f"{m:10s} failed: {r['error']}")
            continue
        print(f"{m:10s} " + " ".join(f"{'-' if r.get(c) is None else format(r[c], '15.4f')}" for c in cols))
    print(("ground truth: the target driven by the source's own curves" if report["ground_truth"] else
           "no ground truth for this pair (marker error only)")
          + (f"\nwrote {args.json}" if args.json else "") + (f"\nwrote {args.html}" if args.html else ""))
    return 0


def _batch(args) -> int:
    """``batch``: many shots on Dask (:func:`core.batch.run_batch`); the CLI only parses."""

    jobs = collect_shots(args.inputs, template=args.template)
    if not jobs:
        raise ValueError("no shots to run")
    say = (lambda line: print(f"\r{line}".ljust(100), file=sys.stderr, flush=True))  # over the bar's line
    bar = None if args.quiet else StderrBar("batch")
    if threading.current_thread() is threading.main_thread():
        # SIGINT stops the batch keeping the finished shots, also when the command was started in the
        # background by a script (`cmd &`: the shell makes it ignore SIGINT and Python then installs no
        # handler, so `kill -INT` did nothing and the batch ran to the end)
        signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        results = run_batch(jobs, args.out, client=args.scheduler, progress=bar, workers=args.workers, files=args.files,
                            csv_precision=args.csv_precision, force=args.force, log=say,
                            dashboard_address=args.dashboard_address, auto_markers=not args.no_auto_markers)
    except KeyboardInterrupt:
        print(f"\ninterrupted: finished shots are in {args.out}; run the same command again to resume", file=sys.stderr)
        return 130
    counts = {s: sum(r.status == s for r in results) for s in ("ok", "skipped", "failed", "pending")}
    for r in results:
        if r.status == "failed":
            print(f"failed: {r.name}: {r.error.splitlines()[0] if r.error else ''} (see {r.folder}/log.txt)", file=sys.stderr)
    print(f"{len(results)} shots: {counts['ok']} computed, {counts['skipped']} already done, {counts['failed']} failed"
          + (f", {counts['pending']} not run" if counts["pending"] else "")
          + f"\nwrote {Path(args.out) / 'summary.csv'} and {Path(args.out) / 'summary.html'}")
    if args.zip:
        print(f"wrote {zip_results(args.out, args.zip)}")
    return 1 if counts["failed"] or counts["pending"] else 0


def _live(args) -> int:
    """``face-retarget live``: a Live Link Face stream retargeted as it arrives (core.live)."""

    host, port = parse_address(args.listen, "0.0.0.0")
    outputs_at = [parse_address(a) if a else None for a in (args.osc, args.livelink_out)]
    with tempfile.TemporaryDirectory(prefix="face-retarget-live-") as tmp:
        pipe = _pipeline(args)
        if not pipe.take.source:  # no recorded take: the stages run on a neutral one (core.live.neutral_take)
            pipe.configure(source=str(neutral_take(Path(tmp) / "neutral.csv")))
        rt = LiveRetargeter(pipe)
    print(rt.choice, flush=True)  # what it does per packet, in auto's sentence style
    session = LiveSession(rt, record=bool(args.record))
    outputs = []
    if outputs_at[0]:
        outputs.append(OscOut(*outputs_at[0], rt.target_names))
    if outputs_at[1]:
        outputs.append(LiveLinkOut(*outputs_at[1], rt.target_names))
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    timer = threading.Timer(args.duration or 0, stop.set)
    timer.daemon = True
    if args.duration:
        timer.start()
    latencies = []

    def ready(h, p):
        print(f"listening on {h}:{p}", flush=True)

    def on_frame(frame, latency):
        if len(latencies) < 1_000_000:
            latencies.append(latency)

    t0 = time.monotonic()
    try:
        listen(session, host, port, outputs, stop, on_frame, ready)
    except OSError as e:  # the port is taken, the address is not this machine's ...
        raise ValueError(f"--listen {args.listen}: cannot listen there ({e.strerror or e})") from None
    finally:
        timer.cancel()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        for out in outputs:
            out.close()
    st = session.stats()
    lat = sorted(latencies)
    st["latency_ms"] = ({"p50": 1e3 * lat[len(lat) // 2], "p95": 1e3 * lat[min(len(lat) - 1, int(0.95 * len(lat)))],
                         "max": 1e3 * lat[-1]} if lat else {})
    st["seconds"] = time.monotonic() - t0
    answered = sum(s["answered"] for s in st["subjects"].values())
    print(f"received {st['received']} packets, answered {answered}, bad {sum(st['bad'].values())} {st['bad']}; "
          + "; ".join(f"{k or '(no name)'}: dropped {s['dropped']}, repeated {s['repeated']}, out of order "
                      f"{s['out_of_order']}, tracking lost {s['tracking_lost']}" for k, s in st["subjects"].items())
          + (f"; latency p50 {st['latency_ms']['p50']:.2f} ms, p95 {st['latency_ms']['p95']:.2f} ms" if lat else ""),
          flush=True)
    if args.record:
        for k, stream in session.streams.items():
            if stream.recorded:
                path = Path(args.record)
                if len(session.streams) > 1:
                    path = path.with_name(f"{path.stem}_{k or 'subject'}{path.suffix}")
                write_livelink(path, stream.take())
                print(f"wrote {path}: {len(stream.recorded)} frames of {k or '(no name)'}")
    if args.stats:
        Path(args.stats).write_text(json.dumps(st, indent=1) + "\n")
    return 0


def _layout(args) -> int:

    print(layout_command(args.from_, args.rig, args.out, source_rig_path=args.source_rig))
    return 0


def _serve(args) -> int:
    from dashboard.serve import serve

    oauth = None
    if args.oauth_provider:
        oauth = {"provider": args.oauth_provider, "key": os.environ.get("FACE_RETARGET_OAUTH_KEY", ""),
                 "secret": os.environ.get("FACE_RETARGET_OAUTH_SECRET", ""), "redirect_uri": args.oauth_redirect_uri,
                 "encryption_key": os.environ.get("FACE_RETARGET_OAUTH_ENCRYPTION_KEY")}
    return serve(port=args.port, address=args.address, show=args.show, allow_websocket_origin=args.allow_websocket_origin,
                 data_dir=args.data_dir, review=not args.no_review, password=args.password or os.environ.get("FACE_RETARGET_PASSWORD"),
                 max_upload_mb=args.max_upload_mb, oauth=oauth, warm_pages=args.warm_pages,
                 warm_wait=args.warm_wait)


def _is_rig(p: Path) -> bool:
    """A rig file or folder (vs a performance): GLB/glTF, an OBJ rig folder (neutral.obj), a USD
    file with UsdSkel blend shapes."""
    suffix = p.suffix.lower()
    if p.is_dir():
        return (p / "neutral.obj").exists()
    if suffix in (".glb", ".gltf", ".vrm"):
        return True
    if suffix in (".usd", ".usda", ".usdc", ".usdz"):
        from .io.usd import has_blendshapes

        return has_blendshapes(p)
    return False


def _info(args) -> int:

    for f in args.files:
        p = Path(f)
        if _is_rig(p):
            r = load_rig(p)
            print(f"{p}: rig {r.name}: {r.n_vertices} vertices, {len(r.faces)} triangles, {r.n_shapes} shapes, "
                  f"size {r.size * 100:.1f} cm, uvs={'yes' if r.uvs is not None else 'no'}")
            print("  shapes: " + ", ".join(r.names))
        else:
            perf = read_performance(p)
            print(f"{p}: {perf.kind}, {perf.n_frames} frames at {perf.fps:g} fps ({perf.duration:.1f} s), "
                  f"{len(perf.names)} channels, {(~perf.valid).sum()} missing samples, units {perf.units}")
            print("  channels: " + ", ".join(perf.names))
    return 0


def _names(args) -> int:
    """Show the vocabularies of the source's and the target's names and which source channels
    drive each target shape (:meth:`core.names.NameMap.automatic`); ``--out`` writes that map
    for a user to edit."""

    vocabs = load_vocabularies(args.vocabulary or ())
    src = Path(args.source)
    source_names = load_rig(src).names if _is_rig(src) else read_performance(src).names
    target = load_rig(args.target_rig)
    names = list(target.names)
    if args.target_shapes:
        names = [target.names[target.index(n.strip())] for n in args.target_shapes.split(",") if n.strip()]
    print(f"source {src.name}: {recognise(source_names, vocabs)}")
    print(f"target {target.name}{' (' + str(len(names)) + ' shapes)' if args.target_shapes else ''}: {recognise(names, vocabs)}")
    nm = NameMap.automatic(source_names, names, vocabs)
    missing = nm.unmapped(names)
    ranked = rank_vocabularies(vocabs, names)  # the order automatic looked the target names up in
    width = max(map(len, names))
    for t in names:
        pairs = nm.entries.get(t)
        hit = arkit_combination(t, ranked)
        how = f"  [{hit[0]}]" if hit else ""
        if pairs:
            print(f"  {t:<{width}} <- " + " + ".join(s if g == 1 else f"{g:.4g}*{s}" for s, g in pairs) + how)
        elif not args.mapped_only:
            why = ("name not recognised" if not hit else "no ARKit counterpart" if not hit[1]
                   else "its ARKit shapes drive another shape or the source lacks them")
            print(f"  {t:<{width}} -- ({why}){how}")
    print(f"{len(nm.entries)} of {len(names)} shapes of {target.name} mapped"
          + (f"; unmapped (edit the map to drive them): {', '.join(missing[:12])}{' ...' if len(missing) > 12 else ''}" if missing else ""))
    if args.out:
        # unmapped shapes are written with an empty list: the keys a user fills in
        NameMap({t: nm.entries.get(t, []) for t in names}).to_json(args.out)
        print(f"wrote {args.out}")
    return 0


def _bench(args) -> int:

    script = ROOT / "benchmarks" / "run.py"
    if not script.exists():
        print("benchmarks/ is not installed with the package; run from a source checkout", file=sys.stderr)
        return 2
    sys.argv = [str(script)] + (args.only or [])
    runpy.run_path(str(script), run_name="__main__")
    return 0


def _auto_markers_flag(parser) -> None:
    parser.add_argument("--no-auto-markers", action="store_true",
                        help="refuse a rig or mesh sequence without a marker layout instead of placing the markers "
                             "automatically (as the page does; the layout is written beside it as <name>.layout.json)")


def build_parser() -> argparse.ArgumentParser:

    p = argparse.ArgumentParser(prog="face-retarget", description="Facial performance retargeting onto blendshape rigs.")
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("retarget", help="retarget a performance onto a rig and write GLB/CSV")
    add_cli_arguments(r)
    r.add_argument("--shot", help="shot JSON to reproduce (from --save-shot or the dashboard's download); the other "
                                  "flags given override it")
    r.add_argument("--save-shot", help="write the shot of this run (files with content hashes, every setting) as JSON")
    r.add_argument("--out", help="output GLB/glTF (the target rig with a morph-weight animation) or USD .usda/.usdc/.usdz "
                                 "(UsdSkel blend shapes + SkelAnimation; needs face-retarget[usd])")
    r.add_argument("--weights-csv", help="output CSV: time_s, frame, valid (0 = no data, filled), one column per target shape")
    r.add_argument("--livelink-csv", help="output Live Link Face CSV of the target's ARKit-named shapes (MetaHuman, "
                                          "Unreal Live Link); ARKit channels the target lacks are 0")
    r.add_argument("--csv-precision", default=6, type=lambda v: v if v == "full" else int(v),
                   help="decimals of the CSV weights, or 'full' for round-trip exact values (default: 6)")
    r.add_argument("--quiet", action="store_true", help="no progress bar")
    r.add_argument("--controls", dest="controls_file", help="per-shape controls table JSON (bounds, gain, offset, active, "
                                                             "symmetry and cancel pairs; see docs/controls.md)")
    r.add_argument("--example-poses", dest="example_poses_file", metavar="FILE.json",
                   help='example poses for auto: [{"frame": F, "weights": {"<target shape>": w, ...}}, ...]; auto learns '
                        "from them a correspondence for the whole take (face-retarget suggest-poses proposes the frames)")
    r.add_argument("--keys", choices=["linear", "cubic"], default=None,
                   help="keyframe reduction: the GLB keeps the fewest keys (linear or cubic Hermite) that stay within "
                        "--keys-tolerance of every frame, and <csv>_keys.csv lists each curve's keys (default: every frame)")
    r.add_argument("--keys-tolerance", type=float, default=0.005, help="largest weight difference of the reduced curves "
                                                                        "(default: 0.005)")
    _auto_markers_flag(r)
    r.set_defaults(func=_retarget)

    sp = sub.add_parser("suggest-poses", help="the frames to pose for auto's example poses: far apart in expression",
                        description="Propose the take frames to pose the target at (farthest apart in expression, the "
                                    "most expressive first) and, with --out, write the current result at them as an "
                                    "example-poses file to correct and pass back with `retarget --example-poses`.")
    add_cli_arguments(sp)
    sp.add_argument("-n", type=int, default=8, help="how many frames (default: 8)")
    sp.add_argument("--shot", help="a shot whose files and settings to use (the flags given override it)")
    sp.add_argument("--out", help="write the poses of the current result at those frames (JSON for --example-poses)")
    _auto_markers_flag(sp)
    sp.set_defaults(func=_suggest_poses)

    ev = sub.add_parser(
        "evaluate", help="score methods on a source + rigs: JSON and a self-contained HTML report",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Run several methods on one take and rig pair and score each as an animator would look: marker "
                    "error, velocity error (mm per frame), weight range, shapes used per frame and, where the target "
                    "shares the take's ARKit names, the vertex error and each curve's distance to its namesake "
                    "(the target driven by the take's own curves is the truth). Prints a table; --json and --html "
                    "write it (the HTML with plots and renders inline).",
        epilog=("example:\n  face-retarget evaluate --source data/performances/livelinkface_take_s07.csv "
                "--source-rig data/rigs/ict_facekit.glb \\\n      --target-rig data/rigs/rocketbox_female_adult_02.glb "
                "--target-shapes arkit --methods auto,bounded,spacetime --html report.html"))
    add_cli_arguments(ev)
    ev.add_argument("--methods", help="comma-separated methods (default: every solve method)")
    ev.add_argument("--shot", help="a shot whose files and settings to evaluate (the flags given override it)")
    ev.add_argument("--json", help="output JSON: {methods: {method: {metric: value}}}")
    ev.add_argument("--html", help="output HTML report (self-contained: plots and renders inline)")
    ev.add_argument("--quiet", action="store_true", help="no progress bar")
    ev.add_argument("--controls", dest="controls_file", help="per-shape controls table JSON (see docs/controls.md)")
    _auto_markers_flag(ev)
    ev.set_defaults(func=_evaluate)

    bt = sub.add_parser("batch", help="retarget many shots on Dask (a local cluster, or --scheduler)",
                        description="Retarget many shots on Dask distributed: one output folder per shot (GLB, CSV, "
                                    "evaluation.json, log.txt, manifest.json) and summary.csv/.html. Finished shots "
                                    "(same shot content) are skipped, so an interrupted batch resumes. See docs/batch.md.")
    bt.add_argument("inputs", nargs="+", metavar="INPUT",
                    help="shot files, folders of shot files, list files (.txt: one path per line) or globs; "
                         "captures (any other file) need --template")
    bt.add_argument("--out", required=True, help="output folder")
    bt.add_argument("--template", help="shot JSON whose rigs and settings are applied to each capture (its source replaced)")
    bt.add_argument("--workers", type=int, default=None, help="local worker processes (default: one per core)")
    bt.add_argument("--scheduler", default=None, help="address of an existing Dask scheduler (tcp://host:8786) "
                                                      "instead of a local cluster")
    bt.add_argument("--files", choices=("auto", "shared", "scatter"), default="auto",
                    help="how input files reach workers: shared (read the recorded paths), scatter (sent once from "
                         "here); auto: shared on the local cluster, scatter on --scheduler (default: auto)")
    bt.add_argument("--csv-precision", default=6, type=lambda v: v if v == "full" else int(v),
                    help="decimals of the CSV weights, or 'full' (default: 6)")
    bt.add_argument("--force", action="store_true", help="recompute shots that are already done")
    bt.add_argument("--zip", default=None, metavar="FILE.zip", help="also zip the output folder into FILE.zip")
    bt.add_argument("--dashboard-address", default=":8787",
                    help="local cluster's dashboard address (default :8787; :0 a free port)")
    bt.add_argument("--quiet", action="store_true", help="no progress bar")
    _auto_markers_flag(bt)
    bt.set_defaults(func=_batch)

    lv = sub.add_parser("live", help="retarget a Live Link Face stream as it arrives; send OSC / Live Link out",
                        description="Receive the Live Link Face app's UDP packets and retarget every packet as it "
                                    "arrives onto the target rig (the shot's rigs, layouts, controls; a bounded "
                                    "per-frame solve with the One Euro filter when the shot asks for it). Prints "
                                    "'listening on HOST:PORT' when ready; stops on Ctrl-C (or after --duration) "
                                    "and prints the counts. See docs/live.md.")
    add_cli_arguments(lv)
    lv.add_argument("--listen", required=True, metavar="HOST:PORT",
                    help="where to receive (the address to give the iPhone app, e.g. 0.0.0.0:11111)")
    lv.add_argument("--shot", help="a shot whose rigs and settings to use (the flags given override it)")
    lv.add_argument("--osc", metavar="HOST:PORT", help="send each frame's target weights as one OSC bundle of "
                                                       "/avatar/parameters/<shape> floats (VRChat: 127.0.0.1:9000)")
    lv.add_argument("--livelink-out", metavar="HOST:PORT", help="re-send the target's ARKit-named shapes as Live Link "
                                                                "Face packets (Unreal / Blender Live Link)")
    lv.add_argument("--record", metavar="FILE.csv", help="write what was received as a Live Link Face take at exit")
    lv.add_argument("--duration", type=float, default=None, help="stop after this many seconds")
    lv.add_argument("--stats", metavar="FILE.json", help="write the counts and latencies at exit")
    lv.set_defaults(func=_live)

    lay = sub.add_parser("layout", help="transfer a marker layout to a rig of any topology (non-rigid ICP)")
    lay.add_argument("--from", dest="from_", required=True, help="layout JSON to transfer")
    lay.add_argument("--rig", required=True, help="rig to place the markers on (GLB, USD, OBJ folder), or a mesh sequence "
                                              "(folder of OBJ/PLY frames, USD mesh with time-sampled points): its first frame")
    lay.add_argument("--out", required=True, help="output layout JSON")
    lay.add_argument("--source-rig", default=None, help="rig the layout was made for (default: its 'rig' field in data/rigs)")
    lay.set_defaults(func=_layout)

    s = sub.add_parser("serve", help="serve the dashboard")
    s.add_argument("--port", type=int, default=5006)
    s.add_argument("--address", default="localhost")
    s.add_argument("--show", action="store_true", help="open a browser")
    s.add_argument("--allow-websocket-origin", action="append", default=None, help="extra allowed origins host:port")
    s.add_argument("--data-dir", default=None, help="review store folder: shots, notes, uploaded files (default: the "
                                                    "per-user data folder, e.g. ~/.local/share/face-retarget)")
    s.add_argument("--no-review", action="store_true", help="pages of their own: nothing shared, nothing kept")
    s.add_argument("--password", default=None, help="ask every visitor for this password (Panel basic auth; or set "
                                                    "FACE_RETARGET_PASSWORD); use with --address to share")
    s.add_argument("--max-upload-mb", type=float, default=200.0, help="largest upload in MB (default: 200)")
    s.add_argument("--oauth-provider", default=None, help="Panel OAuth provider (github, gitlab, google, azure, okta, ...); "
                                                          "key/secret from FACE_RETARGET_OAUTH_KEY/_SECRET (docs/review.md)")
    s.add_argument("--oauth-redirect-uri", default=None, help="OAuth redirect URI (the address reviewers open)")
    s.add_argument("--warm-pages", type=int, default=4, help="pages of each opened shot built ahead while the server is "
                                                            "idle, for that many reviewers opening it at once; a shot that had more people on it at "
                                                            "once keeps that many, up to 24 (default: 4; 0: none)")
    s.add_argument("--warm-wait", type=float, default=30.0,
                   help="seconds without a change or a page request before a warm page is built while someone is on "
                        "the shot (a change made during a build waits for it, ~1 s; default: 30; nobody on it: 3)")
    s.set_defaults(func=_serve)

    n = sub.add_parser("names", help="show the vocabularies of the names and the automatic channel->shape map; "
                                     "--out writes it (JSON) for editing",
                       description="Which vocabularies (ARKit, SRanipal, FACS, Unified Expressions, Meta, visemes ...; "
                                   "data/namemaps/vocabulary_*.json) the source's and the target's names use, and which "
                                   "source channels drive each target shape. See docs/names.md.")
    n.add_argument("--source", required=True, help="performance or rig whose channel/shape names drive")
    n.add_argument("--target-rig", required=True, help="rig whose shapes are driven")
    n.add_argument("--out", default=None, help="name map JSON to write (pass it back with --name-map)")
    n.add_argument("--vocabulary", action="append", default=None, metavar="FILE_OR_FOLDER",
                   help="more vocabulary JSON (or a folder of vocabulary_*.json) on top of the bundled ones; repeatable")
    n.add_argument("--target-shapes", default=None, help="comma-separated target shapes to map (default: all)")
    n.add_argument("--mapped-only", action="store_true", help="list only the target shapes that are driven")
    n.set_defaults(func=_names)

    i = sub.add_parser("info", help="describe rigs and performances")
    i.add_argument("files", nargs="+")
    i.set_defaults(func=_info)

    b = sub.add_parser("bench", help="run the benchmarks (source checkout)")
    b.add_argument("only", nargs="*", help="benchmark names to run (default: all)")
    b.set_defaults(func=_bench)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    with warnings.catch_warnings():
        warnings.simplefilter("default")
        warnings.formatwarning = lambda msg, cat, *a, **k: f"warning: {msg}\n"
        try:
            return args.func(args)
        except (ValueError, FileNotFoundError, KeyError, ImportError) as e:
            msg = e.args[0] if isinstance(e, KeyError) and e.args else e
            print(f"face-retarget {args.command}: error: {msg}", file=sys.stderr)
            return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
