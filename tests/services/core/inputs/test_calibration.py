"""Tests for calibration.json parsing and validation (services/core/inputs/calibration.py, spec §3)."""

from __future__ import annotations

import copy
import json
import math
from typing import Any

import numpy as np
import pytest

from services.core.inputs.calibration import Calibration, CalibrationError, default_calibration, parse_calibration
from tests.tolerances import TOL


def spec_example() -> dict[str, Any]:
    """Return the spec §3 calibration.json example with concrete intrinsics in place of fx, cx, k1, ..."""
    return {
        "image_size": [640, 480],
        "camera_matrix": [[610.0, 0, 330.2], [0, 590.0, 235.7], [0, 0, 1]],
        "dist_coeffs": [-0.12, 0.03, 0.0005, -0.0003, 0.0],
        "px_per_mm": 8.0,
        "young_modulus_kpa": 16.1,
        "poisson_ratio": 0.5,
        "hooke_n_per_mm": 18.0,
        "sensor_separation_mm": [53.0, 53.0],
        "scanner_area_m2": 0.0048,
    }


def minimal() -> dict[str, Any]:
    """Return a document with only the three required fields."""
    doc = spec_example()
    return {k: doc[k] for k in ("image_size", "camera_matrix", "px_per_mm")}


def test_parses_the_spec_example() -> None:
    cal = parse_calibration(json.loads(json.dumps(spec_example())))
    assert cal.image_size == (640, 480)
    assert all(isinstance(v, int) for v in cal.image_size)
    assert cal.principal_point == (330.2, 235.7)
    np.testing.assert_array_equal(cal.K, [[610.0, 0, 330.2], [0, 590.0, 235.7], [0, 0, 1]])
    assert cal.K.dtype == np.float64 and cal.D.dtype == np.float64
    np.testing.assert_array_equal(cal.D, [-0.12, 0.03, 0.0005, -0.0003, 0.0])
    assert cal.px_per_mm == 8.0
    assert cal.sensor_separation_mm == (53.0, 53.0)
    # nu / (E A) = 0.5 / (16100 * 0.0048) = 0.5 / 77.28 = 6.469979296e-3 /N
    assert math.isclose(cal.compliance_per_n, 6.469979296e-3, rel_tol=TOL.hand_value_rel)


def test_defaults_are_filled() -> None:
    cal = parse_calibration(minimal())
    # spec §3: every field but image_size, camera_matrix and px_per_mm has the default of the example
    assert cal.dist_coeffs == (0.0, 0.0, 0.0, 0.0, 0.0)
    assert cal.young_modulus_kpa == 16.1
    assert cal.poisson_ratio == 0.5  # 0.5, not the paper table's misprinted 0.05 (spec §2)
    assert cal.hooke_n_per_mm == 18.0
    assert cal.sensor_separation_mm == (53.0, 53.0)
    assert cal.scanner_area_m2 == 0.0048
    assert cal == parse_calibration(spec_example()).with_overrides(dist_coeffs=[0.0, 0.0, 0.0, 0.0, 0.0])


def test_unknown_field_is_an_error_naming_it() -> None:
    doc = spec_example()
    doc["focal_mm"] = 4.0
    with pytest.raises(CalibrationError, match="focal_mm"):
        parse_calibration(doc)
    # a misspelt known field is unknown, too (and not silently defaulted)
    doc = minimal()
    doc["poisson_ration"] = 0.45
    with pytest.raises(CalibrationError, match="poisson_ration"):
        parse_calibration(doc)


@pytest.mark.parametrize("key", ["image_size", "camera_matrix", "px_per_mm"])
def test_missing_required_field(key: str) -> None:
    doc = minimal()
    del doc[key]
    with pytest.raises(CalibrationError, match=key):
        parse_calibration(doc)


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("px_per_mm", float("nan")),
        ("px_per_mm", float("inf")),
        ("young_modulus_kpa", float("nan")),
        ("poisson_ratio", float("-inf")),
        ("hooke_n_per_mm", float("inf")),
        ("scanner_area_m2", float("nan")),
        ("dist_coeffs", [-0.12, float("nan"), 0.0, 0.0]),
        ("sensor_separation_mm", [53.0, float("inf")]),
        ("camera_matrix", [[610.0, 0, float("nan")], [0, 590.0, 235.7], [0, 0, 1]]),
        ("image_size", [640, float("inf")]),
    ],
)
def test_non_finite_values_are_rejected(key: str, value: Any) -> None:
    doc = spec_example()
    doc[key] = value
    with pytest.raises(CalibrationError, match=key):
        parse_calibration(doc)


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("image_size", [640]),
        ("image_size", [640, 480, 3]),
        ("image_size", [640.5, 480]),  # not whole pixels
        ("image_size", [8, 480]),  # below 16 px
        ("image_size", "640x480"),
        ("camera_matrix", [[610.0, 0, 330.2], [0, 590.0, 235.7]]),  # 2x3
        ("camera_matrix", [[610.0, 0], [0, 590.0], [0, 0]]),  # 3x2
        ("camera_matrix", [[610.0, 0, 330.2], [0, 590.0, 235.7], [0, 0, 2]]),  # last row not (0, 0, 1)
        ("camera_matrix", [[-610.0, 0, 330.2], [0, 590.0, 235.7], [0, 0, 1]]),  # fx <= 0
        ("camera_matrix", [[610.0, 0, 330.2], [5, 590.0, 235.7], [0, 0, 1]]),  # K[1][0] != 0
        (
            "camera_matrix",
            [[610.0, 2.0, 330.2], [0, 590.0, 235.7], [0, 0, 1]],
        ),  # skew: the lens model ignores it
        ("dist_coeffs", [-0.12, 0.03, 0.0005]),  # 3: not an OpenCV model
        ("dist_coeffs", [0.0] * 6),
        ("dist_coeffs", 0.1),
        ("sensor_separation_mm", [53.0]),
        ("sensor_separation_mm", [53.0, 0.0]),
        ("px_per_mm", 0.0),
        ("px_per_mm", -8.0),
        ("px_per_mm", "8"),
        ("px_per_mm", True),  # JSON true is not a number
        ("young_modulus_kpa", 0),
        ("poisson_ratio", 0.6),  # above the incompressible limit 0.5
        ("poisson_ratio", 0.0),
        ("hooke_n_per_mm", -18.0),
        ("scanner_area_m2", [0.0048]),
    ],
)
def test_wrong_shapes_and_values_are_rejected(key: str, value: Any) -> None:
    doc = spec_example()
    doc[key] = value
    with pytest.raises(CalibrationError, match=key):
        parse_calibration(doc)


@pytest.mark.parametrize("doc", [None, [], "calibration", 3])
def test_non_object_document_is_rejected(doc: Any) -> None:
    with pytest.raises(CalibrationError):
        parse_calibration(doc)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("camera_matrix", "610 0 330"),  # a string where rows are expected
        ("camera_matrix", [[610.0, 0, 330.2], [0, 590.0]]),  # ragged
        ("camera_matrix", [[610.0, 0, 330.2], [0, 590.0, "x"], [0, 0, 1]]),  # a non-number inside
        ("image_size", {"w": 640, "h": 480}),
        ("image_size", [640]),
        ("dist_coeffs", [[0.1, 0.2]]),  # nested
        ("px_per_mm", [8.0]),
        ("sensor_separation_mm", "53"),
    ],
)
def test_every_malformed_field_is_a_calibration_error_naming_it(field: str, value: Any) -> None:
    # what callers rely on (the API's 422 invalid_calibration, the scan import's one-line error): a wrong shape or
    # type anywhere is a CalibrationError naming the field, never a TypeError, IndexError or KeyError from inside
    doc = spec_example()
    doc[field] = value
    with pytest.raises(CalibrationError, match=field):
        parse_calibration(doc)


@pytest.mark.parametrize("n", [4, 5, 8, 12, 14])
def test_all_opencv_distortion_lengths_accepted(n: int) -> None:
    doc = minimal()
    doc["dist_coeffs"] = [0.001 * (i + 1) for i in range(n)]
    assert len(parse_calibration(doc).D) == n


def test_parse_does_not_modify_its_input() -> None:
    doc = spec_example()
    before = copy.deepcopy(doc)
    parse_calibration(doc)
    assert doc == before


def test_to_dict_parse_round_trip() -> None:
    cal = parse_calibration(spec_example())
    doc = cal.to_dict()
    assert set(doc) == set(spec_example())  # exactly the spec's fields, no internals
    assert doc == spec_example()
    # through JSON text, as the scan folder and the HTTP API carry it
    again = parse_calibration(json.loads(json.dumps(doc)))
    assert again == cal
    assert again.to_dict() == doc
    # the test helper's calibration round-trips too
    d = default_calibration(400, 320)
    assert parse_calibration(d.to_dict()) == d
    assert d.principal_point == (199.5, 159.5)  # centre of a 400x320 grid of pixel centres


def test_with_overrides() -> None:
    cal = parse_calibration(spec_example())
    stiffer = cal.with_overrides(young_modulus_kpa=32.2, hooke_n_per_mm=20.0)
    assert isinstance(stiffer, Calibration)
    assert stiffer.young_modulus_kpa == 32.2 and stiffer.hooke_n_per_mm == 20.0
    # everything else untouched, the original unchanged (frozen)
    assert stiffer.camera_matrix == cal.camera_matrix and stiffer.dist_coeffs == cal.dist_coeffs
    assert cal.young_modulus_kpa == 16.1
    # doubling E halves the compliance: 0.5 / (32200 * 0.0048) = 3.234989648e-3 /N
    assert math.isclose(stiffer.compliance_per_n, 3.234989648e-3, rel_tol=TOL.hand_value_rel)
    # tuples are accepted like lists and normalised
    moved = cal.with_overrides(sensor_separation_mm=(40.0, 60.0), dist_coeffs=(0.0, 0.0, 0.0, 0.0))
    assert moved.sensor_separation_mm == (40.0, 60.0) and moved.dist_coeffs == (0.0, 0.0, 0.0, 0.0)
    # overrides are validated like a document
    with pytest.raises(CalibrationError, match="poisson_ratio"):
        cal.with_overrides(poisson_ratio=float("nan"))
    with pytest.raises(CalibrationError, match="not_a_field"):
        cal.with_overrides(not_a_field=1.0)
    with pytest.raises(CalibrationError, match="px_per_mm"):
        cal.with_overrides(px_per_mm=-1.0)
