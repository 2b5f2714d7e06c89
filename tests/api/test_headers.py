"""Security headers on every answer (api/headers.py): nosniff everywhere, the API CSP on API answers (the viewer
page keeps its own), and "private, no-store" on /v1/ answers that set no Cache-Control of their own."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from api_helpers import INGEST, calibration_doc
from fastapi.testclient import TestClient

from api.headers import API_CSP
from api.routes.viewer import CSP as VIEWER_CSP


def test_every_answer_has_nosniff_and_api_answers_the_csp(make_client: Any) -> None:
    client = make_client(max_json_bytes=1024)
    created = client.post("/v1/sessions", json={"calibration": calibration_doc()}, headers=INGEST)
    sid = created.json()["id"]
    answers = {
        "healthz": client.get("/healthz"),
        "openapi": client.get("/openapi.json", headers=INGEST),
        "401": client.get(f"/v1/sessions/{sid}"),
        "404": client.get("/v1/nothing-here"),
        "413 (the request middleware's own)": client.post(
            "/v1/sessions", content=b"x" * 2048, headers={**INGEST, "Content-Type": "application/json"}
        ),
        "created": created,
        "session": client.get(f"/v1/sessions/{sid}", headers=INGEST),
        "static": client.get("/static/viewer.js"),
    }
    assert answers["413 (the request middleware's own)"].status_code == 413
    for name, resp in answers.items():
        assert resp.headers.get("X-Content-Type-Options") == "nosniff", name
        assert resp.headers.get("Content-Security-Policy") == API_CSP, name
    assert "default-src 'none'" in API_CSP and "frame-ancestors 'none'" in API_CSP
    docs = client.get("/docs")  # no Swagger UI (its scripts come from a CDN): a 404 with the CSP like any answer
    assert docs.status_code == 404 and docs.headers["Content-Security-Policy"] == API_CSP


def test_patient_data_is_private_no_store(client: TestClient) -> None:
    created = client.post("/v1/sessions", json={"calibration": calibration_doc(), "label": "x"}, headers=INGEST)
    sid, token = created.json()["id"], created.json()["viewer_token"]
    assert created.headers["Cache-Control"] == "private, no-store"  # it carries the viewer token
    for url in (f"/v1/sessions/{sid}", f"/v1/sessions/{sid}/path", f"/v1/sessions/{sid}/path?format=csv"):
        owner = client.get(url, headers=INGEST)
        viewer = client.get(f"{url}{'&' if '?' in url else '?'}token={token}")
        assert owner.status_code == viewer.status_code == 200, url
        assert owner.headers["Cache-Control"] == viewer.headers["Cache-Control"] == "private, no-store", url
    refused = client.get(f"/v1/sessions/{sid}/report", headers=INGEST)
    assert refused.status_code == 404 and refused.headers["Cache-Control"] == "private, no-store"


def test_the_viewer_page_keeps_its_own_csp(make_client: Any, tmp_path: Path) -> None:
    assets = tmp_path / "osd"
    assets.mkdir()
    (assets / "openseadragon.min.js").write_text("/* a stand-in */")
    client = make_client(viewer_assets_dir=assets)
    created = client.post("/v1/sessions", json={"calibration": calibration_doc()}, headers=INGEST).json()
    page = client.get(created["viewer_url"])
    assert page.status_code == 200
    assert page.headers["Content-Security-Policy"] == VIEWER_CSP  # not replaced by the API's
    assert page.headers["X-Content-Type-Options"] == "nosniff" and page.headers["Cache-Control"] == "no-store"
