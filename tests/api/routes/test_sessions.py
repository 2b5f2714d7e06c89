"""Session create/read/finish, error shapes, request ids and logs free of patient data."""

from __future__ import annotations

import io
import json
import logging
import time
from collections.abc import Callable

import pytest
from api_helpers import INGEST, calibration_doc, frame_bytes, upload
from fastapi.testclient import TestClient

from services.jobs import queue
from services.log_format import make_log_handler


def _error(resp) -> dict:  # type: ignore[no-untyped-def]
    body = resp.json()
    assert set(body) == {"error"} and {"code", "message"} <= set(body["error"])
    return body["error"]


def test_create_session_201(client: TestClient) -> None:
    resp = client.post("/v1/sessions", json={"calibration": calibration_doc(), "label": "L"}, headers=INGEST)
    assert resp.status_code == 201
    sid = resp.json()["id"]
    assert len(sid) == 32 and int(sid, 16) >= 0
    assert resp.headers["Location"] == f"/v1/sessions/{sid}"
    state = client.get(f"/v1/sessions/{sid}", headers=INGEST).json()
    assert state["status"] == "receiving"
    assert (state["frames_received"], state["frames_processed"], state["frames_lost"]) == (0, 0, 0)
    assert state["extent"] is None and state["label"] == "L"


STUDY = {
    "patient_id": "PID-0042",
    "patient_name": "Doe^Jane",
    "patient_birth_date": "1971-02-03",
    "patient_sex": "F",
    "accession_number": "ACC-7",
    "laterality": "R",
    "referring_physician": "Who^Doctor",
    "study_description": "NIR vein mapping",
}


def test_study_context_is_stored_and_shown_to_the_owner_only(client: TestClient) -> None:
    created = client.post("/v1/sessions", json={"calibration": calibration_doc(), "study": STUDY}, headers=INGEST)
    assert created.status_code == 201, created.text
    sid, token = created.json()["id"], created.json()["viewer_token"]
    assert client.get(f"/v1/sessions/{sid}", headers=INGEST).json()["study"] == STUDY
    assert client.get(f"/v1/sessions/{sid}", params={"token": token}).json()["study"] is None  # a viewer link
    plain = client.post("/v1/sessions", json={"calibration": calibration_doc()}, headers=INGEST).json()["id"]
    assert client.get(f"/v1/sessions/{plain}", headers=INGEST).json()["study"] is None  # created without one


@pytest.mark.parametrize(
    ("study", "field"),
    [
        ({"patient_sex": "X"}, "study.patient_sex"),
        ({"laterality": "both"}, "study.laterality"),
        ({"patient_birth_date": "1971-02-30"}, "patient_birth_date"),  # the right shape, not a date
        ({"patient_birth_date": "03/02/1971"}, "study.patient_birth_date"),
        ({"accession_number": "A" * 17}, "study.accession_number"),
        ({"patient_name": "Doe\\Jane"}, "patient_name"),  # the DICOM value separator
        ({"nickname": "J"}, "study.nickname"),
    ],
)
def test_bad_study_is_422_naming_the_field_not_the_value(client: TestClient, study: dict, field: str) -> None:
    resp = client.post("/v1/sessions", json={"calibration": calibration_doc(), "study": study}, headers=INGEST)
    assert resp.status_code == 422
    error = _error(resp)
    assert error["code"] == "invalid_study" and field in error["message"]
    value = next(iter(study.values()))
    assert value not in error["message"] or value == "J"


@pytest.mark.parametrize(
    ("calibration", "needle"),
    [
        (calibration_doc(colour="red"), "colour"),
        ({"camera_matrix": calibration_doc()["camera_matrix"], "px_per_mm": 8.0}, "image_size"),
        (calibration_doc(px_per_mm=-1), "px_per_mm"),
    ],
)
def test_bad_calibration_is_422_naming_field(client: TestClient, calibration: dict, needle: str) -> None:
    resp = client.post("/v1/sessions", json={"calibration": calibration}, headers=INGEST)
    assert resp.status_code == 422
    err = _error(resp)
    assert err["code"] == "invalid_calibration"
    assert needle in err["message"] and err["message"].startswith("calibration")


def test_unknown_body_field_is_422_and_bad_json_400(client: TestClient) -> None:
    resp = client.post("/v1/sessions", json={"calibration": calibration_doc(), "labl": "x"}, headers=INGEST)
    assert resp.status_code == 422
    err = _error(resp)
    assert err["code"] == "validation_error" and "labl" in err["message"]
    assert err["details"][0]["field"] == "labl"
    bad = client.post(
        "/v1/sessions", content=b'{"calibration": ', headers={**INGEST, "Content-Type": "application/json"}
    )
    assert bad.status_code == 400 and _error(bad)["code"] == "malformed_json"


def test_finish_sets_processing_queues_marker_and_closes_uploads(client: TestClient, session_id: str) -> None:
    assert upload(client, session_id, 0, frame_bytes(0)).status_code == 202
    resp = client.post(f"/v1/sessions/{session_id}/finish", headers=INGEST)
    assert resp.status_code == 202 and resp.json()["status"] == "processing"
    again = client.post(f"/v1/sessions/{session_id}/finish", headers=INGEST)
    assert again.status_code == 202  # idempotent
    state = client.get(f"/v1/sessions/{session_id}", headers=INGEST).json()
    assert state["status"] == "processing" and state["finished"] and state["frames_received"] == 1
    late = upload(client, session_id, 1, frame_bytes(1))
    assert late.status_code == 409 and _error(late)["code"] == "session_finished"
    forces = client.post(f"/v1/sessions/{session_id}/forces", json={"samples": [[0, 1, 1, 1, 1]]}, headers=INGEST)
    assert forces.status_code == 409
    r, prefix = client.app.state.redis, client.app.state.settings.redis_prefix  # type: ignore[attr-defined]
    entries = r.xrange(queue.frames_stream(prefix))
    kinds = [e[1][b"kind"] for e in entries]
    assert kinds == [b"frame", b"finish"]  # the marker comes after the session's frame jobs, once


def test_unknown_route_and_unhandled_error_use_error_shape(make_client: Callable[..., TestClient]) -> None:
    client = make_client()

    @client.app.get("/boom")  # type: ignore[attr-defined]
    def boom() -> None:
        raise RuntimeError("internal detail /secret/path")

    assert _error(client.get("/nope"))["code"] == "not_found"
    resp = client.get("/boom")
    assert resp.status_code == 500
    assert "secret" not in resp.text and _error(resp)["code"] == "internal_error"
    assert resp.headers["X-Request-ID"]


def test_request_id_and_logs_hold_no_patient_data(client: TestClient) -> None:
    label = "Patient Jane Q. Public, DOB 1970-01-01"
    buf = io.StringIO()
    handler = make_log_handler(buf)
    logger = logging.getLogger("veinmosaic")
    logger.addHandler(handler)
    try:
        resp = client.post(
            "/v1/sessions",
            json={"calibration": calibration_doc(), "label": label},
            headers={**INGEST, "X-Request-ID": "req-123"},
        )
        token = resp.json()["viewer_token"]
        client.get(f"/v1/sessions/{resp.json()['id']}", params={"token": token})
        upload(client, resp.json()["id"], 0, b"not an image")
    finally:
        logger.removeHandler(handler)
    assert resp.headers["X-Request-ID"] == "req-123"
    lines = [json.loads(line) for line in buf.getvalue().splitlines()]
    assert {"request_id": "req-123", "route": "/v1/sessions", "status": 201}.items() <= lines[1].items()
    assert any(d.get("route") == "/v1/sessions/{session_id}" for d in lines)
    assert any(d.get("status") == 415 for d in lines)
    text = buf.getvalue()
    assert "Jane" not in text and token not in text and "camera_matrix" not in text


def test_a_key_over_its_session_quota_gets_429_and_other_keys_are_unaffected(
    make_client: Callable[..., TestClient],
) -> None:
    """quota_sessions_per_key sessions per key and window; the next is 429 quota_exceeded with Retry-After (the
    window's end), nothing created; another key creates its own; a refused or failed create takes no unit."""
    client = make_client(quota_sessions_per_key=2, quota_window_s=3600)
    other = {"Authorization": "Bearer ingest-key-b-0123456789abcdef"}
    body = {"calibration": calibration_doc(), "label": "Jane Doe 1970"}
    bad = client.post("/v1/sessions", json={"calibration": calibration_doc(image_size=[0, 0])}, headers=INGEST)
    assert bad.status_code == 422  # refused before the quota: it takes none
    assert [client.post("/v1/sessions", json=body, headers=INGEST).status_code for _ in range(2)] == [201, 201]
    sessions_dir = client.app.state.settings.data_dir / "sessions"  # type: ignore[attr-defined]
    stored = sorted(p.name for p in sessions_dir.iterdir())
    refused = client.post("/v1/sessions", json=body, headers=INGEST)
    assert refused.status_code == 429, refused.text
    assert 1 <= int(refused.headers["Retry-After"]) <= 3600
    error = _error(refused)
    assert error["code"] == "quota_exceeded" and "2 sessions per 3600 s" in error["message"]
    assert "Jane" not in refused.text and "ingest-key" not in refused.text
    assert sorted(p.name for p in sessions_dir.iterdir()) == stored  # nothing created
    assert client.post("/v1/sessions", json=body, headers=other).status_code == 201  # its own quota
    assert client.post("/v1/sessions", json=body, headers=INGEST).status_code == 429


def test_the_session_quota_is_off_at_0_and_follows_the_window(make_client: Callable[..., TestClient]) -> None:
    unlimited = make_client(quota_sessions_per_key=0)
    body = {"calibration": calibration_doc()}
    assert {unlimited.post("/v1/sessions", json=body, headers=INGEST).status_code for _ in range(5)} == {201}
    client = make_client(quota_sessions_per_key=1, quota_window_s=1)
    assert client.post("/v1/sessions", json=body, headers=INGEST).status_code == 201
    refused = client.post("/v1/sessions", json=body, headers=INGEST)
    if refused.status_code == 201:  # the first landed at the very end of a 1 s window: the next window's unit
        refused = client.post("/v1/sessions", json=body, headers=INGEST)
    assert refused.status_code == 429 and refused.headers["Retry-After"] == "1"
    time.sleep(1.05)  # the next window
    assert client.post("/v1/sessions", json=body, headers=INGEST).status_code == 201
