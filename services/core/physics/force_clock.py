"""The force logger's clock against the camera's, estimated from the scan itself (issue 30, "the force clock").

The registration measures each frame's scale: its pose scale |a| over the rectification's own shrink (1 - its
centre stretch), i.e. how much the skin in view is stretched, which follows the load the skin is under at the
frame's time. If the logger's clock runs delta seconds off the camera's, the load interpolated at the frame's
timestamp is the load at the wrong moment: F(t_k + delta) is the right one. To first order,
F(t_k + delta) = F_k + delta dF/dt(t_k), so the stretches fit

    s_k = alpha + beta (F_k + delta D_k)          (D_k: the load's rate at frame k, N/s; beta > 0, the compliance)

linear in (alpha, beta, beta delta): one least-squares solve gives delta = (beta delta) / beta, with its standard
error from the fit's covariance. The rates come from the frames' own loads (central differences within a run of
frames on the skin), so no other input than the path rows' is needed, live or offline.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

MIN_FRAMES = 20  # frames needed for an estimate
MAX_GAP_S = 0.35  # a rate is taken over neighbours at most this far apart (no rate across a lift or a drop)
MAX_OFFSET_S = 0.2  # an estimate beyond this is reported as not determined (the first-order model no longer holds)


@dataclass(frozen=True)
class ClockOffset:
    """The estimated offset (s: the load at a frame is the logged one at t + offset), its standard error, frames."""

    offset_s: float
    standard_error_s: float
    frames: int

    def to_dict(self) -> dict[str, float | int | None]:
        """Return the report's fields (s), None where not finite."""

        def num(v: float) -> float | None:
            return round(v, 4) if math.isfinite(v) else None

        return {
            "force_clock_offset_s": num(self.offset_s),
            "force_clock_offset_se_s": num(self.standard_error_s),
            "force_clock_frames": self.frames,
        }


def load_rates(t_s: np.ndarray, fz_n: np.ndarray, run: np.ndarray) -> np.ndarray:
    """Return each frame's load rate dF/dt (N/s) by central differences within its run; NaN at a run's ends."""
    t, f, r = (np.asarray(a) for a in (t_s, fz_n, run))
    rates = np.full(len(t), np.nan)
    if len(t) < 3:
        return rates
    dt = t[2:] - t[:-2]
    same = (r[2:] == r[1:-1]) & (r[:-2] == r[1:-1]) & (dt > 0) & (dt <= 2 * MAX_GAP_S)
    rates[1:-1] = np.where(same, (f[2:] - f[:-2]) / np.where(dt > 0, dt, 1.0), np.nan)
    return rates


def estimate_clock_offset(scales: np.ndarray, t_s: np.ndarray, fz_n: np.ndarray, run: np.ndarray) -> ClockOffset | None:
    """Return the force clock's offset from frames' stretches (pose scale / (1 - centre stretch)), times (s), loads
    (N) and run ids, or None.

    Frames in index order; run: an id per frame, equal within a run of consecutive frames on the skin.
    None with too few frames, no clear load dependence to time (beta within 3 standard errors of 0, or negative),
    or an offset beyond MAX_OFFSET_S.
    """
    s, t, f = (np.asarray(a, np.float64) for a in (scales, t_s, fz_n))
    d = load_rates(t, f, np.asarray(run))
    ok = np.isfinite(s) & np.isfinite(f) & np.isfinite(d)
    if int(ok.sum()) < MIN_FRAMES:
        return None
    design = np.column_stack([np.ones(int(ok.sum())), f[ok], d[ok]])
    coef, *_ = np.linalg.lstsq(design, s[ok], rcond=None)
    _, beta, beta_delta = (float(c) for c in coef)
    residual = s[ok] - design @ coef
    dof = max(int(ok.sum()) - 3, 1)
    cov = np.linalg.pinv(design.T @ design) * float(residual @ residual) / dof
    if not beta > 3.0 * math.sqrt(max(float(cov[1, 1]), 0.0)):  # the stretch must follow the load, clearly
        return None
    delta = beta_delta / beta
    # delta = c2 / c1: first-order error propagation
    grad = np.array([0.0, -beta_delta / beta**2, 1.0 / beta])
    se = math.sqrt(max(float(grad @ cov @ grad), 0.0))
    if abs(delta) > MAX_OFFSET_S:
        return None
    return ClockOffset(delta, se, int(ok.sum()))
