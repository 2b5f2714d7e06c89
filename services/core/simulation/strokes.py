"""A clinician's scan in strokes, simulated: rows stroked one way with the probe lifted and carried back through
the air, one stroke set down on ground no frame has seen yet (an island, which later rows overlap), frames taken
in the air, frames the camera dropped, and a force logger whose clock is off the camera's.

The motion is the free-hand motion of services.core.simulation.probe_path along the strokes; the carries through
the air are faster than the strokes (AIR_SPEED), carry no load, and their frames show defocused skin and the LED
ring reflected in the window (air_frame). scenarios.simulate("strokes", seed) puts it together.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from services.core.simulation.probe_path import (
    ProbeMotion,
    dense_grid,
    densify,
    frame_times,
    rotation,
    smooth_load,
    smooth_noise,
    smooth_tilts,
    wobble,
)

ROW_LENGTH_MM = 168.0
ROW_SPACING_MM = 18.0
ROWS = 7
ISLAND_AFTER_ROW = 2  # the island stroke comes after this row (0-based) ...
ISLAND_MM = ((100.0, 81.0), (160.0, 81.0))  # ... between rows 4 and 5 (y 72, 90): unseen until row 4
STEP_MM = 3.8  # mean step between frames on the skin (the shared scans' rasters)
AIR_SPEED = 4.0  # the probe is carried back this many times faster than it strokes
LAND_S = 0.15  # the load ramps up over this after a landing (and down before a lift)
DROP_FRACTION = 0.04  # frames the camera drops singly ...
DROP_BURST = 5  # ... and one burst of this many
CLOCK_SKEW_S = (0.02, 0.05)  # the force logger's clock runs this much (either sign) off the camera's
AIR_DEFOCUS_PX = 6.0  # the skin seen through the window held above it: out of focus ...
AIR_GAIN = 0.55  # ... and darker (the IR ring's light is not coupled into the skin)
LED_SPOTS = 7  # the LED ring reflected in the window: bright spots on a circle
LED_RADIUS_FRACTION = 0.38  # ... of this fraction of the frame's width


@dataclass(frozen=True)
class StrokedMotion:
    """A motion in strokes: the probe's motion and which frames were taken in the air (no contact)."""

    motion: ProbeMotion
    in_air: np.ndarray  # (N,) bool


def stroke_routes() -> list[np.ndarray]:
    """Return the strokes in route mm, in the order scanned: rows left to right, the island after ISLAND_AFTER_ROW."""
    rows = [np.array([[0.0, y], [ROW_LENGTH_MM, y]]) for y in ROW_SPACING_MM * np.arange(ROWS)]
    return [*rows[: ISLAND_AFTER_ROW + 1], np.array(ISLAND_MM), *rows[ISLAND_AFTER_ROW + 1 :]]


def _route_with_carries(strokes: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Return the dense route (M, 2) mm through every stroke and the carries between, and whether each point is
    in the air."""
    points, air = [], []
    for k, stroke in enumerate(strokes):
        if k:
            carry = densify(np.stack([strokes[k - 1][-1], stroke[0]]))[1:-1]
            points.append(carry)
            air.append(np.ones(len(carry), bool))
        dense = densify(stroke)
        points.append(dense)
        air.append(np.zeros(len(dense), bool))
    return np.concatenate(points), np.concatenate(air)


def stroked_motion(
    rng: np.random.Generator,
    kappa_n_per_mm: float,
    separation_mm: tuple[float, float],
    max_tilt_deg: float,
    load_range_n: tuple[float, float] = (2.0, 16.0),
) -> StrokedMotion:
    """Return a free-hand motion along stroke_routes(), carried through the air between strokes (no load there)."""
    route, air_points = _route_with_carries(stroke_routes())
    step = np.linalg.norm(np.diff(route, axis=0), axis=1)
    cost = step / np.where(air_points[1:], AIR_SPEED, 1.0)  # time per route step, in skin steps
    tau = np.concatenate([[0.0], np.cumsum(cost)])
    n = round(float(tau[-1]) / STEP_MM) + 1
    speed = 1.0 + 0.2 * smooth_noise(rng, n - 1, 8.0)
    u = np.concatenate([[0.0], np.cumsum(speed)])
    u *= tau[-1] / u[-1]
    pos = np.stack([np.interp(u, tau, route[:, 0]), np.interp(u, tau, route[:, 1])], axis=1)
    in_air = np.interp(u, tau, air_points.astype(float)) > 0.5
    pos = pos + wobble(rng, n, 1.5, 12.0)
    pos = pos - pos[0]
    yaw0 = rng.uniform(-30.0, 30.0)
    yaw_rel = smooth_noise(rng, n, 40.0)
    yaw_rel = 2.5 * (yaw_rel - yaw_rel[0]) / max(float(np.abs(yaw_rel - yaw_rel[0]).max()), 1e-12)
    centre = pos @ rotation(yaw0).T
    t = frame_times(rng, n, rng.uniform(5.0, 50.0))
    grid = dense_grid(t)
    contact = _contact_envelope(grid, t, in_air)
    fz = smooth_load(rng, grid, *load_range_n, 1.5) * contact
    tx, ty = smooth_tilts(rng, grid, np.maximum(fz, 1e-3), max_tilt_deg, kappa_n_per_mm, separation_mm, 2.0)
    motion = ProbeMotion(t, centre, yaw0 + yaw_rel, grid, fz, tx * contact, ty * contact)
    return StrokedMotion(motion, in_air)


def _contact_envelope(grid_t_s: np.ndarray, frame_t_s: np.ndarray, in_air: np.ndarray) -> np.ndarray:
    """Return 0..1 on the grid: 1 while the window is on the skin, ramping up over LAND_S after a landing and down
    over LAND_S before a lift. The window touches (or leaves) the skin halfway between two frames that differ."""
    midpoints = (frame_t_s[1:] + frame_t_s[:-1]) / 2
    on = (~in_air)[np.searchsorted(midpoints, grid_t_s)].astype(np.float64)
    width = max(round(LAND_S / float(grid_t_s[1] - grid_t_s[0])), 1)
    sums = np.concatenate([[0.0], np.cumsum(on)])
    k = np.arange(len(on))
    before = (sums[k + 1] - sums[np.maximum(k + 1 - width, 0)]) / width  # the mean over the last LAND_S
    after = (sums[np.minimum(k + width, len(on))] - sums[k]) / width  # ... and over the next
    return np.minimum(before, after)


def air_frame(scene: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Return a frame's noiseless scene (float32 reflectance) as seen in the air: defocused, darker, LED spots."""
    img = cv2.GaussianBlur(scene, (0, 0), AIR_DEFOCUS_PX) * np.float32(AIR_GAIN)
    h, w = img.shape
    spots = np.zeros_like(img)
    phase = 0.3  # the LEDs are fixed to the window: the same spots in every frame
    for k in range(LED_SPOTS):
        a = phase + 2.0 * np.pi * k / LED_SPOTS
        x = w / 2 + LED_RADIUS_FRACTION * w * np.cos(a)
        y = h / 2 + LED_RADIUS_FRACTION * w * 0.75 * np.sin(a)
        cv2.circle(spots, (int(x), int(y)), 3, 1.0, -1, cv2.LINE_AA)
    spots = cv2.GaussianBlur(spots, (0, 0), 1.5)
    return np.clip(img + 0.6 * spots, 0.0, 1.0).astype(np.float32)


def dropped_frames(rng: np.random.Generator, n: int) -> np.ndarray:
    """Return (n,) True for the frames the camera dropped: DROP_FRACTION singly and one burst (never frame 0)."""
    drop = rng.random(n) < DROP_FRACTION
    start = int(rng.integers(n // 3, 2 * n // 3))
    drop[start : start + DROP_BURST] = True
    drop[0] = False
    return drop


def clock_skew_s(rng: np.random.Generator) -> float:
    """Return the force logger's clock offset from the camera's (s): CLOCK_SKEW_S in size, either sign."""
    return float(rng.uniform(*CLOCK_SKEW_S) * rng.choice([-1.0, 1.0]))


def stroke_length_mm(centre_mm: np.ndarray, in_air: np.ndarray) -> float:
    """Return the length (mm) travelled on the skin: the steps between consecutive frames both on it."""
    on = ~np.asarray(in_air, bool)
    steps = np.linalg.norm(np.diff(centre_mm, axis=0), axis=1)
    return float(steps[on[1:] & on[:-1]].sum())
