"""Robust similarity pose graph: re-optimises past frame poses from relative constraints (loop closures).

Poses are similarities T_k: p -> a_k p + t_k (complex, frame k's mm -> mosaic mm). An edge (i, j) measures
T_ij = T_i^-1 T_j, so a_j = a_i a_ij and t_j = t_i + a_i t_ij. Both equations are *linear* in the unknowns
(a, t), so each robust iteration (IRLS with Cauchy weights) is one sparse linear least-squares solve
(normal equations, sparse LU).
"""

from __future__ import annotations

from collections.abc import Collection, Mapping
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.sparse import csr_matrix, diags, identity, vstack

from services.core.normal_equations import NormalSolver
from services.core.similarity import Similarity

RIDGE = 1e-9  # relative to unit-sigma rows: far below any real constraint
DROP_WEIGHT = 1e-2  # an edge down-weighted below this is an outlier: it gets no pull at all
PRIOR_A = 0.05  # each pose's a (scale, rotation) is held to its registered value with this sigma (5 %, ~3 deg)
PRIOR_T_MM = 50.0  # ... and its t with this one (mm)
LEVER_MM = 20.0  # an edge's a-row lever (mm) where the edge has none of its own (Edge.lever_mm 0)


@dataclass(frozen=True)
class Edge:
    """A relative constraint T_j = T_i T_ij with its translation standard deviation (mm) and kind.

    affine: the match's full affine (2x3, frame j mm -> frame i mm) when it has one (the edge's measurement);
    view_affine, the affine on its own inliers, and its non-similarity sigma: the evidence
    services.core.physics.tissue_model learns the probe's tilt from.
    """

    i: int
    j: int
    relative: Similarity
    sigma_mm: float
    loop: bool = False
    inliers: int = 0
    affine: np.ndarray | None = field(default=None, compare=False, repr=False)
    affine_sigma: float = field(default=float("inf"), compare=False)
    view_affine: np.ndarray | None = field(default=None, compare=False, repr=False)
    centre: complex = 0j  # frame j's point (mm) the edge is measured about: its inliers' centroid
    lever_mm: float = 0.0  # the inliers' spread about it (mm): the lever of the a-rows; 0 = the graph's default
    # the match's inliers (n, 4: frame j x, y, frame i x, y; mm), the skin drag's evidence (physics.drag)
    pairs: np.ndarray | None = field(default=None, compare=False, repr=False)
    # the pairs near the match's similarity, the inliers among them (the drag's evidence; None: the inliers)
    drag_pairs: np.ndarray | None = field(default=None, compare=False, repr=False)

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
    if not edges:
        return np.zeros(0)
    ai = np.array([poses[e.i].a for e in edges])
    ti = np.array([poses[e.i].t for e in edges])
    aj = np.array([poses[e.j].a for e in edges])
    tj = np.array([poses[e.j].t for e in edges])
    ma = np.array([e.relative.a for e in edges])
    mt = np.array([e.relative.t for e in edges])
    c, lever = edge_centres_and_levers(edges, lever_mm)
    r_a = (aj - ai * ma) * lever
    r_t = (aj - ai * ma) * c + tj - ti - ai * mt
    return np.sqrt(np.abs(r_a) ** 2 + np.abs(r_t) ** 2)


def edge_centres_and_levers(edges: list[Edge], lever_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Return each edge's centre (complex, frame j mm) and lever (mm; lever_mm where the edge has none).

    An edge is measured where its inliers are: its translation row states T_j(c) = T_i T_ij (c) at their centroid
    c, where a least-squares fit knows it best and independently of its rotation and scale, and its a-row is
    weighted by their spread (a fit's a is known to rms / (sqrt(n) spread)); both rows then share sigma_mm.
    Measured at frame j's centre with a fixed lever instead, an edge whose overlap lies off-centre (two frames
    far apart) carried an extrapolated translation and an overweighted rotation.
    """
    c = np.array([e.centre for e in edges], dtype=complex)
    lever = np.array([e.lever_mm if e.lever_mm > 0 else lever_mm for e in edges], dtype=float)
    return c, lever


def edge_yaw_sigma_deg(edges: list[Edge], lever_mm: float = LEVER_MM) -> np.ndarray:
    """Return the SD (deg) each edge's rotation is weighed with in the graph: its a-row's sigma_mm over its lever."""
    _, lever = edge_centres_and_levers(edges, lever_mm)
    return np.degrees(np.array([e.sigma_mm for e in edges], dtype=float) / lever)


def robust_weights(residuals_mm: np.ndarray, edges: list[Edge], scale_mm: float) -> np.ndarray:
    """Return IRLS weights in (0, 1]: Cauchy on residual / (edge sigma + scale_mm), so gross outliers vanish."""
    sig = np.array([e.sigma_mm for e in edges]) + scale_mm
    w = 1.0 / (1.0 + (residuals_mm / sig) ** 2)
    return np.where(w < DROP_WEIGHT, 0.0, w)


def _unit_system(
    initial: dict[int, Similarity], edges: list[Edge], col: dict[int, int], lever_mm: float
) -> tuple[csr_matrix, np.ndarray]:
    """Return (A, b) of optimise_poses' linear system before the per-edge scaling (rows 4k..4k+3 for edge k:
    a re/im at the edge's lever, then t re/im at its centre), with the priors' rows after the edges' (already
    scaled by their sigmas).

    Edge k states (a_j - a_i a_ij) L = 0 and a_j c + t_j - t_i - a_i (a_ij c + t_ij) = 0 in complex form (L, c:
    edge_centres_and_levers), split into real and imaginary rows; a term of a held node (not in col) moves to
    the right-hand side with its pose.
    """
    n_free = len(col)
    ne = len(edges)
    base = 4 * np.arange(ne)
    ci = np.array([col.get(e.i, -1) for e in edges], dtype=np.int64)
    cj = np.array([col.get(e.j, -1) for e in edges], dtype=np.int64)
    ma = np.array([e.relative.a for e in edges], dtype=complex)
    centre, lever = edge_centres_and_levers(edges, lever_mm)
    mt = np.array([e.relative.t for e in edges], dtype=complex) + ma * centre  # T_ij(c) - 0: t-row's a_i factor
    held_i = (
        np.array([initial[e.i].a if e.i not in col else 0j for e in edges], dtype=complex),
        np.array([initial[e.i].t if e.i not in col else 0j for e in edges], dtype=complex),
    )
    held_j = (
        np.array([initial[e.j].a if e.j not in col else 0j for e in edges], dtype=complex),
        np.array([initial[e.j].t if e.j not in col else 0j for e in edges], dtype=complex),
    )
    b = np.zeros(4 * ne + 4 * n_free)
    rows: list[np.ndarray] = []
    cols: list[np.ndarray] = []
    vals: list[np.ndarray] = []

    def put(r: np.ndarray, c: np.ndarray, v: np.ndarray | float) -> None:
        rows.append(r)
        cols.append(c)
        vals.append(np.broadcast_to(np.asarray(v, float), r.shape))

    j, jf = cj >= 0, (cj < 0)
    for off in (0, 1):  # +a_j lever
        put(base[j] + off, cj[j] + off, lever[j])
    for off in (2, 3):  # +t_j
        put(base[j] + off, cj[j] + off, 1.0)
    cc = centre[j]  # +a_j c in the t-rows: real row a_re c_re - a_im c_im, imag row a_re c_im + a_im c_re
    put(base[j] + 2, cj[j], cc.real)
    put(base[j] + 2, cj[j] + 1, -cc.imag)
    put(base[j] + 3, cj[j], cc.imag)
    put(base[j] + 3, cj[j] + 1, cc.real)
    fa, ft = held_j[0][jf] * lever[jf], held_j[1][jf] + held_j[0][jf] * centre[jf]
    for off, v in ((0, fa.real), (1, fa.imag), (2, ft.real), (3, ft.imag)):
        b[base[jf] + off] -= v
    i, fi = ci >= 0, (ci < 0)
    la, lt = ma[i] * lever[i], mt[i]  # -a_i M: real row -(a_re m_re - a_im m_im), imag row -(a_re m_im + a_im m_re)
    put(base[i], ci[i], -la.real)
    put(base[i], ci[i] + 1, la.imag)
    put(base[i] + 1, ci[i], -la.imag)
    put(base[i] + 1, ci[i] + 1, -la.real)
    put(base[i] + 2, ci[i], -lt.real)
    put(base[i] + 2, ci[i] + 1, lt.imag)
    put(base[i] + 3, ci[i], -lt.imag)
    put(base[i] + 3, ci[i] + 1, -lt.real)
    put(base[i] + 2, ci[i] + 2, -1.0)  # -t_i
    put(base[i] + 3, ci[i] + 3, -1.0)
    va = held_i[0][fi] * ma[fi] * lever[fi]
    vt = held_i[0][fi] * mt[fi] + held_i[1][fi]
    for off, v in ((0, va.real), (1, va.imag), (2, vt.real), (3, vt.imag)):
        b[base[fi] + off] += v
    prior_sigma = np.array([PRIOR_A, PRIOR_A, PRIOR_T_MM, PRIOR_T_MM])
    nodes = list(col)
    c = np.array([col[n] for n in nodes], dtype=np.int64)[:, None] + np.arange(4)  # (F, 4) columns
    a0 = np.array([initial[n].a for n in nodes], dtype=complex)
    t0 = np.array([initial[n].t for n in nodes], dtype=complex)
    put((4 * ne + c).ravel(), c.ravel(), np.tile(1.0 / prior_sigma, len(nodes)))
    b[(4 * ne + c).ravel()] = (np.stack([a0.real, a0.imag, t0.real, t0.imag], axis=1) / prior_sigma).ravel()
    shape = (4 * ne + 4 * n_free, 4 * n_free)
    A = csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=shape)
    return A, b


def optimise_poses(
    initial: dict[int, Similarity],
    edges: list[Edge],
    fixed: int | Collection[int],
    lever_mm: float = LEVER_MM,
    robust_mm: float = 0.5,
    iterations: int = 10,
    scale_priors: Mapping[int, tuple[float, float]] | None = None,
    mean_scale: tuple[float, float] | None = None,
) -> GraphSolution:
    """Return poses minimising the robust (Cauchy) sum of edge misfits with node(s) `fixed` held at their poses.

    Holding many nodes makes a local refinement: only the others move, the held ones anchor them.

    Residual rows per edge (spec-free, beyond the paper): (a_j - a_i a_ij) * lever_mm and
    t_j - t_i - a_i t_ij, each divided by the edge's sigma_mm; Cauchy scale sigma + robust_mm on the edge norm.
    Plus a weak prior per free node, (a - a_initial) / PRIOR_A and (t - t_initial) / PRIOR_T_MM: far looser than
    any edge, so loop closures still move poses by millimetres, but the problem stays well posed when outlier
    edges are dropped and part of the graph loses its link to the fixed node (without it such a part is free to
    shrink to scale 0, as it did on a simulated hard scan).
    scale_priors: each listed free node's |a| held to (target, sigma); mean_scale: the free nodes' mean |a| held
    to (target, sigma), one row on the mode the edges leave to the held node's few (_with_mean_scale).
    """
    nodes = sorted(initial)
    held = {fixed} if isinstance(fixed, int) else set(fixed)
    free = [n for n in nodes if n not in held]
    col = {n: 4 * k for k, n in enumerate(free)}  # a_re, a_im, t_re, t_im
    usable = [e for e in edges if e.i in initial and e.j in initial]
    poses = dict(initial)
    weights = robust_weights(edge_residuals_mm(poses, usable, lever_mm), usable, robust_mm)
    if not free or not usable:
        return GraphSolution(poses, weights, np.zeros(len(usable)), 0)
    x0 = np.zeros(4 * len(free))
    for n in free:
        p = initial[n]
        x0[col[n] : col[n] + 4] = [p.a.real, p.a.imag, p.t.real, p.t.imag]
    A0, b0 = _unit_system(initial, usable, col, lever_mm)
    if scale_priors:
        A0, b0 = _with_scale_priors(A0, b0, initial, col, scale_priors)
    if mean_scale is not None:
        A0, b0 = _with_mean_scale(A0, b0, initial, col, mean_scale)
    n_edge_rows = 4 * len(usable)
    sigma = np.array([e.sigma_mm for e in usable])
    it = 0
    solver = NormalSolver()  # the reweighted iterations' systems differ only in their weights
    for it in range(1, iterations + 1):
        # each edge's 4 rows scaled by sqrt(weight) / sigma; the prior rows as built
        scale = np.ones(A0.shape[0])
        scale[:n_edge_rows] = np.repeat(np.sqrt(weights) / sigma, 4)
        A = diags(scale) @ A0
        # normal equations (SuperLU's factor, reused while the weights settle); the tiny ridge keeps a node without
        # edges where it is
        normal = (A.T @ A + RIDGE * identity(A.shape[1], format="csr")).tocsc()
        dx = solver.solve(normal, A.T @ (scale * b0 - A @ x0))
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


def _with_scale_priors(
    A: csr_matrix,
    b: np.ndarray,
    initial: dict[int, Similarity],
    col: dict[int, int],
    priors: Mapping[int, tuple[float, float]],
) -> tuple[csr_matrix, np.ndarray]:
    """Return (A, b) with one row per free node with a prior (target |a|, sigma): the component of a along its
    initial direction, (u . a - target) / sigma, so the prior holds the pose's scale and leaves its rotation."""
    nodes = [n for n in priors if n in col and abs(initial[n].a) > 0]
    if not nodes:
        return A, b
    u = np.array([initial[n].a / abs(initial[n].a) for n in nodes], dtype=complex)
    inv = np.array([1.0 / priors[n][1] for n in nodes])
    k = np.arange(len(nodes))
    c = np.array([col[n] for n in nodes], dtype=np.int64)
    extra = csr_matrix(
        (np.concatenate([u.real * inv, u.imag * inv]), (np.concatenate([k, k]), np.concatenate([c, c + 1]))),
        shape=(len(nodes), A.shape[1]),
    )
    return vstack([A, extra]).tocsr(), np.concatenate([b, np.array([priors[n][0] for n in nodes]) * inv])


def _with_mean_scale(
    A: csr_matrix, b: np.ndarray, initial: dict[int, Similarity], col: dict[int, int], prior: tuple[float, float]
) -> tuple[csr_matrix, np.ndarray]:
    """Return (A, b) with one row holding the free nodes' mean scale to prior (target |a|, sigma): the mean of each
    a's component along its initial direction. The residuals t_j - t_i - a_i t_ij shrink with the scale of every
    free node at once, which only the held node's few edges resist: where many edges disagree, solving shrinks the
    whole map toward 0 (Registrar._optimise). The scales relative to each other stay the edges'."""
    nodes = [n for n in col if abs(initial[n].a) > 0]
    if not nodes:
        return A, b
    u = np.array([initial[n].a / abs(initial[n].a) for n in nodes], dtype=complex) / (len(nodes) * prior[1])
    c = np.array([col[n] for n in nodes], dtype=np.int64)
    zeros = np.zeros(2 * len(nodes), dtype=np.int64)
    row = csr_matrix((np.concatenate([u.real, u.imag]), (zeros, np.concatenate([c, c + 1]))), shape=(1, A.shape[1]))
    return vstack([A, row]).tocsr(), np.concatenate([b, [prior[0] / prior[1]]])


def place_node(placed: dict[int, Similarity], edges: list[Edge], node: int, lever_mm: float = LEVER_MM) -> Similarity:
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
