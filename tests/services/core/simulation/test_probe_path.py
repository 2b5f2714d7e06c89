"""Simulated probe motion: sensor forces invert spec §2, tilts stay feasible, routes and speeds behave."""

from __future__ import annotations

import numpy as np
import pytest

from services.core.inputs.calibration import default_calibration
from services.core.physics.force_model import load_state
from services.core.simulation.probe_path import (
    MIN_SENSOR_FORCE_N,
    calibration_motion,
    dense_grid,
    frame_times,
    free_hand_motion,
    path_length_mm,
    sample_route,
    scenario_motion_spec,
    sensor_forces,
    serpentine_route,
    smooth_noise,
    smooth_tilts,
)


def test_sensor_forces_invert_spec_2() -> None:
    calib = default_calibration(hooke_n_per_mm=17.0, sensor_separation_mm=(50.0, 56.0))
    f = sensor_forces(np.array(12.0), np.deg2rad(0.1), np.deg2rad(-0.05), 17.0, (50.0, 56.0))
    state = load_state(f, calib)
    # spec §2 applied to forces built by its inverse: float64 rounding only
    assert state.fz_n == pytest.approx(12.0, abs=1e-12)
    assert np.rad2deg(state.theta_x_rad) == pytest.approx(0.1, abs=1e-10)
    assert np.rad2deg(state.theta_y_rad) == pytest.approx(-0.05, abs=1e-10)
    # sign: theta_x > 0 loads F2 (+y side) over F1; theta_y < 0 loads F3 (+x side) over F4
    assert f[1] > f[0] and f[2] > f[3]


def test_smooth_noise_spans_the_range_and_is_smooth() -> None:
    x = smooth_noise(np.random.default_rng(0), 1000, 20.0, -2.0, 3.0)
    assert x.min() == pytest.approx(-2.0) and x.max() == pytest.approx(3.0)
    assert np.abs(np.diff(x)).max() < 0.3  # sigma 20 samples: no jumps


def test_tilts_are_always_feasible() -> None:
    rng = np.random.default_rng(3)
    grid = dense_grid(frame_times(rng, 100, 10.0))
    fz = np.linspace(0.3, 30.0, len(grid))
    tx, ty = smooth_tilts(rng, grid, fz, 90.0, 18.0, (53.0, 53.0), 0.5)
    f = sensor_forces(fz, tx, ty, 18.0, (53.0, 53.0))
    assert f.min() >= MIN_SENSOR_FORCE_N
    assert np.rad2deg(np.abs(tx)).max() > 0.2  # with 30 N the feasible tilt reaches ~0.45 deg


def test_sample_route_keeps_frame_count_and_varies_speed() -> None:
    route = serpentine_route(100.0, 3, 18.0)
    pos = sample_route(np.random.default_rng(1), route, 120, 4.0, 0.2, 6.0)
    steps = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    assert pos.shape == (120, 2)
    assert steps.max() / steps.min() == pytest.approx(1.5, abs=0.15)  # (1 + 0.2) / (1 - 0.2)
    assert path_length_mm(pos) == pytest.approx(300 + 2 * 18, rel=0.05)  # corners are rounded a little


def test_free_hand_motion_starts_at_yaw_0_and_stays_within_amplitude() -> None:
    spec = scenario_motion_spec("short")
    m = free_hand_motion(np.random.default_rng(2), spec, 18.0, (53.0, 53.0))
    assert len(m) == spec.n_frames
    rel = m.yaw_deg - m.yaw_deg[0]
    assert np.abs(rel).max() == pytest.approx(spec.yaw_amplitude_deg)
    fz, _, _ = m.load_at(m.frame_t_s)
    assert spec.load_range_n[0] - 1e-9 <= fz.min() and fz.max() <= spec.load_range_n[1] + 1e-9
    assert m.grid_t_s[0] < m.frame_t_s[0] - 0.5 and m.grid_t_s[-1] > m.frame_t_s[-1] + 0.5


def test_calibration_motion_holds_loads_around_frames() -> None:
    m = calibration_motion(np.random.default_rng(5), 18.0, (53.0, 53.0))
    fz, tx, _ = m.load_at(m.frame_t_s)
    fz_near, _, _ = m.load_at(m.frame_t_s + 0.03)
    np.testing.assert_allclose(fz_near, fz, rtol=1e-12)  # held flat within +-40 ms of each frame
    assert len(m) == 24 and np.all(m.centre_mm == 0)
    assert np.all(tx[:16] == 0) and np.any(tx[16:] != 0)


def test_unknown_free_hand_scenario_is_rejected() -> None:
    with pytest.raises(ValueError, match="calib"):
        scenario_motion_spec("calib")
