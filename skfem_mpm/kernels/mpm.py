"""Consistent mass and grid solves on tensor B-spline grids (1D to 3D),
and :class:`Kernels`, the compiled kernels bound to one grid.

The particle-grid transfers (p2g, g2p2g, g2p) are generated per dimension
and degree from one template (:mod:`skfem_mpm.kernels.scatter`,
:mod:`skfem_mpm.kernels.gather`); :class:`Kernels` binds them through
:class:`skfem_mpm.kernels.transfer.Transfers`.

The consistent mass kernels recompute the B-spline weights of each particle
instead of storing N (cheaper than the memory traffic of a stored N), and
scatter race-free: the particles are split into one contiguous block per
thread, each thread adds into its own copy of the stencil over the node
range its block touches, and the copies are summed over those ranges
(deterministic for a fixed thread count). The NumPy reference of every
kernel is the transfer-matrix code of :mod:`skfem_mpm.solve.steps`; the
tests compare the two to 1e-12.
"""
import math

import numpy as np
from numba import get_num_threads, njit, prange, types
from numba.extending import overload

from .band_factor import apply_band_factor
from .coverage_skip import coverage_holds, coverage_reach
from .fringe import apply_corrected
from .kronecker import apply_kronecker, apply_kronecker_axes
from .scatter import holders, node_hull
from .serial import for_threads
from .stencil import closed_axis_functions, extracted_axis_functions
from .tiny_mass import merged_lumped_solve_axes
from .transfer import Transfers
from .weights import FAST, IN_ORDER, extracted_functions, locate_axis_point

__all__ = ["Kernels"]


@njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def _axis(x, breaks, uniform, inv_h, C, p, w, dw):
    """Cell of x and the p + 1 values and d/dx of the axis' B-splines.

    Interior cells of a uniform axis (p <= e < cells - p) use the closed
    form of the uniform B-spline pieces; the others apply their extraction
    matrix to the Bernstein polynomials."""
    e = locate_axis_point(x, breaks, uniform, inv_h)
    ncells = breaks.shape[0] - 1
    if uniform and e >= p and e < ncells - p:
        xi = (x - breaks[e]) * inv_h
        r = 1.0 - xi
        if p == 2:
            w[0] = 0.5 * r * r
            w[1] = 0.5 + xi * r
            w[2] = 0.5 * xi * xi
            dw[0] = -r * inv_h
            dw[1] = (1.0 - 2.0 * xi) * inv_h
            dw[2] = xi * inv_h
        elif p == 3:
            xi2 = xi * xi
            xi3 = xi2 * xi
            w[0] = r * r * r / 6.0
            w[1] = (3.0 * xi3 - 6.0 * xi2 + 4.0) / 6.0
            w[2] = (-3.0 * xi3 + 3.0 * xi2 + 3.0 * xi + 1.0) / 6.0
            w[3] = xi3 / 6.0
            dw[0] = -0.5 * r * r * inv_h
            dw[1] = (1.5 * xi2 - 2.0 * xi) * inv_h
            dw[2] = (-1.5 * xi2 + xi + 0.5) * inv_h
            dw[3] = 0.5 * xi2 * inv_h
        else:
            w[0] = r
            w[1] = xi
            dw[0] = -inv_h
            dw[1] = inv_h
        return e
    extracted_functions(x, e, breaks, C, p, w, dw)
    return e


# A scatter kernel adds into its thread's copy of the grid and records the
# node range it touched (touched[t] = first, last + 1); the copy is zero
# outside that range. The next call zeros only that range before adding,
# and the reduction sums each node over the copies whose range holds it.
# Threads own contiguous particle blocks, so on sorted particles each range
# is a fraction of the grid (half of it in 1D on two threads).
@njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def _clear_touched(g, touched, t):
    """Zero thread t's copy g on the range the previous call touched."""
    g[touched[t, 0]:touched[t, 1], :] = 0.0


@njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def _take(copies, threads, count, k, c):
    """sum of copies[t, k, c] over the given threads."""
    s = 0.0
    for j in range(count):
        s += copies[threads[j], k, c]
    return s


# ------------------------------------------------------------ consistent mass
@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def consistent_1d(x, m, bx, ux, ihx, Cx, p, mass_copies, stiff_copies, touched):
    """Upper half of the consistent mass, M_(k, k+d) = sum m_p N_k N_(k+d)
    for d = 0..p (column d), and sum m_p (dN_k/dx)^2 per dof (the fast-dof
    guard's stiffness weights), into per-thread copies over the node range
    each thread touches (``touched``, as the scatter kernels).
    :func:`reduce_stencil` sums them and mirrors the rest. Quadratic and
    cubic interior particles of a uniform axis keep their weights in
    registers (:func:`~skfem_mpm.kernels.stencil.closed_axis_functions`,
    the values the transfer kernels take there; the same sums in the same
    order)."""
    n = x.shape[0]
    nt = mass_copies.shape[0]
    closed = (p == 2 or p == 3) and ux
    x0, ncx = bx[0], bx.shape[0] - 1
    for t in prange(nt):
        M = mass_copies[t]
        K = stiff_copies[t]
        _clear_touched(M, touched, t)
        K[touched[t, 0]:touched[t, 1]] = 0.0
        first = M.shape[0]
        last = 0
        w = np.empty(4)
        dw = np.empty(4)
        lo = t * n // nt
        hi = (t + 1) * n // nt
        for i in range(lo, hi):
            mi = m[i]
            if closed:
                interior, e, w0, w1, w2, w3, d0, d1, d2, d3 = closed_axis_functions(
                    x[i, 0], x0, ncx, ux, ihx, p)
                if interior and p == 2:
                    first = min(first, e)
                    last = max(last, e + 3)
                    K[e] += mi * d0 * d0
                    m0 = mi * w0
                    M[e, 0] += m0 * w0
                    M[e, 1] += m0 * w1
                    M[e, 2] += m0 * w2
                    K[e + 1] += mi * d1 * d1
                    m1 = mi * w1
                    M[e + 1, 0] += m1 * w1
                    M[e + 1, 1] += m1 * w2
                    K[e + 2] += mi * d2 * d2
                    M[e + 2, 0] += mi * w2 * w2
                    continue
                if interior:  # cubic
                    first = min(first, e)
                    last = max(last, e + 4)
                    K[e] += mi * d0 * d0
                    m0 = mi * w0
                    M[e, 0] += m0 * w0
                    M[e, 1] += m0 * w1
                    M[e, 2] += m0 * w2
                    M[e, 3] += m0 * w3
                    K[e + 1] += mi * d1 * d1
                    m1 = mi * w1
                    M[e + 1, 0] += m1 * w1
                    M[e + 1, 1] += m1 * w2
                    M[e + 1, 2] += m1 * w3
                    K[e + 2] += mi * d2 * d2
                    m2 = mi * w2
                    M[e + 2, 0] += m2 * w2
                    M[e + 2, 1] += m2 * w3
                    K[e + 3] += mi * d3 * d3
                    M[e + 3, 0] += mi * w3 * w3
                    continue
            e = _axis(x[i, 0], bx, ux, ihx, Cx, p, w, dw)
            first = min(first, e)
            last = max(last, e + p + 1)
            for a in range(p + 1):
                K[e + a] += mi * dw[a] * dw[a]
                wa = mi * w[a]
                for a2 in range(a, p + 1):
                    M[e + a, a2 - a] += wa * w[a2]
        touched[t, 0] = first
        touched[t, 1] = last


@njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def _mass_pairs(M, K, k, a, b, wx, dx, wy, dy, mi, p, width, nbx):
    """Node (a, b) of a particle's tensor stencil (weights wx, wy): its
    stiffness weight and its products with the nodes after it (upper half,
    slot (b2 - b + p) width + a2 - a + p - centre)."""
    gx = dx[a] * wy[b]
    gy = wx[a] * dy[b]
    K[k] += mi * (gx * gx + gy * gy)
    wab = mi * wx[a] * wy[b]
    for a2 in range(a, p + 1):
        M[k, a2 - a] += wab * wx[a2] * wy[b]
    for b2 in range(b + 1, p + 1):
        wb2 = wab * wy[b2]
        base = (b2 - b) * width - a
        for a2 in range(p + 1):
            M[k, base + a2] += wb2 * wx[a2]


# Quadratic particles of one cell share its 3 x 3 nodes, so a run
# of them (sorted particles come in runs) is summed in a small window and
# written once per run, as in the 1D kernels. By the tensor structure,
# N_(a,b) N_(a2,b2) = (wx_a wx_a2)(wy_b wy_b2): the window holds the 6 x 6
# sums S[y-pair, x-pair] = sum m_p (wy_b wy_b2)(wx_a wx_a2) over the
# symmetric index pairs (0,0) (0,1) (0,2) (1,1) (1,2) (2,2) (_PAIR), and
# the 9 stiffness weights.
_PAIR = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]])


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def consistent_2d(x, m, bx, by, ux, uy, ihx, ihy, Cx, Cy, p, nbx, mass_copies, stiff_copies,
                  touched):
    """Upper half of the 2D stencil of the consistent mass (the slots from
    the centre on, offsets (da, db) with db > 0 or db = 0 <= da; slot
    (db + p)(2p + 1) + da + p - centre) and the per-dof sum m_p |grad N_k|^2.
    Per-thread copies over touched node ranges, as :func:`consistent_1d`;
    :func:`reduce_stencil` mirrors the lower half (M is symmetric).
    Quadratic particles are summed per run of a cell first (the window
    above, added into M and K when the run ends: at a particle of another
    cell, and after the last particle; interior cells of uniform axes with
    the closed form of their weights). The window's flush is written in the
    particle loop itself (a function of the arrays, inlined or called, cost
    the serial copy reference counts or a call per run)."""
    n = x.shape[0]
    nt = mass_copies.shape[0]
    width = 2 * p + 1
    quadratic = p == 2
    x0, ncx, y0, ncy = bx[0], bx.shape[0] - 1, by[0], by.shape[0] - 1
    for t in prange(nt):
        M = mass_copies[t]
        K = stiff_copies[t]
        _clear_touched(M, touched, t)
        K[touched[t, 0]:touched[t, 1]] = 0.0
        first = M.shape[0]
        last = 0
        wx = np.empty(4)
        dx = np.empty(4)
        wy = np.empty(4)
        dy = np.empty(4)
        S = np.zeros(36)  # the run window
        Kw = np.zeros(9)
        X = np.empty(6)
        run_x = -1
        run_y = -1
        lo = t * n // nt
        hi = (t + 1) * n // nt
        wx0 = wx1 = wx2 = dx0 = dx1 = dx2 = wy0 = wy1 = wy2 = dy0 = dy1 = dy2 = mi = 0.0
        for i in range(lo, hi + 1):  # (i = hi: the end, flush the last window)
            end = i == hi
            ex = -1
            ey = -1
            if not end:
                mi = m[i]
                if not quadratic:
                    ex = _axis(x[i, 0], bx, ux, ihx, Cx, p, wx, dx)
                    ey = _axis(x[i, 1], by, uy, ihy, Cy, p, wy, dy)
                    first = min(first, ey * nbx + ex)
                    last = max(last, (ey + p) * nbx + ex + p + 1)
                    for b in range(p + 1):
                        for a in range(p + 1):
                            _mass_pairs(M, K, (ey + b) * nbx + ex + a, a, b, wx, dx, wy, dy, mi,
                                        p, width, nbx)
                    continue
                in_x, ex, wx0, wx1, wx2, _, dx0, dx1, dx2, _ = closed_axis_functions(
                    x[i, 0], x0, ncx, ux, ihx, 2)
                in_y, ey, wy0, wy1, wy2, _, dy0, dy1, dy2, _ = closed_axis_functions(
                    x[i, 1], y0, ncy, uy, ihy, 2)
                if not in_x:  # (scalars from a call: see skfem_mpm.kernels.stencil)
                    ex, wx0, wx1, wx2, _, dx0, dx1, dx2, _ = extracted_axis_functions(
                        x[i, 0], bx, ux, ihx, Cx, 2)
                if not in_y:
                    ey, wy0, wy1, wy2, _, dy0, dy1, dy2, _ = extracted_axis_functions(
                        x[i, 1], by, uy, ihy, Cy, 2)
            if ex != run_x or ey != run_y:
                if run_x >= 0:  # the flush: the window into M (width 5, slots as
                    for b in range(3):  # _mass_pairs) and K, then cleared
                        for a in range(3):
                            k = (run_y + b) * nbx + run_x + a
                            K[k] += Kw[3 * b + a]
                            yb = 6 * _PAIR[b, b]
                            for a2 in range(a, 3):
                                M[k, a2 - a] += S[yb + _PAIR[a, a2]]
                            for b2 in range(b + 1, 3):
                                yb2 = 6 * _PAIR[b, b2]
                                base = (b2 - b) * 5 - a
                                for a2 in range(3):
                                    M[k, base + a2] += S[yb2 + _PAIR[a, a2]]
                    S[:] = 0.0
                    Kw[:] = 0.0
                if end:
                    break
                run_x = ex
                run_y = ey
                first = min(first, ey * nbx + ex)
                last = max(last, (ey + 2) * nbx + ex + 3)
            elif end:  # (no quadratic particle)
                break
            X[0] = wx0 * wx0
            X[1] = wx0 * wx1
            X[2] = wx0 * wx2
            X[3] = wx1 * wx1
            X[4] = wx1 * wx2
            X[5] = wx2 * wx2
            ys = (mi * wy0 * wy0, mi * wy0 * wy1, mi * wy0 * wy2, mi * wy1 * wy1,
                  mi * wy1 * wy2, mi * wy2 * wy2)
            for j in range(6):
                yj = ys[j]
                for q in range(6):
                    S[6 * j + q] += yj * X[q]
            # m |grad N_(a,b)|^2 = m (dx_a^2 wy_b^2 + wx_a^2 dy_b^2)
            gx = (mi * dx0 * dx0, mi * dx1 * dx1, mi * dx2 * dx2)
            sx = (mi * X[0], mi * X[3], mi * X[5])
            vy = (wy0 * wy0, wy1 * wy1, wy2 * wy2)
            hy = (dy0 * dy0, dy1 * dy1, dy2 * dy2)
            for b in range(3):
                for a in range(3):
                    Kw[3 * b + a] += gx[a] * vy[b] + sx[a] * hy[b]
        touched[t, 0] = first
        touched[t, 1] = last


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def consistent_cells_2d(x, m, ncells, k, bx, by, ux, uy, ihx, ihy, Cx, Cy, p, nbx, mass_copies,
                        stiff_copies, touched):
    """:func:`consistent_2d` (the same stencil slots and per-dof sums
    m |grad N_k|^2, into per-thread copies) of points whose first
    ``ncells`` k x k blocks are tensor Gauss rules of whole cells (block c:
    point (a, b) at c k^2 + a + k b, a along x; as
    :func:`~skfem_mpm.kernels.gauss_rule.gauss_rule_cells` orders them),
    the points after them taken one by one. On a block the sums factorise
    per axis (sum factorisation, Orszag 1980; Melenk, Gerdes & Schwab 2001
    for the mass matrix): with the weights w^x_a(x_i), w^y_b(y_j) of its k
    x- and k y-coordinates,

        M_(a,b),(a2,b2) = sum_j w^y_b(y_j) w^y_b2(y_j) T_j[a, a2],
        T_j[a, a2] = sum_i m_ij w^x_a(x_i) w^x_a2(x_i),

        sum m |grad N_(a,b)|^2 = sum_j (D_j[a] w^y_b(y_j)^2 + T_j[a, a] (dw^y_b(y_j))^2),
        D_j[a] = sum_i m_ij (dw^x_a(x_i))^2,

    2k evaluations of the axis functions instead of 2k^2 and (for p = 2,
    k = 4) about a third of the products."""
    nt = mass_copies.shape[0]
    n = x.shape[0]
    kk = k * k
    q = p + 1
    width = 2 * p + 1
    rest = n - ncells * kk
    x0, ncx, y0, ncy = bx[0], bx.shape[0] - 1, by[0], by.shape[0] - 1
    for t in prange(nt):
        M = mass_copies[t]
        K = stiff_copies[t]
        _clear_touched(M, touched, t)
        K[touched[t, 0]:touched[t, 1]] = 0.0
        first = M.shape[0]
        last = 0
        wx = np.zeros((k, 4))
        dx = np.zeros((k, 4))
        wy = np.zeros((k, 4))
        dy = np.zeros((k, 4))
        T = np.zeros((4, 4))
        D = np.zeros(4)
        W = np.zeros((4, 4, 4, 4))  # W[b, b2, a, a2] of the cell, b2 >= b
        Kc = np.zeros((4, 4))  # [b, a]
        for c in range(t * ncells // nt, (t + 1) * ncells // nt):
            g0 = c * kk
            ex = 0
            ey = 0
            for i in range(k):
                closed, e, v0, v1, v2, v3, h0, h1, h2, h3 = closed_axis_functions(
                    x[g0 + i, 0], x0, ncx, ux, ihx, p)
                if not closed:
                    e, v0, v1, v2, v3, h0, h1, h2, h3 = extracted_axis_functions(
                        x[g0 + i, 0], bx, ux, ihx, Cx, p)
                ex = e
                wx[i, 0], wx[i, 1], wx[i, 2], wx[i, 3] = v0, v1, v2, v3
                dx[i, 0], dx[i, 1], dx[i, 2], dx[i, 3] = h0, h1, h2, h3
                closed, e, v0, v1, v2, v3, h0, h1, h2, h3 = closed_axis_functions(
                    x[g0 + k * i, 1], y0, ncy, uy, ihy, p)
                if not closed:
                    e, v0, v1, v2, v3, h0, h1, h2, h3 = extracted_axis_functions(
                        x[g0 + k * i, 1], by, uy, ihy, Cy, p)
                ey = e
                wy[i, 0], wy[i, 1], wy[i, 2], wy[i, 3] = v0, v1, v2, v3
                dy[i, 0], dy[i, 1], dy[i, 2], dy[i, 3] = h0, h1, h2, h3
            for b in range(q):
                for b2 in range(q):
                    for a in range(q):
                        for a2 in range(q):
                            W[b, b2, a, a2] = 0.0
                for a in range(q):
                    Kc[b, a] = 0.0
            for j in range(k):
                for a in range(q):
                    D[a] = 0.0
                    for a2 in range(q):
                        T[a, a2] = 0.0
                for i in range(k):
                    mi = m[g0 + i + k * j]
                    for a in range(q):
                        wa = mi * wx[i, a]
                        D[a] += mi * dx[i, a] * dx[i, a]
                        for a2 in range(a, q):
                            T[a, a2] += wa * wx[i, a2]
                for a in range(q):
                    for a2 in range(a):
                        T[a, a2] = T[a2, a]
                for b in range(q):
                    yb = wy[j, b]
                    gb = dy[j, b] * dy[j, b]
                    for a in range(q):
                        Kc[b, a] += D[a] * (yb * yb) + T[a, a] * gb
                    for b2 in range(b, q):
                        yy = yb * wy[j, b2]
                        for a in range(q):
                            for a2 in range(q):
                                W[b, b2, a, a2] += yy * T[a, a2]
            first = min(first, ey * nbx + ex)
            last = max(last, (ey + p) * nbx + ex + p + 1)
            for b in range(q):
                for a in range(q):
                    kd = (ey + b) * nbx + ex + a
                    K[kd] += Kc[b, a]
                    for a2 in range(a, q):
                        M[kd, a2 - a] += W[b, b, a, a2]
                    for b2 in range(b + 1, q):
                        base = (b2 - b) * width - a
                        for a2 in range(q):
                            M[kd, base + a2] += W[b, b2, a, a2]
        w0 = np.zeros(4)
        d0 = np.zeros(4)
        w1 = np.zeros(4)
        d1 = np.zeros(4)
        for i in range(ncells * kk + t * rest // nt, ncells * kk + (t + 1) * rest // nt):
            closed, e, v0, v1, v2, v3, h0, h1, h2, h3 = closed_axis_functions(
                x[i, 0], x0, ncx, ux, ihx, p)
            if not closed:
                e, v0, v1, v2, v3, h0, h1, h2, h3 = extracted_axis_functions(
                    x[i, 0], bx, ux, ihx, Cx, p)
            ex = e
            w0[0], w0[1], w0[2], w0[3] = v0, v1, v2, v3
            d0[0], d0[1], d0[2], d0[3] = h0, h1, h2, h3
            closed, e, v0, v1, v2, v3, h0, h1, h2, h3 = closed_axis_functions(
                x[i, 1], y0, ncy, uy, ihy, p)
            if not closed:
                e, v0, v1, v2, v3, h0, h1, h2, h3 = extracted_axis_functions(
                    x[i, 1], by, uy, ihy, Cy, p)
            ey = e
            w1[0], w1[1], w1[2], w1[3] = v0, v1, v2, v3
            d1[0], d1[1], d1[2], d1[3] = h0, h1, h2, h3
            first = min(first, ey * nbx + ex)
            last = max(last, (ey + p) * nbx + ex + p + 1)
            for b in range(q):
                for a in range(q):
                    _mass_pairs(M, K, (ey + b) * nbx + ex + a, a, b, w0, d0, w1, d1, m[i], p,
                                width, nbx)
        touched[t, 0] = first
        touched[t, 1] = last


@njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def _tensor_point(x, i, b0, u0, ih0, C0, b1, u1, ih1, C1, b2, u2, ih2, C2, p, nbx, nby, w, dw):
    """The first of point i's (p + 1)^dim nodes, its axes' B-spline values
    and derivatives in w[d], dw[d] (:func:`_axis`; dim = x.shape[1])."""
    base = 0
    stride = 1
    for d in range(x.shape[1]):
        if d == 0:
            e = _axis(x[i, 0], b0, u0, ih0, C0, p, w[0], dw[0])
        elif d == 1:
            e = _axis(x[i, 1], b1, u1, ih1, C1, p, w[1], dw[1])
        else:
            e = _axis(x[i, 2], b2, u2, ih2, C2, p, w[2], dw[2])
        base += e * stride
        stride *= nbx if d == 0 else nby
    return base


@njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def _tensor_node(q, w, dw, p, nbx, nby, dim):
    """(N_q, |grad N_q|^2, node offset, stencil slot offset) of node q of a
    point's (p + 1)^dim nodes (see :func:`consistent_axes`)."""
    width = 2 * p + 1
    rest = q
    value = 1.0
    node = 0
    offset = 0
    stride = 1
    power = 1
    for d in range(dim):
        a = rest % (p + 1)
        rest //= p + 1
        value *= w[d, a]
        node += a * stride
        offset += a * power
        stride *= nbx if d == 0 else nby
        power *= width
    grad2 = 0.0
    for c in range(dim):
        rest = q
        g = 1.0
        for d in range(dim):
            a = rest % (p + 1)
            rest //= p + 1
            g *= dw[d, a] if d == c else w[d, a]
        grad2 += g * g
    return value, grad2, node, offset


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def consistent_axes(x, m, b0, u0, ih0, C0, b1, u1, ih1, C1, b2, u2, ih2, C2, p, nbx, nby,
                    mass_copies, stiff_copies, touched):
    """The stencil of the consistent mass on a tensor grid of any dimension
    dim = x.shape[1] (axis d: breakpoints b_d, uniform u_d, cells per unit
    length ih_d, extraction C_d, the fields of an Axis record of
    :mod:`skfem_mpm.kernels.records`; the axes from dim on are not read), as :func:`consistent_1d` and
    :func:`consistent_2d`: the upper half of the stencil (slots from the
    centre on) and the per-dof sum m_p |grad N_k|^2, into per-thread copies
    over touched node ranges.

    Stencil slot of the offset (d_0, ..., d_(dim-1)) between two dofs:
    s = sum_i (d_i + p) w^i, w = 2p + 1, centre (w^dim - 1) / 2; the upper
    half holds column s - centre. Node q of a particle's (p + 1)^dim nodes
    has digits a_i (axis 0 fastest), N_q = prod_i w^i_(a_i),
    dN_q/dx_c = g^c_(a_c) prod_(i != c) w^i_(a_i) (Piegl & Tiller 1997,
    sec. 3.4); the pair (q, q2) belongs to the upper half exactly when
    q2 >= q (both orders compare the highest differing digit)."""
    n = x.shape[0]
    dim = x.shape[1]
    nt = mass_copies.shape[0]
    nq = (p + 1) ** dim
    for t in prange(nt):
        M = mass_copies[t]
        K = stiff_copies[t]
        _clear_touched(M, touched, t)
        K[touched[t, 0]:touched[t, 1]] = 0.0
        first = M.shape[0]
        last = 0
        w = np.zeros((3, 4))
        dw = np.zeros((3, 4))
        N = np.empty(nq)
        dof = np.empty(nq, dtype=np.int64)
        slot = np.empty(nq, dtype=np.int64)
        lo = t * n // nt
        hi = (t + 1) * n // nt
        for i in range(lo, hi):
            mi = m[i]
            base = _tensor_point(x, i, b0, u0, ih0, C0, b1, u1, ih1, C1, b2, u2, ih2, C2, p,
                                 nbx, nby, w, dw)
            for q in range(nq):
                value, grad2, node, offset = _tensor_node(q, w, dw, p, nbx, nby, dim)
                N[q] = value
                dof[q] = base + node
                slot[q] = offset
                K[base + node] += mi * grad2
            for q in range(nq):
                k = dof[q]
                mq = mi * N[q]
                for q2 in range(q, nq):
                    M[k, slot[q2] - slot[q]] += mq * N[q2]
            first = min(first, base)
            last = max(last, dof[nq - 1] + 1)
        touched[t, 0] = first
        touched[t, 1] = last


@njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def _copy_rows(mass_copies, stiff_copies, touched, lo, hi, M, K):
    """:func:`reduce_stencil`'s sums of rows lo..hi-1 of the one copy 0:
    its entries where its touched range holds the row (as the holders'
    path copies them: 0 + x is x), else 0; a zero row's other entries 0."""
    nh = mass_copies.shape[2]
    centre = nh - 1
    t0 = touched[0, 0]
    t1 = touched[0, 1]
    for k in range(lo, hi):
        held = t0 <= k and k < t1
        K[k] = stiff_copies[0, k] if held else 0.0
        diagonal = mass_copies[0, k, 0] if held else 0.0
        M[k, centre] = diagonal
        if diagonal == 0.0:  # a zero row (see reduce_stencil)
            for s in range(1, nh):
                M[k, centre + s] = 0.0
            continue
        for s in range(1, nh):
            M[k, centre + s] = mass_copies[0, k, s]


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def reduce_stencil(mass_copies, stiff_copies, touched, lo, hi, p, nbx, nby, dim, M, K):
    """Rows lo..hi-1 (the union of the touched ranges; the caller keeps the
    other rows zero): sum the per-thread upper halves into M[:, centre:] and
    K, then mirror the lower half, M[k, s] = M[j, ns - 1 - s] (j the dof at
    slot s of k; a row outside lo..hi-1 has no entry pairing it with k).

    A row whose diagonal M_kk = sum_p m_p N_k(x_p)^2 is 0 is zero: with
    m_p >= 0 each term is, so m_p N_k(x_p) = 0 at every particle and
    M_kj = sum_p m_p N_k(x_p) N_j(x_p) = 0 (the stencil is a Gram matrix).
    Its other entries are written 0 without being summed or mirrored (the
    rows of the touched ranges beside a body are mostly such rows); K_k is
    summed still (for p = 1 a particle on the edge of N_k's support has
    N_k = 0 but grad N_k != 0)."""
    nt, nk, nh = mass_copies.shape
    ns = 2 * nh - 1
    centre = nh - 1
    if nt == 1:  # one copy (the serial kernels): without the holders' lists
        _copy_rows(mass_copies, stiff_copies, touched, lo, hi, M, K)
    for r in prange(nt if nt > 1 else 0):
        cuts, members, counts = holders(touched, lo + r * (hi - lo) // nt,
                                          lo + (r + 1) * (hi - lo) // nt)
        for j in range(cuts.shape[0] - 1):
            threads = members[j]
            count = counts[j]
            if count == 1:  # one copy holds these rows: copied (0 + x is x)
                t0 = threads[0]
                for k in range(cuts[j], cuts[j + 1]):
                    K[k] = stiff_copies[t0, k]
                    diagonal = mass_copies[t0, k, 0]
                    M[k, centre] = diagonal
                    if diagonal == 0.0:  # a zero row (see above)
                        for s in range(1, nh):
                            M[k, centre + s] = 0.0
                        continue
                    for s in range(1, nh):
                        M[k, centre + s] = mass_copies[t0, k, s]
                continue
            for k in range(cuts[j], cuts[j + 1]):
                sk = 0.0
                for i in range(count):
                    sk += stiff_copies[threads[i], k]
                K[k] = sk
                diagonal = _take(mass_copies, threads, count, k, 0)
                M[k, centre] = diagonal
                if diagonal == 0.0:  # a zero row (see above)
                    for s in range(1, nh):
                        M[k, centre + s] = 0.0
                    continue
                for s in range(1, nh):
                    M[k, centre + s] = _take(mass_copies, threads, count, k, s)
    nbz = M.shape[0] // (nbx * nby)
    offsets = _slot_offsets(p, dim, ns)
    step = np.empty(ns, dtype=np.int64)  # each slot's dof offset (rows p or more from the edges)
    for s in range(ns):
        step[s] = (offsets[s, 2] * nby + offsets[s, 1]) * nbx + offsets[s, 0]
    pb = p if dim >= 2 else 0
    pc = p if dim == 3 else 0
    for k in prange(lo, hi):
        if M[k, centre] == 0.0:  # a zero row: no entry to mirror
            for s in range(centre):
                M[k, s] = 0.0
            continue
        a, b, c = _row_indices(k, nbx, nby, dim)
        if p <= a < nbx - p and pb <= b < nby - pb and pc <= c < nbz - pc:
            for s in range(centre):  # every slot inside the grid
                M[k, s] = M[k + step[s], ns - 1 - s]
            continue
        for s in range(centre):
            j = _offset_dof(a, b, c, offsets, s, nbx, nby, nbz)
            M[k, s] = M[j, ns - 1 - s] if j >= 0 else 0.0


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def lumped_solve(mass, rhs, gravity, constrained, values, has_values, out):
    """out = rhs / m + gravity on free dofs with mass, the constraint
    values (or 0) on constrained ones, 0 on empty dofs."""
    nk, dim = rhs.shape
    for k in prange(nk):
        mk = mass[k]
        for c in range(dim):
            if constrained[k, c]:
                out[k, c] = values[k, c] if has_values else 0.0
            elif mk > 0.0:
                out[k, c] = rhs[k, c] / mk + gravity[c]
            else:
                out[k, c] = 0.0


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def usl_grid(mass, momentum, force, gravity, constrained, v_values, a_values, has_values,
             vdt, a, v_new, occupied):
    """The USL/CD grid step in one pass: a = f / m + g, v_new = P / m + vdt a
    on free dofs with mass; constraint values (or 0) on constrained dofs; 0
    on empty dofs. Written on the nodes of the two ranges of ``occupied``
    (see :func:`skfem_mpm.kernels.scatter.reduce_fields`: the mass is zero
    outside the first, a and v_new outside both hold zeros or constraint
    values), after which the second is the first; ``occupied`` = (0, nk,
    0, nk) writes every node."""
    nk, dim = force.shape
    lo, hi = node_hull(occupied[0], occupied[1], occupied[2], occupied[3])
    for k in prange(lo, hi):
        mk = mass[k]
        for c in range(dim):
            if constrained[k, c]:
                vo = v_values[k, c] if has_values else 0.0
                ak = a_values[k, c] if has_values else 0.0
            elif mk > 0.0:
                vo = momentum[k, c] / mk
                ak = force[k, c] / mk + gravity[c]
            else:
                vo = 0.0
                ak = 0.0
            a[k, c] = ak
            v_new[k, c] = vo + vdt * ak
    occupied[2] = occupied[0]
    occupied[3] = occupied[1]


WORK_BLOCKS = 16
"""Fixed blocks of dofs of :func:`mass_weighted_sum` (not the thread count:
the sum has the same bits however many threads run it)."""


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def mass_weighted_sum(mass, v, out):
    """out[c] = sum_k m_k v_k,c, summed over WORK_BLOCKS fixed blocks of
    dofs and then block by block (compiled: NumPy's BLAS product would leave
    its threads spinning against the kernels' on a small machine)."""
    nk, dim = v.shape
    partial = np.zeros((WORK_BLOCKS, dim))
    for b in prange(WORK_BLOCKS):
        for k in range(b * nk // WORK_BLOCKS, (b + 1) * nk // WORK_BLOCKS):
            for c in range(dim):
                partial[b, c] += mass[k] * v[k, c]
    for c in range(dim):
        s = 0.0
        for b in range(WORK_BLOCKS):
            s += partial[b, c]
        out[c] = s


@njit(cache=True, error_model="numpy")
def work_increment(sums, dt, gravity):
    """The work of gravity in one step, sum_c dt s_c g_c, from the sums
    s = sum_k m_k v_k of :func:`mass_weighted_sum` (see
    :meth:`Kernels.gravity_work`)."""
    w = 0.0
    for c in range(sums.shape[0]):
        w += dt * sums[c] * gravity[c]
    return w


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def small_mass_1d(mass, p, tol, small):
    count = 0
    nk = mass.shape[0]
    for k in prange(nk):
        mk = mass[k]
        small[k] = False
        if mk <= 0.0:
            continue
        big = 0.0
        for j in range(max(0, k - p), min(nk, k + p + 1)):
            if mass[j] > big:
                big = mass[j]
        if mk < tol * big:
            small[k] = True
            count += 1
    return count


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def small_mass_2d(mass, nbx, nby, p, tol, small):
    """small[k] = 0 < m_k < tol * max of m over the dofs sharing a cell with k
    (index offsets -p..p per axis); returns their count."""
    count = 0
    for k in prange(nbx * nby):
        mk = mass[k]
        small[k] = False
        if mk <= 0.0:
            continue
        a = k % nbx
        b = k // nbx
        big = 0.0
        for db in range(-p, p + 1):
            bb = b + db
            if bb < 0 or bb >= nby:
                continue
            for da in range(-p, p + 1):
                aa = a + da
                if aa < 0 or aa >= nbx:
                    continue
                mm = mass[bb * nbx + aa]
                if mm > big:
                    big = mm
        if mk < tol * big:
            small[k] = True
            count += 1
    return count


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def small_mass_axes(mass, nbx, nby, nbz, p, tol, small):
    """small[k] = 0 < m_k < tol * max of m over the dofs sharing a cell with
    k (index offsets -p..p per axis) on a tensor grid of nbx x nby x nbz
    functions, any dimension (1D: nby = nbz = 1; 2D: nbz = 1), dof
    k = a + nbx (b + nby c); returns their count. Same rule and result as
    :func:`small_mass_1d` and :func:`small_mass_2d` (which the compiled
    loop keeps: its serial copies need a body without calls)."""
    count = 0
    for k in prange(nbx * nby * nbz):
        mk = mass[k]
        small[k] = False
        if mk <= 0.0:
            continue
        a = k % nbx
        b = (k // nbx) % nby
        c = k // (nbx * nby)
        big = 0.0
        for cc in range(max(0, c - p), min(nbz, c + p + 1)):
            for bb in range(max(0, b - p), min(nby, b + p + 1)):
                row = (cc * nby + bb) * nbx
                for aa in range(max(0, a - p), min(nbx, a + p + 1)):
                    mm = mass[row + aa]
                    if mm > big:
                        big = mm
        if mk < tol * big:
            small[k] = True
            count += 1
    return count


class Kernels:
    """The compiled kernels bound to one spline grid and the run's block
    count (the number of numba threads when bound): the particle-grid
    transfers (:class:`skfem_mpm.kernels.transfer.Transfers`, generated per
    dimension and degree), the consistent mass stencil and the lumped and
    tiny-mass grid solves.

    ``parallel`` False: every kernel is its serial copy (same blocks, same
    bits; see :mod:`skfem_mpm.kernels.serial`), for runs too small for
    threads; no parallel kernel is compiled for them."""

    def __init__(self, grid, parallel=True):
        self.grid = grid
        self.dim = grid.dim
        self.p = grid.degree
        self.parallel = bool(parallel)
        self._threaded = {}
        self.nthreads = get_num_threads()
        self.transfers = Transfers(grid, self.nthreads, parallel=self.parallel)
        b = grid.breakpoints
        self.args = []
        for axis in range(grid.dim):
            u = b[axis]
            self.args.append((u, bool(grid._uniform[axis]), (u.size - 1) / (u[-1] - u[0]),
                              grid.extraction[axis]))
        self.ndofs = grid.ndofs
        self.nbx = grid.basis_per_axis[0]
        self._scratch = {}
        self._small = np.empty(grid.ndofs, dtype=np.bool_)
        self._coverage = None  # particle_coverage's copies, touched ranges and sums

    def kernel(self, kernel):
        """``kernel`` as this run calls it: itself, or its serial copy."""
        bound = self._threaded.get(kernel)
        if bound is None:
            bound = self._threaded[kernel] = for_threads(kernel, self.parallel)
        return bound

    def p2g(self, particles, fext, cells=None):
        """(lumped mass (dofs,), momentum (dofs, dim), force (dofs, dim)),
        see :mod:`skfem_mpm.kernels.scatter`; reused by the next call
        (``cells``: Transfers.p2g's)."""
        return self.transfers.p2g(particles, fext, cells)

    def g2p2g(self, particles, grid_a, dt, v_new, cells=None):
        """MUSL: v_new = v + dt N a and the grid momentum of m v_new."""
        return self.transfers.g2p2g(particles, grid_a, dt, v_new, cells)

    def g2p(self, particles, grid_a, grid_v, dt, vfactor, flip, fused, material, new, L_out,
            acc_out=None):
        """Particle update into the arrays of ``new`` (a Particles object),
        see :mod:`skfem_mpm.kernels.gather`; with ``fused``, the linear
        elastic ``material``'s stress update (1D: sigma += E dt L); returns
        the flags (first non-finite, outside, J <= 0 particle or -1)."""
        lame = None
        if fused:
            lame = (material.E, 0.0) if self.dim == 1 else (material.lam, material.mu)
        return self.transfers.g2p(particles, grid_a, grid_v, dt, vfactor, flip, new, L_out,
                                  acc_out, lame)

    def rates(self, particles, grid_a, grid_v, fused, material, x_rate, v_rate, L_out,
              stress_rate, V_rate):
        """A Runge-Kutta stage's particle rates (N v, N a, V tr L, and the
        linear elastic ``material``'s stress rate with ``fused``, else L),
        see :mod:`skfem_mpm.kernels.gather`."""
        lame = None
        if fused:
            lame = (material.E, 0.0) if self.dim == 1 else (material.lam, material.mu)
        self.transfers.rates(particles, grid_a, grid_v, x_rate, v_rate, L_out, stress_rate,
                             V_rate, lame)

    def _stencil_pattern(self):
        """CSR pattern of the stencil (rows, valid stencil slots, columns)."""
        if getattr(self, "_pattern", None) is None:
            import scipy.sparse as sp

            p, width = self.p, 2 * self.p + 1
            nd = self.ndofs
            k = np.arange(nd)
            if self.dim == 1:
                cols = k[:, None] + (np.arange(width) - p)[None, :]
                valid = (cols >= 0) & (cols < nd)
            elif self.dim == 3:  # slot ((dc + p) width + db + p) width + da + p
                nbx, nby, nbz = self.grid.basis_per_axis
                a, b, c = k % nbx, (k // nbx) % nby, k // (nbx * nby)
                dc, db, da = (o.ravel() - p for o in np.indices((width,) * 3))
                aa, bb, cc = a[:, None] + da, b[:, None] + db, c[:, None] + dc
                valid = ((aa >= 0) & (aa < nbx) & (bb >= 0) & (bb < nby) & (cc >= 0)
                         & (cc < nbz))
                cols = (cc * nby + bb) * nbx + aa
            else:
                nbx, nby = self.grid.basis_per_axis
                a, b = k % nbx, k // nbx
                da = np.tile(np.arange(width) - p, width)
                db = np.repeat(np.arange(width) - p, width)
                aa, bb = a[:, None] + da[None, :], b[:, None] + db[None, :]
                valid = (aa >= 0) & (aa < nbx) & (bb >= 0) & (bb < nby)
                cols = bb * nbx + aa
            slots = np.flatnonzero(valid.ravel())
            indptr = np.concatenate(([0], np.cumsum(valid.sum(axis=1))))
            self._pattern = (slots, cols.ravel()[slots].astype(np.int32),
                             indptr.astype(np.int32), sp)
            width_total = valid.shape[1]
            self._stencil_shape = (nd, width_total)
            self._stencil_copies = np.zeros((self.nthreads, nd, (width_total + 1) // 2))
            self._stiff_copies = np.zeros((self.nthreads, nd))
            self._stencil_touched = np.zeros((self.nthreads, 2), dtype=np.int64)
            self._stencil_rows = (0, nd)  # rows of the output that may be nonzero
        return self._pattern

    def consistent_mass(self, particles):
        """(M as CSR with the stencil pattern, sum m_p |grad N_k|^2 (dofs,))."""
        stencil, K = self.consistent_stencil(particles)
        return self.stencil_csr(stencil), K

    def stencil_csr(self, stencil):
        """The CSR matrix of a stencil array."""
        slots, cols, indptr, sp = self._stencil_pattern()
        return sp.csr_matrix((stencil.ravel()[slots], cols, indptr),
                             shape=(self.ndofs, self.ndofs))

    def consistent_stencil(self, particles, cells=0, k=0, add=None):
        """(M as a stencil array (dofs, (2p+1)^dim), sum m_p |grad N_k|^2);
        both arrays are reused by the next call. 2D: the first ``cells``
        k x k blocks of points are whole cells' tensor Gauss rules
        (:func:`consistent_cells_2d`); ``add(mass_copies, stiff_copies,
        touched)`` (2D), if given, adds more into that kernel's per-thread
        copies before they are summed (kernels.cell_integrals)."""
        self._stencil_pattern()
        p = particles
        touched = self._stencil_touched
        if self.dim == 2 and (cells > 0 or add is not None):
            (bx, ux, ihx, Cx), (by, uy, ihy, Cy) = self.args
            self.kernel(consistent_cells_2d)(p.x, p.m, cells, k, bx, by, ux, uy, ihx, ihy, Cx,
                                             Cy, self.p, self.nbx, self._stencil_copies,
                                             self._stiff_copies, touched)
            if add is not None:
                add(self._stencil_copies, self._stiff_copies, touched)
        elif self.dim == 1:
            (bx, ux, ihx, Cx), = self.args
            self.kernel(consistent_1d)(p.x, p.m, bx, ux, ihx, Cx, self.p, self._stencil_copies,
                          self._stiff_copies, touched)
        elif self.dim == 3:
            self.kernel(consistent_axes)(p.x, p.m, *self.args[0], *self.args[1], *self.args[2],
                                         self.p, self.nbx, self.grid.basis_per_axis[1],
                                         self._stencil_copies, self._stiff_copies, touched)
        else:
            (bx, ux, ihx, Cx), (by, uy, ihy, Cy) = self.args
            self.kernel(consistent_2d)(p.x, p.m, bx, by, ux, uy, ihx, ihy, Cx, Cy, self.p,
                                       self.nbx, self._stencil_copies, self._stiff_copies,
                                       touched)
        K = self.scratch("stiffness", self.ndofs)
        stencil = self.scratch("stencil", self._stencil_shape)
        # rows outside the touched union are zero: clear those that held
        # entries at the previous call (all rows at the first)
        lo, hi = int(touched[:, 0].min()), int(touched[:, 1].max())
        if hi <= lo:  # no particles
            lo = hi = 0
        was_lo, was_hi = self._stencil_rows
        for a, b in ((was_lo, min(lo, was_hi)), (max(hi, was_lo), was_hi)):
            stencil[a:b] = 0.0
            K[a:b] = 0.0
        self._stencil_rows = (lo, hi)
        self.kernel(reduce_stencil)(self._stencil_copies, self._stiff_copies, touched, lo, hi,
                       *self.stencil_geometry, stencil, K)
        return stencil, K

    def particle_coverage(self, particles, guard=None):
        """The fast-dof guard's coverage sums of ``particles`` (3, dofs):
        rows K, D, m of :func:`particle_coverage`; reused by the next call.
        With ``guard`` = (bound, w, mu, moving, lo, hi, t, F, limit) (the
        arguments of :func:`skfem_mpm.kernels.coverage_skip.coverage_holds`
        after the sums), the last pass's sums
        are returned unchanged where coverage_holds says they give the
        guard's lumping of new ones (each pass keeps the particles'
        positions, masses and the reach W_k of
        :func:`skfem_mpm.kernels.coverage_skip.coverage_reach` for it)."""
        if self._coverage is None:
            self._coverage = (np.zeros((self.nthreads, 3, self.ndofs)),
                              np.zeros((self.nthreads, 2), dtype=np.int64),
                              np.zeros((3, self.ndofs)), np.zeros(self.ndofs), [None, None])
        copies, touched, out, reach, kept = self._coverage
        x, m = particles.x, particles.m
        if guard is not None and kept[0] is not None and self.kernel(coverage_holds)(
                x, m, kept[0], kept[1], out, reach, *guard):
            return out
        axes = list(self.args) + [self.args[0]] * (3 - self.dim)
        nby = self.grid.basis_per_axis[1] if self.dim > 1 else 1
        self.kernel(particle_coverage)(x, m, *axes[0], *axes[1], *axes[2],
                                       self.p, self.nbx, nby, copies, touched)
        self.kernel(reduce_coverage)(copies, touched, out)
        # kept only when the new sums' own ratios stay below the threshold:
        # coverage_holds at zero displacement with reach = D asks exactly that
        # (every bound term is 0, and D_k = 0 marks the rows no particle
        # sees); where it fails, the next step's bound r+ >= r fails too, so
        # the reach and the copies would be wasted
        if guard is None or not self.kernel(coverage_holds)(x, m, x, m, out, out[1], *guard):
            kept[0] = kept[1] = None
        else:
            self.kernel(coverage_reach)(x, m, *axes[0], *axes[1], *axes[2], self.p, self.nbx,
                                        nby, float(guard[0][0]), reach)
            kept[0], kept[1] = np.array(x, dtype=np.float64), np.array(m, dtype=np.float64)
        return out

    @property
    def stencil_geometry(self):
        """(p, nbx, nby, dim) of the stencil helpers (1D: nbx = dofs; 3D:
        nbz = dofs / (nbx nby), derived by the helpers from the stencil)."""
        if self.dim == 1:
            return self.p, self.ndofs, 1, 1
        return (self.p, *self.grid.basis_per_axis[:2], self.dim)

    def scratch(self, name, shape, dtype=np.float64):
        """A work array kept between steps (allocating it anew each step
        costs page faults); valid until the next request of the same name."""
        size = math.prod(shape) if isinstance(shape, tuple) else int(shape)
        a = self._scratch.get(name)
        if a is None or a.size < size or a.dtype != dtype:
            a = self._scratch[name] = np.empty(size + 64, dtype=dtype)
        return a[:size].reshape(shape)

    def gravity_work(self, mass, v_grid, dt, gravity):
        """The work of the uniform acceleration ``gravity`` on the particles
        of a g2p call with grid velocity v_grid, g . sum_p m_p du_p: equal
        to dt g . sum_k m_k v_k with m_k the lumped mass of that step's p2g,
        since du_p = dt sum_k N_kp v_k and m_k = sum_p m_p N_kp."""
        sums = self.scratch("work_sums", self.dim)
        self.kernel(mass_weighted_sum)(mass, v_grid, sums)
        return work_increment(sums, float(dt), gravity)

    def small_mass(self, lumped, tol):
        """Boolean mask of tiny-mass dofs (see grid_system) and its count.

        On the lumped mass of the last p2g call, a node can only be tiny
        (m_k < tol max of its neighbours) if the smallest positive mass is
        below tol times the largest; otherwise the scan is skipped."""
        small = self._small
        if lumped is self.transfers.mass:
            ranges = self.transfers.mass_range.tolist()
            if min(r[0] for r in ranges) >= tol * max(r[1] for r in ranges):
                small[:] = False
                return small, 0
        if self.dim == 2:
            count = self.kernel(small_mass_2d)(lumped, self.nbx, self.grid.basis_per_axis[1],
                                               self.p, tol, small)
        elif self.dim == 1:
            count = self.kernel(small_mass_1d)(lumped, self.p, tol, small)
        else:
            count = self.kernel(small_mass_axes)(lumped, *self.axes_shape, self.p, tol, small)
        return small, int(count)

    def usl_grid(self, mass, momentum, force, gravity, constrained, v_values, a_values, vdt,
                 a, v_new, occupied=None):
        """One pass of the USL/CD grid step (see usl_grid); ``occupied``:
        the node ranges of the transfers' arrays (Transfers.occupied) when
        ``mass`` is theirs and ``a``, ``v_new`` start as zeros, else None
        (every node)."""
        has = v_values is not None
        if occupied is None:
            occupied = np.array([0, mass.shape[0], 0, mass.shape[0]], dtype=np.int64)
        self.kernel(usl_grid)(mass, momentum, force, gravity, constrained,
                              v_values if has else force, a_values if has else force, has, vdt,
                              a, v_new, occupied)

    def merged_solve(self, mass, rhs, gravity, constrained, values, tol, out):
        """Lumped solve with the tiny-mass merge into ``out``; returns the
        number of small dofs, or -1 when the reference merge must be used
        (see :mod:`skfem_mpm.kernels.tiny_mass`)."""
        has = values is not None
        return self.kernel(merged_lumped_solve_axes)(mass, rhs, gravity, constrained,
                                        values if has else rhs, has, *self.axes_shape, self.p,
                                        tol, out)

    @property
    def axes_shape(self):
        """(nbx, nby, nbz): functions per axis, 1 for the missing axes."""
        return tuple(self.grid.basis_per_axis) + (1,) * (3 - self.dim)

    def solve(self, mass, rhs, gravity, constrained, values, out):
        """Lumped solve into ``out`` (see lumped_solve)."""
        has = values is not None
        self.kernel(lumped_solve)(mass, rhs, gravity, constrained, values if has else rhs, has,
                                  out)
        return out


# ------------------------------------------------------- consistent mass solve
# The consistent system is solved on its free dofs only (free: has mass and
# is not constrained in the component group), stored row by row in ELL form:
# A[r, s] is the entry of stencil slot s of free row r and cols[r, s] its
# free column (fixed and outside columns point at r itself with a zero
# entry, so the product needs no branches).


@njit(cache=True, error_model="numpy")
def _slot_offsets(p, dim, ns):
    """The index offsets (da, db, dc) of each stencil slot s = ((dc + pc) w
    + db + pb) w + da + p (w = 2p + 1; pb = p from 2D on, pc = p in 3D,
    else 0): shape (ns, 3), computed once per call so that the row loops
    need no integer division per slot."""
    width = 2 * p + 1
    pb = p if dim >= 2 else 0
    pc = p if dim == 3 else 0
    out = np.empty((ns, 3), dtype=np.int64)
    for s in range(ns):
        out[s, 0] = s % width - p
        out[s, 1] = (s // width) % width - pb if dim >= 2 else 0
        out[s, 2] = s // (width * width) - pc if dim == 3 else 0
    return out


@njit(cache=True, inline="always")
def _row_indices(k, nbx, nby, dim):
    """(a, b, c) of dof k (k = (c nby + b) nbx + a)."""
    a = k % nbx
    b = k // nbx
    c = 0
    if dim == 3:
        b, c = b % nby, b // nby
    return a, b, c


@njit(cache=True, inline="always")
def _offset_dof(a, b, c, offsets, s, nbx, nby, nbz):
    """Dof at stencil slot s of the dof (a, b, c) (``offsets`` from
    :func:`_slot_offsets`), or -1 outside the grid."""
    aa = a + offsets[s, 0]
    bb = b + offsets[s, 1]
    cc = c + offsets[s, 2]
    if aa < 0 or aa >= nbx or bb < 0 or bb >= nby or cc < 0 or cc >= nbz:
        return -1
    return (cc * nby + bb) * nbx + aa


@njit(cache=True, error_model="numpy")
def lumped_reach(fast, p, nbx, nby, dim, ns, near):
    """near_k = whether row k of the stencil (``ns`` slots) has a nonzero
    lumping fraction theta_kj = max(fast_k, fast_j) (:func:`compact_system`):
    fast_k != 0 or fast_j != 0 at a dof j of its stencil. Marked from the
    fast rows (a few per step): each marks its stencil (the stencil is
    symmetric: j is in k's iff k is in j's)."""
    nd = fast.shape[0]
    nbz = nd // (nbx * nby)
    near[:] = False
    first = 0  # the first fast row (none: no offsets made)
    while first < nd and fast[first] == 0.0:
        first += 1
    if first == nd:
        return
    offsets = _slot_offsets(p, dim, ns)
    for k in range(first, nd):
        if fast[k] != 0.0:  # (a NaN fraction too)
            a, b, c = _row_indices(k, nbx, nby, dim)
            for s in range(ns):
                j = _offset_dof(a, b, c, offsets, s, nbx, nby, nbz)
                if j >= 0:
                    near[j] = True


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def compact_system(M, p, nbx, nby, dim, rows, index, fast, near, A, cols, F, fcols, write_cols,
                   write_fixed):
    """The free-dof rows of the consistent mass, ELL form.

    Row k = rows[r] of M with (1) the fraction theta = max(fast_k, fast_j) of
    every off-diagonal entry moved onto the diagonal (fast-row lumping,
    ``fast`` in [0, 1] per dof) and (2) its columns split into free ones
    (index[j] >= 0: A[r, s], cols[r, s] = index[j]) and fixed ones
    (F[r, s] = (1 - theta) M_kj, fcols[r, s] = j), which
    :func:`compact_problem` moves to the right-hand side. cols depends on
    the free-dof set only and F, fcols are read only for nonzero fixed
    values: they are written when ``write_cols``, ``write_fixed``. A row
    whose every theta is 0 (not ``near``, :func:`lumped_reach`) takes its
    entries of M as they are (each term theta M_kj its diagonal would add
    is 0) at its free columns: those that ``cols`` holds when it is not
    written (cols[r, s] != r, and the centre), else those of ``index`` (rows
    p or more from the grid's edges, whose slots need no bounds test)."""
    nr = rows.shape[0]
    ns = M.shape[1]
    centre = (ns - 1) // 2
    nbz = M.shape[0] // (nbx * nby)
    offsets = _slot_offsets(p, dim, ns)
    step = np.empty(ns, dtype=np.int64)  # each slot's dof offset (rows p or more from the edges)
    for s in range(ns):
        step[s] = (offsets[s, 2] * nby + offsets[s, 1]) * nbx + offsets[s, 0]
    pb = p if dim >= 2 else 0
    pc = p if dim == 3 else 0
    for r in prange(nr):
        k = rows[r]
        if not near[k] and not write_fixed and not write_cols:  # cols: the free columns
            for s in range(ns):
                A[r, s] = M[k, s] if cols[r, s] != r else 0.0
            A[r, centre] = M[k, centre]
            continue
        a, b, c = _row_indices(k, nbx, nby, dim)
        inside = p <= a < nbx - p and pb <= b < nby - pb and pc <= c < nbz - pc
        if inside and not near[k] and not write_fixed:
            for s in range(ns):  # (the centre: index[k] = r, its entry M_kk)
                col = index[k + step[s]]
                A[r, s] = M[k, s] if col >= 0 else 0.0
                if write_cols:
                    cols[r, s] = col if col >= 0 else r
            continue
        diag = M[k, centre]
        fast_k = fast[k]
        for s in range(ns):
            A[r, s] = 0.0
            if write_cols:
                cols[r, s] = r
            if write_fixed:
                F[r, s] = 0.0
                fcols[r, s] = k
            if s == centre:
                continue
            if inside:
                j = k + step[s]
            else:
                j = _offset_dof(a, b, c, offsets, s, nbx, nby, nbz)
                if j < 0:
                    continue
            mks = M[k, s]
            theta = fast_k if fast_k > fast[j] else fast[j]
            diag += theta * mks
            if index[j] >= 0:
                A[r, s] = (1.0 - theta) * mks
                if write_cols:
                    cols[r, s] = index[j]
            elif write_fixed:
                F[r, s] = (1.0 - theta) * mks
                fcols[r, s] = j
        A[r, centre] = diag


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def particle_coverage(x, m, b0, u0, ih0, C0, b1, u1, ih1, C1, b2, u2, ih2, C2, p, nbx, nby,
                      copies, touched):
    """The fast-dof guard's coverage sums of the particles, per dof k:
    K_k = sum_p m_p |grad N_k(x_p)|^2, D_k = sum_p m_p N_k(x_p)^2 and
    m_k = sum_p m_p N_k(x_p) (rows 0, 1, 2), into per-thread copies
    (threads, 3, dofs) over the node ranges each thread's particle block
    touches (``touched``, as the scatter kernels); :func:`reduce_coverage`
    sums them. The axes as :func:`consistent_axes` takes them (those from
    dim = x.shape[1] on are not read), N_k and grad N_k as it forms them.
    The NumPy twin: :func:`skfem_mpm.solve.steps.particle_coverage`."""
    n = x.shape[0]
    dim = x.shape[1]
    nt = copies.shape[0]
    nq = (p + 1) ** dim
    for t in prange(nt):
        g = copies[t]
        g[:, touched[t, 0]:touched[t, 1]] = 0.0
        first = g.shape[1]
        last = 0
        w = np.zeros((3, 4))
        dw = np.zeros((3, 4))
        # the axes' rows as views made once (a view made per particle counts
        # a reference to w at each)
        w_0, dw_0, w_1, dw_1 = w[0], dw[0], w[1], dw[1]
        lo = t * n // nt
        hi = (t + 1) * n // nt
        if dim == 1:  # interior cells in registers (closed_axis_functions), as consistent_1d
            x0, ncx = b0[0], b0.shape[0] - 1
            for i in range(lo, hi):
                mi = m[i]
                closed, base, v0, v1, v2, v3, d0, d1, d2, d3 = closed_axis_functions(
                    x[i, 0], x0, ncx, u0, ih0, p)
                if not closed:
                    base = _axis(x[i, 0], b0, u0, ih0, C0, p, w_0, dw_0)
                    v0, v1, v2, v3 = w_0[0], w_0[1], w_0[2], w_0[3]
                    d0, d1, d2, d3 = dw_0[0], dw_0[1], dw_0[2], dw_0[3]
                mv = mi * v0
                g[0, base] += mi * (d0 * d0)
                g[1, base] += mv * v0
                g[2, base] += mv
                mv = mi * v1
                g[0, base + 1] += mi * (d1 * d1)
                g[1, base + 1] += mv * v1
                g[2, base + 1] += mv
                if p >= 2:
                    mv = mi * v2
                    g[0, base + 2] += mi * (d2 * d2)
                    g[1, base + 2] += mv * v2
                    g[2, base + 2] += mv
                if p >= 3:
                    mv = mi * v3
                    g[0, base + 3] += mi * (d3 * d3)
                    g[1, base + 3] += mv * v3
                    g[2, base + 3] += mv
                first = min(first, base)
                last = max(last, base + p + 1)
        elif dim == 2:  # written out: no digit arithmetic per node
            x0, ncx, y0, ncy = b0[0], b0.shape[0] - 1, b1[0], b1.shape[0] - 1
            for i in range(lo, hi):
                mi = m[i]
                closed, ex, w00, w01, w02, w03, g00, g01, g02, g03 = closed_axis_functions(
                    x[i, 0], x0, ncx, u0, ih0, p)
                if not closed:
                    ex = _axis(x[i, 0], b0, u0, ih0, C0, p, w_0, dw_0)
                    w00, w01, w02, w03 = w_0[0], w_0[1], w_0[2], w_0[3]
                    g00, g01, g02, g03 = dw_0[0], dw_0[1], dw_0[2], dw_0[3]
                closed, ey, w10, w11, w12, w13, g10, g11, g12, g13 = closed_axis_functions(
                    x[i, 1], y0, ncy, u1, ih1, p)
                if not closed:
                    ey = _axis(x[i, 1], b1, u1, ih1, C1, p, w_1, dw_1)
                    w10, w11, w12, w13 = w_1[0], w_1[1], w_1[2], w_1[3]
                    g10, g11, g12, g13 = dw_1[0], dw_1[1], dw_1[2], dw_1[3]
                base = ex + nbx * ey
                for b in range(p + 1):
                    wy = w10 if b == 0 else w11 if b == 1 else w12 if b == 2 else w13
                    dy = g10 if b == 0 else g11 if b == 1 else g12 if b == 2 else g13
                    row = base + b * nbx
                    for a in range(p + 1):
                        wx = w00 if a == 0 else w01 if a == 1 else w02 if a == 2 else w03
                        dx = g00 if a == 0 else g01 if a == 1 else g02 if a == 2 else g03
                        value = wx * wy
                        gx = dx * wy
                        gy = wx * dy
                        mv = mi * value
                        g[0, row + a] += mi * (gx * gx + gy * gy)
                        g[1, row + a] += mv * value
                        g[2, row + a] += mv
                first = min(first, base)
                last = max(last, base + p * nbx + p + 1)
        else:
            for i in range(lo, hi):
                mi = m[i]
                base = _tensor_point(x, i, b0, u0, ih0, C0, b1, u1, ih1, C1, b2, u2, ih2, C2,
                                     p, nbx, nby, w, dw)
                node = 0
                for q in range(nq):
                    value, grad2, node, _ = _tensor_node(q, w, dw, p, nbx, nby, dim)
                    mv = mi * value
                    g[0, base + node] += mi * grad2
                    g[1, base + node] += mv * value
                    g[2, base + node] += mv
                first = min(first, base)
                last = max(last, base + node + 1)
        touched[t, 0] = first
        touched[t, 1] = last


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def reduce_coverage(copies, touched, out):
    """out (3, dofs) = the sum of :func:`particle_coverage`'s per-thread
    copies (zero outside every touched range)."""
    nt, nc, nk = copies.shape
    if nt == 1:  # one copy (the serial kernels): the same sums without the holders' lists
        t0 = touched[0, 0]
        t1 = touched[0, 1]
        for k in range(nk):
            held = t0 <= k and k < t1
            for c in range(nc):
                s = 0.0
                if held:
                    s += copies[0, c, k]
                out[c, k] = s
        return
    for r in prange(nt):
        cuts, threads, counts = holders(touched, r * nk // nt, (r + 1) * nk // nt)
        for j in range(cuts.shape[0] - 1):
            count = counts[j]
            for k in range(cuts[j], cuts[j + 1]):
                for c in range(nc):
                    s = 0.0
                    for i in range(count):
                        s += copies[threads[j, i], c, k]
                    out[c, k] = s


@njit(cache=True, parallel=True, error_model="numpy")
def covered_stiffness(stiffness, diagonal, mass, weights, mass_ratios, moving, lo, hi, tail,
                      floor, limit, p, nbx, nby, work, out):
    """out_k: the fast-dof guard's stiffness of
    :func:`skfem_mpm.solve.timestep.covered_stiffness` (the same operations,
    so the same bits). With the tail weight, T_k = K_k (c_k moving_k) +
    a_k moving_k, c_k = tail + (w_k - tail) s_k, a_k = (1 - s_k) (1 - tail)
    floor D_k, s_k = smoothstep over (lo, hi) of tau_k = D_k / (m_k mu_k)
    (K, D = M_kk and m the particles' coverage sums,
    :func:`particle_coverage`); without it (the plain limit)
    P_k = K_k (c'_k moving_k), c'_k = 1 + (w_k - 1) s_k; the tail weight
    withdrawn near a cut cell: out_k = T_k + b_k (P_k - T_k), b_k the
    largest theta_j = smoothstep(2 T_j / (limit D_j) - 1) over the dofs j
    within p indices of k per axis (theta_j = 0 where D_j = 0). inf on a moving dof no
    particle sees (D_k = 0), zero on the dofs that never move. ``work``
    (2, dofs): the theta_j and their running maxima (nbx, nby the dofs per
    axis; nbx = dofs in 1D, nby = 1 in 1D)."""
    nd = mass.shape[0]
    x = work[0]
    for k in prange(nd):
        d = diagonal[k]
        tau = d / (max(mass[k], 1e-300) * mass_ratios[k])
        s = min(max((tau - lo) / (hi - lo), 0.0), 1.0)
        smooth = s * s * (3.0 - 2.0 * s)
        w = tail + (weights[k] - tail) * smooth
        a = (1.0 - smooth) * (1.0 - tail) * floor * d
        if d > 0.0:
            seen = stiffness[k] * (w * moving[k]) + a * moving[k]
            out[k] = seen
            r = min(max(2.0 * (seen / (limit * d)) - 1.0, 0.0), 1.0)
            x[k] = r * r * (3.0 - 2.0 * r)
        else:
            out[k] = np.inf if moving[k] > 0.0 else 0.0
            x[k] = 0.0
    _box_max(work, p, nbx, nby)
    b = work[0]
    for k in prange(nd):
        d = diagonal[k]
        if d > 0.0 and b[k] > 0.0:
            tau = d / (max(mass[k], 1e-300) * mass_ratios[k])
            s = min(max((tau - lo) / (hi - lo), 0.0), 1.0)
            smooth = s * s * (3.0 - 2.0 * s)
            plain = stiffness[k] * ((1.0 + (weights[k] - 1.0) * smooth) * moving[k])
            out[k] = out[k] + b[k] * (plain - out[k])


@njit(cache=True, error_model="numpy")
def _box_max(work, p, nbx, nby):
    """work[0]_k <- the largest work[0]_j over the dofs j within p indices
    of k per axis (x fastest; nbz = dofs / (nbx nby)), one axis at a time
    through work[1]."""
    nd = work.shape[1]
    nbz = nd // (nbx * nby)
    src, dst = work[0], work[1]
    for axis in range(3):
        n, stride = (nbx, 1) if axis == 0 else ((nby, nbx) if axis == 1 else (nbz, nbx * nby))
        if n == 1:
            continue
        for k in range(nd):
            i = (k // stride) % n
            v = src[k]
            for o in range(max(i - p, 0) - i, min(i + p, n - 1) - i + 1):
                v = max(v, src[k + o * stride])
            dst[k] = v
        for k in range(nd):
            src[k] = dst[k]


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def fast_row_fractions(stiffness, diagonal, mass, limit, out):
    """out_k = theta(k_k / (limit D_k)) on dofs with ``mass``, 0 on the
    others: the fast-row lumping fractions of
    :func:`skfem_mpm.solve.timestep.lumping_fraction` (theta(q) =
    smoothstep(2 q - 1); k the guard's stiffness, D the diagonal it was
    formed with) in one pass; returns their count > 0."""
    count = 0
    for k in prange(mass.shape[0]):
        theta = 0.0
        if mass[k] > 0.0:
            q = stiffness[k] / (limit * max(diagonal[k], 1e-300))
            t = min(max(2.0 * q - 1.0, 0.0), 1.0)
            theta = t * t * (3.0 - 2.0 * t)
        out[k] = theta
        if theta > 0.0:
            count += 1
    return count


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def compact_problem(rows, rhs, values, has_values, prev, has_prev, comps, j0, F, fcols, b, x):
    """One problem's columns j = j0 + l (component c = comps[l]) of the
    compact CG system: b[r, j] = rhs[k, c] - sum_s F[r, s] values[fcols[r, s], c]
    (k = rows[r]; the fixed dofs' known values moved to the right-hand side)
    and the warm start x[r, j] = prev[k, c] (0 without one)."""
    nr, ns = F.shape
    for r in prange(nr):
        k = rows[r]
        for l in range(comps.shape[0]):
            c = comps[l]
            acc = rhs[k, c]
            if has_values:
                for s in range(ns):
                    acc -= F[r, s] * values[fcols[r, s], c]
            b[r, j0 + l] = acc
            x[r, j0 + l] = prev[k, c] if has_prev else 0.0


@njit(cache=True, parallel=True, error_model="numpy")
def expand_problem(rows, x, comps, j0, out):
    """out[rows[r], comps[l]] = x[r, j0 + l] (one problem's solution)."""
    for r in prange(rows.shape[0]):
        for l in range(comps.shape[0]):
            out[rows[r], comps[l]] = x[r, j0 + l]


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def stencil_rows_product(M, p, nbx, nby, dim, rows, inactive, fast, x, y):
    """y[r] = (M' x)[rows[r]], M' the stencil with fast-row lumping and the
    columns of massless dofs removed (for reactions on constrained rows)."""
    ns = M.shape[1]
    nc = x.shape[1]
    centre = (ns - 1) // 2
    nbz = M.shape[0] // (nbx * nby)
    offsets = _slot_offsets(p, dim, ns)
    for r in prange(rows.shape[0]):
        k = rows[r]
        diag = M[k, centre]
        a, b, cz = _row_indices(k, nbx, nby, dim)
        for c in range(nc):
            y[r, c] = 0.0
        for s in range(ns):
            if s == centre:
                continue
            j = _offset_dof(a, b, cz, offsets, s, nbx, nby, nbz)
            if j < 0:
                continue
            theta = fast[k] if fast[k] > fast[j] else fast[j]
            diag += theta * M[k, s]
            if not inactive[j]:
                off = (1.0 - theta) * M[k, s]
                for c in range(nc):
                    y[r, c] += off * x[j, c]
        for c in range(nc):
            y[r, c] += diag * x[k, c]


@njit(cache=True, inline="always")
def _chunk(t, nt, n):
    return t * n // nt, (t + 1) * n // nt


@njit(cache=True, error_model="numpy", fastmath=FAST)
def _one_column_product_dot(A, cols, d, q, rows_d):
    """q = A d for the rows of A (one column; ``rows_d`` the rows of d that
    A's rows are), returns sum_r rows_d[r] q[r]: the rows of one block
    passed as arrays of their own, their loop starting at 0 (with a block's
    bounds the same loop compiled ~30% slower)."""
    nr, ns = A.shape
    dq = 0.0
    for r in range(nr):
        acc = 0.0
        for s in range(ns):
            acc += A[r, s] * d[cols[r, s], 0]
        q[r, 0] = acc
        dq += rows_d[r, 0] * acc
    return dq


@njit(cache=True, parallel=True, error_model="numpy", fastmath=IN_ORDER)
def _ell_product_dot(A, cols, d, q, partial):
    """q = A d and partial[t, c] = sum over thread t's rows of d_c q_c
    (compiled without reassociation: each row's columns summed in slot order
    with the row of d one vector load; with reassociation LLVM gathered d's
    entries over the slots instead, slower for two or four columns)."""
    nr, ns = A.shape
    nc = d.shape[1]
    nt = partial.shape[0]
    for t in prange(nt):
        lo, hi = _chunk(t, nt, nr)
        for c in range(nc):
            partial[t, c] = 0.0
        if nc == 1:  # one column: a plain gather, d.q in a register (the same bits)
            partial[t, 0] = _one_column_product_dot(A[lo:hi], cols[lo:hi], d, q[lo:hi],
                                                    d[lo:hi])
        else:
            for r in range(lo, hi):
                if nc == 4:  # two 2D problems at once (USL): four running sums
                    s0 = s1 = s2 = s3 = 0.0
                    for s in range(ns):
                        a = A[r, s]
                        j = cols[r, s]
                        s0 += a * d[j, 0]
                        s1 += a * d[j, 1]
                        s2 += a * d[j, 2]
                        s3 += a * d[j, 3]
                    q[r, 0] = s0
                    q[r, 1] = s1
                    q[r, 2] = s2
                    q[r, 3] = s3
                elif nc == 2:
                    s0 = s1 = 0.0
                    for s in range(ns):
                        a = A[r, s]
                        j = cols[r, s]
                        s0 += a * d[j, 0]
                        s1 += a * d[j, 1]
                    q[r, 0] = s0
                    q[r, 1] = s1
                else:
                    for c in range(nc):
                        acc = 0.0
                        for s in range(ns):
                            acc += A[r, s] * d[cols[r, s], c]
                        q[r, c] = acc
                for c in range(nc):
                    partial[t, c] += d[r, c] * q[r, c]


@njit(cache=True, parallel=True, error_model="numpy", fastmath=IN_ORDER)
def _cg_update(x, r, z, d, q, inv_diag, jacobi, alpha, active, partial):
    """x += alpha d, r -= alpha q on the active components; partial[t] =
    (r.z, r.r) per component over thread t's rows, with z = D^-1 r computed
    here when ``jacobi`` (else r.z is left to the caller). One component:
    the sums in registers (row by row as with several: the same bits)."""
    nr, nc = x.shape
    nt = partial.shape[0]
    for t in prange(nt):
        lo, hi = _chunk(t, nt, nr)
        for c in range(nc):
            partial[t, 0, c] = 0.0
            partial[t, 1, c] = 0.0
        if nc == 1:
            if active[0]:
                a = alpha[0]
                rz = 0.0
                rr = 0.0
                for i in range(lo, hi):
                    x[i, 0] += a * d[i, 0]
                    ri = r[i, 0] - a * q[i, 0]
                    r[i, 0] = ri
                    if jacobi:
                        zi = inv_diag[i] * ri
                        z[i, 0] = zi
                        rz += ri * zi
                    rr += ri * ri
                partial[t, 0, 0] = rz
                partial[t, 1, 0] = rr
        else:
            for i in range(lo, hi):
                for c in range(nc):
                    if not active[c]:
                        continue
                    x[i, c] += alpha[c] * d[i, c]
                    ri = r[i, c] - alpha[c] * q[i, c]
                    r[i, c] = ri
                    if jacobi:
                        zi = inv_diag[i] * ri
                        z[i, c] = zi
                        partial[t, 0, c] += ri * zi
                    partial[t, 1, c] += ri * ri


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def _cg_direction(d, z, beta, active):
    """d = z + beta d on the active components."""
    nr, nc = d.shape
    for i in prange(nr):
        for c in range(nc):
            if active[c]:
                d[i, c] = z[i, c] + beta[c] * d[i, c]


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def _dots(r, z, partial):
    """partial[t, c] = sum over thread t's rows of r_c z_c."""
    nr, nc = r.shape
    nt = partial.shape[0]
    for t in prange(nt):
        lo, hi = _chunk(t, nt, nr)
        for c in range(nc):
            s = 0.0
            for i in range(lo, hi):
                s += r[i, c] * z[i, c]
            partial[t, c] = s


def apply_kron(kron, r, z):
    """z = P^-1 r with the Kronecker arguments ``kron``: those of
    :func:`~skfem_mpm.kernels.kronecker.apply_kronecker` (two factors; in
    2D followed by a band factor and whether to apply it instead:
    :func:`~skfem_mpm.kernels.band_factor.apply_band_factor`), or, a
    tuple of eight ending in the boxes' rows, those of
    ``apply_kronecker_axes`` (three factors per box, 3D). Compiled code only
    (chosen by the type of the tuple's last item)."""
    raise NotImplementedError("apply_kron is called from compiled code only")


@overload(apply_kron)
def _apply_kron_typed(kron, r, z):
    if isinstance(kron[-1], types.Array):  # 3D: the boxes' rows last
        return lambda kron, r, z: apply_kronecker_axes(*kron, r, z)
    if len(kron) == 6:  # 1D: no band factor
        return lambda kron, r, z: apply_kronecker(*kron, r, z)

    def apply(kron, r, z):
        if kron[7]:
            apply_band_factor(kron[6], r, z)
        else:
            apply_kronecker(kron[0], kron[1], kron[2], kron[3], kron[4], kron[5], r, z)
    return apply


def narrow_kron(kron, now, n):
    """The Kronecker arguments ``kron`` with the work box of ``now`` (the
    current ones) narrowed to n columns. Compiled code only."""
    raise NotImplementedError("narrow_kron is called from compiled code only")


@overload(narrow_kron)
def _narrow_kron_typed(kron, now, n):
    if isinstance(kron[-1], types.Array):  # 3D: apply_kronecker_axes reads nc from r
        return lambda kron, now, n: now
    if len(kron) == 6:  # 1D
        return lambda kron, now, n: (kron[0], kron[1], kron[2], kron[3], _narrow(now[4], n),
                                     kron[5])
    return lambda kron, now, n: (kron[0], kron[1], kron[2], kron[3], _narrow(now[4], n),
                                 kron[5], kron[6], kron[7])


@njit(cache=True, error_model="numpy", fastmath=FAST)
def _precondition(A, cols, r, z, t, inv_diag, kron, fringe):
    """z = P^-1 r: the Kronecker preconditioner with the fringe correction
    when ``fringe`` is given, the Kronecker one (or the band factor its
    arguments switch on) when only ``kron`` is, else
    the inverse lumped mass (``t`` work space). ``kron`` and ``fringe`` are
    None or argument tuples: numba prunes the branches of None arguments
    before typing, so a run compiles only the preconditioner it uses."""
    if fringe is not None:
        apply_corrected(A, cols, kron[0], kron[1], kron[2], kron[3], kron[4], kron[5],
                        *fringe, r, z, t)
    elif kron is not None:
        apply_kron(kron, r, z)
    else:
        for i in range(r.shape[0]):
            for c in range(r.shape[1]):
                z[i, c] = inv_diag[i] * r[i, c]


@njit(cache=True, error_model="numpy")
def _pack(a, keep, n):
    """The columns keep[:n] (ascending) of the C-ordered (rows, m) array a,
    moved to the front of its buffer: returns them as an (rows, n) array.
    In place, front to back: no entry is overwritten before it is read."""
    nr, m = a.shape
    flat = a.reshape(nr * m)
    for i in range(nr):
        for j in range(n):
            flat[i * n + j] = flat[i * m + keep[j]]
    return flat[:nr * n].reshape((nr, n))


@njit(cache=True, error_model="numpy")
def _narrow(a, n):
    """The C-ordered array a (..., m) reinterpreted with n <= m columns
    (work space: its values are not kept)."""
    shape = a.shape[:-1] + (n,)
    size = n
    for d in a.shape[:-1]:
        size *= d
    return a.reshape(a.size)[:size].reshape(shape)


@njit(cache=True, inline="always", error_model="numpy")
def _all_converged(sums, limit, active):
    """Whether every active column meets its limit, |r|^2 = sum_t
    sums[t, 1, j] <= limit[j] (summed as the convergence test of
    :func:`ell_pcg` sums it, so both decide alike)."""
    for j in range(limit.shape[0]):
        if active[j]:
            rr_j = 0.0
            for t in range(sums.shape[0]):
                rr_j += sums[t, 1, j]
            if rr_j > limit[j]:
                return False
    return True


@njit(cache=True, error_model="numpy", fastmath=IN_ORDER)
def ell_pcg(A, cols, inv_diag, kron, fringe, b, x, problem, rtol, maxiter, nt, work):
    """Preconditioned conjugate gradients for A x = b (all columns at once,
    each with its own scalars), started from x.

    Column c is converged when |r_c|^2 <= rtol^2 sum |b_c'|^2 over the
    columns c' of its problem (``problem[c]``: the components of one vector
    field are measured together, so a component that is round-off beside
    the others, e.g. the horizontal one of a symmetric body under gravity,
    is not iterated to a relative accuracy of its own). Columns converged
    by the warm start take no iteration; a problem whose right-hand side is
    zero gets x = 0. Converged columns leave the iteration: the others are
    packed to the front of the work arrays, so the late iterations of a few
    slow columns cost only their share. The preconditioner: the inverse
    lumped mass ``inv_diag`` when ``kron`` is None, else the Kronecker one of
    :mod:`skfem_mpm.kernels.kronecker` (``kron``: the arguments of
    ``apply_kronecker`` before r, z, then a band factor and whether it
    replaces the Kronecker step, see ``apply_kron``), with the fringe correction of
    :mod:`skfem_mpm.kernels.fringe` unless ``fringe`` is None (else
    ``FringeFactor.args``, its work space last). Each combination compiles separately, and only
    when used (see ``_precondition``).
    ``work`` holds six arrays shaped like b. Returns the iterations, negated
    when a column ended above its tolerance (the iteration limit, or a
    breakdown: a preconditioner that is not positive definite)."""
    nr, nc = b.shape
    r = work[0]
    q = work[3]
    partial = np.zeros((nt, nc))
    sums = np.zeros((nt, 2, nc))
    _ell_product_dot(A, cols, x, q, partial)
    bb = np.zeros(nc)
    rr = np.zeros(nc)
    if nc == 1:  # the sums in registers (in order: compiled without reassociation)
        sb = 0.0
        sr = 0.0
        for i in range(nr):
            ri = b[i, 0] - q[i, 0]
            r[i, 0] = ri
            sb += b[i, 0] * b[i, 0]
            sr += ri * ri
        bb[0] = sb
        rr[0] = sr
    else:
        for i in range(nr):
            for c in range(nc):
                ri = b[i, c] - q[i, c]
                r[i, c] = ri
                bb[c] += b[i, c] * b[i, c]
                rr[c] += ri * ri
    limit = np.zeros(nc)
    converged = np.zeros(nc, dtype=np.bool_)
    active = np.empty(nc, dtype=np.bool_)
    for c in range(nc):
        for c2 in range(nc):
            if problem[c2] == problem[c]:
                limit[c] += bb[c2]
        limit[c] *= rtol * rtol
        if limit[c] == 0.0:  # b = 0 for the whole problem
            for i in range(nr):
                x[i, c] = 0.0
        converged[c] = limit[c] == 0.0 or rr[c] <= limit[c]
        active[c] = not converged[c]
    columns = np.arange(nc)  # compact column j is column columns[j] of x
    kron_now, fringe_now = kron, fringe  # their work space narrows with the columns
    xc = x
    packed = False  # xc is x until the first packing
    d = work[2]
    rz = np.zeros(nc)
    beta = np.zeros(nc)
    first = True
    it = 0
    alpha = np.zeros(nc)
    # the work views of the current width (made again only when columns
    # leave: each view made counts references)
    z = work[1]
    spare = work[4]
    while True:
        width = xc.shape[1]
        n = 0
        for j in range(width):
            if active[j]:
                n += 1
        if n < width:  # pack the unconverged columns to the front
            if n == 0:
                break
            keep = np.flatnonzero(active[:width])
            if not packed:
                packed = True
                xc = _narrow(work[5], n)
                for i in range(nr):
                    for j in range(n):
                        xc[i, j] = x[i, keep[j]]
            else:
                for j in range(width):
                    if not active[j]:
                        for i in range(nr):
                            x[i, columns[j]] = xc[i, j]
                xc = _pack(xc, keep, n)
            r = _pack(r, keep, n)
            if not first:
                d = _pack(d, keep, n)
            columns = columns[keep]
            limit = limit[keep]
            rz = rz[keep]
            beta = beta[keep]
            active = active[keep]
            if kron is not None:  # the preconditioners' work space
                kron_now = narrow_kron(kron, kron_now, n)
            if fringe is not None:
                fringe_now = fringe[:-4] + (_narrow(fringe_now[-4], n),
                                            _narrow(fringe_now[-3], n),
                                            _narrow(fringe_now[-2], (n + 1) // 2),
                                            _narrow(fringe_now[-1], n))
            z = _narrow(work[1], n)
            q = _narrow(work[3], n)
            spare = _narrow(work[4], n)
            alpha = alpha[:n]
        if it >= maxiter:
            break
        width = n
        if first:  # z = P^-1 r, d = z
            first = False
            d = _narrow(work[2], width)
            _precondition(A, cols, r, z, spare, inv_diag, kron_now, fringe_now)
            if width == 1:
                s = 0.0
                for i in range(nr):
                    d[i, 0] = z[i, 0]
                    s += r[i, 0] * z[i, 0]
                rz[0] = s
            else:
                for j in range(width):
                    rz[j] = 0.0
                for i in range(nr):
                    for j in range(width):
                        d[i, j] = z[i, j]
                        rz[j] += r[i, j] * z[i, j]
            for j in range(width):
                if rz[j] <= 0.0:  # breakdown
                    active[j] = False
            continue
        # the iterations while every column stays: no array is assigned in
        # this loop (each array a loop assigns counts references at every pass)
        while True:
            it += 1
            _ell_product_dot(A, cols, d, q, partial)
            for j in range(width):
                dq = 0.0
                for t in range(nt):
                    dq += partial[t, j]
                if dq <= 0.0:
                    active[j] = False
                alpha[j] = rz[j] / dq if active[j] else 0.0
            _cg_update(xc, r, z, d, q, inv_diag, kron is None, alpha, active, sums)
            if kron is not None and _all_converged(sums, limit, active):
                for j in range(width):  # the next z = P^-1 r is not needed
                    if active[j]:
                        active[j] = False
                        converged[columns[j]] = True
                break
            if kron is not None:  # z = P^-1 r and its r.z
                _precondition(A, cols, r, z, spare, inv_diag, kron_now, fringe_now)
                _dots(r, z, partial)
                for t in range(partial.shape[0]):  # sums[:, 0, :] = partial
                    for j in range(partial.shape[1]):
                        sums[t, 0, j] = partial[t, j]
            for j in range(width):
                if not active[j]:
                    continue
                rz_new = 0.0
                rr_j = 0.0
                for t in range(nt):
                    rz_new += sums[t, 0, j]
                    rr_j += sums[t, 1, j]
                if rr_j <= limit[j]:
                    active[j] = False
                    converged[columns[j]] = True
                    continue
                beta[j] = rz_new / rz[j]
                rz[j] = rz_new
            _cg_direction(d, z, beta, active)
            if it >= maxiter:
                break
            leaving = False
            for j in range(width):
                leaving = leaving or not active[j]
            if leaving:  # (packed at the top of the outer loop)
                break
    if packed:
        for j in range(xc.shape[1]):
            for i in range(nr):
                x[i, columns[j]] = xc[i, j]
    for c in range(nc):
        if not converged[c]:
            return -max(it, 1)
    return it
