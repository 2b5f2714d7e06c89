"""Small valid DICOM objects for the PACS tests: Secondary Capture instances with a 16x16 image, fresh UIDs."""

from __future__ import annotations

import io

import numpy as np
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import ExplicitVRLittleEndian, SecondaryCaptureImageStorage, generate_uid

PATIENT_NAME = "Canary^Patricia"  # must never appear in an error message or a log
PATIENT_ID = "CANARY-4711"


def secondary_capture(study_uid: str, series_uid: str, number: int, syntax: str = ExplicitVRLittleEndian) -> bytes:
    """Return one Part 10 Secondary Capture instance (16x16, 16-bit) of the study, with a new SOP Instance UID."""
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = SecondaryCaptureImageStorage
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = syntax
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID = SecondaryCaptureImageStorage
    ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
    ds.StudyInstanceUID = study_uid
    ds.SeriesInstanceUID = series_uid
    ds.PatientName = PATIENT_NAME
    ds.PatientID = PATIENT_ID
    ds.PatientBirthDate = ""
    ds.PatientSex = "F"
    ds.StudyDate = "20240102"
    ds.StudyTime = "101500"
    ds.StudyID = "1"
    ds.AccessionNumber = "ACC1"
    ds.ReferringPhysicianName = ""
    ds.Modality = "OT"
    ds.ConversionType = "WSD"
    ds.SeriesNumber = 1
    ds.InstanceNumber = number
    ds.PatientOrientation = ""
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.Rows = ds.Columns = 16
    ds.BitsAllocated = ds.BitsStored = 16
    ds.HighBit = 15
    ds.PixelRepresentation = 0
    ds.PixelData = (np.arange(256, dtype=np.uint16).reshape(16, 16) * number).tobytes()
    buf = io.BytesIO()
    ds.save_as(buf, enforce_file_format=True, implicit_vr=syntax != ExplicitVRLittleEndian, little_endian=True)
    return buf.getvalue()


def study(n: int = 2) -> tuple[str, list[bytes], list[str]]:
    """Return a new study's UID, `n` instances of it (one series) and their SOP Instance UIDs."""
    from pydicom import dcmread

    study_uid, series_uid = generate_uid(), generate_uid()
    objects = [secondary_capture(study_uid, series_uid, i + 1) for i in range(n)]
    uids = [str(dcmread(io.BytesIO(o), stop_before_pixels=True).SOPInstanceUID) for o in objects]
    return study_uid, objects, uids
