"""Tests for the lens model and pixel <-> mm conversion (services/core/physics/camera.py)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from services.core.inputs.calibration import Calibration, parse_calibration
from services.core.physics.camera import distort_points_px, mm_to_px, px_to_mm, undistort_points_px
from tests.tolerances import TOL

# The lens: k1 = -0.12, k2 = 0.03, p1 = 0.0005, p2 = -0.0003 (barrel, slight decentring).
LENS = (-0.12, 0.03, 0.0005, -0.0003)
# fx != fy and an off-centre principal point, so a swapped axis or a centred-image assumption shows up.
FX, FY, CX, CY = 610.0, 590.0, 330.2, 235.7


def make_calib(dist: tuple[float, ...] = LENS, px_per_mm: float = 8.0) -> Calibration:
    """Return a 640x480 calibration with the test camera matrix and the given distortion."""
    return parse_calibration(
        {
            "image_size": [640, 480],
            "camera_matrix": [[FX, 0.0, CX], [0.0, FY, CY], [0.0, 0.0, 1.0]],
            "dist_coeffs": list(dist),
            "px_per_mm": px_per_mm,
        }
    )


def image_points(margin: float = 20.0) -> np.ndarray:
    """Return a 60x70 grid of pixel positions covering the 640x480 image plus a margin, shape (N, 2)."""
    xs, ys = np.meshgrid(np.linspace(-margin, 639 + margin, 70), np.linspace(-margin, 479 + margin, 60))
    return np.stack([xs, ys], axis=-1).reshape(-1, 2)


def test_distort_known_answer() -> None:
    # Ideal point at normalised (x, y) = (0.5, 0): r^2 = 0.25
    #   radial = 1 + k1 r^2 + k2 r^4 = 1 - 0.12 * 0.25 + 0.03 * 0.0625 = 1 - 0.03 + 0.001875 = 0.971875
    #   x_d = x radial + 2 p1 x y + p2 (r^2 + 2 x^2) = 0.4859375 + 0 + (-0.0003)(0.25 + 0.5) = 0.4857125
    #   y_d = y radial + p1 (r^2 + 2 y^2) + 2 p2 x y = 0 + 0.0005 * 0.25 + 0 = 0.000125
    #   pixels: u = 330.2 + 610 * 0.4857125 = 626.484625, v = 235.7 + 590 * 0.000125 = 235.77375
    calib = make_calib()
    ideal = np.array([[CX + 0.5 * FX, CY]])
    np.testing.assert_allclose(distort_points_px(ideal, calib), [[626.484625, 235.77375]], rtol=0, atol=1e-9)
    # Normalised (0, -0.4): r^2 = 0.16, radial = 1 - 0.0192 + 0.000768 = 0.981568
    #   x_d = 0 + 0 + p2 (0.16 + 0) = -0.000048;  y_d = -0.4 * 0.981568 + p1 (0.16 + 0.32) + 0
    #       = -0.3926272 + 0.00024 = -0.3923872
    #   u = 330.2 - 610 * 0.000048 = 330.17072, v = 235.7 - 590 * 0.3923872 = 4.191552
    ideal = np.array([[CX, CY - 0.4 * FY]])
    np.testing.assert_allclose(distort_points_px(ideal, calib), [[330.17072, 4.191552]], rtol=0, atol=1e-9)
    # the principal point is fixed by any distortion
    np.testing.assert_allclose(distort_points_px(np.array([CX, CY]), calib), [CX, CY], rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    "dist",
    [
        LENS,  # 4 coefficients
        (*LENS, 0.01),  # 5: with k3
        (*LENS, 0.01, 0.02, -0.01, 0.015),  # 8: rational model k4, k5, k6
    ],
)
def test_undistort_inverts_distort(dist: tuple[float, ...]) -> None:
    calib = make_calib(dist)
    pts = image_points()
    raw = distort_points_px(pts, calib)
    # a real distortion: corners move by several pixels
    assert np.max(np.linalg.norm(raw - pts, axis=1)) > 5.0
    back = undistort_points_px(raw, calib)
    assert back.shape == pts.shape
    np.testing.assert_allclose(back, pts, rtol=0, atol=TOL.undistort_roundtrip_px)


@pytest.mark.parametrize("dist", [LENS, (*LENS, 0.01), (*LENS, 0.01, 0.02, -0.01, 0.015)])
def test_distort_agrees_with_opencv_project_points(dist: tuple[float, ...]) -> None:
    # projectPoints of the 3-D point (x, y, 1) with R = I, t = 0 is exactly "distort the normalised point
    # (x, y) and apply K": the same map distort_points_px applies to the ideal pixel K (x, y, 1).
    calib = make_calib(dist)
    pts = image_points()
    obj = np.column_stack([(pts[:, 0] - CX) / FX, (pts[:, 1] - CY) / FY, np.ones(len(pts))])
    ref, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), calib.K, calib.D)
    np.testing.assert_allclose(distort_points_px(pts, calib), ref.reshape(-1, 2), rtol=0, atol=TOL.project_points_px)


def test_distort_keeps_leading_shape() -> None:
    calib = make_calib()
    grid = image_points().reshape(60, 70, 2)
    out = distort_points_px(grid, calib)
    assert out.shape == (60, 70, 2)
    np.testing.assert_array_equal(out.reshape(-1, 2), distort_points_px(grid.reshape(-1, 2), calib))


def test_zero_distortion_is_identity() -> None:
    calib = make_calib((0.0, 0.0, 0.0, 0.0, 0.0))
    pts = image_points()
    np.testing.assert_allclose(distort_points_px(pts, calib), pts, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(undistort_points_px(pts, calib), pts)
    assert undistort_points_px(np.zeros((0, 2)), make_calib()).shape == (0, 2)


def test_px_mm_conversion_known_answer() -> None:
    # 8 px/mm about (cx, cy) = (330.2, 235.7): pixel (330.2 + 80, 235.7 - 16) is (10, -2) mm
    calib = make_calib(px_per_mm=8.0)
    mm = px_to_mm(np.array([[CX + 80.0, CY - 16.0], [CX, CY]]), calib)
    np.testing.assert_allclose(mm, [[10.0, -2.0], [0.0, 0.0]], rtol=0, atol=1e-12)
    np.testing.assert_allclose(mm_to_px(np.array([10.0, -2.0]), calib), [410.2, 219.7], rtol=0, atol=1e-12)
    pts = image_points().reshape(60, 70, 2)
    np.testing.assert_allclose(mm_to_px(px_to_mm(pts, calib), calib), pts, rtol=0, atol=1e-12)
