"""The DICOM objects handed to a PACS: Part 10 bytes and the few UIDs a transfer needs (no patient data read)."""

from __future__ import annotations

import io
from collections.abc import Sequence
from dataclasses import dataclass

from pydicom import dcmread
from pydicom.errors import InvalidDicomError


@dataclass(frozen=True)
class DicomObject:
    """One Part 10 object: its bytes, SOP Class and Instance UIDs and transfer syntax (from the file meta)."""

    data: bytes
    sop_class_uid: str
    sop_instance_uid: str
    transfer_syntax_uid: str


def read_objects(objects: Sequence[bytes]) -> list[DicomObject]:
    """Return each object's UIDs; ValueError naming the object's position when one is not usable Part 10."""
    out: list[DicomObject] = []
    seen: set[str] = set()
    for i, data in enumerate(objects):
        try:
            meta = dcmread(io.BytesIO(data), stop_before_pixels=True).file_meta
            sop_class = str(meta.MediaStorageSOPClassUID)
            sop_instance = str(meta.MediaStorageSOPInstanceUID)
            syntax = str(meta.TransferSyntaxUID)
        except (InvalidDicomError, AttributeError, EOFError, OSError, ValueError, TypeError):
            # the cause's text could quote the object's content: only its position is named
            raise ValueError(
                f"object {i}: not a DICOM Part 10 file with SOP Class, SOP Instance and Transfer Syntax UIDs"
            ) from None
        if not (sop_class and sop_instance and syntax):
            raise ValueError(f"object {i}: empty SOP Class, SOP Instance or Transfer Syntax UID in its file meta")
        if sop_instance in seen:
            raise ValueError(f"object {i}: SOP Instance UID {sop_instance} given twice")
        seen.add(sop_instance)
        out.append(DicomObject(data, sop_class, sop_instance, syntax))
    return out
