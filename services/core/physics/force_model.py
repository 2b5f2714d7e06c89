"""The force model of spec §2: sensor forces to total load, tilt, local load map and radial rectification."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.core.inputs.calibration import Calibration

MIN_RECTIFY_FACTOR = 0.05  # 1 - c F below this would fold the image; the model is meaningless there


@dataclass(frozen=True)
class LoadState:
    """The probe's load at one instant: total load F_Z (N) and tilts theta_x, theta_y (rad), spec §2."""

    fz_n: float
    theta_x_rad: float
    theta_y_rad: float

    @property
    def normal(self) -> np.ndarray:
        """Return the tilted normal u' = Rx(theta_x) Ry(theta_y) [0, 0, 1]^T (unit vector)."""
        sx, cx = np.sin(self.theta_x_rad), np.cos(self.theta_x_rad)
        sy, cy = np.sin(self.theta_y_rad), np.cos(self.theta_y_rad)
        return np.array([sy, -sx * cy, cx * cy])


def interpolate_forces(sample_t: np.ndarray, samples: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Return sensor forces (N, shape (len(t), C)) linearly interpolated at times t (s); ends are held.

    Samples may be unsorted and may repeat a timestamp (overlapping upload batches): repeats are averaged.
    """
    sample_t = np.asarray(sample_t, dtype=np.float64).ravel()
    samples = np.asarray(samples, dtype=np.float64)
    t = np.atleast_1d(np.asarray(t, dtype=np.float64))
    if len(sample_t) == 0:
        raise ValueError("no force samples to interpolate")
    if samples.ndim == 1:
        samples = samples[:, None]
    if samples.ndim != 2 or samples.shape[0] != len(sample_t):
        raise ValueError(f"force samples: expected {len(sample_t)} rows (one per time), got {samples.shape}")
    uniq, inverse = np.unique(sample_t, return_inverse=True)
    sums = np.zeros((len(uniq), samples.shape[1]))
    np.add.at(sums, inverse, samples)
    means = sums / np.bincount(inverse, minlength=len(uniq))[:, None]
    return np.stack([np.interp(t, uniq, means[:, c]) for c in range(means.shape[1])], axis=1)


def samples_around(sample_t: np.ndarray, samples: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
    """Return the rows of samples at strictly increasing times sample_t (s) that interpolating at time t (s) reads:
    its two neighbours, or the end held (interpolate_forces gives the same forces from them as from all). A long
    examination holds tens of thousands of samples; a frame needs two."""
    k = int(np.searchsorted(sample_t, t))
    lo, hi = max(k - 1, 0), min(k + 1, len(sample_t))
    return sample_t[lo:hi], samples[lo:hi]


def load_state(forces_n: np.ndarray, calib: Calibration) -> LoadState:
    """Return the LoadState for sensor forces (F1, F2, F3, F4) in N (spec §2, sides as settled there)."""
    f1, f2, f3, f4 = (float(v) for v in np.asarray(forces_n, dtype=np.float64).ravel()[:4])
    kappa = calib.hooke_n_per_mm
    s_x, s_y = calib.sensor_separation_mm
    theta_x = float(np.arcsin(np.clip((f2 - f1) / (2.0 * kappa * s_y), -1.0, 1.0)))
    theta_y = float(np.arcsin(np.clip((f4 - f3) / (2.0 * kappa * s_x), -1.0, 1.0)))
    return LoadState(fz_n=f1 + f2 + f3 + f4, theta_x_rad=theta_x, theta_y_rad=theta_y)


def depth_deviation_mm(xy_mm: np.ndarray, state: LoadState) -> np.ndarray:
    """Return Z(x, y) = -(u'_x x + u'_y y) / u'_z in mm for points (..., 2) in mm (spec §2)."""
    u = state.normal
    xy = np.asarray(xy_mm, dtype=np.float64)
    return -(u[0] * xy[..., 0] + u[1] * xy[..., 1]) / u[2]


def local_load_n(xy_mm: np.ndarray, state: LoadState, calib: Calibration) -> np.ndarray:
    """Return F(x, y) = max(0, F_Z + kappa Z(x, y)) in N for points (..., 2) in mm (spec §2)."""
    return np.maximum(0.0, state.fz_n + calib.hooke_n_per_mm * depth_deviation_mm(xy_mm, state))


def rectify_factor(xy_obs_mm: np.ndarray, state: LoadState, calib: Calibration) -> np.ndarray:
    """Return r / r' = 1 - nu / (E A) F(x', y') at observed points (..., 2) in mm (spec §2)."""
    factor = 1.0 - calib.compliance_per_n * local_load_n(xy_obs_mm, state, calib)
    return np.maximum(factor, MIN_RECTIFY_FACTOR)


def rectify_points_mm(xy_obs_mm: np.ndarray, state: LoadState, calib: Calibration) -> np.ndarray:
    """Return undeformed positions (mm, about the principal point) of observed positions (..., 2) in mm."""
    xy = np.asarray(xy_obs_mm, dtype=np.float64)
    return xy * rectify_factor(xy, state, calib)[..., None]


def deform_points_mm(xy_mm: np.ndarray, state: LoadState, calib: Calibration, iterations: int = 8) -> np.ndarray:
    """Return observed positions (mm) of undeformed positions (..., 2) in mm: the inverse of rectification.

    Solves p = p' (1 - c F(p')) for p' by fixed-point iteration p' <- p / (1 - c F(p')); the map is a
    contraction for any physical load (c |grad F| r << 1), and 8 iterations reach far below 1e-6 mm.
    """
    p = np.asarray(xy_mm, dtype=np.float64)
    obs = p.copy()
    for _ in range(iterations):
        obs = p / rectify_factor(obs, state, calib)[..., None]
    return obs


def centre_stretch(state: LoadState, calib: Calibration) -> float:
    """Return the fractional stretch nu F_Z / (E A) at the window centre (dimensionless)."""
    return calib.compliance_per_n * max(0.0, state.fz_n)
