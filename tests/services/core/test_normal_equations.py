"""Sparse normal equations (services.core.normal_equations): the symmetric-mode factor solves as spsolve does, and a
singular system falls back to it."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse import identity
from scipy.sparse import random as sparse_random
from scipy.sparse.linalg import MatrixRankWarning, spsolve

from services.core.normal_equations import solve_normal
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
