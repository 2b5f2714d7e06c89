"""Sparse normal equations (services.core.normal_equations): the symmetric-mode factor solves as spsolve does, and a
singular system falls back to it; a run of reweighted systems reuses one factor."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse import csc_matrix, csr_matrix, diags, identity
from scipy.sparse import random as sparse_random
from scipy.sparse.linalg import MatrixRankWarning, spsolve

from services.core.normal_equations import NormalSolver, solve_normal
from tests.tolerances import TOL


def test_normal_equations_are_solved_as_spsolve_solves_them() -> None:
    """A pose graph's kind of system (A^T A plus the ridge, A sparse with 4 unknowns a frame): the symmetric-mode
    factor gives spsolve's solution (TOL.linear_solve_abs), for the same right side."""
    rng = np.random.default_rng(3)
    design = (
        sparse_random(2000, 400, density=0.01, format="csr", random_state=rng) + identity(2000, format="csr")[:, :400]
    )
    normal = (design.T @ design + 1e-9 * identity(400, format="csr")).tocsc()
    rhs = rng.normal(size=400)
    x = solve_normal(normal, rhs)
    np.testing.assert_allclose(x, spsolve(normal, rhs), rtol=0, atol=TOL.linear_solve_abs)
    np.testing.assert_allclose(normal @ x, rhs, rtol=0, atol=TOL.linear_solve_abs)


def test_a_singular_system_falls_back_to_spsolve() -> None:
    """A normal matrix whose symmetric factor is singular (a frame without edges and without the ridge) is handed
    to spsolve, which warns and returns NaN, as the pose graph has always had it, instead of raising."""
    normal = identity(4, format="csc")
    normal[3, 3] = 0.0
    with pytest.warns(MatrixRankWarning):
        x = solve_normal(normal.tocsc(), np.ones(4))
    assert np.isnan(x).all()


def _reweighted(design: csr_matrix, weights: np.ndarray) -> csc_matrix:
    """Return the normal matrix of a design whose rows are weighted (a robust fit's iteration), with the ridge."""
    return (design.T @ diags(weights) @ design + 1e-9 * identity(design.shape[1], format="csr")).tocsc()


def test_a_run_of_reweighted_systems_reuses_the_factor_and_solves_each() -> None:
    """A robust fit's systems (one design, weights that settle): after the first, each is solved on the first's factor
    (conjugate gradients, no new factor) and every solution is the direct one's to TOL.linear_solve_abs; a system
    far from the factored one (weights changed ten-fold) is factored afresh, and solved as well."""
    rng = np.random.default_rng(5)
    design = (
        sparse_random(2000, 400, density=0.01, format="csr", random_state=rng) + identity(2000, format="csr")[:, :400]
    )
    rhs = rng.normal(size=400)
    solver = NormalSolver()
    weights = np.ones(2000)
    for step in range(4):
        weights = weights * (1.0 + 0.02 * rng.normal(size=2000) / (step + 1))  # settling, as IRLS weights do
        normal = _reweighted(design, weights)
        np.testing.assert_allclose(
            solver.solve(normal, rhs), solve_normal(normal, rhs), rtol=0, atol=TOL.linear_solve_abs
        )
    assert (solver.factored, solver.reused) == (1, 3)
    far = _reweighted(design, rng.uniform(0.1, 10.0, size=2000))
    np.testing.assert_allclose(solver.solve(far, rhs), solve_normal(far, rhs), rtol=0, atol=TOL.linear_solve_abs)
    assert solver.factored == 2
