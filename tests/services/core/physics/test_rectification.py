"""Tests for whole-frame rectification (core/physics/rectification.py, spec §2 order): the maps, checked against
the analytic keypoint rectification, and frames remapped through them as frame_prep.prepare_frame does."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from services.core.inputs.calibration import Calibration, parse_calibration
from services.core.physics.camera import distort_points_px, mm_to_px, px_to_mm, undistort_points_px
from services.core.physics.force_model import LoadState, load_state, rectify_points_mm
from services.core.physics.rectification import pixel_grid, rectify_map
from tests.tolerances import TOL

W, H = 640, 480
FX, FY, CX, CY = 610.0, 590.0, 330.2, 235.7  # off-centre principal point, fx != fy
LENS = (-0.12, 0.03, 0.0005, -0.0003)
# A pressed, tilted probe: F_Z = 12 N, F2 > F1 and F4 > F3 (load higher toward +y and -x).
FORCES = np.array([1.0, 4.0, 2.0, 5.0])


def rectify_keypoints_px(raw_px: np.ndarray, calib: Calibration, state: LoadState) -> np.ndarray:
    """Return rectified pixel positions (N, 2) of raw positions (N, 2): undistort, then rectify (the analytic
    inverse of rectify_map, from the camera and force models)."""
    ideal = undistort_points_px(raw_px, calib)
    return mm_to_px(rectify_points_mm(px_to_mm(ideal, calib), state, calib), calib)


def rectify_image(raw: np.ndarray, calib: Calibration, state: LoadState) -> np.ndarray:
    """Return `raw` rectified as frame_prep.prepare_frame rectifies a frame: cv2.remap through rectify_map,
    bilinear, 0 outside the raw frame."""
    map_x, map_y = rectify_map(calib, state)
    return cv2.remap(raw, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def make_calib(dist: tuple[float, ...] = LENS) -> Calibration:
    """Return a 640x480, 8 px/mm calibration with the paper's force constants."""
    return parse_calibration(
        {
            "image_size": [W, H],
            "camera_matrix": [[FX, 0.0, CX], [0.0, FY, CY], [0.0, 0.0, 1.0]],
            "dist_coeffs": list(dist),
            "px_per_mm": 8.0,
        }
    )


def test_pixel_grid() -> None:
    g = pixel_grid(4, 3)
    assert g.shape == (3, 4, 2) and g.dtype == np.float64
    assert tuple(g[2, 3]) == (3.0, 2.0)  # (x, y) at row 2, column 3


def test_unloaded_undistorted_map_is_identity() -> None:
    calib = make_calib((0.0, 0.0, 0.0, 0.0))
    map_x, map_y = rectify_map(calib, load_state(np.zeros(4), calib))
    assert map_x.dtype == np.float32 and map_x.shape == (H, W)
    g = pixel_grid(W, H)
    np.testing.assert_allclose(map_x, g[..., 0], rtol=0, atol=1e-4)  # float32 spacing at 640 is 6e-5
    np.testing.assert_allclose(map_y, g[..., 1], rtol=0, atol=1e-4)


@pytest.mark.parametrize(
    "forces", [FORCES, np.array([0.5, 0.5, 0.5, 0.5]), np.array([3.0, 9.0, 8.0, 4.0]), np.array([7.0, 6.0, 8.0, 9.0])]
)
def test_interpolated_map_matches_the_exact_model(forces: np.ndarray) -> None:
    # loads 2-30 N with tilts both ways, as on the shared scans (2-26 N): the 8 px grid is interpolated, not
    # approximated by a different model; step 1 is the exact per-pixel evaluation
    calib = make_calib()
    state = load_state(forces, calib)
    exact_x, exact_y = rectify_map(calib, state, step_px=1)
    fast_x, fast_y = rectify_map(calib, state)
    assert fast_x.shape == exact_x.shape == (H, W) and fast_x.dtype == np.float32
    assert np.max(np.abs(fast_x - exact_x)) < TOL.map_interpolation_px
    assert np.max(np.abs(fast_y - exact_y)) < TOL.map_interpolation_px
    # and the stretch itself is there: the loaded map is not the unloaded one
    unloaded_x, _ = rectify_map(calib, load_state(np.zeros(4), calib), step_px=1)
    assert np.max(np.abs(exact_x - unloaded_x)) > 1.0


def test_rectified_keypoint_known_answer() -> None:
    # No lens distortion; forces (1, 3, 2, 2) N, the worked example of test_force_model: a raw keypoint
    # 20 mm = 160 px below the principal point (+y) is rectified to r = 18.91597325 mm = 151.327786 px,
    # and one 20 mm to the right (+x) to 18.96480331 mm = 151.7184265 px.
    calib = make_calib((0.0, 0.0, 0.0, 0.0))
    state = load_state(np.array([1.0, 3.0, 2.0, 2.0]), calib)
    raw = np.array([[CX, CY + 160.0], [CX + 160.0, CY]])
    out = rectify_keypoints_px(raw, calib, state)
    np.testing.assert_allclose(out, [[CX, CY + 151.327786], [CX + 151.7184265, CY]], rtol=0, atol=1e-6)


def test_keypoints_are_undistorted_before_rectification() -> None:
    # spec §2 order: undistort first, then rectify about (cx, cy). A raw point made by distorting the
    # ideal point (cx + 160, cy) must land where that ideal point rectifies to: 151.7184265 px right of cx
    # (the +x axis carries F = F_Z = 8 N for forces (1, 3, 2, 2), see the known answer above).
    calib = make_calib()
    state = load_state(np.array([1.0, 3.0, 2.0, 2.0]), calib)
    raw = distort_points_px(np.array([[CX + 160.0, CY]]), calib)
    assert abs(raw[0, 0] - (CX + 160.0)) > 1.0  # the lens really moves it
    out = rectify_keypoints_px(raw, calib, state)
    np.testing.assert_allclose(out, [[CX + 151.7184265, CY]], rtol=0, atol=TOL.undistort_roundtrip_px)


def _inside(map_x: np.ndarray, map_y: np.ndarray) -> np.ndarray:
    """Return the mask of rectified pixels whose raw source lies inside the raw image (the window)."""
    return (map_x >= 0) & (map_x <= W - 1) & (map_y >= 0) & (map_y <= H - 1)


@pytest.mark.parametrize("dist", [(0.0, 0.0, 0.0, 0.0), LENS])
def test_map_composed_with_keypoint_rectification_is_identity(dist: tuple[float, ...]) -> None:
    # rectify_map sends a rectified pixel q to the raw pixel it comes from; rectify_keypoints_px sends a raw
    # pixel to its rectified position. Their composition must be the identity over the window.
    calib = make_calib(dist)
    state = load_state(FORCES, calib)
    map_x, map_y = rectify_map(calib, state)
    inside = _inside(map_x, map_y)
    assert inside.mean() > 0.8  # most of the frame is still seen
    q = pixel_grid(W, H)[inside]
    raw = np.stack([map_x[inside], map_y[inside]], axis=-1).astype(np.float64)
    # the maps do something: rectified and raw positions differ by up to ~20 px at the edges
    assert np.max(np.linalg.norm(raw - q, axis=1)) > 10.0
    back = rectify_keypoints_px(raw, calib, state)
    err = np.linalg.norm(back - q, axis=1)
    assert err.max() < TOL.map_composition_px


def _blob_centres() -> np.ndarray:
    """Return 5x4 blob centres (rectified pixels) at deliberately non-integer positions, shape (20, 2)."""
    xs = np.linspace(110.0, 530.0, 5) + 0.37
    ys = np.linspace(90.0, 390.0, 4) - 0.29
    return np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)


def _render(points: np.ndarray, centres: np.ndarray, sigma: float) -> np.ndarray:
    """Return the sum of unit Gaussian blobs (sigma px) at `centres`, evaluated at `points` (..., 2)."""
    out = np.zeros(points.shape[:-1], dtype=np.float64)
    for c in centres:
        d2 = np.sum((points - c) ** 2, axis=-1)
        out += np.exp(-d2 / (2 * sigma**2))
    return out


def _centroids(img: np.ndarray, guesses: np.ndarray, half: int = 9) -> np.ndarray:
    """Return intensity-weighted centroids (x, y) of img in (2 half + 1)^2 windows around the guesses."""
    out = []
    for gx, gy in guesses:
        x0, y0 = round(gx), round(gy)
        patch = img[y0 - half : y0 + half + 1, x0 - half : x0 + half + 1].astype(np.float64)
        ys, xs = np.mgrid[y0 - half : y0 + half + 1, x0 - half : x0 + half + 1]
        out.append([np.sum(patch * xs) / patch.sum(), np.sum(patch * ys) / patch.sum()])
    return np.array(out)


@pytest.mark.parametrize("dist", [(0.0, 0.0, 0.0, 0.0), LENS])
def test_deform_then_rectify_image_round_trip(dist: tuple[float, ...]) -> None:
    # Render the undeformed scene U (Gaussian blobs at known sub-pixel positions, rectified pixels), then
    # the raw frame the probe would see: raw(p) = U(rectify_keypoints_px(p)) evaluated analytically (no
    # resampling), i.e. deformed by the load and distorted by the lens. rectify_image must bring every blob
    # back to its known position (one bilinear resampling, so the centroid error stays well below 0.05 px).
    calib = make_calib(dist)
    state = load_state(FORCES, calib)
    centres = _blob_centres()
    sigma = 2.5
    raw_pos = rectify_keypoints_px(pixel_grid(W, H).reshape(-1, 2), calib, state).reshape(H, W, 2)
    raw = _render(raw_pos, centres, sigma).astype(np.float32)
    # the raw blobs really are elsewhere (deformation + lens), by more than a pixel for most of them
    raw_centres = _centroids(raw, centres)
    assert np.median(np.linalg.norm(raw_centres - centres, axis=1)) > 1.0
    rect = rectify_image(raw, calib, state)
    assert rect.shape == raw.shape and rect.dtype == raw.dtype
    found = _centroids(rect, centres)
    err = np.linalg.norm(found - centres, axis=1)
    assert err.max() < TOL.feature_position_px


def test_rectify_image_keeps_dtype_and_blacks_out_unseen_pixels() -> None:
    # A strongly pressed probe (F_Z = 30 N, centre stretch 30 * 6.47e-3 = 19 %): the rectified frame's corners
    # come from outside the raw frame and must be 0; the centre keeps its value (raw is a constant 1000).
    calib = make_calib()
    state = LoadState(fz_n=30.0, theta_x_rad=0.0, theta_y_rad=0.0)
    raw = np.full((H, W), 1000, dtype=np.uint16)
    rect = rectify_image(raw, calib, state)
    assert rect.dtype == np.uint16 and rect.shape == (H, W)
    assert rect[0, 0] == 0 and rect[H - 1, W - 1] == 0 and rect[0, W - 1] == 0 and rect[H - 1, 0] == 0
    assert rect[round(CY), round(CX)] == 1000
