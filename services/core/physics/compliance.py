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
# The tissue's stiffness is known to a few per cent (the calibration; ../shared/scans/README.md: "a few per cent
# off"): a Gaussian prior of 5 % on c / c_nominal. Registration scales carry ~1 % of model error beyond their
# noise (deformation the spec §2 model does not capture: measured residual RMS 0.14-0.8 % of log-scale on the
# shared scans), so each frame's log-scale counts with at least 1 % of uncertainty. Without the two, the fit
# followed that model error to a compliance 15 % off on short_veins_21 (path RMSE 0.43 mm instead of 0.19).
PRIOR_REL = 0.05
LOG_SCALE_FLOOR = 0.01


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


def fit_compliance(
    scales: np.ndarray,
    loads_n: np.ndarray,
    c_nominal: float,
    prior_rel: float | None = PRIOR_REL,
    floor: float = LOG_SCALE_FLOOR,
) -> ComplianceFit | None:
    """Return the compliance and gauge that best explain per-frame scales |a_k| at loads F_k, or None.

    The log-scales log|a_k| + log q(F_k; c) should all equal log g: their variance over c in [0.5 c_n, 1.5 c_n]
    measures the misfit (a +-50% search: E is never that far off). With prior_rel, the maximum a posteriori c
    under a Gaussian prior of prior_rel on c / c_n and a per-frame log-scale noise of at least `floor`;
    without, the least-squares c. g = exp(mean) at that c. None when loads barely vary (not identifiable).
    """
    scales = np.asarray(scales, float)
    loads = np.asarray(loads_n, float)
    ok = np.isfinite(scales) & np.isfinite(loads) & (scales > 0)
    scales, loads = scales[ok], loads[ok]
    if len(scales) < 5 or np.ptp(loads) < MIN_LOAD_SPREAD_N:
        return None
    log_s = np.log(scales)
    bounds = (0.5 * c_nominal, 1.5 * c_nominal)

    def spread(c: float) -> float:
        return float(np.var(log_s + _log_q(loads, c_nominal, c)))

    c = float(minimize_scalar(spread, bounds=bounds, method="bounded").x)
    if prior_rel is not None:
        noise_var = max(spread(c), floor**2)

        def neg_log_posterior(c: float) -> float:
            return len(log_s) * spread(c) / (2.0 * noise_var) + 0.5 * ((c / c_nominal - 1.0) / prior_rel) ** 2

        c = float(minimize_scalar(neg_log_posterior, bounds=bounds, method="bounded").x)
    terms = log_s + _log_q(loads, c_nominal, c)
    return ComplianceFit(c, float(np.exp(np.mean(terms))), float(np.std(terms)), len(scales))
