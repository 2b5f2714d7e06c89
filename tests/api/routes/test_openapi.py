"""GET /openapi.json (api/routes/openapi.py): for API keys by default, public or off by a setting; no /docs or
/redoc pages (Swagger UI and ReDoc load their scripts from a CDN)."""

from __future__ import annotations

from typing import Any

from api_helpers import INGEST, auth

from api.headers import API_CSP


def test_the_document_is_for_api_keys_by_default(client: Any) -> None:
    assert client.app.state.settings.api_docs == "keys"
    refused = client.get("/openapi.json")
    assert refused.status_code == 401 and refused.json()["error"]["code"] == "unauthorized"
    assert client.get("/openapi.json", headers=auth("not-a-key-0123456789abcdef")).status_code == 401
    for key in (INGEST, auth("view-key-0123456789abcdef"), auth("admin-key-0123456789abcdef")):
        doc = client.get("/openapi.json", headers=key)
        assert doc.status_code == 200 and "/v1/sessions" in doc.json()["paths"]
        assert doc.headers["Content-Security-Policy"] == API_CSP
    assert "/openapi.json" not in doc.json()["paths"]


def test_public_or_off_by_the_setting(make_client: Any) -> None:
    public = make_client(api_docs="public")
    assert public.get("/openapi.json").status_code == 200
    off = make_client(api_docs="off")
    assert off.get("/openapi.json").status_code == off.get("/openapi.json", headers=INGEST).status_code == 404


def test_no_interactive_pages_load_scripts_from_a_cdn(make_client: Any) -> None:
    client = make_client(api_docs="public")
    for page in ("/docs", "/redoc", "/docs/oauth2-redirect"):
        resp = client.get(page)
        assert resp.status_code == 404 and "cdn" not in resp.text.lower(), page
        assert resp.headers["Content-Security-Policy"] == API_CSP  # nothing is exempt from the API's CSP
