"""``face-retarget``: the command line.

    face-retarget retarget --source take.csv --source-rig ict.glb --target-rig other.glb --out r.glb
    face-retarget layout --from data/layouts/ict_facekit.json --rig new.glb --out new.json
    face-retarget serve [--port N] [--address A] [--show]
    face-retarget info FILE...
    face-retarget bench

Solver flags (``--alpha``, ``--regions``, ``--mu`` ...) are generated from the pipeline's
settings objects, the same ones that generate the dashboard's widgets.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# The solvers factor many small matrices; BLAS threads only add contention on small
# machines (measured 10-50x slowdowns on 2 loaded cores). Users can still override.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


# options of --method transfer only (not pipeline settings)
TRANSFER_ONLY = ("transfer_details", "detail_tolerance", "transfer_iterations", "transfer_eps", "transfer_max_bases",
                 "transfer_alpha", "transfer_feature_lines")


def _transfer(args) -> int:
    """``--method transfer``: dense transfer (Xu 2014) to a rig of new morph targets."""
    from .io.curves_csv import write_curves_csv
    from .io.gltf import write_rig
    from .io.performance import read_performance
    from .io.rigs import load_rig, read_layout_for
    from .progress import StderrBar
    from .transfer.performance import transfer_performance

    if not getattr(args, "source", None) or not getattr(args, "target_rig", None):
        raise ValueError("transfer needs --source and --target-rig")
    t0 = time.perf_counter()
    source = read_performance(args.source)
    source_rig = load_rig(args.source_rig) if getattr(args, "source_rig", "") else None
    if source_rig is None:
        raise ValueError("transfer needs the source rig (--source-rig): its topology carries the dense sequence")
    target = load_rig(args.target_rig)
    src_layout = read_layout_for(getattr(args, "source_layout", ""), args.source_rig, source_rig)
    tgt_layout = read_layout_for(getattr(args, "target_layout", ""), args.target_rig, target)
    first = getattr(args, "first_frame", 0)
    last = getattr(args, "last_frame", -1)
    source = source.frames(first, None if last < 0 else last + 1)
    settings = dict(iterations=args.transfer_iterations, eps=args.transfer_eps, max_bases=args.transfer_max_bases,
                    alpha=args.transfer_alpha)
    if not args.transfer_feature_lines:
        settings["feature_lines"] = None
    res = transfer_performance(source, source_rig, src_layout, target, tgt_layout,
                               progress=None if args.quiet else StderrBar("transfer"), **settings)
    rig = res.to_rig(name=f"{target.name}_transfer")
    weights = res.weights
    detail_note = ""
    if getattr(args, "transfer_details", "morphs") == "morphs" and res.details is not None:
        # the per-frame details as extra morph targets: a GLB then plays the whole transfer
        import numpy as np

        from .model import Rig
        from .transfer.details import detail_morph_targets

        C, B, err = detail_morph_targets(res.details, rtol=getattr(args, "detail_tolerance", 0.05))
        rig = Rig(rig.neutral, rig.faces, np.concatenate([rig.deltas, B]),
                  list(rig.names) + [f"xu_detail_{j:02d}" for j in range(len(B))], None, "m", rig.name)
        weights = np.hstack([weights, C])
        detail_note = f"; details as {len(B)} morph targets (largest error {err * 1000:.3f} mm)"
    times = source.times - source.times[0]
    if args.out:
        write_rig(args.out, rig, weights=weights, times=times)
    if args.weights_csv:
        write_curves_csv(args.weights_csv, times, weights, rig.names)
    stages = " ".join(f"{k}={v:.1f}s" for k, v in res.timings.items() if isinstance(v, (int, float)))
    print(f"transferred {len(res.weights)} frames to {target.name}: {res.n_bases} bases on {rig.n_vertices} vertices "
          f"(source topology fitted to the target){detail_note} in {time.perf_counter() - t0:.1f}s; stages: {stages}"
          + (f"\nwrote {args.out}" if args.out else "") + (f"\nwrote {args.weights_csv}" if args.weights_csv else ""))
    return 0


def _retarget(args) -> int:
    import numpy as np

    if getattr(args, "method", None) == "transfer":
        return _transfer(args)

    from .io.curves_csv import write_curves_csv
    from .io.gltf import write_rig
    from .pipeline import Pipeline
    from .progress import StderrBar

    settings = {k: v for k, v in vars(args).items()
                if k not in ("func", "out", "weights_csv", "quiet", "command") + TRANSFER_ONLY}
    pipe = Pipeline(**settings)
    bar = None if args.quiet else StderrBar("retarget")
    t0 = time.perf_counter()
    res = pipe.results(["load", "stabilize", "synthesize", "evaluate"], progress=bar)
    ld, st, ev = res["load"], res["stabilize"]["source"], res["evaluate"]
    W = res["synthesize"]["weights"]
    rig = ld["target_rig"]
    out = []
    if args.out:
        write_rig(args.out, rig, weights=np.nan_to_num(W), times=st.times - st.times[0])
        out.append(f"wrote {args.out}")
    if args.weights_csv:
        write_curves_csv(args.weights_csv, st.times - st.times[0], W, rig.names)
        out.append(f"wrote {args.weights_csv}")
        U = pipe.results(["solve"])["solve"]["info"].get("region_weights")
        if U is not None:  # Liu 2011 §6.4: the regional curves an animator edits
            from .solvers.local import region_curves

            curves = region_curves(U, rig.names)
            path = Path(args.weights_csv).with_name(Path(args.weights_csv).stem + "_regions.csv")
            write_curves_csv(path, st.times - st.times[0], np.column_stack(list(curves.values())), list(curves))
            out.append(f"wrote {path} (per-region curves <shape>@r<k>; {args.weights_csv} holds their mask-area blend)")
    timings = " ".join(f"{k}={v * 1e3:.0f}ms" for k, v in pipe.timings.items() if v)
    print(
        f"retargeted {len(W)} frames at {st.fps:g} fps, {len(st.names)} markers -> {rig.name} ({rig.n_shapes} shapes) "
        f"with {pipe.solve.method} in {time.perf_counter() - t0:.1f}s\n"
        f"marker error: median {np.nanmedian(ev['marker_error_mm']):.2f} mm, max {np.nanmax(ev['marker_error_mm']):.2f} mm; "
        f"weights in [{np.nanmin(W):.3f}, {np.nanmax(W):.3f}]\n"
        f"stage timings: {timings}\n" + "\n".join(out)
    )
    return 0


def _layout(args) -> int:
    from .registration import layout_command

    print(layout_command(args.from_, args.rig, args.out, source_rig_path=args.source_rig))
    return 0


def _serve(args) -> int:
    from dashboard.serve import serve

    return serve(port=args.port, address=args.address, show=args.show, allow_websocket_origin=args.allow_websocket_origin)


def _info(args) -> int:
    from .io.performance import read_performance
    from .io.rigs import load_rig

    for f in args.files:
        p = Path(f)
        if p.is_dir() or p.suffix.lower() in (".glb", ".gltf"):
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
    """Write the automatic name map (same canonical ARKit names) for a user to edit."""
    from .io.performance import read_performance
    from .io.rigs import load_rig
    from .names import NameMap

    src = Path(args.source)
    source_names = load_rig(src).names if src.is_dir() or src.suffix.lower() in (".glb", ".gltf") else read_performance(src).names
    target = load_rig(args.target_rig)
    nm = NameMap.automatic(source_names, target.names)
    missing = nm.unmapped(target.names)
    # unmapped shapes are written with an empty list: the keys a user fills in
    NameMap({t: nm.entries.get(t, []) for t in target.names}).to_json(args.out)
    print(f"wrote {args.out}: {len(nm.entries)} of {target.n_shapes} shapes of {target.name} mapped by ARKit name"
          + (f"; unmapped (edit the file to drive them): {', '.join(missing[:12])}{' ...' if len(missing) > 12 else ''}" if missing else ""))
    return 0


def _bench(args) -> int:
    import runpy

    script = ROOT / "benchmarks" / "run.py"
    if not script.exists():
        print("benchmarks/ is not installed with the package; run from a source checkout", file=sys.stderr)
        return 2
    sys.argv = [str(script)] + (args.only or [])
    runpy.run_path(str(script), run_name="__main__")
    return 0


def build_parser() -> argparse.ArgumentParser:
    from .pipeline import add_cli_arguments

    p = argparse.ArgumentParser(prog="face-retarget", description="Facial performance retargeting onto blendshape rigs.")
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("retarget", help="retarget a performance onto a rig and write GLB/CSV")
    add_cli_arguments(r, extra_methods=("transfer",))
    r.add_argument("--out", help="output GLB: the target rig with a morph-weight animation")
    r.add_argument("--weights-csv", help="output CSV: time_s then one column per target shape")
    r.add_argument("--quiet", action="store_true", help="no progress bar")
    r.add_argument("--transfer-details", choices=["morphs", "none"], default="morphs",
                   help="[transfer] fine-scale details in the output: 'morphs' adds them as low-rank morph targets "
                        "(xu_detail_NN, weights in the same animation), 'none' writes the large-scale bases only "
                        "(default: morphs)")
    r.add_argument("--transfer-iterations", type=int, default=40,
                   help="[transfer] Taubin smoothing iterations of the decomposition (default: 40, as in the paper)")
    r.add_argument("--transfer-eps", type=float, default=1e-3,
                   help="[transfer] basis selection stops below this relative residual energy ε (default: 0.001)")
    r.add_argument("--transfer-max-bases", type=int, default=30, help="[transfer] at most this many bases (default: 30)")
    r.add_argument("--transfer-alpha", type=float, default=100.0,
                   help="[transfer] weight α of the eye and mouth feature lines in eq. 9 (default: 100)")
    r.add_argument("--transfer-feature-lines", action=argparse.BooleanOptionalAction, default=True,
                   help="[transfer] feature lines from the rims near the source layout's eye and mouth markers "
                        "(default: on)")
    r.add_argument("--detail-tolerance", type=float, default=0.05,
                   help="[transfer] largest allowed error of the detail morph targets, relative to the largest "
                        "detail (default: 0.05)")
    r.set_defaults(func=_retarget)

    lay = sub.add_parser("layout", help="transfer a marker layout to a rig of any topology (non-rigid ICP)")
    lay.add_argument("--from", dest="from_", required=True, help="layout JSON to transfer")
    lay.add_argument("--rig", required=True, help="rig to place the markers on")
    lay.add_argument("--out", required=True, help="output layout JSON")
    lay.add_argument("--source-rig", default=None, help="rig the layout was made for (default: its 'rig' field in data/rigs)")
    lay.set_defaults(func=_layout)

    s = sub.add_parser("serve", help="serve the dashboard")
    s.add_argument("--port", type=int, default=5006)
    s.add_argument("--address", default="localhost")
    s.add_argument("--show", action="store_true", help="open a browser")
    s.add_argument("--allow-websocket-origin", action="append", default=None, help="extra allowed origins host:port")
    s.set_defaults(func=_serve)

    n = sub.add_parser("names", help="write the automatic channel->shape name map (JSON) for editing")
    n.add_argument("--source", required=True, help="performance or rig whose channel/shape names drive")
    n.add_argument("--target-rig", required=True, help="rig whose shapes are driven")
    n.add_argument("--out", required=True, help="name map JSON to write (pass it back with --name-map)")
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
