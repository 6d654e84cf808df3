"""Fused particle-grid kernels for tensor B-spline grids (1D and 2D).

The NumPy reference of every kernel is the transfer-matrix code of
:mod:`skfem_mpm.solve.steps`; the tests compare the two to 1e-12. The
kernels recompute the B-spline weights of each particle in each pass instead
of storing N (cheaper than the memory traffic of a stored N), and scatter
race-free: the particles are split into one contiguous block per thread, each
thread adds into its own copy of the grid, and the copies are summed
(deterministic for a fixed thread count).

Grid arrays are node-major, all fields of a node adjacent:

    p2g    out[k] = (m_k, P_k (dim), f_k (dim))   lumped mass, momentum, force
           m_k = sum m_p N_kp,  P_k = sum m_p v_p N_kp,
           f_k = sum (-V_p sigma_p . grad N_k(x_p) + f_p N_kp)
    g2p    v_p += c dt sum_k a_k N_kp            (FLIP, c = 1 or 1/2)
           dx_p = dt sum_k v_k N_kp,  x_p += dx_p,  u_p += dx_p
           L_p  = sum_k v_k (x) grad N_k(x_p)
           and for linear elasticity, fused: sigma_p += dt (lambda tr D I + 2 mu D),
           V_p *= det(I + dt L_p), D = sym(L_p)
    g2p2g  (MUSL) v_p^new = v_p + dt sum_k a_k N_kp, and P'_k = sum m_p v_p^new N_kp

Status flags returned by g2p: the first particle with a non-finite value,
outside the grid, or with det(I + dt L) <= 0 (or -1 for none).
"""
import numpy as np
from numba import get_num_threads, njit, prange

from .weights import extracted_functions, locate_axis_point

# fast-math without the no-NaN and no-Inf assumptions: the guards test isfinite
FAST = {"contract", "arcp", "nsz", "reassoc", "afn"}

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


@njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def _quadratic_interior(x, breaks, inv_h):
    """Uniform quadratic axis, scalar form of :func:`_axis` for interior
    cells (2 <= e < cells - 2): (e, w0, w1, w2, dw0, dw1, dw2); e = -1 for
    the boundary cells, which take the general path. Keeping the weights in
    registers instead of small arrays roughly halves the 1D kernels' time."""
    e = locate_axis_point(x, breaks, True, inv_h)
    if e < 2 or e >= breaks.shape[0] - 3:
        return -1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    xi = (x - breaks[e]) * inv_h
    r = 1.0 - xi
    return (e, 0.5 * r * r, 0.5 + xi * r, 0.5 * xi * xi,
            -r * inv_h, (1.0 - 2.0 * xi) * inv_h, xi * inv_h)


@njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def _p2g_node(g, k, N, gx, gy, mi, px, py, fx, fy, sxx, sxy, syy):
    """Scatter one node's share of a particle (2D p2g)."""
    g[k, 0] += N * mi
    g[k, 1] += N * px
    g[k, 2] += N * py
    g[k, 3] += N * fx - (sxx * gx + sxy * gy)
    g[k, 4] += N * fy - (sxy * gx + syy * gy)


@njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def _p2g_row(g, row, wy, dy, wx0, wx1, wx2, dx0, dx1, dx2, mi, px, py, fx, fy, sxx, sxy, syy):
    """The three nodes of one row of a quadratic interior stencil."""
    _p2g_node(g, row, wx0 * wy, dx0 * wy, wx0 * dy, mi, px, py, fx, fy, sxx, sxy, syy)
    _p2g_node(g, row + 1, wx1 * wy, dx1 * wy, wx1 * dy, mi, px, py, fx, fy, sxx, sxy, syy)
    _p2g_node(g, row + 2, wx2 * wy, dx2 * wy, wx2 * dy, mi, px, py, fx, fy, sxx, sxy, syy)


@njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def _g2p_row(grid_a, grid_v, row, wy, dy, wx0, wx1, wx2, dx0, dx1, dx2):
    """Sums over one row of a quadratic interior stencil: (a_x, a_y, v_x,
    v_y, L_xx, L_xy, L_yx, L_yy) contributions."""
    ax = ay = vx = vy = lxx = lxy = lyx = lyy = 0.0
    for a in range(3):
        if a == 0:
            wa, da = wx0, dx0
        elif a == 1:
            wa, da = wx1, dx1
        else:
            wa, da = wx2, dx2
        k = row + a
        N = wa * wy
        gx = da * wy
        gy = wa * dy
        ax += N * grid_a[k, 0]
        ay += N * grid_a[k, 1]
        gvx = grid_v[k, 0]
        gvy = grid_v[k, 1]
        vx += N * gvx
        vy += N * gvy
        lxx += gvx * gx
        lxy += gvx * gy
        lyx += gvy * gx
        lyy += gvy * gy
    return ax, ay, vx, vy, lxx, lxy, lyx, lyy


@njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def _gather_row(grid, row, wy, wx0, wx1, wx2):
    """sum_a N_a grid[row + a] over one row of a quadratic stencil (2 comps)."""
    n0, n1, n2 = wx0 * wy, wx1 * wy, wx2 * wy
    return (n0 * grid[row, 0] + n1 * grid[row + 1, 0] + n2 * grid[row + 2, 0],
            n0 * grid[row, 1] + n1 * grid[row + 1, 1] + n2 * grid[row + 2, 1])


@njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def _scatter_row(g, row, wy, wx0, wx1, wx2, px, py):
    """g[row + a] += N_a (px, py) over one row of a quadratic stencil."""
    n0, n1, n2 = wx0 * wy, wx1 * wy, wx2 * wy
    g[row, 0] += n0 * px
    g[row, 1] += n0 * py
    g[row + 1, 0] += n1 * px
    g[row + 1, 1] += n1 * py
    g[row + 2, 0] += n2 * px
    g[row + 2, 1] += n2 * py


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def _reduce_fields(copies, mass, momentum, force):
    """Sum the per-thread copies of (m, P, f) into three contiguous arrays."""
    nt, nk, nc = copies.shape
    dim = momentum.shape[1]
    for k in prange(nk):
        s = 0.0
        for t in range(nt):
            s += copies[t, k, 0]
        mass[k] = s
        for c in range(dim):
            sp = 0.0
            sf = 0.0
            for t in range(nt):
                sp += copies[t, k, 1 + c]
                sf += copies[t, k, 1 + dim + c]
            momentum[k, c] = sp
            force[k, c] = sf


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def _reduce(copies, out):
    """out = sum over threads of the per-thread grid copies."""
    nt, nk, nc = copies.shape
    for k in prange(nk):
        for c in range(nc):
            s = 0.0
            for t in range(nt):
                s += copies[t, k, c]
            out[k, c] = s


# ----------------------------------------------------------------------- 1D
@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def p2g_1d(x, v, m, V, stress, fext, has_fext, bx, ux, ihx, Cx, p, copies):
    n = x.shape[0]
    nt = copies.shape[0]
    for t in prange(nt):
        g = copies[t]
        g[:, :] = 0.0
        w = np.empty(4)
        dw = np.empty(4)
        lo = t * n // nt
        hi = (t + 1) * n // nt
        quadratic = p == 2 and ux
        for i in range(lo, hi):
            mi = m[i]
            pv = mi * v[i, 0]
            s = V[i] * stress[i, 0, 0]
            f = fext[i, 0] if has_fext else 0.0
            if quadratic:
                e, w0, w1, w2, d0, d1, d2 = _quadratic_interior(x[i, 0], bx, ihx)
                if e >= 0:
                    g[e, 0] += w0 * mi
                    g[e, 1] += w0 * pv
                    g[e, 2] += w0 * f - s * d0
                    g[e + 1, 0] += w1 * mi
                    g[e + 1, 1] += w1 * pv
                    g[e + 1, 2] += w1 * f - s * d1
                    g[e + 2, 0] += w2 * mi
                    g[e + 2, 1] += w2 * pv
                    g[e + 2, 2] += w2 * f - s * d2
                    continue
            e = _axis(x[i, 0], bx, ux, ihx, Cx, p, w, dw)
            for a in range(p + 1):
                k = e + a
                g[k, 0] += w[a] * mi
                g[k, 1] += w[a] * pv
                g[k, 2] += w[a] * f - s * dw[a]


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def g2p2g_1d(x, v, m, grid_a, dt, bx, ux, ihx, Cx, p, v_new, copies):
    n = x.shape[0]
    nt = copies.shape[0]
    for t in prange(nt):
        g = copies[t]
        g[:, :] = 0.0
        w = np.empty(4)
        dw = np.empty(4)
        lo = t * n // nt
        hi = (t + 1) * n // nt
        quadratic = p == 2 and ux
        for i in range(lo, hi):
            if quadratic:
                e, w0, w1, w2, d0, d1, d2 = _quadratic_interior(x[i, 0], bx, ihx)
                if e >= 0:
                    vn = v[i, 0] + dt * (w0 * grid_a[e, 0] + w1 * grid_a[e + 1, 0]
                                         + w2 * grid_a[e + 2, 0])
                    v_new[i, 0] = vn
                    pv = m[i] * vn
                    g[e, 0] += w0 * pv
                    g[e + 1, 0] += w1 * pv
                    g[e + 2, 0] += w2 * pv
                    continue
            e = _axis(x[i, 0], bx, ux, ihx, Cx, p, w, dw)
            acc = 0.0
            for a in range(p + 1):
                acc += w[a] * grid_a[e + a, 0]
            vn = v[i, 0] + dt * acc
            v_new[i, 0] = vn
            pv = m[i] * vn
            for a in range(p + 1):
                g[e + a, 0] += w[a] * pv


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def g2p_1d(x, v, u, m, stress, V, grid_a, grid_v, dt, vfactor, do_flip, bx, ux, ihx, Cx, p,
           lo_x, hi_x, fused, E, x_new, v_new, u_new, stress_new, V_new, L_out, acc_out,
           store_acc, sums, flags):
    n = x.shape[0]
    nt = sums.shape[0]
    for t in prange(nt):
        w = np.empty(4)
        dw = np.empty(4)
        lo = t * n // nt
        hi = (t + 1) * n // nt
        s_mdu = 0.0
        bad = -1
        out = -1
        neg = -1
        quadratic = p == 2 and ux
        for i in range(lo, hi):
            e = -1
            if quadratic:
                e, w0, w1, w2, d0, d1, d2 = _quadratic_interior(x[i, 0], bx, ihx)
                if e >= 0:
                    a0, a1, a2 = grid_a[e, 0], grid_a[e + 1, 0], grid_a[e + 2, 0]
                    v0, v1, v2 = grid_v[e, 0], grid_v[e + 1, 0], grid_v[e + 2, 0]
                    acc = w0 * a0 + w1 * a1 + w2 * a2
                    vg = w0 * v0 + w1 * v1 + w2 * v2
                    L = d0 * v0 + d1 * v1 + d2 * v2
            if e < 0:
                e = _axis(x[i, 0], bx, ux, ihx, Cx, p, w, dw)
                acc = 0.0
                vg = 0.0
                L = 0.0
                for a in range(p + 1):
                    k = e + a
                    acc += w[a] * grid_a[k, 0]
                    vg += w[a] * grid_v[k, 0]
                    L += dw[a] * grid_v[k, 0]
            if store_acc:
                acc_out[i, 0] = acc
            if do_flip:
                v_new[i, 0] = v[i, 0] + vfactor * dt * acc
            dx = dt * vg
            s_mdu += m[i] * dx
            xn = x[i, 0] + dx
            x_new[i, 0] = xn
            u_new[i, 0] = u[i, 0] + dx
            J = 1.0 + dt * L
            if fused:
                stress_new[i, 0, 0] = stress[i, 0, 0] + dt * E * L
                V_new[i] = V[i] * J
            else:
                L_out[i, 0, 0] = L
            if J <= 0.0 and neg < 0:
                neg = i
            if not (np.isfinite(xn) and np.isfinite(v_new[i, 0])) and bad < 0:
                bad = i
            if (xn < lo_x or xn > hi_x) and out < 0:
                out = i
        sums[t, 0] = s_mdu
        flags[t, 0] = bad
        flags[t, 1] = out
        flags[t, 2] = neg


# ----------------------------------------------------------------------- 2D
@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def p2g_2d(x, v, m, V, stress, fext, has_fext, bx, by, ux, uy, ihx, ihy, Cx, Cy, p, nbx,
           copies):
    n = x.shape[0]
    nt = copies.shape[0]
    for t in prange(nt):
        g = copies[t]
        g[:, :] = 0.0
        wx = np.empty(4)
        dx = np.empty(4)
        wy = np.empty(4)
        dy = np.empty(4)
        lo = t * n // nt
        hi = (t + 1) * n // nt
        quadratic = p == 2 and ux and uy
        for i in range(lo, hi):
            mi = m[i]
            px = mi * v[i, 0]
            py = mi * v[i, 1]
            Vi = V[i]
            sxx = Vi * stress[i, 0, 0]
            sxy = Vi * 0.5 * (stress[i, 0, 1] + stress[i, 1, 0])
            syy = Vi * stress[i, 1, 1]
            fx = fext[i, 0] if has_fext else 0.0
            fy = fext[i, 1] if has_fext else 0.0
            if quadratic:
                ex, wx0, wx1, wx2, dx0, dx1, dx2 = _quadratic_interior(x[i, 0], bx, ihx)
                ey, wy0, wy1, wy2, dy0, dy1, dy2 = _quadratic_interior(x[i, 1], by, ihy)
                if ex >= 0 and ey >= 0:
                    row = ey * nbx + ex
                    _p2g_row(g, row, wy0, dy0, wx0, wx1, wx2, dx0, dx1, dx2,
                             mi, px, py, fx, fy, sxx, sxy, syy)
                    _p2g_row(g, row + nbx, wy1, dy1, wx0, wx1, wx2, dx0, dx1, dx2,
                             mi, px, py, fx, fy, sxx, sxy, syy)
                    _p2g_row(g, row + 2 * nbx, wy2, dy2, wx0, wx1, wx2, dx0, dx1, dx2,
                             mi, px, py, fx, fy, sxx, sxy, syy)
                    continue
            ex = _axis(x[i, 0], bx, ux, ihx, Cx, p, wx, dx)
            ey = _axis(x[i, 1], by, uy, ihy, Cy, p, wy, dy)
            for b in range(p + 1):
                row = (ey + b) * nbx + ex
                for a in range(p + 1):
                    N = wx[a] * wy[b]
                    gx = dx[a] * wy[b]
                    gy = wx[a] * dy[b]
                    k = row + a
                    g[k, 0] += N * mi
                    g[k, 1] += N * px
                    g[k, 2] += N * py
                    g[k, 3] += N * fx - (sxx * gx + sxy * gy)
                    g[k, 4] += N * fy - (sxy * gx + syy * gy)


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def g2p2g_2d(x, v, m, grid_a, dt, bx, by, ux, uy, ihx, ihy, Cx, Cy, p, nbx, v_new, copies):
    n = x.shape[0]
    nt = copies.shape[0]
    for t in prange(nt):
        g = copies[t]
        g[:, :] = 0.0
        wx = np.empty(4)
        dx = np.empty(4)
        wy = np.empty(4)
        dy = np.empty(4)
        lo = t * n // nt
        hi = (t + 1) * n // nt
        quadratic = p == 2 and ux and uy
        for i in range(lo, hi):
            if quadratic:
                ex, wx0, wx1, wx2, _, _, _ = _quadratic_interior(x[i, 0], bx, ihx)
                ey, wy0, wy1, wy2, _, _, _ = _quadratic_interior(x[i, 1], by, ihy)
                if ex >= 0 and ey >= 0:
                    r0 = ey * nbx + ex
                    r1 = r0 + nbx
                    r2 = r1 + nbx
                    a0x, a0y = _gather_row(grid_a, r0, wy0, wx0, wx1, wx2)
                    a1x, a1y = _gather_row(grid_a, r1, wy1, wx0, wx1, wx2)
                    a2x, a2y = _gather_row(grid_a, r2, wy2, wx0, wx1, wx2)
                    vx = v[i, 0] + dt * (a0x + a1x + a2x)
                    vy = v[i, 1] + dt * (a0y + a1y + a2y)
                    v_new[i, 0] = vx
                    v_new[i, 1] = vy
                    px = m[i] * vx
                    py = m[i] * vy
                    _scatter_row(g, r0, wy0, wx0, wx1, wx2, px, py)
                    _scatter_row(g, r1, wy1, wx0, wx1, wx2, px, py)
                    _scatter_row(g, r2, wy2, wx0, wx1, wx2, px, py)
                    continue
            ex = _axis(x[i, 0], bx, ux, ihx, Cx, p, wx, dx)
            ey = _axis(x[i, 1], by, uy, ihy, Cy, p, wy, dy)
            ax = 0.0
            ay = 0.0
            for b in range(p + 1):
                row = (ey + b) * nbx + ex
                for a in range(p + 1):
                    N = wx[a] * wy[b]
                    ax += N * grid_a[row + a, 0]
                    ay += N * grid_a[row + a, 1]
            vx = v[i, 0] + dt * ax
            vy = v[i, 1] + dt * ay
            v_new[i, 0] = vx
            v_new[i, 1] = vy
            px = m[i] * vx
            py = m[i] * vy
            for b in range(p + 1):
                row = (ey + b) * nbx + ex
                for a in range(p + 1):
                    N = wx[a] * wy[b]
                    g[row + a, 0] += N * px
                    g[row + a, 1] += N * py


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def g2p_2d(x, v, u, m, stress, V, grid_a, grid_v, dt, vfactor, do_flip, bx, by, ux, uy, ihx,
           ihy, Cx, Cy, p, nbx, lo_x, hi_x, lo_y, hi_y, fused, lam, mu, x_new, v_new, u_new,
           stress_new, V_new, L_out, acc_out, store_acc, sums, flags):
    n = x.shape[0]
    nt = sums.shape[0]
    for t in prange(nt):
        wx = np.empty(4)
        dx = np.empty(4)
        wy = np.empty(4)
        dy = np.empty(4)
        lo = t * n // nt
        hi = (t + 1) * n // nt
        bad = -1
        out = -1
        neg = -1
        smx = 0.0
        smy = 0.0
        quadratic = p == 2 and ux and uy
        for i in range(lo, hi):
            ax = 0.0
            ay = 0.0
            vx = 0.0
            vy = 0.0
            Lxx = 0.0
            Lxy = 0.0
            Lyx = 0.0
            Lyy = 0.0
            done = False
            if quadratic:
                ex, wx0, wx1, wx2, dx0, dx1, dx2 = _quadratic_interior(x[i, 0], bx, ihx)
                ey, wy0, wy1, wy2, dy0, dy1, dy2 = _quadratic_interior(x[i, 1], by, ihy)
                if ex >= 0 and ey >= 0:
                    done = True
                    row = ey * nbx + ex
                    for b in range(3):
                        if b == 0:
                            wb, db = wy0, dy0
                        elif b == 1:
                            wb, db = wy1, dy1
                        else:
                            wb, db = wy2, dy2
                        r = _g2p_row(grid_a, grid_v, row + b * nbx, wb, db,
                                     wx0, wx1, wx2, dx0, dx1, dx2)
                        ax += r[0]
                        ay += r[1]
                        vx += r[2]
                        vy += r[3]
                        Lxx += r[4]
                        Lxy += r[5]
                        Lyx += r[6]
                        Lyy += r[7]
            if not done:
                ex = _axis(x[i, 0], bx, ux, ihx, Cx, p, wx, dx)
                ey = _axis(x[i, 1], by, uy, ihy, Cy, p, wy, dy)
            for b in range(0 if done else p + 1):
                row = (ey + b) * nbx + ex
                for a in range(p + 1):
                    N = wx[a] * wy[b]
                    gx = dx[a] * wy[b]
                    gy = wx[a] * dy[b]
                    k = row + a
                    ax += N * grid_a[k, 0]
                    ay += N * grid_a[k, 1]
                    gvx = grid_v[k, 0]
                    gvy = grid_v[k, 1]
                    vx += N * gvx
                    vy += N * gvy
                    Lxx += gvx * gx
                    Lxy += gvx * gy
                    Lyx += gvy * gx
                    Lyy += gvy * gy
            if store_acc:
                acc_out[i, 0] = ax
                acc_out[i, 1] = ay
            if do_flip:
                v_new[i, 0] = v[i, 0] + vfactor * dt * ax
                v_new[i, 1] = v[i, 1] + vfactor * dt * ay
            xn = x[i, 0] + dt * vx
            yn = x[i, 1] + dt * vy
            x_new[i, 0] = xn
            x_new[i, 1] = yn
            u_new[i, 0] = u[i, 0] + dt * vx
            u_new[i, 1] = u[i, 1] + dt * vy
            smx += m[i] * (dt * vx)
            smy += m[i] * (dt * vy)
            J = (1.0 + dt * Lxx) * (1.0 + dt * Lyy) - dt * dt * Lxy * Lyx
            if fused:
                Dxx = dt * Lxx
                Dyy = dt * Lyy
                Dxy = 0.5 * dt * (Lxy + Lyx)
                tr = lam * (Dxx + Dyy)
                stress_new[i, 0, 0] = stress[i, 0, 0] + tr + 2.0 * mu * Dxx
                stress_new[i, 1, 1] = stress[i, 1, 1] + tr + 2.0 * mu * Dyy
                sxy = stress[i, 0, 1] + 2.0 * mu * Dxy
                stress_new[i, 0, 1] = sxy
                stress_new[i, 1, 0] = stress[i, 1, 0] + 2.0 * mu * Dxy
                V_new[i] = V[i] * J
            else:
                L_out[i, 0, 0] = Lxx
                L_out[i, 0, 1] = Lxy
                L_out[i, 1, 0] = Lyx
                L_out[i, 1, 1] = Lyy
            if J <= 0.0 and neg < 0:
                neg = i
            ok = np.isfinite(xn) and np.isfinite(yn) and np.isfinite(v_new[i, 0]) \
                and np.isfinite(v_new[i, 1])
            if not ok and bad < 0:
                bad = i
            if (xn < lo_x or xn > hi_x or yn < lo_y or yn > hi_y) and out < 0:
                out = i
        sums[t, 0] = smx
        sums[t, 1] = smy
        flags[t, 0] = bad
        flags[t, 1] = out
        flags[t, 2] = neg


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def consistent_1d(x, m, bx, ux, ihx, Cx, p, mass_copies, stiff_copies):
    """M_(k, k+d) = sum m_p N_k N_(k+d) into a stencil (dofs, 2p+1), and
    sum m_p (dN_k/dx)^2 per dof (the fast-dof guard's stiffness weights)."""
    n = x.shape[0]
    nt = mass_copies.shape[0]
    width = 2 * p + 1
    for t in prange(nt):
        M = mass_copies[t]
        K = stiff_copies[t]
        M[:, :] = 0.0
        K[:] = 0.0
        w = np.empty(4)
        dw = np.empty(4)
        lo = t * n // nt
        hi = (t + 1) * n // nt
        for i in range(lo, hi):
            e = _axis(x[i, 0], bx, ux, ihx, Cx, p, w, dw)
            mi = m[i]
            for a in range(p + 1):
                K[e + a] += mi * dw[a] * dw[a]
                wa = mi * w[a]
                for a2 in range(p + 1):
                    M[e + a, a2 - a + p] += wa * w[a2]
    return width


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def consistent_2d(x, m, bx, by, ux, uy, ihx, ihy, Cx, Cy, p, nbx, mass_copies, stiff_copies):
    """The 2D stencil of the consistent mass (offsets -p..p per axis, column
    (db + p)(2p + 1) + da + p) and the per-dof sum m_p |grad N_k|^2."""
    n = x.shape[0]
    nt = mass_copies.shape[0]
    width = 2 * p + 1
    for t in prange(nt):
        M = mass_copies[t]
        K = stiff_copies[t]
        M[:, :] = 0.0
        K[:] = 0.0
        wx = np.empty(4)
        dx = np.empty(4)
        wy = np.empty(4)
        dy = np.empty(4)
        lo = t * n // nt
        hi = (t + 1) * n // nt
        for i in range(lo, hi):
            ex = _axis(x[i, 0], bx, ux, ihx, Cx, p, wx, dx)
            ey = _axis(x[i, 1], by, uy, ihy, Cy, p, wy, dy)
            mi = m[i]
            for b in range(p + 1):
                for a in range(p + 1):
                    k = (ey + b) * nbx + ex + a
                    gx = dx[a] * wy[b]
                    gy = wx[a] * dy[b]
                    K[k] += mi * (gx * gx + gy * gy)
                    wab = mi * wx[a] * wy[b]
                    for b2 in range(p + 1):
                        for a2 in range(p + 1):
                            s = (b2 - b + p) * width + (a2 - a + p)
                            M[k, s] += wab * wx[a2] * wy[b2]
    return width


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def _reduce_stencil(mass_copies, stiff_copies, M, K):
    nt, nk, ns = mass_copies.shape
    for k in prange(nk):
        sk = 0.0
        for t in range(nt):
            sk += stiff_copies[t, k]
        K[k] = sk
        for s in range(ns):
            sm = 0.0
            for t in range(nt):
                sm += mass_copies[t, k, s]
            M[k, s] = sm


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
             vdt, v_old, a, v_new):
    """The USL/CD grid step in one pass: v_old = P / m, a = f / m + g,
    v_new = v_old + vdt a on free dofs with mass; constraint values (or 0)
    on constrained dofs; 0 on empty dofs."""
    nk, dim = force.shape
    for k in prange(nk):
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
            v_old[k, c] = vo
            a[k, c] = ak
            v_new[k, c] = vo + vdt * ak


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


class Kernels:
    """The compiled kernels bound to one spline grid (and its thread count)."""

    def __init__(self, grid):
        self.grid = grid
        self.dim = grid.dim
        self.p = grid.degree
        self.nthreads = get_num_threads()
        b = grid.breakpoints
        self.args = []
        for axis in range(grid.dim):
            u = b[axis]
            self.args.append((u, bool(grid._uniform[axis]), (u.size - 1) / (u[-1] - u[0]),
                              grid.extraction[axis]))
        self.ndofs = grid.ndofs
        self.nbx = grid.basis_per_axis[0]
        self._copies = {}
        self._mass = np.empty(grid.ndofs)
        self._p2g_momentum = np.empty((grid.ndofs, grid.dim))
        self._force = np.empty((grid.ndofs, grid.dim))
        self._momentum = np.empty((grid.ndofs, grid.dim))
        self._small = np.empty(grid.ndofs, dtype=np.bool_)
        self.sums = np.zeros((self.nthreads, grid.dim))
        self.flags = np.full((self.nthreads, 3), -1, dtype=np.int64)

    def _buffer(self, ncomp):
        key = ncomp
        if key not in self._copies:
            self._copies[key] = np.empty((self.nthreads, self.ndofs, ncomp))
        return self._copies[key]

    def p2g(self, particles, fext):
        """(mass (dofs,), momentum (dofs, dim), force (dofs, dim))."""
        p, dim = particles, self.dim
        has = fext is not None
        fx = fext if has else np.zeros((1, dim))
        copies = self._buffer(1 + 2 * dim)
        if dim == 1:
            (bx, ux, ihx, Cx), = self.args
            p2g_1d(p.x, p.v, p.m, p.V, p.stress, fx, has, bx, ux, ihx, Cx, self.p, copies)
        else:
            (bx, ux, ihx, Cx), (by, uy, ihy, Cy) = self.args
            p2g_2d(p.x, p.v, p.m, p.V, p.stress, fx, has, bx, by, ux, uy, ihx, ihy, Cx, Cy,
                   self.p, self.nbx, copies)
        _reduce_fields(copies, self._mass, self._p2g_momentum, self._force)
        return self._mass, self._p2g_momentum, self._force

    def g2p2g(self, particles, grid_a, dt, v_new):
        """MUSL: v_new = v + dt N a and the grid momentum of m v_new."""
        p, dim = particles, self.dim
        copies = self._buffer(dim)
        if dim == 1:
            (bx, ux, ihx, Cx), = self.args
            g2p2g_1d(p.x, p.v, p.m, grid_a, dt, bx, ux, ihx, Cx, self.p, v_new, copies)
        else:
            (bx, ux, ihx, Cx), (by, uy, ihy, Cy) = self.args
            g2p2g_2d(p.x, p.v, p.m, grid_a, dt, bx, by, ux, uy, ihx, ihy, Cx, Cy, self.p,
                     self.nbx, v_new, copies)
        out = self._momentum
        _reduce(copies, out)
        return out

    def g2p(self, particles, grid_a, grid_v, dt, vfactor, flip, fused, material, new, L_out,
            acc_out=None):
        """Particle update into the arrays of ``new`` (a Particles object);
        returns the flags (first non-finite, outside, J <= 0 particle or -1)."""
        p, dim = particles, self.dim
        sums, flags = self.sums, self.flags
        bounds = self.grid.bounds
        store_acc = acc_out is not None
        if not store_acc:
            acc_out = self.sums  # never written
        if dim == 1:
            (bx, ux, ihx, Cx), = self.args
            E = material.E if fused else 0.0
            g2p_1d(p.x, p.v, p.u, p.m, p.stress, p.V, grid_a, grid_v, dt, vfactor, flip, bx, ux, ihx,
                   Cx, self.p, bounds[0][0], bounds[0][1], fused, E, new.x, new.v, new.u,
                   new.stress, new.V, L_out, acc_out, store_acc, sums, flags)
        else:
            (bx, ux, ihx, Cx), (by, uy, ihy, Cy) = self.args
            lam = material.lam if fused else 0.0
            mu = material.mu if fused else 0.0
            g2p_2d(p.x, p.v, p.u, p.m, p.stress, p.V, grid_a, grid_v, dt, vfactor, flip, bx, by,
                   ux, uy, ihx, ihy, Cx, Cy, self.p, self.nbx, bounds[0][0], bounds[0][1],
                   bounds[1][0], bounds[1][1], fused, lam, mu, new.x, new.v, new.u, new.stress,
                   new.V, L_out, acc_out, store_acc, sums, flags)
        found = []
        for j in range(3):
            column = flags[:, j]
            hits = column[column >= 0]
            found.append(int(hits.min()) if hits.size else -1)
        return found

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
            self._stencil = np.empty((nd, width_total))
            self._stencil_copies = np.empty((self.nthreads, nd, width_total))
            self._stiff_copies = np.empty((self.nthreads, nd))
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

    def consistent_stencil(self, particles):
        """(M as a stencil array (dofs, (2p+1)^dim), sum m_p |grad N_k|^2)."""
        self._stencil_pattern()
        p = particles
        if self.dim == 1:
            (bx, ux, ihx, Cx), = self.args
            consistent_1d(p.x, p.m, bx, ux, ihx, Cx, self.p, self._stencil_copies,
                          self._stiff_copies)
        else:
            (bx, ux, ihx, Cx), (by, uy, ihy, Cy) = self.args
            consistent_2d(p.x, p.m, bx, by, ux, uy, ihx, ihy, Cx, Cy, self.p, self.nbx,
                          self._stencil_copies, self._stiff_copies)
        K = np.empty(self.ndofs)
        stencil = np.empty_like(self._stencil)
        _reduce_stencil(self._stencil_copies, self._stiff_copies, stencil, K)
        return stencil, K

    def mass_times_displacement(self):
        """sum_p m_p du_p of the last g2p call, shape (dim,)."""
        return self.sums.sum(axis=0)

    def small_mass(self, lumped, tol):
        """Boolean mask of tiny-mass dofs (see grid_system) and its count."""
        small = self._small
        if self.dim == 2:
            count = small_mass_2d(lumped, self.nbx, self.grid.basis_per_axis[1], self.p, tol,
                                  small)
        else:
            count = small_mass_1d(lumped, self.p, tol, small)
        return small, int(count)

    def usl_grid(self, mass, momentum, force, gravity, constrained, v_values, a_values, vdt,
                 v_old, a, v_new):
        """One pass of the USL/CD grid step (see usl_grid)."""
        has = v_values is not None
        usl_grid(mass, momentum, force, gravity, constrained, v_values if has else force,
                 a_values if has else force, has, vdt, v_old, a, v_new)

    def solve(self, mass, rhs, gravity, constrained, values, out):
        """Lumped solve into ``out`` (see lumped_solve)."""
        has = values is not None
        lumped_solve(mass, rhs, gravity, constrained, values if has else rhs, has, out)
        return out


# ------------------------------------------------------- consistent mass solve
@njit(cache=True, inline="always")
def _neighbour(k, s, p, nbx, nby, dim):
    """Dof index of stencil slot s of row k, or -1 outside the grid."""
    width = 2 * p + 1
    if dim == 1:
        j = k + s - p
        return j if 0 <= j < nbx else -1
    a = k % nbx + s % width - p
    b = k // nbx + s // width - p
    if a < 0 or a >= nbx or b < 0 or b >= nby:
        return -1
    return b * nbx + a


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def stencil_prepare(M, p, nbx, nby, dim, fixed, fast, out):
    """out = M with (1) the fraction max(fast_i, fast_j) of every
    off-diagonal entry moved onto the diagonal of its row (``fast`` in [0, 1]
    per dof) and (2) the rows and columns of ``fixed`` dofs (constrained or
    massless) replaced by the identity."""
    nk, ns = M.shape
    centre = (ns - 1) // 2
    for k in prange(nk):
        for s in range(ns):
            out[k, s] = 0.0
        if fixed[k]:
            out[k, centre] = 1.0
            continue
        diag = M[k, centre]
        for s in range(ns):
            if s == centre:
                continue
            j = _neighbour(k, s, p, nbx, nby, dim)
            if j < 0:
                continue
            theta = fast[k] if fast[k] > fast[j] else fast[j]
            diag += theta * M[k, s]
            if not fixed[j]:
                out[k, s] = (1.0 - theta) * M[k, s]
        out[k, centre] = diag


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def stencil_matvec(M, p, nbx, nby, dim, x, y):
    """y = M x for a stencil matrix and x of shape (dofs, components)."""
    nc = x.shape[1]
    width = 2 * p + 1
    for b in prange(nby):
        for a in range(nbx):
            k = b * nbx + a
            for c in range(nc):
                acc = 0.0
                if dim == 1:
                    for s in range(width):
                        j = k + s - p
                        if j >= 0 and j < nbx:
                            acc += M[k, s] * x[j, c]
                else:
                    for db in range(-p, p + 1):
                        bb = b + db
                        if bb < 0 or bb >= nby:
                            continue
                        row = (db + p) * width + p
                        for da in range(-p, p + 1):
                            aa = a + da
                            if aa >= 0 and aa < nbx:
                                acc += M[k, row + da] * x[bb * nbx + aa, c]
                y[k, c] = acc


@njit(cache=True, error_model="numpy", fastmath=FAST)
def stencil_pcg(M, p, nbx, nby, dim, inv_diag, b, x, rtol, maxiter):
    """Conjugate gradients for M x = b (all components at once, each with its
    own scalars), Jacobi-preconditioned with ``inv_diag`` (the inverse lumped
    mass), started from x. Returns the iterations of the slowest component."""
    nk, nc = b.shape
    r = np.empty_like(b)
    z = np.empty_like(b)
    d = np.empty_like(b)
    q = np.empty_like(b)
    stencil_matvec(M, p, nbx, nby, dim, x, q)
    rz = np.zeros(nc)
    bnorm = np.zeros(nc)
    for k in range(nk):
        for c in range(nc):
            r[k, c] = b[k, c] - q[k, c]
            z[k, c] = inv_diag[k] * r[k, c]
            d[k, c] = z[k, c]
            rz[c] += r[k, c] * z[k, c]
            bnorm[c] += b[k, c] * b[k, c]
    done = np.zeros(nc, dtype=np.bool_)
    for c in range(nc):
        done[c] = rz[c] <= 0.0 or bnorm[c] == 0.0
    it = 0
    while it < maxiter:
        all_done = True
        for c in range(nc):
            if not done[c]:
                all_done = False
        if all_done:
            break
        it += 1
        stencil_matvec(M, p, nbx, nby, dim, d, q)
        dq = np.zeros(nc)
        for k in range(nk):
            for c in range(nc):
                dq[c] += d[k, c] * q[k, c]
        rz_new = np.zeros(nc)
        rr = np.zeros(nc)
        for c in range(nc):
            if done[c] or dq[c] == 0.0:
                continue
            alpha = rz[c] / dq[c]
            for k in range(nk):
                x[k, c] += alpha * d[k, c]
                r[k, c] -= alpha * q[k, c]
                z[k, c] = inv_diag[k] * r[k, c]
                rz_new[c] += r[k, c] * z[k, c]
                rr[c] += r[k, c] * r[k, c]
        for c in range(nc):
            if done[c]:
                continue
            if rr[c] <= rtol * rtol * bnorm[c]:
                done[c] = True
                continue
            beta = rz_new[c] / rz[c]
            rz[c] = rz_new[c]
            for k in range(nk):
                d[k, c] = z[k, c] + beta * d[k, c]
    return it
