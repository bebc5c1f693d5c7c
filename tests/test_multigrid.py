"""stex.multigrid: the block CG over a pyamg hierarchy returns pyamg's solutions, bit for bit."""

import numpy as np
import pyamg
import pytest
import scipy.sparse as sp

from stex.multigrid import cg_solve, supported


def _system(n=60, screen=1e-3):
    A = pyamg.gallery.poisson((n, n), format="csr") + screen * sp.identity(n * n, format="csr")
    return A.tocsr(), pyamg.ruge_stuben_solver(A.tocsr())


@pytest.mark.parametrize("tol", [1e-4, 1e-9])
@pytest.mark.parametrize("k", [1, 2, 3])
def test_block_solve_equals_pyamg_per_column(tol, k):
    A, ml = _system()
    assert supported(ml) and len(ml.levels) > 2
    rng = np.random.default_rng(k)
    B = rng.normal(size=(k, A.shape[0])) * np.array([1.0, 1e-3, 50.0])[:k, None]
    X, iters = cg_solve(ml, B, tol, 50)
    for c in range(k):
        res = []
        want = ml.solve(B[c], x0=np.zeros(A.shape[0]), tol=tol, accel="cg", maxiter=50, residuals=res)
        assert np.array_equal(X[c], want)
        assert iters[c] == len(res) - 1
    # and the solutions solve the system to the tolerance
    for c in range(k):
        assert np.linalg.norm(B[c] - A @ X[c]) <= tol * np.linalg.norm(B[c]) * 1.0001


def test_columns_stop_at_their_own_iteration_and_maxiter():
    A, ml = _system(40)
    rng = np.random.default_rng(0)
    x_true = rng.normal(size=A.shape[0])
    # a zero column stops before the first iteration, the others at the iteration cap
    B = np.stack([A @ x_true, rng.normal(size=A.shape[0]), np.zeros(A.shape[0])])
    X, iters = cg_solve(ml, B, 1e-10, 3)
    assert iters[2] == 0 and not X[2].any()
    for c in range(2):
        res = []
        want = ml.solve(B[c], x0=np.zeros(A.shape[0]), tol=1e-10, accel="cg", maxiter=3, residuals=res)
        assert np.array_equal(X[c], want) and iters[c] == len(res) - 1 <= 3


def test_other_smoothers_are_not_claimed():
    A, _ = _system(30)
    ml = pyamg.ruge_stuben_solver(A, presmoother=("gauss_seidel", {"sweep": "forward"}))
    assert not supported(ml)
    with pytest.raises(ValueError, match="at most 3"):
        cg_solve(_system(30)[1], np.ones((4, A.shape[0])), 1e-4, 5)
