"""Self-calibration of the tissue compliance from registration scales (beyond the paper).

A frame rectified with the nominal compliance c_n but truly deformed with c_t is scaled, about its centre,
by q(F) = (1 - c_n F) / (1 - c_t F) relative to the undeformed surface (spec §2 rectification at the centre,
where the local load is F_Z). The mosaic is the surface times a gauge g, so each placed frame's similarity
scale obeys |a_k| q(F_k) = g. Frames seen at different loads therefore reveal c_t, and g; dividing the path
by g puts it in true millimetres instead of frame 0's slightly mis-rectified ones.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar

MIN_LOAD_SPREAD_N = 1.5  # below this spread of loads the compliance is not identifiable


@dataclass(frozen=True)
class ComplianceFit:
    """Fitted compliance c_t (1/N), gauge g (mosaic units per true mm), residual RMS of log-scales, count."""

    compliance_per_n: float
    gauge: float
    residual_rms: float
    n_frames: int

    def young_modulus_kpa(self, poisson_ratio: float, area_m2: float) -> float:
        """Return E = nu / (c A) in kPa for the fitted compliance."""
        return poisson_ratio / (self.compliance_per_n * area_m2) / 1000.0


def _log_q(loads: np.ndarray, c_nominal: float, c_true: float) -> np.ndarray:
    return np.log(np.clip(1 - c_nominal * loads, 1e-3, None)) - np.log(np.clip(1 - c_true * loads, 1e-3, None))


def fit_compliance(scales: np.ndarray, loads_n: np.ndarray, c_nominal: float) -> ComplianceFit | None:
    """Return the compliance and gauge that best explain per-frame scales |a_k| at loads F_k, or None.

    Minimises the variance of log|a_k| + log q(F_k; c) over c in [0.5 c_n, 1.5 c_n] (a +-50% search: E
    is never that far off); g = exp(mean). None when loads barely vary (not identifiable).
    """
    scales = np.asarray(scales, float)
    loads = np.asarray(loads_n, float)
    ok = np.isfinite(scales) & np.isfinite(loads) & (scales > 0)
    scales, loads = scales[ok], loads[ok]
    if len(scales) < 5 or np.ptp(loads) < MIN_LOAD_SPREAD_N:
        return None
    log_s = np.log(scales)

    def spread(c: float) -> float:
        return float(np.var(log_s + _log_q(loads, c_nominal, c)))

    best = minimize_scalar(spread, bounds=(0.5 * c_nominal, 1.5 * c_nominal), method="bounded")
    c = float(best.x)
    terms = log_s + _log_q(loads, c_nominal, c)
    return ComplianceFit(c, float(np.exp(np.mean(terms))), float(np.std(terms)), len(scales))
