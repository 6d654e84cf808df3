"""B-bar on the compiled paths: the dilatation rate of each particle's
velocity gradient replaced by its cell's volume-weighted mean, before the
material's point law (:class:`skfem_mpm.materials.BBar`, whose
``averaged`` is the NumPy reference; Hughes 1980)::

    theta_p   = tr L_p
    theta_c   = sum_{q in c} V_q theta_q / sum_{q in c} V_q
    L_p      <- L_p + (theta_c(p) - theta_p) / dim  I

Cells as :meth:`skfem_mpm.SplineGrid.locate` numbers them (flat, the first
axis fastest; a point on a cell boundary in the cell on its right), found
per axis by :func:`skfem_mpm.kernels.weights.locate_axis_point` (the same
arithmetic). The sums run over the particles in their order, as
``np.bincount`` does: the result is the reference's to the last bit.
One serial pass over the particles and one over the body's particles
again (a few operations each, against the hundreds of a transfer).
"""
import numpy as np
from numba import njit

from .weights import locate_axis_point

__all__ = ["average_dilatation"]


@njit(cache=True, error_model="numpy")
def average_dilatation(axes, index, every, x, V, L, volume, weighted, cell):
    """L (n, dim, dim) <- L_bar (see the module) in place for the particles
    ``index`` (or every particle), averaged over those particles only;
    ``axes`` the grid record's axes (kernels.records.grid_record);
    ``volume``, ``weighted`` (cells,) and ``cell`` (n,) work arrays."""
    n = x.shape[0] if every else index.shape[0]
    dim = L.shape[1]
    volume[:] = 0.0
    weighted[:] = 0.0
    for k in range(n):
        i = k if every else index[k]
        c = 0
        stride = 1
        for a in range(dim):
            breaks, uniform, inv_h, _ = axes[a]
            c += stride * locate_axis_point(x[i, a], breaks, uniform, inv_h)
            stride *= breaks.shape[0] - 1
        cell[k] = c
        theta = 0.0
        for a in range(dim):
            theta += L[i, a, a]
        volume[c] += V[i]
        weighted[c] += V[i] * theta
    for k in range(n):
        i = k if every else index[k]
        c = cell[k]
        theta = 0.0
        for a in range(dim):
            theta += L[i, a, a]
        shift = (weighted[c] / volume[c] - theta) / dim
        for a in range(dim):
            L[i, a, a] += shift
