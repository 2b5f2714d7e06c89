"""Calibration fits (spec §2 "Calibration"): E from stretch against load, kappa from IMU tilt vs force."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from services.core.calibration_fit import (
    calibrate_scan,
    fit_hooke,
    fit_young_modulus,
    format_calibration_report,
    measure_scales,
    measure_similarities,
)
from services.core.inputs.calibration import default_calibration
from services.core.inputs.scan import Scan, in_memory_loader

NU, AREA = 0.5, 0.0048
W, H = 400, 320
PX_PER_MM = 8.0


def _compliance(e_kpa: float) -> float:
    return NU / (e_kpa * 1000.0 * AREA)


# ------------------------------------------------------------------------------------------ pure fits


def test_fit_young_modulus_exact_scales() -> None:
    e_true, f0 = 16.1, 0.4
    c = _compliance(e_true)
    loads = np.array([2.0, 4.0, 6.5, 9.0, 12.0])
    scales = (1 - c * f0) / (1 - c * loads)
    fit = fit_young_modulus(f0, loads, scales, NU, AREA)
    # Exact synthetic scales satisfy the linearised equation exactly: only rounding error remains.
    assert fit.young_modulus_kpa == pytest.approx(e_true, rel=1e-9)
    assert fit.compliance_per_n == pytest.approx(c, rel=1e-9)
    assert fit.n_frames == 5
    assert fit.residual_rms < 1e-12
    np.testing.assert_allclose(fit.predicted_scales, scales, rtol=1e-12)


def test_fit_young_modulus_with_noise_and_nan() -> None:
    e_true, f0 = 9.0, 0.0
    c = _compliance(e_true)
    loads = np.linspace(2.0, 20.0, 10)
    rng = np.random.default_rng(3)
    sigma = 2e-4  # about what SIFT + RANSAC gives on a 400x320 frame (measured ~5e-5)
    scales = (1 - c * f0) / (1 - c * loads) + rng.normal(0.0, sigma, len(loads))
    scales[4] = np.nan  # a frame that failed to match is ignored
    fit = fit_young_modulus(f0, loads, scales, NU, AREA)
    # Predicted standard error of c: sigma / sqrt(sum a^2) ~ 2e-4 / 40 = 5e-6 on c ~ 0.0116, i.e. ~0.05 %
    # of E; 1 % is a wide margin that still catches any modelling error (e.g. using 1 + cF instead).
    assert fit.young_modulus_kpa == pytest.approx(e_true, rel=0.01)
    assert fit.n_frames == 9
    # The residual RMS estimates the noise level.
    assert 0.3 * sigma < fit.residual_rms < 2.0 * sigma


def test_fit_young_modulus_rejects_unobservable() -> None:
    with pytest.raises(ValueError, match="not observable"):
        fit_young_modulus(0.0, np.zeros(3), np.ones(3), NU, AREA)
    with pytest.raises(ValueError, match="does not grow"):
        fit_young_modulus(0.0, np.array([5.0, 10.0]), np.array([0.98, 0.95]), NU, AREA)
    with pytest.raises(ValueError, match="no frame"):
        fit_young_modulus(0.0, np.array([5.0]), np.array([np.nan]), NU, AREA)


def _imu_forces(
    kappa: float, sep: tuple[float, float], t_force: np.ndarray, t_imu: np.ndarray, base: float = 30.0
) -> tuple[np.ndarray, np.ndarray]:
    def tilts(t: np.ndarray) -> np.ndarray:
        return np.stack([0.8 * np.sin(2 * np.pi * t / 5.0), 0.6 * np.cos(2 * np.pi * t / 4.0)], axis=1)

    tt = tilts(t_force)
    s_x, s_y = sep
    d_y = 2 * kappa * s_y * np.sin(np.radians(tt[:, 0]))  # F2 - F1 (spec §2 inverse)
    d_x = 2 * kappa * s_x * np.sin(np.radians(tt[:, 1]))  # F4 - F3
    forces = np.stack([base - d_y / 2, base + d_y / 2, base - d_x / 2, base + d_x / 2], axis=1)
    return forces, tilts(t_imu)


def test_fit_hooke_exact() -> None:
    t = np.arange(0.0, 10.0, 0.01)
    sep = (50.0, 56.0)
    forces, tilt = _imu_forces(11.5, sep, t, t)
    fit = fit_hooke(t, tilt, t, forces, sep)
    # IMU at the force times: the data obey the model exactly, rounding only.
    assert fit.hooke_n_per_mm == pytest.approx(11.5, rel=1e-9)
    assert fit.residual_rms_n < 1e-9
    assert fit.n_samples > 1000


def test_fit_hooke_interpolated_and_not_enough_tilt() -> None:
    t_force = np.arange(0.0, 10.0, 0.01)
    t_imu = np.arange(0.003, 10.0, 0.02)  # 50 Hz, between force samples
    forces, tilt = _imu_forces(20.0, (53.0, 53.0), t_force, t_imu)
    fit = fit_hooke(t_imu, tilt, t_force, forces, (53.0, 53.0))
    # Linear interpolation of a 0.2-0.25 Hz sine at 100 Hz errs by ~2e-5 relative: 1e-3 is ample.
    assert fit.hooke_n_per_mm == pytest.approx(20.0, rel=1e-3)
    with pytest.raises(ValueError, match="not enough tilt"):
        fit_hooke(t_imu, tilt * 0.01, t_force, forces, (53.0, 53.0))
    with pytest.raises(ValueError, match="inside the force record"):
        fit_hooke(t_imu + 100.0, tilt, t_force, forces, (53.0, 53.0))


# --------------------------------------------------------------------------------- synthetic scan


def _texture(seed: int = 0) -> np.ndarray:
    """A random blob texture larger than the frame (vein-like contrast at a few-pixel scale)."""
    rng = np.random.default_rng(seed)
    noise = rng.normal(size=(H + 240, W + 240)).astype(np.float32)
    tex = cv2.GaussianBlur(noise, (0, 0), 2.5)
    return cv2.normalize(tex, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)


def _frame(tex: np.ndarray, stretch: float, shift_mm: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """The texture seen stretched by `stretch` about the principal point: r' = stretch * r (spec §2)."""
    cx, cy = (W - 1) / 2.0, (H - 1) / 2.0  # default_calibration's principal point
    tcx, tcy = (tex.shape[1] - 1) / 2.0, (tex.shape[0] - 1) / 2.0
    a = 1.0 / stretch
    sx, sy = shift_mm[0] * PX_PER_MM, shift_mm[1] * PX_PER_MM
    # Frame pixel p' shows texture point Tc + shift + (p' - c) / stretch.
    M = np.array([[a, 0.0, tcx + sx - a * cx], [0.0, a, tcy + sy - a * cy]])
    return cv2.warpAffine(tex, M, (W, H), flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP)


def _window_mask() -> np.ndarray:
    yy, xx = np.mgrid[:H, :W]
    return np.where((xx - (W - 1) / 2.0) ** 2 + (yy - (H - 1) / 2.0) ** 2 < 150.0**2, 255, 0).astype(np.uint8)


def _even(load: float) -> np.ndarray:
    return np.full(4, load / 4.0)


def _calib_scan(e_true: float, kappa_true: float, with_imu: bool = True, n_good: int = 5) -> Scan:
    calib = default_calibration(W, H, PX_PER_MM)  # defaults E = 16.1, kappa = 18: the fit must move them
    c = _compliance(e_true)
    tex = _texture()
    sep = calib.sensor_separation_mm
    frames, frame_forces = [], []
    # Reference, lightly loaded and untilted.
    frames.append(_frame(tex, 1.0 / (1 - c * 0.6)))
    frame_forces.append(_even(0.6))
    # Pressed normally at the same place.
    for load in [3.0, 5.0, 7.0, 9.0, 11.0][:n_good]:
        frames.append(_frame(tex, 1.0 / (1 - c * load)))
        frame_forces.append(_even(load))
    # Tilted 0.5 deg about x (F2 - F1 = 2 kappa S_Y sin 0.5deg) with a deliberately wrong scale:
    # must be excluded.
    d = 2 * kappa_true * sep[1] * math.sin(math.radians(0.5))
    frames.append(_frame(tex, 1.0))
    frame_forces.append(_even(24.0) + np.array([-d / 2, d / 2, 0.0, 0.0]))
    # Untilted but 10 mm away with a wrong scale: not "the same place", must be excluded.
    frames.append(_frame(tex, 1.2, (10.0, 4.0)))
    frame_forces.append(_even(6.0))
    mask = _window_mask()
    frames = [np.where(mask > 0, f, 0).astype(np.uint8) for f in frames]  # outside the window: dark
    n = len(frames)
    frame_t = np.arange(n, dtype=np.float64)
    # Force record at 100 Hz: each frame's forces held +-0.3 s around it, ramps in between; then an IMU
    # segment after the last frame where the probe rocks, forces from the spec's inverse tilt equations.
    knots_t = np.concatenate([[t - 0.3, t + 0.3] for t in frame_t])
    knots_f = np.repeat(np.array(frame_forces), 2, axis=0)
    t_frames = np.arange(-0.3, n - 0.7 + 1e-9, 0.01)
    f_frames = np.stack([np.interp(t_frames, knots_t, knots_f[:, k]) for k in range(4)], axis=1)
    imu_t = imu_tilt = None
    force_t, forces = t_frames, f_frames
    if with_imu:
        t_rock = np.arange(n + 1.0, n + 11.0, 0.01)
        f_rock, _ = _imu_forces(kappa_true, sep, t_rock - (n + 1.0), t_rock)
        imu_t = np.arange(n + 1.003, n + 11.0 - 0.01, 0.02)
        _, imu_tilt = _imu_forces(kappa_true, sep, imu_t, imu_t - (n + 1.0))
        force_t, forces = np.concatenate([t_frames, t_rock]), np.concatenate([f_frames, f_rock])
    return Scan(
        calibration=calib,
        frame_seq=np.arange(n),
        frame_t_s=frame_t,
        force_t_s=force_t,
        forces_n=forces,
        frame_loader=in_memory_loader(frames),
        mask=mask,
        imu_t_s=imu_t,
        imu_tilt_deg=imu_tilt,
    )


def test_measure_scales_known_stretch() -> None:
    tex = _texture()
    stretches = [1.0, 1.03, 1.07, 1.11]
    frames = [_frame(tex, s) for s in stretches] + [_frame(_texture(seed=99), 1.0)]
    scan = Scan(
        calibration=default_calibration(W, H, PX_PER_MM),
        frame_seq=np.arange(5),
        frame_t_s=np.arange(5.0),
        force_t_s=np.arange(5.0),
        forces_n=np.zeros((5, 4)),
        frame_loader=in_memory_loader(frames),
    )
    meas = measure_similarities(scan, 0, [1, 2, 3, 4])
    # SIFT localisation (~0.1 px) over hundreds of inliers spread across ~200 px: observed errors ~5e-5;
    # 5e-4 is a 10x margin and still far below the 3 % smallest stretch step.
    np.testing.assert_allclose(meas.scales[:3], stretches[1:], atol=5e-4)
    # Stretch about the principal point does not move the centre content (shift < 0.05 mm = 0.4 px).
    assert np.all(np.abs(meas.shifts_mm[:3]) < 0.05)
    assert np.all(meas.inliers[:3] >= 100)
    # An unrelated texture cannot be matched: NaN.
    assert np.isnan(meas.scales[3]) and np.isnan(meas.shifts_mm[3]).all()
    np.testing.assert_array_equal(measure_scales(scan, 0, [1, 2, 3, 4]), meas.scales)


def test_calibrate_scan_recovers_e_and_kappa() -> None:
    e_true, kappa_true = 12.0, 11.0
    scan = _calib_scan(e_true, kappa_true)
    result = calibrate_scan(scan)
    assert result.hooke is not None and result.modulus is not None, result.notes
    # kappa: IMU sampled between 100 Hz force samples of a smooth rocking; interpolation error ~1e-5.
    assert result.hooke.hooke_n_per_mm == pytest.approx(kappa_true, rel=1e-3)
    # E: scales come out ~2e-4 low inside the round window (a small SIFT localisation bias, 0.02 px at
    # 100 px), which is ~0.3 % on E (observed 12.04 kPa); 1 % bounds that with margin. Including the
    # tilted or moved frame (deliberately wrong scales) would be off by tens of percent.
    assert result.modulus.young_modulus_kpa == pytest.approx(e_true, rel=0.01)
    assert result.reference_seq == 0
    assert result.modulus_seq == (1, 2, 3, 4, 5)  # neither the tilted (6) nor the moved (7) frame
    assert result.modulus.n_frames == 5
    assert result.modulus.residual_rms < 5e-4
    assert result.calibration.young_modulus_kpa == pytest.approx(result.modulus.young_modulus_kpa)
    assert result.calibration.hooke_n_per_mm == pytest.approx(result.hooke.hooke_n_per_mm)
    assert result.calibration.image_size == scan.calibration.image_size
    text = format_calibration_report(result)
    assert f"Young's modulus E: {result.modulus.young_modulus_kpa:.3f} kPa" in text
    assert f"Hooke constant kappa: {result.hooke.hooke_n_per_mm:.4f} N/mm" in text
    assert text.count("\n        ") >= 5  # one table row per fitted frame
    assert "16.1 ->" in text and "18 ->" in text


def test_calibrate_scan_notes_what_it_cannot_fit() -> None:
    scan = _calib_scan(12.0, 11.0, with_imu=False, n_good=2)
    result = calibrate_scan(scan)
    assert result.hooke is None and result.modulus is None
    assert any("kappa not fitted" in n and "imu" in n.lower() for n in result.notes)
    assert any(n.startswith("E not fitted") for n in result.notes)
    assert result.calibration == scan.calibration  # nothing fitted, nothing changed
    text = format_calibration_report(result)
    assert "E: not fitted" in text and "kappa: not fitted" in text and "Notes:" in text


@pytest.mark.slow
def test_calibrate_scan_on_simulated_calib_scenario() -> None:
    from services.core.simulation.scenarios import simulate

    scan = simulate("calib", 1)
    result = calibrate_scan(scan)
    # The simulator's skin stretches 5 % more at 25 mm than spec §2 says (a deliberate unmodelled radial
    # term), so the similarity scale runs high and E comes out ~2 % low (seeds 1-3: -1.3 to -2.8 %);
    # kappa is within ~1.5 %. The brief's 5 % bounds both.
    assert result.modulus is not None and result.hooke is not None, result.notes
    assert result.modulus.young_modulus_kpa == pytest.approx(scan.truth["young_modulus_kpa"], rel=0.05)
    assert result.hooke.hooke_n_per_mm == pytest.approx(scan.truth["hooke_n_per_mm"], rel=0.05)
