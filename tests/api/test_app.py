"""api/app.py's request middleware: an unhandled error in a route is answered 500 and logged with its frames only."""

from __future__ import annotations

import io
import json
import logging

import pytest
from api_helpers import INGEST, calibration_doc
from fastapi.testclient import TestClient

from services.log_format import make_log_handler

CANARY = "CANARY^Zz9"  # a marked study value: it must appear in no log line


def test_an_unhandled_error_quoting_a_study_value_leaves_no_trace_in_the_logs(
    client: TestClient, monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    created = client.post(
        "/v1/sessions",
        json={"calibration": calibration_doc(), "label": CANARY, "study": {"patient_name": CANARY}},
        headers=INGEST,
    )
    assert created.status_code == 201, created.text
    sid = created.json()["id"]

    def session_extent(results: object, session_id: str) -> None:
        try:
            raise KeyError(CANARY)  # a library's lookup quoting the value it choked on
        except KeyError as exc:
            raise ValueError(f"cannot read the study of {CANARY!r}") from exc

    monkeypatch.setattr("api.routes.sessions.session_extent", session_extent)
    buf = io.StringIO()
    handler = make_log_handler(buf)  # the production formatter, on the logger the app's handler sits on
    logger = logging.getLogger("veinmosaic")
    logger.addHandler(handler)
    try:
        resp = client.get(f"/v1/sessions/{sid}", headers=INGEST)
    finally:
        logger.removeHandler(handler)
    assert resp.status_code == 500 and resp.json()["error"]["code"] == "internal_error"
    assert CANARY not in resp.text
    lines = [json.loads(line) for line in buf.getvalue().splitlines()]
    (logged,) = [doc for doc in lines if doc["msg"].startswith("unhandled error")]
    assert "in session_extent" in logged["exc"] and "test_app.py" in logged["exc"]  # the frames are there
    assert "\nKeyError" in logged["exc"] and "\nValueError" in logged["exc"]  # and the types, chain included
    out, err = capfd.readouterr()
    for text in (buf.getvalue(), out, err):
        assert CANARY not in text and "Zz9" not in text
