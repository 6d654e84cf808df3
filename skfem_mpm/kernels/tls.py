"""Conservative Taylor least squares (TLS) per cell, compiled: the twin of
:func:`skfem_mpm.reconstruct.reconstruct_tls` with its default options
(``degree=2, neighbour_weight=0``), which is the oracle.

The method (Wobbes, Moller, Galavi, Vuik 2019, IJNME 117:271-290, Sec. 3):
for each cell e that holds Gauss points of the rule, in the local
coordinates xi = (x - c_e) / h_e (c_e the centre and h_e the sizes per axis
of the box spanned by the cell's Gauss points, as the oracle) and the
monomials

    phi = (1, xi_1, .., xi_d, xi_a xi_b for a <= b)      (m = 3 in 1D, 6 in 2D, 10 in 3D),

the coefficients a_e (m, k) of all k value columns at once solve the
Lagrange system of the volume-weighted fit under the conservation
constraint

    [[A, G], [G^T, 0]] [a_e; lambda] = [b; S],
    A = sum_{p in e} V_p phi_p phi_p^T,  b = sum_{p in e} V_p phi_p f_p,
    G = sum_{g in e} w_g phi_g,          S = sum_{p in e} V_p f_p,

so that the Gauss integral of the fit over the cell is the cell's particle
integral. Fallback levels (never a singular solve): the quadratic when the
leading m x m block of A, scaled to unit diagonal, has its smallest
eigenvalue above TLS_RANK_TOL; else the same with the 1 + d linear
monomials; else the conserving constant S / G_0. A level's fit is kept
for value column c only when its values at the cell's Gauss points stay
within [min_p f_pc - s_c, max_p f_pc + s_c], s_c = TLS_BOUND_TOL (max - min)
+ TLS_BOUND_ABS max |f_pc| over the cell's particles; the columns that
leave it take the next level (the bound test of the oracle). The eigenvalue test is
made as a Cholesky factorisation of D^(-1/2) A D^(-1/2) - TLS_RANK_TOL I
(D = diag A, all > 0): it succeeds exactly when the smallest eigenvalue
exceeds TLS_RANK_TOL. In 1D and 3D the Lagrange system (symmetric
indefinite) is solved by Gaussian elimination with partial pivoting; in 2D
the constraint eliminates the constant (a_0 = (S - sum_(r>=1) G_r a_r) / G_0,
G_0 > 0 the cell's Gauss weight sum), which leaves a symmetric positive
definite system of n - 1 unknowns (5 quadratic, 2 linear) per cell and
level, factored once by Cholesky without pivoting (:func:`_reduced_factor_2d`;
a pivot <= 0 from rounding drops the level, so never a singular solve) and
solved per value column on scalars (:func:`_reduced_solve_6`,
:func:`_reduced_solve_3`). Both give the Lagrange system's solution: the
results agree to rounding, not bit for bit.

Particles are binned to their cells by a counting sort (stable: each
cell's sums run in particle order, as the oracle's np.add.at does), the
Gauss points likewise; the fit of cell e is then evaluated at its points.

A, G, the eigenvalue tests and the factorisation of each level's system
(P K = L U of the Lagrange matrix, in 2D L L^T of the reduced one) depend on
the positions alone: :func:`tls_factor` computes
them once for a set of particles and a rule, and :func:`tls_apply` fits
each field on them (b, S, the solves with the stored factors, the bound
test); a step fits [rho, rho v, sigma] and its MUSL projection fits
rho v^new on one factor. In 1D and 3D each row of the right-hand side takes the
operations of eliminating [K | R] at once, in the same order, so the fit
has the bits of a solve of the whole system (:func:`tls_reconstruct`, both
halves, is the one-call form). The loops over cells run in blocks of
CELLS_PER_BLOCK cells (prange in the parallel kernels; each cell's
arithmetic is the same in any block, so the bits are too).
"""
import numpy as np
from numba import njit, prange

from .cholesky import cholesky

__all__ = ["TLS_BOUND_ABS", "TLS_BOUND_TOL", "TLS_RANK_TOL", "empty_factor", "tls_apply",
           "slot_cells", "tls_coefficients", "tls_factor", "tls_reconstruct"]

TLS_RANK_TOL = 1e-8  # the value of skfem_mpm.reconstruct.TLS_RANK_TOL (a test checks)
TLS_BOUND_TOL = 1.0  # skfem_mpm.reconstruct.TLS_BOUND_TOL and TLS_BOUND_ABS (a test checks)
TLS_BOUND_ABS = 1e-9


@njit(cache=True, inline="always", error_model="numpy")
def _monomials(x0, x1, x2, centre0, centre1, centre2, size0, size1, size2, dim):
    """phi = (1, xi, eta, zeta, xi xi, xi eta, xi zeta, eta eta, eta zeta,
    zeta zeta) of the point (x0, x1, x2), xi = (x0 - centre0) / size0 and so
    on (the oracle's order: 1, the coordinates, then xi_a xi_b for a <= b);
    in 2D (1, xi, eta, xi xi, xi eta, eta eta), in 1D (1, xi, xi xi), the
    rest zeros. Scalars only: an inlined function of array arguments makes
    numba count references to them per call."""
    xi = (x0 - centre0) / size0
    if dim == 1:
        return 1.0, xi, xi * xi, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    eta = (x1 - centre1) / size1
    if dim == 2:
        return 1.0, xi, eta, xi * xi, xi * eta, eta * eta, 0.0, 0.0, 0.0, 0.0
    zeta = (x2 - centre2) / size2
    return (1.0, xi, eta, zeta, xi * xi, xi * eta, xi * zeta, eta * eta, eta * zeta,
            zeta * zeta)


MONOMIALS = 10
"""The most monomials (3D quadratic): the length of phi."""


@njit(cache=True, error_model="numpy")
def _well_posed(A, n, tol, work):
    """Smallest eigenvalue of the leading n x n block of A scaled to unit
    diagonal > tol, by Cholesky of the scaled block minus tol I (in
    ``work``, at least (n + 1) x n)."""
    for i in range(n):
        if not A[i, i] > 0.0:
            return False
        work[n, i] = 1.0 / np.sqrt(A[i, i])  # (a spare row of work)
    for i in range(n):
        for j in range(i + 1):  # the lower triangle: what cholesky reads
            work[i, j] = A[i, j] * work[n, i] * work[n, j]
    return cholesky(work, n, tol, work)


@njit(cache=True, error_model="numpy")
def _factor(K, n, pivot):
    """K[:n, :n] = P^T L U in place by Gaussian elimination with partial
    pivoting (Golub & Van Loan, Alg. 3.4.1): U on and above the diagonal,
    the multipliers of L below it (moved with their rows by later
    interchanges), pivot[j] the row swapped with row j at step j."""
    for j in range(n):
        best = j
        for i in range(j + 1, n):
            if abs(K[i, j]) > abs(K[best, j]):
                best = i
        pivot[j] = best
        if best != j:
            for q in range(n):
                K[j, q], K[best, q] = K[best, q], K[j, q]
        for i in range(j + 1, n):
            f = K[i, j] / K[j, j]
            K[i, j] = f
            if f != 0.0:
                for q in range(j + 1, n):
                    K[i, q] -= f * K[j, q]


@njit(cache=True, error_model="numpy")
def _solve(K, pivot, R, n):
    """R[:n] := K^-1 R[:n] for K factorised by :func:`_factor`: the
    interchanges, then forward and backward substitution. Each row of R
    takes the operations of eliminating [K | R] at once, in the same order
    (the multipliers of step j applied to the rows as they stand after
    step j's interchange), so the same bits."""
    k = R.shape[1]
    for j in range(n):
        best = pivot[j]
        if best != j:
            for c in range(k):
                R[j, c], R[best, c] = R[best, c], R[j, c]
    for j in range(n):
        for i in range(j + 1, n):
            f = K[i, j]
            if f != 0.0:
                for c in range(k):
                    R[i, c] -= f * R[j, c]
    for j in range(n - 1, -1, -1):
        for c in range(k):
            s = R[j, c]
            for q in range(j + 1, n):
                s -= K[j, q] * R[q, c]
            R[j, c] = s / K[j, j]


@njit(cache=True, inline="always", error_model="numpy")
def _lagrange_solve(lu, pivots, s, level, n, b, S, k, R):
    """R[:n + 1] := K^-1 [b; S] for the factorised Lagrange matrix
    lu[s, level] (as :func:`_solve` does, written out: no views)."""
    for r in range(n):
        for col in range(k):
            R[r, col] = b[r, col]
    for col in range(k):
        R[n, col] = S[col]
    for j in range(n + 1):
        best = pivots[s, level, j]
        if best != j:
            for col in range(k):
                R[j, col], R[best, col] = R[best, col], R[j, col]
    for j in range(n + 1):
        for i in range(j + 1, n + 1):
            f = lu[s, level, i, j]
            if f != 0.0:
                for col in range(k):
                    R[i, col] -= f * R[j, col]
    for j in range(n, -1, -1):
        for col in range(k):
            acc = R[j, col]
            for q in range(j + 1, n + 1):
                acc -= lu[s, level, j, q] * R[q, col]
            R[j, col] = acc / lu[s, level, j, j]


@njit(cache=True, error_model="numpy")
def _posed_columns_2d(A, tol):
    """How many leading columns (0 to 6) of the Cholesky factorisation of
    D^(-1/2) A D^(-1/2) - tol I (D = diag A, 2D: 6 x 6) exist: what
    :func:`_well_posed` computes for both levels at once, written out on
    scalars in its order of operations. The factor of a leading block is
    the leading block of the factor, so the quadratic level is well posed
    exactly when 6 columns exist and the linear one when 3 do (and their
    diagonals of A are > 0: only 3 columns are attempted when one of the
    quadratic diagonal entries is not)."""
    if not (A[0, 0] > 0.0 and A[1, 1] > 0.0 and A[2, 2] > 0.0):
        return 0
    full = A[3, 3] > 0.0 and A[4, 4] > 0.0 and A[5, 5] > 0.0
    e0 = 1.0 / np.sqrt(A[0, 0])
    e1 = 1.0 / np.sqrt(A[1, 1])
    e2 = 1.0 / np.sqrt(A[2, 2])
    e3 = e4 = e5 = 0.0
    if full:
        e3 = 1.0 / np.sqrt(A[3, 3])
        e4 = 1.0 / np.sqrt(A[4, 4])
        e5 = 1.0 / np.sqrt(A[5, 5])
    pivot = A[0, 0] * e0 * e0 - tol
    if not pivot > 0.0:
        return 0
    root = np.sqrt(pivot)
    l10 = (A[1, 0] * e1 * e0) / root
    l20 = (A[2, 0] * e2 * e0) / root
    l30 = (A[3, 0] * e3 * e0) / root
    l40 = (A[4, 0] * e4 * e0) / root
    l50 = (A[5, 0] * e5 * e0) / root
    pivot = A[1, 1] * e1 * e1 - tol - l10 * l10
    if not pivot > 0.0:
        return 1
    root = np.sqrt(pivot)
    l21 = (A[2, 1] * e2 * e1 - l20 * l10) / root
    l31 = (A[3, 1] * e3 * e1 - l30 * l10) / root
    l41 = (A[4, 1] * e4 * e1 - l40 * l10) / root
    l51 = (A[5, 1] * e5 * e1 - l50 * l10) / root
    pivot = A[2, 2] * e2 * e2 - tol - l20 * l20 - l21 * l21
    if not pivot > 0.0:
        return 2
    root = np.sqrt(pivot)
    l32 = (A[3, 2] * e3 * e2 - l30 * l20 - l31 * l21) / root
    l42 = (A[4, 2] * e4 * e2 - l40 * l20 - l41 * l21) / root
    l52 = (A[5, 2] * e5 * e2 - l50 * l20 - l51 * l21) / root
    if not full:
        return 3
    pivot = A[3, 3] * e3 * e3 - tol - l30 * l30 - l31 * l31 - l32 * l32
    if not pivot > 0.0:
        return 3
    root = np.sqrt(pivot)
    l43 = (A[4, 3] * e4 * e3 - l40 * l30 - l41 * l31 - l42 * l32) / root
    l53 = (A[5, 3] * e5 * e3 - l50 * l30 - l51 * l31 - l52 * l32) / root
    pivot = A[4, 4] * e4 * e4 - tol - l40 * l40 - l41 * l41 - l42 * l42 - l43 * l43
    if not pivot > 0.0:
        return 4
    root = np.sqrt(pivot)
    l54 = (A[5, 4] * e5 * e4 - l50 * l40 - l51 * l41 - l52 * l42 - l53 * l43) / root
    pivot = A[5, 5] * e5 * e5 - tol - l50 * l50 - l51 * l51 - l52 * l52 - l53 * l53 - l54 * l54
    if not pivot > 0.0:
        return 5
    root = np.sqrt(pivot)
    return 6


@njit(cache=True, error_model="numpy")
def _reduced_factor_2d(A, G, s, lu, most):
    """The 2D constrained fit with the constant eliminated: the constraint
    sum_r G_r a_r = S gives a_0 = c - sum_(r>=1) g_r a_r, c = S / G_0,
    g_r = G_r / G_0 (G_0 the cell's Gauss weight sum, > 0), so
    a = c e_0 + T a', T = [-g^T; I], and the fit's minimum of
    a^T A a - 2 a^T b under the constraint (the Lagrange system's solution)
    solves the symmetric positive definite

        H a' = T^T (b - c A e_0),   H = T^T A T,
        H_rt = A_rt - g_r A_0t - g_t A_r0 + g_r g_t A_00   (r, t >= 1)

    (the null-space method, Golub & Van Loan, "Matrix Computations", 4th
    ed., Sec. 6.2.3). H is positive definite when A is (T has full column
    rank, T^T T >= I), which the caller has tested
    (:func:`_posed_columns_2d`), so Cholesky H = L L^T without pivoting
    (:func:`cholesky`'s order of operations, written out on scalars).

    Writes the quadratic level's L (5 x 5) to lu[s, 0, :5, :5], A[r, 0] to
    lu[s, 0, r, 6], g_r to lu[s, 0, 6, r]; the linear level's (its H is
    the leading 2 x 2 block, whose factor is the leading block of L) to
    lu[s, 1, :2, :2], lu[s, 1, r, 3], lu[s, 1, 3, r]. Returns how many of
    H's columns, up to ``most`` (at least 2), exist: a pivot <= 0 from
    rounding stops it and the caller drops the level (never a singular
    solve)."""
    inv = 1.0 / G[s, 0]
    g1 = G[s, 1] * inv
    g2 = G[s, 2] * inv
    g3 = G[s, 3] * inv
    g4 = G[s, 4] * inv
    g5 = G[s, 5] * inv
    lu[s, 0, 0, 6] = A[0, 0]
    lu[s, 0, 1, 6] = A[1, 0]
    lu[s, 0, 2, 6] = A[2, 0]
    lu[s, 0, 3, 6] = A[3, 0]
    lu[s, 0, 4, 6] = A[4, 0]
    lu[s, 0, 5, 6] = A[5, 0]
    lu[s, 0, 6, 1] = g1
    lu[s, 0, 6, 2] = g2
    lu[s, 0, 6, 3] = g3
    lu[s, 0, 6, 4] = g4
    lu[s, 0, 6, 5] = g5
    lu[s, 1, 0, 3] = A[0, 0]
    lu[s, 1, 1, 3] = A[1, 0]
    lu[s, 1, 2, 3] = A[2, 0]
    lu[s, 1, 3, 1] = g1
    lu[s, 1, 3, 2] = g2
    h11 = A[1, 1] - g1 * A[0, 1] - g1 * A[1, 0] + g1 * g1 * A[0, 0]
    h21 = A[2, 1] - g2 * A[0, 1] - g1 * A[2, 0] + g2 * g1 * A[0, 0]
    h22 = A[2, 2] - g2 * A[0, 2] - g2 * A[2, 0] + g2 * g2 * A[0, 0]
    h31 = A[3, 1] - g3 * A[0, 1] - g1 * A[3, 0] + g3 * g1 * A[0, 0]
    h32 = A[3, 2] - g3 * A[0, 2] - g2 * A[3, 0] + g3 * g2 * A[0, 0]
    h33 = A[3, 3] - g3 * A[0, 3] - g3 * A[3, 0] + g3 * g3 * A[0, 0]
    h41 = A[4, 1] - g4 * A[0, 1] - g1 * A[4, 0] + g4 * g1 * A[0, 0]
    h42 = A[4, 2] - g4 * A[0, 2] - g2 * A[4, 0] + g4 * g2 * A[0, 0]
    h43 = A[4, 3] - g4 * A[0, 3] - g3 * A[4, 0] + g4 * g3 * A[0, 0]
    h44 = A[4, 4] - g4 * A[0, 4] - g4 * A[4, 0] + g4 * g4 * A[0, 0]
    h51 = A[5, 1] - g5 * A[0, 1] - g1 * A[5, 0] + g5 * g1 * A[0, 0]
    h52 = A[5, 2] - g5 * A[0, 2] - g2 * A[5, 0] + g5 * g2 * A[0, 0]
    h53 = A[5, 3] - g5 * A[0, 3] - g3 * A[5, 0] + g5 * g3 * A[0, 0]
    h54 = A[5, 4] - g5 * A[0, 4] - g4 * A[5, 0] + g5 * g4 * A[0, 0]
    h55 = A[5, 5] - g5 * A[0, 5] - g5 * A[5, 0] + g5 * g5 * A[0, 0]
    pivot = h11
    if not pivot > 0.0:
        return 0
    l11 = np.sqrt(pivot)
    lu[s, 0, 0, 0] = l11
    lu[s, 1, 0, 0] = l11
    l21 = h21 / l11
    lu[s, 0, 1, 0] = l21
    lu[s, 1, 1, 0] = l21
    l31 = h31 / l11
    lu[s, 0, 2, 0] = l31
    l41 = h41 / l11
    lu[s, 0, 3, 0] = l41
    l51 = h51 / l11
    lu[s, 0, 4, 0] = l51
    pivot = h22 - l21 * l21
    if not pivot > 0.0:
        return 1
    l22 = np.sqrt(pivot)
    lu[s, 0, 1, 1] = l22
    lu[s, 1, 1, 1] = l22
    l32 = (h32 - l31 * l21) / l22
    lu[s, 0, 2, 1] = l32
    l42 = (h42 - l41 * l21) / l22
    lu[s, 0, 3, 1] = l42
    l52 = (h52 - l51 * l21) / l22
    lu[s, 0, 4, 1] = l52
    if most < 3:
        return 2
    pivot = h33 - l31 * l31 - l32 * l32
    if not pivot > 0.0:
        return 2
    l33 = np.sqrt(pivot)
    lu[s, 0, 2, 2] = l33
    l43 = (h43 - l41 * l31 - l42 * l32) / l33
    lu[s, 0, 3, 2] = l43
    l53 = (h53 - l51 * l31 - l52 * l32) / l33
    lu[s, 0, 4, 2] = l53
    pivot = h44 - l41 * l41 - l42 * l42 - l43 * l43
    if not pivot > 0.0:
        return 3
    l44 = np.sqrt(pivot)
    lu[s, 0, 3, 3] = l44
    l54 = (h54 - l51 * l41 - l52 * l42 - l53 * l43) / l44
    lu[s, 0, 4, 3] = l54
    pivot = h55 - l51 * l51 - l52 * l52 - l53 * l53 - l54 * l54
    if not pivot > 0.0:
        return 4
    l55 = np.sqrt(pivot)
    lu[s, 0, 4, 4] = l55
    return 5


@njit(cache=True, error_model="numpy")
def _gauss_moments_2d(xg, wg, gorder, g0, ng, c0, c1, s0, s1, G, s):
    """G[s] = sum_g w_g phi_g (2D: 6 monomials) over the cell's Gauss
    points gorder[g0:g0 + ng] in the frame (c0, c1), (s0, s1): the loop of
    :func:`tls_factor` written out on scalars (the same sums in the same
    order)."""
    m0 = m1 = m2 = m3 = m4 = m5 = 0.0
    for i in range(ng):
        g = gorder[g0 + i]
        p1 = (xg[g, 0] - c0) / s0
        p2 = (xg[g, 1] - c1) / s1
        w = wg[g]
        m0 += w * 1.0
        m1 += w * p1
        m2 += w * p2
        m3 += w * (p1 * p1)
        m4 += w * (p1 * p2)
        m5 += w * (p2 * p2)
    G[s, 0] += m0
    G[s, 1] += m1
    G[s, 2] += m2
    G[s, 3] += m3
    G[s, 4] += m4
    G[s, 5] += m5


@njit(cache=True, error_model="numpy")
def _reduced_solve_6(lu, s, level, b, S, inv_g0, k, R):
    """R[:6, col] for every value column: the fit's coefficients with the
    6 monomials of 2D level 0, from the factor of :func:`_reduced_factor_2d` in lu[s, level]: the
    right-hand side T^T (b - c A e_0), c = S_col / G_0, forward and
    backward substitution with L, then a_0 = c - sum_r g_r a_r; written out
    on scalars (the divisions by L's diagonal as products with their
    reciprocals)."""
    # the factor's entries as scalars (once per cell and level)
    d1 = 1.0 / lu[s, level, 0, 0]
    l21 = lu[s, level, 1, 0]
    d2 = 1.0 / lu[s, level, 1, 1]
    l31 = lu[s, level, 2, 0]
    l32 = lu[s, level, 2, 1]
    d3 = 1.0 / lu[s, level, 2, 2]
    l41 = lu[s, level, 3, 0]
    l42 = lu[s, level, 3, 1]
    l43 = lu[s, level, 3, 2]
    d4 = 1.0 / lu[s, level, 3, 3]
    l51 = lu[s, level, 4, 0]
    l52 = lu[s, level, 4, 1]
    l53 = lu[s, level, 4, 2]
    l54 = lu[s, level, 4, 3]
    d5 = 1.0 / lu[s, level, 4, 4]
    a0 = lu[s, level, 0, 6]
    a1 = lu[s, level, 1, 6]
    a2 = lu[s, level, 2, 6]
    a3 = lu[s, level, 3, 6]
    a4 = lu[s, level, 4, 6]
    a5 = lu[s, level, 5, 6]
    g1 = lu[s, level, 6, 1]
    g2 = lu[s, level, 6, 2]
    g3 = lu[s, level, 6, 3]
    g4 = lu[s, level, 6, 4]
    g5 = lu[s, level, 6, 5]
    for col in range(k):
        c = S[col] * inv_g0
        rest0 = b[0, col] - c * a0
        y1 = b[1, col] - c * a1 - g1 * rest0
        y2 = b[2, col] - c * a2 - g2 * rest0
        y3 = b[3, col] - c * a3 - g3 * rest0
        y4 = b[4, col] - c * a4 - g4 * rest0
        y5 = b[5, col] - c * a5 - g5 * rest0
        y1 = y1 * d1
        y2 = (y2 - l21 * y1) * d2
        y3 = (y3 - l31 * y1 - l32 * y2) * d3
        y4 = (y4 - l41 * y1 - l42 * y2 - l43 * y3) * d4
        y5 = (y5 - l51 * y1 - l52 * y2 - l53 * y3 - l54 * y4) * d5
        y5 = y5 * d5
        R[5, col] = y5
        y4 = (y4 - l54 * y5) * d4
        R[4, col] = y4
        y3 = (y3 - l43 * y4 - l53 * y5) * d3
        R[3, col] = y3
        y2 = (y2 - l32 * y3 - l42 * y4 - l52 * y5) * d2
        R[2, col] = y2
        y1 = (y1 - l21 * y2 - l31 * y3 - l41 * y4 - l51 * y5) * d1
        R[1, col] = y1
        R[0, col] = c - g1 * y1 - g2 * y2 - g3 * y3 - g4 * y4 - g5 * y5


@njit(cache=True, error_model="numpy")
def _reduced_solve_3(lu, s, level, b, S, inv_g0, k, R):
    """R[:3, col] for every value column: the fit's coefficients with the
    3 monomials of 2D level 1, from the factor of :func:`_reduced_factor_2d` in lu[s, level]: the
    right-hand side T^T (b - c A e_0), c = S_col / G_0, forward and
    backward substitution with L, then a_0 = c - sum_r g_r a_r; written out
    on scalars (the divisions by L's diagonal as products with their
    reciprocals)."""
    # the factor's entries as scalars (once per cell and level)
    d1 = 1.0 / lu[s, level, 0, 0]
    l21 = lu[s, level, 1, 0]
    d2 = 1.0 / lu[s, level, 1, 1]
    a0 = lu[s, level, 0, 3]
    a1 = lu[s, level, 1, 3]
    a2 = lu[s, level, 2, 3]
    g1 = lu[s, level, 3, 1]
    g2 = lu[s, level, 3, 2]
    for col in range(k):
        c = S[col] * inv_g0
        rest0 = b[0, col] - c * a0
        y1 = b[1, col] - c * a1 - g1 * rest0
        y2 = b[2, col] - c * a2 - g2 * rest0
        y1 = y1 * d1
        y2 = (y2 - l21 * y1) * d2
        y2 = y2 * d2
        R[2, col] = y2
        y1 = (y1 - l21 * y2) * d1
        R[1, col] = y1
        R[0, col] = c - g1 * y1 - g2 * y2


@njit(cache=True, error_model="numpy")
def _moments_2d(x, V, porder, first, stop, c0, c1, s0, s1, A):
    """A = sum_p V_p phi_p phi_p^T (6 x 6, both triangles) of the particles
    porder[first:stop] in the frame (c0, c1), (s0, s1), phi the 2D
    monomials of :func:`_monomials`: the loop of :func:`tls_factor` written
    out on scalars (the same sums in the same order)."""
    m00 = 0.0
    m10 = 0.0
    m11 = 0.0
    m20 = 0.0
    m21 = 0.0
    m22 = 0.0
    m30 = 0.0
    m31 = 0.0
    m32 = 0.0
    m33 = 0.0
    m40 = 0.0
    m41 = 0.0
    m42 = 0.0
    m43 = 0.0
    m44 = 0.0
    m50 = 0.0
    m51 = 0.0
    m52 = 0.0
    m53 = 0.0
    m54 = 0.0
    m55 = 0.0
    for i in range(first, stop):
        q = porder[i]
        p1 = (x[q, 0] - c0) / s0
        p2 = (x[q, 1] - c1) / s1
        p3 = p1 * p1
        p4 = p1 * p2
        p5 = p2 * p2
        w = V[q]
        w0 = w
        m00 += w0
        w1 = w * p1
        m10 += w1
        m11 += w1 * p1
        w2 = w * p2
        m20 += w2
        m21 += w2 * p1
        m22 += w2 * p2
        w3 = w * p3
        m30 += w3
        m31 += w3 * p1
        m32 += w3 * p2
        m33 += w3 * p3
        w4 = w * p4
        m40 += w4
        m41 += w4 * p1
        m42 += w4 * p2
        m43 += w4 * p3
        m44 += w4 * p4
        w5 = w * p5
        m50 += w5
        m51 += w5 * p1
        m52 += w5 * p2
        m53 += w5 * p3
        m54 += w5 * p4
        m55 += w5 * p5
    A[0, 0] = m00
    A[1, 0] = m10
    A[0, 1] = m10
    A[1, 1] = m11
    A[2, 0] = m20
    A[0, 2] = m20
    A[2, 1] = m21
    A[1, 2] = m21
    A[2, 2] = m22
    A[3, 0] = m30
    A[0, 3] = m30
    A[3, 1] = m31
    A[1, 3] = m31
    A[3, 2] = m32
    A[2, 3] = m32
    A[3, 3] = m33
    A[4, 0] = m40
    A[0, 4] = m40
    A[4, 1] = m41
    A[1, 4] = m41
    A[4, 2] = m42
    A[2, 4] = m42
    A[4, 3] = m43
    A[3, 4] = m43
    A[4, 4] = m44
    A[5, 0] = m50
    A[0, 5] = m50
    A[5, 1] = m51
    A[1, 5] = m51
    A[5, 2] = m52
    A[2, 5] = m52
    A[5, 3] = m53
    A[3, 5] = m53
    A[5, 4] = m54
    A[4, 5] = m54
    A[5, 5] = m55


@njit(cache=True, error_model="numpy")
def _bins(cell, slot, nslots):
    """Counting sort of the items with slot[cell[i]] >= 0 by that slot
    (stable): items order[start[s]:start[s + 1]] are in slot s."""
    start = np.zeros(nslots + 1, dtype=np.int64)
    for i in range(cell.shape[0]):
        s = slot[cell[i]]
        if s >= 0:
            start[s + 1] += 1
    for s in range(nslots):
        start[s + 1] += start[s]
    fill = start[:-1].copy()
    order = np.empty(start[nslots], dtype=np.int64)
    for i in range(cell.shape[0]):
        s = slot[cell[i]]
        if s >= 0:
            order[fill[s]] = i
            fill[s] += 1
    return order, start


CELLS_PER_BLOCK = 32
"""Cells per block of the loops over cells (each block its own work
arrays; prange over the blocks in the parallel kernels)."""


@njit(cache=True, error_model="numpy")
def _frame(xg, gorder, g0, ng, dim, centre, size):
    """centre, size: the box spanned by the cell's Gauss points
    gorder[g0:g0 + ng] per axis (the oracle's frame); beyond the dimension
    they stay as they are."""
    for a in range(dim):
        lo = np.inf
        hi = -np.inf
        for i in range(ng):
            lo = min(lo, xg[gorder[g0 + i], a])
            hi = max(hi, xg[gorder[g0 + i], a])
        centre[a] = 0.5 * (lo + hi)
        size[a] = hi - lo


@njit(cache=True, error_model="numpy", parallel=True)
def tls_factor(x, V, pcell, xg, wg, gcell, ncells):
    """The half of the TLS fit that depends on the positions alone (the
    particles' x, V and the rule), computed once for every field fitted on
    them (:func:`tls_apply`): the cells' bins, frames, G, whether each
    level is well posed and the factorised Lagrange matrices
    K = [[A, G], [G^T, 0]] of both levels (in 2D the Cholesky factors of
    the reduced systems, :func:`_reduced_factor_2d`; ``pivots`` unused). Arguments as
    :func:`tls_reconstruct`'s; returns the tuple :func:`tls_apply` takes."""
    dim = x.shape[1]
    y = min(1, dim - 1)  # the coordinates' columns (beyond the dimension: read, not used)
    z = dim - 1
    m = 1 + dim + dim * (dim + 1) // 2
    slot = np.full(ncells, -1, dtype=np.int64)
    nact = 0
    for g in range(gcell.shape[0]):
        if slot[gcell[g]] < 0:
            slot[gcell[g]] = nact
            nact += 1
    porder, pstart = _bins(pcell, slot, nact)
    gorder, gstart = _bins(gcell, slot, nact)
    frame = np.zeros((nact, 6))  # centre (3), size (3) per cell
    G = np.zeros((nact, m))
    posed = np.zeros((nact, 2), dtype=np.bool_)
    lu = np.empty((nact, 2, m + 1, m + 1))  # K of the level's n + 1 rows, factorised
    pivots = np.empty((nact, 2, m + 1), dtype=np.int64)  # (entries read: those written)
    nblocks = (nact + CELLS_PER_BLOCK - 1) // CELLS_PER_BLOCK
    for block in prange(nblocks):
        phi = np.zeros(MONOMIALS)
        centre = np.zeros(3)
        size = np.ones(3)
        A = np.empty((m, m))
        work = np.empty((m + 1, m + 1))
        for s in range(block * CELLS_PER_BLOCK, min(nact, (block + 1) * CELLS_PER_BLOCK)):
            g0 = gstart[s]
            ng = gstart[s + 1] - g0
            _frame(xg, gorder, g0, ng, dim, centre, size)
            for a in range(3):
                frame[s, a] = centre[a]
                frame[s, 3 + a] = size[a]
            if dim == 2:
                _moments_2d(x, V, porder, pstart[s], pstart[s + 1], centre[0], centre[1],
                            size[0], size[1], A)
            else:
                A[:] = 0.0
            for i in range(pstart[s], pstart[s + 1] if dim != 2 else 0):
                q = porder[i]
                phi[0], phi[1], phi[2], phi[3], phi[4], phi[5], phi[6], phi[7], phi[8], \
                    phi[9] = _monomials(x[q, 0], x[q, y], x[q, z], centre[0], centre[1],
                                        centre[2], size[0], size[1], size[2], dim)
                for r in range(m):  # the lower triangle (A is symmetric)
                    wr = V[q] * phi[r]
                    for t in range(r + 1):
                        A[r, t] += wr * phi[t]
            for r in range(m if dim != 2 else 0):
                for t in range(r + 1, m):
                    A[r, t] = A[t, r]
            if dim == 2:
                _gauss_moments_2d(xg, wg, gorder, g0, ng, centre[0], centre[1], size[0],
                                  size[1], G, s)
            for i in range(ng if dim != 2 else 0):
                g = gorder[g0 + i]
                phi[0], phi[1], phi[2], phi[3], phi[4], phi[5], phi[6], phi[7], phi[8], \
                    phi[9] = _monomials(xg[g, 0], xg[g, y], xg[g, z], centre[0], centre[1],
                                        centre[2], size[0], size[1], size[2], dim)
                for r in range(m):
                    G[s, r] += wg[g] * phi[r]
            if dim == 2:
                cols = _posed_columns_2d(A, TLS_RANK_TOL)
                if cols >= 3:
                    done = _reduced_factor_2d(A, G, s, lu, 5 if cols == 6 else 2)
                    posed[s, 0] = cols == 6 and done == 5
                    posed[s, 1] = done >= 2
                continue
            for level in range(2):
                n = m if level == 0 else 1 + dim
                if not _well_posed(A, n, TLS_RANK_TOL, work):
                    continue
                K = lu[s, level]
                posed[s, level] = True
                for r in range(n):
                    for t in range(n):
                        K[r, t] = A[r, t]
                    K[r, n] = G[s, r]
                    K[n, r] = G[s, r]
                K[n, n] = 0.0
                _factor(K, n + 1, pivots[s, level])
    return porder, pstart, gorder, gstart, frame, G, posed, lu, pivots


@njit(cache=True, error_model="numpy", parallel=True)
def tls_apply(x, V, values, xg, factor, out):
    """out[g] (ng, k) = the TLS fit of the particle ``values`` (n, k) at
    the Gauss point xg[g], with the position half ``factor`` of
    :func:`tls_factor` on the same particles and rule (see the module
    docstring): the sums b and S, the solves of both levels' factorised
    Lagrange systems, the bound test."""
    nact = factor[5].shape[0]
    nblocks = (nact + CELLS_PER_BLOCK - 1) // CELLS_PER_BLOCK
    no_coef = np.empty((0, 0, 0))
    for block in prange(nblocks):
        _fit_block(block, x, V, values, xg, factor, out, no_coef, True)


@njit(cache=True, error_model="numpy", parallel=True)
def tls_coefficients(x, V, values, xg, factor, coef):
    """coef[s] (m, k) = the monomial coefficients, in cell slot s's frame
    (factor[4]), of the TLS fit of the particle ``values`` (n, k) that
    :func:`tls_apply` evaluates at the cell's Gauss points (the same level
    per column, chosen by the same bound test at those points; the
    conserving constant is c_0 = S / G_0); coef (nact, m, k), the slots of
    :func:`tls_factor` (cell of slot s: the cell of its Gauss points)."""
    nact = factor[5].shape[0]
    nblocks = (nact + CELLS_PER_BLOCK - 1) // CELLS_PER_BLOCK
    no_points = np.empty((0, 0))
    for block in prange(nblocks):
        _fit_block(block, x, V, values, xg, factor, no_points, coef, False)


@njit(cache=True, inline="always", error_model="numpy")
def _fit_block(block, x, V, values, xg, factor, out, coef, at_points):
    """The fits of the cells of one block (see the module docstring): at
    the Gauss points into ``out`` (``at_points``), else their coefficients
    into ``coef`` (the other of the two is not written)."""
    porder, pstart, gorder, gstart, frame, G, posed, lu, pivots = factor
    dim = x.shape[1]
    y = min(1, dim - 1)
    z = dim - 1
    k = values.shape[1]
    m = G.shape[1]
    nact = G.shape[0]
    first = block * CELLS_PER_BLOCK
    stop = min(nact, (block + 1) * CELLS_PER_BLOCK)
    most = 0  # the most Gauss points of one cell of the block
    for s in range(first, stop):
        most = max(most, gstart[s + 1] - gstart[s])
    phig = np.zeros((most, MONOMIALS))  # the monomials at the cell's Gauss points
    fit = np.empty((most, k))  # a level's fit at them
    phi = np.zeros(MONOMIALS)
    b = np.empty((m, k))
    S = np.empty(k)
    R = np.empty((m + 1, k))
    fmin = np.empty(k)
    fmax = np.empty(k)
    slack = np.empty(k)
    low = np.empty(k)
    high = np.empty(k)
    pending = np.empty(k, dtype=np.bool_)
    for s in range(first, stop):
        c0, c1, c2 = frame[s, 0], frame[s, 1], frame[s, 2]
        s0, s1, s2 = frame[s, 3], frame[s, 4], frame[s, 5]
        g0 = gstart[s]
        ng = gstart[s + 1] - g0
        b[:] = 0.0
        S[:] = 0.0
        fmin[:] = np.inf
        fmax[:] = -np.inf
        for i in range(pstart[s], pstart[s + 1]):
            q = porder[i]
            if dim == 2:  # the loop below written out (the same sums)
                w = V[q]
                xi = (x[q, 0] - c0) / s0
                eta = (x[q, 1] - c1) / s1
                w1 = w * xi
                w2 = w * eta
                w3 = w * (xi * xi)
                w4 = w * (xi * eta)
                w5 = w * (eta * eta)
                for col in range(k):
                    f = values[q, col]
                    b[0, col] += w * f
                    b[1, col] += w1 * f
                    b[2, col] += w2 * f
                    b[3, col] += w3 * f
                    b[4, col] += w4 * f
                    b[5, col] += w5 * f
            else:
                phi[0], phi[1], phi[2], phi[3], phi[4], phi[5], phi[6], phi[7], phi[8], \
                    phi[9] = _monomials(x[q, 0], x[q, y], x[q, z], c0, c1, c2, s0, s1, s2,
                                        dim)
                for r in range(m):
                    wr = V[q] * phi[r]
                    for col in range(k):
                        b[r, col] += wr * values[q, col]
            for col in range(k):
                S[col] += V[q] * values[q, col]
                fmin[col] = min(fmin[col], values[q, col])
                fmax[col] = max(fmax[col], values[q, col])
        evaluated = False  # phig holds the monomials at the cell's Gauss points
        for col in range(k):
            slack[col] = TLS_BOUND_TOL * (fmax[col] - fmin[col]) + TLS_BOUND_ABS * max(
                abs(fmin[col]), abs(fmax[col]))
            pending[col] = True
        npending = k
        for level in range(2):
            if npending == 0 or not posed[s, level]:
                continue
            n = m if level == 0 else 1 + dim
            if dim == 2:
                if level == 0:
                    _reduced_solve_6(lu, s, level, b, S, 1.0 / G[s, 0], k, R)
                else:
                    _reduced_solve_3(lu, s, level, b, S, 1.0 / G[s, 0], k, R)
            else:
                _lagrange_solve(lu, pivots, s, level, n, b, S, k, R)
            # the bound test: first the bound |f - c_0| <= B of the monomials
            # on the frame (|xi_a| <= 1/2 at the points), with a margin above
            # the rounding of an evaluation; a column it does not settle (or
            # at_points, which needs the values) is evaluated at the points
            unsure = at_points
            for col in range(k):
                low[col] = np.inf
                high[col] = -np.inf
                if pending[col] and not at_points:
                    spread = 0.0
                    for r in range(1, n):
                        spread += abs(R[r, col]) * (0.5 if r <= dim else 0.25)
                    margin = 1e-14 * (abs(R[0, col]) + spread)
                    lo_c = R[0, col] - spread - margin
                    hi_c = R[0, col] + spread + margin
                    if lo_c >= fmin[col] - slack[col] and hi_c <= fmax[col] + slack[col]:
                        low[col] = lo_c
                        high[col] = hi_c
                    else:  # (also NaN)
                        unsure = True
            if unsure:
                if not evaluated:
                    for i in range(ng):
                        g = gorder[g0 + i]
                        phig[i, 0], phig[i, 1], phig[i, 2], phig[i, 3], phig[i, 4], \
                            phig[i, 5], phig[i, 6], phig[i, 7], phig[i, 8], \
                            phig[i, 9] = _monomials(xg[g, 0], xg[g, y], xg[g, z], c0, c1, c2,
                                                    s0, s1, s2, dim)
                    evaluated = True
                for col in range(k):  # the level's fit at the points
                    if pending[col] and not low[col] < np.inf:
                        for i in range(ng):
                            acc = 0.0
                            for r in range(n):
                                acc += phig[i, r] * R[r, col]
                            fit[i, col] = acc
                            low[col] = min(low[col], acc)
                            high[col] = max(high[col], acc)
            for col in range(k):  # the columns within their bounds keep this level's fit
                if pending[col] and low[col] >= fmin[col] - slack[col] \
                        and high[col] <= fmax[col] + slack[col]:
                    if at_points:
                        for i in range(ng):
                            out[gorder[g0 + i], col] = fit[i, col]
                    else:
                        for r in range(m):
                            coef[s, r, col] = R[r, col] if r < n else 0.0
                    pending[col] = False
                    npending -= 1
        for col in range(k):  # the conserving constant
            if pending[col]:
                constant = S[col] / G[s, 0]
                if at_points:
                    for i in range(ng):
                        out[gorder[g0 + i], col] = constant
                else:
                    coef[s, 0, col] = constant
                    for r in range(1, m):
                        coef[s, r, col] = 0.0


@njit(cache=True, error_model="numpy")
def slot_cells(factor, gcell):
    """The cell of each slot of :func:`tls_factor` (that of its Gauss
    points ``gcell``), for the cell integrals of :func:`tls_coefficients`'
    coefficients (kernels.cell_integrals)."""
    gorder, gstart = factor[2], factor[3]
    nact = gstart.shape[0] - 1
    cells = np.empty(nact, dtype=np.int64)
    for s in range(nact):
        cells[s] = gcell[gorder[gstart[s]]]
    return cells


def empty_factor(dim):
    """A :func:`tls_factor` result of no cells, of the types the kernel
    returns in ``dim`` dimensions (a placeholder for the compiled loop's
    run data)."""
    m = 1 + dim + dim * (dim + 1) // 2
    index = np.zeros(0, dtype=np.int64)
    start = np.zeros(1, dtype=np.int64)
    return (index, start, index.copy(), start.copy(), np.zeros((0, 6)), np.zeros((0, m)),
            np.zeros((0, 2), dtype=np.bool_), np.zeros((0, 2, m + 1, m + 1)),
            np.zeros((0, 2, m + 1), dtype=np.int64))


@njit(cache=True, error_model="numpy")
def tls_reconstruct(x, V, values, pcell, xg, wg, gcell, ncells, out):
    """out[g] (ng, k) = the TLS fit of the particle ``values`` (n, k) of the
    cell gcell[g] at the Gauss point xg[g] (see the module docstring):
    :func:`tls_apply` on :func:`tls_factor`.

    ``x`` (n, d) particle positions, ``V`` (n,) volumes, ``pcell`` (n,) the
    cell of each particle (scikit-fem numbering: ix + nx iy + nx ny iz),
    ``xg`` (ng, d), ``wg`` (ng,), ``gcell`` (ng,) the rule; ``ncells`` the
    grid's number of cells."""
    tls_apply(x, V, values, xg, tls_factor(x, V, pcell, xg, wg, gcell, ncells), out)
