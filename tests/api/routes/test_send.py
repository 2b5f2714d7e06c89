"""POST /v1/sessions/{id}/send (api/routes/send.py): a send to a configured PACS destination is queued as a durable
job (202, followed at /v1/jobs/{id}); an unknown destination is 422 naming none of the configured ones (their
names describe the hospital's network), a failed session
409; only the session's owner (or an admin) may send it. Running the job against a real PACS (Orthanc): see
tests/workers/test_send_job.py."""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

import pytest
from api_helpers import INGEST, auth, calibration_doc
from fastapi.testclient import TestClient

from services.jobs import queue

DESTINATIONS = {"web": {"dicomweb": "http://pacs.example/dicom-web"}, "archive": {"dicomweb": "http://a.example/dw"}}


@pytest.fixture
def pacs_client(make_client: Callable[..., TestClient]) -> TestClient:
    """Return a client with two PACS destinations configured (web, archive)."""
    return make_client(pacs_destinations=DESTINATIONS)


def _session(client: TestClient, key: dict[str, str] = INGEST) -> str:
    resp = client.post("/v1/sessions", json={"calibration": calibration_doc()}, headers=key)
    assert resp.status_code == 201, resp.text
    return str(resp.json()["id"])


def _jobs_on_stream(client: TestClient) -> list[dict[str, str]]:
    r, prefix = client.app.state.redis, client.app.state.settings.redis_prefix  # type: ignore[attr-defined]
    return [{k.decode(): v.decode() for k, v in f.items()} for _, f in r.xrange(queue.jobs_stream(prefix))]


def _send(client: TestClient, sid: str, destination: str, key: dict[str, str] = INGEST) -> Any:
    return client.post(f"/v1/sessions/{sid}/send", json={"destination": destination}, headers=key)


def test_a_send_is_queued_as_a_durable_job_followed_at_its_status_url(pacs_client: TestClient) -> None:
    sid = _session(pacs_client)
    resp = _send(pacs_client, sid, "archive")
    assert resp.status_code == 202, resp.text
    body = resp.json()
    job = body["job"]
    assert body == {"job": job, "session": sid, "status_url": f"/v1/jobs/{job}"}
    (entry,) = _jobs_on_stream(pacs_client)
    assert entry["kind"] == "send" and entry["job"] == job and entry["session"] == sid
    assert json.loads(entry["options"]) == {"destination": "archive"}
    state = pacs_client.get(body["status_url"], headers=INGEST).json()
    assert state["kind"] == "send" and state["state"] == "queued" and state["session"] == sid
    assert state["options"] == {"destination": "archive"} and state["attempts"] == 0
    ledger = pacs_client.app.state.store.jobs  # type: ignore[attr-defined]
    assert [j["id"] for j in ledger.open_jobs()] == [job]  # the 202's promise survives a Redis loss


def test_each_send_is_its_own_job(pacs_client: TestClient) -> None:
    sid = _session(pacs_client)
    first, second = (_send(pacs_client, sid, name).json()["job"] for name in ("web", "archive"))
    assert first != second
    assert [e["job"] for e in _jobs_on_stream(pacs_client)] == [first, second]


def test_an_unknown_destination_is_422_naming_none_of_the_configured_ones_and_queues_nothing(
    pacs_client: TestClient,
) -> None:
    sid = _session(pacs_client)
    resp = _send(pacs_client, sid, "elsewhere")
    assert resp.status_code == 422, resp.text
    error = resp.json()["error"]
    assert error["code"] == "unknown_destination"
    assert error["message"] == "destination: not a configured PACS destination"
    for secret in ("archive", "web", "pacs.example", "a.example", "elsewhere"):  # the hospital's network, echoes
        assert secret not in resp.text
    assert _jobs_on_stream(pacs_client) == []


def test_without_destinations_configured_a_send_is_refused_as_any_unknown_destination(client: TestClient) -> None:
    resp = _send(client, _session(client), "web")
    assert resp.status_code == 422 and resp.json()["error"]["code"] == "unknown_destination"


def test_a_failed_session_has_nothing_to_send(pacs_client: TestClient) -> None:
    sid = _session(pacs_client)
    pacs_client.app.state.store.set_status(sid, "failed")  # type: ignore[attr-defined]
    resp = _send(pacs_client, sid, "web")
    assert resp.status_code == 409 and resp.json()["error"]["code"] == "session_failed"
    assert _jobs_on_stream(pacs_client) == []


def test_only_the_owner_or_an_admin_may_send(pacs_client: TestClient) -> None:
    sid = _session(pacs_client)
    assert (
        _send(pacs_client, sid, "web", auth("ingest-key-b-0123456789abcdef")).status_code == 404
    )  # another owner's: not found
    assert (
        _send(pacs_client, sid, "web", auth("view-key-0123456789abcdef")).status_code == 403
    )  # may look, may not send
    assert pacs_client.post(f"/v1/sessions/{sid}/send", json={"destination": "web"}).status_code == 401
    assert _jobs_on_stream(pacs_client) == []
    assert _send(pacs_client, sid, "web", auth("admin-key-0123456789abcdef")).status_code == 202


def test_the_first_finish_queues_one_send_per_auto_send_destination(make_client: Callable[..., TestClient]) -> None:
    client = make_client(pacs_destinations=DESTINATIONS, pacs_auto_send=["archive"])
    sid = _session(client)
    assert client.post(f"/v1/sessions/{sid}/finish", headers=INGEST).status_code == 202
    assert client.post(f"/v1/sessions/{sid}/finish", headers=INGEST).status_code == 202  # idempotent: no second
    (entry,) = _jobs_on_stream(client)
    assert entry["kind"] == "send" and json.loads(entry["options"]) == {"destination": "archive"}
