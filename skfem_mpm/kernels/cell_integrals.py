"""Grid integrals of per-cell polynomials on a 2D tensor B-spline grid, in
closed form per axis: the TLS fit's quadratics and the 2D spline fit's
bicubics (tensor degree 3 per axis; see "the 2D spline" below), the grid
side of both fits without their Gauss points.

A per-cell reconstruction (:mod:`skfem_mpm.kernels.tls`) gives in each
cell e = ix + nx iy a polynomial in the cell's frame

    f_h(x) = sum_r c_r phi_r(xi, eta),   phi = (1, xi, eta, xi^2, xi eta, eta^2),
    xi = (x - c^x_ix) / s^x_ix,   eta = (y - c^y_iy) / s^y_iy

(c, s: centre and span of the cell's Gauss points per axis, the fit's own
frame). Every grid quantity the step integrates is linear in c and the
monomials and the B-splines are tensor products, so each integral over
the cell splits into 1D integrals per axis (sum factorisation, Orszag
1980), taken once per cell of each axis at setup (:func:`axis_tables`):

    P[i, q, a]    = int_cell xi^q N_a dx          D[i, q, a] = int xi^q N_a' dx
    Q[i, q, a, b] = int_cell xi^q N_a N_b dx      R[i, q, a] = int xi^q (N_a')^2 dx

(N_a, a = 0..p, the cell's p + 1 B-splines of the axis; exact with the
cell's k = p + 2 point Gauss rule, degree 2 + 2p <= 2k - 1). Then with
U_q[a] = sum_p c_(p, q) T^x[ix, p, a] (the x sums of each y power q):

    int f_h N_(a,b)           = sum_q U_q[a] P^y[iy, q, b]        (T^x = P^x)
    int f_h dN_(a,b)/dx       = sum_q U_q[a] P^y[iy, q, b]        (T^x = D^x)
    int f_h dN_(a,b)/dy       = sum_q U_q[a] D^y[iy, q, b]        (T^x = P^x)
    int f_h N_(a,b) N_(a2,b2) = sum_q Q^y[iy, q, b, b2] (sum_p c_(p, q) Q^x[ix, p, a, a2])
    int f_h |grad N_(a,b)|^2  = sum_q (U^R_q[a] Q^y[iy, q, b, b] + U^S_q[a] R^y[iy, q, b])

(U^R with R^x, U^S with the diagonal of Q^x). These are the sums the
Gauss points of the cell give (the same quadrature), in another order:
equal to rounding. :func:`cell_p2g` adds the lumped mass, momentum and
force (p2g's fields: m_k = int rho_h N_k, P_k = int (rho v)_h N_k,
f_k = int (rho b)_h N_k - sym(sigma_h) grad N_k) into p2g's per-thread
copies, :func:`cell_momentum` a momentum into g2p2g's, and
:func:`cell_mass` the consistent mass and sum rho_h |grad N_k|^2 into the
consistent mass kernels' copies (the slots of
:func:`skfem_mpm.kernels.mpm.consistent_cells_2d`), each after the point
kernel of the step has cleared and written its copies: the cells are split
into one block per copy and each block widens its copy's touched range.
"""
import numpy as np
from numba import njit, prange
from numba.extending import overload

from .stencil import axis_functions
from .weights import FAST

__all__ = ["axis_tables", "cell_mass", "cell_momentum", "cell_p2g", "point_axis_tables",
           "spline_axis_tables"]

# IDX[q, p]: the index in phi of xi^p eta^q (-1: not a monomial of degree <= 2)
IDX = np.array([[0, 1, 3], [2, 4, -1], [5, -1, -1]], dtype=np.int64)


@njit(cache=True, error_model="numpy")
def axis_tables(breaks, uniform, C, p, ref, wref):
    """(P, D, Q, R) of one axis (see the module), each (n, 3, ...) over the
    frame's powers xi^q, q = 0..2, each cell i taken whole, its Gauss
    points x_j = u_i + h_i r_j (weights h_i w_j) and frame centre
    0.5 (x_min + x_max), span x_max - x_min, as
    :func:`skfem_mpm.kernels.gauss_rule.gauss_rule_cells` and
    :func:`skfem_mpm.kernels.tls.tls_factor` compute them. Entries beyond
    p are 0."""
    return _tables(breaks, uniform, C, p, ref, wref, C, False)


@njit(cache=True, error_model="numpy")
def spline_axis_tables(breaks, uniform, C, p, cubic, ref, wref):
    """(P, D, Q, R) of one axis (see the module) over the cell's four cubic
    B-splines instead of the frame's powers, each (n, 4, ...):
    P[i, q, a] = int_cell N^3_(i+q) N_a dx and so on (``cubic``: the
    extraction of the cubic space on the same breakpoints, whose functions
    on cell i are i..i+3; exact with the cell's p + 2 point Gauss rule,
    degree 3 + 2p <= 2p + 3). Entries beyond p are 0."""
    return _tables(breaks, uniform, C, p, ref, wref, cubic, 1)


@njit(cache=True, error_model="numpy")
def point_axis_tables(breaks, uniform, C, p, ref, wref):
    """(P, D, Q, R) of one axis (see the module) over the k = p + 2 Gauss
    points of each cell instead of the frame's powers, each (n, k, ...):
    the rule's terms of point j, P[i, j, a] = h_i w_j N_a(x_j),
    D[i, j, a] = h_i w_j N_a'(x_j), Q[i, j, a, b] = h_i w_j N_a(x_j) N_b(x_j),
    R[i, j, a] = h_i w_j N_a'(x_j)^2 (x_j = u_i + h_i r_j, as
    :func:`skfem_mpm.kernels.gauss_rule.gauss_rule_cells` on a whole
    cell). With a fit given by its values at a cell's k x k Gauss points
    (mls: coef (cells, k, k, columns), point (a, b) of the cell at
    [b, a]) the sums of the module are the cell's Gauss sums, factorised
    per axis. Entries beyond p are 0."""
    return _tables(breaks, uniform, C, p, ref, wref, C, 2)


@njit(cache=True, error_model="numpy")
def _tables(breaks, uniform, C, p, ref, wref, cubic, kind):
    """:func:`axis_tables` (``kind`` 0: the frame's powers),
    :func:`spline_axis_tables` (1: the cubic B-splines of ``cubic``) or
    :func:`point_axis_tables` (2: the Gauss points)."""
    splines = kind == 1
    n = breaks.shape[0] - 1
    inv_h = n / (breaks[n] - breaks[0])
    k = ref.shape[0]
    nq = k if kind == 2 else (4 if splines else 3)
    P = np.zeros((n, nq, 4))
    D = np.zeros((n, nq, 4))
    Q = np.zeros((n, nq, 4, 4))
    R = np.zeros((n, nq, 4))
    x = np.empty(k)
    for i in range(n):
        h = breaks[i + 1] - breaks[i]
        lo = np.inf
        hi = -np.inf
        for j in range(k):
            x[j] = breaks[i] + h * ref[j]
            lo = min(lo, x[j])
            hi = max(hi, x[j])
        centre = 0.5 * (lo + hi)
        span = hi - lo
        for j in range(k):
            _, w0, w1, w2, w3, g0, g1, g2, g3 = axis_functions(x[j], breaks, uniform, inv_h, C,
                                                               p)
            w = (w0, w1, w2, w3)
            g = (g0, g1, g2, g3)
            weight = h * wref[j]
            if splines:
                e, f0, f1, f2, f3, _, _, _, _ = axis_functions(x[j], breaks, uniform, inv_h,
                                                               cubic, 3)
                if e != i:
                    raise ValueError("spline_axis_tables: a Gauss point outside its cell")
                fit = (weight * f0, weight * f1, weight * f2, weight * f3)
            elif kind == 2:  # point j alone: its own row
                fit = (weight, 0.0, 0.0, 0.0)
            else:
                xi = (x[j] - centre) / span
                fit = (weight, weight * xi, weight * xi * xi, 0.0)
            for q in range(nq):
                if kind == 2:
                    if q != j:
                        continue
                    power = fit[0]
                else:
                    power = fit[q]
                for a in range(p + 1):
                    P[i, q, a] += power * w[a]
                    D[i, q, a] += power * g[a]
                    R[i, q, a] += power * g[a] * g[a]
                    for b in range(p + 1):
                        Q[i, q, a, b] += power * w[a] * w[b]
    return P, D, Q, R


# ------------------------------------------------------------ the 2D spline
# The spline reconstruction's fit (kernels.spline_2d) is a cubic tensor
# B-spline on the grid's own breakpoints: in cell (ix, iy)
#     f_h = sum_(e, q = 0..3) c_(iy + q, ix + e) N^3_(ix + e)(x) N^3_(iy + q)(y)
# (c the fit's coefficients, row (iy + q) nbf + ix + e, nbf = ncx + 3 the
# cubic functions along x: SplineGrid's n_x + p), so the sums above hold
# with the cell's cubic B-splines for the powers (spline_axis_tables) and
# the x sums U_q[a] = sum_e c_(iy + q, ix + e) T^x[ix, e, a], q = 0..3.
#
# One set of kernels serves both fits: they differ only in where a cell's
# coefficients of x term e in y term q stand (_cell_coefficients, chosen
# by the type of coef: TLS (ns, 6, k) per slot, the spline (nbf nby, k)
# per cubic function) and in how many there are (TLS: e < 3 - q, q < 3;
# the spline: e < 4, q < 4); the sums over them are the same.


def _cell_coefficients(coef, s, cell, ncx, c0, c1, C):
    """C[q, e] = 0.5 (c_(q, e) of column c0 + that of column c1) of the fit
    of slot s (cell ``cell``), each q's first :func:`_terms` e (c0 = c1:
    one column's, without the mean)."""


@overload(_cell_coefficients, inline="always", jit_options={"fastmath": FAST})
def _cell_coefficients_impl(coef, s, cell, ncx, c0, c1, C):
    if coef.ndim == 4:  # values at the Gauss points: coef[s, q, e, column], point (e, q)
        def points(coef, s, cell, ncx, c0, c1, C):
            k = coef.shape[1]
            for q in range(k):
                for e in range(k):
                    if c0 == c1:
                        C[q, e] = coef[s, q, e, c0]
                    else:
                        C[q, e] = 0.5 * (coef[s, q, e, c0] + coef[s, q, e, c1])
        return points
    if coef.ndim == 3:  # TLS: coef[s, IDX[q, e], column], e < 3 - q
        def tls(coef, s, cell, ncx, c0, c1, C):
            for q in range(3):
                for e in range(3 - q):
                    r = IDX[q, e]
                    if c0 == c1:
                        C[q, e] = coef[s, r, c0]
                    else:
                        C[q, e] = 0.5 * (coef[s, r, c0] + coef[s, r, c1])
        return tls

    def spline(coef, s, cell, ncx, c0, c1, C):  # coef[(iy + q) nbf + ix + e, column]
        nbf = ncx + 3
        row = (cell // ncx) * nbf + cell % ncx
        for q in range(4):
            first = row + q * nbf
            for e in range(4):
                if c0 == c1:
                    C[q, e] = coef[first + e, c0]
                else:
                    C[q, e] = 0.5 * (coef[first + e, c0] + coef[first + e, c1])
    return spline


def _rows(coef):
    """How many y terms a cell's fit has (TLS: 3, total degree 2; the
    spline: 4, tensor cubic; values at k x k Gauss points: k), from the
    type of coef."""


@overload(_rows, inline="always")
def _rows_impl(coef):
    if coef.ndim == 4:
        return lambda coef: coef.shape[1]
    if coef.ndim == 3:
        return lambda coef: 3
    return lambda coef: 4


def _terms(coef, q):
    """How many x terms y term q of a cell's fit has (TLS: 3 - q; the
    spline: 4; Gauss points: k)."""


@overload(_terms, inline="always")
def _terms_impl(coef, q):
    if coef.ndim == 4:
        return lambda coef, q: coef.shape[2]
    if coef.ndim == 3:
        return lambda coef, q: 3 - q
    return lambda coef, q: 4


@njit(cache=True, inline="always")
def _rows_of(coef, tx, ty):
    """_rows(coef), checked against the tables' rows."""
    nq = _rows(coef)
    if tx[0].shape[1] != nq or ty[0].shape[1] != nq:
        raise ValueError("cell_integrals: tx, ty must be axis_tables (3 rows) with TLS "
                         "coefficients coef (ns, 6, k), spline_axis_tables (4 rows) with "
                         "the spline's coef (nbf nby, k), point_axis_tables (k rows) with "
                         "values at the Gauss points coef (ns, k, k, columns)")
    return nq


@njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def _x_sums(coef, C, T, ix, p, U):
    """U[q, a] = sum_e C[q, e] T[ix, e, a] (U (nq, 4), C a cell's
    :func:`_cell_coefficients`)."""
    for q in range(_rows(coef)):
        for a in range(p + 1):
            acc = 0.0
            for e in range(_terms(coef, q)):
                acc += C[q, e] * T[ix, e, a]
            U[q, a] = acc


@njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def _column_x_sums(coef, s, cell, ncx, c0, c1, C, T, ix, p, U):
    """:func:`_x_sums` of the mean of columns c0 and c1 (c0 = c1: of one
    column) of slot s."""
    _cell_coefficients(coef, s, cell, ncx, c0, c1, C)
    _x_sums(coef, C, T, ix, p, U)


@njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def _y_sum(nq, U, T, iy, a, b):
    """sum_q U[q, a] T[iy, q, b], q < nq (3 to 5)."""
    acc = U[0, a] * T[iy, 0, b] + U[1, a] * T[iy, 1, b] + U[2, a] * T[iy, 2, b]
    for q in range(3, nq):
        acc += U[q, a] * T[iy, q, b]
    return acc


@njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def _mass_sum(nq, Q, iy, b, b2, T, a, a2):
    """sum_q Q[iy, q, b, b2] T[q, a, a2], q < nq (3 to 5)."""
    acc = Q[iy, 0, b, b2] * T[0, a, a2] + Q[iy, 1, b, b2] * T[1, a, a2] \
        + Q[iy, 2, b, b2] * T[2, a, a2]
    for q in range(3, nq):
        acc += Q[iy, q, b, b2] * T[q, a, a2]
    return acc


@njit(cache=True, inline="always", error_model="numpy")
def _cell_nodes(first, last, ix, iy, p, nbx):
    """The touched range (first, last) widened by the nodes of cell (ix, iy)."""
    return min(first, iy * nbx + ix), max(last, (iy + p) * nbx + ix + p + 1)


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def cell_p2g(coef, cell, ncx, tx, ty, p, nbx, has_fext, copies, touched):
    """Add p2g's fields (m, P, f) of the cells' fitted [rho, rho v,
    sigma (row by row), rho b (with ``has_fext``)] into the per-thread
    copies (nt, dofs, 5) after the point kernel (see the module). ``coef``:
    the TLS fit's (ns, 6, k), cell[s]'s coefficients, with ``tx``, ``ty``
    the :func:`axis_tables` of the axes; or the spline fit's (nbf nby, k),
    its cubic coefficients (see above), with :func:`spline_axis_tables`;
    ``cell`` the cells integrated, ``ncx`` cells along x, ``nbx`` functions
    along x."""
    ns = cell.shape[0]
    nt, nk, nf = copies.shape
    nq = _rows_of(coef, tx, ty)
    Px, Dx = tx[0], tx[1]
    Py, Dy = ty[0], ty[1]
    for t in prange(nt):
        g = copies[t].reshape(nk * nf)
        first = touched[t, 0]
        last = touched[t, 1]
        C = np.empty((nq, nq))
        Um = np.empty((nq, 4))
        U0 = np.empty((nq, 4))
        U1 = np.empty((nq, 4))
        A00 = np.empty((nq, 4))  # sigma_00 with D^x
        A01 = np.empty((nq, 4))  # sym sigma_01 with P^x
        B01 = np.empty((nq, 4))  # sym sigma_01 with D^x
        A11 = np.empty((nq, 4))  # sigma_11 with P^x
        E0 = np.zeros((nq, 4))
        E1 = np.zeros((nq, 4))
        for s in range(t * ns // nt, (t + 1) * ns // nt):
            c = cell[s]
            ix = c % ncx
            iy = c // ncx
            _column_x_sums(coef, s, c, ncx, 0, 0, C, Px, ix, p, Um)
            _column_x_sums(coef, s, c, ncx, 1, 1, C, Px, ix, p, U0)
            _column_x_sums(coef, s, c, ncx, 2, 2, C, Px, ix, p, U1)
            _column_x_sums(coef, s, c, ncx, 3, 3, C, Dx, ix, p, A00)
            _cell_coefficients(coef, s, c, ncx, 4, 5, C)
            _x_sums(coef, C, Px, ix, p, A01)
            _x_sums(coef, C, Dx, ix, p, B01)
            _column_x_sums(coef, s, c, ncx, 6, 6, C, Px, ix, p, A11)
            if has_fext:
                _column_x_sums(coef, s, c, ncx, 7, 7, C, Px, ix, p, E0)
                _column_x_sums(coef, s, c, ncx, 8, 8, C, Px, ix, p, E1)
            for b in range(p + 1):
                for a in range(p + 1):
                    k = ((iy + b) * nbx + ix + a) * nf
                    g[k] += _y_sum(nq, Um, Py, iy, a, b)
                    g[k + 1] += _y_sum(nq, U0, Py, iy, a, b)
                    g[k + 2] += _y_sum(nq, U1, Py, iy, a, b)
                    f0 = -(_y_sum(nq, A00, Py, iy, a, b) + _y_sum(nq, A01, Dy, iy, a, b))
                    f1 = -(_y_sum(nq, B01, Py, iy, a, b) + _y_sum(nq, A11, Dy, iy, a, b))
                    if has_fext:
                        f0 += _y_sum(nq, E0, Py, iy, a, b)
                        f1 += _y_sum(nq, E1, Py, iy, a, b)
                    g[k + 3] += f0
                    g[k + 4] += f1
            first, last = _cell_nodes(first, last, ix, iy, p, nbx)
        touched[t, 0] = first
        touched[t, 1] = last


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def cell_momentum(coef, cell, ncx, tx, ty, p, nbx, copies, touched):
    """Add int (rho v)_h N_k of the cells' fitted momentum density (coef
    the fit's coefficients of its two columns, see :func:`cell_p2g`) into
    g2p2g's per-thread copies (nt, dofs, 2) after the point kernel."""
    ns = cell.shape[0]
    nt, nk, nf = copies.shape
    nq = _rows_of(coef, tx, ty)
    Px = tx[0]
    Py = ty[0]
    for t in prange(nt):
        g = copies[t].reshape(nk * nf)
        first = touched[t, 0]
        last = touched[t, 1]
        C = np.empty((nq, nq))
        U0 = np.empty((nq, 4))
        U1 = np.empty((nq, 4))
        for s in range(t * ns // nt, (t + 1) * ns // nt):
            c = cell[s]
            ix = c % ncx
            iy = c // ncx
            _column_x_sums(coef, s, c, ncx, 0, 0, C, Px, ix, p, U0)
            _column_x_sums(coef, s, c, ncx, 1, 1, C, Px, ix, p, U1)
            for b in range(p + 1):
                for a in range(p + 1):
                    k = ((iy + b) * nbx + ix + a) * nf
                    g[k] += _y_sum(nq, U0, Py, iy, a, b)
                    g[k + 1] += _y_sum(nq, U1, Py, iy, a, b)
            first, last = _cell_nodes(first, last, ix, iy, p, nbx)
        touched[t, 0] = first
        touched[t, 1] = last


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def cell_mass(coef, cell, ncx, tx, ty, p, nbx, mass_copies, stiff_copies, touched):
    """Add the consistent mass int rho_h N_k N_l (upper half of the
    stencil, the slots of kernels.mpm.consistent_cells_2d) and
    int rho_h |grad N_k|^2 of the cells' fitted density (column 0 of coef,
    see :func:`cell_p2g`) into the consistent mass kernels' per-thread
    copies, after the point kernel (see the module)."""
    ns = cell.shape[0]
    nt = mass_copies.shape[0]
    nq = _rows_of(coef, tx, ty)
    width = 2 * p + 1
    Qx, Rx = tx[2], tx[3]
    Qy, Ry = ty[2], ty[3]
    for t in prange(nt):
        M = mass_copies[t]
        K = stiff_copies[t]
        first = touched[t, 0]
        last = touched[t, 1]
        C = np.empty((nq, nq))
        T = np.empty((nq, 4, 4))  # T[q, a, a2] = sum_e c_(q, e) Q^x[ix, e, a, a2]
        UR = np.empty((nq, 4))
        for s in range(t * ns // nt, (t + 1) * ns // nt):
            c = cell[s]
            ix = c % ncx
            iy = c // ncx
            _column_x_sums(coef, s, c, ncx, 0, 0, C, Rx, ix, p, UR)
            for q in range(nq):
                for a in range(p + 1):
                    for a2 in range(a, p + 1):
                        acc = 0.0
                        for e in range(_terms(coef, q)):
                            acc += C[q, e] * Qx[ix, e, a, a2]
                        T[q, a, a2] = acc
                        T[q, a2, a] = acc
            for b in range(p + 1):
                for a in range(p + 1):
                    kd = (iy + b) * nbx + ix + a
                    # sum_q UR[q, a] Q^y[iy, q, b, b] + sum_q T[q, a, a] R^y[iy, q, b],
                    # added term by term in that order
                    stiff = UR[0, a] * Qy[iy, 0, b, b] + UR[1, a] * Qy[iy, 1, b, b]
                    stiff += UR[2, a] * Qy[iy, 2, b, b]
                    for q in range(3, nq):
                        stiff += UR[q, a] * Qy[iy, q, b, b]
                    stiff += T[0, a, a] * Ry[iy, 0, b]
                    stiff += T[1, a, a] * Ry[iy, 1, b]
                    stiff += T[2, a, a] * Ry[iy, 2, b]
                    for q in range(3, nq):
                        stiff += T[q, a, a] * Ry[iy, q, b]
                    K[kd] += stiff
                    for a2 in range(a, p + 1):
                        M[kd, a2 - a] += _mass_sum(nq, Qy, iy, b, b, T, a, a2)
                    for b2 in range(b + 1, p + 1):
                        base = (b2 - b) * width - a
                        for a2 in range(p + 1):
                            M[kd, base + a2] += _mass_sum(nq, Qy, iy, b, b2, T, a, a2)
            first, last = _cell_nodes(first, last, ix, iy, p, nbx)
        touched[t, 0] = first
        touched[t, 1] = last
