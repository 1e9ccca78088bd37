"""Small checks of the discrepancy loop's numerical helpers (no simulation)."""

import numpy as np

from hdjax._diagnose import _solve_normal


def test_gauss_newton_step_solves_the_normal_equations():
    rng = np.random.default_rng(0)
    J = rng.normal(size=(50, 3))
    r = rng.normal(size=50)
    step = _solve_normal(J.T @ J, J.T @ r)
    np.testing.assert_allclose(step, -np.linalg.lstsq(J, r, rcond=None)[0], rtol=1e-6)


def test_gauss_newton_step_is_zero_on_columns_without_information():
    # every simulation failed: the residual is a constant, its Jacobian zero (a column of zeros
    # must neither crash the solve nor move the others)
    rng = np.random.default_rng(1)
    J = rng.normal(size=(40, 3))
    J[:, 1] = 0.0
    r = rng.normal(size=40)
    step = _solve_normal(J.T @ J, J.T @ r)
    assert step[1] == 0.0
    keep = [0, 2]
    np.testing.assert_allclose(step[keep], -np.linalg.lstsq(J[:, keep], r, rcond=None)[0], rtol=1e-6)
    assert np.all(_solve_normal(np.zeros((3, 3)), np.zeros(3)) == 0.0)
