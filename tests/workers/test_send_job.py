"""Send jobs for real (issue 16): `veinmosaic serve`'s launcher (API, a worker process, Redis) sends a session to a
real Orthanc by DICOMweb STOW-RS and by DIMSE C-STORE; the PACS files it under the study's patient, accession
and laterality, every image renders with its own window, and re-sending stores the same instances. An
unreachable destination is retried with back-off and then fails; every attempt is in the audit log. A job's error
names the destination by its configured name, never its address."""

from __future__ import annotations

import json
import os
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from cli.client import ApiError, VeinmosaicClient, upload_scan_folder
from cli.launcher import Service, free_port
from services.pacs.destinations import DicomWebDestination, DimseDestination
from services.settings import Settings
from services.store.audit import AuditLog
from services.store.scan_folder import write_scan_folder
from services.store.secrets import audit_key_bytes
from tests.pacs_server import Orthanc
from tests.sim_cache import simulated
from workers.stages.send import public_error

STUDY = {
    "patient_id": "VM-TEST-0001",
    "patient_name": "Send^Testy",
    "patient_birth_date": "1970-05-06",
    "patient_sex": "F",
    "accession_number": "ACC-SEND-1",
    "laterality": "L",
    "referring_physician": "Ref^Doctor",
    "study_description": "NIR vein mapping",
}
OBJECTS = 4  # vein, force, coverage, report
# A rendered image is "not black" when a visible share of it is lit: the mosaic and both maps cover most of their
# canvas, so 5 % of pixels above grey level 40 fails only for an image rendered (near) black.
LIT_LEVEL, LIT_SHARE = 40, 0.05


@pytest.fixture(scope="module")
def served(orthanc: Orthanc, tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Service, VeinmosaicClient]]:
    """A service (1 worker) whose destinations are the test Orthanc (web, dimse) and a closed port (dead)."""
    tmp = tmp_path_factory.mktemp("send")
    key = f"k-{uuid.uuid4().hex}"
    destinations = {
        "web": {"dicomweb": orthanc.dicomweb_url},
        "dimse": {"dimse": {"host": orthanc.host, "port": orthanc.dicom_port, "called_ae": orthanc.aet}},
        "dead": {"dicomweb": f"http://127.0.0.1:{free_port()}/dicom-web"},
    }
    worker = {"pacs_max_attempts": 2, "pacs_retry_first_s": 0.3, "pacs_wait_s": 0.5}
    env = {
        "VEINMOSAIC_API_KEYS": json.dumps({key: ["ingest", "view"]}),
        "VEINMOSAIC_REDIS_PREFIX": f"vmtest{uuid.uuid4().hex[:8]}:",
        "VEINMOSAIC_PACS_DESTINATIONS": json.dumps(destinations),
        "VEINMOSAIC_PACS_TIMEOUT_S": "5",
        "VEINMOSAIC_PACS_AUTO_SEND": json.dumps(["web"]),  # every session goes to "web" once done
        "VEINMOSAIC_WORKER_CONFIG": json.dumps(worker),
        "VEINMOSAIC_LOG_LEVEL": "WARNING",
    }
    service = Service(tmp / "data", port=free_port(), workers=1, redis_url=os.environ.get("REDIS_URL"), extra_env=env)
    with service:
        client = VeinmosaicClient(service.base_url, key)
        yield service, client
        client.close()


def audit_log(service: Service) -> AuditLog:
    """Return the service's audit log with its key (the service's environment: this one's, data_dir/secret)."""
    path = service.data_dir / "audit" / "audit.jsonl"
    return AuditLog(path, audit_key_bytes(Settings(data_dir=service.data_dir)))


def wait_for_study(orthanc: Orthanc, accession: str, series: int, timeout_s: float) -> dict:
    """Return Orthanc's study of this accession once it holds `series` series (it shows from its first object on)."""
    deadline = time.monotonic() + timeout_s
    while True:
        found = orthanc.find("Study", AccessionNumber=accession)
        if len(found) == 1 and len(found[0]["Series"]) >= series:
            return found[0]
        assert time.monotonic() < deadline, f"the auto-send never reached Orthanc in full: {len(found)} studies"
        time.sleep(0.2)


@pytest.mark.slow
def test_a_session_reaches_orthanc_by_both_protocols_filed_and_rendered(
    served: tuple[Service, VeinmosaicClient], orthanc: Orthanc, tmp_path: Path
) -> None:
    service, client = served
    folder = tmp_path / "scan"
    write_scan_folder(simulated("short", 1), folder)
    sid = upload_scan_folder(client, folder, "send test", study=STUDY)  # finishing it queued the auto-send
    assert client.wait_done(sid, timeout_s=240)["status"] == "done"
    study = wait_for_study(orthanc, STUDY["accession_number"], OBJECTS, timeout_s=120)
    assert study["PatientMainDicomTags"]["PatientID"] == STUDY["patient_id"]
    assert study["PatientMainDicomTags"]["PatientName"] == STUDY["patient_name"]
    assert len(study["Series"]) == OBJECTS
    series = [orthanc.get(f"/series/{s}") for s in study["Series"]]
    images = [s for s in series if s["MainDicomTags"].get("Modality") != "DOC"]
    assert len(images) == 3
    image_tags = [orthanc.get(f"/instances/{s['Instances'][0]}/simplified-tags") for s in images]
    assert {t.get("Laterality") for t in image_tags} == {"L"}
    assert {t.get("BodyPartExamined") for t in image_tags} == {"BREAST"}
    assert {t.get("AccessionNumber") for t in image_tags} == {STUDY["accession_number"]}
    instances = [i for s in series for i in s["Instances"]]
    assert len(instances) == OBJECTS
    for s in images:
        (instance,) = s["Instances"]
        png = orthanc.get_bytes(f"/instances/{instance}/rendered")  # Orthanc applies the object's own window
        img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_GRAYSCALE)
        lit = float(np.mean(img > LIT_LEVEL))
        assert lit > LIT_SHARE, f"{s['MainDicomTags'].get('SeriesDescription')}: {lit:.3f} lit"

    dimse_job = client.send(sid, "dimse")  # the same objects by C-STORE
    assert client.request("GET", f"/v1/jobs/{dimse_job}").json()["kind"] == "send"
    dimse = client.wait_job(dimse_job, timeout_s=120)
    assert dimse["state"] == "done" and dimse["done"] == OBJECTS, dimse
    again = client.wait_job(client.send(sid, "web"), timeout_s=120)  # and again: idempotent
    assert again["state"] == "done" and again["done"] == again["total"] == OBJECTS
    (same,) = orthanc.find("Study", AccessionNumber=STUDY["accession_number"])
    assert sorted(same["Series"]) == sorted(study["Series"])
    assert sum(len(orthanc.get(f"/series/{s}")["Instances"]) for s in same["Series"]) == OBJECTS

    records = audit_log(service).query(session=sid, limit=100)
    sends = [r for r in records if r.get("action") == "pacs.send"]
    assert sorted((r["destination"], r["outcome"]) for r in sends) == [
        ("dimse", "done"),
        ("web", "done"),
        ("web", "done"),
    ]
    requests = [r for r in records if r.get("action") == "pacs.send.request"]
    assert len(requests) == 2  # the auto-send is not a request
    # the worker names the job's key as the API does (the same keyed id)
    assert {r["actor"] for r in sends} == {requests[0]["actor"]} and all(r["instances"] == OBJECTS for r in sends)
    assert audit_log(service).verify().ok  # the API's and the worker's records make one keyed chain
    audit_text = (service.data_dir / "audit" / "audit.jsonl").read_text()
    assert STUDY["patient_name"] not in audit_text and STUDY["accession_number"] not in audit_text


@pytest.mark.slow
def test_an_unreachable_destination_is_retried_then_fails(
    served: tuple[Service, VeinmosaicClient], tmp_path: Path
) -> None:
    service, client = served
    folder = tmp_path / "scan"
    write_scan_folder(simulated("short", 1), folder)
    sid = upload_scan_folder(client, folder, "send test")
    assert client.wait_done(sid, timeout_s=240)["status"] == "done"
    job = client.wait_job(client.send(sid, "dead"), timeout_s=120)
    assert job["state"] == "failed" and job["attempts"] == 2, job
    assert "unreachable" in (job["error"] or "")
    records = audit_log(service).query(session=sid, limit=100)
    outcomes = [r["outcome"] for r in records if r.get("action") == "pacs.send" and r["destination"] == "dead"]
    assert sorted(outcomes) == ["failed", "retry"]
    with pytest.raises(ApiError) as refused:
        client.send(sid, "nowhere")
    assert refused.value.status == 422 and refused.value.code == "unknown_destination"


def test_job_errors_name_the_destination_never_its_address() -> None:
    web = DicomWebDestination("https://user:pw@pacs.internal.example:8443/dicom-web")
    dimse = DimseDestination("10.1.2.3", 11112, "ONCO")
    for destination, name, address in ((web, "radiology", "pacs.internal.example"), (dimse, "onco", "10.1.2.3")):
        raw = f"destination unreachable after 8 attempts: {destination.describe()}: cannot connect (ConnectError)"
        shown = public_error(raw, destination, name)
        assert address not in shown and "11112" not in shown and "8443" not in shown and "pw" not in shown
        assert shown == f"destination unreachable after 8 attempts: destination {name!r}: cannot connect (ConnectError)"
        stray = public_error(f"the destination refused: no route to {address}", destination, name)
        assert address not in stray  # the address is removed wherever it stands
    assert len(public_error("x" * 1000, web, "radiology")) == 300
