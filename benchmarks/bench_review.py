"""Shared review on a real server (``face-retarget serve``), measured with websocket pages
(tests/review_client.py: the Bokeh protocol a browser speaks, without the browser's own layout
time). The reference is today's per-tab app, ``face-retarget serve --no-review``, in the same run:

* ``review_propagation_2pages`` / ``review_propagation_20pages``: page 0 of a shot changes the
  spacetime α (8 times, 1.5 s apart); ours = p50 over the other pages of the time until their
  target viewer has the recomputed curves (the new track's URL arrived and its blob fetched, as
  the browser does; or the track itself when it travels inline) (``setting_p50_s``: until their
  α slider shows the value); ref = the same change on a per-tab page until that page's own viewer
  has the result (the round trip a user waits for today, with 1 resp. 19 more idle per-tab pages
  on the server). Every α value is new to both servers, so every change is a solve.
* ``review_page_20th``: 20 pages of a computed shot requested at once; ours = time until the 20th
  is served (HTML + websocket + its document arrived), ``first_s`` the 1st; ref = 20 per-tab
  pages at once. The server runs with ``--warm-pages 20`` (:mod:`dashboard.warm`: pages built
  ahead while it is idle; the burst starts once its log says they are ready); ``cold_s`` /
  ``cold_first_s`` = the same burst on the same server with ``--warm-pages 0`` (every page
  built when asked for, as before warm pages). The client builds the 20 documents after the last has
  arrived (a browser builds its own; here one Python process would build them all in between).
  ``mb_per_session`` = growth of the cold server's resident memory during its burst / 20 (ref
  the same for per-tab).

The SQLite write latency of an edit is ``store_edit_write`` in bench_store.py.
"""

import asyncio
import math
import os
import re
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import review_client as rc  # noqa: E402

ALPHA = re.compile(r"Seol α")
METHOD = re.compile(r"^Method$")


def _models(page):
    return (page.one("Slider", title=ALPHA),
            {m.id for m in page.doc.models if type(m).__name__.startswith("MeshViewer")})


async def _drive_alpha(base, sid, n, on_patch, on_track, mark, changes, gap, start, settle):
    """Open ``n`` pages (of shot ``sid``, or per-tab ones), then page 0 sets α ``changes`` times
    ``gap`` s apart (``mark(value)`` just before each); ``on_patch`` sees every page's patches,
    ``on_track`` every new track a page has (review_client.Page.on_track)."""
    pages, _ = await rc.open_pages(base, sid, n, on_patch=None)
    for p in pages:
        p.m = _models(p)
        p.on_patch, p.on_track = on_patch, on_track
    if sid is None:
        # a page of its own opens on auto, which sets its own α: page 0 chooses spacetime, as the shot has
        method = pages[0].one("CustomSelect", title=METHOD)  # options are [value, label] pairs
        pages[0].set(method, value="spacetime")
        await asyncio.sleep(settle)
    await asyncio.sleep(2.0)
    for k in range(changes):
        # the α slider is over log10 α (dashboard.widgets.LogSlider): α itself would be out of its range
        v = math.log10(round(start + 0.001 * k, 4))
        mark(v)
        pages[0].set(pages[0].m[0], value=v, value_throttled=v)
        await asyncio.sleep(gap)
    await asyncio.sleep(settle)
    for p in pages:
        await p.close()


async def _propagation(base, sid, n, changes=8, gap=1.5, start=0.02):
    """Ours: page 0 changes α; the other pages' times to the new α and to the new result."""
    marks: dict = {}   # value -> time sent
    seen_setting, seen_result = [], []
    waiting: dict = {}  # page index -> (value, time sent) until its viewer's track changes

    def on_patch(page, changes_, t):
        alpha, viewers = page.m
        for mid, attr, new in changes_:
            if mid == alpha.id and attr == "value" and new in marks and page.index:
                seen_setting.append(t - marks[new])
                waiting[page.index] = (new, marks[new])

    def on_track(page, mid, t):
        if mid in page.m[1] and page.index in waiting:
            seen_result.append(t - waiting.pop(page.index)[1])

    await _drive_alpha(base, sid, n, on_patch, on_track, lambda v: marks.__setitem__(v, time.monotonic()), changes, gap,
                       start, 5.0)
    return seen_setting, seen_result


async def _own_round_trip(base, n, changes=8, gap=1.5, start=0.02):
    """Ref: a per-tab page changes α; the time until its own viewer shows the result."""
    rt, pending = [], {}

    def on_track(page, mid, t):
        if page.index == 0 and mid in page.m[1] and "t" in pending:
            rt.append(t - pending.pop("t"))

    await _drive_alpha(base, None, n, None, on_track, lambda v: pending.__setitem__("t", time.monotonic()), changes, gap,
                       start, 3.0)
    return rt


async def _open_many(base, sid, n, server=None):
    """Open ``n`` pages at once: (completion times, the server's RSS in MB while they are open)."""
    pages, served = await rc.open_pages(base, sid, n, defer=True)
    await asyncio.sleep(1.0)
    rss = server.rss_mb() if server is not None else float("nan")
    for p in pages:
        await p.close()
    return served, rss


def main():
    rc.register_models()
    tmp = Path(tempfile.mkdtemp(prefix="bench-review-"))
    # spacetime: auto (the default) chooses its own α, so an α change would solve nothing
    sid = rc.sample_shot(tmp / "data", "bench", last_frame=-1, method="spacetime")
    with rc.Server("--data-dir", str(tmp / "data"), "--warm-pages", str(WARM), log=tmp / "ours.log") as ours, \
            rc.Server("--no-review", log=tmp / "ref.log") as ref:
        # warm both (the shot computed once, the per-tab sample once)
        rc.run(_open_many(ours.base, sid, 1))
        rc.run(_open_many(ref.base, None, 1))
        _wait_for_warm(tmp / "ours.log", WARM)  # ours builds its warm pages once, before anything is measured
        # each case its own α values: every change is a new solve (the 20-page case re-used the
        # 2-page case's values until stop 26, so it measured cache hits)
        for n, case, start in ((2, "review_propagation_2pages", 0.02), (20, "review_propagation_20pages", 0.03)):
            setting, result = rc.run(_propagation(ours.base, sid, n, start=start))
            own = rc.run(_own_round_trip(ref.base, n, start=start))
            o, r = statistics.median(result), statistics.median(own)
            print(f"BENCH {case} ours_s={o:.3f} ref_s={r:.3f} ratio={r / o:.2f} "
                  f"p95_s={rc.pctl(result, 0.95):.3f} setting_p50_s={statistics.median(setting):.3f} "
                  f"setting_p95_s={rc.pctl(setting, 0.95):.3f} ref_p95_s={rc.pctl(own, 0.95):.3f} receipts={len(result)}",
                  flush=True)
        # 20 pages at once (fresh connections; the previous pages are closed), once the warm pages
        # are ready (ours builds them while idle); the per-tab reference first, while ours is idle
        ready = _wait_for_warm(tmp / "ours.log", WARM)
        time.sleep(3.0)
        r0 = ref.rss_mb()
        ref_served, r1 = rc.run(_open_many(ref.base, None, 20, ref))
        served, _ = rc.run(_open_many(ours.base, sid, 20, ours))
    # the same server without warm pages (a copy of its store: one writer per store): every page
    # built when asked for
    shutil.copytree(tmp / "data", tmp / "cold")
    with rc.Server("--data-dir", str(tmp / "cold"), "--warm-pages", "0", log=tmp / "cold.log") as cold_srv:
        rc.run(_open_many(cold_srv.base, sid, 1))
        time.sleep(2.0)
        m0 = cold_srv.rss_mb()
        cold, m1 = rc.run(_open_many(cold_srv.base, sid, 20, cold_srv))
        print(f"BENCH review_page_20th ours_s={served[-1]:.3f} ref_s={ref_served[-1]:.3f} "
              f"ratio={ref_served[-1] / served[-1]:.2f} first_s={served[0]:.3f} ref_first_s={ref_served[0]:.3f} "
              f"cold_s={cold[-1]:.3f} cold_first_s={cold[0]:.3f} warm_ready_s={ready:.0f} "
              f"mb_per_session={(m1 - m0) / 20:.1f} ref_mb_per_session={(r1 - r0) / 20:.1f}", flush=True)


#: warm pages of the benchmark's server (``face-retarget serve --warm-pages``)
WARM = 20


def _wait_for_warm(log, n, timeout=300.0):
    """Seconds until the server's log says ``n`` warm pages are ready, current and their documents
    made (it does all three while idle): its last line about warm pages is the one saying so (none
    handed out since)."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        said = [ln for ln in Path(log).read_text(errors="replace").splitlines() if "warm page" in ln]
        if said and f"{n} warm pages current, their documents made" in said[-1]:
            return time.monotonic() - t0
        time.sleep(0.5)
    raise RuntimeError(f"the server did not get {n} warm pages ready within {timeout:.0f} s ({log})")


if __name__ == "__main__":
    main()
