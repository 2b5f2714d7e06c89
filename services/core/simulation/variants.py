"""How a simulated scan looks: skin, vessel contrast, noise, motion blur, gain drift and bit depth.

The default (`realistic`) matches the image statistics of the shared reference scans (smooth diffuse skin,
veins as the only structure); `faint` has vessels only 2-10 % darker than skin, below those scans, to show
margin; `textured` is the original simulator's fine-grain skin, an explicitly easy variant never used by
default. Every knob is a field, so a bench can build a robustness matrix with dataclasses.replace.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from services.core.simulation.vein_texture import TEXTURED_CONTRAST

VARIANTS = ("realistic", "faint", "textured")
REALISTIC_CONTRAST = (0.03, 0.28)  # fractional vessel darkening, deepest .. shallowest (crossings reach ~35 %)
FAINT_CONTRAST = (0.02, 0.10)


@dataclass(frozen=True)
class ImagingVariant:
    """The look of a simulated scan.

    vessel_contrast: (deepest, shallowest) fractional darkening of the vessels; textured_skin: fine-grain skin
    (the easy variant) instead of smooth diffuse skin; noise_dn: sensor noise std in 8-bit grey levels (DN);
    blur_fraction: share of frames (after frame 0) with motion blur, blur_length_px: its (min, max) length in
    px along the frame's motion; gain_drift: peak-to-peak slow exposure drift over the scan (fraction);
    gain_jitter: per-frame exposure jitter (+- fraction); bit_depth: 8 or 16 bits per pixel.
    """

    name: str = "realistic"
    vessel_contrast: tuple[float, float] = REALISTIC_CONTRAST
    textured_skin: bool = False
    noise_dn: float = 2.0
    blur_fraction: float = 0.3
    blur_length_px: tuple[int, int] = (2, 5)
    gain_drift: float = 0.12
    gain_jitter: float = 0.01
    bit_depth: int = 8

    def __post_init__(self) -> None:
        lo, hi = self.vessel_contrast
        if not 0.0 <= lo <= hi < 1.0:
            raise ValueError(f"vessel_contrast must satisfy 0 <= lo <= hi < 1, got {self.vessel_contrast}")
        if self.bit_depth not in (8, 16):
            raise ValueError(f"bit_depth must be 8 or 16, got {self.bit_depth}")
        if not 0.0 <= self.blur_fraction <= 1.0:
            raise ValueError(f"blur_fraction must be in [0, 1], got {self.blur_fraction}")
        b0, b1 = self.blur_length_px
        if not 1 <= b0 <= b1:
            raise ValueError(f"blur_length_px must satisfy 1 <= min <= max, got {self.blur_length_px}")
        if self.noise_dn < 0 or self.gain_drift < 0 or self.gain_jitter < 0:
            raise ValueError("noise_dn, gain_drift and gain_jitter must be >= 0")

    @property
    def dtype(self) -> type:
        """Return the frames' numpy dtype (uint8 or uint16)."""
        return np.uint8 if self.bit_depth == 8 else np.uint16

    def to_dict(self) -> dict[str, Any]:
        """Return the variant as a JSON-stable dict (tuples as lists)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}


def scenario_imaging(scenario: str, variant: str = "realistic") -> ImagingVariant:
    """Return the ImagingVariant of a scenario (its blur and bit depth) in a named variant (VARIANTS)."""
    if variant not in VARIANTS:
        raise ValueError(f"unknown imaging variant {variant!r}; expected one of {', '.join(VARIANTS)}")
    if scenario == "hard":
        # quick long steps: most frames blurred (the shared hard scan: 7 px mean, up to 16 px), 16-bit sensor
        base = ImagingVariant(noise_dn=3.0, blur_fraction=0.8, blur_length_px=(2, 14), bit_depth=16)
    elif scenario == "calib":
        # the probe held still at one place: no motion blur, no drift between the compared frames
        base = ImagingVariant(blur_fraction=0.0, gain_drift=0.0, gain_jitter=0.0)
    else:
        base = ImagingVariant()  # free-hand raster, revisit, short: slight blur (the shared short scan: <= 5 px)
    if variant == "faint":
        return dataclasses.replace(base, name="faint", vessel_contrast=FAINT_CONTRAST)
    if variant == "textured":
        return dataclasses.replace(base, name="textured", vessel_contrast=TEXTURED_CONTRAST, textured_skin=True)
    return base
