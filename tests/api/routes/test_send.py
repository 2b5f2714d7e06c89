"""POST /v1/sessions/{id}/send (api/routes/send.py): an unknown destination is refused without naming the
configured ones (their names describe the hospital's network)."""

from __future__ import annotations

from typing import Any

from api_helpers import INGEST, calibration_doc


def test_an_unknown_destination_is_refused_without_listing_the_configured_ones(make_client: Any) -> None:
    destinations = {
        "radiology-main": {"dicomweb": "https://pacs.internal.example/dicom-web"},
        "oncology-archive": {"dimse": {"host": "10.1.2.3", "port": 11112, "called_ae": "ONCO"}},
    }
    client = make_client(pacs_destinations=destinations)
    sid = client.post("/v1/sessions", json={"calibration": calibration_doc()}, headers=INGEST).json()["id"]
    resp = client.post(f"/v1/sessions/{sid}/send", json={"destination": "nowhere"}, headers=INGEST)
    assert resp.status_code == 422 and resp.json()["error"]["code"] == "unknown_destination"
    assert resp.json()["error"]["message"] == "destination: not a configured PACS destination"
    for secret in ("radiology-main", "oncology-archive", "pacs.internal", "10.1.2.3", "ONCO"):
        assert secret not in resp.text
