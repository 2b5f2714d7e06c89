"""Image statistics of NIR frames inside the window, used to keep the simulator close to real scans."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

HIGHPASS_SIGMA_PX = 15.0  # high-pass = image minus its Gaussian mean at this sigma (the definition)
EDGE_MARGIN_PX = 20  # the window mask is eroded by this much so its edge does not count as structure
BACKGROUND_KERNEL_PX = 61  # grey closing larger than the widest vessel (~3.5 mm = 28 px): the skin background
BACKGROUND_SMOOTH_SIGMA_PX = 8.0  # smoothing of the closed background (closing leaves plateaus)
DENOISE_SIGMA_PX = 1.5  # pre-blur before the contrast measure so sensor noise does not read as darkening
VESSEL_CONTRAST_PERCENTILE = 99.0  # the vessel contrast is this percentile of the darkening inside the window


@dataclass(frozen=True)
class FrameStats:
    """Statistics of one frame inside its window, in 8-bit grey levels (DN) unless said.

    Over the whole window mask (the issue's definitions, window edge included): grey_std, the std of the grey
    levels; highpass_std, the std of the image minus its 15 px-sigma Gaussian mean; keypoints, the number of
    SIFT keypoints at cv2.SIFT_create() defaults; mean_level. Over the window eroded by EDGE_MARGIN_PX (skin
    and vessels only): inner_highpass_std; vessel_contrast, the fraction (0..1) by which the darkest vessels
    (the 99th percentile of the darkening) are darker than the local skin background; noise_dn, a robust
    sensor-noise std (DN).
    """

    grey_std: float
    highpass_std: float
    inner_highpass_std: float
    vessel_contrast: float
    keypoints: int
    mean_level: float
    noise_dn: float


def to_8bit(frame: np.ndarray) -> np.ndarray:
    """Return the frame as float32 in 8-bit grey levels (0..255), whatever its integer dtype."""
    if frame.dtype == np.uint8:
        return frame.astype(np.float32)
    if np.issubdtype(frame.dtype, np.integer):
        return frame.astype(np.float32) * np.float32(255.0 / np.iinfo(frame.dtype).max)
    return frame.astype(np.float32)


def inner_mask(mask: np.ndarray, margin_px: int = EDGE_MARGIN_PX) -> np.ndarray:
    """Return the window mask (bool, H x W) eroded by margin_px pixels."""
    m = (np.asarray(mask) > 0).astype(np.uint8)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin_px + 1, 2 * margin_px + 1))
    return cv2.erode(m, kernel) > 0


def darkening(img8: np.ndarray) -> np.ndarray:
    """Return the fractional darkening (float32, H x W) of each pixel below the local skin background."""
    smooth = cv2.GaussianBlur(img8, (0, 0), DENOISE_SIGMA_PX)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (BACKGROUND_KERNEL_PX, BACKGROUND_KERNEL_PX))
    background = cv2.morphologyEx(smooth, cv2.MORPH_CLOSE, kernel)
    background = cv2.GaussianBlur(background, (0, 0), BACKGROUND_SMOOTH_SIGMA_PX)
    return np.clip(1.0 - smooth / np.maximum(background, 1.0), 0.0, 1.0)


def noise_estimate_dn(img8: np.ndarray, inside: np.ndarray) -> float:
    """Return the sensor-noise std (DN) from a 3x3 second-difference residual that smooth skin and soft
    vessels barely excite: for white noise of std s its output has std 6 s and mean |.| of 6 s sqrt(2/pi)."""
    kernel = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    resid = cv2.filter2D(img8, -1, kernel)[inside]
    return float(np.abs(resid).mean() / (6.0 * np.sqrt(2.0 / np.pi)))


def frame_stats(frame: np.ndarray, mask: np.ndarray) -> FrameStats:
    """Return the FrameStats (DN, fraction, count) of one frame (any integer dtype) inside mask (H x W)."""
    img = to_8bit(frame)
    window = np.asarray(mask) > 0
    inside = inner_mask(mask)
    values = img[window]
    highpass = img - cv2.GaussianBlur(img, (0, 0), HIGHPASS_SIGMA_PX)
    dark = darkening(img)[inside]
    img_u8 = np.clip(np.round(img), 0, 255).astype(np.uint8)
    keypoints = cv2.SIFT_create().detect(img_u8, window.astype(np.uint8) * 255)
    return FrameStats(
        grey_std=float(values.std()),
        highpass_std=float(highpass[window].std()),
        inner_highpass_std=float(highpass[inside].std()),
        vessel_contrast=float(np.percentile(dark, VESSEL_CONTRAST_PERCENTILE)),
        keypoints=len(keypoints),
        mean_level=float(values.mean()),
        noise_dn=noise_estimate_dn(img, inside),
    )
