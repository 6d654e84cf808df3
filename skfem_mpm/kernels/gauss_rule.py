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
per axis on the part of the cell the body covers, the box
[l_x, l_x + b_x] x [l_y, l_y + b_y] of :func:`body_boxes` (the whole
cell inside the body), point (a, b) at index a + k b:

    x_g = (l_x + b_x r_a, l_y + b_y r_b),   w_g = (b_x w_a) (b_y w_b),

as :func:`skfem_mpm.reconstruct.integration_rule` computes it (bit for bit). The particles'
cells (:func:`locate_cells`, with the transfers' own
:func:`~skfem_mpm.kernels.weights.locate_axis_point`) are those of
:meth:`SplineGrid.locate`: on a uniform axis floor((x - u_0) (n / (u_n -
u_0))), else the last breakpoint <= x, clamped to the grid's cells.
"""
import llvmlite.ir as ir
import numpy as np
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

from .weights import locate_axis_point

__all__ = ["body_boxes", "cut_cell_particles", "gauss_rule_1d", "gauss_rule_cells",
           "locate_cells"]


@intrinsic
def cube_root(typingctx, x):
    """libm's cbrt(x) (float64). numba's np.cbrt is pow(x, 1/3), which is
    not exact on perfect cubes (27 -> 3.0000000000000004); libm's is (a
    uniform layout of 2 x 2 x 2 particles per cell has V_p / |e| = 1/8,
    whose root 1/2 sizes the particles' boxes exactly)."""
    sig = types.float64(types.float64)

    def codegen(context, builder, signature, args):
        fnty = ir.FunctionType(ir.DoubleType(), [ir.DoubleType()])
        return builder.call(cgutils.get_or_insert_function(builder.module, fnty, "cbrt"), args)

    return sig, codegen


@njit(cache=True, error_model="numpy")
def gauss_points_most(n, ncells, k):
    """The most points of a rule of n particles on ncells cells, k Gauss
    points a cell piece: each piece covers its cells, a cell at most once
    per piece (pieces <= n)."""
    return (ncells + n) * k


@njit(cache=True, error_model="numpy")
def gauss_rule_1d(x, V, gap, breaks, ref, wref):
    """(order, piece_particles, piece_points, xg, wg, cell): ``order`` the
    stable sort of x; piece j holds the sorted particles
    order[piece_particles[j]:piece_particles[j + 1]] and the points
    piece_points[j]:piece_points[j + 1] (ascending)."""
    n = x.shape[0]
    most = gauss_points_most(n, breaks.shape[0] - 1, ref.shape[0])
    starts = np.empty(n + 1, dtype=np.int64)
    piece_points = np.empty(n + 1, dtype=np.int64)
    xg = np.empty(most)
    wg = np.empty(most)
    cell = np.empty(most, dtype=np.int64)
    order = np.empty(n, dtype=np.int64)
    npieces, ng = gauss_rule_1d_into(x, V, gap, breaks, ref, wref, order, starts, np.empty(n),
                                     np.empty(n), np.empty(n, dtype=np.int64), piece_points, xg,
                                     wg, cell)
    return order, starts[:npieces + 1], piece_points[:npieces + 1], xg[:ng], wg[:ng], cell[:ng]


@njit(cache=True, error_model="numpy")
def gauss_rule_1d_into(x, V, gap, breaks, ref, wref, order, starts, lows, highs, first,
                       piece_points, xg, wg, cell):
    """:func:`gauss_rule_1d` into given arrays (a compiled run keeps them):
    returns (npieces, ng); the rule is order (n), starts[:npieces + 1],
    piece_points[:npieces + 1], xg, wg, cell[:ng]; lows, highs, first
    (n each) are work space; starts and piece_points hold n + 1, xg, wg
    and cell :func:`gauss_points_most`."""
    n = x.shape[0]
    k = ref.shape[0]
    ncells = breaks.shape[0] - 1
    stable_order(x, order)
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
    piece_points[0] = 0
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
    return npieces, ng


@njit(cache=True, error_model="numpy")
def stable_order(x, order):
    """order = the stable sort of x (np.argsort(x, kind="mergesort")): by
    insertion from 0..n-1, linear in n on particles that keep their order
    (a 1D body's usually do); past 8 n moves, or at a NaN, by np.argsort."""
    n = x.shape[0]
    for i in range(n):
        order[i] = i
        if x[i] != x[i]:
            order[:] = np.argsort(x, kind="mergesort")
            return
    moves = 0
    for i in range(1, n):
        v = x[i]
        if moves > 8 * n:
            order[:] = np.argsort(x, kind="mergesort")
            return
        j = i - 1
        while j >= 0 and x[order[j]] > v:
            order[j + 1] = order[j]
            j -= 1
            moves += 1
        order[j + 1] = i


@njit(cache=True, error_model="numpy")
def locate_cells(x, axes, uniform):
    """The cell (ix + nx iy + nx ny iz; ix in 1D) of each point x (n, d);
    ``axes`` the grid's breakpoints per axis (a tuple of d arrays),
    ``uniform`` whether each axis is uniform (a tuple of d flags)."""
    n, dim = x.shape
    cell = np.zeros(n, dtype=np.int64)
    stride = 1
    for a in range(dim):  # axis by axis (one look-up of the axis each)
        breaks = axes[a]
        flat = uniform[a]
        m = breaks.shape[0] - 1
        inv_h = m / (breaks[m] - breaks[0])  # the uniform axes' 1 / h, as SplineGrid.locate
        for i in range(n):
            cell[i] += stride * locate_axis_point(x[i, a], breaks, flat, inv_h)
        stride *= m
    return cell


@njit(cache=True, error_model="numpy")
def _cell_counts(axes, dim):
    """Cells per axis (3,) (1 beyond the dimension) and their product."""
    counts = np.ones(3, dtype=np.int64)
    for a in range(dim):
        counts[a] = axes[a].shape[0] - 1
    return counts, counts[0] * counts[1] * counts[2]


@njit(cache=True, error_model="numpy")
def body_boxes(x, V, pcell, axes):
    """(lo, hi), each (ncells, d): the box of each held cell that the body
    covers (rows of cells without particles are not set), the twin of
    :func:`skfem_mpm.reconstruct.body_boxes` in 2D and 3D (``axes`` the
    breakpoints per axis; the same arithmetic, so in 2D the same boxes bit
    for bit; in 3D the cube roots are libm's, NumPy's own differ by up to
    an ulp; see its docstring for the rule)."""
    dim = x.shape[1]
    counts, ncells = _cell_counts(axes, dim)
    held = np.zeros(ncells, dtype=np.bool_)
    pmin = np.full((ncells, dim), np.inf)
    pmax = np.full((ncells, dim), -np.inf)
    hmax = np.zeros((ncells, dim))
    volume = np.zeros(ncells)
    for i in range(pcell.shape[0]):
        held[pcell[i]] = True
    size = np.ones((ncells, dim))  # the held cells' sizes and indices per axis
    index = np.zeros((ncells, dim), dtype=np.int64)
    stride = 1
    for a in range(dim):
        breaks = axes[a]
        for c in range(ncells):
            if held[c]:
                ea = (c // stride) % counts[a]
                index[c, a] = ea
                size[c, a] = breaks[ea + 1] - breaks[ea]
        stride *= counts[a]
    for i in range(pcell.shape[0]):
        c = pcell[i]
        area = size[c, 0]
        for a in range(1, dim):
            area = area * size[c, a]
        ratio = V[i] / area
        scale = np.sqrt(ratio) if dim == 2 else cube_root(ratio)
        for a in range(dim):
            half = 0.5 * (size[c, a] * scale)
            pmin[c, a] = min(pmin[c, a], x[i, a] - half)
            pmax[c, a] = max(pmax[c, a], x[i, a] + half)
            hmax[c, a] = max(hmax[c, a], half)
        volume[c] += V[i]
    lo = np.zeros((ncells, dim))
    hi = np.zeros((ncells, dim))
    lower = np.empty(dim)
    upper = np.empty(dim)
    closed_lo = np.empty(dim, dtype=np.bool_)
    closed_hi = np.empty(dim, dtype=np.bool_)
    est_lo = np.empty(dim)
    est_hi = np.empty(dim)
    for c in range(ncells):
        if not held[c]:
            continue
        n_open = 0
        est_volume = 1.0
        stride = 1
        for a in range(dim):
            breaks = axes[a]
            n = counts[a]
            ea = index[c, a]
            lower[a] = breaks[ea]
            upper[a] = breaks[ea + 1]
            below = ea > 0 and held[c - stride]
            above = ea < n - 1 and held[c + stride]
            stride *= n
            gap_lo = pmin[c, a] - lower[a]
            gap_hi = upper[a] - pmax[c, a]
            closed_lo[a] = below or gap_lo < hmax[c, a] + (max(gap_hi, 0.0) if above else 0.0)
            closed_hi[a] = above or gap_hi < hmax[c, a] + (max(gap_lo, 0.0) if below else 0.0)
            est_lo[a] = lower[a] if closed_lo[a] else max(lower[a], pmin[c, a])
            est_hi[a] = upper[a] if closed_hi[a] else min(upper[a], pmax[c, a])
            if not (closed_lo[a] and closed_hi[a]):
                n_open += 1
            est_volume = est_volume * (est_hi[a] - est_lo[a])
        ratio = volume[c] / est_volume
        factor = ratio if n_open == 1 else (np.sqrt(ratio) if n_open == 2 else cube_root(ratio))
        for a in range(dim):
            if closed_lo[a] and closed_hi[a]:
                lo[c, a] = lower[a]
                hi[c, a] = upper[a]
                continue
            width = min(upper[a] - lower[a], factor * (est_hi[a] - est_lo[a]))
            if closed_lo[a]:
                lo[c, a] = lower[a]
            elif closed_hi[a]:
                lo[c, a] = upper[a] - width
            else:
                lo[c, a] = min(max(lower[a], 0.5 * (est_lo[a] + est_hi[a]) - 0.5 * width),
                               upper[a] - width)
            hi[c, a] = upper[a] if closed_hi[a] else lo[c, a] + width
    return lo, hi


@njit(cache=True, error_model="numpy")
def cut_cell_particles(pcell, lo, hi, axes):
    """(own, kept): the particles (ascending) whose cell's body box lo..hi
    (:func:`body_boxes`) is not the whole cell, a cell a free surface
    cuts, whose particles are points of the rule themselves; and the cells
    of the other particles, in particle order (those :func:`gauss_rule_cells`
    integrates)."""
    n = pcell.shape[0]
    ncells, dim = lo.shape
    held = np.zeros(ncells, dtype=np.bool_)
    for i in range(n):
        held[pcell[i]] = True
    cut_cell = np.zeros(ncells, dtype=np.bool_)  # per held cell, axis by axis
    stride = 1
    for a in range(dim):
        breaks = axes[a]
        m = breaks.shape[0] - 1
        for c in range(ncells):
            if held[c]:
                ea = (c // stride) % m
                if not (lo[c, a] == breaks[ea] and hi[c, a] == breaks[ea + 1]):
                    cut_cell[c] = True
        stride *= m
    cut = np.empty(n, dtype=np.bool_)
    nown = 0
    for i in range(n):
        cut[i] = cut_cell[pcell[i]]
        if cut[i]:
            nown += 1
    own = np.empty(nown, dtype=np.int64)
    kept = np.empty(n - nown, dtype=np.int64)
    j = 0
    for i in range(n):
        if cut[i]:
            own[j] = i
            j += 1
        else:
            kept[i - j] = pcell[i]
    return own, kept


@njit(cache=True, error_model="numpy")
def gauss_rule_cells(pcell, lo, hi, ref, wref):
    """(xg, wg, cell) of the 2D or 3D tensor Gauss rule on the boxes
    lo[c]..hi[c] (:func:`body_boxes`) of the cells c in ``pcell``
    (ascending, each once; see the module docstring)."""
    ncells, dim = lo.shape
    k = ref.shape[0]
    held = np.zeros(ncells, dtype=np.bool_)
    for i in range(pcell.shape[0]):
        held[pcell[i]] = True
    nheld = 0
    for c in range(ncells):
        if held[c]:
            nheld += 1
    kz = k if dim == 3 else 1
    ng = nheld * k * k * kz
    xg = np.empty((ng, dim))
    wg = np.empty(ng)
    cell = np.empty(ng, dtype=np.int64)
    g = 0
    for c in range(ncells):
        if not held[c]:
            continue
        hx = hi[c, 0] - lo[c, 0]
        hy = hi[c, 1] - lo[c, 1]
        hz = hi[c, dim - 1] - lo[c, dim - 1]  # 2D: read, not used
        for q in range(kz):
            for b in range(k):
                for a in range(k):
                    xg[g, 0] = lo[c, 0] + hx * ref[a]
                    xg[g, 1] = lo[c, 1] + hy * ref[b]
                    w = (hx * wref[a]) * (hy * wref[b])
                    if dim == 3:
                        xg[g, 2] = lo[c, 2] + hz * ref[q]
                        w = w * (hz * wref[q])
                    wg[g] = w
                    cell[g] = c
                    g += 1
    return xg, wg, cell
