"""DICOM export: every object of a session's study is valid (dciodvfy: no error), reads back with its pixels,
spacing and study context, renders the force layer in newtons with its own window, and has stable UIDs."""

from __future__ import annotations

import io
import shutil
import subprocess
from datetime import UTC, datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import pytest
from pydicom import dcmread
from pydicom.dataset import Dataset
from pydicom.pixels import apply_modality_lut, apply_rescale, apply_voi_lut

from services.core.inputs.calibration import parse_calibration
from services.core.inputs.scan import Scan, in_memory_loader
from services.core.inputs.study import StudyContext, parse_study
from services.core.mosaic.canvas import MosaicImage
from services.core.outputs.dicom_export import (
    ENCAPSULATED_PDF,
    EXPORT_LAYERS,
    SC_IMAGE,
    STUDY_OBJECTS,
    ExportInfo,
    export_layer,
    export_study,
    scan_digest,
    study_uid,
)

CET = timezone(timedelta(hours=1))
ACQUIRED = datetime(2025, 3, 4, 10, 20, 30, tzinfo=CET)
EXPORTED = datetime(2025, 3, 5, 8, 0, 0, tzinfo=UTC)  # 09:00 in the acquisition's zone
STUDY = StudyContext(
    patient_id="H-123",
    patient_name="Müller^Anna",
    patient_birth_date="1970-01-02",
    patient_sex="F",
    accession_number="ACC-77",
    laterality="L",
    referring_physician="Weber^Max",
    study_description="Breast NIR vein scan",
)
# a minimal valid PDF (one empty page): the report's bytes are the caller's, the export only wraps them
PDF = (
    b"%PDF-1.4\n1 0 obj<</Type/Catalog/Pages 2 0 R>>endobj\n2 0 obj<</Type/Pages/Kids[3 0 R]/Count 1>>endobj\n"
    b"3 0 obj<</Type/Page/Parent 2 0 R/MediaBox[0 0 612 792]>>endobj\n"
    b"4 0 obj<</CreationDate (D:20250305080000Z)>>endobj\ntrailer<</Root 1 0 R/Info 4 0 R>>\n%%EOF\n"
)
KNOWN_N = 15.0  # the force ramp's plateau: the window's centre


def _mosaic() -> MosaicImage:
    vein = np.random.default_rng(1).integers(0, 256, (60, 80), dtype=np.uint8)
    force = np.full((60, 80), np.nan, np.float32)
    force[10:50, 10:70] = np.linspace(0.0, 29.99, 60, dtype=np.float32)
    force[30:40, 40:50] = KNOWN_N
    coverage = np.where(np.isfinite(force), 4.0, 0.0).astype(np.float32)
    coverage[20:30, 20:30] = 300  # saturates at 255 in 8 bits
    return MosaicImage(vein, force, coverage, 8.0, (20.0, 30.0))


def _info(**kw: object) -> ExportInfo:
    args: dict[str, object] = {
        "key": "sess-1",
        "acquired": ACQUIRED,
        "exported": EXPORTED,
        "method": "best",
        "software": "9.8.7",
    }
    return ExportInfo(**{**args, **kw})  # type: ignore[arg-type]


def _read(data: bytes) -> Dataset:
    return dcmread(io.BytesIO(data))


def _study(info: ExportInfo, report: bool = True) -> dict[str, Dataset]:
    return {k: _read(v) for k, v in export_study(_mosaic(), info, PDF if report else None).items()}


# ----- validity: the reference validator ---------------------------------------------------------------------


def dciodvfy(data: bytes, tmp_path: Path, name: str) -> list[str]:
    """Return dciodvfy's output lines for one Part-10 object (dicom3tools' reference IOD validator)."""
    exe = shutil.which("dciodvfy")
    if exe is None:
        pytest.skip("dciodvfy (Debian package dicom3tools) is not installed: the IOD validation cannot run")
    path = tmp_path / f"{name}.dcm"
    path.write_bytes(data)
    run = subprocess.run([exe, str(path)], capture_output=True, text=True, timeout=60, check=False)
    return (run.stdout + run.stderr).splitlines()


@pytest.mark.parametrize(
    ("with_study", "acquired"),
    [(False, ACQUIRED), (True, ACQUIRED), (False, None)],
    ids=["no-study", "study", "no-study-no-date"],
)
def test_every_object_passes_dciodvfy_with_no_error(
    with_study: bool, acquired: datetime | None, tmp_path: Path
) -> None:
    files = export_study(_mosaic(), _info(study=STUDY if with_study else None, acquired=acquired), PDF)
    assert set(files) == set(STUDY_OBJECTS)
    for name, data in files.items():
        lines = dciodvfy(data, tmp_path, name)
        iod = "EncapsulatedPDF" if name == "report" else "SCImage"
        assert iod in lines, (name, lines)  # validated against the IOD meant, not a fallback
        errors = [line for line in lines if line.startswith("Error")]
        assert errors == [], (name, errors)
        if with_study:
            # with the study context even the DICOMDIR and laterality warnings go: nothing is left to say
            assert [line for line in lines if line.startswith("Warning")] == [], (name, lines)


# ----- content ------------------------------------------------------------------------------------------------


def test_every_layer_reads_back_with_pixels_spacing_and_one_study() -> None:
    m = _mosaic()
    ds = _study(_info())
    assert set(ds) == set(STUDY_OBJECTS)
    assert len({d.StudyInstanceUID for d in ds.values()}) == 1 and ds["vein"].StudyInstanceUID == study_uid("sess-1")
    assert len({d.SeriesInstanceUID for d in ds.values()}) == 4  # one series per object
    assert len({int(d.SeriesNumber) for d in ds.values()}) == 4
    for d in ds.values():
        assert d.file_meta.TransferSyntaxUID == "1.2.840.10008.1.2.1"
        assert d.StudyDate == "20250304" and d.StudyTime == "102030" and d.TimezoneOffsetFromUTC == "+0100"
        assert d.AcquisitionDateTime == "20250304102030"
        assert d.InstanceCreationDate == "20250305" and d.InstanceCreationTime == "090000"  # in the same zone
        assert d.Manufacturer == "veinmosaic" and d.ManufacturerModelName and d.SoftwareVersions == "9.8.7"
        assert d.StudyID == "sess-1"  # the session's id, as the sheet names it
    for layer in EXPORT_LAYERS:
        d = ds[layer]
        assert d.SOPClassUID == SC_IMAGE and "NumberOfFrames" not in d
        assert [float(v) for v in d.PixelSpacing] == [0.125, 0.125]  # mm: 1 / px_per_mm
        assert (d.Rows, d.Columns) == (60, 80)
        assert d.BodyPartExamined == "BREAST" and "Laterality" in d
        assert d.DateOfSecondaryCapture == "20250305" and d.TimeOfSecondaryCapture == "090000"
        for absent in ("FrameIncrementPointer", "PageNumberVector", "NominalScannedPixelSpacing"):
            assert absent not in d, (layer, absent)  # the dciodvfy errors of the multi-frame export
    assert np.array_equal(ds["vein"].pixel_array, m.vein)
    assert ds["force"].BitsStored == 16
    newtons = apply_rescale(ds["force"].pixel_array, ds["force"])
    finite = np.isfinite(m.force_n)
    np.testing.assert_allclose(newtons[finite], m.force_n[finite], atol=0.005)  # 0.01 N steps: half a step
    assert np.all(newtons[~finite] == 0)
    cov = ds["coverage"].pixel_array
    assert cov[15, 15] == 4 and cov[25, 25] == 255 and cov[0, 0] == 0
    report = ds["report"]
    assert report.SOPClassUID == ENCAPSULATED_PDF and report.Modality == "DOC"
    assert report.MIMETypeOfEncapsulatedDocument == "application/pdf"
    assert bytes(report.EncapsulatedDocument)[: len(PDF)] == PDF and report.EncapsulatedDocumentLength == len(PDF)


def test_force_layer_renders_in_newtons_not_black() -> None:
    d = _study(_info(), report=False)["force"]
    newtons = apply_modality_lut(d.pixel_array, d)
    shown = apply_voi_lut(newtons, d)  # the window applies after the rescale: it is in N
    y_max = (2 ** int(d.BitsStored) - 1) * float(d.RescaleSlope) + float(d.RescaleIntercept)  # pydicom's range
    grey = shown / y_max
    plateau = grey[30:40, 40:50]
    # 15 N is the window's centre (0..30 N): mid-grey. DICOM's LINEAR window (c - 0.5, w - 1: terms made for
    # integer stored values) puts it at 0.5 + 0.5 / 29 = 0.517 of the range; 0.03 allows that and nothing more
    assert np.all(np.abs(plateau - 0.5) < 0.03), plateau.min()
    scanned = np.isfinite(_mosaic().force_n)
    assert grey[scanned].max() > 0.95 and np.median(grey[scanned]) > 0.3  # the 0..30 N ramp spans the scale
    assert (float(d.WindowCenter), float(d.WindowWidth)) == (15.0, 30.0)
    (rwvm,) = d.RealWorldValueMappingSequence
    (unit,) = rwvm.MeasurementUnitsCodeSequence
    assert (unit.CodeValue, unit.CodingSchemeDesignator, unit.CodeMeaning) == ("N", "UCUM", "newton")
    assert rwvm.RealWorldValueSlope == pytest.approx(float(d.RescaleSlope)) and rwvm.RealWorldValueIntercept == 0
    assert (rwvm.RealWorldValueFirstValueMapped, rwvm.RealWorldValueLastValueMapped) == (0, 65535)


def test_vein_and_coverage_have_a_window_that_shows_them() -> None:
    ds = _study(_info(), report=False)
    for layer in ("vein", "coverage"):
        d = ds[layer]
        grey = apply_voi_lut(d.pixel_array, d) / (2 ** int(d.BitsStored) - 1)
        scanned = _mosaic().coverage > 0
        # not black, not one flat value: the scanned area spans at least half of the grey scale
        assert np.ptp(grey[scanned]) > 0.5 if layer == "vein" else grey[scanned].max() > 0.95, layer


def test_no_patient_identity_is_invented() -> None:
    for d in _study(_info()).values():
        for name in ("PatientName", "PatientID", "PatientBirthDate", "PatientSex", "AccessionNumber"):
            assert name in d and str(d.data_element(name).value or "") == "", name
        assert str(d.ReferringPhysicianName) == ""
        if d.SOPClassUID == SC_IMAGE:
            assert d.Laterality == ""  # Type 2C: present (the breast is paired), empty when unknown
        else:
            assert d.BurnedInAnnotation == "NO"


def test_the_study_context_is_written_as_given() -> None:
    for name, d in _study(_info(study=STUDY)).items():
        got = (str(d.PatientName), d.PatientID, d.PatientBirthDate, d.PatientSex, d.AccessionNumber)
        assert got == ("Müller^Anna", "H-123", "19700102", "F", "ACC-77"), name
        assert str(d.ReferringPhysicianName) == "Weber^Max" and d.StudyDescription == "Breast NIR vein scan"
        if name == "report":
            assert d.BurnedInAnnotation == "YES"  # the report names the patient when a context is given
        else:
            assert d.Laterality == "L"
    parsed = parse_study({"laterality": "R"})
    assert _read(export_layer(_mosaic(), "vein", _info(study=parsed))).Laterality == "R"


# ----- identity ------------------------------------------------------------------------------------------------


def _uids(files: dict[str, Dataset]) -> set[str]:
    return {d.StudyInstanceUID for d in files.values()} | {
        uid for d in files.values() for uid in (d.SeriesInstanceUID, d.SOPInstanceUID)
    }


def test_uids_follow_the_key_and_the_study_context() -> None:
    a, b = _study(_info()), _study(_info(exported=EXPORTED + timedelta(days=3)))
    for name in STUDY_OBJECTS:  # the same session exported again: the same UIDs
        for attr in ("StudyInstanceUID", "SeriesInstanceUID", "SOPInstanceUID"):
            assert getattr(a[name], attr) == getattr(b[name], attr), (name, attr)
    other = _study(_info(key="sess-2"))  # another session (or scan) shares none
    assert not _uids(a) & _uids(other)
    named = _study(_info(study=STUDY))  # patient data added: a study of its own, never one UID for two patients
    assert not _uids(a) & _uids(named)
    relabelled = _study(_info(study=StudyContext(**{**STUDY.to_dict(), "patient_id": "H-124"})))
    assert relabelled["vein"].StudyInstanceUID != named["vein"].StudyInstanceUID
    assert named["vein"].StudyInstanceUID == study_uid("sess-1", STUDY)
    v2 = _study(_info(results_version=2))  # a reprocessed version: new series and instances, the same study
    assert v2["force"].StudyInstanceUID == a["force"].StudyInstanceUID
    assert v2["force"].SeriesInstanceUID != a["force"].SeriesInstanceUID
    assert v2["force"].SOPInstanceUID != a["force"].SOPInstanceUID


def test_the_report_uid_ignores_the_pdf_render_date_but_not_its_content() -> None:
    info = _info()
    base = _read(export_study(_mosaic(), info, PDF)["report"]).SOPInstanceUID
    redated = PDF.replace(b"D:20250305080000Z", b"D:20260101000000Z")
    assert _read(export_study(_mosaic(), info, redated)["report"]).SOPInstanceUID == base
    changed = PDF.replace(b"612 792", b"792 612")
    assert _read(export_study(_mosaic(), info, changed)["report"]).SOPInstanceUID != base


def test_scan_digest_is_the_scans_content() -> None:
    calibration = parse_calibration(
        {"image_size": [32, 24], "camera_matrix": [[40, 0, 15.5], [0, 40, 11.5], [0, 0, 1]], "px_per_mm": 8.0}
    )
    frames = [np.full((24, 32), i, np.uint8) for i in range(3)]

    def scan(frames: list[np.ndarray], forces: float = 1.0) -> Scan:
        return Scan(
            calibration,
            np.arange(3),
            np.arange(3) * 0.1,
            np.arange(3) * 0.1,
            np.full((3, 4), forces),
            in_memory_loader(frames),
        )

    first = scan_digest(scan(frames))
    assert first == scan_digest(scan([f.copy() for f in frames]))  # content, not object identity
    assert first != scan_digest(scan([frames[0], frames[1], frames[1]]))  # one frame's pixels differ
    assert first != scan_digest(scan(frames, forces=1.5))  # the forces differ
    assert len(first) == 64


def test_bad_inputs_are_refused() -> None:
    with pytest.raises(ValueError, match="layer"):
        export_layer(_mosaic(), "pressure", _info())
    with pytest.raises(ValueError, match="timezone-aware"):
        _info(acquired=datetime(2025, 3, 4, 10, 20, 30))
    with pytest.raises(ValueError, match="key"):
        _info(key="")
    with pytest.raises(ValueError, match="PDF"):
        export_study(_mosaic(), _info(), b"not a pdf")
    with pytest.raises(ValueError, match="report"):
        export_study(_mosaic(), _info(), None, only=("report",))
    only = export_study(_mosaic(), _info(), None, only=("force",))
    assert set(only) == {"force"}


def test_dates_may_be_empty() -> None:
    d = _read(export_layer(_mosaic(), "coverage", _info(acquired=None)))
    assert d.StudyDate == "" and d.StudyTime == "" and d.AcquisitionDateTime == ""  # present, empty: unknown
    assert d.TimezoneOffsetFromUTC == "+0000"  # the export's zone: the only time written is the export's
