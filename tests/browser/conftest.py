"""Browser-test harness: a Panel server in a subprocess and headless Debian Chromium.

* ``panel_server(script, *args)``: starts ``panel serve <script> --liveness --plugins
  dashboard.assets`` on a free loopback port, waits on ``/liveness``, returns the base URL;
  every server started is terminated at teardown. ``demo_url`` is that for the viewer demo.
* ``browser``: Playwright Chromium from ``/usr/bin/chromium`` with software WebGL (SwiftShader).
* ``page`` (or ``new_page()`` for longer-lived pages): a fresh page that records every request URL (``page.requests``) and every
  websocket frame (``page.ws_frames``: dicts with ``t``, ``dir`` in/out, ``size``, ``text``).
* ``served(log, *args)``: the real ``face-retarget serve`` in a subprocess (a context manager
  yielding its base URL), for tests of what a user starts.
* ``artifacts``: ``tests/artifacts/`` (gitignored) for screenshots and server logs.

Install the browser with ``apt-get install -y chromium``; a missing browser is a failure
with that instruction, not a skip.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from contextlib import contextmanager
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
ARTIFACTS = ROOT / "tests" / "artifacts"
CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
    "--disable-background-networking", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
]
LOCAL_HOSTS = {"127.0.0.1", "localhost", "[::1]", "::1"}


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_http(url: str, timeout: float, proc: subprocess.Popen | None = None, log: Path | None = None) -> None:
    """Poll ``url`` until it answers 200; raise with the server log when it does not."""
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        if proc is not None and proc.poll() is not None:
            raise RuntimeError(f"server exited with {proc.returncode} before {url} answered:\n"
                               + (log.read_text()[-3000:] if log and log.exists() else ""))
        try:
            with urllib.request.urlopen(url, timeout=2) as r:
                if r.status == 200:
                    return
        except Exception as e:  # noqa: BLE001 - refused / not ready yet
            last = e
        time.sleep(0.2)
    raise TimeoutError(f"{url} did not answer within {timeout} s (last error: {last})")


@contextmanager
def served(log: Path, *args: str, timeout: float = 90.0):
    """The real ``face-retarget serve <args>`` on a free loopback port, its output in ``log``:
    yields the base URL once ``/liveness`` answers; its process group is stopped on exit
    (SIGTERM, then SIGKILL after 30 s)."""
    port = free_port()
    fh = open(log, "w")
    proc = subprocess.Popen([sys.executable, "-m", "core.cli", "serve", "--address", "127.0.0.1", "--port", str(port),
                             *args],
                            cwd=ROOT, env=dict(os.environ, PYTHONUNBUFFERED="1"), stdout=fh, stderr=subprocess.STDOUT,
                            start_new_session=True)
    try:
        wait_http(f"http://127.0.0.1:{port}/liveness", timeout, proc, log)
        yield f"http://127.0.0.1:{port}"
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(30)
        fh.close()


@pytest.fixture(scope="session")
def artifacts() -> Path:
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    return ARTIFACTS


@pytest.fixture(scope="session")
def panel_server(artifacts):
    """Factory: ``panel_server("scripts/x.py", "--extra", ...)`` -> ``http://127.0.0.1:<port>``."""
    procs = []

    def start(script: str, *args: str, timeout: float = 90.0) -> str:
        port = free_port()
        log = artifacts / f"server_{Path(script).stem}.log"
        cmd = [
            sys.executable, "-m", "panel", "serve", str(ROOT / script),
            "--address", "127.0.0.1", "--port", str(port),
            "--allow-websocket-origin", f"127.0.0.1:{port}",
            "--liveness", "--plugins", "dashboard.assets", *args,
        ]
        env = dict(os.environ, BOKEH_LOG_LEVEL="info", PYTHONUNBUFFERED="1")
        fh = open(log, "w")
        proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=fh, stderr=subprocess.STDOUT)
        procs.append((proc, fh))
        wait_http(f"http://127.0.0.1:{port}/liveness", timeout, proc, log)
        return f"http://127.0.0.1:{port}"

    yield start
    for proc, fh in procs:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)
        fh.close()


@pytest.fixture(scope="session")
def demo_url(panel_server) -> str:
    """Base URL of a server running scripts/viewer_demo.py (the app is at ``/viewer_demo``)."""
    return panel_server("scripts/viewer_demo.py")


@pytest.fixture(scope="session")
def browser():
    if not Path(CHROMIUM).exists():
        pytest.fail(f"{CHROMIUM} not found: install it with `apt-get update && apt-get install -y chromium`")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS, headless=True)
        try:
            yield b
        finally:
            b.close()


def recording_page(browser):
    """(context, page): a fresh 1280x900 page that records request URLs (``page.requests``),
    console errors (``page.console_errors``) and websocket frames (``page.ws_frames``)."""
    ctx = browser.new_context(viewport={"width": 1280, "height": 900})
    pg = ctx.new_page()
    pg.requests = []
    pg.console_errors = []
    pg.ws_frames = []

    def on_ws(ws):
        def rec(direction):
            def cb(payload):
                text = payload if isinstance(payload, str) else None
                size = len(payload.encode()) if isinstance(payload, str) else len(payload)
                pg.ws_frames.append({"t": time.monotonic(), "dir": direction, "size": size, "text": text})
            return cb

        ws.on("framereceived", rec("in"))
        ws.on("framesent", rec("out"))

    pg.on("request", lambda req: pg.requests.append(req.url))
    pg.on("websocket", on_ws)
    pg.on("console", lambda msg: pg.console_errors.append(msg.text) if msg.type == "error" else None)
    pg.on("pageerror", lambda exc: pg.console_errors.append(str(exc)))
    return ctx, pg


@pytest.fixture(scope="session")
def new_page(browser):
    """Factory ``new_page() -> (context, page)`` for pages that outlive one test; the caller
    closes the context."""
    return lambda: recording_page(browser)


@pytest.fixture
def page(browser):
    """A fresh recording page (see :func:`recording_page`), closed after the test."""
    ctx, pg = recording_page(browser)
    try:
        yield pg
    finally:
        ctx.close()
