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

:func:`spline_ls_system` assembles A + P as a stencil array (ndofs, 49)
from the particles' cubic B-spline values of :func:`spline_basis` (made
once per set of positions, kept for every fit on them):
entry s = (dy + 3) 7 + (dx + 3) of row i is the coupling with the dof at
offset (dx, dy); A is bitwise symmetric (each particle adds the same
products to (i, j) and (j, i)). The sparse factorisation is the caller's
(:mod:`skfem_mpm.solve.compiled_reconstruct`).
"""
import numpy as np
from numba import njit

from .stencil import closed_axis_functions, extracted_axis_functions

__all__ = ["WIDTH", "band_solve", "spline_band", "spline_basis", "spline_evaluate",
           "spline_ls_system"]

P = 3  # cubic
WIDTH = 2 * P + 1  # stencil offsets -3..3 per axis
CENTRE = P * WIDTH + P


@njit(cache=True, inline="always", error_model="numpy")
def _point_basis(x, y, ax, ay, wx, wy):
    """(ex, ey): the cell of (x, y) along each axis of the cubic grid, and
    wx, wy its four cubic B-splines' values along each (the closed form of
    scalars, else the extraction, not inlined)."""
    bx, ux, ihx, Cx = ax
    by, uy, ihy, Cy = ay
    closed, ex, wx[0], wx[1], wx[2], wx[3], _, _, _, _ = closed_axis_functions(
        x, bx[0], bx.shape[0] - 1, ux, ihx, P)
    if not closed:
        ex, wx[0], wx[1], wx[2], wx[3], _, _, _, _ = extracted_axis_functions(
            x, bx, ux, ihx, Cx, P)
    closed, ey, wy[0], wy[1], wy[2], wy[3], _, _, _, _ = closed_axis_functions(
        y, by[0], by.shape[0] - 1, uy, ihy, P)
    if not closed:
        ey, wy[0], wy[1], wy[2], wy[3], _, _, _, _ = extracted_axis_functions(
            y, by, uy, ihy, Cy, P)
    return ex, ey


@njit(cache=True, error_model="numpy")
def spline_basis(x, ax, ay, cells, W):
    """cells[i] = (ex, ey), the cell of x[i] along each axis of the cubic
    grid (axes ``ax``, ``ay``: breakpoints, uniform, 1/h, extraction), and
    W[i] = the values of its cubic B-splines there, the four along x, then
    the four along y: what :func:`spline_ls_system` sums (kept for the
    other fits on the same particles)."""
    for i in range(x.shape[0]):
        cells[i, 0], cells[i, 1] = _point_basis(x[i, 0], x[i, 1], ax, ay, W[i, :4], W[i, 4:])


@njit(cache=True, error_model="numpy")
def spline_ls_system(V, values, cells, W, nbx, nby, penalty, with_matrix, A, rhs):
    """rhs (ndofs, k) = B^T W f and, ``with_matrix``, A (ndofs, 49) = the
    stencil of A + P (see the module docstring) of the particles' volumes
    V and :func:`spline_basis` (cells, W)."""
    k = values.shape[1]
    if with_matrix:
        A[:] = 0.0
    rhs[:] = 0.0
    for i in range(V.shape[0]):
        ex, ey = cells[i, 0], cells[i, 1]
        for b in range(4):
            for a in range(4):
                row = (ey + b) * nbx + ex + a
                wr = V[i] * W[i, a] * W[i, 4 + b]
                for col in range(k):
                    rhs[row, col] += wr * values[i, col]
                if not with_matrix:
                    continue
                for d in range(4):
                    for c in range(4):
                        A[row, (d - b + P) * WIDTH + (c - a + P)] += wr * (W[i, c] * W[i, 4 + d])
    if with_matrix:
        _penalty(A, nbx, nby, penalty)


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
    wx = np.empty(4)
    wy = np.empty(4)
    for g in range(xg.shape[0]):
        ex, ey = _point_basis(xg[g, 0], xg[g, 1], ax, ay, wx, wy)
        for col in range(k):
            out[g, col] = 0.0
        for b in range(4):
            for a in range(4):
                row = (ey + b) * nbx + ex + a
                w = wx[a] * wy[b]
                for col in range(k):
                    out[g, col] += w * coef[row, col]


@njit(cache=True, error_model="numpy")
def spline_band(A, nbx, band):
    """band (ndofs, 3 nbx + 4): the lower band of the stencil array A of
    :func:`spline_ls_system`, band[i, d] = (A + P)_(i, i - d) (the storage
    of :func:`~skfem_mpm.kernels.kronecker.banded_cholesky_into`)."""
    band[:] = 0.0
    for i in range(A.shape[0]):
        ix = i % nbx
        iy = i // nbx
        for dy in range(-P, 1):
            if iy + dy < 0:
                continue
            for dx in range(-P, P + 1):
                if (dy == 0 and dx > 0) or ix + dx < 0 or ix + dx >= nbx:
                    continue
                band[i, -(dy * nbx + dx)] = A[i, (dy + P) * WIDTH + dx + P]


@njit(cache=True, error_model="numpy")
def band_solve(L, b):
    """b (n, k) := (L L^T)^-1 b for the banded lower Cholesky factor L,
    L[i, d] = L_(i, i - d): forward, then backward substitution."""
    n = L.shape[0]
    p = L.shape[1] - 1
    k = b.shape[1]
    for i in range(n):
        for d in range(1, min(p, i) + 1):
            for c in range(k):
                b[i, c] -= L[i, d] * b[i - d, c]
        for c in range(k):
            b[i, c] /= L[i, 0]
    for i in range(n - 1, -1, -1):
        for d in range(1, min(p, n - 1 - i) + 1):
            for c in range(k):
                b[i, c] -= L[i + d, d] * b[i + d, c]
        for c in range(k):
            b[i, c] /= L[i, 0]
