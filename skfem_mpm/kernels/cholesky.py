"""The Cholesky factorisation of the small moment matrices of the compiled
reconstructions (:mod:`skfem_mpm.kernels.tls`, :mod:`skfem_mpm.kernels.mls`).

    L L^T = M[:n, :n] - shift I,
    L_jj = sqrt(M_jj - shift - sum_(q<j) L_jq^2),
    L_ij = (M_ij - sum_(q<j) L_iq L_jq) / L_jj        (i > j)

(Golub & Van Loan, "Matrix Computations", 4th ed., Alg. 4.2.1). It exists
exactly when M - shift I is positive definite, so with a shift it tests
whether the smallest eigenvalue of M exceeds the shift (both
reconstructions' well-posedness test), and without one it factorises M
for the solve.
"""
import numpy as np
from numba import njit

__all__ = ["cholesky"]


@njit(cache=True, error_model="numpy")
def cholesky(M, n, shift, L):
    """L (lower triangle written) with L L^T = M[:n, :n] - shift I; False
    at the first pivot <= 0 (not positive definite). ``L`` may be ``M``
    itself (in place: each entry is read before it is overwritten)."""
    for j in range(n):
        pivot = M[j, j] - shift
        for q in range(j):
            pivot -= L[j, q] * L[j, q]
        if not pivot > 0.0:
            return False
        root = np.sqrt(pivot)
        L[j, j] = root
        for i in range(j + 1, n):
            s = M[i, j]
            for q in range(j):
                s -= L[i, q] * L[j, q]
            L[i, j] = s / root
    return True
