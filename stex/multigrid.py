"""CG-accelerated V-cycles of a pyamg hierarchy for several right-hand sides at once, with
pyamg's arithmetic.

``pyamg.MultilevelSolver.solve(b, x0=0, tol, accel="cg", maxiter)`` with the Ruge-Stüben
defaults (symmetric Gauss-Seidel pre- and post-smoothing, a V-cycle, the ``pinv`` coarse solver)
solves one right-hand side at a time, and its preconditioner computes two residual norms per
application that CG never reads (two products with the finest matrix each). :func:`cg_solve`
runs the same CG (pyamg.krylov.cg, criterion ``rr``) on the columns of a (k, n) block
together: every sparse product and smoothing sweep reads the matrix once for all k vectors,
and no unused residual is formed. Each column keeps its own CG scalars and stops at its own
iteration, and every floating-point operation is the one pyamg and scipy do, in the same order
(the CSR products and sweeps as scipy's ``csr_matvec`` and pyamg's ``gauss_seidel`` kernels sum,
the inner products and norms by the same numpy calls), so each column is the solution pyamg
returns, bit for bit (tests/test_multigrid.py). Used by :mod:`stex.correction` (the three
colour channels of a slice).
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["WIDTH", "cg_solve", "supported"]


#: columns of the blocks the kernels work on (a colour slice's channels); fewer right-hand sides
#: are padded with zero columns, which cost as much and change no other column
WIDTH = 3


@njit(cache=True, nogil=True)
def _spmv(indptr, indices, data, X, Y):
    """Y[:, c] = A X[:, c] for the three columns of X ((n, 3) float64), each sum in scipy's
    ``csr_matvec`` order (from 0, row order)."""
    for i in range(indptr.shape[0] - 1):
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        for jj in range(indptr[i], indptr[i + 1]):
            a = data[jj]
            j = indices[jj]
            s0 += a * X[j, 0]
            s1 += a * X[j, 1]
            s2 += a * X[j, 2]
        Y[i, 0] = s0
        Y[i, 1] = s1
        Y[i, 2] = s2


@njit(cache=True, nogil=True)
def _gauss_seidel(indptr, indices, data, X, B, start, stop, step):
    """One Gauss-Seidel sweep over rows start, start + step, ... (not stop) of A X = B for the
    three columns of X ((n, 3)) in place, as pyamg's amg_core ``gauss_seidel`` (off-diagonal
    sum from 0 in row order, rows with a zero diagonal left)."""
    i = start
    while i != stop:
        diag = 0.0
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        for jj in range(indptr[i], indptr[i + 1]):
            j = indices[jj]
            if j == i:
                diag = data[jj]
            else:
                a = data[jj]
                s0 += a * X[j, 0]
                s1 += a * X[j, 1]
                s2 += a * X[j, 2]
        if diag != 0.0:
            X[i, 0] = (B[i, 0] - s0) / diag
            X[i, 1] = (B[i, 1] - s1) / diag
            X[i, 2] = (B[i, 2] - s2) / diag
        i += step


def _product(M, X):
    """M X of a CSR matrix and an (n, 3) block."""
    out = np.empty((M.shape[0], WIDTH))
    _spmv(M.indptr, M.indices, M.data, X, out)
    return out


def _columns(rows):
    """The (n, 3) block whose first columns are the rows of ``rows`` ((k, n), k <= 3)."""
    out = np.zeros((rows.shape[1], WIDTH))
    out[:, :len(rows)] = rows.T
    return out


def _rows_product(M, X):
    """M X[c] for every row c of a (k, n) block, as a (k, m) block (C order)."""
    return np.ascontiguousarray(_product(M, _columns(X))[:, :len(X)].T)


def _smooth(A, X, B):
    """pyamg's gauss_seidel(A, x, b, iterations=1, sweep='symmetric') on every column of X."""
    n = A.shape[0]
    _gauss_seidel(A.indptr, A.indices, A.data, X, B, 0, n, 1)
    _gauss_seidel(A.indptr, A.indices, A.data, X, B, n - 1, -1, -1)


def _vcycle(ml, lvl, X, B):
    """MultilevelSolver.__solve(lvl, x, b, 'V') on every column of X ((n, k), in place)."""
    level = ml.levels[lvl]
    A = level.A
    _smooth(A, X, B)
    residual = B - _product(A, X)
    coarse_b = _product(level.R, residual)
    coarse_x = np.zeros_like(coarse_b)
    if lvl == len(ml.levels) - 2:
        for c in range(coarse_b.shape[1]):
            coarse_x[:, c] = ml.coarse_solver(ml.levels[-1].A, np.ascontiguousarray(coarse_b[:, c]))
    else:
        _vcycle(ml, lvl + 1, coarse_x, coarse_b)
    X += _product(level.P, coarse_x)
    _smooth(A, X, B)


def _precondition(ml, R):
    """The preconditioner pyamg's aspreconditioner(cycle='V') applies, one V-cycle from zero, to
    every row of R ((k, n)); (k, n) C order."""
    if len(ml.levels) == 1:
        return np.stack([ml.coarse_solver(ml.levels[0].A, r) for r in R])
    Bt = _columns(R)
    Z = np.zeros_like(Bt)
    _vcycle(ml, 0, Z, Bt)
    return np.ascontiguousarray(Z[:, :len(R)].T)


def supported(ml) -> bool:
    """Whether :func:`cg_solve` reproduces ``ml.solve``: CSR levels, V-cycle smoothing by one
    symmetric Gauss-Seidel sweep (pyamg's default for Ruge-Stüben), the ``pinv`` coarse solver."""
    for level in ml.levels[:-1]:
        for s in (level.presmoother, level.postsmoother):
            kw = getattr(s, "keywords", None)
            if getattr(getattr(s, "func", None), "__name__", "") != "gauss_seidel" or kw != {
                    "iterations": 1, "sweep": "symmetric"}:
                return False
        if any(getattr(M, "format", None) != "csr" for M in (level.A, level.P, level.R)):
            return False
    if getattr(ml.levels[-1].A, "format", None) != "csr":
        return False
    return "pinv" in repr(ml.coarse_solver)


def cg_solve(ml, B, tol: float, maxiter: int):
    """Solve A x = b for every row b of B ((k, n) float64, k <= 3) by CG preconditioned with one V-cycle
    of ``ml`` (a pyamg MultilevelSolver for A with :func:`supported` settings), from x = 0, to a
    relative residual ``tol`` or ``maxiter`` iterations per row.

    Returns (X (k, n) float64, iterations (k,) int): row c equals
    ``ml.solve(B[c], x0=np.zeros(n), tol=tol, accel="cg", maxiter=maxiter)`` and its iteration
    count is the length of that call's residual list minus one.
    """
    # pyamg's own norm, as its cg uses it (an inner product, not numpy's norm)
    from pyamg.util.linalg import norm  # pyamg is slow to import; only the solve needs it

    A = ml.levels[0].A
    B = np.ascontiguousarray(B, np.float64)
    k, n = B.shape
    if k > WIDTH:
        raise ValueError(f"cg_solve takes at most {WIDTH} right-hand sides, got {k}")
    X = np.zeros((k, n))
    R = B - _rows_product(A, X)
    Z = _precondition(ml, R)
    P = Z.copy()
    rz = np.array([np.inner(R[c].conjugate(), Z[c]) for c in range(k)])
    normr = np.array([np.linalg.norm(R[c]) for c in range(k)])
    rtol = np.array([tol * (norm(B[c]) or 1.0) for c in range(k)])
    iters = np.zeros(k, np.int64)
    active = [c for c in range(k) if not normr[c] < rtol[c]]
    it = 0
    while active:
        rows = np.array(active)
        AP = _rows_product(A, P[rows])
        recompute = not (np.mod(it, 8) and it > 0)
        for a, c in enumerate(active):
            pAp = np.inner(AP[a].conjugate(), P[c])
            if pAp < 0.0:
                raise ValueError("multigrid CG: indefinite matrix")
            X[c] += (rz[c] / pAp) * P[c]
            if not recompute:
                R[c] -= (rz[c] / pAp) * AP[a]
        if recompute:
            R[rows] = B[rows] - _rows_product(A, X[rows])
        Zs = _precondition(ml, R[rows])
        it += 1
        still = []
        for a, c in enumerate(active):
            rz_old = rz[c]
            rz[c] = np.inner(R[c].conjugate(), Zs[a])
            if rz[c] < 0.0:
                raise ValueError("multigrid CG: indefinite preconditioner")
            P[c] *= rz[c] / rz_old
            P[c] += Zs[a]
            iters[c] = it
            if not np.linalg.norm(R[c]) < rtol[c] and it < maxiter:
                still.append(c)
        active = still
    return X, iters
