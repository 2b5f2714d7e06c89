"""DICOM export: each layer is a valid Part-10 Secondary Capture that reads back with its pixels and spacing."""

from __future__ import annotations

import io
from datetime import UTC, datetime

import numpy as np
import pytest
from pydicom import dcmread
from pydicom.pixels import apply_rescale

from services.core.dicom_export import (
    EXPORT_LAYERS,
    MF_GRAY_BYTE_SC,
    MF_GRAY_WORD_SC,
    ExportInfo,
    PatientInfo,
    export_all,
    export_layer,
    study_uid,
)
from services.core.mosaic import MosaicImage

ACQUIRED = datetime(2025, 3, 4, 10, 20, 30, tzinfo=UTC)


def _mosaic() -> MosaicImage:
    vein = np.random.default_rng(1).integers(0, 256, (60, 80), dtype=np.uint8)
    force = np.full((60, 80), np.nan, np.float32)
    force[10:50, 10:70] = np.linspace(0.0, 29.99, 60, dtype=np.float32)
    coverage = np.where(np.isfinite(force), 4.0, 0.0).astype(np.float32)
    coverage[20:30, 20:30] = 300  # saturates at 255 in 8 bits
    return MosaicImage(vein, force, coverage, 8.0, (20.0, 30.0))


def _info(**kw: object) -> ExportInfo:
    return ExportInfo(session_key="sess-1", acquired=ACQUIRED, exported=ACQUIRED, method="best", **kw)  # type: ignore[arg-type]


def test_every_layer_reads_back_with_pixels_spacing_and_one_study() -> None:
    m = _mosaic()
    files = export_all(m, _info())
    assert set(files) == set(EXPORT_LAYERS)
    ds = {k: dcmread(io.BytesIO(v)) for k, v in files.items()}
    assert len({d.StudyInstanceUID for d in ds.values()}) == 1 and ds["vein"].StudyInstanceUID == study_uid("sess-1")
    assert len({d.SeriesInstanceUID for d in ds.values()}) == 3
    for d in ds.values():
        assert d.file_meta.TransferSyntaxUID == "1.2.840.10008.1.2.1"
        assert [float(v) for v in d.PixelSpacing] == [0.125, 0.125]  # mm: 1 / px_per_mm
        assert d.StudyDate == "20250304" and d.AcquisitionDateTime == "20250304102030"
        assert (d.Rows, d.Columns, int(d.NumberOfFrames)) == (60, 80, 1)
    assert ds["vein"].SOPClassUID == MF_GRAY_BYTE_SC and np.array_equal(ds["vein"].pixel_array, m.vein)
    assert ds["force"].SOPClassUID == MF_GRAY_WORD_SC and ds["force"].BitsStored == 16
    newtons = apply_rescale(ds["force"].pixel_array, ds["force"])
    finite = np.isfinite(m.force_n)
    np.testing.assert_allclose(newtons[finite], m.force_n[finite], atol=0.005)  # 0.01 N steps
    assert np.all(newtons[~finite] == 0)
    cov = ds["coverage"].pixel_array
    assert cov[15, 15] == 4 and cov[25, 25] == 255 and cov[0, 0] == 0


def test_no_patient_identity_is_invented() -> None:
    d = dcmread(io.BytesIO(export_layer(_mosaic(), "vein", _info())))
    for name in ("PatientName", "PatientID", "PatientBirthDate", "PatientSex"):
        assert name in d and str(d.data_element(name).value or "") == "", name
    given = PatientInfo(name="Müller^Anna", patient_id="H-123", birth_date="19700101", sex="F")
    d = dcmread(io.BytesIO(export_layer(_mosaic(), "vein", _info(patient=given))))
    assert (str(d.PatientName), d.PatientID, d.PatientBirthDate, d.PatientSex) == (
        "Müller^Anna",
        "H-123",
        "19700101",
        "F",
    )


def test_uids_are_stable_and_dates_may_be_empty() -> None:
    a = dcmread(io.BytesIO(export_layer(_mosaic(), "force", _info())))
    b = dcmread(io.BytesIO(export_layer(_mosaic(), "force", _info())))
    assert a.SOPInstanceUID == b.SOPInstanceUID and a.SeriesInstanceUID == b.SeriesInstanceUID
    other = dcmread(io.BytesIO(export_layer(_mosaic(), "force", _info(results_version=2))))
    assert other.SOPInstanceUID != a.SOPInstanceUID and other.StudyInstanceUID == a.StudyInstanceUID
    undated = ExportInfo(session_key="s", acquired=None, exported=ACQUIRED)
    d = dcmread(io.BytesIO(export_layer(_mosaic(), "coverage", undated)))
    assert d.StudyDate == "" and "AcquisitionDateTime" not in d
    with pytest.raises(ValueError, match="layer"):
        export_layer(_mosaic(), "pressure", undated)
