"""Spline connectivity as a scikit-fem ``Dofs`` object.

scikit-fem numbers dofs by vertices, facets and cell interiors; a B-spline
function is shared by (p + 1)^dim neighbouring cells, which none of those
entities describe. ``SplineDofs`` carries the spline element-to-dof table
instead, so ``CellBasis``, ``asm``, ``condense`` and ``solve`` work unchanged.
"""
import numpy as np
from skfem.assembly.dofs import Dofs

__all__ = ["SplineDofs"]


class SplineDofs(Dofs):
    """Dofs given by an explicit element-to-dof table (local dofs x cells)."""

    def __init__(self, mesh, element, element_dofs, ndofs):
        self.topo = mesh
        self.element = element
        self.element_dofs = np.ascontiguousarray(element_dofs, dtype=np.int32)
        self.N = int(ndofs)
        self.nodal_dofs = np.empty((0, mesh.nvertices), dtype=np.int32)
        self.facet_dofs = np.empty((0, 0), dtype=np.int32)
        self.edge_dofs = np.empty((0, 0), dtype=np.int32)
        self.interior_dofs = self.element_dofs

    def _no_topological_dofs(self, *args, **kwargs):
        raise NotImplementedError(
            "spline dofs are not attached to mesh facets or vertices; use "
            "SplineGrid.boundary_dofs(side, component) to find boundary dofs"
        )

    get_vertex_dofs = _no_topological_dofs
    get_facet_dofs = _no_topological_dofs
    get_element_dofs = _no_topological_dofs
