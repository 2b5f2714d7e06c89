"""Simulated scans: shapes, determinism, truth consistency, force streams and imaging of every scenario."""

from __future__ import annotations

from functools import cache

import cv2
import numpy as np
import pytest

from services.core.inputs.scan import Scan
from services.core.physics.force_model import LoadState, interpolate_forces, load_state
from services.core.simulation.probe_path import MIN_SENSOR_FORCE_N, sensor_forces
from services.core.simulation.renderer import DARK_LEVEL
from services.core.simulation.scenarios import (
    FORCE_NOISE_N,
    FORCE_OFFSET_N,
    NOMINAL_E_KPA,
    NOMINAL_KAPPA_N_PER_MM,
    SCENARIOS,
    STREAM_MARGIN_S,
    nominal_calibration,
    simulate,
)
from tests.services.core.physics.test_rectification import rectify_image

SEED = 11


@cache
def sim(scenario: str, seed: int = SEED, imaging: str = "realistic") -> Scan:
    """One simulation per (scenario, seed, imaging) for the whole module (the raster takes a few seconds), with its
    IMU stream (simulate(..., imu=True))."""
    return simulate(scenario, seed, imaging, imu=True)


def test_unknown_scenario_is_rejected() -> None:
    with pytest.raises(ValueError, match="unknown scenario"):
        simulate("nope", 1)


def test_an_imu_stream_only_when_asked_or_for_the_calibration_scan() -> None:
    # the shared scans have no imu.csv: by default the tilt must come from the images; the same motion either way
    plain, with_imu = simulate("short", 5), sim("short", 5)
    assert plain.imu_t_s is None and plain.imu_tilt_deg is None
    assert with_imu.imu_t_s is not None and len(with_imu.imu_t_s) > len(plain)
    np.testing.assert_array_equal(plain.forces_n, with_imu.forces_n)
    np.testing.assert_array_equal(plain.reference_mm, with_imu.reference_mm)
    assert simulate("calib", 5).imu_t_s is not None


def test_same_seed_gives_identical_scan_and_other_seed_differs() -> None:
    a, b, c = simulate("short", 5, imu=True), simulate("short", 5, imu=True), simulate("short", 6, imu=True)
    for name in ("frame_t_s", "force_t_s", "forces_n", "imu_t_s", "imu_tilt_deg", "reference_mm", "mask"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert a.truth == b.truth
    for k in range(len(a)):
        np.testing.assert_array_equal(a.frame(k), b.frame(k))
    assert not np.array_equal(a.frame(0), c.frame(0))
    assert a.truth["young_modulus_kpa"] != c.truth["young_modulus_kpa"]


def test_the_radial_term_changes_the_frames_alone() -> None:
    # simulate(radial=0) renders the same scan (motion, forces, truth) without the strain's growth to the rim
    plain, flat = sim("short", 5), simulate("short", 5, imu=True, radial=0.0)
    for name in ("frame_t_s", "forces_n", "imu_tilt_deg", "reference_mm", "mask"):
        np.testing.assert_array_equal(getattr(plain, name), getattr(flat, name), err_msg=name)
    assert plain.truth["tissue"]["radial"] > 0 and flat.truth["tissue"]["radial"] == 0.0
    assert {k: v for k, v in plain.truth.items() if k != "tissue"} == {
        k: v for k, v in flat.truth.items() if k != "tissue"
    }
    assert not np.array_equal(plain.frame(len(plain) - 1), flat.frame(len(flat) - 1))


@pytest.mark.parametrize(
    ("scenario", "n_frames", "dtype"),
    [("raster", 336, np.uint8), ("revisit", 240, np.uint8), ("hard", 200, np.uint16), ("short", 40, np.uint8),
     ("calib", 24, np.uint8)],
)  # fmt: skip
def test_scenario_shapes(scenario: str, n_frames: int, dtype: type) -> None:
    scan = sim(scenario)
    assert len(scan) == n_frames
    np.testing.assert_array_equal(scan.frame_seq, np.arange(n_frames))
    assert np.all(np.diff(scan.frame_t_s) > 0.05)  # ~10 Hz with +-10 ms jitter
    assert scan.forces_n.shape == (len(scan.force_t_s), 4)
    assert scan.imu_tilt_deg is not None and scan.imu_tilt_deg.shape == (len(scan.imu_t_s), 2)
    assert scan.reference_mm is not None and scan.reference_mm.shape == (n_frames, 2)
    w, h = scan.calibration.image_size
    for k in (0, n_frames - 1):
        frame = scan.frame(k)
        assert frame.shape == (h, w) and frame.dtype == dtype
    truth = scan.truth
    assert truth["scenario"] == scenario and truth["seed"] == SEED
    assert len(truth["poses"]) == len(truth["fz_n"]) == n_frames
    # the scan carries the nominal constants; the truth is 4-10% (E) and up to 10% (kappa) off them
    assert scan.calibration == nominal_calibration()
    assert 0.04 - 1e-12 <= abs(truth["young_modulus_kpa"] / NOMINAL_E_KPA - 1) <= 0.10 + 1e-12
    assert abs(truth["hooke_n_per_mm"] / NOMINAL_KAPPA_N_PER_MM - 1) <= 0.10 + 1e-12


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_reference_poses_and_path_length_agree(scenario: str) -> None:
    scan = sim(scenario)
    poses = np.asarray(scan.truth["poses"])
    np.testing.assert_array_equal(poses[0], [0.0, 0.0, 0.0])
    # the same numbers by two routes; float64 rounding only
    np.testing.assert_allclose(scan.reference_mm, poses[:, :2], atol=1e-12)
    steps = np.linalg.norm(np.diff(scan.reference_mm, axis=0), axis=1)
    assert scan.truth["path_length_mm"] == pytest.approx(float(steps.sum()), abs=1e-9)


def test_raster_path_is_a_long_serpentine_with_overlapping_rows() -> None:
    scan = sim("raster")
    assert scan.truth["path_length_mm"] == pytest.approx(1274.0, rel=0.05)
    steps = np.linalg.norm(np.diff(scan.reference_mm, axis=0), axis=1)
    assert steps.max() < 8.0  # consecutive frames overlap > 80% of the 50 mm view
    yaw = np.asarray(scan.truth["poses"])[:, 2]
    assert np.abs(yaw).max() <= 3.0  # yaw drifts within a few degrees
    fz = np.asarray(scan.truth["fz_n"])
    assert 1.99 <= fz.min() < 4.0 and 10.0 < fz.max() <= 12.01
    # 30 % of frames blurred by 2-5 px (binomial over 335 frames: std 2.5 %, so +-8 % is > 3 sigma)
    blur = np.asarray(scan.truth["blur_px"])
    assert 0.22 <= len(scan.truth["blurred"]) / len(scan) <= 0.38
    np.testing.assert_array_equal(np.flatnonzero(blur), scan.truth["blurred"])
    assert blur[blur > 0].min() >= 2 and blur.max() <= 5


def test_hard_has_long_steps_large_yaw_and_quick_loads() -> None:
    scan = sim("hard")
    steps = np.linalg.norm(np.diff(scan.reference_mm, axis=0), axis=1)
    assert 12.0 < steps.max() <= 18.0 + 1e-9
    yaw = np.asarray(scan.truth["poses"])[:, 2]
    assert 8.0 < np.abs(yaw).max() <= 10.0 + 1e-9
    fz = np.asarray(scan.truth["fz_n"])
    assert fz.min() < 8.0 and fz.max() > 25.0
    assert np.abs(np.diff(fz)).max() > 3.0  # loads change quickly between frames
    assert len(scan.truth["blurred"]) >= 3


def test_revisit_returns_over_its_start() -> None:
    xy = sim("revisit").reference_mm
    dist_to_start = np.linalg.norm(xy, axis=1)
    # after leaving by more than a view width, the probe comes back within a few mm of frame 0
    far = int(np.argmax(dist_to_start > 60.0))
    assert far > 0 and dist_to_start[far:].min() < 5.0


def test_calib_sequence_is_unloaded_then_normal_then_tilted_at_one_place() -> None:
    scan = sim("calib")
    t = scan.truth
    np.testing.assert_array_equal(np.asarray(t["poses"]), 0.0)
    fz = np.asarray(t["fz_n"])
    tilt = np.stack([t["tilt_x_deg"], t["tilt_y_deg"]], axis=1)
    assert fz[0] == pytest.approx(0.3, rel=0.05)
    assert np.all(np.diff(fz[1:16]) > 0) and fz[1] == pytest.approx(2.0, rel=0.05)
    assert fz[15] == pytest.approx(20.0, rel=0.05)
    np.testing.assert_array_equal(tilt[:16], 0.0)
    assert np.all(np.abs(tilt[16:]).max(axis=1) > 0.2) and np.abs(tilt).max() <= 0.5


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_forces_are_feasible_and_recover_the_true_load(scenario: str) -> None:
    scan = sim(scenario)
    t = scan.truth
    calib = nominal_calibration()
    assert scan.force_t_s[0] == pytest.approx(scan.frame_t_s[0] - STREAM_MARGIN_S, abs=1e-9)
    assert scan.force_t_s[-1] >= scan.frame_t_s[-1] + STREAM_MARGIN_S - 0.011
    assert np.all(np.diff(scan.force_t_s) > 0) and np.all(np.diff(scan.imu_t_s) > 0)
    rate = (len(scan.force_t_s) - 1) / (scan.force_t_s[-1] - scan.force_t_s[0])
    assert rate == pytest.approx(100.0, rel=0.02)
    true = sensor_forces(
        np.asarray(t["fz_n"]),
        np.deg2rad(t["tilt_x_deg"]),
        np.deg2rad(t["tilt_y_deg"]),
        t["hooke_n_per_mm"],
        calib.sensor_separation_mm,
    )
    assert true.min() >= MIN_SENSOR_FORCE_N - 1e-9
    measured = interpolate_forces(scan.force_t_s, scan.forces_n, scan.frame_t_s)
    # measured F_Z = true + four offsets (|.| <= 0.1 N) + interpolated noise (sigma <= 0.06 N for 4 sensors)
    fz_err = measured.sum(axis=1) - np.asarray(t["fz_n"])
    assert np.abs(fz_err).max() < 4 * FORCE_OFFSET_N + 6 * 2 * FORCE_NOISE_N
    assert np.mean(fz_err) == pytest.approx(sum(t["force_offsets_n"]), abs=0.05)


def test_sensor_nearer_the_tilt_reads_more_and_imu_tracks_the_tilts() -> None:
    scan = sim("raster")
    t = scan.truth
    f = sensor_forces(np.asarray(t["fz_n"]), np.deg2rad(t["tilt_x_deg"]), np.deg2rad(t["tilt_y_deg"]),
                      t["hooke_n_per_mm"], (53.0, 53.0))  # fmt: skip
    tx, ty = np.asarray(t["tilt_x_deg"]), np.asarray(t["tilt_y_deg"])
    assert (tx > 0.01).any() and (tx < -0.01).any()
    assert np.all((f[:, 1] > f[:, 0]) == (tx > 0)) and np.all((f[:, 3] > f[:, 2]) == (ty > 0))
    # spec §2 applied to the true forces with the true kappa gives back the true tilts (float64 rounding)
    calib = nominal_calibration().with_overrides(hooke_n_per_mm=t["hooke_n_per_mm"])
    state = load_state(f[7], calib)
    assert np.rad2deg(state.theta_x_rad) == pytest.approx(tx[7], abs=1e-9)
    assert np.rad2deg(state.theta_y_rad) == pytest.approx(ty[7], abs=1e-9)
    assert state.fz_n == pytest.approx(t["fz_n"][7], abs=1e-9)
    imu = interpolate_forces(scan.imu_t_s, scan.imu_tilt_deg, scan.frame_t_s)
    # IMU noise is 0.01 deg; interpolating 50 Hz samples of a smooth tilt adds far less
    np.testing.assert_allclose(imu, np.stack([tx, ty], axis=1), atol=0.05)


@pytest.mark.parametrize("scenario", ["short", "hard"])
def test_window_mask_is_applied(scenario: str) -> None:
    scan = sim(scenario)
    frame = scan.frame(3).astype(np.float64)
    full = float(np.iinfo(scan.frame(3).dtype).max)
    mask = scan.mask > 0
    w, h = scan.calibration.image_size
    assert 0.93 < mask.mean() < 0.945  # ~ (624 x 464 - corners) / (640 x 480), as the shared scans' 93.7 %
    assert not mask[0, 0] and not mask[-1, -1] and mask[h // 2, w // 2]
    # outside: dark grey + noise; inside (away from the soft edge): skin well above it
    outside = frame[cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8)) == 0] / full
    inside = frame[cv2.erode(mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0] / full
    assert abs(outside.mean() - DARK_LEVEL) < 0.01 and outside.max() < 0.2
    assert inside.mean() > 0.35


def test_textured_variant_is_the_easy_one_with_many_sift_keypoints() -> None:
    sift = cv2.SIFT_create(nfeatures=0)
    easy, real = sim("short", SEED, "textured"), sim("short")
    easy_counts = [len(sift.detect(easy.frame(k), easy.mask)) for k in range(0, len(easy), 8)]
    real_counts = [len(sift.detect(real.frame(k), real.mask)) for k in range(0, len(real), 8)]
    # measured: textured ~300-600 per frame, realistic 10-40 (the shared scans: 3-57)
    assert np.mean(easy_counts) >= 200, easy_counts
    assert np.mean(real_counts) < 60, real_counts
    # the look never changes the motion: same poses, loads and forces for the same seed
    assert easy.truth["poses"] == real.truth["poses"] and easy.truth["fz_n"] == real.truth["fz_n"]
    np.testing.assert_array_equal(easy.forces_n, real.forces_n)


def test_truth_poses_agree_with_the_image_content() -> None:
    """Rectify with the TRUE constants and loads, match SIFT to frame 0: the similarity is the truth pose.

    On the textured variant, whose many keypoints make plain SIFT a trustworthy independent measurement; the
    geometry (motion, deformation, lens) is the same for every variant (asserted in the test above)."""
    scan = sim("short", SEED, "textured")
    t = scan.truth
    calib = scan.calibration.with_overrides(
        young_modulus_kpa=t["young_modulus_kpa"], hooke_n_per_mm=t["hooke_n_per_mm"]
    )
    pp = np.array(calib.principal_point)
    sift = cv2.SIFT_create()

    def features(k: int) -> tuple[np.ndarray, np.ndarray]:
        state = LoadState(t["fz_n"][k], np.deg2rad(t["tilt_x_deg"][k]), np.deg2rad(t["tilt_y_deg"][k]))
        img, mask = rectify_image(scan.frame(k), calib, state), rectify_image(scan.mask, calib, state)
        kp, desc = sift.detectAndCompute(img, cv2.erode(mask, np.ones((9, 9), np.uint8)))
        return (np.array([p.pt for p in kp]) - pp) / calib.px_per_mm, desc

    q0, d0 = features(0)
    for k in (1, 3):
        pk, dk = features(k)
        good = [a for a, b in cv2.BFMatcher().knnMatch(dk, d0, k=2) if a.distance < 0.75 * b.distance]
        src = pk[[m.queryIdx for m in good]]
        dst = q0[[m.trainIdx for m in good]]
        A, inliers = cv2.estimateAffinePartial2D(src, dst, method=cv2.RANSAC, ransacReprojThreshold=0.3)
        assert inliers.sum() >= 20
        x, y, yaw = t["poses"][k]
        # the unmodelled radial term leaves <= 0.05 * 8% stretch * 25 mm = 0.1 mm at the view's edge, and
        # feature positions are good to ~0.1 px = 0.01 mm: 0.15 mm / 0.2 deg; a sign or centre slip is mm
        assert A[0, 2] == pytest.approx(x, abs=0.15) and A[1, 2] == pytest.approx(y, abs=0.15)
        assert np.rad2deg(np.arctan2(A[1, 0], A[0, 0])) == pytest.approx(yaw, abs=0.2)
        assert np.hypot(A[0, 0], A[1, 0]) == pytest.approx(1.0, abs=0.005)
