"""Simulated friction drag of the skin under the sliding window (issue 31): stick-slip, a centre-to-rim profile.

The skin sticks under the window's centre and is carried along the motion by up to `gain` mm per newton of load
(1-2.5 mm per 10 N), less toward the rim where it slips: a flat core of full drag, then a raised-cosine fall to
none at the rim. Along a stroke the drag builds while the skin sticks and drops when it slips (a sawtooth of a few
frames), and it is gone while the probe is off the skin or still. The profile is deliberately not the Gaussian
the reconstruction fits (services.core.physics.drag): the simulator must not mirror the model it tests.

A frame point p (mm about the window's centre, the frame's axes) shows the skin resting at p - D phi(|p|); the
truth (what a tracker on the skin gives) is the rest position of the skin under the centre, centre - R(yaw) D.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.core.simulation.probe_path import ProbeMotion, rotation

GAIN_MM_PER_N = (0.10, 0.25)  # the drag at the centre per newton of load (the 1-2.5 mm per 10 N)
CORE_MM = (4.0, 12.0)  # the stuck core's radius
RIM_MM = (28.0, 40.0)  # where the drag has faded to none
STICK_FRAMES = (3, 8)  # frames a stick phase lasts before the skin slips
SLIP_TO = (0.3, 0.6)  # the share of the full drag left just after a slip
STILL_MM = 0.2  # a frame moving less than this per frame drags nothing


@dataclass(frozen=True)
class SkinDrag:
    """A scan's true drag: gain (mm per N at the centre, at full stick), the profile's core and rim radii (mm)."""

    gain_mm_per_n: float
    core_mm: float
    rim_mm: float

    def profile(self, radius_mm: np.ndarray) -> np.ndarray:
        """Return the share of the centre's drag (1 in the core, 0 beyond the rim) at radii (mm)."""
        x = np.clip((np.asarray(radius_mm, np.float64) - self.core_mm) / (self.rim_mm - self.core_mm), 0.0, 1.0)
        return 0.5 * (1.0 + np.cos(np.pi * x))

    def to_dict(self) -> dict[str, float]:
        """Return the drag's truth (truth.json)."""
        return {"gain_mm_per_n": self.gain_mm_per_n, "core_mm": self.core_mm, "rim_mm": self.rim_mm}


def draw_skin_drag(rng: np.random.Generator) -> SkinDrag:
    """Return a scan's drag drawn from the ranges above."""
    return SkinDrag(float(rng.uniform(*GAIN_MM_PER_N)), float(rng.uniform(*CORE_MM)), float(rng.uniform(*RIM_MM)))


def frame_drags_mm(
    rng: np.random.Generator, drag: SkinDrag, motion: ProbeMotion, fz_n: np.ndarray, on_skin: np.ndarray
) -> np.ndarray:
    """Return each frame's drag at the centre (N, 2) mm in its own axes: along its motion, gain x load x stick."""
    n = len(motion)
    velocity = np.gradient(motion.centre_mm, axis=0) if n > 1 else np.zeros((n, 2))
    out = np.zeros((n, 2))
    stick, left = 1.0, int(rng.integers(*STICK_FRAMES, endpoint=True))
    for k in range(n):
        v = rotation(-float(motion.yaw_deg[k])) @ velocity[k]  # world mm -> frame k's axes
        speed = float(np.hypot(*v))
        if not on_skin[k] or speed < STILL_MM:
            stick, left = 0.0, int(rng.integers(*STICK_FRAMES, endpoint=True))
            continue
        stick = min(1.0, stick + (1.0 - stick) * 0.6 + 0.1)  # builds while the skin sticks
        left -= 1
        if left <= 0:  # slips: most of the drag is released at once
            stick *= float(rng.uniform(*SLIP_TO))
            left = int(rng.integers(*STICK_FRAMES, endpoint=True))
        out[k] = drag.gain_mm_per_n * max(float(fz_n[k]), 0.0) * stick * v / speed
    return out


def dragged_rest_mm(points_mm: np.ndarray, drag: SkinDrag, drag_mm: np.ndarray) -> np.ndarray:
    """Return the rest positions (..., 2) mm of the skin seen at frame points (..., 2) mm under a frame's drag."""
    radius = np.hypot(points_mm[..., 0], points_mm[..., 1])
    return points_mm - drag.profile(radius)[..., None] * np.asarray(drag_mm, np.float64)
