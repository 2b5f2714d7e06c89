"""Compliance self-calibration: recovering c_true and the gauge from scales made with the docstring's model
(least squares: prior_rel=None), and the default fit's prior pulling weak evidence towards the calibration."""

from __future__ import annotations

import numpy as np
import pytest

from services.core.physics.compliance import fit_compliance

C_NOMINAL = 0.5 / (16.1e3 * 0.0048)  # nu / (E A) at the paper's constants, 1/N
C_TRUE = C_NOMINAL / 0.94  # the tissue is 6% softer than assumed (E_true = 15.134 kPa)
GAUGE = 1.004


def _scales(loads: np.ndarray, noise: float, seed: int) -> np.ndarray:
    """|a_k| = g / q(F_k) with q(F) = (1 - c_n F) / (1 - c_t F) (compliance.py's model), log-normal noise."""
    rng = np.random.default_rng(seed)
    q = (1 - C_NOMINAL * loads) / (1 - C_TRUE * loads)
    return GAUGE / q * np.exp(rng.normal(0.0, noise, len(loads)))


def test_recovers_compliance_and_gauge_noise_free() -> None:
    loads = np.random.default_rng(0).uniform(2.0, 25.0, 40)
    fit = fit_compliance(_scales(loads, 0.0, 1), loads, C_NOMINAL, prior_rel=None)
    assert fit is not None and fit.n_frames == 40
    # bounded Brent stops at xatol 1e-5 (1/N) ~ 1.4e-3 of c: compare at 2e-3 relative; the gauge follows
    # the same small error times the mean log q (~0.1), so 1e-4 relative
    assert fit.compliance_per_n == pytest.approx(C_TRUE, rel=2e-3)
    assert fit.gauge == pytest.approx(GAUGE, rel=1e-4)
    assert fit.residual_rms < 1e-4
    assert fit.young_modulus_kpa(0.5, 0.0048) == pytest.approx(16.1 * 0.94, rel=2e-3)


def test_recovers_compliance_with_registration_noise() -> None:
    loads = np.random.default_rng(0).uniform(2.0, 25.0, 40)
    # 1e-4 scale noise (a similarity fit over ~300 inliers spread over the window): measured 1.6e-4
    # relative error in c; 1% still separates the true c from the nominal one (6% away)
    fit = fit_compliance(_scales(loads, 1e-4, 2), loads, C_NOMINAL, prior_rel=None)
    assert fit is not None
    assert fit.compliance_per_n == pytest.approx(C_TRUE, rel=0.01)
    assert fit.gauge == pytest.approx(GAUGE, rel=2e-4)
    assert fit.residual_rms == pytest.approx(1e-4, rel=0.5)


def test_nominal_truth_is_left_alone() -> None:
    loads = np.linspace(1.0, 20.0, 12)
    fit = fit_compliance(np.full(12, 1.0), loads, C_NOMINAL)  # q = 1 everywhere: nothing to correct
    assert fit is not None
    assert fit.compliance_per_n == pytest.approx(C_NOMINAL, rel=2e-3)
    assert fit.gauge == pytest.approx(1.0, rel=1e-4)  # same budget as the noise-free fit above


def test_none_when_loads_barely_vary() -> None:
    loads = np.random.default_rng(3).uniform(9.5, 10.5, 40)  # spread ~1 N < the 1.5 N needed
    assert fit_compliance(_scales(loads, 1e-4, 4), loads, C_NOMINAL) is None


def test_none_with_too_few_frames_and_bad_values_are_dropped() -> None:
    loads = np.array([2.0, 8.0, 14.0, 20.0])
    assert fit_compliance(_scales(loads, 0.0, 5), loads, C_NOMINAL) is None
    loads6 = np.array([2.0, 6.0, 10.0, 14.0, 18.0, 22.0, 5.0])
    scales = _scales(loads6, 0.0, 6)
    scales[-1] = np.nan  # an unplaced frame: ignored
    fit = fit_compliance(scales, loads6, C_NOMINAL, prior_rel=None)
    assert fit is not None and fit.n_frames == 6
    assert fit.compliance_per_n == pytest.approx(C_TRUE, rel=2e-3)


def test_weak_evidence_is_pulled_towards_the_calibration() -> None:
    # 40 frames whose scales say the tissue is 15 % softer, with 1 % model error per frame (the floor): the
    # evidence is weaker than the 5 % prior, so the default fit lands between nominal and the least-squares c
    loads = np.random.default_rng(7).uniform(4.0, 18.0, 40)
    c_soft = C_NOMINAL / 0.85
    q = (1 - C_NOMINAL * loads) / (1 - c_soft * loads)
    scales = GAUGE / q * np.exp(np.random.default_rng(8).normal(0.0, 0.01, len(loads)))
    free = fit_compliance(scales, loads, C_NOMINAL, prior_rel=None)
    regularised = fit_compliance(scales, loads, C_NOMINAL)
    assert free is not None and regularised is not None
    assert C_NOMINAL < regularised.compliance_per_n < free.compliance_per_n
    assert regularised.compliance_per_n < C_NOMINAL * 1.12  # measured 1.09 (least squares: 1.21)


def test_strong_evidence_overrides_the_prior() -> None:
    # 2000 frames over 2-25 N: the data pin c far tighter than the 5 % prior, so the 6 % softer truth is found
    loads = np.random.default_rng(9).uniform(2.0, 25.0, 2000)
    fit = fit_compliance(_scales(loads, 0.002, 10), loads, C_NOMINAL)
    assert fit is not None
    assert fit.compliance_per_n == pytest.approx(C_TRUE, rel=0.015)  # measured 4e-4 relative
