"""The banded Cholesky factor of a narrow free-dof system, as the exact
preconditioner of its conjugate gradients.

The compact free-dof matrix A of consistent mass (ELL rows of
:func:`skfem_mpm.kernels.mpm.compact_system`, the free dofs numbered in
grid order, axis 0 fastest) is banded: row r couples only to rows
r - w .. r + w, w = max_r (r - min_s cols[r, s]) (about p (n_x + 1) in 2D,
n_x the free dofs' box width). Its Cholesky factor L stays in that band
(Golub & Van Loan, *Matrix Computations*, 4th ed., Thm. 4.3.1), costs
about n w^2 / 2 multiply-adds, and each application of (L L^T)^-1 two
banded triangular solves of n w each. The factor is held twice, by
columns of L (the forward solve L y = b) and by rows (the backward solve
L^T x = y): each solve then updates a contiguous run of the unknowns per
row (an axpy; its only serial dependence is the one unknown the next row
needs), where the backward solve by columns would be a chain of dot
products, each waiting for the last. With P = L L^T = A conjugate
gradients stop after one iteration (its residual is round-off); the
particles move little in a step, so the factor of an earlier step's A
still makes CG stop after two, and the consistent-mass systems keep a
factor over the steps (StencilSystem.BAND_KEEP) instead of making one a
step.

Where the Kronecker preconditioner (:mod:`skfem_mpm.kernels.kronecker`)
is already close to A (particles on a tensor layout, few lumped rows) it
is cheaper than the factor; where lumped rows break its tensor structure
and CG needs many iterations, the factor is cheaper on narrow boxes. The
consistent-mass systems switch to it from the iteration counts (see
:class:`skfem_mpm.solve.stencil_system.StencilSystem`), a deterministic
rule.
"""
import numpy as np
from numba import njit
from numba.extending import register_jitable

from .weights import FAST, IN_ORDER

__all__ = ["ell_band_width", "factor_columns", "factor_band", "factor_layout_ok",
           "fit_band_factor", "apply_band_factor"]


@register_jitable
def factor_columns(w):
    """Columns of the factor array of band w: 2 w + 1 (see fit_band_factor)."""
    return 2 * w + 1


@register_jitable
def factor_band(columns):
    """The band w of a factor array with ``columns`` columns."""
    return (columns - 1) // 2


def factor_layout_ok(C):
    """Whether the array C (kept warm data, possibly from a checkpoint)
    has the layout of fit_band_factor: an odd width and the rows' part
    mirroring the columns' (C[1, 2w] = L_10 = C[0, 1]); an array of the
    earlier layout (columns only, w + 1 wide) is refused, so that the
    system factorises anew."""
    n, width = C.shape
    if width % 2 == 0:
        return False
    w = factor_band(width)
    return n < 2 or w < 1 or C[1, 2 * w] == C[0, 1]


@njit(cache=True, error_model="numpy", fastmath=FAST)
def ell_band_width(cols):
    """w = max_r (r - cols[r, s]) of the ELL columns ``cols`` (unused slots
    point at their own row)."""
    w = 0
    for r in range(cols.shape[0]):
        for s in range(cols.shape[1]):
            w = max(w, r - cols[r, s])
    return w


@njit(cache=True, error_model="numpy", fastmath=FAST)
def fit_band_factor(A, cols, C):
    """C (n, factor_columns(w)): the Cholesky factor L of the ELL matrix A
    (n rows, columns ``cols``, symmetric positive definite, band w) by
    columns, C[k, d] = L_(k + d, k) for 1 <= d <= w and C[k, 0] = 1 / L_kk,
    and by rows, C[k, w + 1 + e] = L_(k, k - w + e) for 0 <= e < w (0 where
    k - w + e < 0). Column k scales by the pivot and updates the columns
    after it (right-looking, Golub & Van Loan, Alg. 4.3.5 by columns; the
    inner loops run along contiguous columns). Returns False when a pivot
    is not positive (A not positive definite to round-off)."""
    n = A.shape[0]
    w = factor_band(C.shape[1])
    C[:, :] = 0.0
    for r in range(n):  # the lower band of A by columns (unused slots add 0)
        for s in range(A.shape[1]):
            c = cols[r, s]
            if c <= r:
                C[c, r - c] += A[r, s]
    for k in range(n):
        pivot = C[k, 0]
        if not pivot > 0.0:
            return False
        inv = 1.0 / np.sqrt(pivot)
        m = min(w, n - 1 - k)
        col = C[k]
        for d in range(1, m + 1):
            col[d] *= inv
        col[0] = inv
        for d1 in range(1, m + 1):
            l1 = col[d1]
            later = C[k + d1]
            for d2 in range(d1, m + 1):
                later[d2 - d1] -= l1 * col[d2]
    for k in range(n):  # the rows of L
        for d in range(1, min(w, n - 1 - k) + 1):
            C[k + d, 2 * w + 1 - d] = C[k, d]
    return True


# without reassociation: two rows' updates of one unknown stay in the order
# of one row at a time (the same bits)
@njit(cache=True, error_model="numpy", fastmath=IN_ORDER)
def _band_solve(C, y):
    """y = (L L^T)^-1 y in place, one contiguous column: L y' = y forward by
    columns of L (y'_k, then y_(k+1..k+w) -= L_(k+1..k+w, k) y'_k), then
    L^T y = y' backward by rows of L (y_k, then y_(k-w..k-1) -= L_(k,
    k-w..k-1) y_k). Two columns (rows) at a time: y'_k, its update of
    y_(k+1), y'_(k+1), then one pass y_j = (y_j - L_jk y'_k) - L_(j,k+1)
    y'_(k+1) over the unknowns both update (each unknown's operations in
    the order of one column at a time; half the passes over y, whose each
    waits for the last)."""
    n = y.shape[0]
    w = factor_band(C.shape[1])
    if w == 0:
        for k in range(n):
            y[k] = y[k] * C[k, 0]
        for k in range(n - 1, -1, -1):
            y[k] = y[k] * C[k, 0]
        return
    for k in range(0, n, 2):  # forward, columns k and k + 1
        v0 = y[k] * C[k, 0]
        y[k] = v0
        if k + 1 == n:
            break
        m0 = min(w, n - 1 - k)  # column k: L_(k+1..k+m0, k) = C[k, 1..m0]
        y[k + 1] -= C[k, 1] * v0
        v1 = y[k + 1] * C[k + 1, 0]
        y[k + 1] = v1
        m1 = min(w, n - 2 - k)  # column k + 1: L_(k+2..k+1+m1, k+1) = C[k+1, 1..m1]
        first = C[k, 2:m0 + 1]
        second = C[k + 1, 1:m0]
        both = y[k + 2:k + m0 + 1]
        for d in range(m0 - 1):
            both[d] = (both[d] - first[d] * v0) - second[d] * v1
        if m1 + 1 > m0:  # y_(k+1+w), below column k's band
            y[k + 1 + m1] -= C[k + 1, m1] * v1
    for k in range(n - 1, -1, -2):  # backward, rows k and k - 1: L_kj = C[k, 2w + 1 - k + j]
        v0 = y[k] * C[k, 0]
        y[k] = v0
        if k == 0:
            break
        y[k - 1] -= C[k, 2 * w] * v0
        v1 = y[k - 1] * C[k - 1, 0]
        y[k - 1] = v1
        lo = max(0, k - w)
        first = C[k, 2 * w + 1 - k + lo:2 * w]
        second = C[k - 1, 2 * w + 2 - k + lo:2 * w + 1]
        both = y[lo:k - 1]
        for e in range(k - 1 - lo):
            both[e] = (both[e] - first[e] * v0) - second[e] * v1
        if k - 1 - w >= 0:  # y_(k-1-w), left of row k's band
            y[k - 1 - w] -= C[k - 1, w + 1] * v1


@njit(cache=True, error_model="numpy", fastmath=FAST)
def apply_band_factor(C, r, z):
    """z = (L L^T)^-1 r, column by column of r, L by columns from
    :func:`fit_band_factor` (each column copied into a contiguous one, so
    that the inner loops run at unit stride; one column: z itself, C-ordered)."""
    n, nc = r.shape
    if nc == 1:  # in z's own column (z C-ordered: contiguous)
        y = z.reshape(n)
        for i in range(n):
            y[i] = r[i, 0]
        _band_solve(C, y)
        return
    y = np.empty(n)
    for c in range(nc):
        for i in range(n):
            y[i] = r[i, c]
        _band_solve(C, y)
        for i in range(n):
            z[i, c] = y[i]
