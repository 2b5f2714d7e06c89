"""The accuracy report's routes (api/routes/report.py, spec §4): POST a reference track, GET the report and its
plots. Served against a results version the workers' services code made (tests/api/results_bundle.py): the
route's RMSE equals the offline evaluation of the same path; a bad reference.csv is 422 naming its line."""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np
import pytest
from api_helpers import INGEST, auth, upload
from fastapi.testclient import TestClient
from results_bundle import Bundle, create_session, png

from services.core.inputs.scan import Scan
from services.core.outputs.evaluation import evaluate_path
from services.store.results_store import ResultsStore


def _error(resp: Any) -> dict[str, Any]:
    body = resp.json()
    assert set(body) == {"error"}
    return body["error"]


def _decode(content: bytes) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(content, np.uint8), cv2.IMREAD_UNCHANGED)


def reference_csv(truth_mm: np.ndarray, seqs: range | list[int] | None = None) -> str:
    """Return reference.csv text for the given seqs (all by default) from true positions in mm."""
    seqs = range(len(truth_mm)) if seqs is None else seqs
    lines = ["seq,x_mm,y_mm", *(f"{s},{truth_mm[s, 0]:.6f},{truth_mm[s, 1]:.6f}" for s in seqs)]
    return "\n".join(lines) + "\n"


def post_reference(client: TestClient, sid: str, text: str, **headers: str) -> Any:
    """POST a reference.csv body; return the response."""
    return client.post(
        f"/v1/sessions/{sid}/reference",
        content=text.encode(),
        headers={**INGEST, "Content-Type": "text/csv", **headers},
    )


def test_reference_report_and_plots(ready: tuple[TestClient, str, dict], bundle: Bundle) -> None:
    client, sid, created = ready
    assert client.get(f"/v1/sessions/{sid}/report", headers=INGEST).status_code == 404
    resp = post_reference(client, sid, reference_csv(bundle.truth_mm))
    assert resp.status_code == 200, resp.text
    report = resp.json()
    estimate = np.array([[r["x_mm"], r["y_mm"]] for r in bundle.rows], float)
    expected = evaluate_path(estimate, np.array([r["status"] == "ok" for r in bundle.rows]), bundle.truth_mm)
    # the route evaluates the same path against the same reference: equal up to the CSV's 6 decimals
    assert math.isclose(report["rmse_mm"], expected.rmse_mm, abs_tol=1e-5)
    assert report["rmse_mm"] < 2.0  # the short scan registers to about a millimetre or better
    assert expected.global_error is not None  # where the error lies, as the offline report.json has it
    # the same fit on the same frames; the CSV's 6 decimals move a ~50 mm path's scale by ~1e-6 %, 1e-3 % is loose
    assert math.isclose(report["global_error"]["scale_pct"], expected.global_error.scale_pct, abs_tol=1e-3)
    assert report["n_frames"] == 40 and report["registered_fraction"] == 1.0 and report["results_version"] == 1
    assert set(report["plots"]) == {"paths", "errors"}
    for url in report["plots"].values():
        plot = client.get(url, headers=INGEST)
        assert plot.status_code == 200 and plot.content.startswith(b"\x89PNG")
        assert _decode(plot.content).shape[0] > 200
        assert client.get(f"{url}&token={created['viewer_token']}").status_code == 200

    for url in (f"/v1/sessions/{sid}/report", report["plots"]["paths"]):
        assert client.get(url).status_code == 401
        assert client.get(url, headers=auth("ingest-key-b-0123456789abcdef")).status_code == 404
        assert client.get(url, headers=auth("admin-key-0123456789abcdef")).status_code == 200
    got = client.get(f"/v1/sessions/{sid}/report", headers=INGEST)
    assert got.status_code == 200 and got.json()["rmse_mm"] == report["rmse_mm"]
    assert client.get(f"/v1/sessions/{sid}/report?token={created['viewer_token']}").status_code == 200
    # the report follows the path: a new mosaic version makes GET /report evaluate again
    rs = ResultsStore(client.app.state.settings.data_dir)  # type: ignore[attr-defined]
    rs.write_mosaic_meta(sid, 1, {**bundle.doc, "version": 7})
    assert client.get(f"/v1/sessions/{sid}/report", headers=INGEST).json()["mosaic_version"] == 7


def test_partial_reference_compares_known_rows(ready: tuple[TestClient, str, dict], bundle: Bundle) -> None:
    client, sid, _ = ready
    resp = post_reference(client, sid, reference_csv(bundle.truth_mm, list(range(0, 40, 3))))
    assert resp.status_code == 200 and resp.json()["n_with_reference"] == 14 and resp.json()["n_compared"] == 14


@pytest.mark.parametrize(
    ("body", "needle"),
    [
        ("seq,x,y\n0,0,0\n", "line 1"),
        ("seq,x_mm,y_mm\n0,0,0\n1,abc,2\n", "line 3"),
        ("seq,x_mm,y_mm\n0,0,0\n0,1,1\n", "line 3"),
        ("seq,x_mm,y_mm\n0,0\n", "line 2"),
        ("seq,x_mm,y_mm\n0,0,nan\n", "line 2"),
        ("seq,x_mm,y_mm\n999,0,0\n", "seq 999"),
        ("seq,x_mm,y_mm\n", "no data rows"),
    ],
)
def test_bad_reference_is_422_naming_the_line(ready: tuple[TestClient, str, dict], body: str, needle: str) -> None:
    client, sid, _ = ready
    resp = post_reference(client, sid, body)
    assert resp.status_code == 422, resp.text
    err = _error(resp)
    assert err["code"] == "invalid_reference" and needle in err["message"]
    assert client.get(f"/v1/sessions/{sid}/report", headers=INGEST).status_code == 404  # nothing stored


def test_reference_media_type_auth_and_not_ready(
    ready: tuple[TestClient, str, dict], client: TestClient, short_scan: Scan, bundle: Bundle
) -> None:
    _, sid, created = ready
    text = reference_csv(bundle.truth_mm)
    assert post_reference(client, sid, text, **{"Content-Type": "application/json"}).status_code == 415
    assert post_reference(client, sid, text, Authorization="Bearer ingest-key-b-0123456789abcdef").status_code == 404
    assert post_reference(client, sid, text, Authorization="Bearer view-key-0123456789abcdef").status_code == 403
    assert post_reference(client, sid, text, Authorization=f"Bearer {created['viewer_token']}").status_code == 401
    bad_utf8 = client.post(
        f"/v1/sessions/{sid}/reference",
        content=b"seq,x_mm,y_mm\n0,\xff,0\n",
        headers={**INGEST, "Content-Type": "text/csv"},
    )
    assert bad_utf8.status_code == 422 and "UTF-8" in _error(bad_utf8)["message"]
    fresh = create_session(client, short_scan)["id"]
    resp = post_reference(client, fresh, text.splitlines()[0] + "\n")
    assert resp.status_code == 422  # a bad file is named even before there is a path
    resp = post_reference(client, fresh, "seq,x_mm,y_mm\n")
    assert resp.status_code == 422
    no_frame = post_reference(client, fresh, "seq,x_mm,y_mm\n0,0,0\n")
    # seq 0 is not a frame of a session without uploads: named as such
    assert no_frame.status_code == 422 and "seq 0" in _error(no_frame)["message"]
    assert upload(client, fresh, 0, png(short_scan.frame(0))).status_code == 202
    not_ready = post_reference(client, fresh, "seq,x_mm,y_mm\n0,0,0\n")
    assert not_ready.status_code == 409 and _error(not_ready)["code"] == "not_ready"
