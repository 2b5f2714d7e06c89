"""Known-answer tests for the spec §2 force model (services/core/physics/force_model.py).

Every expected number below is worked out by hand in a comment and written as a literal, so the tests
check the module against the spec's equations rather than against itself.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.core.inputs.calibration import default_calibration
from services.core.physics.force_model import (
    MIN_RECTIFY_FACTOR,
    LoadState,
    centre_stretch,
    deform_points_mm,
    depth_deviation_mm,
    interpolate_forces,
    load_state,
    local_load_n,
    rectify_factor,
    rectify_points_mm,
    samples_around,
)
from tests.tolerances import TOL

# The paper's constants (spec §2 defaults): kappa = 18 N/mm, S_X = S_Y = 53 mm, E = 16.1 kPa, nu = 0.5,
# A = 0.0048 m^2.
PAPER = default_calibration(640, 480, px_per_mm=8.0)

# Worked example: forces (F1, F2, F3, F4) = (1, 3, 2, 2) N.
#   F_Z = 1 + 3 + 2 + 2 = 8 N
#   theta_x = asin((F2 - F1) / (2 kappa S_Y)) = asin(2 / (2 * 18 * 53)) = asin(2 / 1908)
#           = asin(1.048218029e-3); asin(a) = a + a^3/6 + ... = 1.048218029e-3 + 1.92e-10
#           = 1.048218221e-3 rad (0.0600585 deg)
#   theta_y = asin((F4 - F3) / (2 kappa S_X)) = asin(0) = 0
#   u' = Rx(theta_x) Ry(0) e_z = (0, -sin theta_x, cos theta_x)
#   Z(x, y) = -(0 * x - sin theta_x * y) / cos theta_x = y tan theta_x,
#   tan theta_x = a / sqrt(1 - a^2) = a (1 + a^2/2) = 1.048218029e-3 * (1 + 5.494e-7) = 1.048218605e-3
EXAMPLE_FORCES = (1.0, 3.0, 2.0, 2.0)
A_X = 2.0 / 1908.0  # = 1.0482180293501049e-3
THETA_X = 1.0482182213070546e-3  # asin(A_X)
TAN_X = 1.0482186052211439e-3  # tan(THETA_X)
# Compliance nu / (E A) = 0.5 / (16100 Pa * 0.0048 m^2) = 0.5 / 77.28 N = 6.469979296e-3 /N
COMPLIANCE = 6.469979296066254e-3


def close(a: float, b: float) -> bool:
    """Relative comparison against a hand-written literal (TOL.hand_value_rel: literals carry ~10 digits)."""
    return math.isclose(a, b, rel_tol=TOL.hand_value_rel, abs_tol=TOL.float64_abs)


def test_compliance_of_paper_constants() -> None:
    # nu / (E A) = 0.5 / (16.1e3 * 0.0048) = 0.5 / 77.28 = 6.4699793e-3 per newton
    assert close(PAPER.compliance_per_n, COMPLIANCE)
    assert abs(PAPER.compliance_per_n - 6.4699e-3) < 1e-7


def test_worked_example_load_state() -> None:
    state = load_state(np.array(EXAMPLE_FORCES), PAPER)
    assert state.fz_n == 8.0  # 1 + 3 + 2 + 2, exact in binary
    assert close(state.theta_x_rad, THETA_X)
    assert state.theta_y_rad == 0.0
    assert close(math.degrees(state.theta_x_rad), 0.06005848009)
    # u' = (0, -sin theta_x, cos theta_x), sin theta_x = A_X exactly by construction
    u = state.normal
    assert abs(u[0]) <= TOL.float64_abs
    assert close(u[1], -A_X)
    assert close(u[2], math.sqrt(1.0 - A_X**2))  # cos theta_x = 0.9999994506
    assert close(float(np.linalg.norm(u)), 1.0)


def test_worked_example_depth_and_local_load() -> None:
    state = load_state(np.array(EXAMPLE_FORCES), PAPER)
    pts = np.array([[10.0, 0.0], [0.0, 10.0], [0.0, -10.0], [0.0, 0.0]])
    z = depth_deviation_mm(pts, state)
    # Z(10, 0) = 0 (no tilt about y); Z(0, +-10) = +-10 tan theta_x = +-1.048218605e-2 mm
    assert abs(z[0]) <= TOL.float64_abs
    assert close(z[1], 10 * TAN_X)
    assert close(z[1], 1.048218605e-2)
    assert close(z[2], -1.048218605e-2)
    assert z[3] == 0.0
    f = local_load_n(pts, state, PAPER)
    # F(10, 0) = F_Z = 8 N
    # F(0, 10) = 8 + 18 * 1.048218605e-2 = 8 + 0.1886793489 = 8.188679349 N
    # F(0, -10) = 8 - 0.1886793489 = 7.811320651 N
    assert close(f[0], 8.0)
    assert close(f[1], 8.188679349)
    assert close(f[2], 7.811320651)
    assert close(f[3], 8.0)


def test_worked_example_rectified_radius_at_20_mm() -> None:
    state = load_state(np.array(EXAMPLE_FORCES), PAPER)
    obs = np.array([[0.0, 20.0], [20.0, 0.0]])
    # On +y at r' = 20 mm: F = 8 + 18 * 20 * tan theta_x = 8 + 360 * 1.048218605e-3 = 8.377358698 N
    #   r = 20 (1 - 6.469979296e-3 * 8.377358698) = 20 (1 - 0.05420133) = 18.91597325 mm
    # On +x at r' = 20 mm: F = 8 N, r = 20 (1 - 8 * 6.469979296e-3) = 20 * 0.9482401656 = 18.96480331 mm
    factor = rectify_factor(obs, state, PAPER)
    assert close(factor[0], 0.9457986627)
    assert close(factor[1], 0.9482401656)
    rect = rectify_points_mm(obs, state, PAPER)
    assert abs(rect[0, 0]) <= TOL.float64_abs and abs(rect[1, 1]) <= TOL.float64_abs  # radial: direction kept
    assert close(rect[0, 1], 18.91597325)
    assert close(rect[1, 0], 18.96480331)
    # at the centre: stretch nu F_Z / (E A) = 8 * 6.469979296e-3 = 0.05175983437
    assert close(centre_stretch(state, PAPER), 0.05175983437)


def test_combined_tilt_with_unequal_separations() -> None:
    # kappa = 1 N/mm, S_X = 4 mm, S_Y = 10 mm; forces (1, 11, 6, 2) N:
    #   theta_x = asin((11 - 1) / (2 * 1 * 10)) = asin(0.5) = +30 deg (S_Y, not S_X: asin(10/8) would clip)
    #   theta_y = asin((2 - 6) / (2 * 1 * 4)) = asin(-0.5) = -30 deg
    #   Ry(-30) e_z = (-1/2, 0, sqrt3/2); Rx(30) (x, y, z) = (x, cy - sz, sy + cz)
    #   u' = (-1/2, -(1/2)(sqrt3/2), (sqrt3/2)(sqrt3/2)) = (-1/2, -sqrt3/4, 3/4)
    #   Z(x, y) = -(-x/2 - sqrt3 y / 4) / (3/4) = (2/3) x + (sqrt3/3) y
    #   F_Z = 20 N; F(x, y) = max(0, 20 + (2/3) x + (sqrt3/3) y)
    calib = default_calibration(hooke_n_per_mm=1.0, sensor_separation_mm=(4.0, 10.0))
    state = load_state(np.array([1.0, 11.0, 6.0, 2.0]), calib)
    assert close(state.theta_x_rad, math.pi / 6)
    assert close(state.theta_y_rad, -math.pi / 6)
    assert state.fz_n == 20.0
    np.testing.assert_allclose(state.normal, [-0.5, -math.sqrt(3) / 4, 0.75], rtol=0, atol=TOL.float64_abs)
    pts = np.array([[3.0, 0.0], [0.0, math.sqrt(3)], [-30.0, 0.0], [-45.0, 0.0], [30.0, 0.0]])
    # Z(3, 0) = 2; Z(0, sqrt3) = 1; Z(-30, 0) = -20; Z(-45, 0) = -30; Z(30, 0) = 20
    np.testing.assert_allclose(depth_deviation_mm(pts, state), [2.0, 1.0, -20.0, -30.0, 20.0], rtol=0, atol=1e-12 * 30)
    # F: 22, 21, max(0, 0) = 0, max(0, -10) = 0 (the floor), 40
    np.testing.assert_allclose(local_load_n(pts, state, calib), [22.0, 21.0, 0.0, 0.0, 40.0], atol=1e-11)


def test_normal_is_rx_times_ry_times_ez() -> None:
    # Independent check of u' = Rx(theta_x) Ry(theta_y) e_z with explicit matrices (spec §2 order).
    for tx, ty in [(0.3, -0.2), (-0.7, 0.4), (0.0, 1.1)]:
        rx = np.array([[1, 0, 0], [0, math.cos(tx), -math.sin(tx)], [0, math.sin(tx), math.cos(tx)]])
        ry = np.array([[math.cos(ty), 0, math.sin(ty)], [0, 1, 0], [-math.sin(ty), 0, math.cos(ty)]])
        expected = rx @ ry @ np.array([0.0, 0.0, 1.0])
        got = LoadState(fz_n=1.0, theta_x_rad=tx, theta_y_rad=ty).normal
        np.testing.assert_allclose(got, expected, rtol=0, atol=TOL.float64_abs)


@pytest.mark.parametrize(
    ("forces", "high_pt", "low_pt"),
    [
        # F2 (the +y side) > F1 (the -y side): load higher at +y
        ((1.0, 3.0, 2.0, 2.0), (0.0, 10.0), (0.0, -10.0)),
        # F1 > F2: higher at -y
        ((3.0, 1.0, 2.0, 2.0), (0.0, -10.0), (0.0, 10.0)),
        # F4 (the -x side) > F3 (the +x side): higher at -x
        ((2.0, 2.0, 1.0, 3.0), (-10.0, 0.0), (10.0, 0.0)),
        # F3 > F4: higher at +x
        ((2.0, 2.0, 3.0, 1.0), (10.0, 0.0), (-10.0, 0.0)),
        # both: F2 > F1 and F3 > F4 -> highest toward (+x, +y)
        ((1.0, 3.0, 3.0, 1.0), (10.0, 10.0), (-10.0, -10.0)),
    ],
)
def test_sign_rule_load_rises_toward_the_sensors_reading_more(
    forces: tuple[float, ...], high_pt: tuple[float, float], low_pt: tuple[float, float]
) -> None:
    state = load_state(np.array(forces), PAPER)
    f_high, f_low = local_load_n(np.array([high_pt, low_pt]), state, PAPER)
    # the worked example gives a 0.377 N difference over 20 mm for a 2 N imbalance; require a real gap
    assert f_high - f_low > 0.3
    # symmetric about the centre: F(p) + F(-p) = 2 F_Z while both are above the floor
    assert math.isclose(f_high + f_low, 2 * state.fz_n, abs_tol=1e-12)
    # the side pressed harder is stretched more, so it shrinks more when rectified
    fac_high, fac_low = rectify_factor(np.array([high_pt, low_pt]), state, PAPER)
    assert fac_high < fac_low


def test_asin_argument_is_clipped() -> None:
    # F2 - F1 = 3000 N: 3000 / (2 * 18 * 53) = 1.572 > 1 -> clipped to 1 -> theta_x = pi/2 (not NaN)
    # F4 - F3 = -3000 N -> clipped to -1 -> theta_y = -pi/2
    state = load_state(np.array([0.0, 3000.0, 3000.0, 0.0]), PAPER)
    assert state.theta_x_rad == pytest.approx(math.pi / 2, abs=TOL.float64_abs)
    assert state.theta_y_rad == pytest.approx(-math.pi / 2, abs=TOL.float64_abs)
    assert np.all(np.isfinite(state.normal))
    # just past the edge: 1908.001 / 1908 > 1 still clips to exactly pi/2
    edge = load_state(np.array([0.0, 1908.001, 0.0, 0.0]), PAPER)
    assert edge.theta_x_rad == pytest.approx(math.pi / 2, abs=TOL.float64_abs)
    # the downstream maps stay finite (the local-load floor and rectify floor keep them bounded)
    pts = np.array([[5.0, 5.0], [-5.0, -5.0], [0.0, 0.0]])
    assert np.all(np.isfinite(local_load_n(pts, state, PAPER)))
    assert np.all(np.isfinite(rectify_points_mm(pts, state, PAPER)))


def test_local_load_floor_is_zero_not_negative() -> None:
    # Unloaded probe, tiny tilt: forces (0, 0, 0, 1): F_Z = 1 N, theta_y = asin(1/1908) > 0,
    # F(x, 0) = 1 - 18 x tan theta_y = 1 - 18 x / 1908 (to 1e-7) -> 0 at x = 106 mm; at x = 200 it would be
    # 1 - 1.887 = -0.887 N without the floor.
    state = load_state(np.array([0.0, 0.0, 0.0, 1.0]), PAPER)
    f = local_load_n(np.array([[200.0, 0.0], [-200.0, 0.0]]), state, PAPER)
    assert f[0] == 0.0
    assert math.isclose(f[1], 1.0 + 18 * 200 / 1908, rel_tol=1e-6)  # 2.887 N on the -x side
    # with no load at all the local load and stretch are exactly zero, and rectification is the identity
    zero = load_state(np.zeros(4), PAPER)
    pts = np.array([[12.5, -7.0]])
    assert local_load_n(pts, zero, PAPER)[0] == 0.0
    np.testing.assert_array_equal(rectify_points_mm(pts, zero, PAPER), pts)
    assert centre_stretch(LoadState(-5.0, 0.0, 0.0), PAPER) == 0.0


def test_rectify_factor_floor() -> None:
    # F_Z = 400 N: 1 - 6.47e-3 * 400 = -1.588 -> would fold the image; floored at MIN_RECTIFY_FACTOR
    state = LoadState(fz_n=400.0, theta_x_rad=0.0, theta_y_rad=0.0)
    assert rectify_factor(np.array([[1.0, 2.0]]), state, PAPER)[0] == MIN_RECTIFY_FACTOR


def test_deform_inverts_rectify() -> None:
    # deform_points_mm solves p = p' (1 - c F(p')); rectifying the result must give p back.
    rng = np.random.default_rng(7)
    pts = rng.uniform(-30.0, 30.0, size=(200, 2))
    for forces in [EXAMPLE_FORCES, (0.5, 4.0, 3.5, 1.0), (6.0, 2.0, 1.0, 5.0)]:
        state = load_state(np.array(forces), PAPER)
        obs = deform_points_mm(pts, state, PAPER)
        # a real deformation: the observed points lie further out than the undeformed ones
        assert np.all(np.linalg.norm(obs, axis=1) >= np.linalg.norm(pts, axis=1))
        assert np.max(np.abs(obs - pts)) > 0.5
        np.testing.assert_allclose(rectify_points_mm(obs, state, PAPER), pts, rtol=0, atol=TOL.fixed_point_mm)
    # hand check on the +x axis with the worked example (F = 8 N there, independent of x):
    # p = p' (1 - 8 c) -> p' = 18.96480331 / 0.9482401656 = 20 mm
    state = load_state(np.array(EXAMPLE_FORCES), PAPER)
    back = deform_points_mm(np.array([[18.96480331, 0.0]]), state, PAPER)
    assert close(back[0, 0], 20.0)


# ---- force interpolation (forces arrive at the sensors' rate, frames at theirs: spec §2) ----


def test_interpolate_unsorted_samples() -> None:
    # samples at t = 2, 0, 1 s with values 20, 0, 10 N: the line f = 10 t; f(0.5) = 5, f(1.5) = 15
    out = interpolate_forces(np.array([2.0, 0.0, 1.0]), np.array([20.0, 0.0, 10.0]), np.array([0.5, 1.5]))
    assert out.shape == (2, 1)
    np.testing.assert_allclose(out[:, 0], [5.0, 15.0], rtol=0, atol=TOL.force_interp_n)


def test_the_samples_around_a_time_interpolate_as_all_of_them() -> None:
    """The prepare stage interpolates a frame's forces from samples_around alone: the same numbers to the bit as
    from every sample, between samples, on one, and beyond either end (held)."""
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.005, 0.02, 500))
    f = rng.uniform(0, 20, (500, 4))
    queries = [t[0] - 1.0, t[0], float(rng.uniform(t[0], t[-1])), t[250], (t[10] + t[11]) / 2, t[-1], t[-1] + 1.0]
    for q in queries:
        near_t, near_f = samples_around(t, f, q)
        assert 1 <= len(near_t) <= 2
        np.testing.assert_array_equal(
            interpolate_forces(near_t, near_f, np.array([q])), interpolate_forces(t, f, np.array([q]))
        )


def test_interpolate_repeated_timestamps_are_averaged() -> None:
    # overlapping batches repeat t = 1: values 10 and 30 -> mean 20; f(0.5) = (0 + 20)/2 = 10,
    # f(1) = 20, f(1.5) = (20 + 40)/2 = 30
    t = np.array([0.0, 1.0, 1.0, 2.0])
    f = np.array([0.0, 10.0, 30.0, 40.0])
    out = interpolate_forces(t, f, np.array([0.5, 1.0, 1.5]))
    np.testing.assert_allclose(out[:, 0], [10.0, 20.0, 30.0], rtol=0, atol=TOL.force_interp_n)


def test_interpolate_holds_the_ends() -> None:
    t = np.array([1.0, 2.0])
    f = np.array([[3.0, 4.0], [5.0, 8.0]])
    out = interpolate_forces(t, f, np.array([-10.0, 0.999, 2.001, 99.0]))
    np.testing.assert_allclose(out, [[3.0, 4.0], [3.0, 4.0], [5.0, 8.0], [5.0, 8.0]], rtol=0, atol=0)
    # a single sample is held everywhere
    one = interpolate_forces(np.array([5.0]), np.array([[1.0, 2.0, 3.0, 4.0]]), np.array([0.0, 5.0, 9.0]))
    np.testing.assert_array_equal(one, np.tile([1.0, 2.0, 3.0, 4.0], (3, 1)))


def test_interpolate_four_channels_independently() -> None:
    # channel c is the line f_c(t) = (c + 1) * t + 10 c, sampled at 100 Hz, shuffled;
    # at t = 0.1234 s: f = 0.1234, 10.2468, 20.3702, 30.4936 N (linear interpolation is exact on lines)
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 1.0, 0.01)
    f = np.stack([(c + 1) * t + 10 * c for c in range(4)], axis=1)
    order = rng.permutation(len(t))
    out = interpolate_forces(t[order], f[order], 0.1234)
    assert out.shape == (1, 4)
    np.testing.assert_allclose(out[0], [0.1234, 10.2468, 20.3702, 30.4936], rtol=0, atol=1e-12)


def test_interpolate_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match="no force samples"):
        interpolate_forces(np.array([]), np.zeros((0, 4)), np.array([0.0]))
    # 4 times but 5 rows must not be silently reshaped into 5 channels
    with pytest.raises(ValueError, match="rows"):
        interpolate_forces(np.arange(4.0), np.zeros((5, 4)), np.array([0.0]))
