"""Liveness, readiness and settings."""

from __future__ import annotations

import json
import os
import stat
from collections.abc import Callable
from pathlib import Path

import pytest
from api_helpers import INGEST
from fastapi.testclient import TestClient

from services.settings import Settings
from services.store.secrets import token_secret_bytes


def test_healthz_and_readyz_ok(client: TestClient) -> None:
    assert client.get("/healthz").json() == {"status": "ok", "checks": {}}
    resp = client.get("/readyz")
    assert resp.status_code == 200 and resp.json()["checks"] == {"redis": True, "storage": True, "disk_space": True}


@pytest.mark.parametrize("backend", ["embedded"], indirect=True)
def test_readyz_503_when_redis_unreachable(make_client: Callable[..., TestClient]) -> None:
    client = make_client(redis_url="redis://127.0.0.1:1/0")  # nothing listens on port 1
    assert client.get("/healthz").status_code == 200
    resp = client.get("/readyz")
    assert resp.status_code == 503 and "Retry-After" in resp.headers
    assert resp.json()["error"]["code"] == "not_ready" and "redis" in resp.json()["error"]["message"]


def test_readyz_503_when_storage_not_writable(client: TestClient, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(client.app.state.store, "writable", lambda: False)  # type: ignore[attr-defined]
    resp = client.get("/readyz")
    assert resp.status_code == 503 and "storage" in resp.json()["error"]["message"]


def test_openapi_served(client: TestClient) -> None:
    doc = client.get("/openapi.json", headers=INGEST).json()
    assert doc["info"]["title"] == "veinmosaic"
    assert "/v1/sessions/{session_id}/frames" in doc["paths"]


def test_settings_from_environment(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    k1, k2 = "k1-0123456789abcdef0123456", "k2-0123456789abcdef0123456"
    monkeypatch.setenv("VEINMOSAIC_API_KEYS", json.dumps({k1: ["ingest", "view"], k2: ["admin"]}))
    monkeypatch.setenv("REDIS_URL", "redis://example:6379/3")
    monkeypatch.setenv("VEINMOSAIC_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("VEINMOSAIC_QUEUE_MAX_DEPTH", "12")
    s = Settings()
    assert s.api_keys == {k1: ["ingest", "view"], k2: ["admin"]}
    assert s.redis_url == "redis://example:6379/3" and s.data_dir == tmp_path and s.queue_max_depth == 12
    assert k1 not in repr(s)  # keys never end up in a logged repr
    monkeypatch.setenv("VEINMOSAIC_API_KEYS", json.dumps({k1: ["superuser"]}))
    with pytest.raises(ValueError, match="api_keys"):
        Settings()


def test_token_secret_file_made_once_and_private(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("VEINMOSAIC_TOKEN_SECRET", raising=False)
    s = Settings(data_dir=tmp_path, token_secret=None)
    first = token_secret_bytes(s)
    assert len(first) == 32 and token_secret_bytes(Settings(data_dir=tmp_path, token_secret=None)) == first
    assert stat.S_IMODE(os.stat(tmp_path / "secret").st_mode) == 0o600
    assert [p.name for p in tmp_path.iterdir()] == ["secret"]  # no temp file left behind
    assert token_secret_bytes(Settings(data_dir=tmp_path, token_secret="s" * 32)) == b"s" * 32
