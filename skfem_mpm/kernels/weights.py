"""Compiled evaluation of the 1D B-spline functions of one grid axis.

Same result as :meth:`SplineGrid.axis_functions` with the NumPy backend
(the reference): per point, the cell e (floor on uniform axes, bisection
otherwise), xi = (x - u_e) / h_e, the Bernstein values of degree p by the
de Casteljau-type recursion B^k_j = (1 - xi) B^(k-1)_j + xi B^(k-1)_(j-1),
their derivatives p (B^(p-1)_(j-1) - B^(p-1)_j), and the extraction
N_(e+a) = sum_j C_e[a, j] B_j (Borden et al. 2011, eq. 8).
"""
import numpy as np
from numba import njit, prange

# fast-math without the no-NaN and no-Inf assumptions: the guards test isfinite
FAST = {"contract", "arcp", "nsz", "reassoc", "afn"}
# ... and without reassociation, for loops whose sums must keep their order
# (a sum in a register that FAST would split into vector lanes)
IN_ORDER = FAST - {"reassoc"}


@njit(cache=True, inline="always", error_model="numpy")
def locate_axis_point(x, breaks, uniform, inv_h):
    """Cell index of coordinate x (clamped to the last cell at the end)."""
    ncells = breaks.shape[0] - 1
    if uniform:
        e = int(np.floor((x - breaks[0]) * inv_h))
    else:
        lo, hi = 0, ncells
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if breaks[mid] <= x:
                lo = mid
            else:
                hi = mid
        e = lo
    if e < 0:
        e = 0
    elif e > ncells - 1:
        e = ncells - 1
    return e


@njit(cache=True, inline="always", error_model="numpy")
def bernstein4(p, xi):
    """Bernstein values of degree p <= 3 (b0..b3) and of degree p - 1 (c0..c3)."""
    one = 1.0 - xi
    b0, b1, b2, b3 = 1.0, 0.0, 0.0, 0.0
    c0, c1, c2, c3 = 0.0, 0.0, 0.0, 0.0
    for _ in range(p):
        c0, c1, c2, c3 = b0, b1, b2, b3
        b0, b1, b2, b3 = one * c0, one * c1 + xi * c0, one * c2 + xi * c1, one * c3 + xi * c2
    return b0, b1, b2, b3, c0, c1, c2, c3


@njit(cache=True, inline="always", error_model="numpy")
def extracted_functions(x, e, breaks, C, p, w, dw):
    """Values w[a] and d/dx dw[a] of the p + 1 B-splines of cell e at x:
    the cell's extraction matrix applied to the Bernstein polynomials."""
    h = breaks[e + 1] - breaks[e]
    xi = (x - breaks[e]) / h
    b0, b1, b2, b3, c0, c1, c2, c3 = bernstein4(p, xi)
    d0 = -p * c0
    d1 = p * (c0 - c1)
    d2 = p * (c1 - c2)
    d3 = p * (c2 - c3)
    inv = 1.0 / h
    for a in range(p + 1):
        v = C[e, a, 0] * b0 + C[e, a, 1] * b1
        d = C[e, a, 0] * d0 + C[e, a, 1] * d1
        if p >= 2:
            v += C[e, a, 2] * b2
            d += C[e, a, 2] * d2
        if p >= 3:
            v += C[e, a, 3] * b3
            d += C[e, a, 3] * d3
        w[a] = v
        dw[a] = d * inv


@njit(cache=True, parallel=True, error_model="numpy")
def axis_functions_kernel(x, breaks, uniform, inv_h, C, p, first, values, derivs):
    n = x.shape[0]
    for i in prange(n):
        e = locate_axis_point(x[i], breaks, uniform, inv_h)
        first[i] = e
        extracted_functions(x[i], e, breaks, C, p, values[i], derivs[i])


@njit(cache=True, error_model="numpy")
def axis_functions_serial(x, breaks, uniform, inv_h, C, p, first, values, derivs):
    """:func:`axis_functions_kernel` on one thread (same values)."""
    for i in range(x.shape[0]):
        e = locate_axis_point(x[i], breaks, uniform, inv_h)
        first[i] = e
        extracted_functions(x[i], e, breaks, C, p, values[i], derivs[i])


SERIAL_BELOW = 8192
"""Points below which the basis is evaluated on one thread: a parallel
region costs more than the work there, and far more when another process
holds a core (the threads wait for each other)."""


def axis_functions(x, breaks, uniform, C, p):
    """(first, values, derivatives) of one axis, compiled."""
    x = np.ascontiguousarray(x, dtype=np.float64)
    n = x.shape[0]
    first = np.empty(n, dtype=np.int64)
    values = np.empty((n, p + 1))
    derivs = np.empty((n, p + 1))
    inv_h = (breaks.shape[0] - 1) / (breaks[-1] - breaks[0])
    kernel = axis_functions_serial if n < SERIAL_BELOW else axis_functions_kernel
    kernel(x, breaks, bool(uniform), inv_h, C, p, first, values, derivs)
    return first, values, derivs
