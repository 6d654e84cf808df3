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
exactly when the smallest eigenvalue exceeds the tolerance); the solve is a
Cholesky solve of M itself.

Neighbours: the particles are binned (counting sort, stable) into a
uniform box grid of side r over their bounding box, so the particles within
r of x_g lie in the 3^d boxes around the box of x_g.
"""
import numpy as np
from numba import njit

from .cholesky import cholesky

__all__ = ["MLS_RANK_TOL", "mls_reconstruct"]

MLS_RANK_TOL = 1e-6  # the reference's threshold (eigvalsh(M / scale)[0] > 1e-6; a test checks)
MAX_DIM = 3


@njit(cache=True, inline="always", error_model="numpy")
def _kernel(s):
    """W(s): the cubic B-spline kernel with W(0) = 1 (see the module docstring)."""
    if s <= 0.5:
        return 1.0 - 6.0 * s * s + 6.0 * s * s * s
    if s < 1.0:
        t = 1.0 - s
        return 2.0 * t * t * t
    return 0.0


@njit(cache=True, error_model="numpy")
def _boxes(x, r):
    """(lower, nbox, order, start): the particles in box b (x fastest,
    b = sum_a i_a prod_(c < a) nbox[c], i_a = floor((x_a - lower_a) / r)) are
    order[start[b]:start[b + 1]], in index order."""
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
def mls_reconstruct(x, values, xg, r, out):
    """out[g] (ng, k) = the linear MLS fit of the particle ``values`` (n, k)
    at the point xg[g] (see the module docstring); ``x`` (n, d) particle
    positions, ``r`` the kernel radius."""
    dim = x.shape[1]
    k = values.shape[1]
    m = dim + 1
    lower, nbox, order, start = _boxes(x, r)
    M = np.empty((m, m))
    b = np.empty((m, k))
    L = np.empty((m, m))
    scaled = np.empty((m, m))
    phi = np.empty(m)
    lo = np.zeros(MAX_DIM, dtype=np.int64)
    hi = np.zeros(MAX_DIM, dtype=np.int64)
    idx = np.zeros(MAX_DIM, dtype=np.int64)
    for g in range(xg.shape[0]):
        M[:] = 0.0
        b[:] = 0.0
        ncombos = 1
        for a in range(dim):
            c = int(np.floor((xg[g, a] - lower[a]) / r))
            lo[a] = max(c - 1, 0)
            hi[a] = min(c + 1, nbox[a] - 1)
            ncombos *= max(hi[a] - lo[a] + 1, 0)
        for combo in range(ncombos):
            rest, box, stride = combo, 0, 1
            for a in range(dim):
                span = hi[a] - lo[a] + 1
                idx[a] = lo[a] + rest % span
                rest //= span
                box += idx[a] * stride
                stride *= nbox[a]
            for i in range(start[box], start[box + 1]):
                q = order[i]
                d2 = 0.0
                for a in range(dim):
                    d = x[q, a] - xg[g, a]
                    d2 += d * d
                dist = np.sqrt(d2)
                if not dist < r:
                    continue
                w = _kernel(dist / r)
                if not w > 0.0:
                    continue
                phi[0] = 1.0
                for a in range(dim):
                    phi[1 + a] = (x[q, a] - xg[g, a]) / r
                for s in range(m):
                    ws = w * phi[s]
                    for t in range(m):
                        M[s, t] += ws * phi[t]
                    for col in range(k):
                        b[s, col] += ws * values[q, col]
        if not M[0, 0] > 0.0:
            for col in range(k):
                out[g, col] = 0.0
            continue
        trace = 0.0
        for s in range(m):
            trace += M[s, s]
        scale = max(trace / m, 1e-300)
        for s in range(m):
            for t in range(m):
                scaled[s, t] = M[s, t] / scale
        if cholesky(scaled, m, MLS_RANK_TOL, L) and cholesky(M, m, 0.0, L):
            for col in range(k):  # L L^T c = b[:, col]; out = c_0
                for s in range(m):
                    acc = b[s, col]
                    for t in range(s):
                        acc -= L[s, t] * phi[t]
                    phi[s] = acc / L[s, s]
                for s in range(m - 1, -1, -1):
                    acc = phi[s]
                    for t in range(s + 1, m):
                        acc -= L[t, s] * phi[t]
                    phi[s] = acc / L[s, s]
                out[g, col] = phi[0]
        else:
            for col in range(k):
                out[g, col] = b[0, col] / M[0, 0]
