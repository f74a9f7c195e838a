"""Two rigs driven by one Live Link Face take, side by side, on one frame slider.

Run either way (three.js is served by our server from node_modules; run `npm ci` first):

    python scripts/viewer_demo.py --port 5006
    panel serve scripts/viewer_demo.py --plugins dashboard.assets

Left: the ICT FaceKit head (14,629 vertices, 53 shapes); right: the Rocketbox head (its 175
shapes cut to the 52 the ARKit curves drive). Both play the same curves, mapped by canonical
ARKit name (core.names.NameMap.automatic), in the browser at the capture rate.

URL query parameters (used by the browser tests, handy for measuring):
    ?sync_interval=0   do not write the frame back to Python while playing
    ?drive=python      the slider sends K weights per frame from Python instead of a frame index
    ?markers=0         no markers
    ?blend=gpu|cpu     force three.js morph targets / JS blending (default: auto)
    ?shading=standard|fast  force per-pixel PBR / per-vertex lighting (default: auto)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import panel as pn

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from core.io.gltf import read_rig  # noqa: E402
from core.names import NameMap  # noqa: E402
from dashboard.viewer import MeshViewer  # noqa: E402

RIGS = ROOT / "data" / "rigs"
TAKE = ROOT / "data" / "performances" / "livelinkface_take_s07.csv"
LAYOUTS = ROOT / "data" / "layouts"
FPS = 30.0  # Live Link Face samples at 30 Hz (data/SOURCES.md)


def read_livelink_curves(path: Path) -> tuple[list[str], np.ndarray]:
    """(channel names, (T, 52) weights) from a Live Link Face CSV: columns 2..53 are ARKit."""
    with open(path) as f:
        header = f.readline().strip().split(",")
    channels = header[2:54]
    weights = np.loadtxt(path, delimiter=",", skiprows=1, usecols=range(2, 54), dtype=np.float64, ndmin=2)
    if weights.shape[1] != len(channels):
        raise ValueError(f"{path}: expected {len(channels)} weight columns, got {weights.shape[1]}")
    return channels, weights


def drive(rig, channels, weights):
    """The rig cut to the shapes the curves drive, and its (T, K) track: W @ G.T."""
    G = NameMap.automatic(channels, rig.names).matrix(channels, rig.names)
    driven = np.flatnonzero(np.abs(G).sum(axis=1) > 0)
    sub = rig.subset([rig.names[i] for i in driven])
    return sub, weights @ G[driven].T


def layout_for(rig):
    """The bundled marker layout of ``rig`` (data/layouts/<rig>.json), or None when absent."""
    path = LAYOUTS / f"{rig.name}.json"
    if not path.exists():
        return None
    try:
        from core.io.layout import read_layout
    except ImportError:
        return None
    return read_layout(path, rig)


def query(name, default):
    args = pn.state.session_args if pn.state.curdoc and pn.state.curdoc.session_context else {}
    vals = args.get(name) if args else None
    return vals[0].decode() if vals else default


_CACHE = {}


def load():
    """Rigs, tracks and layouts, read once per server process (read-only afterwards)."""
    if not _CACHE:
        channels, weights = read_livelink_curves(TAKE)
        for key, fname in (("source", "ict_facekit.glb"), ("target", "rocketbox_female_adult_02.glb")):
            rig = read_rig(RIGS / fname)
            sub, track = drive(rig, channels, weights)
            _CACHE[key] = (sub, np.clip(track, 0.0, 1.0), layout_for(rig))
    return _CACHE


def app():
    data = load()
    sync_interval = float(query("sync_interval", "0.5"))
    drive_mode = query("drive", "browser")
    markers = query("markers", "1") != "0"
    modes = {k: query(k, "auto") for k in ("blend", "shading")}
    group = "" if drive_mode == "python" else "demo"
    viewers = {}
    for key, title in (("source", "ICT FaceKit"), ("target", "Rocketbox Female_Adult_02")):
        rig, track, layout = data[key]
        viewers[key] = MeshViewer.from_rig(
            rig, track, fps=FPS, layout=layout if markers else None, label=f"{title} ({key})",
            sync_group=group, sync_interval=sync_interval, height=560, sizing_mode="stretch_width",
            min_width=300, **modes,
        )
    src, tgt = viewers["source"], viewers["target"]
    T = src.n_frames
    slider = pn.widgets.IntSlider(name="Frame", start=0, end=T - 1, value=0, sizing_mode="stretch_width")
    play = pn.widgets.Toggle(name="▶ Play / ❚❚ Pause", button_type="primary", width=160)
    if drive_mode == "python":
        # Python scrubbing: K weights per frame per viewer, no track playback in the browser
        play.disabled = True

        def scrub(event):
            for key, v in viewers.items():
                v.set_weights(data[key][1][event.new])

        slider.param.watch(scrub, "value")
        scrub(type("E", (), {"new": slider.value})())
    else:
        # one slider and one play button drive the source viewer; the target follows it in the
        # browser through the shared clock of sync_group "demo"
        slider.link(src, value="frame", bidirectional=True)
        play.link(src, value="playing", bidirectional=True)
    info = pn.pane.Markdown(
        f"**{TAKE.name}**: {T} frames at {FPS:g} fps, {len(load()['source'][0].names)} ICT shapes / "
        f"{len(load()['target'][0].names)} Rocketbox shapes driven by the 52 ARKit curves. "
        "Drag to orbit, shift/right-drag to pan, wheel to zoom, double-click to reset.",
        sizing_mode="stretch_width",
    )
    return pn.Column(
        "## face-retarget: playback viewer demo",
        info,
        pn.Row(src, tgt, sizing_mode="stretch_width"),
        pn.Row(play, slider, sizing_mode="stretch_width"),
        sizing_mode="stretch_width",
    )


pn.extension()

if __name__.startswith("bokeh"):  # `panel serve scripts/viewer_demo.py --plugins dashboard.assets`
    app().servable(title="face-retarget viewer demo")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--port", type=int, default=5006)
    parser.add_argument("--address", default="localhost")
    parser.add_argument("--show", action="store_true", help="open a browser tab")
    args = parser.parse_args(argv)
    from dashboard import assets

    load()
    assets.serve({"viewer_demo": app}, port=args.port, address=args.address, show=args.show,
                 title="face-retarget viewer demo", liveness=True, threaded=False)


if __name__ == "__main__":
    main()
