"""Known-answer tests for the path accuracy report (spec §4)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from services.core.outputs.evaluation import (
    edge_yaw_bias,
    evaluate_angles,
    evaluate_path,
    reference_path_length_mm,
)

NAN = float("nan")


def test_known_answer_small_path() -> None:
    # Reference: 3-4-5 steps, total length 5 + 5 + 5 = 15 mm.
    reference = np.array([[0.0, 0.0], [3.0, 4.0], [6.0, 8.0], [9.0, 12.0]])
    # Errors: 0, 1 (x off by 1), 0, 2 (y off by 2).
    estimate = np.array([[0.0, 0.0], [4.0, 4.0], [6.0, 8.0], [9.0, 14.0]])
    report = evaluate_path(estimate, np.ones(4, bool), reference)
    # Hand-computed, exact in float64 up to rounding (1e-12).
    assert report.rmse_mm == pytest.approx(math.sqrt((0 + 1 + 0 + 4) / 4), abs=1e-12)
    assert report.max_error_mm == pytest.approx(2.0, abs=1e-12)
    assert report.final_drift_mm == pytest.approx(2.0, abs=1e-12)
    assert report.path_length_mm == pytest.approx(15.0, abs=1e-12)
    assert report.error_ratio_pct == pytest.approx(100.0 * 2.0 / 15.0, abs=1e-12)
    assert report.registered_fraction == 1.0
    assert (report.n_frames, report.n_registered, report.n_with_reference) == (4, 4, 4)
    np.testing.assert_allclose(report.errors_mm, [0.0, 1.0, 0.0, 2.0], atol=1e-12)


def test_unregistered_and_unknown_frames_are_skipped() -> None:
    reference = np.array([[0.0, 0.0], [1.0, 0.0], [NAN, NAN], [3.0, 0.0], [4.0, 0.0]])
    estimate = np.array([[0.0, 0.0], [1.0, 0.5], [2.0, 0.0], [NAN, NAN], [4.0, 1.0]])
    registered = np.array([True, True, True, False, False])
    report = evaluate_path(estimate, registered, reference)
    # Compared: frames 0 (err 0) and 1 (err 0.5). Frame 2 has no reference, frames 3-4 are not registered
    # (frame 4 has an estimate but registered=False wins).
    assert report.rmse_mm == pytest.approx(math.sqrt(0.25 / 2), abs=1e-12)
    assert report.max_error_mm == pytest.approx(0.5, abs=1e-12)
    assert report.final_drift_mm == pytest.approx(0.5, abs=1e-12)  # last compared frame is frame 1
    # Path length over known reference rows 0, 1, 3, 4: 1 + 2 + 1 = 4 mm (the gap is bridged).
    assert report.path_length_mm == pytest.approx(4.0, abs=1e-12)
    assert report.error_ratio_pct == pytest.approx(100 * 0.5 / 4.0, abs=1e-12)
    # Registered share of the frames with a reference (0, 1 of 0, 1, 3, 4); frame 2 is registered without one
    assert report.registered_fraction == pytest.approx(2 / 4)
    assert (report.n_registered, report.n_with_reference, report.n_compared) == (3, 4, 2)
    assert report.n_registered_without_reference == 1
    assert np.isnan(report.errors_mm[2:]).all()


def test_no_alignment_is_applied() -> None:
    # An estimate offset by a constant (1, 1) must report the offset, not align it away.
    reference = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0]])
    report = evaluate_path(reference + 1.0, np.ones(3, bool), reference)
    assert report.rmse_mm == pytest.approx(math.sqrt(2.0), abs=1e-12)


def test_to_dict_is_json_with_none_for_nan() -> None:
    reference = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
    estimate = np.array([[0.0, 0.0], [NAN, NAN], [2.0, 0.3]])
    doc = evaluate_path(estimate, np.array([True, False, True]), reference).to_dict()
    text = json.dumps(doc, allow_nan=False)  # raises if any NaN slipped through
    assert json.loads(text)["errors_mm"][1] is None
    assert doc["errors_mm"][2] == pytest.approx(0.3)
    assert doc["final_drift_mm"] == pytest.approx(0.3)


def test_zero_length_path_has_nan_ratio_and_none_in_json() -> None:
    reference = np.zeros((2, 2))
    report = evaluate_path(np.zeros((2, 2)), np.ones(2, bool), reference)
    assert report.path_length_mm == 0.0
    assert math.isnan(report.error_ratio_pct)
    assert report.to_dict()["error_ratio_pct"] is None


def test_shape_mismatch_raises() -> None:
    with pytest.raises(ValueError, match="length mismatch"):
        evaluate_path(np.zeros((3, 2)), np.ones(3, bool), np.zeros((4, 2)))
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        evaluate_path(np.zeros((3, 3)), np.ones(3, bool), np.zeros((3, 2)))
    with pytest.raises(ValueError, match="registered"):
        evaluate_path(np.zeros((3, 2)), np.ones((3, 1), bool), np.zeros((3, 2)))


def test_nothing_comparable_raises() -> None:
    reference = np.full((3, 2), NAN)
    with pytest.raises(ValueError, match="nothing to compare"):
        evaluate_path(np.zeros((3, 2)), np.ones(3, bool), reference)
    with pytest.raises(ValueError, match="nothing to compare"):
        evaluate_path(np.zeros((3, 2)), np.zeros(3, bool), np.zeros((3, 2)))


def test_reference_path_length_helper() -> None:
    assert reference_path_length_mm(np.array([[0.0, 0.0], [3.0, 4.0]])) == pytest.approx(5.0)
    assert reference_path_length_mm(np.array([[0.0, 0.0]])) == 0.0


def test_only_frame_zero_registered_is_not_a_perfect_score() -> None:
    # frame 0 is the origin of both paths: its zero error says nothing; the figures must not read 0.000 mm
    reference = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [3.0, 0.0]])
    estimate = np.array([[0.0, 0.0], [NAN, NAN], [NAN, NAN], [NAN, NAN]])
    report = evaluate_path(estimate, np.array([True, False, False, False]), reference)
    assert not report.meaningful and math.isnan(report.rmse_mm) and math.isnan(report.final_drift_mm)
    doc = report.to_dict()
    assert doc["rmse_mm"] is None and doc["meaningful"] is False and doc["registered_fraction"] == 0.25
    assert report.global_error is None and doc["global_error"] is None  # one frame spans no extent
    assert report.summary() == "accuracy not measurable: 1/4 frames registered (25.0 %), 1 compared with the reference"


def test_summary_states_the_registered_share() -> None:
    reference = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [3.0, 0.0]])
    estimate = np.array([[0.0, 0.0], [1.0, 0.1], [NAN, NAN], [3.0, 0.2]])
    text = evaluate_path(estimate, np.array([True, True, False, True]), reference).summary()
    assert text.startswith("RMSE ") and "3/4 frames registered (75.0 %)" in text
    assert "frames not registered are not in these figures" in text


def test_angle_errors_known_answer() -> None:
    # yaw compared on registered frames only and wrapped (359 vs -1 is 0 off); tilts on every frame with both.
    est = np.array([[0.0, 1.0, 0.0], [359.0, 2.0, 1.0], [10.0, 3.0, NAN], [5.0, 0.0, 0.0]])
    ref = np.array([[0.0, 0.0, 0.0], [-1.0, 0.0, 1.0], [0.0, 3.0, 2.0], [3.0, 0.0, 0.0]])
    out = evaluate_angles(est, np.array([True, True, False, True]), ref)
    assert out["yaw_rmse_deg"] == pytest.approx(math.sqrt((0 + 0 + 4) / 3), abs=1e-9)
    assert out["yaw_compared"] == 3 and out["yaw_max_error_deg"] == pytest.approx(2.0, abs=1e-9)
    assert out["tilt_x_rmse_deg"] == pytest.approx(math.sqrt((1 + 4 + 0 + 0) / 4), abs=1e-9)
    assert out["tilt_y_compared"] == 3 and out["tilt_y_rmse_deg"] == pytest.approx(0.0, abs=1e-12)


def test_angle_errors_skip_unknown_angles() -> None:
    est = np.zeros((3, 3))
    assert evaluate_angles(est, np.ones(3, bool), np.full((3, 3), NAN)) == {}


def _raster(n: int = 120) -> np.ndarray:
    """Return a 6-row serpentine (4 mm steps, rows 25 mm apart, 0.5 mm jitter) starting at the origin (mm)."""
    rng = np.random.default_rng(3)
    x = np.tile(np.r_[np.arange(20), np.arange(19, -1, -1)] * 4.0, 3)[:n]
    y = np.repeat(np.arange(n // 20 + 1) * 25.0, 20)[:n]
    path = np.c_[x, y] + rng.normal(0.0, 0.5, (n, 2))
    return path - path[0]


def test_a_global_scale_and_turn_is_recovered_and_leaves_nothing() -> None:
    reference = _raster()
    b = 1.01 * np.exp(1j * np.radians(0.3))  # the estimate 1 % too large and turned 0.3 deg (x toward y)
    turned = (reference[:, 0] + 1j * reference[:, 1]) * b
    report = evaluate_path(np.c_[turned.real, turned.imag], np.ones(len(reference), bool), reference)
    g = report.global_error
    assert g is not None and report.rmse_mm > 0.2  # the error is real ...
    # ... and all of it one similarity: exact up to float64 rounding on ~100 mm coordinates (1e-9)
    assert g.scale_pct == pytest.approx(1.0, abs=1e-9) and g.turn_deg == pytest.approx(0.3, abs=1e-9)
    assert g.after_similarity_mm < 1e-9 and g.after_linear_mm < 1e-9
    doc = json.loads(json.dumps(report.to_dict(), allow_nan=False))  # as report.json is written
    assert doc["global_error"]["turn_deg"] == pytest.approx(0.3, abs=1e-9)
    assert "+1.00 % in scale" in g.summary() and "turned +0.300 deg" in g.summary()
    assert abs(g.lead_mm) < 1e-9  # nothing left along the travel either


def test_a_path_ahead_along_its_travel_shows_as_its_lead() -> None:
    # each frame 0.1 mm ahead of the reference along its own direction of travel (a drag not undone in full):
    # +x on one row, -x on the next, so no similarity about frame 0 takes it; the lead finds it whichever way a row
    # goes, up to what the similarity's small fit takes (1 % of it) and the row ends (their steps ~25 mm: left out)
    reference = _raster()
    c = reference[:, 0] + 1j * reference[:, 1]
    travel = np.gradient(np.round(c / 4.0).real)  # the serpentine's rows: +1 or -1 in x (0 at a row's turn)
    ahead = c + 0.1 * np.sign(travel)
    g = evaluate_path(np.c_[ahead.real, ahead.imag], np.ones(len(c), bool), reference).global_error
    assert g is not None and g.lead_mm == pytest.approx(0.1, abs=0.003)
    behind = c - 0.1 * np.sign(travel)
    g = evaluate_path(np.c_[behind.real, behind.imag], np.ones(len(c), bool), reference).global_error
    assert g is not None and g.lead_mm == pytest.approx(-0.1, abs=0.003)
    assert f"its mean along the travel {g.lead_mm:+.3f} mm (+ = ahead)" in g.summary()


def test_a_shape_error_is_left_after_the_similarity_and_a_shear_after_it_too() -> None:
    reference = _raster()
    noisy = reference.copy()
    noisy[1:, 1] += np.random.default_rng(5).normal(0.0, 0.2, len(reference) - 1)
    report = evaluate_path(noisy, np.ones(len(reference), bool), reference)
    g = report.global_error
    assert g is not None
    # zero-mean noise of 0.2 mm (y only) on a ~100 mm path: no global map to speak of (0.05 % / 0.05 deg at
    # most, a few times the fit's standard error), and the similarity leaves the RMSE within 5 %
    assert abs(g.scale_pct) < 0.05 and abs(g.turn_deg) < 0.05
    assert g.after_similarity_mm == pytest.approx(report.rmse_mm, rel=0.05)
    assert abs(g.lead_mm) < 0.02  # the noise is across the rows' travel (x): little of it along
    sheared = reference @ np.array([[1.0, 0.0], [0.01, 1.0]])  # x += 0.01 y: not a similarity, but linear
    g2 = evaluate_path(sheared, np.ones(len(reference), bool), reference).global_error
    assert g2 is not None and g2.after_similarity_mm > 0.1 and g2.after_linear_mm < 1e-9


def test_a_straight_path_has_no_linear_map_and_stays_json() -> None:
    reference = np.c_[np.arange(10.0) * 4.0, np.zeros(10)]
    estimate = reference * 1.002  # 0.2 % too large along a line: a similarity, but no 2x2 map is determined
    doc = evaluate_path(estimate, np.ones(10, bool), reference).to_dict()
    g = json.loads(json.dumps(doc, allow_nan=False))["global_error"]
    assert g["after_linear_mm"] is None
    assert g["lead_mm"] == pytest.approx(0.0, abs=1e-9)  # along a line the similarity takes every error
    assert g["scale_pct"] == pytest.approx(0.2, abs=1e-9) and g["after_similarity_mm"] < 1e-9


def test_edge_yaw_bias_known_answer_per_edge_kind() -> None:
    # the tracker's yaw per frame (one frame unknown, and a turn across +-180 deg); loop closures measure 0.02 deg
    # less than it, the other edges 0.01 more: the two biases come back apart, the unknown frame's edges left out
    ref = np.array([0.0, 1.5, 3.0, 179.5, -179.0, math.nan, 10.0])
    edges = []
    for i, j in ((0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (5, 6)):  # consecutive: "other"
        edges.append(
            (i, j, (ref[j] - ref[i] + 0.01 + 180.0) % 360.0 - 180.0 if np.isfinite(ref[j] - ref[i]) else 0.0, 0, 0.01)
        )
    for i, j in ((0, 3), (1, 4), (0, 6), (2, 5)):  # loops
        edges.append(
            (i, j, (ref[j] - ref[i] - 0.02 + 180.0) % 360.0 - 180.0 if np.isfinite(ref[j] - ref[i]) else 0.0, 1, 0.01)
        )
    got = edge_yaw_bias(np.array(edges, float), ref)
    assert got["other_edges"] == 4 and got["loop_edges"] == 3  # the edges of frame 5 are not compared
    assert got["other_yaw_bias_deg"] == pytest.approx(0.01, abs=1e-9)
    assert got["loop_yaw_bias_deg"] == pytest.approx(-0.02, abs=1e-9)
    assert got["other_yaw_sd_deg"] == pytest.approx(0.0, abs=1e-9)
    empty = edge_yaw_bias(np.zeros((0, 5)), ref)
    assert empty["loop_edges"] == 0 and math.isnan(empty["loop_yaw_bias_deg"])


def test_edge_yaw_bias_of_the_loop_closures_at_the_top_third_of_loads() -> None:
    # six loop closures at mean loads 3..18 N, the two heaviest off by -0.05 deg, the others by +0.01; a chain edge
    # at 30 N off by +1 deg counts in no loop figure: the top third's mean is the heavy closures' alone
    ref = np.zeros(12)
    loads = [3.0, 6.0, 9.0, 12.0, 15.0, 18.0]
    edges = [(k, k + 6, -0.05 if load > 13 else 0.01, 1, 0.02, load) for k, load in enumerate(loads)]
    edges.append((0, 1, 1.0, 0, 0.02, 30.0))
    got = edge_yaw_bias(np.array(edges, float), ref)
    assert got["loop_high_load_edges"] == 2
    assert got["loop_yaw_bias_high_load_deg"] == pytest.approx(-0.05, abs=1e-12)
    assert got["loop_yaw_bias_deg"] == pytest.approx((4 * 0.01 - 2 * 0.05) / 6, abs=1e-12)
    # without the loads' column (five columns) the figure is not made up
    assert "loop_yaw_bias_high_load_deg" not in edge_yaw_bias(np.array(edges, float)[:, :5], ref)


def test_edge_yaw_bias_z_is_the_errors_sd_in_units_of_each_edges_sigma() -> None:
    # loop closures off by +-0.04 deg weighed at 0.02 deg (z +-2), the chain's edges off by +-0.01 at 0.02 (z +-0.5):
    # the loops pull twice as hard as they should against the chain, four times over what their evidence warrants
    ref = np.zeros(9)
    edges = [(k, k + 1, 0.01 * (-1) ** k, 0, 0.02) for k in range(8)]
    edges += [(k, k + 5, 0.04 * (-1) ** k, 1, 0.02) for k in range(4)]
    got = edge_yaw_bias(np.array(edges, float), ref)
    assert got["other_yaw_z_sd"] == pytest.approx(0.5, abs=1e-9)
    assert got["loop_yaw_z_sd"] == pytest.approx(2.0, abs=1e-9)
    assert got["loop_yaw_sd_deg"] == pytest.approx(0.04, abs=1e-9)  # the SD in degrees as before
