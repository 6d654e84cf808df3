"""The not-a-knot cubic spline through particle values, per connected
piece of a 1D body, evaluated at the Gauss points of that piece (the
compiled twin of the ``knots="particles"`` spline of
:mod:`skfem_mpm.reconstruct`, which is the oracle).

Per piece the particles are taken in sorted order and coincident
positions merged (their values averaged): knots x_0 < ... < x_(n-1),
values y_i, h_i = x_(i+1) - x_i, d_i = (y_(i+1) - y_i) / h_i. The slopes
s_i solve the tridiagonal system (de Boor, A Practical Guide to Splines,
1978, ch. IV)

    h_i s_(i-1) + 2 (h_(i-1) + h_i) s_i + h_(i-1) s_(i+1)
        = 3 (h_i d_(i-1) + h_(i-1) d_i),                    0 < i < n - 1,

closed by not-a-knot (s''' continuous at x_1 and x_(n-2)):

    h_1 s_0 + (h_0 + h_1) s_1 = ((h_0 + 2 (h_0 + h_1)) h_1 d_0 + h_0^2 d_1) / (h_0 + h_1)

and its mirror at the right end. n = 3: the parabola through the three
points (s_i = its derivative there), n = 2: the line, n = 1: the
constant. Between knots, with t = x - x_i, the cubic Hermite piece

    y_i + t (s_i + t (c_2 + t c_3)),  c_2 = (3 d_i - 2 s_i - s_(i+1)) / h_i,
    c_3 = (s_i + s_(i+1) - 2 d_i) / h_i^2,

extended beyond the end knots by the end pieces. The system is solved by
Gaussian elimination without pivoting (Thomas), one factorisation for all
value columns.
"""
import numpy as np
from numba import njit

__all__ = ["not_a_knot_spline"]


@njit(cache=True, error_model="numpy")
def _slopes(xm, ym, n, s):
    """The slopes s[:n] of the not-a-knot spline through (xm, ym)[:n]."""
    k = ym.shape[1]
    if n == 2:
        for c in range(k):
            s[0, c] = s[1, c] = (ym[1, c] - ym[0, c]) / (xm[1] - xm[0])
        return
    if n == 3:
        h0 = xm[1] - xm[0]
        h1 = xm[2] - xm[1]
        for c in range(k):
            d0 = (ym[1, c] - ym[0, c]) / h0
            d1 = (ym[2, c] - ym[1, c]) / h1
            curv = (d1 - d0) / (h0 + h1)
            s[0, c] = d0 - curv * h0
            s[1, c] = d0 + curv * h0
            s[2, c] = d1 + curv * h1
        return
    lower = np.empty(n)
    diag = np.empty(n)
    upper = np.empty(n)
    for i in range(1, n - 1):
        h_left = xm[i] - xm[i - 1]
        h_right = xm[i + 1] - xm[i]
        lower[i] = h_right
        diag[i] = 2.0 * (h_left + h_right)
        upper[i] = h_left
        for c in range(k):
            s[i, c] = 3.0 * (h_right * (ym[i, c] - ym[i - 1, c]) / h_left
                             + h_left * (ym[i + 1, c] - ym[i, c]) / h_right)
    h0 = xm[1] - xm[0]
    h1 = xm[2] - xm[1]
    span = xm[2] - xm[0]
    diag[0] = h1
    upper[0] = span
    for c in range(k):
        d0 = (ym[1, c] - ym[0, c]) / h0
        d1 = (ym[2, c] - ym[1, c]) / h1
        s[0, c] = ((h0 + 2.0 * span) * h1 * d0 + h0 * h0 * d1) / span
    ha = xm[n - 2] - xm[n - 3]
    hb = xm[n - 1] - xm[n - 2]
    span = xm[n - 1] - xm[n - 3]
    diag[n - 1] = ha
    lower[n - 1] = span
    for c in range(k):
        da = (ym[n - 2, c] - ym[n - 3, c]) / ha
        db = (ym[n - 1, c] - ym[n - 2, c]) / hb
        s[n - 1, c] = (hb * hb * da + (2.0 * span + hb) * ha * db) / span
    # forward elimination, back substitution
    for i in range(1, n):
        f = lower[i] / diag[i - 1]
        diag[i] -= f * upper[i - 1]
        for c in range(k):
            s[i, c] -= f * s[i - 1, c]
    for c in range(k):
        s[n - 1, c] /= diag[n - 1]
    for i in range(n - 2, -1, -1):
        for c in range(k):
            s[i, c] = (s[i, c] - upper[i] * s[i + 1, c]) / diag[i]


@njit(cache=True, error_model="numpy")
def not_a_knot_spline(x, values, order, piece_particles, piece_points, xg, out):
    """out[g] = the spline of each piece's particle ``values`` (n, k) at the
    piece's points xg[g] (see the module docstring); ``order``,
    ``piece_particles`` and ``piece_points`` as returned by
    :func:`skfem_mpm.kernels.gauss_rule.gauss_rule_1d`."""
    k = values.shape[1]
    npieces = piece_particles.shape[0] - 1
    largest = 0
    for j in range(npieces):
        largest = max(largest, piece_particles[j + 1] - piece_particles[j])
    xm = np.empty(largest)
    ym = np.empty((largest, k))
    s = np.empty((largest, k))
    for j in range(npieces):
        # merge coincident positions (sorted order): knots xm, mean values ym
        n = 0
        count = 0
        for i in range(piece_particles[j], piece_particles[j + 1]):
            q = order[i]
            if n > 0 and x[q] == xm[n - 1]:
                count += 1
                for c in range(k):
                    ym[n - 1, c] += values[q, c]
                continue
            if n > 0 and count > 1:
                for c in range(k):
                    ym[n - 1, c] /= count
            xm[n] = x[q]
            for c in range(k):
                ym[n, c] = values[q, c]
            n += 1
            count = 1
        if n > 0 and count > 1:
            for c in range(k):
                ym[n - 1, c] /= count
        g0, g1 = piece_points[j], piece_points[j + 1]
        if n == 1:
            for g in range(g0, g1):
                for c in range(k):
                    out[g, c] = ym[0, c]
            continue
        _slopes(xm, ym, n, s)
        i = 0
        for g in range(g0, g1):
            while i < n - 2 and xg[g] >= xm[i + 1]:
                i += 1
            h = xm[i + 1] - xm[i]
            t = xg[g] - xm[i]
            for c in range(k):
                d = (ym[i + 1, c] - ym[i, c]) / h
                c2 = (3.0 * d - 2.0 * s[i, c] - s[i + 1, c]) / h
                c3 = (s[i, c] + s[i + 1, c] - 2.0 * d) / (h * h)
                out[g, c] = ym[i, c] + t * (s[i, c] + t * (c2 + t * c3))
