"""The Gauss rule over the body that reconstructed particle data is
integrated with, built in one compiled pass.

1D: the body is the union of the particles' extents [x_p - V_p/2,
x_p + V_p/2] (sorted by x_p, stable), cut into connected pieces where an
extent starts more than ``gap`` beyond the running maximum of the
previous ones' ends; each piece [lo, hi] (clipped to the grid) is covered
by the grid cells it overlaps, cell e by [max(u_e, lo), min(u_(e+1), hi)]
of width b, with the points and weights

    x_g = max(u_e, lo) + b r_j,   w_g = b w_j   (r_j, w_j: Gauss-Legendre on [0, 1]).

This is :func:`skfem_mpm.reconstruct.integration_rule` (the oracle)
computed without the Python loop over pieces; the same arithmetic, so the
points agree bit for bit.

2D (:func:`gauss_rule_cells`): the cells that hold particles (ascending
scikit-fem numbering e = ix + nx iy), each with the tensor rule of k points
per axis, point (a, b) at index a + k b:

    x_g = (u_ix + h_ix r_a, v_iy + k_iy r_b),   w_g = (h_ix w_a) (k_iy w_b),

as :meth:`SplineGrid.gauss_rule` computes it (bit for bit). The particles'
cells (:func:`locate_cells`, with the transfers' own
:func:`~skfem_mpm.kernels.weights.locate_axis_point`) are those of
:meth:`SplineGrid.locate`: on a uniform axis floor((x - u_0) (n / (u_n -
u_0))), else the last breakpoint <= x, clamped to the grid's cells.
"""
import numpy as np
from numba import njit

from .weights import locate_axis_point

__all__ = ["gauss_rule_1d", "gauss_rule_cells", "locate_cells"]


@njit(cache=True, error_model="numpy")
def gauss_rule_1d(x, V, gap, breaks, ref, wref):
    """(order, piece_particles, piece_points, xg, wg, cell): ``order`` the
    stable sort of x; piece j holds the sorted particles
    order[piece_particles[j]:piece_particles[j + 1]] and the points
    piece_points[j]:piece_points[j + 1] (ascending)."""
    n = x.shape[0]
    k = ref.shape[0]
    ncells = breaks.shape[0] - 1
    order = np.argsort(x, kind="mergesort")
    starts = np.empty(n + 1, dtype=np.int64)
    lows = np.empty(n)
    highs = np.empty(n)
    npieces = 0
    run_hi = -np.inf
    for i in range(n):
        q = order[i]
        lo = x[q] - 0.5 * V[q]
        hi = x[q] + 0.5 * V[q]
        if i == 0 or lo > run_hi + gap:
            if i > 0:
                highs[npieces - 1] = run_hi
            starts[npieces] = i
            lows[npieces] = lo
            npieces += 1
            run_hi = hi
        else:
            run_hi = max(run_hi, hi)
    if n > 0:
        highs[npieces - 1] = run_hi
    starts[npieces] = n
    # cells of each piece: count, then fill
    first = np.empty(npieces, dtype=np.int64)
    piece_points = np.zeros(npieces + 1, dtype=np.int64)
    for j in range(npieces):
        lo = max(lows[j], breaks[0])
        hi = min(highs[j], breaks[ncells])
        lows[j], highs[j] = lo, hi
        e = max(np.searchsorted(breaks, lo, side="right") - 1, 0)
        first[j] = e
        count = 0
        for c in range(e, ncells):
            if breaks[c] >= hi:
                break
            if min(breaks[c + 1], hi) > max(breaks[c], lo):
                count += 1
        piece_points[j + 1] = piece_points[j] + count * k
    ng = piece_points[npieces]
    xg = np.empty(ng)
    wg = np.empty(ng)
    cell = np.empty(ng, dtype=np.int64)
    for j in range(npieces):
        lo, hi = lows[j], highs[j]
        g = piece_points[j]
        for c in range(first[j], ncells):
            if breaks[c] >= hi:
                break
            left = max(breaks[c], lo)
            right = min(breaks[c + 1], hi)
            if right > left:
                width = right - left
                for a in range(k):
                    xg[g] = left + width * ref[a]
                    wg[g] = width * wref[a]
                    cell[g] = c
                    g += 1
    return order, starts[:npieces + 1].copy(), piece_points, xg, wg, cell


@njit(cache=True, error_model="numpy")
def locate_cells(x, breaks0, breaks1, uniform0, uniform1):
    """The cell (ix + nx iy; ix in 1D) of each point x (n, d)."""
    n, dim = x.shape
    nx = breaks0.shape[0] - 1
    ny = breaks1.shape[0] - 1
    inv_h0 = nx / (breaks0[nx] - breaks0[0])  # the uniform axes' 1 / h, as SplineGrid.locate
    inv_h1 = ny / (breaks1[ny] - breaks1[0])
    cell = np.empty(n, dtype=np.int64)
    for i in range(n):
        c = locate_axis_point(x[i, 0], breaks0, uniform0, inv_h0)
        if dim == 2:
            c += nx * locate_axis_point(x[i, 1], breaks1, uniform1, inv_h1)
        cell[i] = c
    return cell


@njit(cache=True, error_model="numpy")
def gauss_rule_cells(pcell, breaks0, breaks1, ref, wref):
    """(xg, wg, cell) of the 2D tensor Gauss rule on the cells in ``pcell``
    (ascending, each once; see the module docstring)."""
    nx = breaks0.shape[0] - 1
    ncells = nx * (breaks1.shape[0] - 1)
    k = ref.shape[0]
    held = np.zeros(ncells, dtype=np.bool_)
    for i in range(pcell.shape[0]):
        held[pcell[i]] = True
    nheld = 0
    for c in range(ncells):
        if held[c]:
            nheld += 1
    ng = nheld * k * k
    xg = np.empty((ng, 2))
    wg = np.empty(ng)
    cell = np.empty(ng, dtype=np.int64)
    g = 0
    for c in range(ncells):
        if not held[c]:
            continue
        ix, iy = c % nx, c // nx
        hx = breaks0[ix + 1] - breaks0[ix]
        hy = breaks1[iy + 1] - breaks1[iy]
        for b in range(k):
            for a in range(k):
                xg[g, 0] = breaks0[ix] + hx * ref[a]
                xg[g, 1] = breaks1[iy] + hy * ref[b]
                wg[g] = (hx * wref[a]) * (hy * wref[b])
                cell[g] = c
                g += 1
    return xg, wg, cell
