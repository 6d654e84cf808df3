"""B-spline elements for scikit-fem, built by Bezier extraction.

On every cell the element evaluates the Bernstein polynomials on scikit-fem's
reference cell [0, 1]^dim and multiplies them with that cell's extraction
matrix (Borden et al. 2011, IJNME 87:15-47, eq. 8):

    N_(e, i)(xi) = sum_j C_e[i, j] B_j(xi)              (1D)
    N_(e, a + (p+1) b)(xi, eta) = N^x_(e_x, a)(xi) N^y_(e_y, b)(eta)   (2D)

The local-to-global dof table (the spline connectivity) is not the one
scikit-fem derives from vertices; use the element through
:class:`skfem_mpm.SplineGrid`, which supplies the matching ``dofs`` and
mapping (``grid.basis()``, ``grid.element``, ``grid.dofs``).
"""
import numpy as np
from skfem.element import DiscreteField, Element
from skfem.refdom import RefLine, RefQuad

from .bernstein import bernstein, bernstein_derivative
from .knots import check_breakpoints, check_degree, extraction_operators

__all__ = ["ElementLineBSpline", "ElementQuadBSpline"]


def _axis_local(C, cells, p, xi):
    """Local 1D spline values and reference derivatives on the given cells.

    ``xi`` is (nqp,) shared by all cells or (ncells, nqp) per cell; returns
    two arrays of shape (p + 1, ncells, nqp).
    """
    Ce = C[cells]  # (nel, p+1, p+1)
    if xi.ndim == 1:
        B = bernstein(p, xi)  # (nqp, p+1)
        dB = bernstein_derivative(p, xi)
        return np.einsum("eij,qj->ieq", Ce, B), np.einsum("eij,qj->ieq", Ce, dB)
    B = bernstein(p, xi)  # (nel, nqp, p+1)
    dB = bernstein_derivative(p, xi)
    return np.einsum("eij,eqj->ieq", Ce, B), np.einsum("eij,eqj->ieq", Ce, dB)


class _BSplineElement(Element):
    """Shared parts of the line and quadrilateral B-spline elements."""

    def __init__(self, degree, breakpoints):
        self.degree = check_degree(degree)
        p = self.degree
        self.breakpoints = tuple(
            check_breakpoints(b, name=f"breakpoints[{axis}]")
            for axis, b in enumerate(breakpoints)
        )
        self.cells_per_axis = tuple(b.size - 1 for b in self.breakpoints)
        self.extraction = tuple(extraction_operators(b, p) for b in self.breakpoints)
        nloc = (p + 1) ** len(self.breakpoints)
        self.interior_dofs = nloc
        self.dofnames = ["u"] * nloc

    def _cells(self, mapping, tind):
        if tind is None:
            return np.arange(mapping.mesh.t.shape[1])
        return np.asarray(tind)

    def _physical_gradient(self, mapping, X, tind, dref):
        invDF = mapping.invDF(X, tind)
        return np.einsum("ijkl,ikl->jkl", invDF, dref)


class ElementLineBSpline(_BSplineElement):
    """B-spline element of degree ``p`` (1, 2 or 3) on a line.

    ``breakpoints`` are the cell boundaries of the grid (default: one cell
    [0, 1]); the space has maximal smoothness C^(p-1) and an open knot vector.
    p = 1 is the piecewise-linear Lagrange space of ``ElementLineP1``.
    """

    refdom = RefLine

    def __init__(self, p, breakpoints=(0.0, 1.0)):
        super().__init__(p, (breakpoints,))
        self.maxdeg = self.degree

    def gbasis(self, mapping, X, i, tind=None):
        p = self.degree
        if not 0 <= i < p + 1:
            self._index_error()
        cells = self._cells(mapping, tind)
        Ce = self.extraction[0][cells][:, i, :]  # (nel, p+1)
        xi = X[0]
        if xi.ndim == 1:
            val = Ce @ bernstein(p, xi).T
            dval = Ce @ bernstein_derivative(p, xi).T
        else:
            val = np.einsum("ej,eqj->eq", Ce, bernstein(p, xi))
            dval = np.einsum("ej,eqj->eq", Ce, bernstein_derivative(p, xi))
        grad = self._physical_gradient(mapping, X, tind, dval[None])
        return (DiscreteField(value=val, grad=grad),)


class ElementQuadBSpline(_BSplineElement):
    """Tensor-product B-spline element of degree ``p`` (1, 2 or 3) on quads.

    ``breakpoints`` is a pair (x breakpoints, y breakpoints) of the grid whose
    cells are numbered e = e_x + n_x e_y (default: one cell [0, 1]^2). Local
    function l = a + (p + 1) b is N^x_a N^y_b. p = 1 is the bilinear Lagrange
    space of ``ElementQuad1``.
    """

    refdom = RefQuad

    def __init__(self, p, breakpoints=((0.0, 1.0), (0.0, 1.0))):
        if len(breakpoints) != 2:
            raise ValueError(
                f"ElementQuadBSpline needs a pair of breakpoint arrays, got {len(breakpoints)}"
            )
        super().__init__(p, breakpoints)
        self.maxdeg = 2 * self.degree  # total degree of Q_p, scikit-fem's convention

    def gbasis(self, mapping, X, i, tind=None):
        p = self.degree
        if not 0 <= i < (p + 1) ** 2:
            self._index_error()
        a, b = i % (p + 1), i // (p + 1)
        cells = self._cells(mapping, tind)
        nx = self.cells_per_axis[0]
        ex, ey = cells % nx, cells // nx
        vals, dvals = [], []
        for C, e, local, xi in ((self.extraction[0], ex, a, X[0]),
                                (self.extraction[1], ey, b, X[1])):
            Ce = C[e][:, local, :]
            if xi.ndim == 1:
                vals.append(Ce @ bernstein(p, xi).T)
                dvals.append(Ce @ bernstein_derivative(p, xi).T)
            else:
                vals.append(np.einsum("ej,eqj->eq", Ce, bernstein(p, xi)))
                dvals.append(np.einsum("ej,eqj->eq", Ce, bernstein_derivative(p, xi)))
        value = vals[0] * vals[1]
        dref = np.stack((dvals[0] * vals[1], vals[0] * dvals[1]))
        grad = self._physical_gradient(mapping, X, tind, dref)
        return (DiscreteField(value=value, grad=grad),)
