"""Self-calibration of the tissue's strain law from registration scales (beyond the paper).

A frame rectified with the nominal compliance c_n (spec §2: r = r' (1 - c_n F)) but truly strained by eps(F) is
scaled, about its centre, by q(F) = (1 - c_n F) / (1 - eps(F)) relative to the undeformed surface (spec §2
rectification at the centre, where the local load is F_Z). The mosaic is the surface times a gauge g, so each
placed frame's similarity scale obeys |a_k| q(F_k) = g. Frames seen at different loads therefore reveal the law,
and g; dividing the path by g puts it in true millimetres instead of frame 0's slightly mis-rectified ones.

The law is spec §2's linear one, eps = c F, unless the scales show the tissue stiffening under compression; then
one of two shapes, whichever explains the scales better: stiffening, eps(F) = c F / (1 + s F) (c the zero-load
compliance, F_s = 1 / s the load at which the strain is half the linear law's), or saturating, eps(F) =
(c / s) (1 - exp(-s F)) (the strain levels off at c / s; half the linear law's at F_s = 1.594 / s). g
extrapolates the law to no load, so a linear fit to a stiffening tissue's scales misplaces the whole path's scale
(README, "Compliance self-calibration"). Two steps: the law's shape and s from the scales alone (their scatter
about the linear fit is the noise; adopted only when it beats the linear law both by BIC's ln n and past
chi-square's 1 % point), then its level by MAP, with the calibration's prior on the secant compliance
eps(F_ref) / F_ref at the frames' mean load F_ref (the calibration fits stretch against load at loads like the
scan's: spec §2, Calibration).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import minimize_scalar

MIN_LOAD_SPREAD_N = 1.5  # below this spread of loads the compliance is not identifiable
# The tissue's stiffness is known to a few per cent (the calibration; ../shared/scans/README.md: "a few per cent
# off"): a Gaussian prior of 5 % on k / c_nominal, k the secant compliance at the frames' mean load (c itself for
# the linear law). Registration scales carry ~1 % of model error beyond their
# noise (deformation the spec §2 model does not capture: measured residual RMS 0.14-0.8 % of log-scale on the
# shared scans), so each frame's log-scale counts with at least 1 % of uncertainty. Without the two, the fit
# followed that model error to a compliance 15 % off on short_veins_21 (path RMSE 0.43 mm instead of 0.19).
PRIOR_REL = 0.05
LOG_SCALE_FLOOR = 0.01
# The stiffening rate s = 1 / F_s (1/N) has a half-normal prior centred on the linear law, 1/30 N^-1 at one sigma
# (half the linear law's strain at 30 N, breast tissue's stiffening over a probe's loads); F_s is never below 5 N.
STIFFENING_PRIOR_PER_N = 1.0 / 30.0
STIFFENING_MAX_PER_N = 0.2
# The two curved shapes, each with its rate s in units where 1 / F_s (the half-strain load's inverse) is s / scale:
# the prior and the bound above are on 1 / F_s, so both shapes are held alike.
SATURATING_HALF_STRAIN = 1.5936  # s F at which (1 - exp(-s F)) / (s F) = 1/2
SHAPES = {"stiffening": 1.0, "saturating": SATURATING_HALF_STRAIN}
# The two shapes agree over a scan's loads and part below them, where the level is extrapolated: saturating is
# chosen only when it explains the scales better by this much chi-square (95 % for one degree of freedom).
SATURATING_MIN_GAIN_CHI2 = 4.0
# BIC's ln n alone admits a chance curvature on a 40-frame scan 2.7 % of the time (s is bounded at 0, so under the
# linear law its chi2 is 0 half the time, else chi-square with one degree of freedom, which exceeds ln 40 = 3.7 at
# 5.5 %): short_veins_21 adopted s = 0.0031 N^-1 at chi2 4.8, its path 0.20 % too large (0.096 mm) against 0.10 %
# (0.051 mm) with the linear law. The law must also pass chi-square's 1 % point (0.5 % for the bounded s); none of
# 45 simulated cells of bench/accuracy.py's kinds (seeds 1-3) falls between the two (they adopt at chi2 >= 8.0 or
# stay below 2.2; docs/accuracy.md).
STIFFENING_MIN_CHI2 = 6.63
# The scales' scatter about the linear fit is the noise the shape step weighs curvature against, at least the
# registration's own 1e-4 of log-scale (a similarity over ~300 inliers spread over the window).
SHAPE_NOISE_FLOOR = 1e-4
_DIFF_STEP = 1e-4  # relative step of the numerical second derivatives (Laplace 68 % ranges)
_TIGHT = {"xatol": 1e-12}  # the profiled level to ~1e-10 of itself, so those derivatives are not its rounding


@dataclass(frozen=True)
class ComplianceFit:
    """The fitted strain law (spec §2's c F when s = 0; else of the shape named) and the path's gauge.

    compliance_per_n: c, the zero-load compliance (1/N); gauge: mosaic units per true mm; residual_rms: RMS of the
    frames' log-scales about the fit; n_frames: frames used; stiffening_per_n: s (1/N, 0 = linear law), the rate
    of `shape` ("stiffening": c F / (1 + s F); "saturating": (c / s) (1 - exp(-s F)));
    reference_load_n: F_ref, the frames' mean load (N), where the prior holds the secant compliance;
    compliance_sd_per_n, stiffening_sd_per_n: 68 % half-widths (1/N); gauge_sd: that of log g (relative);
    stiffening_chi2: the chi-square the stiffening term gains over the linear law (adopted above
    max(ln n_frames, STIFFENING_MIN_CHI2)).
    """

    compliance_per_n: float
    gauge: float
    residual_rms: float
    n_frames: int
    stiffening_per_n: float = 0.0
    reference_load_n: float = 0.0
    compliance_sd_per_n: float = 0.0
    stiffening_sd_per_n: float = 0.0
    gauge_sd: float = 0.0
    stiffening_chi2: float = 0.0
    shape: str = "stiffening"
    shape_residual_rms: tuple[tuple[str, float], ...] = ()  # each curved shape's log-scale RMS at its best rate

    @property
    def law(self) -> str:
        """Return the shape ("stiffening" or "saturating") when the fit adopted a curved law, else "linear"."""
        return self.shape if self.stiffening_per_n > 0 else "linear"

    @property
    def half_strain_load_n(self) -> float:
        """Return F_s in N, the load at which the strain is half the linear law's (inf when linear)."""
        return SHAPES[self.shape] / self.stiffening_per_n if self.stiffening_per_n > 0 else math.inf

    @property
    def secant_compliance_per_n(self) -> float:
        """Return eps(F_ref) / F_ref in 1/N, the compliance the calibration's prior holds at the reference load."""
        return self.compliance_per_n / _zero_load_slope(self.stiffening_per_n, self.reference_load_n, self.shape)

    def strain(self, loads_n: np.ndarray | float) -> np.ndarray:
        """Return the fitted strain (dimensionless) at loads in N (spec §2's c F when linear)."""
        f = np.maximum(np.asarray(loads_n, float), 0.0)
        return self.secant_compliance_per_n * _shape(f, self.stiffening_per_n, self.reference_load_n, self.shape)

    def expected_scales(self, loads_n: np.ndarray, c_nominal: float) -> np.ndarray:
        """Return the pose scales |a_k| (dimensionless) this law and gauge predict for frames at loads F_k (N)
        rectified at the nominal compliance c_nominal: g (1 - eps(F)) / (1 - c_n F), fit_compliance's model."""
        f = np.asarray(loads_n, float)
        return self.gauge * (1.0 - self.strain(f)) / np.clip(1.0 - c_nominal * f, 1e-3, None)

    def young_modulus_kpa(self, poisson_ratio: float, area_m2: float) -> float:
        """Return E = nu / (c A) in kPa for the fitted zero-load compliance (the small-strain modulus)."""
        return poisson_ratio / (self.compliance_per_n * area_m2) / 1000.0

    def law_dict(self) -> dict[str, Any]:
        """Return the law's parameters with their 68 % ranges for the learned-model document (None = unbounded)."""
        s, sd = self.stiffening_per_n, self.stiffening_sd_per_n

        def finite(v: float) -> float | None:
            return float(v) if math.isfinite(v) else None

        def half_load(rate: float) -> float | None:
            return finite(SHAPES[self.shape] / rate) if rate > 0 else None

        return {
            "compliance_law": self.law,
            "compliance_sd_per_n": finite(self.compliance_sd_per_n),
            "compliance_reference_load_n": self.reference_load_n,
            "compliance_secant_per_n": self.secant_compliance_per_n,
            "stiffening_per_n": s,
            "stiffening_sd_per_n": finite(sd),
            "stiffening_chi2": self.stiffening_chi2,
            "half_strain_load_n": half_load(s),
            "half_strain_load_low_n": half_load(s + sd) if s > 0 else None,
            "half_strain_load_high_n": half_load(s - sd) if s > 0 else None,
            "gauge_sd": finite(self.gauge_sd),
            "compliance_shape_residual_rms": dict(self.shape_residual_rms) or None,
        }


def _shape(loads: np.ndarray, s: float, reference_n: float, shape: str = "stiffening") -> np.ndarray:
    """Return the strain (N) of secant compliance 1 at F_ref (spec §2's F when s = 0): F (1 + s F_ref) / (1 + s F)
    stiffening, F_ref (1 - exp(-s F)) / (1 - exp(-s F_ref)) saturating."""
    if shape == "saturating" and s * reference_n > 1e-9:
        return reference_n * np.expm1(-s * loads) / math.expm1(-s * reference_n)
    return loads * (1.0 + s * reference_n) / (1.0 + s * loads)


def _zero_load_slope(s: float, reference_n: float, shape: str) -> float:
    """Return d_shape/dF at F = 0: the zero-load compliance over the secant at F_ref (1 when linear)."""
    if shape == "saturating" and s * reference_n > 1e-9:
        return s * reference_n / -math.expm1(-s * reference_n)
    return 1.0 + s * reference_n


def _second_derivative(f: Any, x: float, h: float) -> float:
    """Return f''(x) by central differences with step h."""
    return (f(x + h) - 2.0 * f(x) + f(x - h)) / (h * h)


def fit_compliance(
    scales: np.ndarray,
    loads_n: np.ndarray,
    c_nominal: float,
    prior_rel: float | None = PRIOR_REL,
    floor: float = LOG_SCALE_FLOOR,
    stiffening: bool = True,
    stiffening_prior_per_n: float | None = STIFFENING_PRIOR_PER_N,
) -> ComplianceFit | None:
    """Return the strain law and gauge that best explain per-frame scales |a_k| at loads F_k (N), or None.

    Shape (when `stiffening`): s in [0, STIFFENING_MAX_PER_N] maximising the scales' likelihood (noise: their
    scatter about the linear fit, at least SHAPE_NOISE_FLOOR) under the half-normal prior on s; kept when it gains
    more than ln n and STIFFENING_MIN_CHI2 in chi-square over s = 0, else the linear law. Level: the secant
    compliance k at F_ref (the mean load) whose log-scales log|a_k| + log q(F_k) scatter least, over k in
    [0.5 c_n, 1.5 c_n] (E is never that far off); with prior_rel, the maximum a posteriori k under a Gaussian
    prior of prior_rel on k / c_n and a per-frame log-scale noise of at least `floor`; without, the least-squares k.
    g = exp(mean) at the fit.
    None when loads barely vary (not identifiable).
    """
    scales = np.asarray(scales, float)
    loads = np.asarray(loads_n, float)
    ok = np.isfinite(scales) & np.isfinite(loads) & (scales > 0)
    scales, loads = scales[ok], loads[ok]
    n = len(scales)
    if n < 5 or np.ptp(loads) < MIN_LOAD_SPREAD_N:
        return None
    y = np.log(scales) + np.log(np.clip(1 - c_nominal * loads, 1e-3, None))  # log g + log(1 - eps(F_k))
    reference = float(np.mean(loads))
    bounds = (0.5 * c_nominal, 1.5 * c_nominal)

    def terms(k: float, s: float, shape: str) -> np.ndarray:
        return y - np.log(np.clip(1 - k * _shape(loads, s, reference, shape), 1e-3, None))

    def spread(k: float, s: float, shape: str) -> float:
        return float(np.var(terms(k, s, shape)))

    def least_squares(s: float, shape: str) -> float:
        return float(minimize_scalar(lambda k: spread(k, s, shape), bounds=bounds, method="bounded", options=_TIGHT).x)

    shape, s, s_sd, chi2 = "stiffening", 0.0, 0.0, 0.0  # the linear law: s = 0, where both shapes are the same
    shape_rms: dict[str, float] = {}
    if stiffening:
        noise_var = max(spread(least_squares(0.0, shape), 0.0, shape), SHAPE_NOISE_FLOOR**2)  # about the linear law

        def data_cost(rate: float, shape: str) -> float:  # n/2 x the log-scales' variance, profiled over the level
            return n * spread(least_squares(rate, shape), rate, shape) / 2.0

        def prior_curvature(shape: str) -> float:  # of the half-normal prior on 1 / F_s, in the shape's rate
            return 0.0 if stiffening_prior_per_n is None else (SHAPES[shape] * stiffening_prior_per_n) ** -2

        def shape_cost(rate: float, shape: str) -> float:  # -log posterior of the shape
            return data_cost(rate, shape) / noise_var + 0.5 * prior_curvature(shape) * rate**2

        costs: dict[str, tuple[float, float]] = {}  # each curved shape: (its cost, its rate) at its best rate
        for name, unit in SHAPES.items():
            found = minimize_scalar(
                shape_cost, args=(name,), bounds=(0.0, unit * STIFFENING_MAX_PER_N), method="bounded"
            )
            costs[name] = (float(found.fun), float(found.x))
            shape_rms[name] = math.sqrt(spread(least_squares(costs[name][1], name), costs[name][1], name))
        better = costs["saturating"][0] < costs["stiffening"][0] - SATURATING_MIN_GAIN_CHI2 / 2.0
        curved = "saturating" if better else "stiffening"
        chi2 = max(0.0, 2.0 * (shape_cost(0.0, curved) - costs[curved][0]))
        if chi2 > max(math.log(n), STIFFENING_MIN_CHI2):
            shape, s = curved, costs[curved][1]
            h = max(_DIFF_STEP * SHAPES[shape] * STIFFENING_MAX_PER_N, 1e-3 * s)
            fitted_var = max(spread(least_squares(s, shape), s, shape), SHAPE_NOISE_FLOOR**2)  # about the law
            curvature = _second_derivative(lambda r: data_cost(r, shape), max(s, h), h) / fitted_var
            curvature += prior_curvature(shape)
            s_sd = 1.0 / math.sqrt(curvature) if curvature > 0 else math.inf

    k = least_squares(s, shape)
    if prior_rel is not None:
        level_var = max(spread(k, s, shape), floor**2)

        def neg_log_posterior(kk: float) -> float:
            return n * spread(kk, s, shape) / (2.0 * level_var) + 0.5 * ((kk / c_nominal - 1.0) / prior_rel) ** 2

        k = float(minimize_scalar(neg_log_posterior, bounds=bounds, method="bounded").x)
        k_curvature = _second_derivative(neg_log_posterior, k, _DIFF_STEP * k)
    else:
        k_curvature = _second_derivative(lambda kk: n * spread(kk, s, shape) / 2.0, k, _DIFF_STEP * k) / max(
            spread(k, s, shape), SHAPE_NOISE_FLOOR**2
        )
    k_sd = 1.0 / math.sqrt(k_curvature) if k_curvature > 0 else math.inf

    t = terms(k, s, shape)
    log_g = float(np.mean(t))
    # 68 % half-widths (Laplace): the level's given the shape, the shape's moving the level along its profile
    # (the least-squares level at each s), and the mean log-scale's own scatter
    dlogg_dk = (np.mean(terms(k * (1 + _DIFF_STEP), s, shape)) - log_g) / (k * _DIFF_STEP)
    gauge_var = (dlogg_dk * k_sd) ** 2 + float(np.var(t)) / n
    grow = _zero_load_slope(s, reference, shape)
    c0 = k * grow  # the zero-load compliance of the law with secant k at F_ref
    c0_var = (grow * k_sd) ** 2
    if s > 0 and math.isfinite(s_sd):
        ds = max(_DIFF_STEP * STIFFENING_MAX_PER_N, 1e-3 * s)
        s_lo, s_hi = max(s - ds, 0.0), s + ds
        k_lo, k_hi = least_squares(s_lo, shape), least_squares(s_hi, shape)
        dlogg_ds = (np.mean(terms(k_hi, s_hi, shape)) - np.mean(terms(k_lo, s_lo, shape))) / (s_hi - s_lo)
        c0_lo, c0_hi = (kk * _zero_load_slope(ss, reference, shape) for kk, ss in ((k_lo, s_lo), (k_hi, s_hi)))
        dc0_ds = (c0_hi - c0_lo) / (s_hi - s_lo)
        gauge_var += (dlogg_ds * s_sd) ** 2
        c0_var += (dc0_ds * s_sd) ** 2
    return ComplianceFit(
        compliance_per_n=c0,
        gauge=math.exp(log_g),
        residual_rms=float(np.std(t)),
        n_frames=n,
        stiffening_per_n=s,
        reference_load_n=reference,
        compliance_sd_per_n=math.sqrt(c0_var),
        stiffening_sd_per_n=s_sd,
        gauge_sd=math.sqrt(gauge_var),
        stiffening_chi2=chi2,
        shape=shape,
        shape_residual_rms=tuple(shape_rms.items()),
    )
