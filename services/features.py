"""Keypoints and descriptors: SIFT, the paper's modified A-SIFT, and full ASIFT (spec §2 "Modified A-SIFT")."""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

FEATURE_KINDS = ("sift", "modified-asift", "asift")
MODIFIED_ASIFT_TILT = math.sqrt(1.13)
MODIFIED_ASIFT_ROLLS_DEG = tuple(range(0, 180, 20))  # 0, 20, ..., 160
EDGE_THRESHOLD = 10.0


@dataclass(frozen=True)
class Features:
    """Keypoints: positions (N, 2) float64 (pixels from detect_features; frame_prep turns them into mm about the
    principal point), descriptors (N, D) float32, detection scales (N,) in pixels."""

    points: np.ndarray
    descriptors: np.ndarray
    sizes_px: np.ndarray

    def __len__(self) -> int:
        return len(self.points)

    def subset(self, keep: np.ndarray) -> Features:
        """Return the features selected by a boolean mask or index array."""
        return Features(self.points[keep], self.descriptors[keep], self.sizes_px[keep])


def empty_features(descriptor_size: int = 128) -> Features:
    """Return a Features with no keypoints."""
    return Features(np.zeros((0, 2)), np.zeros((0, descriptor_size), np.float32), np.zeros(0))


def modified_asift_views() -> tuple[list[float], list[float]]:
    """Return (tilts, rolls_deg) of the paper's 10 views: t = 1, then t = sqrt(1.13) at 0, 20, ..., 160 deg."""
    tilts = [1.0] + [MODIFIED_ASIFT_TILT] * len(MODIFIED_ASIFT_ROLLS_DEG)
    rolls = [0.0] + [float(r) for r in MODIFIED_ASIFT_ROLLS_DEG]
    return tilts, rolls


def _detector(kind: str, max_features: int, contrast_threshold: float) -> cv2.Feature2D:
    sift = cv2.SIFT_create(nfeatures=max_features, edgeThreshold=EDGE_THRESHOLD, contrastThreshold=contrast_threshold)
    if kind == "sift":
        return sift
    if kind == "asift":
        return cv2.AffineFeature_create(sift)
    if kind == "modified-asift":
        detector = cv2.AffineFeature_create(sift)
        tilts, rolls = modified_asift_views()
        detector.setViewParams(tilts, rolls)
        return detector
    raise ValueError(f"unknown feature kind {kind!r}; expected one of {FEATURE_KINDS}")


def detect_features(
    image: np.ndarray,
    mask: np.ndarray | None,
    kind: str = "sift",
    max_features: int = 0,
    contrast_threshold: float = 0.03,
) -> Features:
    """Return keypoints (pixels) and descriptors of an 8-bit image, kept only where mask > 0.

    AffineFeature does not apply the mask to its unwarped view, so every kind is filtered here too.
    max_features caps SIFT per view (0 = no cap).
    """
    if image.dtype != np.uint8:
        raise ValueError("detect_features expects an 8-bit image")
    detector = _detector(kind, max_features, contrast_threshold)
    keypoints, descriptors = detector.detectAndCompute(image, mask)
    if descriptors is None or len(keypoints) == 0:
        return empty_features()
    points = np.array([k.pt for k in keypoints], dtype=np.float64)
    sizes = np.array([k.size for k in keypoints], dtype=np.float64)
    descriptors = np.asarray(descriptors, dtype=np.float32)
    if mask is not None:
        h, w = mask.shape
        xi = np.clip(np.round(points[:, 0]).astype(int), 0, w - 1)
        yi = np.clip(np.round(points[:, 1]).astype(int), 0, h - 1)
        keep = mask[yi, xi] > 0
        points, descriptors, sizes = points[keep], descriptors[keep], sizes[keep]
    return Features(points, descriptors, sizes)
