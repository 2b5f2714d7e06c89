"""DICOM export of a session's mosaic layers for PACS: one Secondary Capture file per layer (pydicom).

Design: one study per session; in it one series per layer, each holding one single-frame instance:
- vein mosaic  — Multi-frame Grayscale Byte SC, 8-bit, the mosaic as served;
- force map    — Multi-frame Grayscale Word SC, 16-bit, pixel x 0.01 (RescaleSlope) = local load in N, 0 where
                 not scanned;
- coverage     — Multi-frame Grayscale Byte SC, 8-bit, the number of frames that saw each point (255 saturates).
Pixel Spacing is the mosaic's (mm, undeformed tissue: the force model's rectification). Study, series and
instance UIDs are derived from the session key (and, for instances, the results version and pixel content),
so exporting the same results twice gives the same UIDs. Patient attributes come only from the integrator's
PatientInfo; without one they are present and empty (Type 2), never invented. Every file is read back with
pydicom before it is returned.
"""

from __future__ import annotations

import hashlib
import io
from dataclasses import dataclass
from datetime import datetime

import numpy as np
from pydicom import dcmread
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.filewriter import dcmwrite
from pydicom.uid import ExplicitVRLittleEndian, generate_uid

from services.core.mosaic import MosaicImage

MF_GRAY_BYTE_SC = "1.2.840.10008.5.1.4.1.1.7.2"
MF_GRAY_WORD_SC = "1.2.840.10008.5.1.4.1.1.7.3"
EXPORT_LAYERS = ("vein", "force", "coverage")
FORCE_SLOPE_N = 0.01
_SERIES = {  # layer -> (series number, description, SOP class)
    "vein": (1, "NIR vein mosaic (undeformed, 850 nm)", MF_GRAY_BYTE_SC),
    "force": (2, "Force map: local load, N = pixel x 0.01", MF_GRAY_WORD_SC),
    "coverage": (3, "Coverage: frames that saw each point", MF_GRAY_BYTE_SC),
}


@dataclass(frozen=True)
class PatientInfo:
    """Patient identity as supplied by the integrator (DICOM formats: name 'Family^Given', date YYYYMMDD)."""

    name: str = ""
    patient_id: str = ""
    birth_date: str = ""
    sex: str = ""  # M, F, O or empty


@dataclass(frozen=True)
class ExportInfo:
    """What identifies the export: the session key (UIDs), dates, patient (or None), method, results version."""

    session_key: str
    acquired: datetime | None
    exported: datetime
    patient: PatientInfo | None = None
    method: str = ""
    results_version: int = 1


def _uid(*parts: str) -> str:
    return str(generate_uid(entropy_srcs=["veinmosaic", *parts]))


def study_uid(session_key: str) -> str:
    """Return the Study Instance UID of a session (deterministic)."""
    return _uid("study", session_key)


def _pixels(mosaic: MosaicImage, layer: str) -> tuple[np.ndarray, str]:
    cov = np.nan_to_num(np.asarray(mosaic.coverage, np.float64))
    if layer == "vein":
        return np.ascontiguousarray(mosaic.vein, np.uint8), ""
    if layer == "coverage":
        return np.clip(np.rint(cov), 0, 255).astype(np.uint8), "pixel = number of frames that saw the point"
    if layer == "force":
        force = np.nan_to_num(np.asarray(mosaic.force_n, np.float64), nan=0.0) / FORCE_SLOPE_N
        cn = np.where(cov > 0, np.clip(np.rint(force), 0, 65535), 0).astype(np.uint16)
        return cn, "pixel x 0.01 = local load in N (Rescale Slope); 0 where not scanned"
    raise ValueError(f"layer must be one of {', '.join(EXPORT_LAYERS)}")


def _date(d: datetime | None) -> tuple[str, str]:
    return ("", "") if d is None else (d.strftime("%Y%m%d"), d.strftime("%H%M%S"))


def build_layer_dataset(mosaic: MosaicImage, layer: str, info: ExportInfo) -> Dataset:
    """Return the DICOM dataset (with file meta) of one mosaic layer."""
    pixels, comment = _pixels(mosaic, layer)
    number, description, sop_class = _SERIES[layer]
    digest = hashlib.sha256(pixels.tobytes()).hexdigest()[:32]
    sop_uid = _uid("instance", info.session_key, layer, str(info.results_version), digest)
    ds = Dataset()
    ds.file_meta = FileMetaDataset()
    ds.file_meta.MediaStorageSOPClassUID = sop_class
    ds.file_meta.MediaStorageSOPInstanceUID = sop_uid
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.SpecificCharacterSet = "ISO_IR 192"  # UTF-8: integrator-supplied names may be non-ASCII
    ds.SOPClassUID, ds.SOPInstanceUID = sop_class, sop_uid
    patient = info.patient or PatientInfo()
    ds.PatientName, ds.PatientID = patient.name, patient.patient_id  # Type 2: empty unless supplied
    ds.PatientBirthDate, ds.PatientSex = patient.birth_date, patient.sex
    acq_date, acq_time = _date(info.acquired)
    ds.StudyInstanceUID = study_uid(info.session_key)
    ds.StudyDate, ds.StudyTime = acq_date, acq_time
    ds.ReferringPhysicianName, ds.StudyID, ds.AccessionNumber = "", "", ""
    ds.StudyDescription = "Near-infrared vein mosaic and force map (veinmosaic)"
    ds.Modality = "OT"
    ds.SeriesInstanceUID = _uid("series", info.session_key, layer)
    ds.SeriesNumber, ds.SeriesDescription = number, description
    ds.SeriesDate, ds.SeriesTime = acq_date, acq_time
    if info.acquired is not None:
        ds.AcquisitionDateTime = info.acquired.strftime("%Y%m%d%H%M%S")
        ds.ContentDate, ds.ContentTime = acq_date, acq_time
    ds.Manufacturer = "veinmosaic"
    ds.ConversionType = "WSD"  # produced by a workstation from the probe's frames
    ds.DateOfSecondaryCapture, ds.TimeOfSecondaryCapture = _date(info.exported)
    ds.SecondaryCaptureDeviceManufacturer = "veinmosaic"
    ds.DerivationDescription = (
        f"Mosaic of force-rectified NIR probe frames, method {info.method or 'unknown'}, "
        f"results version {info.results_version}"
    )[:1024]
    ds.InstanceNumber = 1
    ds.PatientOrientation = ""
    ds.BurnedInAnnotation = "NO"
    ds.ImageType = ["DERIVED", "SECONDARY"]
    if comment:
        ds.ImageComments = comment
    rows, cols = pixels.shape
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.PresentationLUTShape = "IDENTITY"
    ds.Rows, ds.Columns = rows, cols
    bits = 16 if pixels.dtype == np.uint16 else 8
    ds.BitsAllocated, ds.BitsStored, ds.HighBit = bits, bits, bits - 1
    ds.PixelRepresentation = 0
    ds.NumberOfFrames = 1
    ds.PageNumberVector = [1]
    ds.FrameIncrementPointer = 0x00182001  # Page Number Vector
    spacing = 1.0 / float(mosaic.px_per_mm)
    ds.PixelSpacing = [f"{spacing:.10g}", f"{spacing:.10g}"]  # row spacing, column spacing (mm)
    ds.NominalScannedPixelSpacing = ds.PixelSpacing
    ds.PixelSpacingCalibrationType = "GEOMETRY"
    ds.PixelSpacingCalibrationDescription = "probe camera calibration (px_per_mm), undeformed tissue"
    if layer == "force":
        ds.RescaleIntercept, ds.RescaleSlope, ds.RescaleType = "0", f"{FORCE_SLOPE_N}", "US"
        ds.WindowCenter, ds.WindowWidth = 1500, 3000  # 0..30 N, the viewer's force scale
    else:
        ds.RescaleIntercept, ds.RescaleSlope, ds.RescaleType = "0", "1", "US"
    ds.PixelData = pixels.tobytes()
    return ds


def export_layer(mosaic: MosaicImage, layer: str, info: ExportInfo) -> bytes:
    """Return one layer as a DICOM Part-10 file (bytes), checked by reading it back."""
    ds = build_layer_dataset(mosaic, layer, info)
    buf = io.BytesIO()
    dcmwrite(buf, ds, enforce_file_format=True)
    data = buf.getvalue()
    back = dcmread(io.BytesIO(data))
    if back.SOPInstanceUID != ds.SOPInstanceUID or back.pixel_array.shape != mosaic.vein.shape:
        raise ValueError("DICOM export: the written file does not read back as written")
    return data


def export_all(mosaic: MosaicImage, info: ExportInfo) -> dict[str, bytes]:
    """Return {layer: DICOM bytes} for the vein mosaic, the force map and the coverage."""
    return {layer: export_layer(mosaic, layer, info) for layer in EXPORT_LAYERS}
