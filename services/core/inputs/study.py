"""The study context: what the hospital system knows of the examination (spec §5, POST /v1/sessions `study`).

It is patient data. It travels with the session into the DICOM export and the one-page report, and nowhere
else: error messages name the field that is wrong, never its value.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from datetime import date
from types import MappingProxyType
from typing import Any

# field -> (DICOM value representation, maximum length in characters); PN: per component group
STUDY_FIELDS: Mapping[str, tuple[str, int]] = MappingProxyType(
    {
        "patient_id": ("LO", 64),
        "patient_name": ("PN", 64),
        "patient_birth_date": ("DA", 10),
        "patient_sex": ("CS", 1),
        "accession_number": ("SH", 16),
        "laterality": ("CS", 1),
        "referring_physician": ("PN", 64),
        "study_description": ("LO", 64),
    }
)
SEXES = ("M", "F", "O")
LATERALITIES = ("L", "R")
_CONTROL = re.compile(r"[\x00-\x1f\x7f\\]")  # control characters and the DICOM value separator
_ISO_DATE = re.compile(r"^\d{4}-\d{2}-\d{2}$")


class StudyContextError(ValueError):
    """A study field is invalid; the message names the field, never its value."""


@dataclass(frozen=True)
class StudyContext:
    """The examination's context as the integrator gave it; empty strings for what was not given."""

    patient_id: str = ""
    patient_name: str = ""  # DICOM PN, "Family^Given"
    patient_birth_date: str = ""  # YYYY-MM-DD
    patient_sex: str = ""  # M, F or O
    accession_number: str = ""
    laterality: str = ""  # L or R: which breast
    referring_physician: str = ""  # DICOM PN
    study_description: str = ""

    def to_dict(self) -> dict[str, str]:
        """Return the fields that were given (the stored and returned form)."""
        return {k: v for k, v in asdict(self).items() if v}

    @property
    def is_empty(self) -> bool:
        """Return True when no field was given."""
        return not self.to_dict()

    @property
    def dicom_birth_date(self) -> str:
        """Return the birth date as a DICOM DA (YYYYMMDD), or ''."""
        return self.patient_birth_date.replace("-", "")


def _check(name: str, value: Any) -> str:
    if value is None:
        return ""
    if not isinstance(value, str):
        raise StudyContextError(f"study: {name}: must be a string")
    value = value.strip()
    vr, limit = STUDY_FIELDS[name]
    if _CONTROL.search(value):
        raise StudyContextError(f"study: {name}: control characters and backslashes are not allowed")
    if vr == "PN":
        groups = value.split("=")
        if len(groups) > 3 or any(len(g) > limit or g.count("^") > 4 for g in groups):
            raise StudyContextError(f"study: {name}: a DICOM person name, 'Family^Given', at most {limit} characters")
    elif len(value) > limit:
        raise StudyContextError(f"study: {name}: at most {limit} characters")
    if name == "patient_birth_date" and value:
        try:
            if not _ISO_DATE.match(value):
                raise ValueError
            date.fromisoformat(value)
        except ValueError:
            raise StudyContextError(f"study: {name}: a date YYYY-MM-DD") from None
    if name == "patient_sex" and value and value not in SEXES:
        raise StudyContextError(f"study: {name}: one of {', '.join(SEXES)}")
    if name == "laterality" and value and value not in LATERALITIES:
        raise StudyContextError(f"study: {name}: one of {', '.join(LATERALITIES)} (which breast)")
    return value


def parse_study(doc: Mapping[str, Any] | None) -> StudyContext | None:
    """Return the validated study context of a mapping (None for None or nothing given); raise StudyContextError."""
    if doc is None:
        return None
    if not isinstance(doc, Mapping):
        raise StudyContextError("study: must be an object")
    unknown = sorted(set(doc) - set(STUDY_FIELDS))
    if unknown:
        raise StudyContextError(f"study: unknown field(s): {', '.join(unknown)[:200]}")
    study = StudyContext(**{name: _check(name, doc.get(name)) for name in STUDY_FIELDS})
    return None if study.is_empty else study
