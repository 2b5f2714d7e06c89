"""A real PACS for tests: Debian's Orthanc with its DICOMweb plugin, on free ports, with its own storage.

The session-scoped fixture `orthanc` (tests/conftest.py) starts one Orthanc for the whole test run (it takes a
moment to start) and stops it at the end; it skips with the reason when Orthanc or the plugin is missing
(scripts/test.sh installs them when root). Tests share it, so each should use its own Study/SOP Instance UIDs
and count what it sent through the query helpers, e.g. `orthanc.study_instance_uids(study_uid)`.

    def test_x(orthanc: Orthanc) -> None:
        send_objects(DicomWebDestination(orthanc.dicomweb_url), objs, 10.0)
        assert orthanc.study_instance_uids(study_uid) == {...}
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest

ORTHANC = Path("/usr/sbin/Orthanc")
DICOMWEB_PLUGIN = Path("/usr/share/orthanc/plugins/libOrthancDicomWeb.so")
ORTHANC_AET = "VMTESTPACS"
READY_TIMEOUT_S = 30.0


@dataclass
class Orthanc:
    """A running Orthanc: its REST URL, DICOMweb root, DICOM port and AE title, process and log file."""

    http_url: str
    dicom_port: int
    aet: str
    proc: subprocess.Popen[bytes]
    log_path: Path
    host: str = "127.0.0.1"

    @property
    def dicomweb_url(self) -> str:
        """Return the DICOMweb base URL (STOW-RS at <it>/studies)."""
        return f"{self.http_url}/dicom-web"

    def get(self, path: str, **params: Any) -> Any:
        """GET a REST path of Orthanc's API and return its JSON."""
        resp = httpx.get(f"{self.http_url}{path}", params=params, timeout=10.0)
        resp.raise_for_status()
        return resp.json()

    def get_bytes(self, path: str) -> bytes:
        """GET a REST path of Orthanc's API and return the body (e.g. an instance's /rendered PNG)."""
        resp = httpx.get(f"{self.http_url}{path}", timeout=30.0)
        resp.raise_for_status()
        return resp.content

    def find(self, level: str, **query: str) -> list[dict[str, Any]]:
        """Return the expanded resources at `level` (Patient, Study, Series, Instance) matching DICOM tags."""
        body = {"Level": level, "Query": query, "Expand": True}
        resp = httpx.post(f"{self.http_url}/tools/find", json=body, timeout=10.0)
        resp.raise_for_status()
        return resp.json()

    def study_instance_uids(self, study_instance_uid: str) -> set[str]:
        """Return the SOP Instance UIDs Orthanc holds in the study (empty when it holds no such study)."""
        studies = self.find("Study", StudyInstanceUID=study_instance_uid)
        uids: set[str] = set()
        for study in studies:
            for instance in self.get(f"/studies/{study['ID']}/instances"):
                uids.add(instance["MainDicomTags"]["SOPInstanceUID"])
        return uids

    def study_instance_count(self, study_instance_uid: str) -> int:
        """Return how many instances Orthanc holds in the study (the count its index keeps, not distinct UIDs)."""
        studies = self.find("Study", StudyInstanceUID=study_instance_uid)
        return sum(len(self.get(f"/studies/{s['ID']}/instances")) for s in studies)

    def instance_tags(self, sop_instance_uid: str) -> dict[str, Any]:
        """Return the simplified tags ({"PatientID": ...}) of the one instance with that SOP Instance UID."""
        found = self.find("Instance", SOPInstanceUID=sop_instance_uid)
        assert len(found) == 1, f"{len(found)} instances with SOP Instance UID {sop_instance_uid}"
        return self.get(f"/instances/{found[0]['ID']}/simplified-tags")

    def log_lines(self) -> list[str]:
        """Return what Orthanc wrote to its log so far."""
        return self.log_path.read_text(errors="replace").splitlines()


def orthanc_missing() -> str | None:
    """Return why Orthanc cannot run here (a skip reason), or None when it and its DICOMweb plugin are installed."""
    if not os.access(ORTHANC, os.X_OK):
        return f"Orthanc not installed ({ORTHANC}; Debian package orthanc, installed by scripts/test.sh when root)"
    if not DICOMWEB_PLUGIN.exists():
        return f"Orthanc's DICOMweb plugin not installed ({DICOMWEB_PLUGIN}; Debian package orthanc-dicomweb)"
    return None


def orthanc_config(root: Path, http_port: int, dicom_port: int, aet: str = ORTHANC_AET) -> dict[str, Any]:
    """Return an Orthanc configuration: loopback only, no authentication, DICOMweb at /dicom-web/, own storage."""
    return {
        "Name": "veinmosaic-test-pacs",
        "StorageDirectory": str(root / "storage"),
        "IndexDirectory": str(root / "storage"),
        "TemporaryDirectory": str(root / "tmp"),
        "Plugins": [str(DICOMWEB_PLUGIN)],
        "DicomWeb": {"Enable": True, "Root": "/dicom-web/", "EnableWado": False},
        "HttpServerEnabled": True,
        "HttpPort": http_port,
        "RemoteAccessAllowed": False,  # loopback clients only
        "AuthenticationEnabled": False,
        "HttpDescribeErrors": True,
        "OrthancExplorerEnabled": False,
        "WebDavEnabled": False,
        "HttpThreadsCount": 8,
        "DicomServerEnabled": True,
        "DicomAet": aet,
        "DicomPort": dicom_port,
        "DicomCheckCalledAet": True,  # Orthanc accepts any called AE title unless told to check it
        "DicomAlwaysAllowStore": True,
        "DicomAlwaysAllowEcho": True,
        "DicomModalities": {},
        "DicomThreadsCount": 2,
        "DicomAssociationCloseDelay": 0,
        "SaveJobs": False,
        "ConcurrentJobs": 1,
        "MetricsEnabled": False,
        "StorageCompression": False,
        "OverwriteInstances": False,  # the default: a re-sent instance is kept once
        "StableAge": 3600,
    }


def free_port() -> int:
    """Return a TCP port free on 127.0.0.1 right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _wait_until_ready(url: str, proc: subprocess.Popen[bytes]) -> None:
    """Block until GET url answers 200; RuntimeError when the process exits first or time runs out."""
    deadline = time.monotonic() + READY_TIMEOUT_S
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"Orthanc exited early (code {proc.returncode})")
        try:
            if httpx.get(url, timeout=2.0).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.1)
    raise RuntimeError(f"{url} did not answer 200 within {READY_TIMEOUT_S:.0f} s")


def _stop(proc: subprocess.Popen[bytes], timeout_s: float) -> None:
    """SIGTERM the process, then SIGKILL it when it is not gone within timeout_s."""
    if proc.poll() is None:
        proc.terminate()
    try:
        proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


@contextmanager
def run_orthanc(root: Path, attempts: int = 3) -> Iterator[Orthanc]:
    """Start Orthanc under `root` on free ports (retried when a port was taken meanwhile); stop it afterwards."""
    root.mkdir(parents=True, exist_ok=True)
    (root / "tmp").mkdir(exist_ok=True)
    last_error = ""
    for attempt in range(attempts):
        http_port, dicom_port = free_port(), free_port()
        config = root / f"orthanc-{attempt}.json"
        config.write_text(json.dumps(orthanc_config(root, http_port, dicom_port), indent=2))
        log_path = root / f"orthanc-{attempt}.log"
        with open(log_path, "ab") as out:
            proc = subprocess.Popen([str(ORTHANC), "--no-jobs", str(config)], stdout=out, stderr=subprocess.STDOUT)
        server = Orthanc(f"http://127.0.0.1:{http_port}", dicom_port, ORTHANC_AET, proc, log_path)
        try:
            _wait_until_ready(f"{server.http_url}/system", proc)
        except RuntimeError as exc:
            _stop(proc, 5.0)
            last_error = f"{exc}:\n" + "\n".join(server.log_lines()[-15:])
            continue
        try:
            yield server
        finally:
            _stop(proc, 10.0)
        return
    raise RuntimeError(f"Orthanc did not start in {attempts} attempts: {last_error}")


@pytest.fixture(scope="session")
def orthanc(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Orthanc]:
    """A running Orthanc (DICOMweb and DIMSE) shared by the session's tests; skipped when not installed."""
    reason = orthanc_missing()
    if reason:
        pytest.skip(reason)
    with run_orthanc(tmp_path_factory.mktemp("orthanc")) as server:
        yield server
