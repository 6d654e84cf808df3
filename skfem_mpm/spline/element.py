"""B-spline elements for scikit-fem, built by Bezier extraction.

On every cell the element evaluates the Bernstein polynomials on scikit-fem's
reference cell [0, 1]^dim and multiplies them with that cell's extraction
matrix (Borden et al. 2011, IJNME 87:15-47, eq. 8):

    N_(e, i)(xi) = sum_j C_e[i, j] B_j(xi)              (1D)
    N_(e, a + (p+1) b)(xi, eta) = N^x_(e_x, a)(xi) N^y_(e_y, b)(eta)   (2D)
    N_(e, a + (p+1) b + (p+1)^2 c)(xi, eta, zeta)
        = N^x_(e_x, a)(xi) N^y_(e_y, b)(eta) N^z_(e_z, c)(zeta)         (3D)

with cells numbered e = e_x + n_x e_y + n_x n_y e_z (x fastest).

The local-to-global dof table (the spline connectivity) is not the one
scikit-fem derives from vertices; use the element through
:class:`skfem_mpm.SplineGrid`, which supplies the matching ``dofs`` and
mapping (``grid.basis()``, ``grid.element``, ``grid.dofs``).
"""
import numpy as np
from skfem.element import DiscreteField, Element
from skfem.refdom import RefHex, RefLine, RefQuad

from .bernstein import bernstein, bernstein_derivative
from .knots import check_breakpoints, check_degree, extraction_operators

__all__ = ["ElementHexBSpline", "ElementLineBSpline", "ElementQuadBSpline"]


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


class _TensorBSplineElement(_BSplineElement):
    """Tensor products of the axes' 1D B-splines (quadrilaterals, hexahedra).

    Local function l = sum_d a_d (p + 1)^d (x fastest) is prod_d N^d_(a_d);
    its reference gradient has the components
    dN^d_(a_d) prod_(k != d) N^k_(a_k).
    """

    def __init__(self, p, breakpoints):
        dim = self.refdom.dim()
        if len(breakpoints) != dim:
            raise ValueError(
                f"{type(self).__name__} needs {dim} breakpoint arrays (one per axis), "
                f"got {len(breakpoints)}"
            )
        super().__init__(p, breakpoints)
        self.maxdeg = dim * self.degree  # total degree of Q_p, scikit-fem's convention

    def gbasis(self, mapping, X, i, tind=None):
        p = self.degree
        dim = len(self.breakpoints)
        if not 0 <= i < (p + 1) ** dim:
            self._index_error()
        cells = self._cells(mapping, tind)
        vals, dvals = [], []
        stride = 1
        for axis in range(dim):
            n = self.cells_per_axis[axis]
            e = (cells // stride) % n
            local = (i // (p + 1) ** axis) % (p + 1)
            stride *= n
            Ce = self.extraction[axis][e][:, local, :]
            xi = X[axis]
            if xi.ndim == 1:
                vals.append(Ce @ bernstein(p, xi).T)
                dvals.append(Ce @ bernstein_derivative(p, xi).T)
            else:
                vals.append(np.einsum("ej,eqj->eq", Ce, bernstein(p, xi)))
                dvals.append(np.einsum("ej,eqj->eq", Ce, bernstein_derivative(p, xi)))
        value = np.prod(vals, axis=0)
        dref = np.stack([
            np.prod([dvals[k] if k == d else vals[k] for k in range(dim)], axis=0)
            for d in range(dim)])
        grad = self._physical_gradient(mapping, X, tind, dref)
        return (DiscreteField(value=value, grad=grad),)


class ElementQuadBSpline(_TensorBSplineElement):
    """Tensor-product B-spline element of degree ``p`` (1, 2 or 3) on quads.

    ``breakpoints`` is a pair (x breakpoints, y breakpoints) of the grid whose
    cells are numbered e = e_x + n_x e_y (default: one cell [0, 1]^2). Local
    function l = a + (p + 1) b is N^x_a N^y_b. p = 1 is the bilinear Lagrange
    space of ``ElementQuad1``.
    """

    refdom = RefQuad

    def __init__(self, p, breakpoints=((0.0, 1.0), (0.0, 1.0))):
        super().__init__(p, breakpoints)


class ElementHexBSpline(_TensorBSplineElement):
    """Tensor-product B-spline element of degree ``p`` (1, 2 or 3) on hexahedra.

    ``breakpoints`` is a triple (x, y, z breakpoints) of the grid whose cells
    are numbered e = e_x + n_x e_y + n_x n_y e_z (default: one cell [0, 1]^3)
    and mapped affinely from scikit-fem's reference cube [0, 1]^3. Local
    function l = a + (p + 1) b + (p + 1)^2 c is N^x_a N^y_b N^z_c. p = 1 is
    the trilinear Lagrange space of ``ElementHex1``.
    """

    refdom = RefHex

    def __init__(self, p, breakpoints=((0.0, 1.0), (0.0, 1.0), (0.0, 1.0))):
        super().__init__(p, breakpoints)
