"""``LagrangeGrid``: a plain scikit-fem mesh and Lagrange element as an MPM grid.

The general (non-spline) path: P1 on MeshLine1/MeshTri1/MeshTet1, Q1 on
MeshQuad1/MeshHex1, so triangulated or tetrahedral domains from Gmsh can
carry particles. It offers the same
methods the solver uses on a :class:`~skfem_mpm.SplineGrid` (``locate``,
``shape_functions``, ``boundary_dofs``, ``basis``).

Point location avoids ``mesh.element_finder`` (which builds dense
point-by-element arrays): a k-d tree of cell centroids proposes the k nearest
cells of each point, and a vectorised barycentric test picks the one that
contains it (points that fail are retried with more candidates); quads and
hexahedra are searched through their split into triangles or tetrahedra
(scikit-fem's ``to_meshtri`` / ``to_meshtet``, simplex j inside cell
j mod ncells).
"""
import numpy as np
from scipy.spatial import cKDTree
from skfem import CellBasis, FacetBasis, MeshHex1, MeshLine1, MeshQuad1, MeshTet1, MeshTri1
from skfem.assembly import Dofs
from skfem.element import ElementVector
from skfem.mapping import MappingAffine, MappingIsoparametric

from .validation import as_points

__all__ = ["LagrangeGrid"]

_CANDIDATES = 8
_MESHES = (MeshLine1, MeshTri1, MeshQuad1, MeshTet1, MeshHex1)
# the side names of every dimension as aliases of scikit-fem's default tags
_SIDE_ALIASES = {"xmin": "left", "xmax": "right", "ymin": "bottom", "ymax": "top",
                 "zmin": "front", "zmax": "back"}


class LagrangeGrid:
    """An MPM grid on a scikit-fem mesh with a Lagrange element.

    ``element`` defaults to the mesh's own (P1 on lines, triangles and
    tetrahedra, Q1 on quadrilaterals and hexahedra). Boundary sides are the
    mesh's named boundaries, or scikit-fem's defaults ``left``/``right``/
    ``bottom``/``top``/``front``/``back`` of the bounding box when the mesh
    has none; ``xmin`` ... ``zmax`` name the defaults in every dimension.
    """

    def __init__(self, mesh, element=None):
        if not isinstance(mesh, _MESHES):
            raise ValueError(
                f"LagrangeGrid supports {', '.join(m.__name__ for m in _MESHES)}, "
                f"got {type(mesh).__name__}"
            )
        if not mesh.boundaries:
            mesh = mesh.with_defaults()
        self.mesh = mesh
        self.element = mesh.elem() if element is None else element
        if self.element.maxdeg > max(2, mesh.dim()) or self.element.refdom is not mesh.refdom:
            raise ValueError(
                f"LagrangeGrid needs a first-order Lagrange element on {type(mesh).__name__}, "
                f"got {type(self.element).__name__}"
            )
        self.dim = mesh.dim()
        self.degree = 1
        self.dofs = Dofs(mesh, self.element)
        self.ndofs = self.dofs.N
        self.vector_element = ElementVector(self.element, self.dim)
        self.vector_dofs = Dofs(mesh, self.vector_element)
        self.ncells = mesh.nelements
        lo, hi = mesh.p.min(axis=1), mesh.p.max(axis=1)
        self.bounds = tuple((float(a), float(b)) for a, b in zip(lo, hi))
        edges = mesh.p[:, mesh.facets[0]] - mesh.p[:, mesh.facets[-1]] if self.dim > 1 else \
            mesh.p[:, mesh.t[1]] - mesh.p[:, mesh.t[0]]
        h = float(np.sqrt((edges ** 2).sum(axis=0)).min())
        self.h = (h,) * self.dim
        self._affine = isinstance(mesh, (MeshLine1, MeshTri1, MeshTet1))
        self.mapping = self.new_mapping()
        self._triangles = (mesh.to_meshtri() if isinstance(mesh, MeshQuad1)
                           else mesh.to_meshtet() if isinstance(mesh, MeshHex1) else mesh)
        tri = self._triangles
        self._tri_mapping = MappingAffine(tri)
        self._tree = cKDTree(tri.p[:, tri.t].mean(axis=1).T)

    def new_mapping(self):
        """A fresh mapping object (isoparametric mappings cache every point
        set they see; a fresh one per particle basis keeps memory bounded)."""
        if self._affine:
            return MappingAffine(self.mesh)
        return MappingIsoparametric(self.mesh, self.mesh.elem(), self.mesh.bndelem)

    # ------------------------------------------------------------- location
    def _check_inside(self, x, cells):
        bad = cells < 0
        if bad.any():
            first = int(np.flatnonzero(bad)[0])
            raise ValueError(
                f"{int(bad.sum())} point(s) lie outside the mesh; the first is index "
                f"{first} at {x[first].tolist()}"
            )

    def _find_triangles(self, x, k):
        tri = self._triangles
        if self.dim == 1:
            u = tri.p[0]
            order = np.argsort(u)
            cells = np.searchsorted(u[order], x[:, 0], side="right") - 1
            cells = np.where(x[:, 0] == u[order][-1], len(order) - 2, cells)
            ok = (cells >= 0) & (cells < len(order) - 1)
            out = np.full(len(x), -1)
            # cell whose left vertex is order[cells]
            left_to_cell = np.full(tri.p.shape[1], -1)
            left = np.where(tri.p[0, tri.t[0]] < tri.p[0, tri.t[1]], tri.t[0], tri.t[1])
            left_to_cell[left] = np.arange(tri.t.shape[1])
            out[ok] = left_to_cell[order[cells[ok]]]
            return out
        k = min(k, tri.t.shape[1])
        _, cand = self._tree.query(x, k=k)
        cand = cand.reshape(len(x), k)
        invA, b = self._tri_mapping.invA, self._tri_mapping.b
        rel = x[:, None, :] - b.T[cand]  # (n, k, dim)
        lam = np.einsum("nkij,nkj->nki", np.moveaxis(invA, 2, 0)[cand], rel)
        tol = 1e-12
        inside = np.all(lam >= -tol, axis=-1) & (lam.sum(axis=-1) <= 1 + tol)
        found = inside.any(axis=1)
        out = np.where(found, cand[np.arange(len(x)), inside.argmax(axis=1)], -1)
        missing = np.flatnonzero(~found)
        if missing.size and k < tri.t.shape[1]:
            out[missing] = self._find_triangles(x[missing], 8 * k)
        return out

    def locate(self, x):
        """Cell indices (n,) and reference coordinates (n, dim) of points."""
        x = as_points("x", x, self.dim)
        cells = self._find_triangles(x, _CANDIDATES)
        self._check_inside(x, cells)
        if isinstance(self.mesh, (MeshQuad1, MeshHex1)):
            cells = cells % self.mesh.nelements
        ref = self.new_mapping().invF(x.T[:, :, None], tind=cells)[:, :, 0].T
        return cells, np.ascontiguousarray(ref)

    def inside(self, x):
        """Boolean mask of the points (n, dim) that lie in the mesh."""
        return self._find_triangles(np.asarray(x, dtype=np.float64), _CANDIDATES) >= 0

    def locate_axes(self, x):
        """Location data for :meth:`shape_functions` (cells, reference coordinates)."""
        return self.locate(x)

    def shape_functions(self, x, check=True, backend=None, located=None):
        """Dofs (n, k), values (n, k) and gradients (n, k, dim) at points."""
        cells, ref = self.locate(x) if located is None else located
        mapping = self.new_mapping()
        X = ref.T[:, :, None]
        nloc = self.dofs.element_dofs.shape[0]
        values = np.empty((len(cells), nloc))
        grads = np.empty((len(cells), nloc, self.dim))
        for i in range(nloc):
            field = self.element.gbasis(mapping, X, i, tind=cells)[0]
            values[:, i] = np.asarray(field)[:, 0]
            grads[:, i, :] = np.asarray(field.grad)[:, :, 0].T
        return self.dofs.element_dofs[:, cells].T, values, grads

    def evaluate(self, coeffs, x, gradient=False):
        """Values (and gradients) of a finite element field at points."""
        c = np.asarray(coeffs, dtype=np.float64)
        dofs, values, grads = self.shape_functions(x)
        local = c[dofs]
        if c.ndim == 1:
            out = (values * local).sum(axis=1)
            return (out, np.einsum("nkd,nk->nd", grads, local)) if gradient else out
        out = np.einsum("nk,nkm->nm", values, local)
        return (out, np.einsum("nkd,nkm->nmd", grads, local)) if gradient else out

    def gauss_rule(self, points_per_axis, cells=None):
        """Quadrature points (n, dim), weights (n,) and cell index (n,) of
        scikit-fem's rule exact to degree 2 points_per_axis - 1."""
        basis = CellBasis(self.mesh, self.element, intorder=2 * int(points_per_axis) - 1,
                          elements=None if cells is None else np.asarray(cells))
        pts = np.asarray(basis.global_coordinates())
        x = pts.reshape(self.dim, -1).T
        w = np.asarray(basis.dx).ravel()
        cells = np.arange(self.ncells) if cells is None else np.asarray(cells)
        return x, w, np.repeat(cells, pts.shape[-1])

    # ----------------------------------------------------------- scikit-fem
    def basis(self, intorder=None, vector=False):
        """Gauss-quadrature ``CellBasis`` (scalar or vector)."""
        elem = self.vector_element if vector else self.element
        return CellBasis(self.mesh, elem, intorder=intorder)

    def facet_basis(self, side, intorder=None, vector=False):
        elem = self.vector_element if vector else self.element
        return FacetBasis(self.mesh, elem, facets=self._check_side(side), intorder=intorder)

    def _check_side(self, side):
        names = tuple(self.mesh.boundaries)
        if side not in names and _SIDE_ALIASES.get(side) in names:
            return _SIDE_ALIASES[side]
        if side not in names:
            raise ValueError(f"side must be one of {', '.join(map(repr, names))}, got {side!r}")
        return side

    def boundary_dofs(self, side, component=None):
        """Dofs on a named boundary; scalar numbering, or component c of the
        vector space (dim * s + c) when ``component`` is given."""
        facets = self.mesh.boundaries[self._check_side(side)]
        scalar = np.unique(self.mesh.facets[:, facets].ravel())
        if component is None:
            return scalar
        if isinstance(component, bool) or not isinstance(component, (int, np.integer)) \
                or not 0 <= component < self.dim:
            raise ValueError(
                f"component must be None or an integer in [0, {self.dim - 1}], got {component!r}"
            )
        return self.dim * scalar + int(component)

    def __repr__(self):
        return (f"LagrangeGrid({type(self.mesh).__name__}, {type(self.element).__name__}, "
                f"cells={self.ncells}, dofs={self.ndofs})")
