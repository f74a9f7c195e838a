"""Twenty participants of one shared shot on one server for 60 s (websocket clients speaking
Bokeh's protocol, tests/review_client.py): page 0 presents and scrubs, everyone scrubs now and
then, changes the spacetime α or β (so changes of one setting race and changes of two rebase)
and adds notes. Nothing may be lost: every setting a page sent is in the shot's history or was
refused on that page with a message, every note is stored, every page ends up showing the shot's
values, and the server logs no error. The p50/p95 of the server's response to a scrub and of
cross-page propagation are printed and written to tests/artifacts/review_load.json.

Localhost only, one server process, bounded: 20 pages x 60 s (about two minutes in all).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

import review_client as rc

ART = Path(__file__).resolve().parent / "artifacts"
PAGES, SECONDS = 20, 60.0


@pytest.fixture(scope="module")
def shot_on_server(tmp_path_factory):
    data = tmp_path_factory.mktemp("review-load")
    sid = rc.sample_shot(data, "load")
    ART.mkdir(exist_ok=True)
    log = ART / "server_review_load.log"
    with rc.Server("--data-dir", str(data), log=log) as srv:
        yield srv, sid, data, log


@pytest.mark.slow
def test_twenty_pages_for_a_minute_lose_nothing(shot_on_server):
    from core.store import Store

    rc.register_models()
    srv, sid, data, log = shot_on_server

    async def warm():  # the shot computed once (the 20 pages are of a computed shot)
        pages, _ = await rc.open_pages(srv.base, sid, 1)
        await pages[0].close()

    rc.run(warm())
    rss0 = srv.rss_mb()
    r = rc.run(rc.review_load(srv.base, sid, PAGES, SECONDS, seed=1))
    rss1 = srv.rss_mb()
    assert srv.alive(), "the server died under load"

    store = Store(data)
    hist = store.settings_history(sid)
    notes = {n["text"] for n in store.notes(sid)}
    store.close()
    accepted = {(h["setting"], h["new"]) for h in hist}
    final = {k: [h["new"] for h in hist if h["setting"] == k] for k in ("alpha", "beta")}

    stats = {k: {"n": len(r[k]), "p50_s": round(rc.pctl(r[k], 0.5), 3), "p95_s": round(rc.pctl(r[k], 0.95), 3),
                 "max_s": round(max(r[k]), 3) if r[k] else None} for k in ("response", "setting", "seek")}
    sent = sum(len(x["alpha"]) + len(x["beta"]) for x in r["sent"])
    out = dict(pages=PAGES, seconds=SECONDS, served_first_s=round(r["served"][0], 2), served_last_s=round(r["served"][-1], 2),
               rss_before_mb=round(rss0, 1), rss_after_mb=round(rss1, 1), settings_sent=sent,
               settings_refused=sum(len(x) for x in r["refused"]), notes_sent=sum(len(x["notes"]) for x in r["sent"]), **stats)
    (ART / "review_load.json").write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps(out, indent=2))

    assert not r["errors"], r["errors"][:5]
    errors = [ln for ln in log.read_text(errors="replace").splitlines() if re.search(r"\bERROR\b", ln)]
    assert not errors, "\n".join(errors[:10])
    # every setting change: in the history, or refused on its page with a message
    for i, x in enumerate(r["sent"]):
        took = sum((k, v) in accepted for k in ("alpha", "beta") for v in x[k])
        assert took + len(r["refused"][i]) == len(x["alpha"]) + len(x["beta"]), (i, x, r["refused"][i])
    assert sent >= 10 and len(r["seek"]) > 100 and len(r["response"]) > 100, out  # the load did happen
    # every note stored
    missing = [t for x in r["sent"] for t in x["notes"] if t not in notes]
    assert not missing, missing
    # every page shows the shot's values at the end
    for i, f in enumerate(r["final"]):
        for k in ("alpha", "beta"):
            if final[k]:
                assert f[k] == final[k][-1], json.dumps([i, k, f[k], final[k][-1], r["trail"][i], [(h["version"], h["author"], h["setting"], h["new"], h["at"]) for h in hist[-6:]]])
