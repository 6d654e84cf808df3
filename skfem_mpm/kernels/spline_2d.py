"""Least squares in the cubic B-spline space of a 2D grid, compiled: the
assembly and evaluation of the 2D ``spline`` reconstruction of
:mod:`skfem_mpm.reconstruct` (``_spline_ls``, the oracle).

With N_i the cubic tensor B-splines on the grid's breakpoints (C2; dofs
numbered x fastest) and the particles' volumes V_p, the coefficients c
(ndofs, k) of all k value columns solve

    (A + P) c = B^T W f,    A_ij = sum_p V_p N_i(x_p) N_j(x_p),
                            (B^T W f)_i = sum_p V_p N_i(x_p) f_p,

where P regularises the functions the particles barely see: with
t = median of the positive diagonal entries of A and "weak" dofs those with
A_ii < t / 10, P = penalty t (D_w^T D_w + diag(A_ii == 0)), D_w the rows of
the second differences (c_j - 2 c_(j+1) + c_(j+2) along either axis) that
touch a weak dof; P = 0 when no dof is weak. The fit at the Gauss points is
f_h(x_g) = sum_i N_i(x_g) c_i.

:func:`spline_ls_system` assembles A + P as a stencil array (ndofs, 49),
keeping the particles' cubic B-spline values for the other fits on the
same positions: entry s = (dy + 3) 7 + (dx + 3) of row i is the coupling
with the dof at offset (dx, dy). Its lower half (the dofs j <= i) is
summed, the upper half copied from it: A is bitwise symmetric. The
factorisation is the caller's (:mod:`skfem_mpm.solve.compiled_reconstruct`:
the banded Cholesky factor of :mod:`skfem_mpm.kernels.band_factor`, which
reads the lower half).
"""
import numpy as np
from numba import njit

from .stencil import closed_axis_functions, extracted_axis_functions

__all__ = ["WIDTH", "spline_ell_columns", "spline_evaluate", "spline_ls_system"]

P = 3  # cubic
WIDTH = 2 * P + 1  # stencil offsets -3..3 per axis
CENTRE = P * WIDTH + P


@njit(cache=True, error_model="numpy")
def spline_ls_system(x, V, values, ax, ay, nbx, nby, penalty, fresh, with_matrix, cells, W, A,
                     rhs):
    """rhs (ndofs, k) = B^T W f and, ``with_matrix``, A (ndofs, 49) = the
    stencil of A + P (see the module docstring); ``ax``, ``ay`` the cubic
    grid's axes (breakpoints, uniform, 1/h, extraction). The particles'
    cubic B-spline values: with ``fresh`` computed and kept, cells[i] =
    (ex, ey) the cell of x[i] along each axis and W[i] its four functions'
    values along x, then the four along y; else read from cells, W (kept by
    an earlier call on the same positions)."""
    k = values.shape[1]
    if with_matrix:
        A[:] = 0.0
    rhs[:] = 0.0
    bx, ux, ihx, Cx = ax
    by, uy, ihy, Cy = ay
    x0, ncx = bx[0], bx.shape[0] - 1
    y0, ncy = by[0], by.shape[0] - 1
    wx = np.empty(4)
    wy = np.empty(4)
    for i in range(V.shape[0]):
        if fresh:
            # the closed form of scalars, else the extraction (not inlined)
            closed, ex, wx[0], wx[1], wx[2], wx[3], _, _, _, _ = closed_axis_functions(
                x[i, 0], x0, ncx, ux, ihx, P)
            if not closed:
                ex, wx[0], wx[1], wx[2], wx[3], _, _, _, _ = extracted_axis_functions(
                    x[i, 0], bx, ux, ihx, Cx, P)
            closed, ey, wy[0], wy[1], wy[2], wy[3], _, _, _, _ = closed_axis_functions(
                x[i, 1], y0, ncy, uy, ihy, P)
            if not closed:
                ey, wy[0], wy[1], wy[2], wy[3], _, _, _, _ = extracted_axis_functions(
                    x[i, 1], by, uy, ihy, Cy, P)
            cells[i, 0] = ex
            cells[i, 1] = ey
            for a in range(4):
                W[i, a] = wx[a]
                W[i, 4 + a] = wy[a]
        else:
            ex = cells[i, 0]
            ey = cells[i, 1]
            for a in range(4):
                wx[a] = W[i, a]
                wy[a] = W[i, 4 + a]
        for b in range(4):
            for a in range(4):
                row = (ey + b) * nbx + ex + a
                wr = V[i] * wx[a] * wy[b]
                for col in range(k):
                    rhs[row, col] += wr * values[i, col]
    if with_matrix:
        _cell_blocks(V, nbx, nby, cells, W, A)
        _mirror(A, nbx, nby)
        _penalty(A, nbx, nby, penalty)


# the 10 products wx_a wx_c (a >= c) of one axis's four functions
# (_PAIRS[q] = (a, c)) and the pair index of any (a, c) (_PAIR_OF)
_PAIRS = np.array([(a, c) for a in range(4) for c in range(a + 1)], dtype=np.int64)
_PAIR_OF = np.zeros((4, 4), dtype=np.int64)
for _q, (_a, _c) in enumerate(_PAIRS):
    _PAIR_OF[_a, _c] = _PAIR_OF[_c, _a] = _q


@njit(cache=True, error_model="numpy")
def _cell_blocks(V, nbx, nby, cells, W, A):
    """The lower half of A = sum_p V_p N(x_p) N(x_p)^T into the stencil
    array A (zeroed) from the particles' cubic B-spline values (cells, W),
    cell by cell. With N_ab = wx_a wy_b the entry of dofs (a, b), (c, d)
    of a cell is sum_p V_p (wy_b wy_d)_p (wx_a wx_c)_p: the particles of a
    cell are summed into the 10 x 10 block S_(bd),(ac) of the products of
    each axis's pairs (a >= c, b >= d; 100 multiply-adds a particle where
    the 136 lower-half entries took 136 scattered ones), whose entries are
    added to A once per cell. The cells are taken in the order of a
    counting sort of the particles by cell, each cell's particles in index
    order."""
    n = V.shape[0]
    ncx, ncy = nbx - P, nby - P
    start = np.zeros(ncx * ncy + 1, dtype=np.int64)
    for i in range(n):
        start[cells[i, 1] * ncx + cells[i, 0] + 1] += 1
    for e in range(ncx * ncy):
        start[e + 1] += start[e]
    order = np.empty(n, dtype=np.int64)
    fill = start[:-1].copy()
    for i in range(n):
        e = cells[i, 1] * ncx + cells[i, 0]
        order[fill[e]] = i
        fill[e] += 1
    pairs, pair_of = _PAIRS, _PAIR_OF
    S = np.empty((10, 10))
    X = np.empty(10)
    Y = np.empty(10)
    for e in range(ncx * ncy):
        if start[e] == start[e + 1]:
            continue
        S[:, :] = 0.0
        for j in range(start[e], start[e + 1]):
            i = order[j]
            v = V[i]
            for q in range(10):
                X[q] = W[i, pairs[q, 0]] * W[i, pairs[q, 1]]
                Y[q] = v * (W[i, 4 + pairs[q, 0]] * W[i, 4 + pairs[q, 1]])
            for q in range(10):
                yq = Y[q]
                for r in range(10):
                    S[q, r] += yq * X[r]
        ex, ey = e % ncx, e // ncx
        for b in range(4):
            for a in range(4):
                row = (ey + b) * nbx + ex + a
                for d in range(b + 1):  # the lower half: dof (c, d) not after (a, b)
                    sy = S[pair_of[b, d]]
                    for c in range(4 if d < b else a + 1):
                        A[row, (d - b + P) * WIDTH + (c - a + P)] += sy[pair_of[a, c]]


@njit(cache=True, error_model="numpy")
def _mirror(A, nbx, nby):
    """The upper half of the stencil array A from its lower half:
    A[i, s] = A[j, 48 - s] (s the offset (dx, dy) to dof j, 48 - s the
    offset back) where j comes after i."""
    for i in range(nbx * nby):
        ix = i % nbx
        iy = i // nbx
        for dy in range(0, P + 1):
            if iy + dy >= nby:
                break
            for dx in range(-P if dy > 0 else 1, P + 1):
                if 0 <= ix + dx < nbx:
                    s = (dy + P) * WIDTH + dx + P
                    A[i, s] = A[i + dy * nbx + dx, WIDTH * WIDTH - 1 - s]


@njit(cache=True, error_model="numpy")
def _penalty(A, nbx, nby, penalty):
    """A += P (see the module docstring)."""
    ndofs = nbx * nby
    npos = 0
    diag = np.empty(ndofs)
    for i in range(ndofs):
        if A[i, CENTRE] > 0.0:
            diag[npos] = A[i, CENTRE]
            npos += 1
    if npos == 0:
        return
    typical = np.median(diag[:npos])
    weak = np.empty(ndofs, dtype=np.bool_)
    unseen = np.empty(ndofs, dtype=np.bool_)
    anyweak = False
    for i in range(ndofs):
        weak[i] = A[i, CENTRE] < 0.1 * typical
        unseen[i] = not A[i, CENTRE] > 0.0
        anyweak = anyweak or weak[i]
    if not anyweak:
        return
    scale = penalty * typical
    stencil = np.array([1.0, -2.0, 1.0])
    for axis in range(2):
        n = nbx if axis == 0 else nby
        other = nby if axis == 0 else nbx
        step = 1 if axis == 0 else nbx
        if n < 3:
            continue
        for o in range(other):
            for j in range(n - 2):
                first = o * nbx + j if axis == 0 else j * nbx + o
                touches = False
                for q in range(3):
                    touches = touches or weak[first + q * step]
                if not touches:
                    continue
                for q in range(3):
                    for r in range(3):
                        off = (r - q) * (WIDTH if axis == 1 else 1)
                        A[first + q * step, CENTRE + off] += scale * stencil[q] * stencil[r]
    for i in range(ndofs):
        if unseen[i]:
            A[i, CENTRE] += scale


@njit(cache=True, error_model="numpy")
def spline_evaluate(xg, coef, ax, ay, nbx, out):
    """out[g] (ng, k) = sum_i N_i(xg[g]) coef[i] for the cubic grid's axes."""
    k = coef.shape[1]
    bx, ux, ihx, Cx = ax
    by, uy, ihy, Cy = ay
    x0, ncx = bx[0], bx.shape[0] - 1
    y0, ncy = by[0], by.shape[0] - 1
    wx = np.empty(4)
    wy = np.empty(4)
    for g in range(xg.shape[0]):
        # the closed form of scalars, else the extraction (not inlined)
        closed, ex, wx[0], wx[1], wx[2], wx[3], _, _, _, _ = closed_axis_functions(
            xg[g, 0], x0, ncx, ux, ihx, P)
        if not closed:
            ex, wx[0], wx[1], wx[2], wx[3], _, _, _, _ = extracted_axis_functions(
                xg[g, 0], bx, ux, ihx, Cx, P)
        closed, ey, wy[0], wy[1], wy[2], wy[3], _, _, _, _ = closed_axis_functions(
            xg[g, 1], y0, ncy, uy, ihy, P)
        if not closed:
            ey, wy[0], wy[1], wy[2], wy[3], _, _, _, _ = extracted_axis_functions(
                xg[g, 1], by, uy, ihy, Cy, P)
        for col in range(k):
            out[g, col] = 0.0
        for b in range(4):
            for a in range(4):
                row = (ey + b) * nbx + ex + a
                w = wx[a] * wy[b]
                for col in range(k):
                    out[g, col] += w * coef[row, col]


def spline_ell_columns(nbx, nby):
    """cols (ndofs, 49): the dof of stencil entry s of each row of
    :func:`spline_ls_system`'s A (its ELL columns; an offset outside the
    grid: the row's own dof, where A holds 0)."""
    dof = np.arange(nbx * nby)
    a, b = dof % nbx, dof // nbx
    offsets = np.arange(WIDTH) - P
    aa = a[:, None] + np.tile(offsets, WIDTH)[None, :]
    bb = b[:, None] + np.repeat(offsets, WIDTH)[None, :]
    valid = (aa >= 0) & (aa < nbx) & (bb >= 0) & (bb < nby)
    return np.where(valid, bb * nbx + aa, dof[:, None]).astype(np.int64)
