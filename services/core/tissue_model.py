"""The probe's true tilt, learned from the scan: an effective kappa fitted from every match's affine evidence.

Spec §2 gives the tilt as theta = asin(dF / (2 kappa S)) and says kappa is a per-patient unknown: the
calibration's 18 N/mm (one phantom's) makes a hand's force differences hundredths of a degree, while a
hand-held probe tilts by degrees (on ../shared/scans the tracker's tilts follow the force differences with
an effective kappa of 0.13-0.17 N/mm, correlation >= 0.997). A tilted view is an affine stretch of the surface,
1/cos(theta) along the tilt direction (the paper's model, the reason for its A-SIFT): observed mm = D undeformed
mm about the window centre. Two frames tilted differently are related by an affine, not a similarity, and
the part of each pairwise affine that no similarity explains measures kappa:

    C_ij(kappa) = D_i(kappa)^-1 A_ij D_j(kappa)     (A_ij: the match's affine, frame j mm -> frame i mm)

is a similarity at the true kappa. fit_kappa finds the kappa that makes every C_ij most similar (MAP, a wide
log-normal prior on the calibration's kappa, Cauchy-robust); corrected_relative returns C_ij's similarity, the
edge the pose graph then uses, so the path and the mosaic are in undeformed millimetres, frame 0's included.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar

from services.core.registration import Similarity

KAPPA_BOUNDS_N_PER_MM = (0.01, 100.0)  # the search range: tilts of tens of degrees down to none
PRIOR_LOG_SIGMA = 3.0  # the calibration's kappa is a weak prior: e^3 = 20x either way is one sigma
AFFINE_FLOOR = 1e-3  # non-similarity noise floor per edge (0.1 %: deformation no model here captures)
MIN_AFFINE_EDGES = 8  # fewer edges with affine evidence: kappa stays at the prior
CAUCHY_SCALE = 3.0  # robust scale, in units of an edge's sigma
MIN_COS_TILT = 0.25  # a view tilted beyond 75 deg is no view: the stretch is capped there (4x)


@dataclass(frozen=True)
class AffineEvidence:
    """One match's full affine (2x3, frame j mm -> frame i mm) and its non-similarity sigma (dimensionless)."""

    i: int
    j: int
    affine: np.ndarray
    sigma: float


@dataclass(frozen=True)
class KappaFit:
    """The fitted effective kappa (N/mm), its 1-sigma range in log space, edges used and residual RMS."""

    kappa_n_per_mm: float
    log_sigma: float
    n_edges: int
    residual_rms: float
    residual_rms_nominal: float  # the same residual with the prior's kappa: how much the fit explains

    def to_dict(self) -> dict[str, float | int]:
        """Return the fit as JSON-able numbers (kappa N/mm with its 68 % range, residuals dimensionless)."""
        return {
            "kappa_n_per_mm": self.kappa_n_per_mm,
            "kappa_low_n_per_mm": self.kappa_n_per_mm * math.exp(-self.log_sigma),
            "kappa_high_n_per_mm": self.kappa_n_per_mm * math.exp(self.log_sigma),
            "edges": self.n_edges,
            "affine_residual_rms": self.residual_rms,
            "affine_residual_rms_nominal": self.residual_rms_nominal,
        }


def tilt_angles_rad(forces_n: np.ndarray, kappa_n_per_mm: float, separation_mm: Sequence[float]) -> np.ndarray:
    """Return (..., 2) tilts (theta_x, theta_y) in rad of sensor forces (..., 4) N: spec §2 with this kappa."""
    f = np.asarray(forces_n, np.float64)
    s_x, s_y = float(separation_mm[0]), float(separation_mm[1])
    theta_x = np.arcsin(np.clip((f[..., 1] - f[..., 0]) / (2.0 * kappa_n_per_mm * s_y), -1.0, 1.0))
    theta_y = np.arcsin(np.clip((f[..., 3] - f[..., 2]) / (2.0 * kappa_n_per_mm * s_x), -1.0, 1.0))
    return np.stack([theta_x, theta_y], axis=-1)


def foreshortening(forces_n: np.ndarray, kappa_n_per_mm: float, separation_mm: Sequence[float]) -> np.ndarray:
    """Return D (..., 2, 2): observed mm = D undeformed mm, a stretch 1/cos(tilt) along the tilt direction.

    The tilted normal u' = Rx(theta_x) Ry(theta_y) [0, 0, 1] (spec §2); its image-plane part (u'_x, u'_y)
    points along the tilt, and u'_z is the cosine of the whole tilt.
    """
    theta = tilt_angles_rad(forces_n, kappa_n_per_mm, separation_mm)
    sx, cx = np.sin(theta[..., 0]), np.cos(theta[..., 0])
    sy, cy = np.sin(theta[..., 1]), np.cos(theta[..., 1])
    n = np.stack([sy, -sx * cy], axis=-1)
    nz = np.maximum(cx * cy, MIN_COS_TILT)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    g = np.divide(n, norm, out=np.zeros_like(n), where=norm > 1e-12)
    stretch = (1.0 / nz - 1.0)[..., None, None]
    return np.eye(2) + stretch * (g[..., :, None] * g[..., None, :])


def corrected_affine(affine: np.ndarray, d_i: np.ndarray, d_j: np.ndarray) -> np.ndarray:
    """Return (..., 2, 3) D_i^-1 [A | t] with D_j applied on the right: the match between undeformed frames."""
    a = np.asarray(affine, np.float64)
    inv_i = np.linalg.inv(d_i)
    linear = inv_i @ a[..., :, :2] @ d_j
    shift = (inv_i @ a[..., :, 2:3])[..., 0]
    return np.concatenate([linear, shift[..., None]], axis=-1)


def nearest_similarity(affine: np.ndarray) -> Similarity:
    """Return the similarity nearest (least squares on the linear part) to a 2x3 affine."""
    m = np.asarray(affine, np.float64)
    a = complex((m[0, 0] + m[1, 1]) / 2.0, (m[1, 0] - m[0, 1]) / 2.0)
    return Similarity(a, complex(m[0, 2], m[1, 2]))


def corrected_relative(relative: Similarity, affine: np.ndarray | None, d_i: np.ndarray, d_j: np.ndarray) -> Similarity:
    """Return an edge's relative similarity between undeformed frames (from its affine, else its similarity)."""
    measured = np.asarray(affine, np.float64) if affine is not None else relative.matrix()
    return nearest_similarity(corrected_affine(measured, d_i, d_j))


def _non_similarity(affines: np.ndarray) -> np.ndarray:
    """Return (N, 2) the part of each 2x3 affine's linear part no similarity explains, relative to its scale."""
    m = affines[:, :, :2]
    scale = np.sqrt(np.abs(np.linalg.det(m)))
    return np.stack([(m[:, 0, 0] - m[:, 1, 1]) / 2.0, (m[:, 0, 1] + m[:, 1, 0]) / 2.0], axis=1) / scale[:, None]


def fit_kappa(
    evidence: Sequence[AffineEvidence],
    forces_n: Mapping[int, np.ndarray],
    separation_mm: Sequence[float],
    kappa_prior_n_per_mm: float,
) -> KappaFit | None:
    """Return the MAP effective kappa (N/mm) that makes every match's corrected affine a similarity, or None.

    Each edge's non-similarity residual counts with its sigma (evidence, with AFFINE_FLOOR added) under a
    Cauchy loss; log kappa has a Gaussian prior of PRIOR_LOG_SIGMA about the calibration's kappa. The 1-D
    search is over log kappa in KAPPA_BOUNDS_N_PER_MM; its sigma from the curvature of the objective.
    None with fewer than MIN_AFFINE_EDGES edges.
    """
    usable = [e for e in evidence if e.i in forces_n and e.j in forces_n]
    if len(usable) < MIN_AFFINE_EDGES:
        return None
    affines = np.stack([e.affine for e in usable])
    f_i = np.stack([forces_n[e.i] for e in usable])
    f_j = np.stack([forces_n[e.j] for e in usable])
    sigma = np.sqrt(np.array([e.sigma for e in usable]) ** 2 + AFFINE_FLOOR**2)
    prior = math.log(kappa_prior_n_per_mm)

    def residuals(log_kappa: float) -> np.ndarray:
        k = math.exp(log_kappa)
        c = corrected_affine(affines, foreshortening(f_i, k, separation_mm), foreshortening(f_j, k, separation_mm))
        return np.linalg.norm(_non_similarity(c), axis=1) / sigma

    def objective(log_kappa: float) -> float:
        r = residuals(log_kappa)
        data = float(np.sum(np.log1p((r / CAUCHY_SCALE) ** 2))) * CAUCHY_SCALE**2 / 2.0
        return data + 0.5 * ((log_kappa - prior) / PRIOR_LOG_SIGMA) ** 2

    lo, hi = (math.log(b) for b in KAPPA_BOUNDS_N_PER_MM)
    grid = np.linspace(lo, hi, 41)  # the objective can have a shoulder: a coarse scan, then a bounded search
    best = int(np.argmin([objective(g) for g in grid]))
    step = grid[1] - grid[0]
    found = minimize_scalar(
        objective, bounds=(grid[max(best - 1, 0)], grid[min(best + 1, len(grid) - 1)]), method="bounded"
    )
    log_k = float(found.x)
    h = 0.01
    curvature = (objective(log_k + h) - 2.0 * objective(log_k) + objective(log_k - h)) / h**2
    log_sigma = 1.0 / math.sqrt(curvature) if curvature > 0 else step
    r_fit = residuals(log_k) * sigma
    r_nominal = residuals(prior) * sigma
    return KappaFit(
        kappa_n_per_mm=math.exp(log_k),
        log_sigma=float(log_sigma),
        n_edges=len(usable),
        residual_rms=float(np.sqrt(np.mean(r_fit**2))),
        residual_rms_nominal=float(np.sqrt(np.mean(r_nominal**2))),
    )
