"""`veinmosaic send RESULTS --to URL|HOST:PORT:AET|NAME`: a results folder's DICOM files to a real PACS (Orthanc)."""

from __future__ import annotations

import io
import json
import os
from pathlib import Path

import pytest
from pydicom import dcmread
from pydicom.uid import generate_uid

from cli.main import main
from tests.pacs_server import Orthanc, free_port
from tests.services.pacs.dicom_objects import PATIENT_ID, PATIENT_NAME, secondary_capture


@pytest.fixture(autouse=True)
def clean_env(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in list(os.environ):
        if name.startswith("VEINMOSAIC_"):
            monkeypatch.delenv(name)


def results_folder(root: Path) -> tuple[Path, str, dict[str, str]]:
    """Write a results folder as `veinmosaic export` leaves it (RESULTS/dicom/<layer>.dcm, other files beside);
    return it, its Study Instance UID and {file name: SOP Instance UID}."""
    results = root / "results"
    (results / "dicom").mkdir(parents=True)
    (results / "mosaic.json").write_text("{}")
    study_uid, series_uid = generate_uid(), generate_uid()
    uids = {}
    for number, layer in enumerate(("vein", "force", "coverage"), start=1):
        data = secondary_capture(study_uid, series_uid, number)
        (results / "dicom" / f"{layer}.dcm").write_bytes(data)
        uids[f"{layer}.dcm"] = str(dcmread(io.BytesIO(data)).SOPInstanceUID)
    return results, study_uid, uids


def test_send_by_dicomweb_stores_every_file(
    orthanc: Orthanc, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    results, study_uid, uids = results_folder(tmp_path)
    assert main(["send", str(results), "--to", orthanc.dicomweb_url]) == 0
    out = capsys.readouterr().out
    for name, uid in uids.items():
        assert f"stored {results / 'dicom' / name} ({uid})" in out
    assert "3/3 instance(s) stored at DICOMweb http://127.0.0.1" in out
    assert orthanc.study_instance_uids(study_uid) == set(uids.values())
    assert PATIENT_NAME not in out and PATIENT_ID not in out


def test_send_by_c_store_and_again_by_a_configured_name(
    orthanc: Orthanc, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    results, study_uid, _ = results_folder(tmp_path)
    target = f"{orthanc.host}:{orthanc.dicom_port}:{orthanc.aet}"
    assert main(["send", str(results), "--to", target, "--calling-ae", "VMCLI", "--timeout", "10"]) == 0
    assert f"3/3 instance(s) stored at DIMSE VMCLI->{orthanc.aet}@" in capsys.readouterr().out
    dests = {"pacs": {"dimse": {"host": orthanc.host, "port": orthanc.dicom_port, "called_ae": orthanc.aet}}}
    monkeypatch.setenv("VEINMOSAIC_PACS_DESTINATIONS", json.dumps(dests))
    assert main(["send", str(results), "--to", "pacs"]) == 0  # the same instances again: stored once
    assert "3/3 instance(s) stored at DIMSE VEINMOSAIC->" in capsys.readouterr().out
    assert orthanc.study_instance_count(study_uid) == 3


def test_a_failed_send_exits_1_and_says_why(
    orthanc: Orthanc, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    results, study_uid, _ = results_folder(tmp_path)
    assert main(["send", str(results), "--to", f"127.0.0.1:{free_port()}:{orthanc.aet}", "--timeout", "5"]) == 1
    assert "veinmosaic: send failed: DIMSE" in capsys.readouterr().err
    assert main(["send", str(results), "--to", f"{orthanc.host}:{orthanc.dicom_port}:ELSEWHERE"]) == 1
    assert "Called AE title not recognised" in capsys.readouterr().err
    assert orthanc.study_instance_count(study_uid) == 0


def test_an_instance_the_pacs_refuses_exits_1_naming_it(
    orthanc: Orthanc, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    results, study_uid, uids = results_folder(tmp_path)
    force = results / "dicom" / "force.dcm"
    ds = dcmread(force)
    del ds.SeriesInstanceUID  # Orthanc cannot file an instance without its series
    ds.save_as(force)
    assert main(["send", str(results), "--to", orthanc.dicomweb_url]) == 1
    out = capsys.readouterr().out
    assert f"REFUSED {force} ({uids['force.dcm']}): status 0x" in out and "2/3 instance(s) stored" in out
    assert orthanc.study_instance_uids(study_uid) == {uids["vein.dcm"], uids["coverage.dcm"]}


def test_a_folder_without_dicom_or_a_bad_target_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "empty").mkdir()
    assert main(["send", str(tmp_path / "empty"), "--to", "http://127.0.0.1:1/dw"]) == 2
    assert "no DICOM files (*.dcm)" in capsys.readouterr().err
    results, _, _ = results_folder(tmp_path)
    assert main(["send", str(results), "--to", "pacs.example:104"]) == 2
    assert "HOST:PORT:AET" in capsys.readouterr().err
    assert main(["send", str(results), "--to", "pacs.example:104:PACS", "--calling-ae", "X" * 17]) == 2
    assert "--calling-ae: AE title" in capsys.readouterr().err
    (results / "dicom" / "sheet.dcm").write_bytes(b"%PDF-1.4 not DICOM")
    assert main(["send", str(results), "--to", "pacs.example:104:PACS"]) == 2
    assert "sheet.dcm: not a DICOM Part 10 file" in capsys.readouterr().err
