"""core.progress: the CLI's progress line (StderrBar) and the warnings shown while it is drawn; one
time-left estimate for a whole run (TimeLeft)."""

import io
import sys
import warnings

from core.pipeline import Pipeline, StageCache
from core.progress import StderrBar, TimeLeft
from dense_case import tiger_files


def terminal(text: str) -> list:
    """The lines a terminal shows for ``text``: a carriage return goes back to column 0 and the
    next characters overwrite (not erase) the ones there."""
    lines, row, col = [], [], 0
    for ch in text:
        if ch == "\n":
            lines.append("".join(row).rstrip())
            row, col = [], 0
        elif ch == "\r":
            col = 0
        else:
            if col < len(row):
                row[col] = ch
            else:
                row.append(ch)
            col += 1
    if row:
        lines.append("".join(row).rstrip())
    return lines


def test_a_warning_while_the_bar_is_drawn_gets_a_line_of_its_own(monkeypatch):
    """Issue 33 item 8: a warning shown mid-run was written after the bar on the bar's line
    ("solve [###...]  50% ... warning: ..."); now the bar's line is cleared first, the warning
    has its own line and the bar is drawn again under it."""
    buf = io.StringIO()
    monkeypatch.setattr(sys, "stderr", buf)
    monkeypatch.setattr(warnings, "formatwarning", lambda msg, cat, *a, **k: f"warning: {msg}\n")  # the CLI's
    bar = StderrBar("solve", min_interval=0)
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        # Python's default (to stderr) in place of pytest's recorder
        warnings.showwarning = lambda m, c, f, n, file=None, line=None: sys.stderr.write(warnings.formatwarning(m, c, f, n))
        bar(0.5, "half way")
        warnings.warn("3 target shapes move no marker")
        bar(1.0, "done")
    shown = terminal(buf.getvalue())
    assert "warning: 3 target shapes move no marker" in shown, shown
    assert shown[-1].startswith("solve [") and "100%" in shown[-1] and "done" in shown[-1], shown
    assert all("warning" not in line for line in shown if line.startswith("solve [")), shown


def test_the_bar_alone_is_written_as_before():
    buf = io.StringIO()
    bar = StderrBar("x", stream=buf, width=4, min_interval=0)
    bar(0.5, "m")
    bar(1.0, "")
    assert buf.getvalue().startswith("\rx [##..]  50%") and buf.getvalue().endswith("\n")
    assert terminal(buf.getvalue())[-1].startswith("x [####] 100%")


def test_time_left_is_for_the_whole_run():
    """elapsed × (1 − f) / f, from 5 % on; the last call (done) says none."""
    now = [0.0]
    heard = []
    tl = TimeLeft(lambda f, m: heard.append(m), clock=lambda: now[0])
    tl(0.01, "register")
    now[0] = 10.0
    tl(0.25, "register: ICP")
    now[0] = 40.0
    tl(1.0, "done")
    assert heard == ["register", "register: ICP — about 30 s left in all", "done"]


def test_a_dense_run_says_one_time_left_for_all_its_stages(tmp_path):
    """Issue 33 item 8: the dense transfer's time left was the registration's own (the non-rigid
    ICP's iterations left), not the run's, and the stages after it said none."""
    pipe = Pipeline(cache=StageCache(disk=False), method="transfer", transfer_max_bases=4, **tiger_files(tmp_path))
    heard = []
    pipe.results(["transfer"], progress=lambda f, m: heard.append((f, m)))
    fr = [f for f, _ in heard]
    assert fr == sorted(fr) and fr[-1] == 1.0
    said = [m for f, m in heard if 0.05 <= f < 1.0]
    stages = {m.split(":")[0].rstrip("…") for m in said}
    assert {"decompose", "details"} <= stages, stages
    assert all(m.count("left") == 1 and m.endswith("s left in all") for m in said), said
