"""Whether the window touches the skin, frame by frame (spec §4 `no_contact`; issue "Real clinical scanning").

A clinician scans in strokes: between two, the probe is lifted and carried through the air. A frame taken in the
air shows defocused skin (and the LED ring reflected in the window) under no load. Two kinds of evidence decide:

- the load: the total force F_Z against the sensors' own tare (they read a few hundredths of a newton with
  nothing on them). The tare and its noise are estimated from the scan's own no-contact frames;
- the image: the fine-detail contrast of the window (`focus_measure`), against that of the recent frames under a
  clear load. Skin in contact is in focus; in the air it is blurred by the window's standoff.

The load decides unless the image clearly disagrees: a frame whose force reads off but whose image is as sharp
as skin in contact is a landing the force logger's skewed clock has not seen yet; a frame under a load whose
image is as blurred as the air is a lift the logger has not seen yet. The decision is causal (it depends only on
the frames before), so a live session and an offline run of the same scan decide the same.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import cv2
import numpy as np

from services.core.order_statistics import median

DEFAULT_TARE_N = 0.0  # before any no-contact frame was seen
DEFAULT_NOISE_N = 0.03  # the sensors' noise about their tare, before it is measured (N)
FORCE_MARGIN_N = 0.15  # a load this far above the tare (at least; or TARE_NOISE_SIGMAS of its noise) is contact
TARE_NOISE_SIGMAS = 6.0
TARE_CEILING_N = 0.5  # a frame below this total load (N) may be in the air: it feeds the tare's estimate ...
TARE_FRAMES = 200  # ... the newest this many of them
CLEAR_LOAD_N = 1.0  # a frame this far above the tare is surely in contact: its focus is the reference
FOCUS_FRAMES = 50  # the reference focus: the median over the newest this many surely-in-contact frames
FOCUS_MIN_REFERENCE = 5  # frames needed before the image may overrule the load
# The image overrules the load only on strong evidence: the focus of skin varies with its texture, collapse and
# motion blur (on the shared clinical scan, contact frames 0.67-1.5 of the reference and frames in the air 0.3-0.61;
# on a simulated one (strokes, seed 1), 0.40-1.6 and 0.6-0.72)
FOCUS_ON = 1.0  # focus at least the reference's, with some load (a noise sigma): a landing the log has not seen
FOCUS_OFF = 0.5  # focus below this share of it: the air ...
LIFT_LOAD_N = 1.0  # ... overruling a load below this much above the tare (a lift the logger lags; a frame under
# a clear load whose focus is low is motion-blurred skin, not the air)
FOCUS_FINE_SIGMA_PX = 1.5  # focus_measure's band: detail between these two blur scales (rectified pixels)
FOCUS_COARSE_SIGMA_PX = 5.0
FOCUS_PERCENTILE = 90.0
SPECK_LEVEL = 1.2  # grey levels this far above the window's median are specks, not skin ...
SPECK_MARGIN_PX = 11  # ... left out of the measure with this much around them


def focus_measure(image: np.ndarray, mask: np.ndarray) -> float:
    """Return the window's fine-detail contrast (the 90th percentile of |band-pass|, relative to its median grey).

    image: 8-bit frame (any normalisation: the measure divides by the window's median); mask: uint8 0/255 window.
    Bright specks (the LED ring's reflections, glare) are clipped so they do not read as detail.
    """
    # at half resolution (the band's scales halved): the same measure at a quarter of the cost
    small = cv2.pyrDown(image.astype(np.float32))
    small_mask = cv2.resize(mask, (small.shape[1], small.shape[0]), interpolation=cv2.INTER_NEAREST)
    inside = small_mask > 0
    if not np.any(inside):
        return 0.0
    level = max(median(small[inside]), 1.0)
    v = np.minimum(small / level, SPECK_LEVEL)
    band = cv2.GaussianBlur(v, (0, 0), FOCUS_FINE_SIGMA_PX / 2) - cv2.GaussianBlur(v, (0, 0), FOCUS_COARSE_SIGMA_PX / 2)
    inner = cv2.erode(small_mask, np.ones((5, 5), np.uint8)) > 0  # the window's rim is a step, not detail
    specks = cv2.dilate((v >= SPECK_LEVEL).astype(np.uint8), np.ones((SPECK_MARGIN_PX // 2 + 1,) * 2, np.uint8)) > 0
    keep = inner & ~specks  # nor are bright specks (the LED ring's reflections, glare) and their rims
    values = np.abs(band[keep if np.count_nonzero(keep) > 25 else inside])
    return float(np.percentile(values, FOCUS_PERCENTILE))


@dataclass(frozen=True)
class ContactDecision:
    """One frame's contact decision and its evidence (N, dimensionless ratio; NaN when not known yet)."""

    contact: bool
    load_above_tare_n: float
    focus_ratio: float
    by: str  # "load", "image" (the image overruled the load) or "load+image" (both agree)


@dataclass
class ContactDetector:
    """Causal contact decisions over a scan's frames, fed in order (the tare and focus reference learned as it goes)."""

    _air_loads: deque[float] = field(default_factory=lambda: deque(maxlen=TARE_FRAMES))
    _focus: deque[float] = field(default_factory=lambda: deque(maxlen=FOCUS_FRAMES))
    frames_without_contact: int = 0

    @property
    def tare_n(self) -> float:
        """Return the sensors' tare (N): the median total load of the frames that may be in the air."""
        return float(np.median(self._air_loads)) if len(self._air_loads) >= 3 else DEFAULT_TARE_N

    @property
    def noise_n(self) -> float:
        """Return the tare's noise (N): 1.4826 x the median absolute deviation of those loads."""
        if len(self._air_loads) < 3:
            return DEFAULT_NOISE_N
        loads = np.asarray(self._air_loads)
        return max(1.4826 * float(np.median(np.abs(loads - np.median(loads)))), 0.005)

    def decide(self, fz_n: float, focus: float) -> ContactDecision:
        """Return whether a frame under total load fz_n (N) with focus_measure `focus` touches the skin; learn."""
        tare, noise = self.tare_n, self.noise_n
        above = fz_n - tare
        load_on = above > max(FORCE_MARGIN_N, TARE_NOISE_SIGMAS * noise)
        known = len(self._focus) >= FOCUS_MIN_REFERENCE and math.isfinite(focus)
        ratio = focus / max(float(np.median(self._focus)), 1e-9) if known else math.nan
        by = "load"
        contact = load_on
        if known:
            if not load_on and ratio >= FOCUS_ON and above > noise:
                contact, by = True, "image"
            elif load_on and ratio < FOCUS_OFF and above < LIFT_LOAD_N:
                contact, by = False, "image"
            elif load_on == (ratio >= FOCUS_ON):
                by = "load+image"
        if fz_n < TARE_CEILING_N and not contact:
            self._air_loads.append(float(fz_n))
        if above > CLEAR_LOAD_N and contact and math.isfinite(focus):
            self._focus.append(float(focus))
        if not contact:
            self.frames_without_contact += 1
        return ContactDecision(contact, float(above), float(ratio), by)
