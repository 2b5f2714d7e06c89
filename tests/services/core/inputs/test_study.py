"""The study context (services/core/inputs/study.py): what is accepted and refused, and that errors name only fields."""

from __future__ import annotations

import pytest

from services.core.inputs.study import StudyContext, StudyContextError, parse_study


def test_parse_keeps_given_fields_and_converts_the_birth_date() -> None:
    study = parse_study({"patient_name": " Doe^Jane ", "patient_birth_date": "1971-02-03", "laterality": "L"})
    assert study == StudyContext(patient_name="Doe^Jane", patient_birth_date="1971-02-03", laterality="L")
    assert study.dicom_birth_date == "19710203"
    assert study.to_dict() == {"patient_name": "Doe^Jane", "patient_birth_date": "1971-02-03", "laterality": "L"}


def test_nothing_given_is_none() -> None:
    assert parse_study(None) is None
    assert parse_study({}) is None
    assert parse_study({"patient_id": "", "laterality": None}) is None


@pytest.mark.parametrize(
    ("doc", "field"),
    [
        ({"patient_sex": "male"}, "patient_sex"),
        ({"laterality": "B"}, "laterality"),
        ({"patient_birth_date": "1971-13-01"}, "patient_birth_date"),
        ({"patient_birth_date": "19710101"}, "patient_birth_date"),
        ({"accession_number": "SECRET-ACCESSION-123"}, "accession_number"),
        ({"patient_id": "SECRET\x07"}, "patient_id"),
        ({"patient_name": "A^B^C^D^E^SECRET"}, "patient_name"),
        ({"study_description": 7}, "study_description"),
        ({"favourite_colour": "SECRET"}, "favourite_colour"),
    ],
)
def test_bad_fields_are_refused_naming_the_field_never_the_value(doc: dict, field: str) -> None:
    with pytest.raises(StudyContextError) as err:
        parse_study(doc)
    assert field in str(err.value)
    assert "SECRET" not in str(err.value)
