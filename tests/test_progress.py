"""core.progress.StderrBar: the CLI's progress line and the warnings shown while it is drawn."""

import io
import sys
import warnings

from core.progress import StderrBar


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
