"""``face-retarget serve``: the dashboard on a Panel/Bokeh server, three.js from our own route."""

from __future__ import annotations

import logging
import os


def serve(port: int = 5006, address: str = "localhost", show: bool = False, allow_websocket_origin=None) -> int:
    """Serve the dashboard until interrupted. No browser opens unless ``show``."""
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    from dashboard import assets
    from dashboard.app import create_app

    assets.three_dir()  # fail early with the `npm ci` hint when three.js is missing
    origins = [f"{address}:{port}", f"localhost:{port}", f"127.0.0.1:{port}"] + list(allow_websocket_origin or [])
    print(f"face-retarget dashboard: http://{address}:{port}/  (Ctrl-C to stop)", flush=True)
    assets.serve({"/": create_app}, port=port, address=address, show=show, title="face-retarget",
                 websocket_origin=origins, liveness=True, threaded=True)
    return 0
