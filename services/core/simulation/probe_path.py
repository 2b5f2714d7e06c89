"""Simulated probe motion: frame times, poses (world mm, deg) and the continuous true load and tilts."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d

FRAME_PERIOD_S = 0.1  # ~10 Hz camera
FRAME_JITTER_S = 0.01  # frame timestamps jitter +-10 ms
GRID_DT_S = 0.002  # the dense time grid the continuous load and tilts are tabulated on
GRID_MARGIN_S = 1.0  # the grid extends this far beyond the first and last frame (force stream covers +-0.5 s)
MIN_SENSOR_FORCE_N = 0.05  # every true sensor force stays at or above this (a feasible load)
FEASIBILITY_MARGIN_N = 0.02  # extra headroom above MIN_SENSOR_FORCE_N when limiting the tilts
ROUTE_STEP_MM = 0.5  # routes are densified to this arc-length spacing before corner smoothing


@dataclass(frozen=True)
class ProbeMotion:
    """A probe's true motion: per-frame poses in world mm / deg and the continuous load on a dense grid.

    Arrays: frame_t_s (N,) s; centre_mm (N, 2) world position of the principal point; yaw_deg (N,) world
    yaw (R(yaw) maps frame mm to world mm); grid_t_s (T,) s; fz_n (T,) total load F_Z in N; tilt_x_rad,
    tilt_y_rad (T,) the tilts theta_x, theta_y of spec §2 in radians.
    """

    frame_t_s: np.ndarray
    centre_mm: np.ndarray
    yaw_deg: np.ndarray
    grid_t_s: np.ndarray
    fz_n: np.ndarray
    tilt_x_rad: np.ndarray
    tilt_y_rad: np.ndarray

    def __len__(self) -> int:
        return len(self.frame_t_s)

    def load_at(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return (F_Z in N, theta_x in rad, theta_y in rad) linearly interpolated at times t_s (s)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        return (
            np.interp(t, self.grid_t_s, self.fz_n),
            np.interp(t, self.grid_t_s, self.tilt_x_rad),
            np.interp(t, self.grid_t_s, self.tilt_y_rad),
        )

    def sensor_forces_at(
        self, t_s: np.ndarray, kappa_n_per_mm: float, separation_mm: tuple[float, float]
    ) -> np.ndarray:
        """Return the true sensor forces (len(t), 4) in N as F1..F4 at times t_s (inverse of spec §2)."""
        fz, tx, ty = self.load_at(t_s)
        return sensor_forces(fz, tx, ty, kappa_n_per_mm, separation_mm)


def sensor_forces(
    fz_n: np.ndarray,
    tilt_x_rad: np.ndarray,
    tilt_y_rad: np.ndarray,
    kappa_n_per_mm: float,
    separation_mm: tuple[float, float],
) -> np.ndarray:
    """Return sensor forces (..., 4) in N as F1..F4 for a load and tilts (the inverse of spec §2).

    F1 = F_Z/4 - kappa S_Y sin(theta_x), F2 = F_Z/4 + kappa S_Y sin(theta_x),
    F3 = F_Z/4 - kappa S_X sin(theta_y), F4 = F_Z/4 + kappa S_X sin(theta_y); so spec §2's
    theta_x = asin((F2 - F1) / (2 kappa S_Y)) and theta_y = asin((F4 - F3) / (2 kappa S_X)) recover them.
    """
    s_x, s_y = separation_mm
    quarter = np.asarray(fz_n, dtype=np.float64) / 4.0
    dx = kappa_n_per_mm * s_y * np.sin(np.asarray(tilt_x_rad, dtype=np.float64))
    dy = kappa_n_per_mm * s_x * np.sin(np.asarray(tilt_y_rad, dtype=np.float64))
    return np.stack([quarter - dx, quarter + dx, quarter - dy, quarter + dy], axis=-1)


def smooth_noise(rng: np.random.Generator, n: int, sigma: float, lo: float = -1.0, hi: float = 1.0) -> np.ndarray:
    """Return n samples of Gaussian-smoothed white noise (sigma in samples) rescaled to span [lo, hi]."""
    pad = int(4 * sigma) + 1
    raw = gaussian_filter1d(rng.standard_normal(n + 2 * pad), max(sigma, 1e-6), mode="reflect")[pad : pad + n]
    span = raw.max() - raw.min()
    unit = (raw - raw.min()) / span if span > 0 else np.full(n, 0.5)
    return lo + (hi - lo) * unit


def rotation(yaw_deg: float) -> np.ndarray:
    """Return the 2x2 rotation matrix R(yaw) in image coordinates (x right, y down)."""
    a = np.deg2rad(yaw_deg)
    return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])


def frame_times(rng: np.random.Generator, n: int, t0_s: float) -> np.ndarray:
    """Return n frame timestamps (s) at ~10 Hz, each jittered by up to +-10 ms, strictly increasing."""
    return t0_s + FRAME_PERIOD_S * np.arange(n) + rng.uniform(-FRAME_JITTER_S, FRAME_JITTER_S, n)


def densify(route_mm: np.ndarray, step_mm: float = ROUTE_STEP_MM) -> np.ndarray:
    """Return the polyline route (M, 2) mm resampled at equal arc-length steps of about step_mm."""
    seg = np.linalg.norm(np.diff(route_mm, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(2, int(np.ceil(s[-1] / step_mm)) + 1)
    u = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(u, s, route_mm[:, 0]), np.interp(u, s, route_mm[:, 1])], axis=1)


def arc_length(points_mm: np.ndarray) -> np.ndarray:
    """Return the cumulative arc length (M,) in mm along a polyline (M, 2)."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points_mm, axis=0), axis=1))])


def sample_route(
    rng: np.random.Generator,
    route_mm: np.ndarray,
    n_frames: int,
    corner_sigma_mm: float,
    speed_variation: float,
    speed_tau_frames: float,
) -> np.ndarray:
    """Return n_frames positions (n, 2) mm along a route with rounded corners and a varying speed.

    Steps between frames are proportional to 1 + speed_variation * smooth noise in [-1, 1].
    """
    dense = densify(route_mm)
    if corner_sigma_mm > 0:
        dense = gaussian_filter1d(dense, corner_sigma_mm / ROUTE_STEP_MM, axis=0, mode="nearest")
    s = arc_length(dense)
    speed = 1.0 + speed_variation * smooth_noise(rng, n_frames - 1, speed_tau_frames)
    u = np.concatenate([[0.0], np.cumsum(speed)])
    u *= s[-1] / u[-1]
    return np.stack([np.interp(u, s, dense[:, 0]), np.interp(u, s, dense[:, 1])], axis=1)


def wobble(rng: np.random.Generator, n: int, amplitude_mm: float, tau_frames: float) -> np.ndarray:
    """Return a smooth free-hand wobble (n, 2) in mm, each axis spanning [-amplitude, amplitude]."""
    return np.stack([smooth_noise(rng, n, tau_frames, -amplitude_mm, amplitude_mm) for _ in range(2)], axis=1)


def path_length_mm(points_mm: np.ndarray) -> float:
    """Return the summed length (mm) of the steps between consecutive positions (n, 2) mm."""
    return float(np.linalg.norm(np.diff(points_mm, axis=0), axis=1).sum())


def dense_grid(frame_t_s: np.ndarray) -> np.ndarray:
    """Return the dense time grid (s) covering the frames with GRID_MARGIN_S either side."""
    t0 = frame_t_s[0] - GRID_MARGIN_S
    n = int(np.ceil((frame_t_s[-1] + GRID_MARGIN_S - t0) / GRID_DT_S)) + 1
    return t0 + GRID_DT_S * np.arange(n)


def smooth_load(rng: np.random.Generator, grid_t_s: np.ndarray, lo_n: float, hi_n: float, tau_s: float) -> np.ndarray:
    """Return a smooth random total load F_Z (T,) in N with time scale tau_s, spanning [lo_n, hi_n] over the
    frames (the grid's GRID_MARGIN_S ends are clipped to the same range)."""
    raw = smooth_noise(rng, len(grid_t_s), tau_s / GRID_DT_S)
    inner = raw[int(GRID_MARGIN_S / GRID_DT_S) : len(raw) - int(GRID_MARGIN_S / GRID_DT_S)]
    span = max(float(inner.max() - inner.min()), 1e-12)
    return np.clip(lo_n + (hi_n - lo_n) * (raw - inner.min()) / span, lo_n, hi_n)


def tilt_limit(fz_n: np.ndarray, max_tilt_deg: float, kappa_n_per_mm: float, sep_mm: float) -> np.ndarray:
    """Return the largest feasible sin(tilt) (T,): every sensor force >= MIN_SENSOR_FORCE_N, capped at max."""
    headroom = np.maximum(0.0, np.asarray(fz_n) / 4.0 - MIN_SENSOR_FORCE_N - FEASIBILITY_MARGIN_N)
    return np.minimum(np.sin(np.deg2rad(max_tilt_deg)), headroom / (kappa_n_per_mm * sep_mm))


def smooth_tilts(
    rng: np.random.Generator,
    grid_t_s: np.ndarray,
    fz_n: np.ndarray,
    max_tilt_deg: float,
    kappa_n_per_mm: float,
    separation_mm: tuple[float, float],
    tau_s: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Return smooth random feasible tilts (theta_x, theta_y) in rad on the grid, |theta| <= max_tilt_deg."""
    s_x, s_y = separation_mm
    gx = 0.95 * smooth_noise(rng, len(grid_t_s), tau_s / GRID_DT_S)
    gy = 0.95 * smooth_noise(rng, len(grid_t_s), tau_s / GRID_DT_S)
    tx = np.arcsin(gx * tilt_limit(fz_n, max_tilt_deg, kappa_n_per_mm, s_y))
    ty = np.arcsin(gy * tilt_limit(fz_n, max_tilt_deg, kappa_n_per_mm, s_x))
    return tx, ty


def held_series(grid_t_s: np.ndarray, frame_t_s: np.ndarray, values: np.ndarray, hold_s: float = 0.04) -> np.ndarray:
    """Return a series on the grid that holds values[k] within +-hold_s of frame k and ramps in between."""
    knots_t = np.stack([frame_t_s - hold_s, frame_t_s + hold_s], axis=1).ravel()
    knots_v = np.repeat(np.asarray(values, dtype=np.float64), 2)
    return np.interp(grid_t_s, knots_t, knots_v)


# --- routes (polylines in route mm, before the world yaw) -------------------------------------------------


def serpentine_route(row_length_mm: float, n_rows: int, row_spacing_mm: float) -> np.ndarray:
    """Return the corners (2 n_rows, 2) mm of a serpentine raster along +x, stepping +y between rows."""
    pts = []
    for i in range(n_rows):
        y = i * row_spacing_mm
        xs = (0.0, row_length_mm) if i % 2 == 0 else (row_length_mm, 0.0)
        pts += [(xs[0], y), (xs[1], y)]
    return np.asarray(pts, dtype=np.float64)


def figure_eight_route(half_width_mm: float, half_height_mm: float, turns: float) -> np.ndarray:
    """Return a figure-eight (M, 2) mm starting at its crossing point and running `turns` times round."""
    phi = np.linspace(0.0, 2.0 * np.pi * turns, int(2000 * turns))
    return np.stack([half_width_mm * np.sin(phi), half_height_mm * np.sin(2.0 * phi)], axis=1)


def sweep_turn_route(first_mm: float, second_mm: float) -> np.ndarray:
    """Return an L-shaped sweep (3, 2) mm: first_mm along +x, a right-angle turn, second_mm along +y."""
    return np.array([[0.0, 0.0], [first_mm, 0.0], [first_mm, second_mm]])


def exam_route(
    length_mm: float, width_mm: float = 168.0, height_mm: float = 108.0, spacing_mm: float = 18.0
) -> np.ndarray:
    """Return the corners (M, 2) mm of a minutes-long examination: serpentine passes over one width x height area,
    alternately along rows (+x) and along columns (+y), each pass back over the last, cut at length_mm."""
    rows = serpentine_route(width_mm, round(height_mm / spacing_mm) + 1, spacing_mm)
    cols = serpentine_route(height_mm, round(width_mm / spacing_mm) + 1, spacing_mm)[:, ::-1]
    passes, pts = (rows, rows[::-1], cols, cols[::-1]), [np.zeros((1, 2))]
    total, k = 0.0, 0
    while total < length_mm:
        nxt = passes[k % len(passes)]
        seg = np.concatenate([pts[-1][-1:], nxt])
        total += float(np.linalg.norm(np.diff(seg, axis=0), axis=1).sum())
        pts.append(nxt)
        k += 1
    route = np.concatenate(pts)
    s = arc_length(route)
    end = int(np.searchsorted(s, length_mm))
    last = route[end - 1] + (route[end] - route[end - 1]) * (length_mm - s[end - 1]) / max(s[end] - s[end - 1], 1e-9)
    return np.concatenate([route[:end], last[None]])


# --- scenario motions ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class MotionSpec:
    """Parameters of a free-hand motion along a route (mm, frames, N, deg, s)."""

    n_frames: int
    route_mm: np.ndarray
    corner_sigma_mm: float
    speed_variation: float
    speed_tau_frames: float
    wobble_mm: float
    wobble_tau_frames: float
    yaw_amplitude_deg: float
    yaw_tau_frames: float
    load_range_n: tuple[float, float]
    load_tau_s: float
    max_tilt_deg: float
    tilt_tau_s: float
    target_length_mm: float | None = None  # rescale the sampled path to this length
    max_step_mm: float | None = None  # shrink the path if any step is longer


def free_hand_motion(
    rng: np.random.Generator,
    spec: MotionSpec,
    kappa_n_per_mm: float,
    separation_mm: tuple[float, float],
) -> ProbeMotion:
    """Return a ProbeMotion along spec.route_mm with wobble, yaw drift, speed variation, load and tilts."""
    n = spec.n_frames
    yaw0 = rng.uniform(-30.0, 30.0)
    pos = sample_route(rng, spec.route_mm, n, spec.corner_sigma_mm, spec.speed_variation, spec.speed_tau_frames)
    pos = pos + wobble(rng, n, spec.wobble_mm, spec.wobble_tau_frames)
    pos = pos - pos[0]
    if spec.target_length_mm is not None:
        pos *= spec.target_length_mm / path_length_mm(pos)
    if spec.max_step_mm is not None:
        longest = float(np.linalg.norm(np.diff(pos, axis=0), axis=1).max())
        if longest > spec.max_step_mm:
            pos *= spec.max_step_mm / longest
    yaw_rel = smooth_noise(rng, n, spec.yaw_tau_frames)
    yaw_rel -= yaw_rel[0]
    yaw_rel *= spec.yaw_amplitude_deg / max(float(np.abs(yaw_rel).max()), 1e-12)  # |yaw - yaw_0| <= amplitude
    # the route is laid out in frame 0's axes: rotate it into the world by frame 0's yaw
    centre = pos @ rotation(yaw0).T
    t = frame_times(rng, n, rng.uniform(5.0, 50.0))
    grid = dense_grid(t)
    fz = smooth_load(rng, grid, *spec.load_range_n, spec.load_tau_s)
    tx, ty = smooth_tilts(rng, grid, fz, spec.max_tilt_deg, kappa_n_per_mm, separation_mm, spec.tilt_tau_s)
    return ProbeMotion(t, centre, yaw0 + yaw_rel, grid, fz, tx, ty)


def calibration_motion(
    rng: np.random.Generator, kappa_n_per_mm: float, separation_mm: tuple[float, float]
) -> ProbeMotion:
    """Return the calibration sequence: 24 frames at one place (unloaded, 15 normal loads, 8 tilted).

    Frame 0 at F_Z ~ 0.3 N; frames 1..15 at 2..20 N with no tilt; frames 16..23 at 30 N with tilts up to
    ~0.45 deg (or the feasible limit with the true kappa). Loads are held around each frame time.
    """
    n_normal, n_tilted, tilted_load_n = 15, 8, 30.0
    n = 1 + n_normal + n_tilted
    t = frame_times(rng, n, rng.uniform(5.0, 50.0))
    grid = dense_grid(t)
    loads = np.concatenate([[0.3], np.linspace(2.0, 20.0, n_normal), np.full(n_tilted, tilted_load_n)])
    loads = loads * (1.0 + rng.uniform(-0.02, 0.02, n))
    s_x, s_y = separation_mm
    lim_x = float(tilt_limit(loads[-1] * 0.98, 0.5, kappa_n_per_mm, s_y))
    lim_y = float(tilt_limit(loads[-1] * 0.98, 0.5, kappa_n_per_mm, s_x))
    pattern = np.array(
        [[0.9, 0.0], [-0.9, 0.0], [0.0, 0.9], [0.0, -0.9], [0.6, 0.6], [-0.6, 0.6], [0.6, -0.6], [-0.6, -0.6]]
    )
    pattern = pattern + rng.uniform(-0.05, 0.05, pattern.shape) * (pattern != 0)
    tilts = np.zeros((n, 2))
    tilts[1 + n_normal :, 0] = np.arcsin(pattern[:, 0] * lim_x)
    tilts[1 + n_normal :, 1] = np.arcsin(pattern[:, 1] * lim_y)
    yaw0 = rng.uniform(-30.0, 30.0)
    return ProbeMotion(
        frame_t_s=t,
        centre_mm=np.zeros((n, 2)),
        yaw_deg=np.full(n, yaw0),
        grid_t_s=grid,
        fz_n=held_series(grid, t, loads),
        tilt_x_rad=held_series(grid, t, tilts[:, 0]),
        tilt_y_rad=held_series(grid, t, tilts[:, 1]),
    )


EXAM_STEP_MM = 3.63  # the raster's mean step between frames (1274 mm over 336 frames), kept over an examination


def scenario_motion_spec(scenario: str, n_frames: int | None = None) -> MotionSpec:
    """Return the MotionSpec of a free-hand scenario (raster, revisit, hard, short; exam of n_frames, 2400 by
    default: 4 minutes at 10 frames/s, ~8.7 m over one 168 x 108 mm area, as a breast examination)."""
    if scenario == "exam":
        n = 2400 if n_frames is None else int(n_frames)
        return MotionSpec(
            n_frames=n, route_mm=exam_route(n * EXAM_STEP_MM), corner_sigma_mm=4.0,
            speed_variation=0.2, speed_tau_frames=8.0, wobble_mm=1.5, wobble_tau_frames=12.0,
            yaw_amplitude_deg=2.5, yaw_tau_frames=40.0, load_range_n=(2.0, 12.0), load_tau_s=1.5,
            max_tilt_deg=0.3, tilt_tau_s=2.0,
        )  # fmt: skip
    if scenario == "raster":
        # 7 rows, 18 mm apart (the 40 mm-high view overlaps the next row by 55%), ~3.8 mm between frames
        return MotionSpec(
            n_frames=336, route_mm=serpentine_route(168.0, 7, 18.0), corner_sigma_mm=4.0,
            speed_variation=0.2, speed_tau_frames=8.0, wobble_mm=1.5, wobble_tau_frames=12.0,
            yaw_amplitude_deg=2.5, yaw_tau_frames=40.0, load_range_n=(2.0, 12.0), load_tau_s=1.5,
            max_tilt_deg=0.3, tilt_tau_s=2.0, target_length_mm=1274.0,
        )  # fmt: skip
    if scenario == "revisit":
        # a figure-eight that crosses its own track at the start and runs 15% past it
        return MotionSpec(
            n_frames=240, route_mm=figure_eight_route(75.0, 40.0, 1.15), corner_sigma_mm=0.0,
            speed_variation=0.2, speed_tau_frames=8.0, wobble_mm=1.5, wobble_tau_frames=12.0,
            yaw_amplitude_deg=3.0, yaw_tau_frames=40.0, load_range_n=(3.0, 14.0), load_tau_s=1.2,
            max_tilt_deg=0.3, tilt_tau_s=2.0,
        )  # fmt: skip
    if scenario == "hard":
        # long steps (up to ~18 mm: consecutive overlap ~60%), quick load changes, +-10 deg yaw
        return MotionSpec(
            n_frames=200, route_mm=serpentine_route(330.0, 6, 20.0), corner_sigma_mm=6.0,
            speed_variation=0.6, speed_tau_frames=4.0, wobble_mm=2.0, wobble_tau_frames=8.0,
            yaw_amplitude_deg=10.0, yaw_tau_frames=30.0, load_range_n=(5.0, 30.0), load_tau_s=0.25,
            max_tilt_deg=90.0, tilt_tau_s=0.6, max_step_mm=18.0,
        )  # fmt: skip
    if scenario == "short":
        return MotionSpec(
            n_frames=40, route_mm=sweep_turn_route(70.0, 45.0), corner_sigma_mm=6.0,
            speed_variation=0.2, speed_tau_frames=6.0, wobble_mm=1.0, wobble_tau_frames=10.0,
            yaw_amplitude_deg=2.0, yaw_tau_frames=20.0, load_range_n=(3.0, 12.0), load_tau_s=1.0,
            max_tilt_deg=0.3, tilt_tau_s=1.5,
        )  # fmt: skip
    raise ValueError(f"no free-hand motion for scenario {scenario!r}")
