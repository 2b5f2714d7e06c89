"""Per-client rate limits (api/limits.py): anonymous floods meet 429 and leave a bounded audit log; the expensive
reads are throttled per caller. The event streams' cap is tested in tests/api/routes/test_events.py."""

from __future__ import annotations

import time
import uuid
from typing import Any

import pytest
from api_helpers import INGEST, auth
from fastapi.testclient import TestClient

from api.limits import TokenBuckets
from services.settings import Settings
from services.store.results_store import ResultsStore
from tests.api.routes.test_export import create, install_known


def audit_size(client: TestClient) -> int:
    """Return the size in bytes of the app's audit log (0 before its first record)."""
    path = client.app.state.settings.data_dir / "audit" / "audit.jsonl"  # type: ignore[attr-defined]
    return path.stat().st_size if path.exists() else 0


def test_token_buckets_refill_at_their_rate() -> None:
    now = [100.0]
    buckets = TokenBuckets(per_s=2.0, burst=3, clock=lambda: now[0])
    assert [buckets.take("a") for _ in range(3)] == [None, None, None]
    wait = buckets.take("a")
    assert wait is not None and wait == pytest.approx(0.5)  # one token comes back in 1 / per_s
    assert buckets.take("b") is None  # another client has its own bucket
    now[0] += 0.5
    assert buckets.take("a") is None and buckets.take("a") is not None
    now[0] += 100.0
    assert [buckets.take("a") for _ in range(4)].count(None) == 3  # refilled up to the burst, not beyond
    assert all(TokenBuckets(per_s=1.0, burst=0).take("a") is None for _ in range(1000))  # burst 0: no limit


def test_defaults_allow_the_test_suites_rates() -> None:
    defaults = Settings()
    # schemathesis sends a few hundred credential-less probes in ~25 s from one address; tests render a few sheets
    assert defaults.rate_limit_anonymous_burst >= 200 and defaults.rate_limit_anonymous_per_s >= 10
    assert defaults.rate_limit_expensive_burst >= 20
    assert defaults.events_max_per_principal >= 8 and defaults.events_max_total >= defaults.events_max_per_principal


def test_anonymous_flood_meets_429_and_grows_the_audit_log_by_at_most_64_kb(client: TestClient) -> None:
    before = audit_size(client)
    statuses: dict[int, int] = {}
    first_429: Any = None
    started = time.monotonic()
    for i in range(3000):
        sid = uuid.uuid4().hex if i % 3 else f"Jane-Doe-{i}"  # ids of the valid form, and raw text that is not one
        resp = client.get(f"/v1/sessions/{sid}")
        statuses[resp.status_code] = statuses.get(resp.status_code, 0) + 1
        if resp.status_code == 429 and first_429 is None:
            first_429 = resp
    assert set(statuses) == {401, 429}, statuses
    settings = client.app.state.settings  # type: ignore[attr-defined]
    allowed = settings.rate_limit_anonymous_burst + settings.rate_limit_anonymous_per_s * (time.monotonic() - started)
    assert statuses[401] <= allowed + 1, (statuses, allowed)  # the burst, then the refill rate
    assert first_429 is not None and int(first_429.headers["Retry-After"]) >= 1
    assert first_429.json()["error"]["code"] == "rate_limited"
    grown = audit_size(client) - before
    assert grown <= 64 * 1024, grown
    raw = (client.app.state.settings.data_dir / "audit" / "audit.jsonl").read_text()  # type: ignore[attr-defined]
    assert "Jane-Doe" not in raw  # a raw path parameter is never recorded
    # a client with a valid key from the same address is not throttled by the anonymous flood
    assert client.get("/v1/sessions/" + uuid.uuid4().hex, headers=INGEST).status_code == 404


def test_anonymous_refusals_are_recorded_per_client_without_raw_ids(make_client: Any) -> None:
    client = make_client(audit_coalesce_s=3600)
    junk = "Jane%20Doe%201970"
    for sid in (uuid.uuid4().hex, junk, uuid.uuid4().hex):
        assert client.get(f"/v1/sessions/{sid}").status_code == 401
    assert client.get(f"/v1/sessions/{junk}/path", headers=auth("no-such-key")).status_code == 401
    records = client.get("/v1/audit", params={"actor": "anonymous"}, headers=auth("admin-key-0123456789abcdef")).json()[
        "records"
    ]
    assert len(records) == 1  # one record per client and status in the window, whatever the route and id
    assert records[0]["status"] == 401 and records[0]["session"] is not None and len(records[0]["session"]) == 32
    raw = (client.app.state.settings.data_dir / "audit" / "audit.jsonl").read_text()  # type: ignore[attr-defined]
    assert "Jane" not in raw
    # an authenticated caller's invalid id is recorded as the placeholder too
    client.get(f"/v1/sessions/{junk}", headers=INGEST)
    mine = client.get("/v1/audit", params={"session": "(invalid)"}, headers=auth("admin-key-0123456789abcdef")).json()[
        "records"
    ]
    assert [r["status"] for r in mine] == [404]


def test_failing_auth_is_rate_limited_per_client(make_client: Any) -> None:
    client = make_client(rate_limit_anonymous_burst=5, rate_limit_anonymous_per_s=0.01)
    sid = create(client)["id"]
    answers = [client.get(f"/v1/sessions/{sid}?token=forged").status_code for _ in range(5)]
    answers += [client.get(f"/v1/sessions/{sid}", headers=auth("wrong-key")).status_code for _ in range(2)]
    answers.append(client.post("/v1/sessions", json={}).status_code)
    assert answers == [401] * 5 + [429] * 3
    refused = client.get(f"/v1/sessions/{sid}")
    assert refused.status_code == 429 and int(refused.headers["Retry-After"]) >= 60  # one token per 100 s
    assert refused.json()["error"]["code"] == "rate_limited"
    assert client.get(f"/v1/sessions/{sid}", headers=INGEST).status_code == 200  # the valid key still gets in


def test_expensive_reads_are_rate_limited_per_caller(make_client: Any) -> None:
    client = make_client(rate_limit_expensive_burst=2, rate_limit_expensive_per_s=0.01)
    created = create(client)
    sid = created["id"]
    install_known(client, sid)
    assert client.get(f"/v1/sessions/{sid}/sheet.pdf", headers=INGEST).status_code == 200
    assert client.get(f"/v1/sessions/{sid}/export.dcm?layer=report", headers=INGEST).status_code == 200
    refused = client.get(f"/v1/sessions/{sid}/sheet.pdf", headers=INGEST)
    assert refused.status_code == 429 and int(refused.headers["Retry-After"]) >= 1
    assert refused.json()["error"]["code"] == "rate_limited"
    assert client.get(f"/v1/sessions/{sid}/export.dcm?layer=report", headers=INGEST).status_code == 429
    assert client.get(f"/v1/sessions/{sid}/export.dcm?layer=vein", headers=INGEST).status_code == 200  # cheap
    # another caller (the viewer link) has its own allowance
    token = created["viewer_token"]
    assert client.get(f"/v1/sessions/{sid}/sheet.pdf?token={token}").status_code == 200
    # GET /report may evaluate the report: limited too
    ResultsStore(client.app.state.settings.data_dir).write_reference(sid, "seq,x_mm,y_mm\n0,0,0\n")  # type: ignore[attr-defined]
    assert client.get(f"/v1/sessions/{sid}/report", headers=INGEST).status_code == 429


def test_429_is_documented_on_authenticated_routes(client: TestClient) -> None:
    paths = client.get("/openapi.json", headers=INGEST).json()["paths"]
    assert "429" in paths["/v1/sessions/{session_id}"]["get"]["responses"]
    assert "Retry-After" in paths["/v1/sessions/{session_id}"]["get"]["responses"]["429"]["headers"]
    assert "429" not in paths["/healthz"]["get"]["responses"]
