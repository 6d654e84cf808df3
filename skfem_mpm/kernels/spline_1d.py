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
value columns. The divisions by h_i and by the pivots are taken once
(reciprocals), and each piece's c_2, c_3 once per knot interval, not per
point: a few ulp from the divisions written out, far below the 1e-12 of
the agreement with the NumPy spline.
"""
import numpy as np
from numba import njit

__all__ = ["not_a_knot_spline", "not_a_knot_spline_into", "spline_work_size"]


@njit(cache=True, error_model="numpy")
def _slopes(xm, ym, n, s, inv_h, work):
    """The slopes s[:n] of the not-a-knot spline through (xm, ym)[:n];
    inv_h[:n - 1] = 1 / h_i (written here); ``work`` (3, n) is work space."""
    k = ym.shape[1]
    for i in range(n - 1):
        inv_h[i] = 1.0 / (xm[i + 1] - xm[i])
    if n == 2:
        for c in range(k):
            s[0, c] = s[1, c] = (ym[1, c] - ym[0, c]) * inv_h[0]
        return
    if n == 3:
        h0 = xm[1] - xm[0]
        h1 = xm[2] - xm[1]
        inv_span = 1.0 / (h0 + h1)
        for c in range(k):
            d0 = (ym[1, c] - ym[0, c]) * inv_h[0]
            d1 = (ym[2, c] - ym[1, c]) * inv_h[1]
            curv = (d1 - d0) * inv_span
            s[0, c] = d0 - curv * h0
            s[1, c] = d0 + curv * h0
            s[2, c] = d1 + curv * h1
        return
    lower = work[0]
    diag = work[1]
    upper = work[2]
    for i in range(1, n - 1):
        h_left = xm[i] - xm[i - 1]
        h_right = xm[i + 1] - xm[i]
        lower[i] = h_right
        diag[i] = 2.0 * (h_left + h_right)
        upper[i] = h_left
        for c in range(k):
            s[i, c] = 3.0 * (h_right * ((ym[i, c] - ym[i - 1, c]) * inv_h[i - 1])
                             + h_left * ((ym[i + 1, c] - ym[i, c]) * inv_h[i]))
    h0 = xm[1] - xm[0]
    h1 = xm[2] - xm[1]
    span = xm[2] - xm[0]
    diag[0] = h1
    upper[0] = span
    for c in range(k):
        d0 = (ym[1, c] - ym[0, c]) * inv_h[0]
        d1 = (ym[2, c] - ym[1, c]) * inv_h[1]
        s[0, c] = ((h0 + 2.0 * span) * h1 * d0 + h0 * h0 * d1) / span
    ha = xm[n - 2] - xm[n - 3]
    hb = xm[n - 1] - xm[n - 2]
    span = xm[n - 1] - xm[n - 3]
    diag[n - 1] = ha
    lower[n - 1] = span
    for c in range(k):
        da = (ym[n - 2, c] - ym[n - 3, c]) * inv_h[n - 3]
        db = (ym[n - 1, c] - ym[n - 2, c]) * inv_h[n - 2]
        s[n - 1, c] = (hb * hb * da + (2.0 * span + hb) * ha * db) / span
    # forward elimination (diag becomes 1 / the pivots), back substitution
    diag[0] = 1.0 / diag[0]
    for i in range(1, n):
        f = lower[i] * diag[i - 1]
        diag[i] = 1.0 / (diag[i] - f * upper[i - 1])
        for c in range(k):
            s[i, c] -= f * s[i - 1, c]
    for c in range(k):
        s[n - 1, c] *= diag[n - 1]
    for i in range(n - 2, -1, -1):
        for c in range(k):
            s[i, c] = (s[i, c] - upper[i] * s[i + 1, c]) * diag[i]


@njit(cache=True, error_model="numpy")
def spline_work_size(largest, k):
    """The floats of the work space of :func:`not_a_knot_spline_into` for
    pieces of up to ``largest`` particles and ``k`` value columns."""
    return largest * (5 + 2 * k) + 3 * k


@njit(cache=True, error_model="numpy")
def _largest_piece(piece_particles):
    largest = 0
    for j in range(piece_particles.shape[0] - 1):
        largest = max(largest, piece_particles[j + 1] - piece_particles[j])
    return largest


@njit(cache=True, error_model="numpy")
def not_a_knot_spline(x, values, order, piece_particles, piece_points, xg, out):
    """out[g] = the spline of each piece's particle ``values`` (n, k) at the
    piece's points xg[g] (see the module docstring); ``order``,
    ``piece_particles`` and ``piece_points`` as returned by
    :func:`skfem_mpm.kernels.gauss_rule.gauss_rule_1d`."""
    work = np.empty(spline_work_size(_largest_piece(piece_particles), values.shape[1]))
    not_a_knot_spline_into(x, values, order, piece_particles, piece_points, xg, out, work)


@njit(cache=True, error_model="numpy")
def not_a_knot_spline_into(x, values, order, piece_particles, piece_points, xg, out, space):
    """:func:`not_a_knot_spline` in the work space ``space`` (at least
    :func:`spline_work_size` floats; a compiled run keeps one)."""
    k = values.shape[1]
    npieces = piece_particles.shape[0] - 1
    largest = _largest_piece(piece_particles)
    xm = space[:largest]
    at = largest
    ym = space[at:at + largest * k].reshape((largest, k))
    at += largest * k
    s = space[at:at + largest * k].reshape((largest, k))
    at += largest * k
    inv_h = space[at:at + largest]
    at += largest
    work = space[at:at + 3 * largest].reshape((3, largest))
    at += 3 * largest
    cubic = space[at:at + 3 * k].reshape((3, k))  # the current piece's d_i, c_2, c_3 per column
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
        _slopes(xm, ym, n, s, inv_h, work)
        i = -1
        for g in range(g0, g1):
            at = max(i, 0)
            while at < n - 2 and xg[g] >= xm[at + 1]:
                at += 1
            if at != i:  # the piece's coefficients, once per knot interval
                i = at
                r = inv_h[i]
                for c in range(k):
                    d = (ym[i + 1, c] - ym[i, c]) * r
                    cubic[0, c] = d
                    cubic[1, c] = (3.0 * d - 2.0 * s[i, c] - s[i + 1, c]) * r
                    cubic[2, c] = (s[i, c] + s[i + 1, c] - 2.0 * d) * (r * r)
            t = xg[g] - xm[i]
            for c in range(k):
                out[g, c] = ym[i, c] + t * (s[i, c] + t * (cubic[1, c] + t * cubic[2, c]))
