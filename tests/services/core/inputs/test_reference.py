"""The reference track parser (spec §4): both headers, rows aligned to seqs, every error names its line."""

from __future__ import annotations

import numpy as np
import pytest

from services.core.inputs.reference import ReferenceFormatError, parse_reference_csv, reference_csv
from tests.shared_scans import SHARED_SCANS


def test_positions_only_header_leaves_angles_unknown() -> None:
    ref = parse_reference_csv("seq,x_mm,y_mm\n2,1.5,-2\n0,0,0\n\n", [0, 1, 2])
    assert ref.shape == (3, 5)
    assert np.array_equal(ref[0, :2], [0, 0]) and np.array_equal(ref[2, :2], [1.5, -2])
    assert np.all(np.isnan(ref[1])) and np.all(np.isnan(ref[:, 2:]))


def test_tracker_header_reads_yaw_and_tilts() -> None:
    text = "seq,x_mm,y_mm,yaw_deg,tilt_x_deg,tilt_y_deg\n0,0,0,0,4.5,4.9\n1,4.35,0.2,-2.31,4.92,5.25\n"
    ref = parse_reference_csv(text, [0, 1])
    np.testing.assert_array_equal(ref[1], [4.35, 0.2, -2.31, 4.92, 5.25])
    assert np.array_equal(parse_reference_csv(reference_csv([0, 1], ref), [0, 1]), ref)  # round trip


def test_shared_scan_reference_parses() -> None:
    path = SHARED_SCANS / "short_veins_21" / "reference.csv"
    if not path.exists():
        pytest.skip("the shared reference scans are not next to this checkout")
    ref = parse_reference_csv(path.read_text(), range(40))
    assert np.isfinite(ref).all() and np.abs(ref[:, 3:]).max() > 1.0  # degrees of tilt, not hundredths


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("a,b,c\n", "line 1"),
        ("seq,x_mm,y_mm\n0,1\n", "line 2"),
        ("seq,x_mm,y_mm\n0,x,1\n", "line 2"),
        ("seq,x_mm,y_mm\n7,1,1\n", "seq 7"),
        ("seq,x_mm,y_mm\n0,1,1\n0,1,1\n", "repeats line 2"),
        ("seq,x_mm,y_mm\n0,nan,1\n", "finite"),
        ("seq,x_mm,y_mm,yaw_deg,tilt_x_deg,tilt_y_deg\n0,1,1,0\n", "expected 6 values"),
        ("seq,x_mm,y_mm,yaw_deg,tilt_x_deg,tilt_y_deg\n0,1,1,0,inf,0\n", "finite"),
    ],
)
def test_malformed_reference_is_refused_naming_the_line(text: str, needle: str) -> None:
    with pytest.raises(ReferenceFormatError, match=needle):
        parse_reference_csv(text, [0, 1])
