"""Reprocess jobs: validation of options (422 naming the field), enqueueing, job state, batches and visibility."""

from __future__ import annotations

import json
from typing import Any

import pytest
from api_helpers import INGEST, auth, calibration_doc, frame_bytes, upload
from fastapi.testclient import TestClient

from services.jobs import queue


def _error(resp: Any) -> dict[str, Any]:
    body = resp.json()
    assert set(body) == {"error"}
    return body["error"]


def finished_session(client: TestClient, key: dict[str, str] = INGEST) -> str:
    """Return the id of a finished session with one frame, owned by `key`."""
    sid = client.post("/v1/sessions", json={"calibration": calibration_doc()}, headers=key).json()["id"]
    assert upload(client, sid, 0, frame_bytes(0), headers=key).status_code == 202
    assert client.post(f"/v1/sessions/{sid}/finish", headers=key).status_code == 202
    return sid


def _r_prefix(client: TestClient) -> tuple[Any, str]:
    return client.app.state.redis, client.app.state.settings.redis_prefix  # type: ignore[attr-defined]


def jobs_on_stream(client: TestClient) -> list[dict[str, str]]:
    """Return the entries of the jobs stream as str dicts."""
    r, prefix = _r_prefix(client)
    out = []
    for _, fields in r.xrange(queue.jobs_stream(prefix)):
        out.append({k.decode(): v.decode() for k, v in fields.items()})
    return out


def test_reprocess_enqueues_a_job(client: TestClient) -> None:
    sid = finished_session(client)
    options = {"method": "paper", "method_options": {"min_inliers": 25}, "calibration": {"young_modulus_kpa": 15.0}}
    resp = client.post(f"/v1/sessions/{sid}/reprocess", json={"options": options}, headers=INGEST)
    assert resp.status_code == 202, resp.text
    body = resp.json()
    job = body["job"]
    assert body["session"] == sid and body["status_url"] == f"/v1/jobs/{job}"
    (entry,) = jobs_on_stream(client)
    assert entry["kind"] == "reprocess" and entry["job"] == job and entry["session"] == sid
    assert json.loads(entry["options"]) == options
    state = client.get(f"/v1/jobs/{job}", headers=INGEST).json()
    assert state["status"] == "queued" and state["session"] == sid and state["progress"] is None
    assert state["options"]["method"] == "paper" and state["version"] is None

    # a worker reports progress in the job hash
    r, prefix = _r_prefix(client)
    r.hset(queue.job_key(job, prefix), mapping={"state": "running", "done": 5, "total": 20, "version": 2})
    state = client.get(f"/v1/jobs/{job}", headers=INGEST).json()
    assert (state["status"], state["progress"], state["version"]) == ("running", 0.25, 2)


def test_default_options_are_best(client: TestClient) -> None:
    sid = finished_session(client)
    resp = client.post(f"/v1/sessions/{sid}/reprocess", json={}, headers=INGEST)
    assert resp.status_code == 202
    assert json.loads(jobs_on_stream(client)[0]["options"]) == {"method": "best"}


@pytest.mark.parametrize(
    ("options", "code", "needle"),
    [
        ({"method": "magic"}, "invalid_options", "method"),
        ({"method": 3}, "invalid_options", "method"),
        ({"method_options": {"turbo": True}}, "invalid_options", "turbo"),
        ({"method_options": {"min_inliers": "many"}}, "invalid_options", "min_inliers"),
        ({"method_options": {"refine": 1}}, "invalid_options", "refine"),
        ({"method_options": {"features": "orb"}}, "invalid_options", "features"),
        ({"method_options": {"ransac_px": -1.0}}, "invalid_options", "ransac_px"),
        (
            {"method_options": {"target_features": 10**6}},
            "invalid_options",
            "target_features: Input should be less than or equal to 10000",
        ),
        (
            {"method_options": {"neighbours": 10**6}},
            "invalid_options",
            "neighbours: Input should be less than or equal to 32",
        ),
        ({"method_options": {"name": "x"}}, "invalid_options", "name"),
        ({"calibration": {"young_modulus_kpa": -2}}, "invalid_calibration", "young_modulus_kpa"),
        ({"calibration": {"colour": "red"}}, "invalid_calibration", "colour"),
        ({"calibration": {"image_size": [10, 10]}}, "invalid_calibration", "image_size"),
        ({"speed": "fast"}, "invalid_options", "speed"),
    ],
)
def test_bad_options_are_422_naming_the_field(client: TestClient, options: dict, code: str, needle: str) -> None:
    sid = finished_session(client)
    resp = client.post(f"/v1/sessions/{sid}/reprocess", json={"options": options}, headers=INGEST)
    assert resp.status_code == 422, resp.text
    err = _error(resp)
    assert err["code"] == code and needle in err["message"], err
    assert jobs_on_stream(client) == []  # nothing queued


def test_reprocess_preconditions_and_auth(client: TestClient, session_id: str) -> None:
    resp = client.post(f"/v1/sessions/{session_id}/reprocess", json={}, headers=INGEST)
    assert resp.status_code == 409 and _error(resp)["code"] == "not_finished"
    sid = finished_session(client)
    url = f"/v1/sessions/{sid}/reprocess"
    assert client.post(url, json={}).status_code == 401
    assert client.post(url, json={}, headers=auth("ingest-key-b-0123456789abcdef")).status_code == 404
    assert client.post(url, json={}, headers=auth("view-key-0123456789abcdef")).status_code == 403
    token = client.post("/v1/sessions", json={"calibration": calibration_doc()}, headers=INGEST).json()
    assert client.post(url, json={}, headers={"Authorization": f"Bearer {token['viewer_token']}"}).status_code == 401
    assert client.post(url, json={"options": {}, "extra": 1}, headers=INGEST).status_code == 422
    assert client.post(url, json={}, headers=auth("admin-key-0123456789abcdef")).status_code == 202
    empty = client.post("/v1/sessions", json={"calibration": calibration_doc()}, headers=INGEST).json()["id"]
    client.post(f"/v1/sessions/{empty}/finish", headers=INGEST)
    resp = client.post(f"/v1/sessions/{empty}/reprocess", json={}, headers=INGEST)
    assert resp.status_code == 409 and _error(resp)["code"] == "no_frames"


def test_job_visibility(client: TestClient) -> None:
    sid = finished_session(client)
    job = client.post(f"/v1/sessions/{sid}/reprocess", json={}, headers=INGEST).json()["job"]
    url = f"/v1/jobs/{job}"
    assert client.get(url, headers=INGEST).status_code == 200
    assert client.get(url, headers=auth("admin-key-0123456789abcdef")).status_code == 200
    assert client.get(url, headers=auth("ingest-key-b-0123456789abcdef")).status_code == 404
    assert client.get(url, headers=auth("view-key-0123456789abcdef")).status_code == 404
    assert client.get(url).status_code == 401
    assert client.get("/v1/jobs/0123456789abcdef0123456789abcdef", headers=INGEST).status_code == 404
    assert client.get("/v1/jobs/..%2Fsecret", headers=INGEST).status_code == 404


def test_batch_reprocess(client: TestClient) -> None:
    a1, a2 = finished_session(client), finished_session(client)
    b1 = finished_session(client, key=auth("ingest-key-b-0123456789abcdef"))
    body = {"sessions": [a1, a2, a1], "options": {"method": "sift-chain"}}
    resp = client.post("/v1/reprocess", json=body, headers=INGEST)
    assert resp.status_code == 202, resp.text
    batch = resp.json()
    assert len(batch["jobs"]) == 2  # duplicates are reprocessed once
    assert [e["session"] for e in jobs_on_stream(client)] == [a1, a2]
    state = client.get(batch["status_url"], headers=INGEST).json()
    assert state["status"] == "queued" and [j["session"] for j in state["jobs"]] == [a1, a2]
    assert client.get(batch["status_url"], headers=auth("ingest-key-b-0123456789abcdef")).status_code == 404
    assert client.get(f"/v1/jobs/{batch['jobs'][0]}", headers=INGEST).json()["batch"] == batch["batch"]

    # a session of another key: 404 for the whole batch, nothing queued
    resp = client.post("/v1/reprocess", json={"sessions": [a1, b1]}, headers=INGEST)
    assert resp.status_code == 404 and len(jobs_on_stream(client)) == 2
    assert client.post("/v1/reprocess", json={"sessions": ["nope"]}, headers=INGEST).status_code == 404
    assert client.post("/v1/reprocess", json={"sessions": []}, headers=INGEST).status_code == 422
    bad = client.post("/v1/reprocess", json={"sessions": [a1], "options": {"method": "x"}}, headers=INGEST)
    assert bad.status_code == 422 and len(jobs_on_stream(client)) == 2
    # admin may batch sessions of several owners
    resp = client.post("/v1/reprocess", json={"sessions": [a1, b1]}, headers=auth("admin-key-0123456789abcdef"))
    assert resp.status_code == 202 and len(jobs_on_stream(client)) == 4

    r, prefix = _r_prefix(client)
    for job in batch["jobs"]:
        r.hset(queue.job_key(job, prefix), mapping={"state": "done", "done": 1, "total": 1})
    done = client.get(batch["status_url"], headers=INGEST).json()
    assert done["status"] == "done" and all(j["progress"] == 1.0 for j in done["jobs"])


def test_a_full_job_queue_is_503_for_reprocess_and_send_and_queues_nothing(make_client: Any) -> None:
    """enqueue_jobs refuses past queue_max_depth (QueueFullError -> 503 queue_full with Retry-After, api/errors.py)."""
    client = make_client(queue_max_depth=1, retry_after_s=7, pacs_destinations={"web": {"dicomweb": "http://pacs/dw"}})
    sid = finished_session(client)
    assert client.post(f"/v1/sessions/{sid}/reprocess", json={}, headers=INGEST).status_code == 202
    for path, body in ((f"/v1/sessions/{sid}/reprocess", {}), (f"/v1/sessions/{sid}/send", {"destination": "web"})):
        resp = client.post(path, json=body, headers=INGEST)
        assert resp.status_code == 503 and resp.headers["Retry-After"] == "7", resp.text
        assert _error(resp)["code"] == "queue_full"
    assert len(jobs_on_stream(client)) == 1
    assert len(client.app.state.store.jobs.open_jobs()) == 1  # type: ignore[attr-defined]


def test_a_job_says_status_like_a_session_and_state_only_as_its_deprecated_alias(client: TestClient) -> None:
    sid = finished_session(client)
    job = client.post(f"/v1/sessions/{sid}/reprocess", json={}, headers=INGEST).json()["job"]
    assert client.get(f"/v1/sessions/{sid}", headers=INGEST).json()["status"]  # a session's word
    queued = client.get(f"/v1/jobs/{job}", headers=INGEST).json()
    assert queued["status"] == queued["state"] == "queued"
    r, prefix = _r_prefix(client)
    r.hset(queue.job_key(job, prefix), mapping={"state": "running", "done": 1, "total": 4})
    running = client.get(f"/v1/jobs/{job}", headers=INGEST).json()
    assert running["status"] == running["state"] == "running"
    batch = client.post("/v1/reprocess", json={"sessions": [sid]}, headers=INGEST).json()
    state = client.get(batch["status_url"], headers=INGEST).json()
    assert state["status"] == state["state"] == "queued" and state["jobs"][0]["status"] == "queued"
    schemas = client.get("/openapi.json", headers=INGEST).json()["components"]["schemas"]
    for name in ("JobState", "BatchState"):
        props = schemas[name]["properties"]
        assert "status" in schemas[name]["required"] and not props["status"].get("deprecated")
        assert props["state"]["deprecated"] is True and "alias of `status`" in props["state"]["description"]


def test_a_key_over_its_job_quota_gets_429_and_other_keys_are_unaffected(make_client: Any) -> None:
    client = make_client(queue_max_jobs_per_key=2, pacs_destinations={"web": {"dicomweb": "http://pacs.example/dw"}})
    other = auth("ingest-key-b-0123456789abcdef")
    mine, theirs = finished_session(client), finished_session(client, other)
    first = client.post(f"/v1/sessions/{mine}/reprocess", json={}, headers=INGEST)
    assert first.status_code == 202
    assert client.post(f"/v1/sessions/{mine}/send", json={"destination": "web"}, headers=INGEST).status_code == 202
    for url, body in [(f"/v1/sessions/{mine}/reprocess", {}), (f"/v1/sessions/{mine}/send", {"destination": "web"})]:
        refused = client.post(url, json=body, headers=INGEST)  # reprocess and send share the quota
        assert refused.status_code == 429 and int(refused.headers["Retry-After"]) >= 1, refused.text
        assert _error(refused)["code"] == "quota_exceeded" and "2 jobs" in _error(refused)["message"]
    assert len(jobs_on_stream(client)) == 2  # nothing queued for the refused requests
    assert client.post(f"/v1/sessions/{theirs}/reprocess", json={}, headers=other).status_code == 202  # its own quota
    r, prefix = _r_prefix(client)
    r.hset(queue.job_key(first.json()["job"], prefix), "state", "done")  # a worker finished one: a place is free
    assert client.post(f"/v1/sessions/{mine}/reprocess", json={}, headers=INGEST).status_code == 202
