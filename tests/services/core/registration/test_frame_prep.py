"""Per-frame preparation: window mask and flat field from frames, rectification and features in mm."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from services.core.inputs.scan import Scan
from services.core.methods import method_options
from services.core.physics.camera import mm_to_px, px_to_mm
from services.core.physics.force_model import LoadState, local_load_n
from services.core.physics.rectification import pixel_grid
from services.core.registration.frame_prep import (
    describe_frame,
    estimate_flat_field,
    estimate_window_mask,
    leaves_features,
    load_map_n,
    normalise_photometry,
    prepare_frame,
    to_unit_float,
    tracks_when_behind,
)
from services.core.registration.matching import estimate_similarity, match_features
from services.core.simulation.renderer import WINDOW_SIZE_PX, vignette_gain
from tests.sim_cache import simulated


@pytest.fixture(scope="module")
def scan() -> Scan:
    return simulated("short", 1)  # made once per run, shared with other modules


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a > 0, b > 0
    return float(np.count_nonzero(a & b) / np.count_nonzero(a | b))


def test_window_mask_from_simulated_frames(scan: Scan) -> None:
    found = estimate_window_mask([scan.frame(i) for i in range(0, len(scan), 2)])
    assert found.dtype == np.uint8 and set(np.unique(found)) <= {0, 255}
    assert _iou(found, scan.mask) > 0.9  # measured 0.988


def test_window_mask_from_sixteen_bit_frames(scan: Scan) -> None:
    frames16 = [scan.frame(i).astype(np.uint16) * 257 for i in range(0, len(scan), 4)]
    assert _iou(estimate_window_mask(frames16), scan.mask) > 0.9


def _synthetic_vignetting() -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """15 frames of independent random texture times a known radial gain inside an elliptic window."""
    h, w = 240, 300
    rng = np.random.default_rng(0)
    mask = np.zeros((h, w), np.uint8)
    cv2.ellipse(mask, (150, 120), (130, 100), 0, 0, 360, 255, -1)
    ys, xs = np.mgrid[0:h, 0:w]
    gain = (0.8 + 0.3 * (((xs - 150) / 130) ** 2 + ((ys - 120) / 100) ** 2)).astype(np.float32)
    frames = []
    for _ in range(15):
        tex = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 3)
        tex = 0.4 + (tex - tex.mean()) * 3
        f = np.where(mask > 0, tex * gain * 0.6, 0.05)
        frames.append(np.clip(f * 255, 0, 255).astype(np.uint8))
    return frames, mask, gain


def test_flat_field_recovers_synthetic_vignetting() -> None:
    frames, mask, gain = _synthetic_vignetting()
    flat = estimate_flat_field(frames, mask)
    inside = mask > 0
    truth = gain / gain[inside].mean()
    assert float(np.mean(flat[inside])) == pytest.approx(1.0, abs=1e-5)  # normalised to mean 1
    err = np.abs(flat / truth - 1)[inside]
    untouched = np.abs(1.0 / truth - 1)[inside]  # what "no flat field" would score
    # the median of 15 textured frames, smoothed at 15 px: measured median 1.2%, worst 8.7% (at the rim)
    assert np.median(err) < 0.03 < np.median(untouched)
    assert np.percentile(err, 95) < 0.06
    assert np.ptp(flat[~inside]) == 0.0 and flat[~inside][0] > 0.5  # a harmless constant outside


def test_flat_field_recovers_the_simulators_vignette(scan: Scan) -> None:
    frames = [scan.frame(i) for i in range(0, len(scan), 2)]
    flat = estimate_flat_field(frames, scan.mask)
    inside = cv2.erode(scan.mask, np.ones((11, 11), np.uint8)) > 0
    truth = vignette_gain(scan.calibration)
    truth = truth / truth[scan.mask > 0].mean()
    err = np.abs(flat / truth - 1)[inside]
    assert np.median(err) < 0.04  # measured 2.2% (the frames overlap, so the texture is not independent)


def test_photometry_maps_the_window_median_to_128(scan: Scan) -> None:
    out = normalise_photometry(scan.frame(0), scan.mask, None)
    assert out.dtype == np.uint8
    assert abs(float(np.median(out[scan.mask > 0])) - 128) <= 1


def test_to_unit_float_rejects_other_types() -> None:
    with pytest.raises(ValueError, match="8- or 16-bit"):
        to_unit_float(np.zeros((4, 4), np.float32))
    with pytest.raises(ValueError, match="single-channel"):
        to_unit_float(np.zeros((4, 4, 3), np.uint8))


def _prepare(
    scan: Scan, forces: np.ndarray, rectify: bool = True, index: int = 0, vein_scale: float = 0.5, **overrides
):
    options = method_options("best").with_overrides({"rectify": rectify, "vein_scale": vein_scale, **overrides})
    return prepare_frame(
        scan.frame(index),
        index=index,
        seq=index,
        t_s=float(scan.frame_t_s[index]),
        forces_n=forces,
        calib=scan.calibration,
        mask=scan.mask,
        flat=None,
        options=options,
    )


def test_features_are_in_mm_about_the_principal_point(scan: Scan) -> None:
    calib = scan.calibration
    pf = _prepare(scan, np.full(4, 1.5))
    pts = pf.features.points  # mm about the principal point here (see PreparedFrame)
    assert len(pts) > 100
    half_w, half_h = WINDOW_SIZE_PX[0] / 2 / calib.px_per_mm, WINDOW_SIZE_PX[1] / 2 / calib.px_per_mm
    assert np.all(np.abs(pts[:, 0]) < half_w) and np.all(np.abs(pts[:, 1]) < half_h)  # 23.1 x 18.1 mm
    # spread over the window on both sides of the centre (pixels would be 0..400; an offset would show)
    assert pts[:, 0].min() < -12 and pts[:, 0].max() > 12
    assert pts[:, 1].min() < -8 and pts[:, 1].max() > 8
    # mapped back to rectified pixels, every feature lies inside the rectified window
    px = np.round(mm_to_px(pts, calib)).astype(int)
    assert np.all(pf.mask[px[:, 1], px[:, 0]] > 0)


def test_half_resolution_features_land_where_full_resolution_ones_do(scan: Scan) -> None:
    # the vein map and its keypoints at half resolution (the default, 4x cheaper) are mapped back to frame
    # pixels: the same frame's keypoints at full resolution must agree with them under the identity (a missing
    # factor 2 would show as scale 2 and shifts of millimetres).
    half = _prepare(scan, np.full(4, 1.5), vein_scale=0.5)
    full = _prepare(scan, np.full(4, 1.5), vein_scale=1.0)
    assert half.vein.shape == (full.vein.shape[0] // 2, full.vein.shape[1] // 2)
    iq, it = match_features(half.features, full.features, ratio=0.8)
    fit = estimate_similarity(half.features.points[iq], full.features.points[it], threshold=0.1)
    assert fit is not None and fit.inliers > 50
    # tolerance: keypoints of two maps blurred at different resolutions jitter; measured 0.048 mm (0.4 px) and
    # a scale within 0.1 %: 0.1 mm and 0.5 % hold that with margin and fail any resolution slip by far
    assert abs(fit.transform.t) < 0.1 and abs(abs(fit.transform.a) - 1) < 0.005


def test_rectified_window_shrinks_as_load_grows(scan: Scan) -> None:
    calib = scan.calibration
    light = _prepare(scan, np.full(4, 0.5))  # 2 N, no tilt
    heavy = _prepare(scan, np.full(4, 6.25))  # 25 N, no tilt
    area = {k: float(np.count_nonzero(p.mask)) for k, p in (("light", light), ("heavy", heavy))}
    c = calib.compliance_per_n
    expected = ((1 - c * 25.0) / (1 - c * 2.0)) ** 2  # spec §2: uniform load scales radii by 1 - c F
    # ~70,000 px window: the boundary quantisation (~1,000 px) is ~1.5% of the area; allow 2%
    assert area["heavy"] / area["light"] == pytest.approx(expected, rel=0.02)  # 0.72
    assert heavy.stretch == pytest.approx(c * 25.0, rel=1e-12)
    assert heavy.load.fz_n == pytest.approx(25.0, rel=1e-12)
    # without rectification the geometry ignores the load: the two masks are identical
    flat_light = _prepare(scan, np.full(4, 0.5), rectify=False)
    flat_heavy = _prepare(scan, np.full(4, 6.25), rectify=False)
    np.testing.assert_array_equal(flat_light.mask, flat_heavy.mask)


def test_prepared_image_is_normalised_and_sharp(scan: Scan) -> None:
    pf = _prepare(scan, np.full(4, 1.5))
    assert pf.image.dtype == np.uint8 and pf.image.shape == scan.mask.shape
    assert abs(float(np.median(pf.image[pf.mask > 0])) - 128) <= 3
    blurred = prepare_frame(
        cv2.GaussianBlur(scan.frame(0), (0, 0), 4),
        index=0,
        seq=0,
        t_s=0.0,
        forces_n=np.full(4, 1.5),
        calib=scan.calibration,
        mask=scan.mask,
        flat=None,
        options=method_options("best"),
    )
    assert blurred.sharpness < 0.1 * pf.sharpness  # measured ~2 vs ~124 grey levels^2


def test_frame_size_must_match_calibration(scan: Scan) -> None:
    with pytest.raises(ValueError, match="differs from calibration"):
        prepare_frame(
            scan.frame(0)[:-1],
            index=0,
            seq=0,
            t_s=0.0,
            forces_n=np.zeros(4),
            calib=scan.calibration,
            mask=scan.mask,
            flat=None,
            options=method_options("best"),
        )


@pytest.mark.parametrize("state", [LoadState(12.0, 0.0, 0.0), LoadState(20.0, 0.2, -0.1), LoadState(2.0, 0.3, 0.3)])
def test_load_map_is_spec_local_load_on_every_pixel(scan: Scan, state: LoadState) -> None:
    # load_map_n builds F from one row and one column (Z is linear in x and y); it must equal spec §2's
    # F(x, y) = max(0, F_Z + kappa Z(x, y)) evaluated pixel by pixel, the clamp at 0 included (the last state
    # unloads part of the window); float32 rounding only: the row and the column are rounded to float32 before
    # their sum, so 1e-5 relative plus a few ulp of terms of tens of N (5e-5 N absolute)
    calib = scan.calibration
    w, h = calib.image_size
    expected = local_load_n(px_to_mm(pixel_grid(w, h), calib), state, calib)
    got = load_map_n(calib, state)
    assert got.shape == (h, w) and got.dtype == np.float32
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=5e-5)


@pytest.mark.parametrize(
    ("overrides", "behind", "leaves"),
    [
        ({}, False, False),  # best, a session keeping up: every frame described when prepared
        ({}, True, True),  # best, a live session behind its uploads: left to registration, to be tracked
        ({"track_overlap_behind": 0.0}, True, False),  # ... unless tracking behind is off
        ({"track_overlap": 0.85}, False, True),  # a method that tracks frames: always left
        ({"registration": "previous"}, True, False),  # the baselines track nothing
    ],
)
def test_a_frame_is_prepared_without_features_only_when_registration_may_track_it(
    scan: Scan, overrides: dict, behind: bool, leaves: bool
) -> None:
    options = method_options("best").with_overrides(overrides)
    assert leaves_features(options, behind) is leaves
    # being behind matters (the worker reads the session's mark) only to a method that tracks such frames
    assert tracks_when_behind(options) is ("registration" not in overrides and "track_overlap_behind" not in overrides)
    pf = prepare_frame(
        scan.frame(2),
        index=2,
        seq=2,
        t_s=float(scan.frame_t_s[2]),
        forces_n=np.full(4, 1.5),
        calib=scan.calibration,
        mask=scan.mask,
        flat=None,
        options=options,
        behind=behind,
    )
    assert (pf.features is None) is leaves


@pytest.mark.parametrize("enhance", [True, False], ids=["vein-map", "grey-levels"])
def test_features_on_demand_are_the_features_prepared(scan: Scan, enhance: bool) -> None:
    # a method that tracks frames prepares them without features; describing one later (a keyframe) must give
    # exactly what preparing it with features gives, so tracking changes which frames are described, not how
    prepared = _prepare(scan, np.full(4, 1.5), index=3, enhance=enhance)
    lazy = _prepare(scan, np.full(4, 1.5), index=3, enhance=enhance, track_overlap=0.8)
    assert prepared.features is not None and lazy.features is None
    options = method_options("best").with_overrides({"enhance": enhance, "track_overlap": 0.8})
    described = describe_frame(lazy, options, scan.calibration.principal_point, scan.calibration.px_per_mm)
    assert described.features is not None and len(described.features) > 100
    for got, want in zip(
        (described.features.points, described.features.descriptors, described.features.sizes_px),
        (prepared.features.points, prepared.features.descriptors, prepared.features.sizes_px),
        strict=True,
    ):
        assert got.dtype == want.dtype and np.array_equal(got, want)
    assert describe_frame(described, options, (0.0, 0.0), 1.0) is described  # described once
