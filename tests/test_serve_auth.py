"""``face-retarget serve --password`` and ``--oauth-provider`` (docs/review.md): a page without a
login is sent to the login, a wrong password is refused, the right one opens the dashboard; with
OAuth the page sends the browser to the provider with our client id and redirect address.
Localhost only: nothing here talks to the provider."""

from __future__ import annotations

import os
import urllib.parse

import pytest
import requests

import review_client as rc


def _get(url, session=None, **kw):
    return (session or requests).get(url, allow_redirects=False, timeout=60, **kw)


@pytest.mark.slow
def test_password_protects_every_page(tmp_path):
    with rc.Server("--data-dir", str(tmp_path / "d"), "--password", "s3cret-review") as srv:
        r = _get(srv.base + "/")
        assert r.status_code in (302, 303) and "/login" in r.headers["Location"], (r.status_code, r.headers)
        assert _get(srv.base + "/liveness").status_code == 200  # health checks stay open
        mesh = srv.base + "/face-retarget/payload/" + "0" * 32  # the viewers' meshes ask for the same login
        r = _get(mesh)
        assert r.status_code in (302, 303) and "/login" in r.headers["Location"], (r.status_code, r.headers)
        s = requests.Session()
        bad = s.post(srv.base + "/login", data={"username": "ana", "password": "wrong"}, allow_redirects=False, timeout=30)
        assert _get(srv.base + "/", s).status_code in (302, 303), "a wrong password opened the page"
        ok = s.post(srv.base + "/login", data={"username": "ana", "password": "s3cret-review"}, allow_redirects=False,
                    timeout=30)
        assert ok.status_code in (200, 302, 303), ok.status_code
        page = _get(srv.base + "/", s)
        assert page.status_code == 200 and "face-retarget" in page.text, (page.status_code, page.text[:300])
        assert _get(mesh, s).status_code == 404  # logged in: past the login, and no such mesh
        assert bad.status_code != 500


@pytest.mark.slow
def test_oauth_sends_the_browser_to_the_provider(tmp_path, monkeypatch):
    monkeypatch.setenv("FACE_RETARGET_OAUTH_KEY", "our-client-id")
    monkeypatch.setenv("FACE_RETARGET_OAUTH_SECRET", "our-client-secret")
    with rc.Server("--data-dir", str(tmp_path / "d"), "--oauth-provider", "github",
                   "--oauth-redirect-uri", "http://127.0.0.1:5006/login") as srv:
        assert os.environ["FACE_RETARGET_OAUTH_KEY"] == "our-client-id"
        r = _get(srv.base + "/")
        loc = r.headers.get("Location", "")
        if r.status_code in (302, 303) and "/login" in loc and "github.com" not in loc:  # Panel's login step first
            r = _get(urllib.parse.urljoin(srv.base + "/", loc))
            loc = r.headers.get("Location", "")
        assert r.status_code in (302, 303), (r.status_code, r.text[:300])
        u = urllib.parse.urlparse(loc)
        q = urllib.parse.parse_qs(u.query)
        assert u.netloc == "github.com" and u.path.endswith("/login/oauth/authorize"), loc
        assert q["client_id"] == ["our-client-id"] and q["redirect_uri"] == ["http://127.0.0.1:5006/login"], q
        assert "our-client-secret" not in loc
