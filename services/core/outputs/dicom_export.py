"""DICOM export of a session for a hospital's PACS: one study, the three mosaic layers and the one-page report.

Design. `export_study` is the one builder of a session's objects; the HTTP route, the CLI and the PACS-send
job all call it and get {object: Part-10 bytes}. One study per session; in it one series per object, each
holding one instance, every object checked against the reference validator (dicom3tools' dciodvfy, in the
tests) with no error:
- vein      — Secondary Capture Image Storage (single frame), 8-bit MONOCHROME2, the mosaic as served;
- force     — Secondary Capture Image Storage, 16-bit: stored value x 0.01 (Rescale Slope) = local load in N,
              0 where never scanned. The window (0..30 N) is in the rescaled unit, newtons, since a VOI window
              applies after the rescale; a Real World Value Mapping item codes the unit (UCUM "N", newton) so
              a viewer can show the value under the cursor in N;
- coverage  — Secondary Capture Image Storage, 8-bit: the number of frames that saw each point (255
              saturates), windowed over the scanned range;
- report    — Encapsulated PDF Storage: the one-page report (its own series), when the caller gives its bytes.
Why single-frame SC: each layer is one picture, so the multi-frame SC classes' frame pointers would be
conditions never met (dciodvfy errors), and the Parametric Map IOD would need a patient coordinate system
(Frame of Reference, plane position and orientation) a hand-held probe on a curved breast does not have.
Pixel Spacing is the mosaic's (mm of undeformed tissue: the force model's rectification).

Identity. Every UID is derived (pydicom's root, a hash of its sources) from the export's identity: the key (the
service: the session id; the CLI: a digest of the scan's content, never a path) together with the study
context, so re-exporting the same session gives the same UIDs, another scan never shares them, and the
same results filed under patient data get a study of their own (one StudyInstanceUID never holds two
patients). Series also depend on the results version and method (a reprocessed version is a new series in
the same study); image instances also on their pixels.

Study context. Patient, order and laterality come only from the integrator's StudyContext; without one the
Type 2 attributes are present and empty, never invented. Laterality is required (Type 2C) because the body
part examined, the breast, is paired. Dates and times are in the acquisition's own time zone, with
Timezone Offset From UTC. Every file is read back with pydicom before it is returned.
"""

from __future__ import annotations

import hashlib
import io
import json
import re
from collections.abc import Collection
from dataclasses import dataclass
from datetime import datetime, tzinfo
from types import MappingProxyType

import numpy as np
from pydicom import dcmread
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.filewriter import dcmwrite
from pydicom.sequence import Sequence
from pydicom.uid import ExplicitVRLittleEndian, generate_uid

from services.core.inputs.scan import Scan
from services.core.inputs.study import StudyContext
from services.core.mosaic.canvas import MosaicImage

SC_IMAGE = "1.2.840.10008.5.1.4.1.1.7"  # Secondary Capture Image Storage
ENCAPSULATED_PDF = "1.2.840.10008.5.1.4.1.1.104.1"  # Encapsulated PDF Storage
EXPORT_LAYERS = ("vein", "force", "coverage")
STUDY_OBJECTS = (*EXPORT_LAYERS, "report")
FORCE_SLOPE_N = 0.01  # N per stored value
FORCE_WINDOW_N = (0.0, 30.0)  # the viewer's force scale, N
MANUFACTURER = "veinmosaic"
MODEL_NAME = "veinmosaic NIR vein mosaic"
DEFAULT_STUDY_DESCRIPTION = "NIR vein mosaic and force map"
_SERIES = MappingProxyType(
    {  # object -> (series number, description)
        "vein": (1, "NIR vein mosaic (undeformed, 850 nm)"),
        "force": (2, "Force map: local load (N)"),
        "coverage": (3, "Coverage: frames that saw each point"),
        "report": (4, "One-page report"),
    }
)
_SAFE_ID = re.compile(r"[^A-Za-z0-9._-]")


@dataclass(frozen=True)
class ExportInfo:
    """What identifies an export: the key (session id or scan digest), study context, dates (aware), results."""

    key: str
    exported: datetime
    acquired: datetime | None = None
    study: StudyContext | None = None
    method: str = ""
    results_version: int = 1
    software: str = "unknown"  # the producing software's version (DICOM SoftwareVersions): the caller's to read

    def __post_init__(self) -> None:
        if not self.key:
            raise ValueError("ExportInfo.key: the session id or the scan's content digest is required")
        for name in ("exported", "acquired"):
            value = getattr(self, name)
            if value is not None and value.utcoffset() is None:
                raise ValueError(f"ExportInfo.{name}: a timezone-aware datetime is required")


def scan_digest(scan: Scan) -> str:
    """Return a hex SHA-256 of a scan's content (calibration, frame table and pixels, forces, IMU, mask)."""
    h = hashlib.sha256(b"veinmosaic scan v1\0")
    h.update(json.dumps(scan.calibration.to_dict(), sort_keys=True, default=str).encode())
    arrays = (scan.frame_seq, scan.frame_t_s, scan.force_t_s, scan.forces_n, scan.imu_t_s, scan.imu_tilt_deg)
    for arr in (*arrays, scan.mask):
        h.update(_array_bytes(arr))
    for index in range(len(scan)):
        h.update(_array_bytes(scan.frame(index)))
    return h.hexdigest()


def _array_bytes(arr: np.ndarray | None) -> bytes:
    """Return an array's dtype, shape and data as bytes (b'none' for None): what a digest of it covers."""
    if arr is None:
        return b"none\0"
    a = np.ascontiguousarray(arr)
    return f"{a.dtype.str}{a.shape}\0".encode() + a.tobytes()


def _identity(key: str, study: StudyContext | None) -> str:
    context = study.to_dict() if study is not None else {}
    return hashlib.sha256(json.dumps([key, context], sort_keys=True).encode()).hexdigest()


def _uid(*parts: str) -> str:
    # pydicom hashes its sources joined with no separator: join them with one, so no two part lists collide
    return str(generate_uid(entropy_srcs=[json.dumps(["veinmosaic", *parts])]))


def study_uid(key: str, study: StudyContext | None = None) -> str:
    """Return the Study Instance UID of an export key with its study context (deterministic)."""
    return _uid("study", _identity(key, study))


def _series_uid(info: ExportInfo, obj: str) -> str:
    return _uid("series", _identity(info.key, info.study), obj, str(info.results_version), info.method)


def _instance_uid(info: ExportInfo, obj: str, content: str) -> str:
    return _uid("instance", _identity(info.key, info.study), obj, str(info.results_version), info.method, content)


def _study_id(key: str) -> str:
    """Return the equipment-generated Study ID (SH, 16): the key's leading characters, as the sheet shows."""
    return _SAFE_ID.sub("", key)[:16] or hashlib.sha256(key.encode()).hexdigest()[:16]


def _pixels(mosaic: MosaicImage, layer: str) -> tuple[np.ndarray, str]:
    cov = np.nan_to_num(np.asarray(mosaic.coverage, np.float64))
    if layer == "vein":
        return np.ascontiguousarray(mosaic.vein, np.uint8), ""
    if layer == "coverage":
        return np.clip(np.rint(cov), 0, 255).astype(np.uint8), "pixel = number of frames that saw the point"
    if layer == "force":
        force = np.nan_to_num(np.asarray(mosaic.force_n, np.float64), nan=0.0) / FORCE_SLOPE_N
        cn = np.where(cov > 0, np.clip(np.rint(force), 0, 65535), 0).astype(np.uint16)
        return cn, f"pixel x {FORCE_SLOPE_N} = local load in N (Rescale Slope); 0 where not scanned"
    raise ValueError(f"layer must be one of {', '.join(EXPORT_LAYERS)}")


def _zone(info: ExportInfo) -> tzinfo:
    """Return the time zone every date and time of the export is written in: the acquisition's (else export's)."""
    zone = (info.acquired or info.exported).tzinfo
    assert zone is not None  # ExportInfo checks it
    return zone


def _da_tm(d: datetime | None) -> tuple[str, str]:
    return ("", "") if d is None else (d.strftime("%Y%m%d"), d.strftime("%H%M%S"))


def _offset(d: datetime) -> str:
    delta = d.utcoffset()
    minutes = round(delta.total_seconds() / 60) if delta is not None else 0
    sign = "-" if minutes < 0 else "+"
    return f"{sign}{abs(minutes) // 60:02d}{abs(minutes) % 60:02d}"


def _code(value: str, scheme: str, meaning: str) -> Dataset:
    item = Dataset()
    item.CodeValue, item.CodingSchemeDesignator, item.CodeMeaning = value, scheme, meaning
    return item


def _base(info: ExportInfo, obj: str, sop_class: str, sop_uid: str) -> Dataset:
    """Return the modules every object shares: SOP Common, Patient, General Study, series and equipment."""
    zone = _zone(info)
    acquired = info.acquired.astimezone(zone) if info.acquired is not None else None
    exported = info.exported.astimezone(zone)
    study = info.study or StudyContext()
    ds = Dataset()
    ds.file_meta = FileMetaDataset()
    ds.file_meta.MediaStorageSOPClassUID = sop_class
    ds.file_meta.MediaStorageSOPInstanceUID = sop_uid
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    # SOP Common
    ds.SpecificCharacterSet = "ISO_IR 192"  # UTF-8: integrator-supplied names may be non-ASCII
    ds.SOPClassUID, ds.SOPInstanceUID = sop_class, sop_uid
    ds.InstanceCreationDate, ds.InstanceCreationTime = _da_tm(exported)
    ds.TimezoneOffsetFromUTC = _offset(exported)
    # Patient (Type 2: empty unless the integrator gave them)
    ds.PatientName, ds.PatientID = study.patient_name, study.patient_id
    ds.PatientBirthDate, ds.PatientSex = study.dicom_birth_date, study.patient_sex
    # General Study
    acq_date, acq_time = _da_tm(acquired)
    ds.StudyInstanceUID = study_uid(info.key, info.study)
    ds.StudyDate, ds.StudyTime = acq_date, acq_time
    ds.ReferringPhysicianName = study.referring_physician
    ds.StudyID = _study_id(info.key)
    ds.AccessionNumber = study.accession_number
    ds.StudyDescription = study.study_description or DEFAULT_STUDY_DESCRIPTION
    # series (General Series, or Encapsulated Document Series for the report)
    number, description = _SERIES[obj]
    ds.SeriesInstanceUID = _series_uid(info, obj)
    ds.SeriesNumber, ds.SeriesDescription = number, f"{description}, results v{info.results_version}"[:64]
    ds.SeriesDate, ds.SeriesTime = acq_date, acq_time
    # General Equipment and SC Equipment
    ds.Manufacturer, ds.ManufacturerModelName = MANUFACTURER, MODEL_NAME
    ds.SoftwareVersions = info.software
    ds.ConversionType = "WSD"  # produced by a workstation from the probe's frames
    ds.SecondaryCaptureDeviceManufacturer = MANUFACTURER
    ds.SecondaryCaptureDeviceManufacturerModelName = MODEL_NAME
    ds.SecondaryCaptureDeviceSoftwareVersions = ds.SoftwareVersions
    ds.AcquisitionDateTime = acquired.strftime("%Y%m%d%H%M%S") if acquired is not None else ""  # Type 2 (PDF)
    ds.ContentDate, ds.ContentTime = acq_date, acq_time
    ds.InstanceNumber = 1
    return ds


def build_layer_dataset(mosaic: MosaicImage, layer: str, info: ExportInfo) -> Dataset:
    """Return the Secondary Capture dataset (with file meta) of one mosaic layer (vein, force in N, coverage)."""
    pixels, comment = _pixels(mosaic, layer)
    digest = hashlib.sha256(pixels.tobytes()).hexdigest()[:32]
    ds = _base(info, layer, SC_IMAGE, _instance_uid(info, layer, digest))
    study = info.study or StudyContext()
    ds.Modality = "OT"
    ds.Laterality = study.laterality  # Type 2C: the breast is a paired body part
    ds.BodyPartExamined = "BREAST"
    ds.DateOfSecondaryCapture, ds.TimeOfSecondaryCapture = _da_tm(info.exported.astimezone(_zone(info)))
    ds.DerivationDescription = (
        f"Mosaic of force-rectified NIR probe frames, method {info.method or 'unknown'}, "
        f"results version {info.results_version}"
    )[:1024]
    ds.PatientOrientation = ""
    ds.BurnedInAnnotation = "NO"
    ds.RecognizableVisualFeatures = "YES" if layer == "vein" else "NO"  # a vein pattern is a biometric
    ds.LossyImageCompression = "00"
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
    spacing = 1.0 / float(mosaic.px_per_mm)
    ds.PixelSpacing = [f"{spacing:.10g}", f"{spacing:.10g}"]  # row spacing, column spacing (mm)
    ds.PixelSpacingCalibrationType = "GEOMETRY"
    ds.PixelSpacingCalibrationDescription = "probe camera calibration (px_per_mm), undeformed tissue"
    if layer == "force":
        _force_mapping(ds)
    elif layer == "coverage":
        top = float(pixels.max()) if pixels.size else 0.0
        top = max(top, 1.0)
        ds.WindowCenter, ds.WindowWidth = f"{top / 2:.6g}", f"{top + 1:.6g}"  # 0..max frames
        ds.WindowCenterWidthExplanation = "0 to the most frames that saw a point"
    else:
        ds.WindowCenter, ds.WindowWidth = "127.5", "256"  # the full 8-bit range
        ds.WindowCenterWidthExplanation = "full range"
    ds.PixelData = pixels.tobytes()
    return ds


def _force_mapping(ds: Dataset) -> None:
    """Set the force layer's rescale (stored x 0.01 = N), its window in N and the coded unit (UCUM N)."""
    lo, hi = FORCE_WINDOW_N
    ds.RescaleIntercept, ds.RescaleSlope, ds.RescaleType = "0", f"{FORCE_SLOPE_N}", "US"
    ds.WindowCenter, ds.WindowWidth = f"{(lo + hi) / 2:g}", f"{hi - lo:g}"  # in N: a window follows the rescale
    ds.WindowCenterWidthExplanation = f"local load {lo:g} to {hi:g} N"
    item = Dataset()
    item.RealWorldValueFirstValueMapped = 0
    item.RealWorldValueLastValueMapped = 65535
    item.RealWorldValueIntercept = 0.0
    item.RealWorldValueSlope = FORCE_SLOPE_N
    item.LUTExplanation = "local load (N)"
    item.LUTLabel = "FORCE_N"
    item.MeasurementUnitsCodeSequence = Sequence([_code("N", "UCUM", "newton")])
    ds.RealWorldValueMappingSequence = Sequence([item])


def build_report_dataset(report_pdf: bytes, info: ExportInfo) -> Dataset:
    """Return the Encapsulated PDF dataset (with file meta) of the one-page report, in the session's study."""
    if not report_pdf.startswith(b"%PDF"):
        raise ValueError("the report must be a PDF document")
    ds = _base(info, "report", ENCAPSULATED_PDF, _instance_uid(info, "report", _pdf_digest(report_pdf)))
    study = info.study or StudyContext()
    ds.Modality = "DOC"
    # the report shows the patient when a study context names one: conservative for de-identification
    named = bool(study.patient_name or study.patient_id or study.patient_birth_date)
    ds.BurnedInAnnotation = "YES" if named else "NO"
    ds.DocumentTitle = "veinmosaic one-page report"
    ds.ConceptNameCodeSequence = Sequence()  # Type 2: no coded document title
    ds.MIMETypeOfEncapsulatedDocument = "application/pdf"
    ds.EncapsulatedDocument = report_pdf + (b"\0" if len(report_pdf) % 2 else b"")
    ds.EncapsulatedDocumentLength = len(report_pdf)
    return ds


def _pdf_digest(pdf: bytes) -> str:
    """Return a digest of a PDF without its creation and modification dates (which change on every render)."""
    stable = re.sub(rb"/(CreationDate|ModDate)\s*\([^)]*\)", b"", pdf)
    return hashlib.sha256(stable).hexdigest()[:32]


def _part10(ds: Dataset) -> bytes:
    buf = io.BytesIO()
    dcmwrite(buf, ds, enforce_file_format=True)
    data = buf.getvalue()
    back = dcmread(io.BytesIO(data))
    if back.SOPInstanceUID != ds.SOPInstanceUID or back.StudyInstanceUID != ds.StudyInstanceUID:
        raise ValueError("DICOM export: the written file does not read back as written")
    return data


def export_layer(mosaic: MosaicImage, layer: str, info: ExportInfo) -> bytes:
    """Return one layer as a DICOM Part-10 file (bytes), checked by reading it back."""
    ds = build_layer_dataset(mosaic, layer, info)
    data = _part10(ds)
    if dcmread(io.BytesIO(data)).pixel_array.shape != mosaic.vein.shape:
        raise ValueError("DICOM export: the written file does not read back as written")
    return data


def export_study(
    mosaic: MosaicImage, info: ExportInfo, report_pdf: bytes | None = None, *, only: Collection[str] | None = None
) -> dict[str, bytes]:
    """Return {vein, force, coverage[, report]: DICOM Part-10 bytes}: every object of a session's study.

    The report is there when report_pdf is given; `only` restricts the result to the named objects (a caller
    that serves one object need not build the others; the objects are the same either way).
    """
    wanted = set(STUDY_OBJECTS if only is None else only)
    unknown = wanted - set(STUDY_OBJECTS)
    if unknown:
        raise ValueError(f"objects must be among {', '.join(STUDY_OBJECTS)}")
    if "report" in wanted and only is not None and report_pdf is None:
        raise ValueError("the report object needs the report's PDF bytes")
    out = {layer: export_layer(mosaic, layer, info) for layer in EXPORT_LAYERS if layer in wanted}
    if report_pdf is not None and "report" in wanted:
        out["report"] = _part10(build_report_dataset(report_pdf, info))
    return out
