"""Sending DICOM objects to a real PACS (Orthanc, tests/pacs_server.py) by STOW-RS and by C-STORE."""

from __future__ import annotations

import io
import json
import logging
import threading
import time
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import pytest
from pydicom import dcmread
from pydicom.uid import ExplicitVRLittleEndian, ImplicitVRLittleEndian, generate_uid

from services.pacs.cstore import presentation_contexts
from services.pacs.destinations import DicomWebDestination, DimseDestination
from services.pacs.objects import read_objects
from services.pacs.send import PacsRejected, PacsUnreachable, SendOutcome, send_objects
from tests.pacs_server import Orthanc, free_port
from tests.services.pacs.dicom_objects import PATIENT_ID, PATIENT_NAME, secondary_capture, study

TIMEOUT_S = 10.0
KINDS = ["dicomweb", "dimse"]


def destination(orthanc: Orthanc, kind: str) -> DicomWebDestination | DimseDestination:
    """Return the Orthanc fixture as a destination of that kind."""
    if kind == "dicomweb":
        return DicomWebDestination(orthanc.dicomweb_url)
    return DimseDestination(orthanc.host, orthanc.dicom_port, orthanc.aet, "VMTEST")


def rewrite(data: bytes, **changes: Any) -> bytes:
    """Return the object with attributes changed (None deletes one)."""
    ds = dcmread(io.BytesIO(data))
    for keyword, value in changes.items():
        if value is None:
            delattr(ds, keyword)
        else:
            setattr(ds, keyword, value)
    if "SOPClassUID" in changes:
        ds.file_meta.MediaStorageSOPClassUID = changes["SOPClassUID"]
    buf = io.BytesIO()
    ds.save_as(buf)
    return buf.getvalue()


def no_patient_data(*texts: str) -> bool:
    """Return whether none of the texts names the test patient."""
    return not any(marker in text for text in texts for marker in (PATIENT_NAME, "Canary", PATIENT_ID))


@pytest.mark.parametrize("kind", KINDS)
def test_the_instances_are_found_in_orthanc(orthanc: Orthanc, kind: str) -> None:
    study_uid, objects, uids = study(2)
    outcome = send_objects(destination(orthanc, kind), objects, TIMEOUT_S)
    assert isinstance(outcome, SendOutcome) and outcome.ok
    assert outcome.stored == tuple(uids) and dict(outcome.failed) == {} and 0 < outcome.elapsed_s < TIMEOUT_S
    assert orthanc.study_instance_uids(study_uid) == set(uids)
    assert orthanc.study_instance_count(study_uid) == 2
    tags = orthanc.instance_tags(uids[1])
    assert (tags["PatientID"], tags["InstanceNumber"], tags["SOPClassUID"]) == (
        PATIENT_ID,
        "2",
        "1.2.840.10008.5.1.4.1.1.7",
    )


@pytest.mark.parametrize("kind", KINDS)
def test_resending_stores_the_same_instances(orthanc: Orthanc, kind: str) -> None:
    study_uid, objects, uids = study(3)
    first = send_objects(destination(orthanc, kind), objects, TIMEOUT_S)
    again = send_objects(destination(orthanc, kind), objects, TIMEOUT_S)
    other = send_objects(destination(orthanc, "dimse" if kind == "dicomweb" else "dicomweb"), objects, TIMEOUT_S)
    assert first.stored == again.stored == other.stored == tuple(uids) and again.ok and other.ok
    assert orthanc.study_instance_count(study_uid) == 3
    assert orthanc.study_instance_uids(study_uid) == set(uids)


def test_c_store_carries_mixed_transfer_syntaxes_in_one_association(orthanc: Orthanc) -> None:
    study_uid, series_uid = generate_uid(), generate_uid()
    objects = [
        secondary_capture(study_uid, series_uid, 1, ExplicitVRLittleEndian),
        secondary_capture(study_uid, series_uid, 2, ImplicitVRLittleEndian),
    ]
    contexts = presentation_contexts(read_objects(objects))
    assert contexts == [
        ("1.2.840.10008.5.1.4.1.1.7", [ExplicitVRLittleEndian, ImplicitVRLittleEndian]),
        ("1.2.840.10008.5.1.4.1.1.7", [ImplicitVRLittleEndian, ExplicitVRLittleEndian]),
    ]
    outcome = send_objects(destination(orthanc, "dimse"), objects, TIMEOUT_S)
    assert outcome.ok and outcome.sent == 2
    assert orthanc.study_instance_count(study_uid) == 2


@pytest.mark.parametrize("kind", KINDS)
def test_an_instance_the_pacs_cannot_store_is_reported_and_the_rest_stored(orthanc: Orthanc, kind: str) -> None:
    study_uid, objects, uids = study(3)
    objects[1] = rewrite(objects[1], SeriesInstanceUID=None)  # Orthanc refuses an instance without a series
    outcome = send_objects(destination(orthanc, kind), objects, TIMEOUT_S)
    assert not outcome.ok
    assert outcome.stored == (uids[0], uids[2]) and outcome.sent == 2 and list(outcome.failed) == [uids[1]]
    assert "status 0x" in outcome.failed[uids[1]]  # Orthanc: 0xC000 by STOW-RS, 0xA700 by C-STORE
    assert orthanc.study_instance_uids(study_uid) == {uids[0], uids[2]}


@pytest.mark.parametrize("kind", KINDS)
def test_nothing_stored_is_a_rejection_with_the_reasons(
    orthanc: Orthanc, kind: str, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG)
    study_uid, objects, uids = study(2)
    refused = [rewrite(o, SeriesInstanceUID=None) for o in objects]
    with pytest.raises(PacsRejected) as info:
        send_objects(destination(orthanc, kind), refused, TIMEOUT_S)
    assert info.value.outcome is not None and info.value.outcome.stored == ()
    assert set(info.value.outcome.failed) == set(uids) and uids[0] in str(info.value)
    assert orthanc.study_instance_count(study_uid) == 0
    assert no_patient_data(str(info.value), caplog.text)


def test_a_sop_class_the_pacs_does_not_take_is_refused_by_c_store(orthanc: Orthanc) -> None:
    study_uid, objects, uids = study(2)
    private = rewrite(objects[1], SOPClassUID="1.2.826.0.1.3680043.8.498.1.99")  # not a storage SOP class
    outcome = send_objects(destination(orthanc, "dimse"), [objects[0], private], TIMEOUT_S)
    assert outcome.stored == (uids[0],) and "presentation context" in outcome.failed[uids[1]]
    with pytest.raises(PacsRejected, match="none of the objects' SOP classes"):
        send_objects(destination(orthanc, "dimse"), [private], TIMEOUT_S)
    assert orthanc.study_instance_uids(study_uid) == {uids[0]}


@pytest.mark.parametrize("kind", KINDS)
def test_a_closed_port_is_unreachable(kind: str, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG)
    port = free_port()  # nothing listens there
    dest = DicomWebDestination(f"http://127.0.0.1:{port}/dicom-web") if kind == "dicomweb" else None
    dest = dest or DimseDestination("127.0.0.1", port, "ANY")
    _, objects, _ = study(1)
    started = time.monotonic()
    with pytest.raises(PacsUnreachable) as info:
        send_objects(dest, objects, TIMEOUT_S)
    assert time.monotonic() - started < TIMEOUT_S / 2  # refused at once, not timed out
    assert f"127.0.0.1:{port}" in str(info.value) and no_patient_data(str(info.value), caplog.text)
    assert "Errno" not in str(info.value)  # the network library's own text is left out, only its type named


def test_a_wrong_called_ae_title_is_rejected(orthanc: Orthanc, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG)
    study_uid, objects, _ = study(1)
    dest = DimseDestination(orthanc.host, orthanc.dicom_port, "NOT_THE_PACS")
    with pytest.raises(PacsRejected, match="Called AE title not recognised") as info:
        send_objects(dest, objects, TIMEOUT_S)  # Orthanc checks it (DicomCheckCalledAet in the fixture)
    assert "NOT_THE_PACS" in str(info.value) and no_patient_data(str(info.value), caplog.text)
    assert orthanc.study_instance_count(study_uid) == 0


def test_a_missing_stow_service_is_rejected(orthanc: Orthanc) -> None:
    _, objects, _ = study(1)
    with pytest.raises(PacsRejected, match="HTTP 404"):
        send_objects(DicomWebDestination(f"{orthanc.http_url}/no-dicom-web"), objects, TIMEOUT_S)


def test_objects_that_are_not_dicom_are_refused_before_sending(orthanc: Orthanc) -> None:
    study_uid, objects, _ = study(1)
    with pytest.raises(ValueError, match="object 1: not a DICOM Part 10 file"):
        send_objects(destination(orthanc, "dicomweb"), [objects[0], b"PNG not DICOM"], TIMEOUT_S)
    with pytest.raises(ValueError, match="given twice"):
        send_objects(destination(orthanc, "dicomweb"), [objects[0], objects[0]], TIMEOUT_S)
    assert orthanc.study_instance_count(study_uid) == 0
    assert send_objects(destination(orthanc, "dimse"), [], TIMEOUT_S).stored == ()


# A scripted STOW-RS server for the answers Orthanc does not give (202, 409, 5xx, a slow PACS)


class _Scripted(BaseHTTPRequestHandler):
    answer: tuple[int, dict[str, Any] | None, float] = (200, None, 0.0)
    received: list[bytes] = []  # noqa: RUF012

    def do_POST(self) -> None:
        status, body, delay = self.answer
        self.received.append(self.rfile.read(int(self.headers["Content-Length"])))
        time.sleep(delay)
        data = json.dumps(body).encode() if body is not None else b""
        self.send_response(status)
        self.send_header("Content-Type", "application/dicom+json")
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        self.wfile.write(data)

    def log_message(self, format: str, *args: Any) -> None:
        pass


@pytest.fixture
def scripted() -> Iterator[tuple[str, type[_Scripted]]]:
    """A STOW-RS server on a free port whose answer the test sets: (status, DICOM JSON body, delay s)."""
    handler = type("Handler", (_Scripted,), {"received": []})
    server = ThreadingHTTPServer(("127.0.0.1", 0), handler)
    server.daemon_threads, server.block_on_close = True, False  # a slow answer still sleeping is not waited for
    thread = threading.Thread(target=server.serve_forever, args=(0.05,), daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{server.server_address[1]}/dw", handler
    server.shutdown()
    server.server_close()


def stow_response(stored: list[str], failed: dict[str, int]) -> dict[str, Any]:
    """Return a Store Instances Response in DICOM JSON."""

    def item(uid: str, reason: int | None = None) -> dict[str, Any]:
        doc: dict[str, Any] = {"00081155": {"vr": "UI", "Value": [uid]}}
        if reason is not None:
            doc["00081197"] = {"vr": "US", "Value": [reason]}
        return doc

    return {
        "00081199": {"vr": "SQ", "Value": [item(u) for u in stored]},
        "00081198": {"vr": "SQ", "Value": [item(u, r) for u, r in failed.items()]},
    }


def test_a_partial_stow_answer_names_what_failed(scripted: tuple[str, type[_Scripted]]) -> None:
    url, handler = scripted
    _, objects, uids = study(3)
    handler.answer = (202, stow_response([uids[0]], {uids[1]: 0xA900}), 0.0)
    outcome = send_objects(DicomWebDestination(url, {"Authorization": "Bearer abc"}), objects, TIMEOUT_S)
    assert outcome.stored == (uids[0],)
    assert outcome.failed == {
        uids[1]: "status 0xA900 (data set does not match SOP class)",
        uids[2]: "HTTP 202 without a status for this instance",
    }
    body = handler.received[0]
    assert body.count(b"Content-Type: application/dicom\r\n") == 3 and all(o in body for o in objects)


def test_a_409_stow_answer_is_a_rejection(scripted: tuple[str, type[_Scripted]]) -> None:
    url, handler = scripted
    _, objects, uids = study(2)
    handler.answer = (409, stow_response([], {uids[0]: 0xC000, uids[1]: 0x0122}), 0.0)
    with pytest.raises(PacsRejected) as info:
        send_objects(DicomWebDestination(url), objects, TIMEOUT_S)
    assert info.value.outcome is not None
    assert info.value.outcome.failed[uids[1]] == "status 0x0122 (SOP class not supported)"


@pytest.mark.parametrize(("status", "error"), [(503, PacsUnreachable), (429, PacsUnreachable), (401, PacsRejected)])
def test_a_stow_status_maps_to_retry_or_not(
    scripted: tuple[str, type[_Scripted]], status: int, error: type[Exception]
) -> None:
    url, handler = scripted
    handler.answer = (status, {"detail": f"patient {PATIENT_NAME}"}, 0.0)  # a body is never quoted
    with pytest.raises(error) as info:
        send_objects(DicomWebDestination(url), study(1)[1], TIMEOUT_S)
    assert f"HTTP {status}" in str(info.value) and no_patient_data(str(info.value))


def test_a_slow_pacs_times_out_as_unreachable(scripted: tuple[str, type[_Scripted]]) -> None:
    url, handler = scripted
    handler.answer = (200, None, 1.5)
    started = time.monotonic()
    with pytest.raises(PacsUnreachable, match=r"no answer within 0\.3 s"):
        send_objects(DicomWebDestination(url), study(1)[1], 0.3)
    assert time.monotonic() - started < 1.4
