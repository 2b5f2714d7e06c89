"""Per-frame preparation, independent across frames: photometry, undistortion + rectification, features."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np

from services.core.contact import focus_measure
from services.core.inputs.calibration import Calibration
from services.core.methods import MethodOptions
from services.core.order_statistics import median
from services.core.physics.camera import px_to_mm_about
from services.core.physics.force_model import LoadState, centre_stretch, depth_deviation_mm, load_state
from services.core.physics.rectification import rectify_map
from services.core.registration.features import Features, detect_features
from services.core.registration.vein_enhancement import enhance_veins

UNLOADED = LoadState(0.0, 0.0, 0.0)
FEATURE_MARGIN_PX = 6  # keypoints this close to the window edge straddle the dark housing: drop them


@dataclass(frozen=True)
class PreparedFrame:
    """A frame ready for registration: rectified 8-bit image and mask, features in mm, load and sharpness."""

    index: int
    seq: int
    t_s: float
    forces_n: np.ndarray  # (4,) F1..F4 at the frame time, N
    load: LoadState
    stretch: float  # nu F_Z / (E A) at the centre, dimensionless
    image: np.ndarray  # (H, W) uint8, rectified, photometrically normalised (median skin = 128)
    mask: np.ndarray  # (H, W) uint8 0/255, the window in rectified pixels
    features: Features | None  # points in mm about the principal point (rectified, undeformed); None: not described
    # yet (a method that tracks frames describes only its keyframes: describe_frame)
    vein: np.ndarray  # (h, w) uint8 vein map of the rectified frame (0 = skin) at options.vein_scale of (H, W)
    vein_mask: np.ndarray  # (h, w) uint8 0/255, where the vein map is valid (the window less a margin)
    sharpness: float  # variance of the Laplacian inside the window, grey levels^2
    imu_tilt_deg: np.ndarray | None = None  # (2,) reference tilts (tilt_x, tilt_y) deg at the frame time, if an IMU
    focus: float = math.nan  # the window's fine-detail contrast (services.core.contact.focus_measure); NaN: unknown


def to_unit_float(raw: np.ndarray) -> np.ndarray:
    """Return a float32 image in 0..1 from an 8- or 16-bit grayscale frame."""
    if raw.ndim != 2:
        raise ValueError("frames must be single-channel grayscale")
    if raw.dtype == np.uint8:
        return raw.astype(np.float32) / 255.0
    if raw.dtype == np.uint16:
        return raw.astype(np.float32) / 65535.0
    raise ValueError(f"frames must be 8- or 16-bit, got {raw.dtype}")


def estimate_window_mask(frames: Sequence[np.ndarray]) -> np.ndarray:
    """Return the window's field of view (uint8 0/255) found from frames: bright, textured, one blob."""
    mean = np.mean([to_unit_float(f) for f in frames], axis=0)
    level = cv2.normalize(mean, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    _, binary = cv2.threshold(level, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(binary)
    if count <= 1:
        return np.full(mean.shape, 255, np.uint8)
    largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    mask = np.where(labels == largest, 255, 0).astype(np.uint8)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    filled = np.zeros_like(mask)
    cv2.drawContours(filled, contours, -1, 255, thickness=cv2.FILLED)
    return cv2.erode(filled, np.ones((3, 3), np.uint8))


def estimate_flat_field(frames: Sequence[np.ndarray], mask: np.ndarray, sigma_px: float = 15.0) -> np.ndarray:
    """Return the illumination gain (H, W) float32, mean 1 in the window: the smoothed median of frames."""
    inside = mask > 0
    stack = []
    for f in frames:
        v = to_unit_float(f)
        stack.append(v / max(median(v[inside]), 1e-6))
    gain = np.median(np.stack(stack), axis=0).astype(np.float32)
    gain = np.where(inside, gain, 0).astype(np.float32)
    norm = cv2.GaussianBlur(inside.astype(np.float32), (0, 0), sigma_px)
    gain = cv2.GaussianBlur(gain, (0, 0), sigma_px) / np.maximum(norm, 1e-6)
    gain = np.where(inside, gain, 1.0)
    return (gain / float(np.mean(gain[inside]))).astype(np.float32)


def normalise_photometry(raw: np.ndarray, mask: np.ndarray, flat: np.ndarray | None) -> np.ndarray:
    """Return an 8-bit frame with vignetting divided out and the window's median mapped to grey 128."""
    v = to_unit_float(raw)
    if flat is not None:
        v = v / np.maximum(flat, 0.05)
    med = max(median(v[mask > 0]), 1e-6)
    return np.clip(v * (128.0 / med), 0, 255).astype(np.uint8)


def prepare_frame(
    raw: np.ndarray,
    *,
    index: int,
    seq: int,
    t_s: float,
    forces_n: np.ndarray,
    calib: Calibration,
    mask: np.ndarray,
    flat: np.ndarray | None,
    options: MethodOptions,
    imu_tilt_deg: np.ndarray | None = None,
    behind: bool = False,
) -> PreparedFrame:
    """Return the prepared frame: photometry, undistort + rectify (spec §2 order), features in mm.

    imu_tilt_deg: the IMU's (tilt_x, tilt_y) deg at the frame time (kept, not used here); None or NaN: no IMU.
    behind: the live session is behind its uploads: the features are left to registration (leaves_features).
    """
    if raw.shape != (calib.image_size[1], calib.image_size[0]):
        raise ValueError(f"frame {seq}: size {raw.shape[::-1]} differs from calibration {calib.image_size}")
    state = load_state(forces_n, calib)
    geometry = state if options.rectify else UNLOADED
    map_x, map_y = rectify_map(calib, geometry)
    image = cv2.remap(normalise_photometry(raw, mask, flat), map_x, map_y, cv2.INTER_LINEAR)
    rect_mask = cv2.remap(mask, map_x, map_y, cv2.INTER_NEAREST, borderValue=0)
    vein = enhance_veins(image, rect_mask, FEATURE_MARGIN_PX, options.vein_scale)
    inner = _inner(rect_mask)
    lap = cv2.Laplacian(image, cv2.CV_32F)
    sharpness = float(np.var(lap[inner > 0])) if np.any(inner) else 0.0
    prepared = PreparedFrame(
        index=index,
        seq=seq,
        t_s=float(t_s),
        forces_n=np.asarray(forces_n, float),
        load=state,
        stretch=centre_stretch(state, calib),
        image=image,
        mask=rect_mask,
        features=None,
        vein=vein.image,
        vein_mask=vein.mask,
        sharpness=sharpness,
        imu_tilt_deg=_imu_or_none(imu_tilt_deg),
        focus=focus_measure(image, rect_mask),
    )
    if leaves_features(options, behind):  # features on demand: only the frames that become keyframes need them
        return prepared
    return describe_frame(prepared, options, calib.principal_point, calib.px_per_mm)


def tracks_frames(options: MethodOptions) -> bool:
    """Return whether the method tracks most frames without features (so preparation leaves them to registration)."""
    return options.registration == "keyframes" and options.track_overlap > 0


def tracks_when_behind(options: MethodOptions) -> bool:
    """Return whether the method tracks the frames a live session behind its uploads prepared without features
    (keyframes registration with options.track_overlap_behind > 0): whether being behind changes its preparation."""
    return options.registration == "keyframes" and options.track_overlap_behind > 0


def leaves_features(options: MethodOptions, behind: bool) -> bool:
    """Return whether a frame is prepared without features, for registration to track it or describe it: always
    when the method tracks frames, and for a live session behind its uploads when it tracks those
    (tracks_when_behind; Registrar.track_overlap)."""
    return tracks_frames(options) or (behind and tracks_when_behind(options))


def describe_frame(
    pf: PreparedFrame, options: MethodOptions, centre_px: tuple[float, float], px_per_mm: float
) -> PreparedFrame:
    """Return the prepared frame with its features (points in mm about the principal point centre_px); itself when
    it has them already."""
    if pf.features is not None:
        return pf
    if options.enhance:  # features of the vein map, back in frame pixels (pixel centres scale about their corner)
        scale = options.vein_scale  # the vein map's pixels per frame pixel (enhance_veins)
        found = _detect(pf.vein, pf.vein_mask, options)
        found = Features((found.points + 0.5) / scale - 0.5, found.descriptors, found.sizes_px / scale)
    else:
        found = _detect(pf.image, _inner(pf.mask), options)
    points_mm = px_to_mm_about(found.points, centre_px, px_per_mm)
    return replace(pf, features=Features(points_mm, found.descriptors, found.sizes_px))


def _inner(mask: np.ndarray) -> np.ndarray:
    """Return the window less FEATURE_MARGIN_PX: where keypoints and sharpness are taken (0/255)."""
    return cv2.erode(mask, np.ones((2 * FEATURE_MARGIN_PX + 1,) * 2, np.uint8))


def _imu_or_none(imu_tilt_deg: np.ndarray | None) -> np.ndarray | None:
    """Return the IMU's tilts as (2,) float64, or None when there are none (None or NaN: no sample around)."""
    if imu_tilt_deg is None:
        return None
    tilt = np.asarray(imu_tilt_deg, np.float64).reshape(2)
    return tilt if np.all(np.isfinite(tilt)) else None


def _detect(image: np.ndarray, mask: np.ndarray, options: MethodOptions) -> Features:
    """Return the method's keypoints (pixels of `image`) and descriptors inside mask."""
    return detect_features(
        image,
        mask,
        options.features,
        options.max_features,
        options.contrast_threshold,
        options.target_features,
        options.sift_finest_octave,
    )


def load_map_n(calib: Calibration, state: LoadState) -> np.ndarray:
    """Return the local load F(x, y) (N, float32) over the rectified pixel grid (spec §2).

    F = max(0, F_Z + kappa Z(x, y)) with Z linear in x and y: Z(x, 0) + Z(0, y) from one row and one column,
    summed in float32 (the planes are float32; 4x faster than a float64 grid).
    """
    w, h = calib.image_size
    cx, cy = calib.principal_point
    x_mm = ((np.arange(w) - cx) / calib.px_per_mm)[:, None] * np.array([1.0, 0.0])
    y_mm = ((np.arange(h) - cy) / calib.px_per_mm)[:, None] * np.array([0.0, 1.0])
    row = (state.fz_n + calib.hooke_n_per_mm * depth_deviation_mm(x_mm, state)).astype(np.float32)
    column = (calib.hooke_n_per_mm * depth_deviation_mm(y_mm, state)).astype(np.float32)
    load = np.add(column[:, None], row[None, :])
    return np.maximum(load, np.float32(0.0), out=load)
