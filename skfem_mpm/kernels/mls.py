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
particles within r of x_g lie in the 5^d boxes around the box of x_g; of
those, each row of boxes along x (contiguous in the box order) is cut to
the boxes that the ball of radius r reaches, given the row's distance from
x_g on the other axes.
"""
import numpy as np
from numba import njit, prange

from .cholesky import cholesky

__all__ = ["MLS_RANK_TOL", "empty_mls_store", "mls_fit", "mls_reconstruct", "mls_store"]

MLS_RANK_TOL = 1e-6  # the reference's threshold (eigvalsh(M / scale)[0] > 1e-6; a test checks)
MAX_DIM = 3
POINTS_PER_BLOCK = 64
"""Gauss points per block of :func:`mls_fit` (each block its own work arrays)."""
MLS_PAIR_BYTES = 32 << 20
"""The most memory a pair store (:func:`mls_store`) takes; above it the
fits without coefficients search the particles again."""


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
def mls_store(store, ng, most):
    """The pair store for the next fit with coefficients on ``ng`` points
    (see :func:`mls_fit`): ``store`` (coef, hit, kept) itself when it has
    ng rows and at least ``most`` slots (the last such fit's largest count
    of particles in reach of a point), else new arrays of ng rows and max
    (most, slots) slots, or none (0 slots) where they would exceed
    MLS_PAIR_BYTES."""
    coef, hit, kept = store
    slots = max(most, coef.shape[1])
    if coef.shape[0] == ng and coef.shape[1] == slots:
        return store
    if ng * slots * 12 > MLS_PAIR_BYTES:
        slots = 0
    return np.empty((ng, slots)), np.empty((ng, slots), dtype=np.int32), \
        np.full(ng, -1, dtype=np.int64)


def empty_mls_store():
    """A pair store of no slots (:func:`mls_store` sizes it)."""
    return np.empty((0, 0)), np.empty((0, 0), dtype=np.int32), np.empty(0, dtype=np.int64)


@njit(cache=True, error_model="numpy")
def _stored_sums(coef, hit, stored, values, out, lo, hi):
    """out[g] = sum_j coef[g, j] values[hit[g, j]] for the points lo <= g < hi
    whose pairs are stored (stored[g] >= 0; see :func:`mls_fit`): a call
    per block of points, not inlined (arrays, see mls_fit)."""
    k = values.shape[1]
    for g in range(lo, hi):
        if stored[g] < 0:
            continue
        for col in range(k):
            out[g, col] = 0.0
        for j in range(stored[g]):
            c = coef[g, j]
            q = hit[g, j]
            for col in range(k):
                out[g, col] += c * values[q, col]


@njit(cache=True, error_model="numpy", parallel=True)
def mls_fit(x, values, xg, r, alpha, out, with_coefficients, store):
    """out[g] (ng, k) = the linear MLS fit of the particle ``values`` (n, k)
    at the point xg[g] (see the module docstring), ``x`` (n, d) particle
    positions, ``r`` the kernel radius: with ``with_coefficients`` it
    computes alpha[g] (ng, d + 1) = M_g^-1 e_0 first, else it takes them
    from an earlier call on the same particles and points.

    ``store`` (coef, hit, kept), arrays of ng rows (:func:`mls_store`):
    a call with coefficients writes there each point's weights
    c_p = w_p (alpha . phi_p) and particles p, in the order of the sum
    (kept[g] = their count, or -1 where they exceed the slots); a call
    without takes a point's stored pairs where it has them (the same
    products in the same order: the same bits) and searches the particles
    only for the others. Returns the largest count of particles in reach
    of a point (0 without coefficients).

    Per point, the particles in reach (sqrt(|x_q - x_g|^2) < r, the
    reference's test) are gathered row of boxes by row (box order within a
    row, index order within a box) without a branch on the distance (a
    branch that fails at random costs more than the test), then tested;
    the loops are written out here rather than in helpers, which would
    take the arrays (see :mod:`skfem_mpm.kernels.stencil`: counted
    references per call). The values are read in box order (a copy, made
    once), as the positions: the particles of a row of boxes are adjacent
    in memory. The points run in blocks of POINTS_PER_BLOCK (prange in the
    parallel kernel; each point's sums are the same in any block)."""
    dim = x.shape[1]
    k = values.shape[1]
    m = dim + 1
    ng = xg.shape[0]
    coef, hit, stored = store
    slots = coef.shape[1]
    nblocks = (ng + POINTS_PER_BLOCK - 1) // POINTS_PER_BLOCK
    if not with_coefficients and slots > 0 and stored.shape[0] == ng:
        search = False
        for g in range(ng):
            if stored[g] < 0:
                search = True
        if not search:  # every point's pairs stored
            for block in prange(nblocks):
                _stored_sums(coef, hit, stored, values, out, block * POINTS_PER_BLOCK,
                             min(ng, (block + 1) * POINTS_PER_BLOCK))
            return 0
    use_store = slots > 0 and stored.shape[0] == ng
    side = 0.5 * r
    inv_r = 1.0 / r
    reach = r * (1.0 + 1e-9)  # the candidates: a margin over rounding
    reach2 = reach * reach
    lower, nbox, order, start, xb, most = _neighbours(x, r)
    lower1 = lower[1] if dim > 1 else 0.0
    lower2 = lower[2] if dim > 2 else 0.0
    nbox0 = nbox[0]
    nbox1 = nbox[1] if dim > 1 else 1
    nbox2 = nbox[2] if dim > 2 else 1
    n = x.shape[0]
    vb = np.empty((n, k))  # the values in box order
    for i in range(n):
        for col in range(k):
            vb[i, col] = values[order[i], col]
    largest = np.zeros(nblocks, dtype=np.int64)
    for block in prange(nblocks):
        cand = np.empty(most, dtype=np.int64)
        hits = np.empty(most, dtype=np.int64)
        phi = np.empty((most, 4))  # (x_q - x_g) / r per axis (0 beyond dim), W
        M = np.zeros((MAX_DIM + 1, MAX_DIM + 1))
        L = np.empty((MAX_DIM + 1, MAX_DIM + 1))
        scaled = np.empty((MAX_DIM + 1, MAX_DIM + 1))
        a = np.zeros(MAX_DIM + 1)
        lo_g = block * POINTS_PER_BLOCK
        hi_g = min(ng, (block + 1) * POINTS_PER_BLOCK)
        if use_store and not with_coefficients:  # the points stored (not all were)
            _stored_sums(coef, hit, stored, values, out, lo_g, hi_g)
        for g in range(lo_g, hi_g):
            if use_store and not with_coefficients and stored[g] >= 0:
                continue
            y0 = xg[g, 0]
            y1 = xg[g, 1] if dim > 1 else 0.0
            y2 = xg[g, 2] if dim > 2 else 0.0
            lo1 = hi1 = lo2 = hi2 = 0  # the rows: two boxes either side on axes 1, 2
            if dim > 1:
                c = int(np.floor((y1 - lower1) / side))
                lo1, hi1 = max(c - 2, 0), min(c + 2, nbox1 - 1)
            if dim > 2:
                c = int(np.floor((y2 - lower2) / side))
                lo2, hi2 = max(c - 2, 0), min(c + 2, nbox2 - 1)
            count = 0
            for j2 in range(lo2, hi2 + 1):
                e2 = max(lower2 + j2 * side - y2, y2 - (lower2 + (j2 + 1) * side), 0.0) \
                    if dim > 2 else 0.0
                for j1 in range(lo1, hi1 + 1):
                    e1 = max(lower1 + j1 * side - y1, y1 - (lower1 + (j1 + 1) * side), 0.0) \
                        if dim > 1 else 0.0
                    gap2 = e1 * e1 + e2 * e2  # the row's distance from x_g
                    if gap2 > reach2:
                        continue
                    half = np.sqrt(reach2 - gap2)  # the ball's extent along axis 0
                    first = max(int(np.floor((y0 - half - lower[0]) / side)), 0)
                    last = min(int(np.floor((y0 + half - lower[0]) / side)), nbox0 - 1)
                    row = (j2 * nbox1 + j1) * nbox0
                    for i in range(start[row + first], start[row + last + 1] if last >= first
                                   else start[row + first]):
                        d0 = xb[i, 0] - y0
                        d1 = xb[i, 1] - y1
                        d2 = xb[i, 2] - y2
                        cand[count] = i
                        count += 1 if d0 * d0 + d1 * d1 + d2 * d2 <= reach2 else 0
            kept = 0
            m00 = m10 = m11 = m20 = m21 = m22 = m30 = m31 = m32 = m33 = 0.0
            for j in range(count):
                i = cand[j]
                d0 = xb[i, 0] - y0
                d1 = xb[i, 1] - y1
                d2 = xb[i, 2] - y2
                dist = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
                if not dist < r:
                    continue
                w = _kernel(dist * inv_r)
                p1 = d0 * inv_r
                p2 = d1 * inv_r
                p3 = d2 * inv_r
                hits[kept] = i  # box order
                phi[kept, 0] = p1
                phi[kept, 1] = p2
                phi[kept, 2] = p3
                phi[kept, 3] = w
                kept += 1
                if with_coefficients:  # the lower triangle of M: sum_p (w_p phi_s) phi_t
                    w1 = w * p1
                    w2 = w * p2
                    w3 = w * p3
                    m00 += w
                    m10 += w1
                    m11 += w1 * p1
                    m20 += w2
                    m21 += w2 * p1
                    m22 += w2 * p2
                    m30 += w3
                    m31 += w3 * p1
                    m32 += w3 * p2
                    m33 += w3 * p3
            if with_coefficients:
                if m00 > 0.0:
                    M[0, 0], M[1, 0], M[1, 1] = m00, m10, m11
                    M[2, 0], M[2, 1], M[2, 2] = m20, m21, m22
                    M[3, 0], M[3, 1], M[3, 2], M[3, 3] = m30, m31, m32, m33
                    _constant_row(M, m, L, scaled, a)
                else:  # no particle in reach
                    a[:] = 0.0
                for q in range(m):
                    alpha[g, q] = a[q]
            a0 = alpha[g, 0]
            a1 = alpha[g, 1]
            a2 = alpha[g, 2] if dim > 1 else 0.0
            a3 = alpha[g, 3] if dim > 2 else 0.0
            for col in range(k):
                out[g, col] = 0.0
            keep = with_coefficients and use_store and kept <= slots
            for j in range(kept):  # out = sum_p w_p (alpha . phi_p) f_p
                c = phi[j, 3] * (a0 + a1 * phi[j, 0] + a2 * phi[j, 1] + a3 * phi[j, 2])
                q = hits[j]
                if keep:
                    coef[g, j] = c
                    hit[g, j] = order[q]
                for col in range(k):
                    out[g, col] += c * vb[q, col]
            if with_coefficients:
                largest[block] = max(largest[block], kept)
                if use_store:
                    stored[g] = kept if keep else -1
    return largest.max() if nblocks > 0 else 0


@njit(cache=True, error_model="numpy")
def mls_reconstruct(x, values, xg, r, out):
    """out[g] (ng, k) = the linear MLS fit of the particle ``values`` (n, k)
    at the point xg[g] (see the module docstring); ``x`` (n, d) particle
    positions, ``r`` the kernel radius."""
    alpha = np.empty((xg.shape[0], x.shape[1] + 1))
    mls_fit(x, values, xg, r, alpha, out, True,
            (np.empty((0, 0)), np.empty((0, 0), dtype=np.int32), np.empty(0, dtype=np.int64)))
