"""GET /viewer/{id}: the page (auth, no patient label, security headers) and its static assets."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from api_helpers import INGEST, auth, calibration_doc
from fastapi.testclient import TestClient


def _create(client: TestClient, key: dict[str, str] = INGEST) -> dict:
    resp = client.post("/v1/sessions", json={"calibration": calibration_doc(), "label": "Jane Doe 1970"}, headers=key)
    assert resp.status_code == 201
    return resp.json()


def test_viewer_page_with_token(client: TestClient) -> None:
    created = _create(client)
    resp = client.get(created["viewer_url"])
    assert resp.status_code == 200 and resp.headers["content-type"].startswith("text/html")
    html = resp.text
    assert "/static/vendor/openseadragon/openseadragon.min.js" in html and "/static/viewer.js" in html
    assert "Jane Doe" not in html and created["id"] not in html  # nothing about the session in the page
    assert resp.headers["Referrer-Policy"] == "no-referrer"  # the URL carries the token
    assert "default-src 'self'" in resp.headers["Content-Security-Policy"]
    assert resp.headers["Cache-Control"] == "no-store"


def test_viewer_page_auth(client: TestClient) -> None:
    mine, theirs = _create(client), _create(client, auth("ingest-key-b-0123456789abcdef"))
    assert client.get(f"/viewer/{mine['id']}").status_code == 401
    assert client.get(f"/viewer/{mine['id']}?token={theirs['viewer_token']}").status_code == 401
    assert client.get(f"/viewer/{mine['id']}?token=123.abc").status_code == 401
    assert client.get(f"/viewer/{theirs['id']}", headers=INGEST).status_code == 404
    assert client.get(f"/viewer/{mine['id']}", headers=INGEST).status_code == 200
    assert (
        client.get("/viewer/0123456789abcdef0123456789abcdef", headers=auth("admin-key-0123456789abcdef")).status_code
        == 404
    )


def test_static_assets(client: TestClient) -> None:
    js = client.get("/static/viewer.js")
    assert js.status_code == 200 and "javascript" in js.headers["content-type"]
    assert "veinmosaicViewer" in js.text and 'drawer: "canvas"' in js.text
    assert client.get("/static/viewer.css").status_code == 200
    osd = client.get("/static/vendor/openseadragon/openseadragon.min.js")
    assert osd.status_code == 200 and "OpenSeadragon" in osd.text[:5000]
    assert client.get("/static/vendor/openseadragon/images/home_rest.png").status_code == 200
    for bad in (
        "/static/../routes/viewer.py",
        "/static/%2e%2e/app.py",
        "/static/vendor/openseadragon/../../package.json",
    ):
        assert client.get(bad).status_code == 404, bad


def test_viewer_assets_dir_setting(make_client: Callable[..., TestClient], tmp_path: Path) -> None:
    """An installed package (Docker) finds OpenSeadragon where VEINMOSAIC_VIEWER_ASSETS_DIR says."""
    assets = tmp_path / "osd"
    assets.mkdir()
    (assets / "openseadragon.min.js").write_text("/* OpenSeadragon from the setting */")
    client = make_client(viewer_assets_dir=assets)
    osd = client.get("/static/vendor/openseadragon/openseadragon.min.js")
    assert osd.status_code == 200 and "from the setting" in osd.text
    sid = _create(client)["id"]
    assert client.get(f"/viewer/{sid}", headers=INGEST).status_code == 200
    empty = make_client(viewer_assets_dir=tmp_path / "missing")
    sid = _create(empty)["id"]
    missing = empty.get(f"/viewer/{sid}", headers=INGEST)
    assert missing.status_code == 503 and missing.json()["error"]["message"].startswith("the viewer's assets")
