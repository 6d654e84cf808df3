"""Moving least squares (MLS) at the Gauss points, compiled: the twin of
:func:`skfem_mpm.reconstruct.reconstruct_mls`, which is the oracle. One
source serves every dimension (the loops run over ``x.shape[1]``).

The method (Lancaster & Salkauskas 1981, Math. Comp. 37:141-158; with the
linear basis): at a point x_g with the particles p at distances
d_p = |x_p - x_g| < r, the weights w_p = W(d_p / r) of the cubic B-spline
kernel normalised to W(0) = 1,

    W(s) = 1 - 6 s^2 + 6 s^3  (s <= 1/2),   2 (1 - s)^3  (1/2 < s < 1),   0 else,

and the scaled linear basis phi_p = (1, (x_p - x_g) / r), the moment matrix
and right-hand side

    M = sum_p w_p phi_p phi_p^T,    b = sum_p w_p phi_p f_p^T     ((d+1) x k),

give the value f_h(x_g) = (M^-1 b)_0 (the constant coefficient: the basis
is centred at x_g). Where M is not safely invertible (its smallest
eigenvalue, scaled by trace(M) / (d + 1), is <= MLS_RANK_TOL: fewer than
d + 1 particles in reach, or them on a line) the value is the weighted mean
b_0 / M_00 (Shepard), and 0 where no particle is in reach. The eigenvalue
test is a Cholesky factorisation of M / scale - MLS_RANK_TOL I (it succeeds
exactly when the smallest eigenvalue exceeds the tolerance).

M is symmetric, so (M^-1 b)_0 = alpha^T b with alpha = M^-1 e_0 (a Cholesky
solve of M itself), and the value is a weighted sum of the particle values,

    f_h(x_g) = sum_p w_p (alpha . phi_p) f_p,

(Shepard: alpha = e_0 / M_00; no particle in reach: alpha = 0).
alpha depends on the positions alone: :func:`mls_fit` computes it, or
takes it from an earlier fit on the same particles and points (a step's
MUSL projection) and computes only the sums. Rounding differs from the
reference's (its sums run in another order, it divides by r where this
multiplies by 1 / r, it solves M a = b per column): the two agree to
rounding times the condition number of M (test_recon_compiled).

Neighbours: the particles are binned (counting sort, stable) into a
uniform box grid of side r / 2 over their bounding box (x fastest), so the
particles within r of x_g lie in the 5^d boxes around the box of x_g. The
points are fitted in groups (consecutive points of one cell, at most
LANES: the Gauss points of a cell see nearly the same particles): the
group's candidates are gathered once, from the rows of boxes (contiguous
in the box order along x) within reach of the group's bounding box, each
row cut to the boxes the reach covers, then those particles within reach
of the box; for each candidate the work on all the group's points is one
loop (vectorised), a point's pairs out of reach weighing 0. Each point's
particles in reach come in the order of a search of its own, so a point
has the same sums in any group (test_recon_compiled).
"""
import numpy as np
from numba import njit, prange

from .cholesky import cholesky

__all__ = ["MLS_RANK_TOL", "mls_fit", "mls_reconstruct"]

MLS_RANK_TOL = 1e-6  # the reference's threshold (eigvalsh(M / scale)[0] > 1e-6; a test checks)
MAX_DIM = 3
LANES = 16
"""The most points of one group of :func:`mls_fit` (its inner loop)."""
GROUPS_PER_BLOCK = 4
"""Groups per block of :func:`mls_fit` (each block its own work arrays)."""


@njit(cache=True, inline="always", error_model="numpy")
def _kernel(s):
    """W(s) for 0 <= s < 1: the cubic B-spline kernel with W(0) = 1 (see
    the module docstring), both pieces computed and one selected (no
    branch that fails at random)."""
    t = 1.0 - s
    near = 1.0 - 6.0 * s * s + 6.0 * s * s * s
    far = 2.0 * t * t * t
    return near if s <= 0.5 else far


@njit(cache=True, error_model="numpy")
def _boxes(x, r):
    """(lower, nbox, order, start): the particles in box b (x fastest,
    b = sum_a i_a prod_(c < a) nbox[c], i_a = floor((x_a - lower_a) / r), r
    the boxes' side) are order[start[b]:start[b + 1]], in index order."""
    n, dim = x.shape
    lower = np.empty(dim)
    nbox = np.ones(dim, dtype=np.int64)
    for a in range(dim):
        lo, hi = np.inf, -np.inf
        for i in range(n):
            lo = min(lo, x[i, a])
            hi = max(hi, x[i, a])
        lower[a] = lo if n > 0 else 0.0
        if n > 0:
            nbox[a] = int(np.floor((hi - lo) / r)) + 1
    total = 1
    for a in range(dim):
        total *= nbox[a]
    box = np.empty(n, dtype=np.int64)
    start = np.zeros(total + 1, dtype=np.int64)
    for i in range(n):
        b, stride = 0, 1
        for a in range(dim):
            ia = min(int(np.floor((x[i, a] - lower[a]) / r)), nbox[a] - 1)
            b += ia * stride
            stride *= nbox[a]
        box[i] = b
        start[b + 1] += 1
    for b in range(total):
        start[b + 1] += start[b]
    fill = start[:-1].copy()
    order = np.empty(n, dtype=np.int64)
    for i in range(n):
        order[fill[box[i]]] = i
        fill[box[i]] += 1
    return lower, nbox, order, start


@njit(cache=True, error_model="numpy")
def _neighbours(x, r):
    """(lower, nbox, order, start, xb, most): the boxes of side r / 2 of
    :func:`_boxes`, the positions in box order xb (n, MAX_DIM; zero beyond
    the dimension) and the most particles the 5^d boxes around a point can
    hold."""
    n, dim = x.shape
    lower, nbox, order, start = _boxes(x, 0.5 * r)
    xb = np.zeros((n, MAX_DIM))
    for i in range(n):
        for a in range(dim):
            xb[i, a] = x[order[i], a]
    fullest = 0
    for b in range(start.shape[0] - 1):
        fullest = max(fullest, start[b + 1] - start[b])
    return lower, nbox, order, start, xb, 5 ** dim * fullest


@njit(cache=True, error_model="numpy")
def _groups(cell):
    """The starts of the point groups (ngroups + 1): runs of consecutive
    points of one cell, at most LANES points each."""
    ng = cell.shape[0]
    starts = np.empty(ng + 1, dtype=np.int64)
    count = 0
    g = 0
    while g < ng:
        starts[count] = g
        count += 1
        e = g + 1
        while e < ng and e - g < LANES and cell[e] == cell[g]:
            e += 1
        g = e
    starts[count] = ng
    return starts[:count + 1].copy()


@njit(cache=True, error_model="numpy")
def _group_ranges(xg, s, e, lower, nbox, start, side, reach2, ranges):
    """(rows, candidates): the ranges order[b:e] of the particles that may
    lie within reach of any of the points xg[s:e] (the rows of boxes of
    :func:`_neighbours` that the ball of radius reach around the points'
    bounding box meets, each cut to the boxes it reaches along axis 0),
    written to ranges[j] = (b, e) for j < rows while ranges has room, in
    box order (rows along axes 2, 1 ascending). Each point's own ranges
    (the per-point search this replaces) lie inside these, in the same
    order."""
    dim = xg.shape[1]
    ylo0 = ylo1 = ylo2 = np.inf
    yhi0 = yhi1 = yhi2 = -np.inf
    for g in range(s, e):
        ylo0 = min(ylo0, xg[g, 0])
        yhi0 = max(yhi0, xg[g, 0])
        if dim > 1:
            ylo1 = min(ylo1, xg[g, 1])
            yhi1 = max(yhi1, xg[g, 1])
        if dim > 2:
            ylo2 = min(ylo2, xg[g, 2])
            yhi2 = max(yhi2, xg[g, 2])
    lower0 = lower[0]
    lower1 = lower[1] if dim > 1 else 0.0
    lower2 = lower[2] if dim > 2 else 0.0
    nbox0 = nbox[0]
    nbox1 = nbox[1] if dim > 1 else 1
    nbox2 = nbox[2] if dim > 2 else 1
    lo1 = hi1 = lo2 = hi2 = 0  # two boxes either side of the points' boxes on axes 1, 2
    if dim > 1:
        lo1 = max(int(np.floor((ylo1 - lower1) / side)) - 2, 0)
        hi1 = min(int(np.floor((yhi1 - lower1) / side)) + 2, nbox1 - 1)
    if dim > 2:
        lo2 = max(int(np.floor((ylo2 - lower2) / side)) - 2, 0)
        hi2 = min(int(np.floor((yhi2 - lower2) / side)) + 2, nbox2 - 1)
    rows = 0
    total = 0
    for j2 in range(lo2, hi2 + 1):
        e2 = max(lower2 + j2 * side - yhi2, ylo2 - (lower2 + (j2 + 1) * side), 0.0) \
            if dim > 2 else 0.0
        for j1 in range(lo1, hi1 + 1):
            e1 = max(lower1 + j1 * side - yhi1, ylo1 - (lower1 + (j1 + 1) * side), 0.0) \
                if dim > 1 else 0.0
            gap2 = e1 * e1 + e2 * e2  # the row's distance from the points' box
            if gap2 > reach2:
                continue
            half = np.sqrt(reach2 - gap2)  # the ball's extent along axis 0
            first = max(int(np.floor((ylo0 - half - lower0) / side)), 0)
            last = min(int(np.floor((yhi0 + half - lower0) / side)), nbox0 - 1)
            if last < first:
                continue
            row = (j2 * nbox1 + j1) * nbox0
            b = start[row + first]
            f = start[row + last + 1]
            if f > b:
                if rows < ranges.shape[0]:
                    ranges[rows, 0] = b
                    ranges[rows, 1] = f
                rows += 1
                total += f - b
    return rows, total


@njit(cache=True, error_model="numpy")
def _plan(xg, groups, lower, nbox, start, side, reach2):
    """(most rows, most candidates) of a group of points (:func:`_groups`,
    :func:`_group_ranges`): the sizes of a block's work arrays."""
    ranges = np.empty((0, 2), dtype=np.int64)
    most_rows = 0
    most = 0
    for j in range(groups.shape[0] - 1):
        rows, total = _group_ranges(xg, groups[j], groups[j + 1], lower, nbox, start, side,
                                    reach2, ranges)
        most_rows = max(most_rows, rows)
        most = max(most, total)
    return most_rows, most


@njit(cache=True, error_model="numpy")
def _constant_row(M, m, L, scaled, a):
    """a[:m] = M^-1 e_0 for the moment matrix M (its lower triangle set),
    or e_0 / M_00 where M is not well posed (see the module docstring)."""
    for s in range(m):  # symmetric
        a[s] = 0.0
        for t in range(s + 1, m):
            M[s, t] = M[t, s]
    trace = 0.0
    for s in range(m):
        trace += M[s, s]
    scale = max(trace / m, 1e-300)
    for s in range(m):
        for t in range(m):
            scaled[s, t] = M[s, t] / scale
    if cholesky(scaled, m, MLS_RANK_TOL, L) and cholesky(M, m, 0.0, L):
        for s in range(m):  # L L^T a = e_0
            acc = 1.0 if s == 0 else 0.0
            for t in range(s):
                acc -= L[s, t] * a[t]
            a[s] = acc / L[s, s]
        for s in range(m - 1, -1, -1):
            acc = a[s]
            for t in range(s + 1, m):
                acc -= L[t, s] * a[t]
            a[s] = acc / L[s, s]
    else:
        a[0] = 1.0 / M[0, 0]


@njit(cache=True, error_model="numpy")
def _constant_rows_2d(sums, lanes, A):
    """A[:3, g] = M_g^-1 e_0 for the points g < lanes of a group in 2D, M_g's
    lower triangle in sums[:6, g] (see :func:`mls_fit`):
    :func:`_constant_row`'s arithmetic, operation for operation (the same
    bits: both Cholesky factorisations, the well-posedness test, the two
    triangular solves; e_0 / M_00 where it fails, 0 where M_00 = 0), on
    all the points at once (no branch: each failed pivot's NaN is
    discarded by the selection)."""
    tol = MLS_RANK_TOL
    for g in range(lanes):
        m00 = sums[0, g]
        m10 = sums[1, g]
        m11 = sums[2, g]
        m20 = sums[3, g]
        m21 = sums[4, g]
        m22 = sums[5, g]
        scale = max(((0.0 + m00) + m11 + m22) / 3, 1e-300)
        s00 = m00 / scale
        s10 = m10 / scale
        s11 = m11 / scale
        s20 = m20 / scale
        s21 = m21 / scale
        s22 = m22 / scale
        q0 = s00 - tol  # cholesky(M / scale, 3, tol): the smallest eigenvalue > tol
        r0 = np.sqrt(q0)
        t10 = s10 / r0
        t20 = s20 / r0
        q1 = s11 - tol - t10 * t10
        r1 = np.sqrt(q1)
        t21 = (s21 - t20 * t10) / r1
        q2 = s22 - tol - t20 * t20 - t21 * t21
        p0 = m00 - 0.0  # cholesky(M, 3, 0)
        l00 = np.sqrt(p0)
        l10 = m10 / l00
        l20 = m20 / l00
        p1 = m11 - 0.0 - l10 * l10
        l11 = np.sqrt(p1)
        l21 = (m21 - l20 * l10) / l11
        p2 = m22 - 0.0 - l20 * l20 - l21 * l21
        l22 = np.sqrt(p2)
        a0 = 1.0 / l00  # L L^T a = e_0
        a1 = (0.0 - l10 * a0) / l11
        a2 = (0.0 - l20 * a0 - l21 * a1) / l22
        a2 = a2 / l22
        a1 = (a1 - l21 * a2) / l11
        a0 = (a0 - l10 * a1 - l20 * a2) / l00
        good = q0 > 0.0 and q1 > 0.0 and q2 > 0.0 and p0 > 0.0 and p1 > 0.0 and p2 > 0.0
        held = m00 > 0.0
        A[0, g] = a0 if good and held else (1.0 / m00 if held else 0.0)
        A[1, g] = a1 if good and held else 0.0
        A[2, g] = a2 if good and held else 0.0


@njit(cache=True, error_model="numpy", parallel=True)
def mls_fit(x, values, xg, cell, r, alpha, out, with_coefficients):
    """out[g] (ng, k) = the linear MLS fit of the particle ``values`` (n, k)
    at the point xg[g] (see the module docstring), ``x`` (n, d) particle
    positions, ``cell`` (ng,) the points' cells, ``r`` the kernel radius:
    with ``with_coefficients`` it computes alpha[g] (ng, d + 1) =
    M_g^-1 e_0 first, else it takes them from an earlier call on the same
    particles and points (a step's MUSL projection).

    The points run in groups (:func:`_groups`: consecutive points of one
    cell, at most LANES), each with the particles that may be in reach of
    any of its points, gathered once for the group: those of the rows of
    boxes of :func:`_group_ranges` within reach of the points' bounding
    box (a test without a branch). Per particle, the group's points are
    the inner loop (the same operations on all of them: vectorised), a
    pair out of reach (sqrt(|x_q - x_g|^2) >= r, the reference's test)
    weighing 0. A point's particles in reach come in the order of a
    search of its own (rows of boxes, box order, index order), so each sum
    adds the same products in the same order as a point-by-point fit,
    and zeros. The values are read in box order (a copy, made once), as
    the positions. The groups run in blocks of GROUPS_PER_BLOCK (prange in
    the parallel kernel; each point's sums are the same in any block). In
    2D without ``with_coefficients`` each pair's weight is made and summed
    into the values at once (no pair or weight arrays; the same
    operations, so the bits of the two-pass form)."""
    dim = x.shape[1]
    k = values.shape[1]
    m = dim + 1
    groups = _groups(cell)
    ngroups = groups.shape[0] - 1
    nblocks = (ngroups + GROUPS_PER_BLOCK - 1) // GROUPS_PER_BLOCK
    side = 0.5 * r
    inv_r = 1.0 / r
    reach = r * (1.0 + 1e-9)  # the candidates: a margin over rounding
    reach2 = reach * reach
    lower, nbox, order, start, xb, _ = _neighbours(x, r)
    most_rows, most = _plan(xg, groups, lower, nbox, start, side, reach2)
    n = x.shape[0]
    vb = np.empty((n, k))  # the values in box order
    for i in range(n):
        for col in range(k):
            vb[i, col] = values[order[i], col]
    for block in prange(nblocks):
        ranges = np.empty((most_rows, 2), dtype=np.int64)
        cand = np.empty(most, dtype=np.int64)
        pair = np.empty((most, 4, LANES))  # per particle and point: w, (x_q - x_g) / r per axis
        weight = np.empty((most, LANES))  # w (alpha . phi)
        sums = np.zeros((10, LANES))  # the lower triangle of M per point
        acc = np.empty((k, LANES))
        A = np.zeros((4, LANES))
        Y = np.zeros((3, LANES))
        M = np.zeros((MAX_DIM + 1, MAX_DIM + 1))
        L = np.empty((MAX_DIM + 1, MAX_DIM + 1))
        scaled = np.empty((MAX_DIM + 1, MAX_DIM + 1))
        a = np.zeros(MAX_DIM + 1)
        for j in range(block * GROUPS_PER_BLOCK, min(ngroups, (block + 1) * GROUPS_PER_BLOCK)):
            s = groups[j]
            lanes = groups[j + 1] - s
            lo0 = lo1 = lo2 = np.inf
            hi0 = hi1 = hi2 = -np.inf
            for g in range(lanes):
                for c in range(dim):
                    Y[c, g] = xg[s + g, c]
                lo0 = min(lo0, Y[0, g])
                hi0 = max(hi0, Y[0, g])
                lo1 = min(lo1, Y[1, g])
                hi1 = max(hi1, Y[1, g])
                lo2 = min(lo2, Y[2, g])
                hi2 = max(hi2, Y[2, g])
            rows, _ = _group_ranges(xg, s, s + lanes, lower, nbox, start, side, reach2, ranges)
            nc = 0  # the particles within reach of the points' box
            for t in range(rows):
                for i in range(ranges[t, 0], ranges[t, 1]):
                    e0 = max(lo0 - xb[i, 0], xb[i, 0] - hi0, 0.0)
                    e1 = max(lo1 - xb[i, 1], xb[i, 1] - hi1, 0.0)
                    e2 = max(lo2 - xb[i, 2], xb[i, 2] - hi2, 0.0)
                    cand[nc] = i
                    nc += 1 if e0 * e0 + e1 * e1 + e2 * e2 <= reach2 else 0
            for t in range(10):
                for g in range(lanes):
                    sums[t, g] = 0.0
            fused = dim == 2 and not with_coefficients
            if fused:  # the points' kept alpha, the sums cleared (summed below)
                for t in range(3):
                    for g in range(lanes):
                        A[t, g] = alpha[s + g, t]
                for col in range(k):
                    for g in range(lanes):
                        acc[col, g] = 0.0
            if dim == 2:  # the particles' weights and scaled offsets (and M's sums)
                for q in range(nc):
                    i = cand[q]
                    x0 = xb[i, 0]
                    x1 = xb[i, 1]
                    if with_coefficients:
                        for g in range(lanes):
                            d0 = x0 - Y[0, g]
                            d1 = x1 - Y[1, g]
                            dist = np.sqrt(d0 * d0 + d1 * d1)
                            w = _kernel(dist * inv_r) if dist < r else 0.0
                            p1 = d0 * inv_r
                            p2 = d1 * inv_r
                            pair[q, 0, g] = w
                            pair[q, 1, g] = p1
                            pair[q, 2, g] = p2
                            w1 = w * p1
                            w2 = w * p2
                            sums[0, g] += w
                            sums[1, g] += w1
                            sums[2, g] += w1 * p1
                            sums[3, g] += w2
                            sums[4, g] += w2 * p1
                            sums[5, g] += w2 * p2
                    else:  # alpha kept: each pair's weight and value sums at once
                        for g in range(lanes):
                            d0 = x0 - Y[0, g]
                            d1 = x1 - Y[1, g]
                            dist = np.sqrt(d0 * d0 + d1 * d1)
                            w = _kernel(dist * inv_r) if dist < r else 0.0
                            weight[0, g] = w * (A[0, g] + A[1, g] * (d0 * inv_r)
                                                + A[2, g] * (d1 * inv_r))
                        for col in range(k):
                            v = vb[i, col]
                            for g in range(lanes):
                                acc[col, g] += weight[0, g] * v
                if with_coefficients:
                    _constant_rows_2d(sums, lanes, A)
                    for g in range(lanes):
                        for t in range(m):
                            alpha[s + g, t] = A[t, g]
            else:
                for q in range(nc):
                    i = cand[q]
                    x0 = xb[i, 0]
                    x1 = xb[i, 1]
                    x2 = xb[i, 2]
                    for g in range(lanes):
                        d0 = x0 - Y[0, g]
                        d1 = x1 - Y[1, g]
                        d2 = x2 - Y[2, g]
                        dist = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
                        w = _kernel(dist * inv_r) if dist < r else 0.0
                        p1 = d0 * inv_r
                        p2 = d1 * inv_r
                        p3 = d2 * inv_r
                        pair[q, 0, g] = w
                        pair[q, 1, g] = p1
                        pair[q, 2, g] = p2
                        pair[q, 3, g] = p3
                        if with_coefficients:
                            w1 = w * p1
                            w2 = w * p2
                            w3 = w * p3
                            sums[0, g] += w
                            sums[1, g] += w1
                            sums[2, g] += w1 * p1
                            sums[3, g] += w2
                            sums[4, g] += w2 * p1
                            sums[5, g] += w2 * p2
                            sums[6, g] += w3
                            sums[7, g] += w3 * p1
                            sums[8, g] += w3 * p2
                            sums[9, g] += w3 * p3
                if with_coefficients:
                    for g in range(lanes):
                        if sums[0, g] > 0.0:
                            M[0, 0], M[1, 0], M[1, 1] = sums[0, g], sums[1, g], sums[2, g]
                            M[2, 0], M[2, 1], M[2, 2] = sums[3, g], sums[4, g], sums[5, g]
                            M[3, 0], M[3, 1], M[3, 2], M[3, 3] = \
                                sums[6, g], sums[7, g], sums[8, g], sums[9, g]
                            _constant_row(M, m, L, scaled, a)
                        else:  # no particle in reach
                            a[:] = 0.0
                        for t in range(m):
                            alpha[s + g, t] = a[t]
            if dim != 2:  # the points' alpha (0 beyond dim)
                for t in range(4):
                    for g in range(lanes):
                        A[t, g] = alpha[s + g, t] if t < m else 0.0
            if not fused:  # (fused: summed above)
                for col in range(k):
                    for g in range(lanes):
                        acc[col, g] = 0.0
                for q in range(nc):  # out = sum_p w_p (alpha . phi_p) f_p
                    if dim == 2:
                        for g in range(lanes):
                            weight[q, g] = pair[q, 0, g] * (A[0, g] + A[1, g] * pair[q, 1, g]
                                                            + A[2, g] * pair[q, 2, g])
                    else:
                        for g in range(lanes):
                            weight[q, g] = pair[q, 0, g] * (A[0, g] + A[1, g] * pair[q, 1, g]
                                                            + A[2, g] * pair[q, 2, g]
                                                            + A[3, g] * pair[q, 3, g])
                    i = cand[q]
                    for col in range(k):
                        v = vb[i, col]
                        for g in range(lanes):
                            acc[col, g] += weight[q, g] * v
            for g in range(lanes):
                for col in range(k):
                    out[s + g, col] = acc[col, g]


@njit(cache=True, error_model="numpy")
def mls_reconstruct(x, values, xg, cell, r, out):
    """out[g] (ng, k) = the linear MLS fit of the particle ``values`` (n, k)
    at the point xg[g] (see the module docstring); ``x`` (n, d) particle
    positions, ``cell`` (ng,) the points' cells (consecutive points of a
    cell are fitted together, see :func:`mls_fit`), ``r`` the kernel
    radius."""
    alpha = np.empty((xg.shape[0], x.shape[1] + 1))
    mls_fit(x, values, xg, cell, r, alpha, out, True)
