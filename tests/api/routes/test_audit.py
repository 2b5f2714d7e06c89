"""The audit log (issue 8): who did what to which session, hash-chained, admin-queryable; and a label canary
that must never reach a log line or a response other than the owner's own session state."""

from __future__ import annotations

import json
import uuid
from collections.abc import Callable
from pathlib import Path

import httpx
import pytest
from api_helpers import INGEST, KEYS, auth, calibration_doc, frame_bytes, meta_json, upload
from fastapi.testclient import TestClient
from live_server import live_api

from api.auth import fingerprint
from services.store.audit import AuditLog

ADMIN = auth("admin-key-0123456789abcdef")
KEY = b"audit-test-key-0123456789abcdef-0123"


def test_chain_verifies_and_any_edit_breaks_it(tmp_path: Path) -> None:
    log = AuditLog(tmp_path / "audit.jsonl", KEY)
    for i in range(5):
        log.append({"ts": float(i), "actor": "key:x", "action": "session.read", "session": f"s{i}"})
    assert log.verify().ok and log.verify().records == 5
    other = AuditLog(tmp_path / "audit.jsonl", KEY)  # a second writer (another process) continues the chain
    other.append({"ts": 5.0, "actor": "key:y", "action": "session.read", "session": "s5"})
    log.append({"ts": 6.0, "actor": "key:x", "action": "session.read", "session": "s6"})
    assert log.verify().ok and log.verify().records == 7
    assert [r["session"] for r in log.query(limit=3)] == ["s6", "s5", "s4"]

    lines = (tmp_path / "audit.jsonl").read_text().splitlines()
    edited = lines.copy()
    edited[2] = edited[2].replace('"s2"', '"s9"')
    (tmp_path / "audit.jsonl").write_text("\n".join(edited) + "\n")
    bad = AuditLog(tmp_path / "audit.jsonl", KEY).verify()
    assert not bad.ok and bad.first_bad_line == 3 and "hash" in (bad.reason or "")
    (tmp_path / "audit.jsonl").write_text("\n".join(lines[:2] + lines[3:]) + "\n")  # a record deleted
    gone = AuditLog(tmp_path / "audit.jsonl", KEY).verify()
    assert not gone.ok and gone.first_bad_line == 3 and "prev" in (gone.reason or "")


def test_a_torn_last_line_is_cut_off_before_the_next_append(tmp_path: Path) -> None:
    path = tmp_path / "audit.jsonl"
    AuditLog(path, KEY).append({"ts": 1.0, "actor": "a", "action": "x"})
    with open(path, "ab") as fh:
        fh.write(b'{"ts": 2.0, "act')  # a crash mid-write (never acknowledged)
    log = AuditLog(path, KEY)
    log.append({"ts": 3.0, "actor": "a", "action": "y"})
    result = log.verify()
    assert result.ok and result.records == 2


def test_requests_are_audited_and_admins_query_them(client: TestClient, session_id: str) -> None:
    token = client.post("/v1/sessions", json={"calibration": calibration_doc()}, headers=INGEST).json()
    assert upload(client, session_id, 0, frame_bytes(0)).status_code == 202
    assert upload(client, session_id, 1, frame_bytes(1), t_s=0.1).status_code == 202
    assert client.get(f"/v1/sessions/{session_id}/path?format=csv", headers=INGEST).status_code == 200
    viewer = client.get(f"/v1/sessions/{token['id']}?token={token['viewer_token']}")
    assert viewer.status_code == 200
    assert client.get(f"/v1/sessions/{session_id}", headers=auth("ingest-key-b-0123456789abcdef")).status_code == 404

    assert client.get("/v1/audit", headers=INGEST).status_code == 403  # admin scope only
    assert client.get("/v1/audit").status_code == 401
    page = client.get("/v1/audit", params={"session": session_id, "limit": 50}, headers=ADMIN).json()
    actions = [(r["action"], r["actor"], r["status"]) for r in page["records"]]
    audit: AuditLog = client.app.state.audit  # type: ignore[attr-defined]
    owner = audit.key_actor(fingerprint("ingest-key-a-0123456789abcdef"))
    assert owner != f"key:{fingerprint('ingest-key-a-0123456789abcdef')[:16]}"  # keyed: not the key's plain hash
    assert ("frame.upload", owner, 202) in actions and actions.count(("frame.upload", owner, 202)) == 2
    assert ("path.export", owner, 200) in actions
    other = audit.key_actor(fingerprint("ingest-key-b-0123456789abcdef"))
    assert ("session.read", other, 404) in actions  # a refused look
    assert all(r["client"] and r["request_id"] for r in page["records"])
    by_token = client.get("/v1/audit", params={"session": token["id"]}, headers=ADMIN).json()["records"]
    assert ("session.read", f"token:{token['id']}") in [(r["action"], r["actor"]) for r in by_token]
    raw = (client.app.state.settings.data_dir / "audit" / "audit.jsonl").read_text()  # type: ignore[attr-defined]
    assert "ingest-key-a-0123456789abcdef" not in raw and token["viewer_token"] not in raw  # never a key or a token
    verified = client.get("/v1/audit/verify", headers=ADMIN).json()
    assert verified["ok"] and verified["records"] >= 8


def test_repeated_reads_are_coalesced_writes_are_not(client: TestClient, session_id: str) -> None:
    for _ in range(5):
        client.get(f"/v1/sessions/{session_id}", headers=INGEST)
    client.post(f"/v1/sessions/{session_id}/finish", headers=INGEST)
    client.post(f"/v1/sessions/{session_id}/finish", headers=INGEST)
    records = client.get("/v1/audit", params={"session": session_id}, headers=ADMIN).json()["records"]
    assert [r["action"] for r in records].count("session.read") == 1
    assert [r["action"] for r in records].count("session.finish") == 2


def test_the_services_audit_log_rotates_at_its_setting(make_client: Callable[..., TestClient]) -> None:
    # audit_max_bytes reaches the API's log: a 2000-byte cap rotates it within a few requests, the chain verified
    client = make_client(audit_max_bytes=2000)
    for i in range(12):
        client.post("/v1/sessions", json={"calibration": calibration_doc(), "label": f"l{i}"}, headers=INGEST)
    verified = client.get("/v1/audit/verify", headers=ADMIN).json()
    assert verified["ok"] and verified["files"] > 1, verified


@pytest.mark.slow
def test_label_canary_never_in_logs_or_foreign_responses(tmp_path: Path) -> None:
    marker = f"CANARY-{uuid.uuid4().hex}"
    accession = f"ACC{uuid.uuid4().hex[:13]}"  # an accession number is at most 16 characters (DICOM SH)
    study = {
        "patient_id": marker,
        "patient_name": f"{marker}^Jane",
        "accession_number": accession,
        "laterality": "L",
        "referring_physician": f"{marker}^Ref",
        "study_description": marker,
    }
    bodies: list[tuple[str, str]] = []
    with live_api(tmp_path, KEYS, log_level="DEBUG") as api:
        http = httpx.Client(base_url=api.base_url, timeout=10)

        def call(method: str, path: str, **kw: object) -> httpx.Response:
            resp = http.request(method, path, **kw)  # type: ignore[arg-type]
            bodies.append((f"{method} {path} -> {resp.status_code}", resp.text + json.dumps(dict(resp.headers))))
            return resp

        created = call(
            "POST",
            "/v1/sessions",
            json={"calibration": calibration_doc(), "label": marker, "study": study},
            headers=INGEST,
        )
        sid, token = created.json()["id"], created.json()["viewer_token"]
        for bad in (
            {"patient_sex": marker},
            {"patient_birth_date": marker},
            {"laterality": marker},
            {"patient_id": marker * 3},
            {"patient_name": f"{marker}\\x"},
        ):
            call("POST", "/v1/sessions", json={"calibration": calibration_doc(), "study": bad}, headers=INGEST)
        call("POST", "/v1/sessions", json={"calibration": {"bogus": marker}, "label": marker}, headers=INGEST)
        call("POST", "/v1/sessions", json={"calibration": calibration_doc(), "label": marker * 10}, headers=INGEST)
        for seq in range(3):
            files = {"image": (f"{marker}.png", frame_bytes(seq), "image/png")}
            call(
                "POST",
                f"/v1/sessions/{sid}/frames",
                files=files,
                data={"meta": meta_json(seq, seq * 0.1)},
                headers=INGEST,
            )
        call(
            "POST",
            f"/v1/sessions/{sid}/frames",
            files={"image": ("x", marker.encode())},
            data={"meta": marker},
            headers=INGEST,
        )
        call(
            "POST", f"/v1/sessions/{sid}/forces", json={"samples": [[0.0, 1, 1, 1, 1]], "note": marker}, headers=INGEST
        )
        call("POST", f"/v1/sessions/{sid}/forces", json={"samples": [[0.0, 1, 1, 1, 1]]}, headers=INGEST)
        owner_view = call("GET", f"/v1/sessions/{sid}", headers=INGEST)
        admin_view = call("GET", f"/v1/sessions/{sid}", headers=ADMIN)
        call("GET", f"/v1/sessions/{sid}?token={token}")
        call("GET", f"/v1/sessions/{sid}", headers=auth("ingest-key-b-0123456789abcdef"))
        for path in ("/path", "/path?format=csv", "/mosaic.json", "/report", "/mosaic.png"):
            call("GET", f"/v1/sessions/{sid}{path}", params={"token": token})
        call("POST", f"/v1/sessions/{sid}/finish", headers=INGEST)
        call("POST", f"/v1/sessions/{sid}/reprocess", json={"options": {"method": "best"}}, headers=INGEST)
        call("GET", "/v1/audit", params={"session": sid}, headers=ADMIN)
        call("GET", "/metrics")
        call("GET", "/openapi.json", headers=INGEST)
        http.close()
        logs = api.log_lines()
        audit_text = (api.data_dir / "audit" / "audit.jsonl").read_text()

    assert owner_view.json()["label"] == marker and admin_view.json()["label"] == marker  # the owner's own data
    assert owner_view.json()["study"] == study and admin_view.json()["study"] == study
    assert len(logs) > 20, "the API logged its requests"
    assert [line for line in logs if marker in line or accession in line] == []
    assert marker not in audit_text and accession not in audit_text
    leaked = [
        what
        for what, text in bodies
        if (marker in text or accession in text) and not what.startswith(f"GET /v1/sessions/{sid} -> 200")
    ]
    assert leaked == [], leaked
