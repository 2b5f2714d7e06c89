"""Friction drag of the skin under a sliding window, learned from the scan (beyond spec §2's radial model).

A probe sliding over skin drags it along: the skin under the window's centre, where it sticks, is displaced most,
and less toward the rim, where it slips. A frame point p (rectified mm about the window's centre, complex) shows the
skin whose rest position is, in the frame's undeformed coordinates,

    p - D_k phi(|p|),    phi(r) = exp(-r^2 / (2 w^2))

with D_k the frame's drag (complex mm, the frame's axes) and w the profile's width, one per scan. The skin under the
centre rests at -D_k: the path is the pose of that point (the rest position the mosaic and a tracker are about).

Evidence: every feature match's inlier pairs (p_j in frame j, p_i in frame i, the same skin point). With the drag
undone they are related by an affine (the similarity of the poses, times the views' stretches), so

    r = P (p_i - D_i phi(p_i) + a_ij D_j phi(p_j))

is zero but for noise, P projecting out what an affine of p_j explains (so the tilt and tissue models, affine,
are left alone) and a_ij the match's rotation and scale. What no affine explains is the profile's curvature over
the overlap, seen at two places of the window: r is linear in the drags, so every frame's drag is one sparse
least-squares solve, with a prior that grows along the motion with the load (D_k ~ g F_k u_k, g fitted, u_k
the direction of travel in the frame's axes), tighter across the travel than along it (a window's friction drags the
skin along its stroke: what turns a drag across it is more often the pairs' noise; solved in real form). The width
is chosen by the evidence (the smallest weighted residual on a grid); the drag is kept only where it explains the
residuals beyond its parameters (an AIC test).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy.sparse import bmat, coo_matrix, csc_matrix

from services.core.normal_equations import solve_normal
from services.core.similarity import Similarity, fit_affine, lsq_similarity

WIDTHS_MM = (8.0, 11.0, 15.0, 20.0, 27.0)  # the profile widths tried (the shared scans' window: ~78 x 58 mm)
PRIOR_SIGMA_MM = 0.6  # a frame's drag about the prior g F u (1 sigma): stick-slip swings it by about this
GAIN_SIGMA_MM_PER_N = 0.5  # the gain g's own weak prior about 0 (mm per N)
MIN_EDGES = 20  # fewer feature edges: no drag fitted
MIN_PAIRS = 8  # an edge with fewer inlier pairs carries no curvature worth fitting
NOISE_FLOOR_MM = 0.02  # an edge's point noise is at least this (a perfect-looking fit is no infinite weight)
REGATE_ROUNDS = 3  # a gate about a least-squares similarity, refitted on what it keeps this many times
RESELECT_ROUNDS = 1  # fit_drag's evidence re-selected about the undragged skin this many times (2 overshot the drag)
AIC_FACTOR = 2.0  # the drag is kept when it lowers the weighted residual by more than this per effective parameter
# a window's friction drags the skin along its stroke: a drag turned further than this from the direction of travel
# is some other deformation's doing (the shared clinical scan's gain: -3 deg; a simulated hard scan without drag
# kept one at -100 deg, which took its path from 1.34 to 2.55 mm)
MAX_ALONG_TRAVEL_DEG = 45.0


def along_travel(drag: complex, direction: complex) -> bool:
    """Return whether a drag (complex, any units) lies within MAX_ALONG_TRAVEL_DEG of a direction of travel
    (complex, the same axes); False when either is zero."""
    if drag == 0 or direction == 0:
        return False
    return bool(abs(np.degrees(np.angle(drag * np.conj(direction)))) <= MAX_ALONG_TRAVEL_DEG)


@dataclass(frozen=True)
class DragEvidence:
    """One feature match: frames i (placed) and j, inlier pairs (n, 4: p_j x, y then p_i x, y; mm) and the match's
    rotation and scale a_ij (frame j mm -> frame i mm)."""

    i: int
    j: int
    pairs: np.ndarray
    a: complex


@dataclass(frozen=True)
class DragFit:
    """The scan's drag: the profile width (mm), every frame's drag (complex mm, the frame's axes), the gain of the
    prior (complex mm per N along the motion), the weighted residuals (chi-square units) without and with the
    drag, the edges and pairs used, and whether the evidence keeps it (kept False: every drag is 0)."""

    width_mm: float
    drag_mm: Mapping[int, complex]
    gain_mm_per_n: complex
    cost_without: float
    cost_with: float
    n_edges: int
    n_pairs: int
    kept: bool

    def of(self, frame: int) -> complex:
        """Return a frame's drag (complex mm, its axes): 0 where none was fitted or the drag is not kept."""
        return self.drag_mm.get(frame, 0j) if self.kept else 0j

    def filled(self, frames: Sequence[int], reach: int) -> DragFit:
        """Return the fit with a drag for every frame in `frames` that has none of its own: its neighbours' in the
        sequence, interpolated linearly (complex mm, the frame's axes), or the nearer one's when the other is more
        than `reach` frames away (frames placed without feature evidence: a tracked frame between keyframes)."""
        known = np.array(sorted(self.drag_mm), np.int64)
        if not len(known):
            return self
        values = np.array([self.drag_mm[int(f)] for f in known], complex)
        drags = dict(self.drag_mm)
        for f in frames:
            if f in drags:
                continue
            k = int(np.searchsorted(known, f))
            before = k - 1 if k > 0 and f - known[k - 1] <= reach else None
            after = k if k < len(known) and known[k] - f <= reach else None
            if before is not None and after is not None:
                w = (f - known[before]) / (known[after] - known[before])
                drags[f] = complex((1 - w) * values[before] + w * values[after])
            elif before is not None or after is not None:
                drags[f] = complex(values[before if before is not None else after])
        return replace(self, drag_mm=drags)

    def to_dict(self) -> dict[str, float | int | bool]:
        """Return the fitted profile for the report's "tissue" (mm, mm/N, deg from the motion, chi-square units)."""
        drags = np.abs(np.array(list(self.drag_mm.values()) or [0j]))
        return {
            "drag_kept": self.kept,
            "drag_width_mm": self.width_mm,
            "drag_gain_mm_per_n": abs(self.gain_mm_per_n),
            "drag_angle_deg": math.degrees(float(np.angle(self.gain_mm_per_n))),
            "drag_median_mm": float(np.median(drags)) if self.kept else 0.0,
            "drag_max_mm": float(drags.max()) if self.kept else 0.0,
            "drag_residual_without": self.cost_without,
            "drag_residual_with": self.cost_with,
            "drag_edges": self.n_edges,
            "drag_pairs": self.n_pairs,
        }


def profile(points: np.ndarray, width_mm: float) -> np.ndarray:
    """Return phi(|p|) (dimensionless, 1 at the centre) of complex points (mm about the window's centre)."""
    return np.exp(-(np.abs(points) ** 2) / (2.0 * width_mm**2))


def undrag(points: np.ndarray, drag_mm: complex, width_mm: float) -> np.ndarray:
    """Return complex frame points (mm) with the drag undone: p - D phi(|p|) (the skin's rest place)."""
    return points - drag_mm * profile(points, width_mm)


def undrag_maps(
    shape: tuple[int, int], centre_px: tuple[float, float], px_per_mm: float, drag_mm: complex, width_mm: float
) -> tuple[np.ndarray, np.ndarray]:
    """Return cv2.remap maps (float32 x, y; pixels) that resample a rectified frame (H, W) with its drag undone:
    the pixel at rest place q takes the frame's pixel at q + D phi(|q|), the first-order inverse of p - D phi(p)
    (its error |D| |D phi'|: under 0.05 mm for a 1 mm drag over the narrowest profile).

    The Gaussian profile is separable, phi(|q|) = phi(x) phi(y): one outer product of a row and a column, in
    float32 (what remap reads; it resolves 1/32 pixel), instead of a complex grid (12x the time).
    """
    h, w = shape
    fx = profile((np.arange(w, dtype=np.float64) - centre_px[0]) / px_per_mm, width_mm).astype(np.float32)
    fy = profile((np.arange(h, dtype=np.float64) - centre_px[1]) / px_per_mm, width_mm).astype(np.float32)
    phi = fy[:, None] * fx[None, :]
    map_x = phi * np.float32(drag_mm.real * px_per_mm)
    map_x += np.arange(w, dtype=np.float32)[None, :]
    map_y = phi * np.float32(drag_mm.imag * px_per_mm)
    map_y += np.arange(h, dtype=np.float32)[:, None]
    return map_x, map_y


def _complex(pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p = np.asarray(pairs, np.float64)
    return p[:, 0] + 1j * p[:, 1], p[:, 2] + 1j * p[:, 3]


@dataclass(frozen=True)
class _Terms:
    """Each edge's inner products after the affine projection (module docstring): |P phi_i|^2, P phi_i . P phi_j,
    |P phi_j|^2 (real), P phi_i . P p_i, P phi_j . P p_i (complex), |P p_i|^2, each times the edge's weight."""

    gii: np.ndarray
    gij: np.ndarray
    gjj: np.ndarray
    hi: np.ndarray
    hj: np.ndarray
    hh: np.ndarray


@dataclass(frozen=True)
class _Batch:
    """The evidence padded to (E, n) pairs: p_j, p_i (complex mm), which are real (not padding), each edge's
    orthonormal basis (E, n, 3) of what an affine of p_j explains, P p_i (complex), and each edge's weight (1/mm^2)."""

    pj: np.ndarray
    pi: np.ndarray
    real: np.ndarray
    basis: np.ndarray
    h: np.ndarray
    weight: np.ndarray

    def project(self, v: np.ndarray) -> np.ndarray:
        """Return P v of real (E, n) vectors (0 at padding): v less its least-squares fit by an affine of p_j."""
        v = np.where(self.real, v, 0.0)
        return v - np.einsum("enk,ek->en", self.basis, np.einsum("enk,en->ek", self.basis, v))


def _batch(evidence: Sequence[DragEvidence]) -> _Batch:
    """Return the evidence as one padded _Batch (one batched QR), with its weights: one point noise for the scan
    (the median edge's affine RMS residual), Cauchy-down-weighted where an edge's own residual is far above it (a
    match that neither an affine nor a drag explains)."""
    n = max(len(ev.pairs) for ev in evidence)
    raw = np.zeros((len(evidence), n, 4))
    real = np.zeros((len(evidence), n), bool)
    for k, ev in enumerate(evidence):
        raw[k, : len(ev.pairs)] = ev.pairs
        real[k, : len(ev.pairs)] = True
    pj, pi = raw[..., 0] + 1j * raw[..., 1], raw[..., 2] + 1j * raw[..., 3]
    design = np.stack([pj.real, pj.imag, np.ones(pj.shape)], axis=-1) * real[..., None]  # padding fits nothing
    basis, _ = np.linalg.qr(design)
    batch = _Batch(pj, pi, real, basis, np.zeros(pj.shape, complex), np.zeros(len(evidence)))
    h = batch.project(pi.real) + 1j * batch.project(pi.imag)
    rms = np.sqrt(np.sum(np.abs(h) ** 2, axis=1) / np.maximum(real.sum(axis=1) - 3, 1))
    noise = max(float(np.median(rms)), NOISE_FLOOR_MM)
    weight = 1.0 / (noise**2 * (1.0 + (rms / (3.0 * noise)) ** 2))
    return _Batch(pj, pi, real, basis, h, weight)


def _terms(batch: _Batch, width_mm: float) -> _Terms:
    w, h = batch.weight, batch.h
    gi = batch.project(profile(batch.pi, width_mm))
    gj = batch.project(profile(batch.pj, width_mm))
    return _Terms(
        w * np.sum(gi * gi, axis=1),
        w * np.sum(gi * gj, axis=1),
        w * np.sum(gj * gj, axis=1),
        w * np.sum(gi * h, axis=1),
        w * np.sum(gj * h, axis=1),
        w * np.sum(np.abs(h) ** 2, axis=1),
    )


def _solve(
    evidence: Sequence[DragEvidence],
    terms: _Terms,
    frames: Sequence[int],
    prior_mean: np.ndarray,
    across_sigma_mm: float = PRIOR_SIGMA_MM,
) -> tuple[np.ndarray, complex, float]:
    """Return (each frame's drag, the gain g, the weighted cost) minimising the evidence's residuals plus the
    prior |D_k - g m_k|^2 / PRIOR_SIGMA^2 (m_k = F_k u_k), tightened to across_sigma_mm across the travel
    (_across_prior), and |g|^2 / GAIN_SIGMA^2: one sparse solve."""
    n = len(frames)
    col = {f: k for k, f in enumerate(frames)}
    ii = np.array([col[ev.i] for ev in evidence])
    jj = np.array([col[ev.j] for ev in evidence])
    a = np.array([ev.a for ev in evidence], complex)
    # the edge's quadratic form in (D_i, D_j): [[gii, -a gij], [-conj(a) gij, |a|^2 gjj]], right side [hi, -conj(a) hj]
    rows = [ii, ii, jj, jj]
    cols = [ii, jj, ii, jj]
    vals = [terms.gii + 0j, -a * terms.gij, -np.conj(a) * terms.gij, np.abs(a) ** 2 * terms.gjj]
    rhs = np.zeros(n + 1, complex)
    np.add.at(rhs, ii, terms.hi)
    np.add.at(rhs, jj, -np.conj(a) * terms.hj)
    # the prior: (D_k - g m_k) / s, unknown g at column n
    p = 1.0 / PRIOR_SIGMA_MM**2
    k = np.arange(n)
    m = np.asarray(prior_mean, complex)
    rows += [k, k, np.full(n, n), np.array([n])]
    cols += [k, np.full(n, n), k, np.array([n])]
    vals += [np.full(n, p + 0j), -p * m, -p * np.conj(m), np.array([p * np.vdot(m, m) + 1.0 / GAIN_SIGMA_MM_PER_N**2])]
    normal = coo_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n + 1, n + 1)
    ).tocsc()
    # in real form (re then im of every unknown), where the across-travel prior, not complex-linear, can be added
    real = bmat([[normal.real, -normal.imag], [normal.imag, normal.real]], format="csc")
    b = np.concatenate([rhs.real, rhs.imag])
    real = (real + _across_prior(m, n, across_sigma_mm)).tocsc()
    x = solve_normal(real, b)  # normal equations: symmetric positive definite
    cost = float(np.sum(terms.hh) - np.dot(x, b))  # at the minimum: h.h - x.b
    z = x[: n + 1] + 1j * x[n + 1 :]
    return z[:n], complex(z[n]), cost


def _across_prior(prior_mean: np.ndarray, n: int, across_sigma_mm: float) -> csc_matrix:
    """Return the real normal matrix (2n + 2 square) that tightens the prior across each moving frame's travel from
    PRIOR_SIGMA_MM to across_sigma_mm: (1/s_across^2 - 1/s^2) c_k^2, with c_k = Im((D_k - g m_k) conj(u_k)) =
    Im(D_k conj(u_k)) - F_k Im(g) (u_k = m_k / F_k): the drag's part across the travel, beyond the gain's turn."""
    moving = np.flatnonzero(np.abs(prior_mean) > 0)
    tighter = 1.0 / across_sigma_mm**2 - 1.0 / PRIOR_SIGMA_MM**2
    if not len(moving) or tighter <= 0:
        return csc_matrix((2 * n + 2, 2 * n + 2))
    load = np.abs(prior_mean[moving])
    u = prior_mean[moving] / load
    columns = np.stack([moving, n + 1 + moving, np.full(len(moving), 2 * n + 1)], axis=1)  # re D_k, im D_k, im g
    coef = np.stack([-u.imag, u.real, -load], axis=1)
    values = tighter * coef[:, :, None] * coef[:, None, :]
    rows = np.repeat(columns, 3, axis=1).ravel()
    cols = np.tile(columns, (1, 3)).ravel()
    return coo_matrix((values.ravel(), (rows, cols)), shape=(2 * n + 2, 2 * n + 2)).tocsc()


def fit_drag(
    evidence: Sequence[DragEvidence],
    loads_n: Mapping[int, float],
    directions: Mapping[int, complex],
    widths_mm: Sequence[float] = WIDTHS_MM,
    reselect_gate_mm: float = 0.0,
    reselect_rounds: int = RESELECT_ROUNDS,
    across_sigma_mm: float = PRIOR_SIGMA_MM,
) -> DragFit | None:
    """Return the scan's drag fitted to the matches' inlier pairs (module docstring), or None on too little
    evidence. loads_n: each frame's load (N); directions: its unit direction of travel in its own axes (0: still).

    reselect_gate_mm > 0: the evidence holds each match's near pairs (a wider gate than its RANSAC's); the pairs
    fitted are those within this gate of their similarity, first as measured, then with the first fit's drags
    undone (reselect_rounds times): a gate about the similarity keeps the pairs the drag moved least, one about the
    undragged skin does not. across_sigma_mm: the prior's sigma across the travel (PRIOR_SIGMA_MM: as along it).
    """
    usable = [ev for ev in evidence if ev.pairs is not None and len(ev.pairs) >= MIN_PAIRS]
    if len(usable) < MIN_EDGES:
        return None
    if reselect_gate_mm <= 0:
        return _fit(usable, loads_n, directions, widths_mm, across_sigma_mm)
    fit = _fit(_reselected(usable, None, reselect_gate_mm), loads_n, directions, widths_mm, across_sigma_mm)
    for _ in range(reselect_rounds):
        if fit is None or not fit.kept:
            break
        fit = _fit(_reselected(usable, fit, reselect_gate_mm), loads_n, directions, widths_mm, across_sigma_mm)
    return fit


def _reselected(evidence: Sequence[DragEvidence], fit: DragFit | None, gate_mm: float) -> list[DragEvidence]:
    """Return the evidence with each match's pairs cut to those within gate_mm of their own similarity once the
    fit's drags are undone (fit None: as measured); a match left with fewer than MIN_PAIRS is dropped."""
    out = []
    for ev in evidence:
        pj, pi = _complex(ev.pairs)
        if fit is not None:
            pj = undrag(pj, fit.drag_mm.get(ev.j, 0j), fit.width_mm)
            pi = undrag(pi, fit.drag_mm.get(ev.i, 0j), fit.width_mm)
        keep = _within_gate(pj, pi, gate_mm)
        if keep is not None:
            out.append(replace(ev, pairs=ev.pairs[keep]))
    return out


def _within_gate(pj: np.ndarray, pi: np.ndarray, gate_mm: float) -> np.ndarray | None:
    """Return the mask of complex pairs (frame j -> frame i, mm) within gate_mm of their least-squares similarity,
    refitted on the pairs kept (REGATE_ROUNDS times), or None when fewer than MIN_PAIRS remain."""
    keep = np.ones(len(pj), bool)
    for _ in range(REGATE_ROUNDS):
        if keep.sum() < MIN_PAIRS:
            return None
        fit = lsq_similarity(pj[keep], pi[keep])
        keep = np.abs(fit.a * pj + fit.t - pi) < gate_mm
    return keep if keep.sum() >= MIN_PAIRS else None


def _fit(
    usable: Sequence[DragEvidence],
    loads_n: Mapping[int, float],
    directions: Mapping[int, complex],
    widths_mm: Sequence[float],
    across_sigma_mm: float = PRIOR_SIGMA_MM,
) -> DragFit | None:
    """Return the drag fitted to the evidence's pairs (fit_drag), or None on fewer than MIN_EDGES matches."""
    if len(usable) < MIN_EDGES:
        return None
    frames = sorted({ev.i for ev in usable} | {ev.j for ev in usable})
    prior_mean = np.array([loads_n.get(f, 0.0) * directions.get(f, 0j) for f in frames], complex)
    best: tuple[float, float, np.ndarray, complex] | None = None
    batch = _batch(usable)
    without = float(np.sum(batch.weight * np.sum(np.abs(batch.h) ** 2, axis=1)))  # no drag: what no affine explains
    for width in widths_mm:
        drags, gain, cost = _solve(usable, _terms(batch, width), frames, prior_mean, across_sigma_mm)
        if best is None or cost < best[0]:
            best = (cost, width, drags, gain)
    assert best is not None
    cost, width, drags, gain = best
    # effective parameters: 2 per frame shrunk by the prior, counted as the frames the evidence pins (a bound); and
    # the gain is the drag's ratio to each frame's direction of travel: it must lie along it
    kept = without - cost > AIC_FACTOR * 2.0 * (len(frames) + 2) and along_travel(complex(gain), 1 + 0j)
    return DragFit(
        width,
        dict(zip(frames, (complex(d) for d in drags), strict=True)),
        gain,
        without,
        cost,
        len(usable),
        int(sum(len(ev.pairs) for ev in usable)),
        kept,
    )


def undragged_transforms(
    relative: Similarity,
    affines: Sequence[np.ndarray | None],
    pairs: np.ndarray,
    drag_i: complex,
    drag_j: complex,
    width_mm: float,
    near_pairs: np.ndarray | None = None,
    gate_mm: float = 0.0,
) -> tuple[Similarity, list[np.ndarray | None]]:
    """Return an edge's relative similarity and affines (frame j mm -> frame i mm, 2x3) between undragged frames.

    Each is the measured one composed (on frame i's side) with what undoing the drags changes in the least-squares
    fit of the edge's pairs (a similarity for the relative, an affine for the affines): so what the measurement
    adds to its raw pairs (a direct alignment's refinement, the inliers the pairs leave out) is kept.
    near_pairs and gate_mm > 0: the fit after undoing is of the near pairs (a wider RANSAC gate) within gate_mm of
    their similarity once undragged, not of the inliers, which the gate about the dragged similarity chose (the
    pairs the drag moved least: undone, they leave the edge turned; issue 31).
    """
    pj, pi = _complex(pairs)
    qj, qi = undrag(pj, drag_j, width_mm), undrag(pi, drag_i, width_mm)
    if near_pairs is not None and gate_mm > 0:
        nj, ni = _complex(near_pairs)
        nj, ni = undrag(nj, drag_j, width_mm), undrag(ni, drag_i, width_mm)
        keep = _within_gate(nj, ni, gate_mm)
        if keep is not None:
            qj, qi = nj[keep], ni[keep]
    moved = lsq_similarity(qj, qi).compose(lsq_similarity(pj, pi).inverse()).compose(relative)
    raw, fixed = fit_affine(_xy(pj), _xy(pi)), fit_affine(_xy(qj), _xy(qi))
    if raw is None or fixed is None:  # degenerate pairs (collinear): the affines as measured
        return moved, list(affines)
    delta = _homogeneous(fixed) @ np.linalg.inv(_homogeneous(raw))
    return moved, [None if a is None else (delta @ _homogeneous(a))[:2] for a in affines]


def _xy(points: np.ndarray) -> np.ndarray:
    return np.column_stack([points.real, points.imag])


def _homogeneous(affine: np.ndarray) -> np.ndarray:
    return np.vstack([np.asarray(affine, np.float64), [0.0, 0.0, 1.0]])
