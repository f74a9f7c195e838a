"""Locate three.js (installed from npm) and serve it from our own Panel server, never a CDN.

three.js comes from the npm registry: ``npm ci`` at the repository root installs the exact
version pinned in ``package.json`` / ``package-lock.json`` into ``node_modules/three``. The
browser loads ``three.module.js`` (which imports ``./three.core.js`` next to it) through the
import map of :class:`dashboard.viewer.MeshViewer`, from the route :data:`THREE_ROUTE` that
this module adds to the server.

Three ways to get the route onto a server:

* ``python scripts/viewer_demo.py`` / :func:`serve`: wraps ``pn.serve`` with the route (and
  the route of the viewers' meshes, :mod:`dashboard.payloads`, which only this way is used);
* ``panel serve app.py --plugins dashboard.assets``: Panel's plugin hook imports this module
  and adds :data:`ROUTES`;
* anything else that builds a tornado app: add :func:`routes` (or :func:`static_dirs` for
  ``pn.serve(..., static_dirs=...)`` / ``panel serve --static-dirs``).

Lookup order for the three.js package directory (the folder holding ``package.json`` and
``build/three.module.js``):

1. the environment variable ``FACE_RETARGET_THREE_DIR`` (either that package directory or
   its ``build/`` folder);
2. ``node_modules/three`` at the repository root (the parent of ``dashboard/``);
3. ``node_modules/three`` under the current working directory.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

#: URL prefix (relative to the server root) under which three.js's ``build/`` is served
THREE_ROUTE = "face-retarget/three"

#: the environment variable that overrides where three.js is looked for
ENV_VAR = "FACE_RETARGET_THREE_DIR"

REPO_ROOT = Path(__file__).resolve().parents[1]

#: files the viewer needs from ``build/``: the module imports ./three.core.js
REQUIRED = ("three.module.js", "three.core.js")


class ThreeNotFound(FileNotFoundError):
    """three.js is not installed where we look; the message says how to install it."""


def _candidates() -> list[tuple[str, Path]]:
    out = []
    env = os.environ.get(ENV_VAR)
    if env:
        out.append((f"${ENV_VAR}", Path(env).expanduser()))
    out.append(("repository", REPO_ROOT / "node_modules" / "three"))
    cwd = Path.cwd() / "node_modules" / "three"
    if cwd.resolve() != (REPO_ROOT / "node_modules" / "three").resolve():
        out.append(("working directory", cwd))
    return out


def three_dir() -> Path:
    """The three.js package directory (holding ``build/three.module.js``).

    Returns
    -------
    pathlib.Path
        Absolute path of the npm package ``three``.

    Raises
    ------
    ThreeNotFound
        (a FileNotFoundError) naming every place looked at and the fix (``npm ci``).
        When ``FACE_RETARGET_THREE_DIR`` is set but wrong it is an error on its own: a
        misspelt override must not silently fall back to another copy.
    """
    looked = []
    for label, path in _candidates():
        pkg = path.parent if path.name == "build" else path
        build = pkg / "build"
        missing = [f for f in REQUIRED if not (build / f).is_file()]
        if not missing:
            return pkg.resolve()
        looked.append(f"{label}: {build} (missing {', '.join(missing)})")
        if label.startswith("$"):
            raise ThreeNotFound(
                f"{ENV_VAR}={os.environ[ENV_VAR]!r} does not point at the npm package 'three': "
                f"looked for {build}/{{{','.join(REQUIRED)}}}. Point it at node_modules/three "
                f"(or its build/ folder), or unset it and run `npm ci` in {REPO_ROOT}."
            )
    raise ThreeNotFound(
        "three.js is not installed; the 3D viewer serves it locally from node_modules. "
        f"Run `npm ci` in {REPO_ROOT} (installs the version pinned in package.json), or set "
        f"{ENV_VAR} to a node_modules/three directory. Looked in: " + "; ".join(looked)
    )


def three_build_dir() -> Path:
    """``three_dir() / "build"``; raises :class:`ThreeNotFound` like :func:`three_dir`."""
    return three_dir() / "build"


def three_version() -> str:
    """The installed three.js version from its ``package.json`` (e.g. ``"0.187.0"``)."""
    pkg = three_dir() / "package.json"
    try:
        return str(json.loads(pkg.read_text())["version"])
    except (OSError, ValueError, KeyError) as e:
        raise ThreeNotFound(f"{pkg}: cannot read field 'version' ({e}); reinstall with `npm ci`") from None


def three_url(prefix: str = ".") -> str:
    """URL of ``three.module.js`` as the browser should import it.

    ``prefix`` is the path from the page to the server root: ``"."`` for an app served at
    ``/name`` (Panel's default), or Panel's ``state.rel_path`` for nested/prefixed apps.
    """
    return f"{prefix.rstrip('/') or '.'}/{THREE_ROUTE}/three.module.js"


def static_dirs() -> dict:
    """``{THREE_ROUTE: build dir}`` for ``pn.serve(static_dirs=...)`` / ``--static-dirs``.

    Raises :class:`ThreeNotFound` when three.js is missing.
    """
    return {THREE_ROUTE: str(three_build_dir())}


def _handler():
    from tornado.web import HTTPError, StaticFileHandler

    class ThreeHandler(StaticFileHandler):
        """Serves three.js's build folder, resolved per request so a missing install gives
        a readable 500 naming the fix instead of a server that will not start."""

        def initialize(self, path=None, default_filename=None):
            try:
                root = str(three_build_dir())
            except ThreeNotFound as e:
                self._missing = str(e)
                root = str(REPO_ROOT)
            else:
                self._missing = None
            super().initialize(path=root, default_filename=default_filename)

        async def get(self, path, include_body=True):
            if self._missing:
                raise HTTPError(500, reason=self._missing.replace("\n", " ")[:400])
            # only three.js's own files; no directory listings
            if not path.endswith((".js", ".js.map")):
                raise HTTPError(403, reason="only three.js build files are served here")
            return await super().get(path, include_body)

    return ThreeHandler


def routes() -> list:
    """Tornado routes serving three.js under ``/`` + :data:`THREE_ROUTE`, and the viewers' meshes
    (:mod:`dashboard.payloads`)."""
    from . import payloads

    return [(rf"/{THREE_ROUTE}/(.*)", _handler(), {})] + payloads.routes()


#: Panel's plugin hook: ``panel serve app.py --plugins dashboard.assets`` adds these routes
ROUTES = routes()


def serve(panels, port: int = 0, address: str = "localhost", show: bool = False, **kwargs):
    """``pn.serve`` with the three.js route added (checked up front: raises
    :class:`ThreeNotFound` before starting a server that could not show a 3D view).

    Extra keyword arguments go to ``pn.serve`` (``threaded``, ``liveness``, ``title`` ...).
    """
    import panel as pn

    from . import payloads

    three_dir()
    extra = list(kwargs.pop("extra_patterns", [])) + routes()
    payloads.enable()  # viewers made from now on send their mesh by URL, not inside the document
    return pn.serve(panels, port=port, address=address, show=show, extra_patterns=extra, **kwargs)
