"""The simulator's imaging: zero-load view = the world through the lens, the true deformation, the window."""

from __future__ import annotations

from functools import cache

import cv2
import numpy as np
import pytest

from services.core.physics.camera import distort_points_px
from services.core.physics.force_model import LoadState
from services.core.simulation.probe_path import rotation
from services.core.simulation.renderer import (
    DARK_LEVEL,
    UNMODELLED_RADIAL,
    FrameGeometry,
    Imaging,
    TissueLaw,
    apply_imaging,
    frame_geometry,
    motion_blur_kernel,
    render_scene,
    true_undeformed_mm,
    vignette_gain,
)
from services.core.simulation.scenarios import nominal_calibration
from services.core.simulation.vein_texture import World, make_world

CALIB = nominal_calibration()


@cache
def world() -> World:
    return make_world(np.random.default_rng(4), (-60.0, -50.0, 60.0, 50.0), CALIB.px_per_mm)


@cache
def geometry() -> FrameGeometry:
    return frame_geometry(CALIB)


def sample(img: np.ndarray, xy_px: np.ndarray) -> np.ndarray:
    """Bilinear samples of img at (N, 2) pixel positions."""
    m = np.asarray(xy_px, np.float32).reshape(-1, 1, 2)
    return cv2.remap(img, m[..., 0], m[..., 1], cv2.INTER_LINEAR).ravel()


def test_unloaded_frame_is_the_world_patch_seen_through_the_lens() -> None:
    centre, yaw = np.array([3.0, -4.0]), 7.0
    scene = render_scene(world(), geometry(), centre, yaw, LoadState(0.0, 0.0, 0.0), CALIB)
    # independent route: ideal pixel q -> lens distortion (forward model) -> where the raw frame shows it
    rng = np.random.default_rng(0)
    q = rng.uniform((40, 40), (360, 280), (2000, 2))
    raw = distort_points_px(q, CALIB)
    cx, cy = CALIB.principal_point
    world_mm = ((q - (cx, cy)) / CALIB.px_per_mm) @ rotation(yaw).T + centre
    expected = sample(world().image, world().mm_to_px(world_mm))
    got = sample(scene, raw)
    # two bilinear resamplings of a band-limited image (blur sigma >= 0.9 px, values 0..1): interpolation
    # error is ~1e-3 (measured 0.0008 mean, 0.007 max); skipping the lens model gives 0.012 mean
    assert np.abs(got - expected).mean() < 0.002
    assert np.abs(got - expected).max() < 0.015
    # ... and sampling at the wrong (undistorted) place is clearly worse: the check has teeth
    assert np.abs(sample(scene, q) - expected).mean() > 3 * np.abs(got - expected).mean()


def test_true_deformation_matches_its_formula() -> None:
    g = geometry()
    true_calib = CALIB.with_overrides(young_modulus_kpa=15.0, hooke_n_per_mm=19.0)
    state = LoadState(10.0, 0.0, 0.0)
    p = true_undeformed_mm(g, state, true_calib)
    obs = g.observed_mm
    r2 = np.sum(obs * obs, axis=-1)
    c = 0.5 / (15.0e3 * 0.0048)
    factor = 1 - c * 10.0 * (1 + UNMODELLED_RADIAL * r2 / 625.0)
    np.testing.assert_allclose(p, obs * factor[..., None], rtol=1e-12)  # the same closed form: rounding only
    # pressing stretches the skin: every point appears farther out than it is
    assert np.all(np.linalg.norm(p, axis=-1) <= np.linalg.norm(obs, axis=-1) + 1e-12)
    # without the radial term (as the shared scans are) the strain is the same over the whole window
    flat = true_undeformed_mm(g, state, true_calib, TissueLaw("linear", c, radial=0.0))
    np.testing.assert_allclose(flat, obs * (1 - c * 10.0), rtol=1e-12)
    assert np.abs(flat - p).max() > 0.01  # mm: the term's 5 % of a 7 % strain at 25 mm shows (the check has teeth)


def test_an_anisotropy_fixed_in_the_tissue_turns_against_the_probe() -> None:
    # 5 % anisotropy along the world's x axis: with the probe yawed 90 deg it lies along the frame's y axis (as an
    # axis in the probe at 90 deg); an axis in the probe stays where it is in the frame whatever the yaw
    g = geometry()
    state = LoadState(10.0, 0.0, 0.0)
    c = CALIB.compliance_per_n
    tissue = TissueLaw("linear", c, anisotropy=0.05, anisotropy_axis="tissue")
    probe = TissueLaw("linear", c, anisotropy=0.05, anisotropy_axis="probe")
    turned = TissueLaw("linear", c, anisotropy=0.05, anisotropy_axis="probe", anisotropy_angle_deg=90.0)
    at = lambda law, yaw: true_undeformed_mm(g, state, CALIB, law, yaw)  # noqa: E731
    np.testing.assert_allclose(at(tissue, 90.0), at(turned, 0.0), atol=1e-12)
    np.testing.assert_allclose(at(tissue, 0.0), at(probe, 0.0), atol=1e-12)
    np.testing.assert_allclose(at(probe, 90.0), at(probe, 0.0), atol=1e-12)
    assert np.abs(at(tissue, 90.0) - at(tissue, 0.0)).max() > 0.02  # mm: the turn shows (0.05 x 4 % x 20 mm)
    # along the axis the skin strains (1 + 0.05) / (1 - 0.05) times as much as across it: the isotropic law's
    # strain there, times 1.05 and 0.95
    iso = true_undeformed_mm(g, state, CALIB, TissueLaw("linear", c))
    strain_iso = g.observed_mm - iso
    np.testing.assert_allclose(g.observed_mm - at(probe, 0.0), strain_iso * [1.05, 0.95], atol=1e-12)


def test_every_curved_law_has_the_calibrations_secant_at_its_anchor() -> None:
    # the calibration's E is the secant compliance at the loads a normal press uses (spec §2): each law's strain at
    # the anchor load is c times it; below it the curved laws strain more than the linear one, above it less
    for kind in ("stiffening", "power", "toe", "saturating"):
        law = TissueLaw(kind, 0.006, anchor_n=7.0)
        assert float(law.strain(7.0)) == pytest.approx(0.042, rel=1e-12), kind
        assert float(law.strain(3.0)) > 0.018 and float(law.strain(12.0)) < 0.072, kind


def test_tilt_raises_the_load_toward_the_sensor_that_reads_more() -> None:
    g = geometry()
    state = LoadState(10.0, np.deg2rad(0.2), 0.0)  # theta_x > 0: F2 (+y side) reads more
    p = true_undeformed_mm(g, state, CALIB)
    cx, cy = (round(v) for v in CALIB.principal_point)
    down, up = (cx, cy + 120), (cx, cy - 120)  # +y and -y, 15 mm out
    shrink = lambda yx: np.linalg.norm(p[yx[1], yx[0]]) / np.linalg.norm(g.observed_mm[yx[1], yx[0]])  # noqa: E731
    assert shrink(down) < shrink(up)  # more load, more stretch on the +y side


def test_window_mask_is_a_rounded_rectangle_almost_filling_the_frame() -> None:
    mask = geometry().mask > 0
    ys, xs = np.nonzero(mask)
    # 624 x 464 px centred in the 640 x 480 frame, as the shared scans' mask.png: pixels 8..631 and 8..471
    assert (xs.min(), xs.max(), ys.min(), ys.max()) == (8, 631, 8, 471)
    # corners are cut by the 40 px radius: the bounding box's corner pixels are outside, edge middles inside
    assert not mask[8, 8] and not mask[471, 631] and mask[8, 320] and mask[240, 8]
    assert mask.mean() == pytest.approx(0.937, abs=0.005)  # the shared scans' mask covers 93.7 %


def test_vignette_is_brightest_in_the_centre_and_falls_off_like_the_shared_scans() -> None:
    v = vignette_gain(CALIB)
    # measured on the shared scans (median frame, normalised): ~0.88 at the edges' middles, ~0.78 near the
    # corners; +-0.03 covers the two scans' difference and the slight left-right imbalance
    assert v[240, 320] == pytest.approx(1.0, abs=0.01)
    assert v[240, 10] == pytest.approx(0.88, abs=0.03) and v[240, 629] == pytest.approx(0.88, abs=0.03)
    assert v[10, 320] == pytest.approx(0.88, abs=0.03) and v[469, 320] == pytest.approx(0.88, abs=0.03)
    assert v[20, 20] == pytest.approx(0.78, abs=0.03)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_imaging_quantises_masks_and_adds_noise(dtype: type) -> None:
    g = geometry()
    scene = np.full(g.mask.shape, 0.6, np.float32)
    out = apply_imaging(scene, g, Imaging(noise_dn=3.0, dtype=dtype), np.random.default_rng(1))
    assert out.dtype == dtype
    x = out.astype(np.float64) / np.iinfo(dtype).max
    inner = cv2.erode(g.mask, np.ones((3, 3), np.uint8)) > 0
    # the noise is given in 8-bit grey levels whatever the bit depth: 3 DN = 3/255 of full scale; inside the
    # window the vignette varies smoothly, so neighbour differences see the noise alone (std sqrt(2) sigma)
    diff = np.diff(x * 255.0, axis=1)[inner[:, 1:] & inner[:, :-1]]
    assert diff.std() / np.sqrt(2.0) == pytest.approx(3.0, rel=0.05)  # 1e5 samples: sampling error < 1 %
    outside = x[cv2.dilate(g.mask, np.ones((3, 3), np.uint8)) == 0]
    # outside: ~1.5 DN of black plus noise clipped at 0, so its mean sits a little above DARK_LEVEL
    assert DARK_LEVEL < outside.mean() < DARK_LEVEL + 2.0 / 255.0
    inside = x[cv2.erode(g.mask, np.ones((3, 3), np.uint8)) > 0]
    gain = g.vignette[cv2.erode(g.mask, np.ones((3, 3), np.uint8)) > 0]
    assert np.mean(inside - 0.6 * gain) == pytest.approx(0.0, abs=0.002)


def test_motion_blur_kernel_is_normalised_and_directional() -> None:
    k = motion_blur_kernel(9, 0.0)
    assert k.sum() == pytest.approx(1.0, abs=1e-6)
    assert k.shape == (9, 9)
    rows, cols = np.nonzero(k > 0.01)
    assert np.ptp(cols) >= 6 and np.ptp(rows) <= 2  # a horizontal streak
    kv = motion_blur_kernel(9, 90.0)
    rows, cols = np.nonzero(kv > 0.01)
    assert np.ptp(rows) >= 6 and np.ptp(cols) <= 2
