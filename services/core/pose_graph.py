"""Robust similarity pose graph: re-optimises past frame poses from relative constraints (loop closures).

Poses are similarities T_k: p -> a_k p + t_k (complex, frame k's mm -> mosaic mm). An edge (i, j) measures
T_ij = T_i^-1 T_j, so a_j = a_i a_ij and t_j = t_i + a_i t_ij. Both equations are *linear* in the unknowns
(a, t), so each robust iteration (IRLS with Cauchy weights) is one sparse linear least-squares solve
(normal equations, sparse LU).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.sparse import csr_matrix, identity
from scipy.sparse.linalg import spsolve

from services.core.registration import Similarity

RIDGE = 1e-9  # relative to unit-sigma rows: far below any real constraint
DROP_WEIGHT = 1e-2  # an edge down-weighted below this is an outlier: it gets no pull at all
PRIOR_A = 0.05  # each pose's a (scale, rotation) is held to its registered value with this sigma (5 %, ~3 deg)
PRIOR_T_MM = 50.0  # ... and its t with this one (mm)


@dataclass(frozen=True)
class Edge:
    """A relative constraint T_j = T_i T_ij with its translation standard deviation (mm) and kind.

    affine: the match's full affine (2x3, frame j mm -> frame i mm) when it has one, and its non-similarity
    sigma: the evidence services.core.tissue_model learns the probe's tilt from.
    """

    i: int
    j: int
    relative: Similarity
    sigma_mm: float
    loop: bool = False
    inliers: int = 0
    affine: np.ndarray | None = field(default=None, compare=False, repr=False)
    affine_sigma: float = field(default=float("inf"), compare=False)

    def with_relative(self, relative: Similarity) -> Edge:
        """Return the same edge measuring another relative similarity (e.g. between undeformed frames)."""
        return replace(self, relative=relative)


@dataclass(frozen=True)
class GraphSolution:
    """Optimised poses by node id, the robust weights of the edges, and per-edge residual norms (mm)."""

    poses: dict[int, Similarity]
    edge_weights: np.ndarray
    residuals_mm: np.ndarray
    iterations: int


def edge_residuals_mm(poses: dict[int, Similarity], edges: list[Edge], lever_mm: float) -> np.ndarray:
    """Return each edge's residual norm in mm: translation misfit plus rotation/scale misfit at lever_mm."""
    out = np.zeros(len(edges))
    for k, e in enumerate(edges):
        ti, tj = poses[e.i], poses[e.j]
        r_a = (tj.a - ti.a * e.relative.a) * lever_mm
        r_t = tj.t - ti.t - ti.a * e.relative.t
        out[k] = float(np.sqrt(abs(r_a) ** 2 + abs(r_t) ** 2))
    return out


def robust_weights(residuals_mm: np.ndarray, edges: list[Edge], scale_mm: float) -> np.ndarray:
    """Return IRLS weights in (0, 1]: Cauchy on residual / (edge sigma + scale_mm), so gross outliers vanish."""
    sig = np.array([e.sigma_mm for e in edges]) + scale_mm
    w = 1.0 / (1.0 + (residuals_mm / sig) ** 2)
    return np.where(w < DROP_WEIGHT, 0.0, w)


def optimise_poses(
    initial: dict[int, Similarity],
    edges: list[Edge],
    fixed: int,
    lever_mm: float = 20.0,
    robust_mm: float = 0.5,
    iterations: int = 10,
) -> GraphSolution:
    """Return poses minimising the robust (Cauchy) sum of edge misfits with node `fixed` held at its pose.

    Residual rows per edge (spec-free, beyond the paper): (a_j - a_i a_ij) * lever_mm and
    t_j - t_i - a_i t_ij, each divided by the edge's sigma_mm; Cauchy scale sigma + robust_mm on the edge norm.
    Plus a weak prior per free node, (a - a_initial) / PRIOR_A and (t - t_initial) / PRIOR_T_MM: far looser than
    any edge, so loop closures still move poses by millimetres, but the problem stays well posed when outlier
    edges are dropped and part of the graph loses its link to the fixed node (without it such a part is free to
    shrink to scale 0, as it did on a simulated hard scan).
    """
    nodes = sorted(initial)
    free = [n for n in nodes if n != fixed]
    col = {n: 4 * k for k, n in enumerate(free)}  # a_re, a_im, t_re, t_im
    anchor = initial[fixed]
    usable = [e for e in edges if e.i in initial and e.j in initial]
    poses = dict(initial)
    weights = robust_weights(edge_residuals_mm(poses, usable, lever_mm), usable, robust_mm)
    if not free or not usable:
        return GraphSolution(poses, weights, np.zeros(len(usable)), 0)
    x0 = np.zeros(4 * len(free))
    for n in free:
        p = initial[n]
        x0[col[n] : col[n] + 4] = [p.a.real, p.a.imag, p.t.real, p.t.imag]
    it = 0
    for it in range(1, iterations + 1):
        rows, cols, vals, rhs = [], [], [], []
        r = 0

        def put(row: int, node: int, offset: int, value: float, rows=rows, cols=cols, vals=vals) -> None:
            rows.append(row)
            cols.append(col[node] + offset)
            vals.append(value)

        for k, e in enumerate(usable):
            s = np.sqrt(weights[k]) / e.sigma_mm
            m = e.relative
            # complex equation c_j * X_j - M * X_i = 0, split in real/imag; X = a (scaled by lever) or t.
            for eq in ("a", "t"):
                scale = lever_mm if eq == "a" else 1.0
                b = np.zeros(2)
                # term +X_j (a_j or t_j)
                off_j = 0 if eq == "a" else 2
                if e.j == fixed:
                    v = anchor.a if eq == "a" else anchor.t
                    b -= np.array([v.real, v.imag]) * scale * s
                else:
                    put(r, e.j, off_j, scale * s)
                    put(r + 1, e.j, off_j + 1, scale * s)
                # term -a_i * m_a (for a) or -t_i - a_i * m_t (for t)
                mult = m.a if eq == "a" else m.t
                if e.i == fixed:
                    v = anchor.a * mult + (anchor.t if eq == "t" else 0)
                    b += np.array([v.real, v.imag]) * scale * s
                else:
                    # -(a_re + i a_im)(m_re + i m_im) -> real: -(a_re m_re - a_im m_im); imag: -(a_re m_im + a_im m_re)
                    put(r, e.i, 0, -mult.real * scale * s)
                    put(r, e.i, 1, mult.imag * scale * s)
                    put(r + 1, e.i, 0, -mult.imag * scale * s)
                    put(r + 1, e.i, 1, -mult.real * scale * s)
                    if eq == "t":
                        put(r, e.i, 2, -s)
                        put(r + 1, e.i, 3, -s)
                rhs.extend(b.tolist())
                r += 2
        for n in free:
            p = initial[n]
            for offset, (value, sigma) in enumerate(
                ((p.a.real, PRIOR_A), (p.a.imag, PRIOR_A), (p.t.real, PRIOR_T_MM), (p.t.imag, PRIOR_T_MM))
            ):
                put(r, n, offset, 1.0 / sigma)
                rhs.append(value / sigma)
                r += 1
        A = csr_matrix((vals, (rows, cols)), shape=(r, 4 * len(free)))
        # normal equations, solved directly (SuperLU); the tiny ridge keeps a node without edges where it is
        normal = (A.T @ A + RIDGE * identity(A.shape[1], format="csr")).tocsc()
        dx = spsolve(normal, A.T @ (np.asarray(rhs) - A @ x0))
        x0 = x0 + dx
        for n in free:
            v = x0[col[n] : col[n] + 4]
            poses[n] = Similarity(complex(v[0], v[1]), complex(v[2], v[3]))
        new_w = robust_weights(edge_residuals_mm(poses, usable, lever_mm), usable, robust_mm)
        if np.allclose(new_w, weights, atol=1e-3) and it > 1:
            weights = new_w
            break
        weights = new_w
    resid = edge_residuals_mm(poses, usable, lever_mm)
    return GraphSolution(poses, weights, resid, it)


def place_node(placed: dict[int, Similarity], edges: list[Edge], node: int, lever_mm: float = 20.0) -> Similarity:
    """Return the pose of `node` that best fits its edges to already placed nodes (their poses held)."""
    num_a, num_t, den = 0j, 0j, 0.0
    for e in edges:
        w = 1.0 / e.sigma_mm**2
        if e.j == node and e.i in placed:
            pi = placed[e.i]
            est = pi.compose(e.relative)
        elif e.i == node and e.j in placed:
            est = placed[e.j].compose(e.relative.inverse())
        else:
            continue
        num_a += w * est.a
        num_t += w * est.t
        den += w
    if den == 0:
        raise ValueError("node has no edge to a placed node")
    return Similarity(num_a / den, num_t / den)
