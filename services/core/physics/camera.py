"""Lens model (OpenCV pinhole + Brown-Conrady distortion) and the pixel <-> mm conversion about (cx, cy)."""

from __future__ import annotations

import cv2
import numpy as np

from services.core.inputs.calibration import Calibration


def undistort_points_px(points_px: np.ndarray, calib: Calibration) -> np.ndarray:
    """Return ideal (undistorted) pixel coordinates, shape (N, 2), of raw image points (N, 2) in pixels."""
    pts = np.asarray(points_px, dtype=np.float64).reshape(-1, 1, 2)
    if len(pts) == 0 or not np.any(calib.D):
        return pts.reshape(-1, 2).copy()
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-9)
    undistort_iter = getattr(cv2, "undistortPointsIter", None)  # OpenCV 4.x; 5.x: undistortPoints(criteria=)
    if undistort_iter is not None:
        out = undistort_iter(pts, calib.K, calib.D, None, calib.K, criteria)
    else:
        out = cv2.undistortPoints(pts, calib.K, calib.D, R=None, P=calib.K, criteria=criteria)
    return out.reshape(-1, 2)


def distort_points_px(ideal_px: np.ndarray, calib: Calibration) -> np.ndarray:
    """Return raw (distorted) pixel coordinates (..., 2) of ideal pixel coordinates (..., 2)."""
    p = np.asarray(ideal_px, dtype=np.float64)
    K = calib.K
    if len(calib.D) > 5 and np.any(calib.D[5:]) and p.size:
        # rational / thin-prism / tilted models (8, 12, 14 coefficients): let OpenCV evaluate the whole
        # model, the same one undistort_points_px inverts (the closed form below has k1, k2, p1, p2, k3 only)
        flat = p.reshape(-1, 2)
        obj = np.column_stack([(flat[:, 0] - K[0, 2]) / K[0, 0], (flat[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(flat))])
        img, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), K, calib.D)
        return img.reshape(p.shape)
    d = np.zeros(5)
    d[: min(5, len(calib.D))] = calib.D[:5]
    k1, k2, p1, p2, k3 = d
    x = (p[..., 0] - K[0, 2]) / K[0, 0]
    y = (p[..., 1] - K[1, 2]) / K[1, 1]
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd * K[0, 0] + K[0, 2], yd * K[1, 1] + K[1, 2]], axis=-1)


def px_to_mm(points_px: np.ndarray, calib: Calibration) -> np.ndarray:
    """Return positions in mm about the principal point of ideal pixel positions (..., 2)."""
    return px_to_mm_about(points_px, calib.principal_point, calib.px_per_mm)


def px_to_mm_about(points_px: np.ndarray, centre_px: tuple[float, float], px_per_mm: float) -> np.ndarray:
    """Return positions in mm about centre_px (the principal point) of ideal pixel positions (..., 2)."""
    cx, cy = centre_px
    p = np.asarray(points_px, dtype=np.float64)
    return np.stack([(p[..., 0] - cx), (p[..., 1] - cy)], axis=-1) / px_per_mm


def mm_to_px(points_mm: np.ndarray, calib: Calibration) -> np.ndarray:
    """Return ideal pixel positions (..., 2) of positions in mm about the principal point."""
    cx, cy = calib.principal_point
    p = np.asarray(points_mm, dtype=np.float64) * calib.px_per_mm
    return np.stack([p[..., 0] + cx, p[..., 1] + cy], axis=-1)
