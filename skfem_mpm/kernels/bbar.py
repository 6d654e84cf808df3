"""B-bar on the compiled paths: the dilatation rate of each particle's
velocity gradient replaced by its lumped projection onto a space of
dilatations, before the material's point law
(:class:`skfem_mpm.materials.BBar`, whose ``averaged`` is the NumPy
reference and gives the formulas and sources)::

    theta_p   = tr L_p
    theta_A   = sum_q H_A(x_q) V_q theta_q / sum_q H_A(x_q) V_q
    theta_bar = sum_A H_A(x_p) theta_A
    L_p      <- L_p + (theta_bar - theta_p) / dim  I

with H_A the cells' indicators (``vertices`` False: theta_bar is the
cell's volume-weighted mean) or the continuous piecewise-(bi/tri)linear
functions of the knot grid's vertices (``vertices`` True: H_A(x) the
product over the axes of (1 - t) or t, t = (x - x_e) / (x_(e+1) - x_e) in
the point's cell e; a term with H_A(x_p) = 0 is left out).

Cells as :meth:`skfem_mpm.SplineGrid.locate` numbers them (flat, the first
axis fastest; a point on a cell boundary in the cell on its right), found
per axis by :func:`skfem_mpm.kernels.weights.locate_axis_point` (the same
arithmetic); vertices likewise (n_a + 1 per axis). The sums run over the
particles in their order and a particle's vertices in theirs (the first
axis fastest), as ``np.bincount`` over the flattened (particle, vertex)
pairs does: the result is the reference's to the last bit. One serial
pass over the particles and one over the body's particles again (a few
operations each, against the hundreds of a transfer).
"""
import numpy as np
from numba import njit

from .weights import locate_axis_point

__all__ = ["average_dilatation"]


@njit(cache=True, error_model="numpy")
def average_dilatation(axes, index, every, vertices, x, V, L, volume, weighted, ids, values):
    """L (n, dim, dim) <- L_bar (see the module) in place for the particles
    ``index`` (or every particle), projected over those particles only;
    ``axes`` the grid record's axes (kernels.records.grid_record);
    ``vertices``: the vertex functions, else the cells'; work arrays
    ``volume``, ``weighted`` (one entry per function: cells or vertices),
    ``ids`` (n, 2^dim) int and ``values`` (n, 2^dim) (each particle's
    functions; cells: the first column)."""
    n = x.shape[0] if every else index.shape[0]
    dim = L.shape[1]
    count = (1 << dim) if vertices else 1
    volume[:] = 0.0
    weighted[:] = 0.0
    for k in range(n):
        i = k if every else index[k]
        for j in range(count):
            ids[k, j] = 0
            values[k, j] = 1.0
        stride = 1
        for a in range(dim):
            breaks, uniform, inv_h, _ = axes[a]
            e = locate_axis_point(x[i, a], breaks, uniform, inv_h)
            if vertices:
                t = (x[i, a] - breaks[e]) / (breaks[e + 1] - breaks[e])
                for j in range(count):
                    if (j >> a) & 1:
                        ids[k, j] += stride * (e + 1)
                        values[k, j] = values[k, j] * t
                    else:
                        ids[k, j] += stride * e
                        values[k, j] = values[k, j] * (1.0 - t)
                stride *= breaks.shape[0]
            else:
                ids[k, 0] += stride * e
                stride *= breaks.shape[0] - 1
        theta = 0.0
        for a in range(dim):
            theta += L[i, a, a]
        for j in range(count):
            w = values[k, j] * V[i]
            volume[ids[k, j]] += w
            weighted[ids[k, j]] += w * theta
    for k in range(n):
        i = k if every else index[k]
        theta = 0.0
        for a in range(dim):
            theta += L[i, a, a]
        mean = 0.0
        for j in range(count):
            if values[k, j] != 0.0:
                mean += values[k, j] * (weighted[ids[k, j]] / volume[ids[k, j]])
        shift = (mean - theta) / dim
        for a in range(dim):
            L[i, a, a] += shift
