"""``SplineGrid``: a tensor-product B-spline space on a scikit-fem mesh.

The grid owns the mesh (MeshLine1, MeshQuad1 or MeshHex1 with cells numbered
e = e_x + n_x e_y + n_x n_y e_z and vertices in scikit-fem's reference order),
the element (Bezier extraction, see :mod:`skfem_mpm.spline.element`), the
spline dof numbering (dof a + n_bx b + n_bx n_by c for the function
N^x_a N^y_b N^z_c, n_bx = n_x + p), and fast point location on its
breakpoints. Vector fields use the interleaved numbering
dim * s + c of scikit-fem's ``ElementVector``.
"""
import numbers

import numpy as np
from skfem import CellBasis, FacetBasis, MeshHex1, MeshLine1, MeshQuad1
from skfem.element import ElementVector

from ..kernels import resolve_backend
from ..validation import as_points, check_positive_int
from .bernstein import bernstein, bernstein_derivative
from .dofs import SplineDofs
from .element import ElementHexBSpline, ElementLineBSpline, ElementQuadBSpline
from .knots import check_breakpoints, check_degree, open_knot_vector
from .mapping import MappingRectangular

__all__ = ["SplineGrid"]

# side name -> (axis, end): end 0 is the lower bound, 1 the upper
SIDE_AXES = {
    "left": (0, 0), "right": (0, 1), "bottom": (1, 0), "top": (1, 1),
    "xmin": (0, 0), "xmax": (0, 1), "ymin": (1, 0), "ymax": (1, 1),
    "zmin": (2, 0), "zmax": (2, 1),
}
SIDES = {dim: tuple(name for name, (axis, _) in SIDE_AXES.items() if axis < dim)
         for dim in (1, 2, 3)}
MESHES = {2: MeshQuad1, 3: MeshHex1}
ELEMENTS = {1: ElementLineBSpline, 2: ElementQuadBSpline, 3: ElementHexBSpline}


def side_axis(side, dim):
    """(axis, end) of a side name in ``dim`` dimensions: 'left'/'xmin' is
    (0, 0), 'right'/'xmax' (0, 1), 'bottom'/'ymin' (1, 0), 'top'/'ymax'
    (1, 1), 'zmin' (2, 0), 'zmax' (2, 1); raises ValueError for a name that
    is not a side of a ``dim``-dimensional grid."""
    valid = SIDES[dim]
    if not isinstance(side, str) or side not in valid:
        raise ValueError(
            f"side must be one of {', '.join(map(repr, valid))} for a "
            f"{dim}D grid, got {side!r}"
        )
    return SIDE_AXES[side]


def _is_per_axis(breakpoints):
    if isinstance(breakpoints, np.ndarray):
        return breakpoints.dtype == object
    try:
        return len(breakpoints) > 0 and np.ndim(breakpoints[0]) == 1
    except TypeError:
        return False



def _real(name, value):
    """A real number (not a bool or a string), as a float."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (numbers.Real, np.floating,
                                                                       np.integer)):
        raise ValueError(f"{name} must be a real number, got {value!r}")
    return float(value)


def _cell_indices(cells, ncells):
    """Flat cell indices: integers in [0, ncells)."""
    a = np.asarray(cells)
    if a.ndim != 1 or (a.size and a.dtype.kind not in "iu"):
        raise ValueError(f"cells must be a 1-D array of integer cell indices, got "
                         f"{a.dtype} of shape {a.shape}")
    if a.size and (a.min() < 0 or a.max() >= ncells):
        bad = a[(a < 0) | (a >= ncells)][0]
        raise ValueError(f"cells must lie in [0, {ncells}) (the grid's cells), got {bad}")
    return a.astype(np.int64)

class SplineGrid:
    """B-spline space of degree ``degree`` on a line, a rectangle or a box.

    Parameters
    ----------
    breakpoints
        The cell boundaries: one strictly increasing array for a line, or a
        tuple of arrays (x, y) for a rectangle, (x, y, z) for a box.
        Non-uniform spacing is allowed.
    degree
        1, 2 or 3. The knot vectors are open (clamped), so the space
        interpolates at the boundary, and the functions are C^(degree-1).

    Use :meth:`line`, :meth:`rectangle` and :meth:`box` for uniform grids.
    """

    def __init__(self, breakpoints, degree):
        self.degree = check_degree(degree)
        if _is_per_axis(breakpoints):
            axes = tuple(breakpoints)
        else:
            axes = (breakpoints,)
        if len(axes) not in (1, 2, 3):
            raise ValueError(f"a SplineGrid has 1, 2 or 3 axes, got {len(axes)}")
        self.breakpoints = tuple(
            check_breakpoints(b, name=f"breakpoints[{i}]" if len(axes) > 1 else "breakpoints")
            for i, b in enumerate(axes)
        )
        p = self.degree
        self.dim = len(self.breakpoints)
        self.cells_per_axis = tuple(b.size - 1 for b in self.breakpoints)
        self.basis_per_axis = tuple(n + p for n in self.cells_per_axis)
        self.ncells = int(np.prod(self.cells_per_axis))
        self.ndofs = int(np.prod(self.basis_per_axis))
        self.knot_vectors = tuple(open_knot_vector(b, p) for b in self.breakpoints)
        self.cell_sizes = tuple(np.diff(b) for b in self.breakpoints)
        self.h = tuple(float(s.min()) for s in self.cell_sizes)
        self.bounds = tuple((float(b[0]), float(b[-1])) for b in self.breakpoints)
        # uniform up to the rounding of the breakpoints themselves (linspace on
        # 250k cells varies the widths by 2.5e-11 relative)
        self._uniform = tuple(
            bool(np.allclose(s, s.mean(), rtol=1e-9, atol=0.0)) for s in self.cell_sizes
        )
        self._build_mesh()
        self.element = ELEMENTS[self.dim](p, self.breakpoints if self.dim > 1
                                          else self.breakpoints[0])
        self.extraction = self.element.extraction
        self.dofs = SplineDofs(self.mesh, self.element, self._element_dofs(), self.ndofs)
        self.vector_element = ElementVector(self.element, self.dim)
        self.vector_dofs = SplineDofs(
            self.mesh, self.vector_element, self._vector_element_dofs(), self.dim * self.ndofs
        )

    # ------------------------------------------------------------------ build
    @classmethod
    def line(cls, a, b, cells, degree):
        """Uniform grid of ``cells`` cells on [a, b]."""
        cells = check_positive_int("cells", cells)
        a, b = _real("a", a), _real("b", b)
        if not (np.isfinite(a) and np.isfinite(b) and b > a):
            raise ValueError(f"the interval must satisfy a < b (finite), got a={a}, b={b}")
        return cls(np.linspace(a, b, cells + 1), degree)

    @classmethod
    def rectangle(cls, xlim, ylim, cells, degree):
        """Uniform grid on [x0, x1] x [y0, y1] with ``cells = (nx, ny)``
        (an int gives the same count on both axes)."""
        return cls._uniform_box((xlim, ylim), cells, degree)

    @classmethod
    def box(cls, xlim, ylim, zlim, cells, degree):
        """Uniform grid on [x0, x1] x [y0, y1] x [z0, z1] with
        ``cells = (nx, ny, nz)`` (an int gives the same count on every axis)."""
        return cls._uniform_box((xlim, ylim, zlim), cells, degree)

    @classmethod
    def _uniform_box(cls, lims, cells, degree):
        dim = len(lims)
        if isinstance(cells, (int, np.integer)) and not isinstance(cells, bool):
            cells = (cells,) * dim
        try:
            count = len(cells)
        except TypeError:
            count = None
        if count != dim:
            names = ("nx", "ny", "nz")[:dim]
            raise ValueError(
                f"cells must be an int or {dim} ints ({', '.join(names)}), got {cells!r}")
        axes = []
        for name, lim, n in zip(("xlim", "ylim", "zlim"), lims, cells):
            n = check_positive_int("cells", n)
            if isinstance(lim, (str, bytes)) or not hasattr(lim, "__len__") or len(lim) != 2:
                raise ValueError(f"{name} must be a pair (lo, hi) of numbers, got {lim!r}")
            lo, hi = _real(f"{name}[0]", lim[0]), _real(f"{name}[1]", lim[1])
            if not (np.isfinite(lo) and np.isfinite(hi) and hi > lo):
                raise ValueError(f"{name} must satisfy lo < hi (finite), got {tuple(lim)}")
            axes.append(np.linspace(lo, hi, n + 1))
        return cls(tuple(axes), degree)

    def _build_mesh(self):
        if self.dim == 1:
            u = self.breakpoints[0]
            n = u.size - 1
            t = np.vstack((np.arange(n), np.arange(1, n + 1)))
            self.mesh = MeshLine1(u[None, :].copy(), t)
            self.mapping = self.mesh._mapping()
            return
        # vertex (i_x, i_y[, i_z]) is i_x + (n_x + 1) i_y + (n_x + 1)(n_y + 1) i_z;
        # vertex k of a cell sits at its lower corner + corner[:, k]: quads
        # counter-clockwise (RefQuad.p), hexahedra as MeshHex1's own unit cube
        # lists them (its doflocs, 1 - RefHex.p), which scikit-fem's meshio
        # export turns into VTK's hexahedron order
        mesh_type = MESHES[self.dim]
        ref = mesh_type.elem.refdom.p
        corner = ref if self.dim == 2 else 1.0 - ref
        counts = [n + 1 for n in self.cells_per_axis]
        stride = np.cumprod([1] + counts[:-1])
        coords = np.meshgrid(*self.breakpoints, indexing="ij")
        points = np.vstack([c.ravel(order="F") for c in coords])
        first = np.meshgrid(*[np.arange(n) for n in self.cells_per_axis], indexing="ij")
        v0 = sum(stride[d] * first[d].ravel(order="F") for d in range(self.dim))
        offsets = np.rint(stride @ corner).astype(np.int64)  # (nverts,)
        t = v0[None, :] + offsets[:, None]
        self.mesh = mesh_type(points, t)
        self.mapping = MappingRectangular(self.mesh)

    def _element_dofs(self):
        p = self.degree
        if self.dim == 1:
            cells = np.arange(self.ncells)
            return cells[None, :] + np.arange(p + 1)[:, None]
        cells = np.arange(self.ncells)
        local = np.arange((p + 1) ** self.dim)
        out = np.zeros((local.size, self.ncells), dtype=np.int64)
        cell_stride, dof_stride = 1, 1
        for axis in range(self.dim):
            e = (cells // cell_stride) % self.cells_per_axis[axis]
            a = (local // (p + 1) ** axis) % (p + 1)
            out += dof_stride * (e[None, :] + a[:, None])
            cell_stride *= self.cells_per_axis[axis]
            dof_stride *= self.basis_per_axis[axis]
        return out

    def _vector_element_dofs(self):
        scalar = self._element_dofs()
        d = self.dim
        out = np.empty((scalar.shape[0] * d, scalar.shape[1]), dtype=np.int64)
        for c in range(d):
            out[c::d] = d * scalar + c
        return out

    # ----------------------------------------------------------- scikit-fem
    def basis(self, intorder=None, vector=False):
        """A scikit-fem ``CellBasis`` with Gauss quadrature on this space.

        ``intorder`` is the polynomial degree integrated exactly (per axis in
        2D); the default 2p integrates the mass matrix exactly. ``vector=True``
        gives the vector-valued space (``ElementVector``) for elasticity.
        """
        if intorder is None:
            intorder = 2 * self.degree
        elem, dofs = self._element_and_dofs(vector)
        basis = CellBasis(self.mesh, elem, mapping=self.mapping, intorder=intorder,
                          dofs=dofs, disable_doflocs=True)
        basis.doflocs = self.doflocs(vector)
        return basis

    def facet_basis(self, side, intorder=None, vector=False):
        """A scikit-fem ``FacetBasis`` on one side of the grid (for tractions
        and boundary integrals with Gauss quadrature)."""
        facets = self._side_facets(side)
        if intorder is None:
            intorder = 2 * self.degree
        elem, dofs = self._element_and_dofs(vector)
        return FacetBasis(self.mesh, elem, mapping=self.mapping, intorder=intorder,
                          facets=facets, dofs=dofs, disable_doflocs=True)

    def _element_and_dofs(self, vector):
        if vector:
            return self.vector_element, self.vector_dofs
        return self.element, self.dofs

    def doflocs(self, vector=False):
        """Greville abscissae of the basis functions, shape (dim, ndofs)
        (repeated per component, interleaved, when ``vector``)."""
        p = self.degree
        axes = []
        for tau in self.knot_vectors:
            nb = tau.size - p - 1
            idx = np.arange(nb)[:, None] + np.arange(1, p + 1)[None, :]
            axes.append(tau[idx].mean(axis=1))
        grids = np.meshgrid(*axes, indexing="ij")
        locs = np.vstack([g.ravel(order="F") for g in grids])  # x fastest
        if vector:
            locs = np.repeat(locs, self.dim, axis=1)
        return locs

    def _check_side(self, side):
        side_axis(side, self.dim)
        return side

    def _side_facets(self, side):
        axis, end = side_axis(side, self.dim)
        value = self.bounds[axis][end]
        mid = self.mesh.p[:, self.mesh.facets].mean(axis=1)
        boundary = self.mesh.boundary_facets()
        on_side = np.isclose(mid[axis, boundary], value, rtol=0.0,
                             atol=1e-12 * max(1.0, abs(value)))
        return boundary[on_side]

    def boundary_dofs(self, side, component=None):
        """Dofs of the basis functions that are non-zero on a side.

        ``side`` is ``'xmin'``, ``'xmax'``, ``'ymin'``, ``'ymax'``,
        ``'zmin'``, ``'zmax'`` (as far as the grid has axes), or their
        aliases ``'left'``, ``'right'`` (x), ``'bottom'``, ``'top'`` (y). With ``component=None`` the indices are
        those of the scalar space; with ``component=c`` (0 <= c < dim) they
        are the dofs of component c in the vector space (dim * s + c).
        With open knot vectors exactly one layer of functions touches a side,
        and setting those dofs fixes the field on that side.
        """
        axis, end = side_axis(side, self.dim)
        index = np.arange(self.ndofs).reshape(self.basis_per_axis[::-1])  # [.., b, a]
        layer = np.take(index, 0 if end == 0 else -1, axis=self.dim - 1 - axis)
        scalar = layer.ravel()
        if component is None:
            return scalar
        if isinstance(component, bool) or not isinstance(component, (int, np.integer)) \
                or not 0 <= component < self.dim:
            raise ValueError(
                f"component must be None or an integer in [0, {self.dim - 1}], got {component!r}"
            )
        return self.dim * scalar + int(component)

    # ------------------------------------------------------- point location
    def _locate_axis(self, axis, x):
        u = self.breakpoints[axis]
        n = u.size - 1
        if self._uniform[axis]:
            t = (x - u[0]) * (n / (u[-1] - u[0]))
            e = t.astype(np.int64)  # t >= 0 inside the grid: truncation is floor
            np.clip(e, 0, n - 1, out=e)
            return e, t - e
        else:
            e = np.searchsorted(u, x, side="right") - 1
            np.clip(e, 0, n - 1, out=e)
        xi = (x - u[e]) / (u[e + 1] - u[e])
        return e, xi

    def _check_inside(self, x):
        outside = np.zeros(x.shape[0], dtype=bool)
        for axis, (lo, hi) in enumerate(self.bounds):
            outside |= (x[:, axis] < lo) | (x[:, axis] > hi)
        if outside.any():
            first = int(np.flatnonzero(outside)[0])
            box = " x ".join(f"[{lo:g}, {hi:g}]" for lo, hi in self.bounds)
            raise ValueError(
                f"{int(outside.sum())} point(s) lie outside the grid {box}; "
                f"the first is index {first} at {x[first].tolist()}"
            )

    def locate(self, x):
        """Cells and reference coordinates of points.

        ``x`` has shape (n, dim) (or (n,) in 1D). Returns the scikit-fem
        element index of every point, shape (n,), and its reference
        coordinates in [0, 1]^dim, shape (n, dim). Points on a cell boundary
        belong to the cell on their right (the last cell at the upper end).
        Raises ``ValueError`` for points outside the grid.
        """
        x = as_points("x", x, self.dim)
        self._check_inside(x)
        return self._locate_unchecked(x)

    def _locate_unchecked(self, x):
        cells = np.zeros(x.shape[0], dtype=np.int64)
        xi = np.empty(x.shape)
        stride = 1
        for axis in range(self.dim):
            e, xi[:, axis] = self._locate_axis(axis, x[:, axis])
            cells += stride * e
            stride *= self.cells_per_axis[axis]
        return cells, xi

    def axis_functions(self, axis, x_axis, backend=None):
        """The p + 1 non-zero 1D B-splines of one axis at coordinates ``x_axis``.

        Returns ``(first, values, derivatives)``: the index of the first
        non-zero function (the cell index on that axis), its values (n, p+1)
        and derivatives d/dx (n, p+1). Points must lie inside the grid.
        ``backend`` is ``"numba"`` (compiled) or ``"numpy"`` (the reference).
        """
        x_axis = np.asarray(x_axis, dtype=np.float64)
        if resolve_backend(backend) == "numba":
            from ..kernels.weights import axis_functions
            return axis_functions(x_axis, self.breakpoints[axis], self._uniform[axis],
                                  self.extraction[axis], self.degree)
        e, xi = self._locate_axis(axis, x_axis)
        return (e,) + self._axis_values(axis, e, xi)

    def _axis_values(self, axis, e, xi):
        """Values and d/dx of the p + 1 functions of cells ``e`` at ``xi``."""
        p = self.degree
        B = bernstein(p, xi)
        dB = bernstein_derivative(p, xi)
        C = self.extraction[axis]
        if self._uniform[axis] and C.shape[0] > 2 * p + 1:
            # uniform interior cells share one extraction matrix: apply it to
            # all points, then redo the p boundary cells at each end
            interior = C[p]
            values = B @ interior.T
            derivatives = dB @ interior.T
            edge = (e < p) | (e >= C.shape[0] - p)
            if edge.any():
                Ce = C[e[edge]]
                values[edge] = np.einsum("nij,nj->ni", Ce, B[edge])
                derivatives[edge] = np.einsum("nij,nj->ni", Ce, dB[edge])
            derivatives *= 1.0 / self.cell_sizes[axis][0]
            return values, derivatives
        Ce = C[e]
        values = np.einsum("nij,nj->ni", Ce, B)
        inv_h = 1.0 / self.cell_sizes[axis][e]
        return values, np.einsum("nij,nj->ni", Ce, dB) * inv_h[:, None]

    def inside(self, x):
        """Boolean mask of the points (n, dim) that lie in the grid."""
        ok = np.ones(x.shape[0], dtype=bool)
        for axis, (lo, hi) in enumerate(self.bounds):
            ok &= (x[:, axis] >= lo) & (x[:, axis] <= hi)
        return ok

    def locate_axes(self, x):
        """Per axis (cell index, reference coordinate) of points inside the
        grid (no checks): the first half of :meth:`shape_functions`."""
        return tuple(self._locate_axis(axis, x[:, axis]) for axis in range(self.dim))

    def shape_functions(self, x, check=True, backend=None, located=None):
        """Dofs, values and gradients of the non-zero basis functions at points.

        Returns ``dofs`` (n, k) int, ``values`` (n, k) and ``gradients``
        (n, k, dim), with k = (p + 1)^dim and local order a + (p + 1) b.
        ``located`` (from :meth:`locate_axes`) skips the location step.
        """
        if check:
            x = as_points("x", x, self.dim)
            self._check_inside(x)
        if located is None:
            axes = [self.axis_functions(a, x[:, a], backend) for a in range(self.dim)]
        else:
            axes = [(e,) + self._axis_values(a, e, xi) for a, (e, xi) in enumerate(located)]
        return self._tensor_product(axes, x.shape[0])

    def _tensor_product(self, axes, n):
        """Products of the per-axis (first, values, derivatives) with local
        order a + (p + 1) b + (p + 1)^2 c (x fastest)."""
        p = self.degree
        dim = self.dim
        k = (p + 1) ** dim
        local = np.arange(p + 1)
        dofs = np.zeros((n,) + (1,) * dim, dtype=np.int64)
        values, derivatives = [], []
        stride = 1
        for axis, (e, v, d) in enumerate(axes):
            shape = [n] + [1] * dim
            shape[dim - axis] = p + 1  # axis 0 is the last (fastest) index
            dofs = dofs + stride * (e[:, None] + local).reshape(shape)
            values.append(v.reshape(shape))
            derivatives.append(d.reshape(shape))
            stride *= self.basis_per_axis[axis]
        full = (n,) + (p + 1,) * dim

        def product(factors):
            out = factors[0]
            for f in factors[1:]:
                out = out * f
            return np.broadcast_to(out, full).reshape(n, k)

        grads = np.stack([
            product([derivatives[a] if a == d else values[a] for a in range(dim)])
            for d in range(dim)], axis=-1)
        return np.broadcast_to(dofs, full).reshape(n, k), product(values), grads

    def evaluate(self, coeffs, x, gradient=False):
        """Values (and gradients) of a spline field at points ``x``.

        ``coeffs`` is (ndofs,) for a scalar field, (ndofs, k) for k fields,
        or (dim * ndofs,) in the interleaved numbering of the vector basis
        (read as (ndofs, dim)). Returns values of shape (n,) or (n, k), and
        with ``gradient=True`` also gradients (n, dim) or (n, k, dim).
        """
        c = np.asarray(coeffs, dtype=np.float64)
        if c.ndim == 1 and c.size == self.dim * self.ndofs and self.dim > 1:
            c = c.reshape(self.ndofs, self.dim)
        if c.shape[0] != self.ndofs or c.ndim > 2:
            raise ValueError(
                f"coeffs must have shape ({self.ndofs},), ({self.ndofs}, k) or "
                f"({self.dim * self.ndofs},), got {c.shape}"
            )
        dofs, values, grads = self.shape_functions(x)
        local = c[dofs]  # (n, k) or (n, k, m)
        if c.ndim == 1:
            out = (values * local).sum(axis=1)
            if gradient:
                return out, np.einsum("nkd,nk->nd", grads, local)
            return out
        out = np.einsum("nk,nkm->nm", values, local)
        if gradient:
            return out, np.einsum("nkd,nkm->nmd", grads, local)
        return out

    def gauss_rule(self, points_per_axis, cells=None):
        """Gauss points (n, dim), weights (n,) and cell index (n,) of the
        tensor Gauss rule with ``points_per_axis`` points per axis on the
        given cells (default: all), cell by cell."""
        k = check_positive_int("points_per_axis", points_per_axis)
        if k > 64:
            raise ValueError(f"points_per_axis must be at most 64, got {k}")
        ref, wref = np.polynomial.legendre.leggauss(k)
        ref, wref = 0.5 * (ref + 1.0), 0.5 * wref
        cells = np.arange(self.ncells) if cells is None else _cell_indices(cells, self.ncells)
        dim = self.dim
        e, stride = [], 1
        for axis in range(dim):
            e.append((cells // stride) % self.cells_per_axis[axis])
            stride *= self.cells_per_axis[axis]
        # local point a + k b + k^2 c (x fastest), as the cells' local functions
        shape = (cells.size,) + (k,) * dim
        x = np.empty(shape + (dim,))
        w = np.ones(shape)
        for axis in range(dim):
            lo = self.breakpoints[axis][e[axis]]
            size = self.cell_sizes[axis][e[axis]]
            view = [cells.size] + [1] * dim
            view[dim - axis] = k
            x[..., axis] = (lo[:, None] + size[:, None] * ref[None, :]).reshape(view)
            w = w * (size[:, None] * wref[None, :]).reshape(view)
        return x.reshape(-1, dim), w.ravel(), np.repeat(cells, k ** dim)

    def vertex_values(self, coeffs):
        """Field values at the mesh vertices, for ``mesh.save(point_data=...)``."""
        return self.evaluate(coeffs, self.mesh.p.T)

    def interpolate(self, f):
        """Spline coefficients of the L2 projection of a callable ``f(x)``
        (x of shape (n, dim)) onto the space, computed with Gauss quadrature;
        exact for functions in the space."""
        basis = self.basis()
        from skfem import BilinearForm, LinearForm, asm, solve

        @BilinearForm
        def mass(u, v, _):
            return u * v

        @LinearForm
        def load(v, w):
            return w["f"] * v

        x = np.asarray(basis.global_coordinates())  # (dim, nel, nqp)
        values = np.asarray(f(x.reshape(self.dim, -1).T), dtype=np.float64).reshape(x.shape[1:])
        return solve(asm(mass, basis), asm(load, basis, f=values))

    def __repr__(self):
        cells = " x ".join(str(n) for n in self.cells_per_axis)
        box = " x ".join(f"[{lo:g}, {hi:g}]" for lo, hi in self.bounds)
        return (f"SplineGrid(degree={self.degree}, cells={cells}, domain={box}, "
                f"dofs={self.ndofs})")
