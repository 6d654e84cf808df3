"""Fused particle-grid kernels for tensor B-spline grids (1D and 2D).

The NumPy reference of every kernel is the transfer-matrix code of
:mod:`skfem_mpm.solve.steps`; the tests compare the two to 1e-12. The
kernels recompute the B-spline weights of each particle in each pass instead
of storing N (cheaper than the memory traffic of a stored N), and scatter
race-free: the particles are split into one contiguous block per thread, each
thread adds into its own copy of the grid over the node range its block
touches, and the copies are summed over those ranges (deterministic for a
fixed thread count).

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

from .fringe import apply_corrected
from .kronecker import apply_kronecker
from .tiny_mass import merged_lumped_solve
from .weights import FAST, extracted_functions, locate_axis_point

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
    registers instead of small arrays roughly halves the 1D kernels' time.
    The local coordinate is xi = t - e with t = (x - u_0) / h (no load of
    the cell's breakpoint)."""
    t = (x - breaks[0]) * inv_h
    e = int(np.floor(t))
    if e < 2 or e >= breaks.shape[0] - 3:  # also catches NaN (e is then negative)
        return -1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    xi = t - e
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


@njit(cache=True, error_model="numpy")
def _segments(touched, lo, hi):
    """Split nodes lo..hi-1 where the set of threads whose touched range
    holds them changes: (cuts, members, counts); segment j is
    cuts[j]..cuts[j + 1] - 1 and its threads are members[j, :counts[j]]."""
    nt = touched.shape[0]
    cuts = np.empty(2 * nt + 2, dtype=np.int64)
    cuts[0] = lo
    cuts[1] = hi
    for t in range(nt):
        cuts[2 + 2 * t] = min(max(touched[t, 0], lo), hi)
        cuts[3 + 2 * t] = min(max(touched[t, 1], lo), hi)
    cuts = np.unique(cuts)
    members = np.empty((cuts.shape[0], nt), dtype=np.int64)
    counts = np.zeros(cuts.shape[0], dtype=np.int64)
    for j in range(cuts.shape[0] - 1):
        for t in range(nt):
            if touched[t, 0] <= cuts[j] and cuts[j + 1] <= touched[t, 1]:
                members[j, counts[j]] = t
                counts[j] += 1
    return cuts, members, counts


@njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def _take(copies, threads, count, k, c):
    """sum of copies[t, k, c] over the given threads."""
    s = 0.0
    for j in range(count):
        s += copies[threads[j], k, c]
    return s


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def _reduce_fields(copies, touched, mass, momentum, force, mass_range):
    """Sum the per-thread copies of (m, P, f) into three contiguous arrays;
    mass_range[r] = (smallest positive, largest) mass of chunk r's nodes."""
    nt, nk, nc = copies.shape
    dim = momentum.shape[1]
    nr = mass_range.shape[0]
    for r in prange(nr):
        smallest = np.inf
        largest = 0.0
        cuts, members, counts = _segments(touched, r * nk // nr, (r + 1) * nk // nr)
        for j in range(cuts.shape[0] - 1):
            threads = members[j]
            count = counts[j]
            for k in range(cuts[j], cuts[j + 1]):
                s = _take(copies, threads, count, k, 0)
                mass[k] = s
                if s > 0.0:
                    smallest = min(smallest, s)
                    largest = max(largest, s)
                for c in range(dim):
                    momentum[k, c] = _take(copies, threads, count, k, 1 + c)
                    force[k, c] = _take(copies, threads, count, k, 1 + dim + c)
        mass_range[r, 0] = smallest
        mass_range[r, 1] = largest


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def _reduce(copies, touched, out):
    """out = sum over threads of the per-thread grid copies."""
    nt, nk, nc = copies.shape
    for r in prange(nt):
        cuts, members, counts = _segments(touched, r * nk // nt, (r + 1) * nk // nt)
        for j in range(cuts.shape[0] - 1):
            for k in range(cuts[j], cuts[j + 1]):
                for c in range(nc):
                    out[k, c] = _take(copies, members[j], counts[j], k, c)


# ----------------------------------------------------------------------- 1D
# Sorted particles come in runs sharing a cell. The quadratic 1D kernels add
# a run's contributions to its three nodes in registers (a "window") and
# write them to the grid once per run: adding into memory particle after
# particle makes every particle wait for the previous one's store to the
# same nodes (measured, kernel alone: 5.1 ms -> 3.7 ms per 1e6 particles). Any order
# gives the same sums; unsorted particles only flush more often.
@njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def _flush_window(g, e, c, s0, s1, s2):
    """g[e + a, c] += s_a for the three nodes of a quadratic window."""
    if e >= 0:
        g[e, c] += s0
        g[e + 1, c] += s1
        g[e + 2, c] += s2


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def p2g_1d(x, v, m, V, stress, fext, has_fext, bx, ux, ihx, Cx, p, copies, touched):
    n = x.shape[0]
    nt = copies.shape[0]
    for t in prange(nt):
        g = copies[t]
        _clear_touched(g, touched, t)
        first = g.shape[0]
        last = 0
        w = np.empty(4)
        dw = np.empty(4)
        lo = t * n // nt
        hi = (t + 1) * n // nt
        quadratic = p == 2 and ux
        run = -1  # the window's cell; its sums of (m, m v, f) per node:
        m0 = m1 = m2 = p0 = p1 = p2 = f0 = f1 = f2 = 0.0
        for i in range(lo, hi):
            mi = m[i]
            pv = mi * v[i, 0]
            s = V[i] * stress[i, 0, 0]
            f = fext[i, 0] if has_fext else 0.0
            if quadratic:
                e, w0, w1, w2, d0, d1, d2 = _quadratic_interior(x[i, 0], bx, ihx)
                if e >= 0:
                    if e != run:
                        _flush_window(g, run, 0, m0, m1, m2)
                        _flush_window(g, run, 1, p0, p1, p2)
                        _flush_window(g, run, 2, f0, f1, f2)
                        run = e
                        first = min(first, e)
                        last = max(last, e + 3)
                        m0 = m1 = m2 = p0 = p1 = p2 = f0 = f1 = f2 = 0.0
                    m0 += w0 * mi
                    m1 += w1 * mi
                    m2 += w2 * mi
                    p0 += w0 * pv
                    p1 += w1 * pv
                    p2 += w2 * pv
                    f0 += w0 * f - s * d0
                    f1 += w1 * f - s * d1
                    f2 += w2 * f - s * d2
                    continue
            e = _axis(x[i, 0], bx, ux, ihx, Cx, p, w, dw)
            first = min(first, e)
            last = max(last, e + p + 1)
            for a in range(p + 1):
                k = e + a
                g[k, 0] += w[a] * mi
                g[k, 1] += w[a] * pv
                g[k, 2] += w[a] * f - s * dw[a]
        _flush_window(g, run, 0, m0, m1, m2)
        _flush_window(g, run, 1, p0, p1, p2)
        _flush_window(g, run, 2, f0, f1, f2)
        touched[t, 0] = first
        touched[t, 1] = last


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def g2p2g_1d(x, v, m, grid_a, dt, bx, ux, ihx, Cx, p, v_new, copies, touched):
    n = x.shape[0]
    nt = copies.shape[0]
    for t in prange(nt):
        g = copies[t]
        _clear_touched(g, touched, t)
        first = g.shape[0]
        last = 0
        w = np.empty(4)
        dw = np.empty(4)
        lo = t * n // nt
        hi = (t + 1) * n // nt
        quadratic = p == 2 and ux
        run = -1
        p0 = p1 = p2 = 0.0
        for i in range(lo, hi):
            if quadratic:
                e, w0, w1, w2, d0, d1, d2 = _quadratic_interior(x[i, 0], bx, ihx)
                if e >= 0:
                    vn = v[i, 0] + dt * (w0 * grid_a[e, 0] + w1 * grid_a[e + 1, 0]
                                         + w2 * grid_a[e + 2, 0])
                    v_new[i, 0] = vn
                    pv = m[i] * vn
                    if e != run:
                        _flush_window(g, run, 0, p0, p1, p2)
                        run = e
                        first = min(first, e)
                        last = max(last, e + 3)
                        p0 = p1 = p2 = 0.0
                    p0 += w0 * pv
                    p1 += w1 * pv
                    p2 += w2 * pv
                    continue
            e = _axis(x[i, 0], bx, ux, ihx, Cx, p, w, dw)
            first = min(first, e)
            last = max(last, e + p + 1)
            acc = 0.0
            for a in range(p + 1):
                acc += w[a] * grid_a[e + a, 0]
            vn = v[i, 0] + dt * acc
            v_new[i, 0] = vn
            pv = m[i] * vn
            for a in range(p + 1):
                g[e + a, 0] += w[a] * pv
        _flush_window(g, run, 0, p0, p1, p2)
        touched[t, 0] = first
        touched[t, 1] = last


@njit(cache=True, error_model="numpy", fastmath=FAST)
def _axis_sums_1d(x, bx, ux, ihx, Cx, p, grid_a, grid_v, w, dw):
    """(sum N a, sum N v, sum dN/dx v) at x by the general basis path (not
    inlined: it serves only the particles the quadratic form does not)."""
    e = _axis(x, bx, ux, ihx, Cx, p, w, dw)
    acc = 0.0
    vg = 0.0
    L = 0.0
    for a in range(p + 1):
        k = e + a
        acc += w[a] * grid_a[k, 0]
        vg += w[a] * grid_v[k, 0]
        L += dw[a] * grid_v[k, 0]
    return acc, vg, L


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def g2p_1d(x, v, u, stress, V, grid_a, grid_v, dt, vfactor, do_flip, bx, ux, ihx, Cx, p,
           lo_x, hi_x, fused, E, x_new, v_new, u_new, stress_new, V_new, L_out, acc_out,
           store_acc, flags):
    n = x.shape[0]
    nt = flags.shape[0]
    for t in prange(nt):
        w = np.empty(4)
        dw = np.empty(4)
        lo = t * n // nt
        hi = (t + 1) * n // nt
        bad = -1
        out = -1
        neg = -1
        quadratic = p == 2 and ux
        for i in range(lo, hi):
            e = -1
            if quadratic:
                e, w0, w1, w2, d0, d1, d2 = _quadratic_interior(x[i, 0], bx, ihx)
                if e >= 0:
                    v0, v1, v2 = grid_v[e, 0], grid_v[e + 1, 0], grid_v[e + 2, 0]
                    acc = w0 * grid_a[e, 0] + w1 * grid_a[e + 1, 0] + w2 * grid_a[e + 2, 0]
                    vg = w0 * v0 + w1 * v1 + w2 * v2
                    L = d0 * v0 + d1 * v1 + d2 * v2
            if e < 0:
                acc, vg, L = _axis_sums_1d(x[i, 0], bx, ux, ihx, Cx, p, grid_a, grid_v, w, dw)
            if store_acc:
                acc_out[i, 0] = acc
            if do_flip:
                vn = v[i, 0] + vfactor * dt * acc
                v_new[i, 0] = vn
            else:
                vn = v_new[i, 0]
            dx = dt * vg
            xn = x[i, 0] + dx
            x_new[i, 0] = xn
            u_new[i, 0] = u[i, 0] + dx
            J = 1.0 + dt * L
            if fused:
                stress_new[i, 0, 0] = stress[i, 0, 0] + dt * E * L
                V_new[i] = V[i] * J
            else:
                L_out[i, 0, 0] = L
            finite = np.isfinite(xn) and np.isfinite(vn)
            inside = not (xn < lo_x or xn > hi_x)  # NaN counts as non-finite only
            if J <= 0.0 or not finite or not inside:  # one test on the common path
                if J <= 0.0 and neg < 0:
                    neg = i
                if not finite and bad < 0:
                    bad = i
                if not inside and out < 0:
                    out = i
        flags[t, 0] = bad
        flags[t, 1] = out
        flags[t, 2] = neg


# ----------------------------------------------------------------------- 2D
@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def p2g_2d(x, v, m, V, stress, fext, has_fext, bx, by, ux, uy, ihx, ihy, Cx, Cy, p, nbx,
           copies, touched):
    n = x.shape[0]
    nt = copies.shape[0]
    for t in prange(nt):
        g = copies[t]
        _clear_touched(g, touched, t)
        first = g.shape[0]
        last = 0
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
                    first = min(first, row)
                    last = max(last, row + 2 * nbx + 3)
                    _p2g_row(g, row, wy0, dy0, wx0, wx1, wx2, dx0, dx1, dx2,
                             mi, px, py, fx, fy, sxx, sxy, syy)
                    _p2g_row(g, row + nbx, wy1, dy1, wx0, wx1, wx2, dx0, dx1, dx2,
                             mi, px, py, fx, fy, sxx, sxy, syy)
                    _p2g_row(g, row + 2 * nbx, wy2, dy2, wx0, wx1, wx2, dx0, dx1, dx2,
                             mi, px, py, fx, fy, sxx, sxy, syy)
                    continue
            ex = _axis(x[i, 0], bx, ux, ihx, Cx, p, wx, dx)
            ey = _axis(x[i, 1], by, uy, ihy, Cy, p, wy, dy)
            first = min(first, ey * nbx + ex)
            last = max(last, (ey + p) * nbx + ex + p + 1)
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
        touched[t, 0] = first
        touched[t, 1] = last


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def g2p2g_2d(x, v, m, grid_a, dt, bx, by, ux, uy, ihx, ihy, Cx, Cy, p, nbx, v_new, copies,
             touched):
    n = x.shape[0]
    nt = copies.shape[0]
    for t in prange(nt):
        g = copies[t]
        _clear_touched(g, touched, t)
        first = g.shape[0]
        last = 0
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
                    first = min(first, r0)
                    last = max(last, r0 + 2 * nbx + 3)
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
            first = min(first, ey * nbx + ex)
            last = max(last, (ey + p) * nbx + ex + p + 1)
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
        touched[t, 0] = first
        touched[t, 1] = last


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def g2p_2d(x, v, u, stress, V, grid_a, grid_v, dt, vfactor, do_flip, bx, by, ux, uy, ihx,
           ihy, Cx, Cy, p, nbx, lo_x, hi_x, lo_y, hi_y, fused, lam, mu, x_new, v_new, u_new,
           stress_new, V_new, L_out, acc_out, store_acc, flags):
    n = x.shape[0]
    nt = flags.shape[0]
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
                vnx = v[i, 0] + vfactor * dt * ax
                vny = v[i, 1] + vfactor * dt * ay
                v_new[i, 0] = vnx
                v_new[i, 1] = vny
            else:
                vnx = v_new[i, 0]
                vny = v_new[i, 1]
            xn = x[i, 0] + dt * vx
            yn = x[i, 1] + dt * vy
            x_new[i, 0] = xn
            x_new[i, 1] = yn
            u_new[i, 0] = u[i, 0] + dt * vx
            u_new[i, 1] = u[i, 1] + dt * vy
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
            finite = np.isfinite(xn) and np.isfinite(yn) and np.isfinite(vnx) \
                and np.isfinite(vny)
            inside = not (xn < lo_x or xn > hi_x or yn < lo_y or yn > hi_y)
            if J <= 0.0 or not finite or not inside:  # one test on the common path
                if J <= 0.0 and neg < 0:
                    neg = i
                if not finite and bad < 0:
                    bad = i
                if not inside and out < 0:
                    out = i
        flags[t, 0] = bad
        flags[t, 1] = out
        flags[t, 2] = neg


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def consistent_1d(x, m, bx, ux, ihx, Cx, p, mass_copies, stiff_copies, touched):
    """Upper half of the consistent mass, M_(k, k+d) = sum m_p N_k N_(k+d)
    for d = 0..p (column d), and sum m_p (dN_k/dx)^2 per dof (the fast-dof
    guard's stiffness weights), into per-thread copies over the node range
    each thread touches (``touched``, as the scatter kernels).
    :func:`reduce_stencil` sums them and mirrors the rest."""
    n = x.shape[0]
    nt = mass_copies.shape[0]
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
            e = _axis(x[i, 0], bx, ux, ihx, Cx, p, w, dw)
            first = min(first, e)
            last = max(last, e + p + 1)
            mi = m[i]
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


# Quadratic interior particles of one cell share its 3 x 3 nodes, so a run
# of them (sorted particles come in runs) is summed in a small window and
# written once per run, as in the 1D kernels. By the tensor structure,
# N_(a,b) N_(a2,b2) = (wx_a wx_a2)(wy_b wy_b2): the window holds the 6 x 6
# sums S[y-pair, x-pair] = sum m_p (wy_b wy_b2)(wx_a wx_a2) over the
# symmetric index pairs (0,0) (0,1) (0,2) (1,1) (1,2) (2,2) (_PAIR), and
# the 9 stiffness weights.
_PAIR = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]])


@njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def _flush_mass_window(M, K, S, Kw, ex, ey, nbx):
    """Add a quadratic run window (cell (ex, ey); none if ex < 0) into the
    upper half of the stencil M (width 5, slots as :func:`_mass_pairs`) and
    into K, and clear it."""
    if ex < 0:
        return
    for b in range(3):
        for a in range(3):
            k = (ey + b) * nbx + ex + a
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


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def consistent_2d(x, m, bx, by, ux, uy, ihx, ihy, Cx, Cy, p, nbx, mass_copies, stiff_copies,
                  touched):
    """Upper half of the 2D stencil of the consistent mass (the slots from
    the centre on, offsets (da, db) with db > 0 or db = 0 <= da; slot
    (db + p)(2p + 1) + da + p - centre) and the per-dof sum m_p |grad N_k|^2.
    Per-thread copies over touched node ranges, as :func:`consistent_1d`;
    :func:`reduce_stencil` mirrors the lower half (M is symmetric).
    Quadratic interior particles are summed per run of a cell first (see
    :func:`_flush_mass_window`)."""
    n = x.shape[0]
    nt = mass_copies.shape[0]
    width = 2 * p + 1
    quadratic = p == 2 and ux and uy
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
        for i in range(lo, hi):
            mi = m[i]
            if quadratic:
                ex, wx0, wx1, wx2, dx0, dx1, dx2 = _quadratic_interior(x[i, 0], bx, ihx)
                ey, wy0, wy1, wy2, dy0, dy1, dy2 = _quadratic_interior(x[i, 1], by, ihy)
                if ex >= 0 and ey >= 0:
                    if ex != run_x or ey != run_y:
                        _flush_mass_window(M, K, S, Kw, run_x, run_y, nbx)
                        run_x = ex
                        run_y = ey
                        first = min(first, ey * nbx + ex)
                        last = max(last, (ey + 2) * nbx + ex + 3)
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
                    continue
            ex = _axis(x[i, 0], bx, ux, ihx, Cx, p, wx, dx)
            ey = _axis(x[i, 1], by, uy, ihy, Cy, p, wy, dy)
            first = min(first, ey * nbx + ex)
            last = max(last, (ey + p) * nbx + ex + p + 1)
            for b in range(p + 1):
                for a in range(p + 1):
                    _mass_pairs(M, K, (ey + b) * nbx + ex + a, a, b, wx, dx, wy, dy, mi, p,
                                width, nbx)
        _flush_mass_window(M, K, S, Kw, run_x, run_y, nbx)
        touched[t, 0] = first
        touched[t, 1] = last


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def reduce_stencil(mass_copies, stiff_copies, touched, lo, hi, p, nbx, nby, dim, M, K):
    """Rows lo..hi-1 (the union of the touched ranges; the caller keeps the
    other rows zero): sum the per-thread upper halves into M[:, centre:] and
    K, then mirror the lower half, M[k, s] = M[j, ns - 1 - s] (j the dof at
    slot s of k; a row outside lo..hi-1 has no entry pairing it with k)."""
    nt, nk, nh = mass_copies.shape
    ns = 2 * nh - 1
    centre = nh - 1
    for r in prange(nt):
        cuts, members, counts = _segments(touched, lo + r * (hi - lo) // nt,
                                          lo + (r + 1) * (hi - lo) // nt)
        for j in range(cuts.shape[0] - 1):
            threads = members[j]
            count = counts[j]
            for k in range(cuts[j], cuts[j + 1]):
                sk = 0.0
                for i in range(count):
                    sk += stiff_copies[threads[i], k]
                K[k] = sk
                for s in range(nh):
                    M[k, centre + s] = _take(mass_copies, threads, count, k, s)
    width = 2 * p + 1
    pb = p if dim == 2 else 0
    for k in prange(lo, hi):
        a = k % nbx
        b = k // nbx
        for s in range(centre):
            j = _slot_dof(a, b, s, p, pb, width, nbx, nby)
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
             vdt, a, v_new):
    """The USL/CD grid step in one pass: a = f / m + g, v_new = P / m + vdt a
    on free dofs with mass; constraint values (or 0) on constrained dofs; 0
    on empty dofs."""
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
            a[k, c] = ak
            v_new[k, c] = vo + vdt * ak


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def mass_weighted_sum(mass, v, out):
    """out[c] = sum_k m_k v_k,c (compiled: NumPy's BLAS product would leave
    its threads spinning against the kernels' on a small machine)."""
    nk, dim = v.shape
    for c in range(dim):
        s = 0.0
        for k in prange(nk):
            s += mass[k] * v[k, c]
        out[c] = s


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


def _first_flags(rows):
    """Per flag column, the smallest particle index >= 0 over the threads'
    rows, or -1 (a few threads: plain Python beats array calls here)."""
    found = []
    for j in range(3):
        hits = [row[j] for row in rows if row[j] >= 0]
        found.append(min(hits) if hits else -1)
    return found


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
        self._scratch = {}
        self._mass = np.empty(grid.ndofs)
        self._p2g_momentum = np.empty((grid.ndofs, grid.dim))
        self._force = np.empty((grid.ndofs, grid.dim))
        self._momentum = np.empty((grid.ndofs, grid.dim))
        self._small = np.empty(grid.ndofs, dtype=np.bool_)
        self._mass_range = np.zeros((self.nthreads, 2))
        self._no_acc = np.zeros((1, grid.dim))
        self.flags = np.full((self.nthreads, 3), -1, dtype=np.int64)

    def _buffer(self, ncomp):
        """Per-thread grid copies with ncomp fields (zero between calls) and
        their touched node ranges."""
        if ncomp not in self._copies:
            self._copies[ncomp] = (np.zeros((self.nthreads, self.ndofs, ncomp)),
                                   np.zeros((self.nthreads, 2), dtype=np.int64))
        return self._copies[ncomp]

    def p2g(self, particles, fext):
        """(mass (dofs,), momentum (dofs, dim), force (dofs, dim))."""
        p, dim = particles, self.dim
        has = fext is not None
        fx = fext if has else np.zeros((1, dim))
        copies, touched = self._buffer(1 + 2 * dim)
        if dim == 1:
            (bx, ux, ihx, Cx), = self.args
            p2g_1d(p.x, p.v, p.m, p.V, p.stress, fx, has, bx, ux, ihx, Cx, self.p, copies,
                   touched)
        else:
            (bx, ux, ihx, Cx), (by, uy, ihy, Cy) = self.args
            p2g_2d(p.x, p.v, p.m, p.V, p.stress, fx, has, bx, by, ux, uy, ihx, ihy, Cx, Cy,
                   self.p, self.nbx, copies, touched)
        _reduce_fields(copies, touched, self._mass, self._p2g_momentum, self._force,
                       self._mass_range)
        return self._mass, self._p2g_momentum, self._force

    def g2p2g(self, particles, grid_a, dt, v_new):
        """MUSL: v_new = v + dt N a and the grid momentum of m v_new."""
        p, dim = particles, self.dim
        copies, touched = self._buffer(dim)
        if dim == 1:
            (bx, ux, ihx, Cx), = self.args
            g2p2g_1d(p.x, p.v, p.m, grid_a, dt, bx, ux, ihx, Cx, self.p, v_new, copies, touched)
        else:
            (bx, ux, ihx, Cx), (by, uy, ihy, Cy) = self.args
            g2p2g_2d(p.x, p.v, p.m, grid_a, dt, bx, by, ux, uy, ihx, ihy, Cx, Cy, self.p,
                     self.nbx, v_new, copies, touched)
        out = self._momentum
        _reduce(copies, touched, out)
        return out

    def g2p(self, particles, grid_a, grid_v, dt, vfactor, flip, fused, material, new, L_out,
            acc_out=None):
        """Particle update into the arrays of ``new`` (a Particles object);
        returns the flags (first non-finite, outside, J <= 0 particle or -1)."""
        p, dim = particles, self.dim
        flags = self.flags
        bounds = self.grid.bounds
        store_acc = acc_out is not None
        if not store_acc:
            acc_out = self._no_acc  # never written
        if dim == 1:
            (bx, ux, ihx, Cx), = self.args
            E = material.E if fused else 0.0
            g2p_1d(p.x, p.v, p.u, p.stress, p.V, grid_a, grid_v, dt, vfactor, flip, bx, ux, ihx,
                   Cx, self.p, bounds[0][0], bounds[0][1], fused, E, new.x, new.v, new.u,
                   new.stress, new.V, L_out, acc_out, store_acc, flags)
        else:
            (bx, ux, ihx, Cx), (by, uy, ihy, Cy) = self.args
            lam = material.lam if fused else 0.0
            mu = material.mu if fused else 0.0
            g2p_2d(p.x, p.v, p.u, p.stress, p.V, grid_a, grid_v, dt, vfactor, flip, bx, by,
                   ux, uy, ihx, ihy, Cx, Cy, self.p, self.nbx, bounds[0][0], bounds[0][1],
                   bounds[1][0], bounds[1][1], fused, lam, mu, new.x, new.v, new.u, new.stress,
                   new.V, L_out, acc_out, store_acc, flags)
        return _first_flags(flags.tolist())

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

    def consistent_stencil(self, particles):
        """(M as a stencil array (dofs, (2p+1)^dim), sum m_p |grad N_k|^2);
        both arrays are reused by the next call."""
        self._stencil_pattern()
        p = particles
        touched = self._stencil_touched
        if self.dim == 1:
            (bx, ux, ihx, Cx), = self.args
            consistent_1d(p.x, p.m, bx, ux, ihx, Cx, self.p, self._stencil_copies,
                          self._stiff_copies, touched)
        else:
            (bx, ux, ihx, Cx), (by, uy, ihy, Cy) = self.args
            consistent_2d(p.x, p.m, bx, by, ux, uy, ihx, ihy, Cx, Cy, self.p, self.nbx,
                          self._stencil_copies, self._stiff_copies, touched)
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
        reduce_stencil(self._stencil_copies, self._stiff_copies, touched, lo, hi,
                       *self.stencil_geometry, stencil, K)
        return stencil, K

    @property
    def stencil_geometry(self):
        """(p, nbx, nby, dim) of the stencil helpers (1D: nbx = dofs)."""
        if self.dim == 1:
            return self.p, self.ndofs, 1, 1
        return (self.p, *self.grid.basis_per_axis, 2)

    def axis_mass(self):
        """([bands per axis], [row sums per axis]) of the unit-density Gauss
        mass of each axis (the Kronecker preconditioner's factors)."""
        if getattr(self, "_axis_mass", None) is None:
            from .kronecker import axis_mass_bands

            pairs = [axis_mass_bands(self.grid, axis) for axis in range(self.dim)]
            self._axis_mass = ([b for b, _ in pairs], [s for _, s in pairs])
        return self._axis_mass

    def scratch(self, name, shape, dtype=np.float64):
        """A work array kept between steps (allocating it anew each step
        costs page faults); valid until the next request of the same name."""
        a = self._scratch.get(name)
        if a is None or a.size < int(np.prod(shape)) or a.dtype != dtype:
            a = self._scratch[name] = np.empty(int(np.prod(shape)) + 64, dtype=dtype)
        return a[:int(np.prod(shape))].reshape(shape)

    def mass_times_displacement(self, mass, v_grid, dt):
        """sum_p m_p du_p of a g2p call with grid velocity v_grid: equal to
        dt sum_k m_k v_k with m_k the lumped mass of that step's p2g, since
        du_p = dt sum_k N_kp v_k and m_k = sum_p m_p N_kp."""
        out = np.empty(self.dim)
        mass_weighted_sum(mass, v_grid, out)
        return dt * out

    def small_mass(self, lumped, tol):
        """Boolean mask of tiny-mass dofs (see grid_system) and its count.

        On the lumped mass of the last p2g call, a node can only be tiny
        (m_k < tol max of its neighbours) if the smallest positive mass is
        below tol times the largest; otherwise the scan is skipped."""
        small = self._small
        if lumped is self._mass:
            ranges = self._mass_range.tolist()
            if min(r[0] for r in ranges) >= tol * max(r[1] for r in ranges):
                small[:] = False
                return small, 0
        if self.dim == 2:
            count = small_mass_2d(lumped, self.nbx, self.grid.basis_per_axis[1], self.p, tol,
                                  small)
        else:
            count = small_mass_1d(lumped, self.p, tol, small)
        return small, int(count)

    def usl_grid(self, mass, momentum, force, gravity, constrained, v_values, a_values, vdt,
                 a, v_new):
        """One pass of the USL/CD grid step (see usl_grid)."""
        has = v_values is not None
        usl_grid(mass, momentum, force, gravity, constrained, v_values if has else force,
                 a_values if has else force, has, vdt, a, v_new)

    def merged_solve(self, mass, rhs, gravity, constrained, values, tol, out):
        """Lumped solve with the tiny-mass merge into ``out``; returns the
        number of small dofs, or -1 when the reference merge must be used
        (see :mod:`skfem_mpm.kernels.tiny_mass`)."""
        has = values is not None
        nbx, nby = (self.ndofs, 1) if self.dim == 1 else self.grid.basis_per_axis
        return merged_lumped_solve(mass, rhs, gravity, constrained, values if has else rhs, has,
                                   nbx, nby, self.p, tol, out)

    def solve(self, mass, rhs, gravity, constrained, values, out):
        """Lumped solve into ``out`` (see lumped_solve)."""
        has = values is not None
        lumped_solve(mass, rhs, gravity, constrained, values if has else rhs, has, out)
        return out


# ------------------------------------------------------- consistent mass solve
# The consistent system is solved on its free dofs only (free: has mass and
# is not constrained in the component group), stored row by row in ELL form:
# A[r, s] is the entry of stencil slot s of free row r and cols[r, s] its
# free column (fixed and outside columns point at r itself with a zero
# entry, so the product needs no branches).


@njit(cache=True, inline="always")
def _slot_dof(a, b, s, p, pb, width, nbx, nby):
    """Dof at stencil slot s of the dof (a, b) (slot (db + pb) width + da + p;
    pb = p in 2D, 0 in 1D), or -1 outside the grid."""
    aa = a + s % width - p
    bb = b + s // width - pb
    if aa < 0 or aa >= nbx or bb < 0 or bb >= nby:
        return -1
    return bb * nbx + aa


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def compact_system(M, p, nbx, nby, dim, rows, index, fast, A, cols, F, fcols, write_cols,
                   write_fixed):
    """The free-dof rows of the consistent mass, ELL form.

    Row k = rows[r] of M with (1) the fraction theta = max(fast_k, fast_j) of
    every off-diagonal entry moved onto the diagonal (fast-row lumping,
    ``fast`` in [0, 1] per dof) and (2) its columns split into free ones
    (index[j] >= 0: A[r, s], cols[r, s] = index[j]) and fixed ones
    (F[r, s] = (1 - theta) M_kj, fcols[r, s] = j), which
    :func:`compact_problem` moves to the right-hand side. cols depends on
    the free-dof set only and F, fcols are read only for nonzero fixed
    values: they are written when ``write_cols``, ``write_fixed``."""
    nr = rows.shape[0]
    ns = M.shape[1]
    centre = (ns - 1) // 2
    width = 2 * p + 1
    pb = p if dim == 2 else 0
    for r in prange(nr):
        k = rows[r]
        diag = M[k, centre]
        a = k % nbx
        b = k // nbx
        for s in range(ns):
            A[r, s] = 0.0
            if write_cols:
                cols[r, s] = r
            if write_fixed:
                F[r, s] = 0.0
                fcols[r, s] = k
            if s == centre:
                continue
            j = _slot_dof(a, b, s, p, pb, width, nbx, nby)
            if j < 0:
                continue
            mks = M[k, s]
            theta = fast[k] if fast[k] > fast[j] else fast[j]
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
def fast_row_fractions(stiffness, stencil, mass, limit, out):
    """out_k = theta(K_k / (limit M_kk)) on dofs with mass, 0 on the others:
    the fast-row lumping fractions of :func:`skfem_mpm.solve.timestep.lumping_fraction`
    (theta(q) = smoothstep(2 q - 1)) in one pass; returns their count > 0."""
    centre = (stencil.shape[1] - 1) // 2
    count = 0
    for k in prange(mass.shape[0]):
        theta = 0.0
        if mass[k] > 0.0:
            q = stiffness[k] / (limit * max(stencil[k, centre], 1e-300))
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
    width = 2 * p + 1
    pb = p if dim == 2 else 0
    for r in prange(rows.shape[0]):
        k = rows[r]
        diag = M[k, centre]
        a = k % nbx
        b = k // nbx
        for c in range(nc):
            y[r, c] = 0.0
        for s in range(ns):
            if s == centre:
                continue
            j = _slot_dof(a, b, s, p, pb, width, nbx, nby)
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


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def _ell_product_dot(A, cols, d, q, partial):
    """q = A d and partial[t, c] = sum over thread t's rows of d_c q_c."""
    nr, ns = A.shape
    nc = d.shape[1]
    nt = partial.shape[0]
    for t in prange(nt):
        lo, hi = _chunk(t, nt, nr)
        for c in range(nc):
            partial[t, c] = 0.0
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


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def _cg_update(x, r, z, d, q, inv_diag, jacobi, alpha, active, partial):
    """x += alpha d, r -= alpha q on the active components; partial[t] =
    (r.z, r.r) per component over thread t's rows, with z = D^-1 r computed
    here when ``jacobi`` (else r.z is left to the caller)."""
    nr, nc = x.shape
    nt = partial.shape[0]
    for t in prange(nt):
        lo, hi = _chunk(t, nt, nr)
        for c in range(nc):
            partial[t, 0, c] = 0.0
            partial[t, 1, c] = 0.0
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


@njit(cache=True, error_model="numpy", fastmath=FAST)
def _precondition(A, cols, r, z, t, inv_diag, mode, kron, fringe):
    """z = P^-1 r: mode 0 the inverse lumped mass, 1 Kronecker, 2 Kronecker
    with the fringe correction (``t`` work space)."""
    if mode == 2:
        apply_corrected(A, cols, *kron, *fringe, r, z, t)
    elif mode == 1:
        apply_kronecker(*kron, r, z)
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
    return a.reshape(a.size)[:np.prod(np.array(shape))].reshape(shape)


@njit(cache=True, error_model="numpy", fastmath=FAST)
def ell_pcg(A, cols, inv_diag, mode, kron, fringe, b, x, problem, rtol, maxiter, nt, work):
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
    slow columns cost only their share. The preconditioner (``mode``) is 0
    the inverse lumped mass ``inv_diag``, 1 the Kronecker one of
    :mod:`skfem_mpm.kernels.kronecker` (``kron``: the arguments of
    ``apply_kronecker`` before r, z), 2 that with the fringe correction of
    :mod:`skfem_mpm.kernels.fringe` (``fringe``: ``FringeFactor.args``).
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
    xc = x
    packed = False  # xc is x until the first packing
    d = work[2]
    rz = np.zeros(nc)
    beta = np.zeros(nc)
    first = True
    it = 0
    while True:
        width = xc.shape[1]
        keep = np.flatnonzero(active[:width])
        n = keep.shape[0]
        if n < width:  # pack the unconverged columns to the front
            if n == 0:
                break
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
            if mode > 0:  # the preconditioners' work space
                kron = (kron[0], kron[1], kron[2], kron[3], _narrow(kron[4], n), kron[5])
            if mode == 2:
                fringe = fringe[:11] + (_narrow(fringe[11], n), _narrow(fringe[12], n),
                                        _narrow(fringe[13], (n + 1) // 2))
        if it >= maxiter:
            break
        width = n
        z = _narrow(work[1], width)
        q = _narrow(work[3], width)
        spare = _narrow(work[4], width)
        if first:  # z = P^-1 r, d = z
            first = False
            d = _narrow(work[2], width)
            _precondition(A, cols, r, z, spare, inv_diag, mode, kron, fringe)
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
        it += 1
        _ell_product_dot(A, cols, d, q, partial)
        alpha = np.zeros(width)
        for j in range(width):
            dq = 0.0
            for t in range(nt):
                dq += partial[t, j]
            if dq <= 0.0:
                active[j] = False
            alpha[j] = rz[j] / dq if active[j] else 0.0
        _cg_update(xc, r, z, d, q, inv_diag, mode == 0, alpha, active, sums)
        if mode > 0:  # z = P^-1 r and its r.z
            _precondition(A, cols, r, z, spare, inv_diag, mode, kron, fringe)
            _dots(r, z, partial)
            sums[:, 0, :] = partial
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
    if packed:
        for j in range(xc.shape[1]):
            for i in range(nr):
                x[i, columns[j]] = xc[i, j]
    for c in range(nc):
        if not converged[c]:
            return -max(it, 1)
    return it
