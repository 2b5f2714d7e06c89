"""Outputs a hospital archives over HTTP: GET export.dcm?layer= (DICOM) and the one-page sheet.png / sheet.pdf.

The results are a known fixture written with ResultsStore as a worker writes them (mosaic.png, layers.npz,
mosaic.json, path.json): a 20-frame straight path at 8 px/mm with one lost and one rejected frame, a force
ramp of 0..29.9 N and a coverage of 1..4 frames with an unscanned corner. So every DICOM pixel is known
exactly, and the sheet's text (read from the PDF's content streams) can be checked for what it must say.
"""

from __future__ import annotations

import io
import re
from importlib import metadata
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from api_helpers import INGEST, auth
from fastapi.testclient import TestClient
from pydicom import dcmread
from pydicom.pixels import apply_rescale

from api.auth import make_viewer_token
from services.core.inputs.study import parse_study
from services.core.mosaic.canvas import MosaicImage
from services.core.outputs.dicom_export import ENCAPSULATED_PDF, SC_IMAGE, study_uid
from services.core.path_rows import PathRow
from services.store.results_store import ResultsStore
from services.store.version_state import VersionState
from tests.pdf_text import pdf_text
from tests.services.core.outputs.test_dicom_export import dciodvfy

PX_PER_MM = 8.0
H, W = 120, 200  # px: 15 x 25 mm
N_FRAMES = 20
LOST, REJECTED = 5, 12
LAYERS = ("vein", "force", "coverage")
OBJECTS = (*LAYERS, "report")  # export.dcm?layer=: the layers and the one-page report
STUDY = {
    "patient_id": "H-4711",
    "patient_name": "Doe^Jane",
    "patient_birth_date": "1970-05-06",
    "patient_sex": "F",
    "accession_number": "ACC-0815",
    "laterality": "R",
    "referring_physician": "Who^Doctor",
    "study_description": "NIR breast vein scan",
}


def known_mosaic() -> MosaicImage:
    """Return a mosaic whose layers are known pixel by pixel (force in N, NaN and coverage 0 where unscanned)."""
    yy, xx = np.mgrid[0:H, 0:W]
    vein = ((xx * 7 + yy * 3) % 256).astype(np.uint8)
    coverage = (1 + (xx * 4) // W).astype(np.float32)  # 1..4 frames, left to right
    coverage[:30, :40] = 0  # a corner never scanned
    force = np.where(coverage > 0, np.round(xx * 29.9 / (W - 1), 2), np.nan).astype(np.float32)
    return MosaicImage(vein, force, coverage, PX_PER_MM, (20.0, 60.0))


def path_rows() -> list[PathRow]:
    """Return the path: frames 1 mm apart along x, frame LOST lost and frame REJECTED rejected."""
    nan = float("nan")
    rows = []
    for seq in range(N_FRAMES):
        status = "lost" if seq == LOST else "rejected" if seq == REJECTED else "ok"
        placed = status == "ok"
        reason = {"lost": "few_inliers", "rejected": "blur"}.get(status, "")
        x = float(seq) if placed else nan
        rows.append(PathRow(seq, 0.1 * seq, x, 0.0 if placed else nan, 0.0 if placed else nan, 5.0, 0.0, 0.0, 1.0,
                            80 if placed else 0, status, reason))  # fmt: skip
    return rows


def install_known(client: TestClient, sid: str) -> MosaicImage:
    """Write results version 1 of `sid` (as a worker does when the version completes); return its mosaic."""
    rs = ResultsStore(client.app.state.settings.data_dir)  # type: ignore[attr-defined]
    mosaic = known_mosaic()
    rs.ensure_version(sid, 1, {"method": "best"})
    rs.write_mosaic_images(sid, 1, mosaic)
    rs.write_mosaic_meta(sid, 1, {**mosaic.meta(), "version": 1, "results_version": 1, "status": "done"})
    rs.write_path(sid, 1, path_rows())
    rs.write_state(sid, 1, VersionState(cursor=N_FRAMES, fence=1, finished=True, lost=[LOST], rejected=[REJECTED]))
    return mosaic


def create(client: TestClient, key: dict[str, str] = INGEST, study: dict[str, str] | None = None) -> dict[str, Any]:
    """Create a session (64 x 48 frames at 8 px/mm), with a study context when given; return the 201 body."""
    calibration = {
        "image_size": [64, 48],
        "camera_matrix": [[80.0, 0.0, 31.5], [0.0, 80.0, 23.5], [0.0, 0.0, 1.0]],
        "px_per_mm": PX_PER_MM,
    }
    body: dict[str, Any] = {"calibration": calibration, "label": "Jane Doe 1970"}
    if study is not None:
        body["study"] = study
    resp = client.post("/v1/sessions", json=body, headers=key)
    assert resp.status_code == 201, resp.text
    return resp.json()


@pytest.fixture
def ready(client: TestClient) -> tuple[TestClient, dict[str, Any], MosaicImage]:
    """Return (client, create body, mosaic) of a session whose finished results are installed."""
    created = create(client)
    return client, created, install_known(client, created["id"])


def _error(resp: Any) -> dict[str, Any]:
    body = resp.json()
    assert set(body) == {"error"}, body
    return body["error"]


# ----- DICOM ------------------------------------------------------------------------------------------------------


def test_export_each_layer_is_dicom_with_known_pixels(ready: tuple[TestClient, dict, MosaicImage]) -> None:
    client, created, mosaic = ready
    sid = created["id"]
    got = {}
    for layer in LAYERS:
        resp = client.get(f"/v1/sessions/{sid}/export.dcm?layer={layer}", headers=INGEST)
        assert resp.status_code == 200, (layer, resp.text)
        assert resp.headers["content-type"] == "application/dicom"
        assert resp.headers["X-Results-Version"] == "1"
        assert "no-store" in resp.headers["Cache-Control"] and "private" in resp.headers["Cache-Control"]
        assert resp.headers["Content-Disposition"] == f'attachment; filename="{layer}.dcm"'
        assert resp.content[128:132] == b"DICM"  # a Part-10 file: preamble then the magic
        got[layer] = dcmread(io.BytesIO(resp.content))
    # the default layer is the vein mosaic
    default = client.get(f"/v1/sessions/{sid}/export.dcm", headers=INGEST)
    assert default.status_code == 200
    again = dcmread(io.BytesIO(default.content))  # the same results export with the same UIDs (not bytes: the
    assert again.SOPInstanceUID == got["vein"].SOPInstanceUID  # secondary capture time is the export's)
    assert again.SeriesInstanceUID == got["vein"].SeriesInstanceUID
    for ds in got.values():
        assert [float(v) for v in ds.PixelSpacing] == [0.125, 0.125]  # mm: 1 / 8 px/mm
        assert (ds.Rows, ds.Columns) == (H, W)
        assert ds.StudyInstanceUID == study_uid(sid)  # one study per session
        assert ds.SoftwareVersions == metadata.version("veinmosaic")  # the installed package's, read by the store
        assert re.fullmatch(r"\d{8}", ds.StudyDate) and ds.AcquisitionDateTime.startswith(ds.StudyDate)
        for name in ("PatientName", "PatientID", "PatientBirthDate", "PatientSex"):
            # the session's label is not patient identity: nothing is invented or copied into the file
            assert str(ds.data_element(name).value or "") == "", name
        assert "Jane" not in str(ds) and "1970" not in ds.PatientBirthDate
    assert len({ds.SeriesInstanceUID for ds in got.values()}) == 3  # one series per layer
    assert all(ds.SOPClassUID == SC_IMAGE for ds in got.values())  # single-frame Secondary Capture
    assert np.array_equal(got["vein"].pixel_array, mosaic.vein)
    force = got["force"]
    assert force.BitsStored == 16 and (float(force.WindowCenter), float(force.WindowWidth)) == (15.0, 30.0)  # N
    newtons = apply_rescale(force.pixel_array, force)
    scanned = mosaic.coverage > 0
    # 0.01 N steps (RescaleSlope), half a step of rounding; 0 where never scanned
    np.testing.assert_allclose(newtons[scanned], mosaic.force_n[scanned], atol=0.005 + 1e-6)
    assert np.all(newtons[~scanned] == 0)
    assert np.array_equal(got["coverage"].pixel_array, mosaic.coverage.astype(np.uint8))


def test_export_bad_layer_is_a_clear_422(ready: tuple[TestClient, dict, MosaicImage]) -> None:
    client, created, _ = ready
    for bad in ("mosaic.png", "FORCE", "", "../force"):
        resp = client.get(f"/v1/sessions/{created['id']}/export.dcm", params={"layer": bad}, headers=INGEST)
        assert resp.status_code == 422, (bad, resp.text)
        assert resp.headers["content-type"].startswith("application/json")
        err = _error(resp)
        # names the parameter that was wrong and what is allowed; the bad value is not echoed
        assert err["code"] == "validation_error" and "layer" in err["message"], err
        assert all(f"'{name}'" in err["message"] for name in OBJECTS), err


def test_export_and_sheet_before_results_are_404_not_ready(client: TestClient) -> None:
    sid = create(client)["id"]
    for route in ("/export.dcm?layer=force", "/sheet.png", "/sheet.pdf"):
        resp = client.get(f"/v1/sessions/{sid}{route}", headers=INGEST)
        assert resp.status_code == 404, route
        assert _error(resp)["code"] == "not_ready", route


AUTH_ROUTES = (
    "/export.dcm?layer=vein",
    "/export.dcm?layer=force",
    "/export.dcm?layer=coverage",
    "/export.dcm?layer=report",
    "/sheet.png",
    "/sheet.pdf",
)


def test_export_and_sheet_auth(ready: tuple[TestClient, dict, MosaicImage]) -> None:
    client, created, _ = ready
    sid, token = created["id"], created["viewer_token"]
    other = create(client, key=auth("ingest-key-b-0123456789abcdef"))
    expired = make_viewer_token(client.app.state.token_secrets, sid, 10, now=1000.0)  # type: ignore[attr-defined]
    for route in AUTH_ROUTES:
        url = f"/v1/sessions/{sid}{route}"
        sep = "&" if "?" in url else "?"
        assert client.get(url).status_code == 401, route  # no key
        assert client.get(url, headers=auth("no-such-key")).status_code == 401, route
        assert client.get(url, headers=auth("ingest-key-b-0123456789abcdef")).status_code == 404, (
            route
        )  # another key's session
        assert client.get(url, headers=auth("view-key-0123456789abcdef")).status_code == 404, (
            route
        )  # view scope, not the owner
        assert client.get(f"{url}{sep}token={other['viewer_token']}").status_code == 401, route  # another session
        assert client.get(f"{url}{sep}token={expired}").status_code == 401, route
        assert client.get(url, headers=auth("admin-key-0123456789abcdef")).status_code == 200, route
        assert client.get(url, headers=INGEST).status_code == 200, route
        assert client.get(f"{url}{sep}token={token}").status_code == 200, route  # the viewer's link
    # a refusal says nothing about the session (no patient data in errors)
    refused = client.get(f"/v1/sessions/{sid}/sheet.pdf", headers=auth("ingest-key-b-0123456789abcdef"))
    assert _error(refused)["code"] == "not_found" and "Jane" not in refused.text


def test_export_files_the_study_context_and_the_report(client: TestClient, tmp_path: Path) -> None:
    created = create(client, study=STUDY)
    sid = created["id"]
    install_known(client, sid)
    got = {}
    for name in OBJECTS:
        resp = client.get(f"/v1/sessions/{sid}/export.dcm?layer={name}", headers=INGEST)
        assert resp.status_code == 200, (name, resp.text)
        assert resp.headers["Content-Disposition"] == f'attachment; filename="{name}.dcm"'
        errors = [line for line in dciodvfy(resp.content, tmp_path, name) if line.startswith("Error")]
        assert errors == [], (name, errors)  # the reference validator: every object is valid
        got[name] = dcmread(io.BytesIO(resp.content))
    context = parse_study(STUDY)
    for name, ds in got.items():
        assert ds.StudyInstanceUID == study_uid(sid, context), name  # one study: the session with its context
        assert (str(ds.PatientName), ds.PatientID, ds.PatientBirthDate, ds.PatientSex) == (
            "Doe^Jane",
            "H-4711",
            "19700506",
            "F",
        ), name
        assert ds.AccessionNumber == "ACC-0815" and str(ds.ReferringPhysicianName) == "Who^Doctor", name
        assert ds.StudyDescription == "NIR breast vein scan" and ds.TimezoneOffsetFromUTC == "+0000", name
    assert all(got[layer].Laterality == "R" and got[layer].BodyPartExamined == "BREAST" for layer in LAYERS)
    report = got["report"]
    assert report.SOPClassUID == ENCAPSULATED_PDF and report.MIMETypeOfEncapsulatedDocument == "application/pdf"
    sheet = client.get(f"/v1/sessions/{sid}/sheet.pdf", headers=INGEST)
    document = bytes(report.EncapsulatedDocument)[: report.EncapsulatedDocumentLength]  # less the even-length pad
    assert document.startswith(b"%PDF") and pdf_text(document) == pdf_text(sheet.content)  # the sheet, wrapped
    again = dcmread(io.BytesIO(client.get(f"/v1/sessions/{sid}/export.dcm?layer=report", headers=INGEST).content))
    assert again.SOPInstanceUID == report.SOPInstanceUID  # re-exported: the same instance, not a duplicate
    assert len({ds.SeriesInstanceUID for ds in got.values()}) == 4
    # a viewer link never sees patient data: its objects carry none, so they are not the patient's study
    token = created["viewer_token"]
    for name in ("vein", "report"):
        viewed = client.get(f"/v1/sessions/{sid}/export.dcm?layer={name}&token={token}")
        assert viewed.status_code == 200, name
        ds = dcmread(io.BytesIO(viewed.content))
        assert ds.PatientID == "" and str(ds.PatientName) == "" and ds.AccessionNumber == "", name
        assert ds.StudyInstanceUID == study_uid(sid) != got[name].StudyInstanceUID, name
        assert b"H-4711" not in viewed.content and b"Doe^Jane" not in viewed.content, name
        if name == "report":  # the wrapped sheet's drawn text (its streams are compressed) names no patient either
            drawn = pdf_text(bytes(ds.EncapsulatedDocument))
            assert "H-4711" not in drawn and "Doe" not in drawn and ds.BurnedInAnnotation == "NO", drawn
    assert "H-4711" in pdf_text(document) and report.BurnedInAnnotation == "YES"  # the owner's sheet names them


# ----- the one-page sheet -----------------------------------------------------------------------------------------


def test_sheet_png_and_pdf(ready: tuple[TestClient, dict, MosaicImage]) -> None:
    client, created, _ = ready
    sid = created["id"]
    png = client.get(f"/v1/sessions/{sid}/sheet.png", headers=INGEST)
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    assert png.headers["X-Results-Version"] == "1" and "no-store" in png.headers["Cache-Control"]
    img = cv2.imdecode(np.frombuffer(png.content, np.uint8), cv2.IMREAD_COLOR)
    assert img is not None and img.shape[0] > img.shape[1] > 1000  # one A4 portrait page, print resolution
    assert np.ptp(img.reshape(-1, 3), axis=1).max() > 100  # colour scales: not a grey page
    pdf = client.get(f"/v1/sessions/{sid}/sheet.pdf", headers=INGEST)
    assert pdf.status_code == 200 and pdf.headers["content-type"] == "application/pdf"
    assert pdf.content.startswith(b"%PDF") and "no-store" in pdf.headers["Cache-Control"]
    assert len(re.findall(rb"/Type\s*/Page\b", pdf.content)) == 1  # one page
    text = " ".join(pdf_text(pdf.content).split())  # wrapped lines joined
    assert sid in text and "Results version 1" in text and "Method best" in text  # the session key, never the label
    assert "Jane" not in text and "Accession number not given" in text  # no study: nothing invented
    assert "Scan date and time 20" in text and " UTC" in text  # the session's creation, with its zone
    assert "(N)" in text and "newtons (N)" in text, text  # the force map's colour scale is in N
    assert "frames (linear" in text and "95th percentile" in text and "never scanned" in text  # the coverage scale
    assert "20 mm" in text or "10 mm" in text or "5 mm" in text  # a scale bar
    assert f"received: {N_FRAMES}" in text and f"placed (registered): {N_FRAMES - 2}" in text, text
    assert "lost: 1 (few inliers 1)" in text and "rejected: 1 (blur 1)" in text  # the lost-frame summary
    assert "no reference track: not measured" in text
    assert "WARNING: 2 of 20 frames (10.0 %) were not placed" in text  # the 5 % rule, on the page


def test_sheet_identifies_the_patient_for_the_owner_only(client: TestClient) -> None:
    created = create(client, study=STUDY)
    sid = created["id"]
    install_known(client, sid)
    owner = " ".join(pdf_text(client.get(f"/v1/sessions/{sid}/sheet.pdf", headers=INGEST).content).split())
    assert "Accession number ACC-0815" in owner and "Patient ID H-4711" in owner and "Doe, Jane" in owner
    assert "Laterality right breast" in owner and "Birth date 1970-05-06" in owner and "Who, Doctor" in owner
    # a viewer link never sees patient data: the same page with the study's fields not given
    viewed = client.get(f"/v1/sessions/{sid}/sheet.pdf?token={created['viewer_token']}")
    assert viewed.status_code == 200
    text = " ".join(pdf_text(viewed.content).split())
    assert sid in text and "Accession number not given" in text and "Laterality not given" in text
    assert not any(value in text for value in ("ACC-0815", "H-4711", "Jane", "1970-05-06", "Doctor"))


def test_sheet_shows_accuracy_with_a_reference(ready: tuple[TestClient, dict, MosaicImage]) -> None:
    client, created, _ = ready
    sid = created["id"]
    # a reference 2 % longer than the path and 0.5 mm beside it: an error to show, whatever is aligned first
    lines = ["seq,x_mm,y_mm", *(f"{s},{1.02 * s:.4f},0.5" for s in range(N_FRAMES))]
    resp = client.post(
        f"/v1/sessions/{sid}/reference",
        content=("\n".join(lines) + "\n").encode(),
        headers={**INGEST, "Content-Type": "text/csv"},
    )
    assert resp.status_code == 200, resp.text
    pdf = client.get(f"/v1/sessions/{sid}/sheet.pdf", headers=INGEST)
    assert pdf.status_code == 200
    text = " ".join(pdf_text(pdf.content).split())
    assert "no reference track" not in text
    # (no "fi" in what is looked for: the PDF draws it as one ligature glyph, which pdf_text does not map back)
    assert re.search(r"RMSE \d+\.\d{3} mm", text) and "max error" in text and "drift / path length" in text, text
    assert "reference track" in text  # the reference track is drawn (and named) over the mosaic with the estimate


def test_outputs_are_made_once_and_again_when_their_inputs_change(
    ready: tuple[TestClient, dict, MosaicImage], monkeypatch: pytest.MonkeyPatch
) -> None:
    from services.store import session_export

    client, created, _ = ready
    sid, token = created["id"], created["viewer_token"]
    renders: list[tuple[str, bool]] = []
    render = session_export.render_sheet

    def counted(store: Any, rs: Any, sid: str, version: int, fmt: str, with_study: bool = True) -> bytes:
        renders.append((fmt, with_study))
        return render(store, rs, sid, version, fmt, with_study)

    monkeypatch.setattr(session_export, "render_sheet", counted)
    first = client.get(f"/v1/sessions/{sid}/sheet.pdf", headers=INGEST)
    again = client.get(f"/v1/sessions/{sid}/sheet.pdf", headers=INGEST)
    assert first.status_code == again.status_code == 200 and first.content == again.content
    report = client.get(f"/v1/sessions/{sid}/export.dcm?layer=report", headers=INGEST)
    assert report.status_code == 200 and renders == [("pdf", True)]  # the report object holds the kept sheet
    vein = [client.get(f"/v1/sessions/{sid}/export.dcm?layer=vein", headers=INGEST).content for _ in range(2)]
    assert vein[0] == vein[1]  # the same bytes, export time included
    assert client.get(f"/v1/sessions/{sid}/sheet.pdf?token={token}").status_code == 200  # without the study: its own
    assert renders == [("pdf", True), ("pdf", False)]
    assert "no reference track" in " ".join(pdf_text(first.content).split())

    lines = ["seq,x_mm,y_mm", *(f"{s},{1.02 * s:.4f},0.5" for s in range(N_FRAMES))]
    posted = client.post(
        f"/v1/sessions/{sid}/reference",
        content="\n".join(lines).encode(),
        headers={**INGEST, "Content-Type": "text/csv"},
    )
    assert posted.status_code == 200
    newer = client.get(f"/v1/sessions/{sid}/sheet.pdf", headers=INGEST)
    assert renders[-1] == ("pdf", True) and len(renders) == 3  # a new reference: made again, with its accuracy
    assert re.search(r"RMSE \d+\.\d{3} mm", " ".join(pdf_text(newer.content).split()))
    outputs = ResultsStore(client.app.state.settings.data_dir).output_path(sid, 1, "x").parent  # type: ignore[attr-defined]
    names = sorted(p.name for p in outputs.iterdir())
    assert len([n for n in names if n.startswith("sheet.pdf.study.")]) == 1  # the stale one was removed
    assert all(STUDY["patient_id"].lower() not in n and "doe" not in n for n in names)  # names are digests
