"""Bearer keys and scopes, ownership (404 for another key's session), signed viewer tokens."""

from __future__ import annotations

import base64
import hashlib
import json
import time

from api_helpers import INGEST, auth, calibration_doc, frame_bytes, upload
from fastapi.testclient import TestClient
from itsdangerous import URLSafeSerializer

from api.auth import fingerprint, make_viewer_token, token_serializer, verify_viewer_token

SECRET = b"test-secret"


def test_missing_or_unknown_key_is_401_with_challenge(client: TestClient) -> None:
    for headers in ({}, auth("not-a-key"), {"Authorization": "Basic abc"}):
        resp = client.post("/v1/sessions", json={"calibration": calibration_doc()}, headers=headers)
        assert resp.status_code == 401
        assert resp.headers["WWW-Authenticate"].startswith("Bearer")
        assert resp.json()["error"]["code"] == "unauthorized"


def test_key_without_scope_is_403(client: TestClient) -> None:
    resp = client.post(
        "/v1/sessions", json={"calibration": calibration_doc()}, headers=auth("view-key-0123456789abcdef")
    )
    assert resp.status_code == 403
    assert resp.json()["error"]["code"] == "forbidden"


def test_other_owner_gets_404_admin_sees_all(client: TestClient, session_id: str) -> None:
    other = auth("ingest-key-b-0123456789abcdef")
    assert client.get(f"/v1/sessions/{session_id}", headers=other).status_code == 404
    assert upload(client, session_id, 0, frame_bytes(), headers=other).status_code == 404
    assert client.post(f"/v1/sessions/{session_id}/finish", headers=other).status_code == 404
    # same answer as for an id that does not exist: existence does not leak
    missing = client.get("/v1/sessions/" + "0" * 32, headers=other)
    assert (
        missing.status_code == 404 and missing.json() == client.get(f"/v1/sessions/{session_id}", headers=other).json()
    )
    assert client.get(f"/v1/sessions/{session_id}", headers=auth("admin-key-0123456789abcdef")).status_code == 200
    assert client.get(f"/v1/sessions/{session_id}", headers=INGEST).status_code == 200
    # a view-only key did not create the session, so it cannot see it either
    assert client.get(f"/v1/sessions/{session_id}", headers=auth("view-key-0123456789abcdef")).status_code == 404


def test_session_owner_is_key_fingerprint_never_key(client: TestClient, session_id: str) -> None:
    store = client.app.state.store  # type: ignore[attr-defined]
    meta = store.get_meta(session_id)
    assert meta.owner == fingerprint("ingest-key-a-0123456789abcdef")
    raw = (store.session_dir(session_id) / "session.json").read_text()
    assert "ingest-key-a-0123456789abcdef" not in raw


def test_viewer_token_from_create_grants_view_only(client: TestClient) -> None:
    resp = client.post("/v1/sessions", json={"calibration": calibration_doc(), "label": "x"}, headers=INGEST)
    body = resp.json()
    sid, token = body["id"], body["viewer_token"]
    assert body["viewer_url"] == f"/viewer/{sid}?token={token}"
    by_query = client.get(f"/v1/sessions/{sid}", params={"token": token})
    assert by_query.status_code == 200
    assert by_query.json()["label"] is None  # a shared link never reveals the (patient) label
    assert client.get(f"/v1/sessions/{sid}", headers=auth(token)).status_code == 200
    # view-only: it cannot upload or finish
    assert upload(client, sid, 0, frame_bytes(), headers=auth(token)).status_code == 401
    assert client.post(f"/v1/sessions/{sid}/finish", params={"token": token}).status_code == 401


def test_viewer_token_expired_or_for_other_session_is_401(client: TestClient, session_id: str) -> None:
    other = client.post("/v1/sessions", json={"calibration": calibration_doc()}, headers=INGEST).json()["id"]
    expired = make_viewer_token(SECRET, session_id, ttl_s=60, now=time.time() - 120)
    wrong_session = make_viewer_token(SECRET, other, ttl_s=60, now=time.time())
    forged = make_viewer_token(b"another-secret", session_id, ttl_s=60, now=time.time())
    for token in (expired, wrong_session, forged, "garbage", "99999999999.AAAA"):
        resp = client.get(f"/v1/sessions/{session_id}", params={"token": token})
        assert resp.status_code == 401, token
        assert set(resp.json()["error"]) >= {"code", "message"}


def test_token_roundtrip_and_tamper() -> None:
    token = make_viewer_token(SECRET, "a" * 32, ttl_s=10, now=1000.0)
    assert verify_viewer_token(SECRET, token, "a" * 32, now=1009.0)
    assert not verify_viewer_token(SECRET, token, "a" * 32, now=1010.0)  # expiry is exclusive
    assert not verify_viewer_token(SECRET, token, "b" * 32, now=1000.0)
    # a later expiry (or another session) pasted into the payload breaks the signature
    _, signature = token.rsplit(".", 1)
    for claims in ({"sid": "a" * 32, "scope": "view", "exp": 1100}, {"sid": "b" * 32, "scope": "view", "exp": 1010}):
        payload = base64.urlsafe_b64encode(json.dumps(claims, separators=(",", ":")).encode()).rstrip(b"=").decode()
        assert not verify_viewer_token(SECRET, f"{payload}.{signature}", str(claims["sid"]), now=1000.0)
    assert not verify_viewer_token(SECRET, token + "x" * 600, "a" * 32, now=1000.0)  # oversized: refused at once
    assert all(c.isalnum() or c in "-_." for c in token)  # URL-safe as is


def test_token_of_another_use_or_scope_is_refused() -> None:
    """Only a view-scope payload signed with the viewer-token salt is a viewer token."""
    other_use = URLSafeSerializer(SECRET, salt="something-else", signer_kwargs={"digest_method": hashlib.sha256})
    claims = {"sid": "a" * 32, "scope": "view", "exp": 2000}
    assert not verify_viewer_token(SECRET, str(other_use.dumps(claims)), "a" * 32, now=1000.0)
    ingest = token_serializer(SECRET).dumps({**claims, "scope": "ingest"})
    assert not verify_viewer_token(SECRET, str(ingest), "a" * 32, now=1000.0)
    assert verify_viewer_token(SECRET, str(token_serializer(SECRET).dumps(claims)), "a" * 32, now=1000.0)


def test_rotated_secrets_verify_old_tokens_and_sign_with_the_newest() -> None:
    old, new = b"o" * 32, b"n" * 32
    issued_before = make_viewer_token(old, "a" * 32, ttl_s=60, now=1000.0)
    assert verify_viewer_token([old, new], issued_before, "a" * 32, now=1010.0)  # still valid through rotation
    assert not verify_viewer_token([new], issued_before, "a" * 32, now=1010.0)  # the old secret dropped: refused
    issued_after = make_viewer_token([old, new], "a" * 32, ttl_s=60, now=1000.0)
    assert verify_viewer_token(new, issued_after, "a" * 32, now=1010.0)  # signed with the newest (the last)
    assert not verify_viewer_token(old, issued_after, "a" * 32, now=1010.0)
