"""An affine mapping for axis-aligned rectangular and box-shaped cells.

    x = x_e + h_e * xi   (componentwise),   DF = diag(h_e),   det DF = prod(h_e)

scikit-fem maps quadrilaterals and hexahedra isoparametrically; that mapping
caches every set of evaluation points and cannot take per-element points
without element indices. On the cells of a tensor grid the map is affine and
diagonal, so this class evaluates it in closed form (2.4x faster in 2D, no
cache).

A facet of such a cell is an axis-aligned segment (2D) or rectangle (3D):
it is parametrised over the reference facet [0, 1]^(dim - 1) by its varying
axes in increasing order, x = lo_f + (hi_f - lo_f) * (s placed on those
axes), so det DG = its length or area, and its outward normal is +-e_k for
its constant axis k.
"""
import numpy as np
from skfem.mapping import Mapping

__all__ = ["MappingRectangular"]


class MappingRectangular(Mapping):
    """Mapping of scikit-fem's reference cell [0, 1]^dim onto axis-aligned
    cells (dim = 2 or 3).

    Every cell of ``mesh`` (a MeshQuad1 or MeshHex1) must be an axis-aligned
    rectangle or box whose vertices are its 2^dim corners, in any order: the
    map sends the reference origin to the cell's lower corner whatever the
    vertex order (scikit-fem's own hexahedral meshes list the corners
    mirrored against ``RefHex.p``, which its isoparametric map follows with
    det DF < 0; this map keeps det DF > 0).
    """

    def __init__(self, mesh):
        self.mesh = mesh
        p, t = mesh.p, mesh.t
        corners = p[:, t]  # (dim, nverts, cells)
        self.dim = p.shape[0]
        self.lower = corners.min(axis=1)
        self.size = corners.max(axis=1) - self.lower
        ok = np.all(self.size > 0)
        if ok:
            unit = (corners - self.lower[:, None, :]) / self.size[:, None, :]
            code = np.rint(unit)
            ok = (np.allclose(unit, code, rtol=0.0, atol=1e-12) and t.shape[0] == 2 ** self.dim
                  and np.all(np.sort((code * (2 ** np.arange(self.dim))[:, None, None])
                                     .sum(axis=0), axis=0)
                             == np.arange(2 ** self.dim)[:, None]))
        if not ok:
            raise ValueError(
                "MappingRectangular needs axis-aligned rectangles or boxes whose vertices "
                "are their 2^dim corners"
            )

    def _cell_arrays(self, tind):
        if tind is None:
            return self.lower, self.size
        return self.lower[:, tind], self.size[:, tind]

    def F(self, X, tind=None):
        lower, size = self._cell_arrays(tind)
        if X.ndim == 2:
            return lower[:, :, None] + size[:, :, None] * X[:, None, :]
        return lower[:, :, None] + size[:, :, None] * X

    def invF(self, x, tind=None):
        lower, size = self._cell_arrays(tind)
        return (x - lower[:, :, None]) / size[:, :, None]

    def _nqp(self, X):
        return X.shape[-1]

    def _diagonal(self, diag, X):
        out = np.zeros((self.dim, self.dim, diag.shape[1], self._nqp(X)))
        for d in range(self.dim):
            out[d, d] = diag[d][:, None]
        return out

    def DF(self, X, tind=None):
        return self._diagonal(self._cell_arrays(tind)[1], X)

    def invDF(self, X, tind=None):
        return self._diagonal(1.0 / self._cell_arrays(tind)[1], X)

    def detDF(self, X, tind=None):
        _, size = self._cell_arrays(tind)
        det = np.prod(size, axis=0)
        return np.broadcast_to(det[:, None], (det.size, self._nqp(X))).copy()

    def _facet_boxes(self, find):
        """Lower corner, extent (dim, nf) and varying axes (nf, dim - 1) of facets."""
        facets = self.mesh.facets if find is None else self.mesh.facets[:, find]
        corners = self.mesh.p[:, facets]  # (dim, nverts, nf)
        lo, hi = corners.min(axis=1), corners.max(axis=1)
        extent = hi - lo
        varying = np.argsort(extent == 0.0, axis=0, kind="stable")[:-1].T  # (nf, dim-1)
        return lo, extent, varying

    def G(self, X, find=None):
        lo, extent, varying = self._facet_boxes(find)
        nf = lo.shape[1]
        Xf = X if X.ndim == 3 else np.broadcast_to(X[:, None, :], (X.shape[0], nf, X.shape[-1]))
        out = np.repeat(lo[:, :, None], Xf.shape[-1], axis=2)
        facet = np.arange(nf)
        for j in range(self.dim - 1):
            axis = varying[:, j]
            out[axis, facet, :] += extent[axis, facet][:, None] * Xf[j]
        return out

    def detDG(self, X, find=None):
        _, extent, _ = self._facet_boxes(find)
        measure = np.prod(np.where(extent > 0.0, extent, 1.0), axis=0)
        return np.broadcast_to(measure[:, None], (measure.size, X.shape[-1])).copy()

    def normals(self, X, tind, find, t2f):
        lo, extent, _ = self._facet_boxes(find)
        constant = np.argmin(extent, axis=0)
        nf = lo.shape[1]
        centre = self.lower[:, tind] + 0.5 * self.size[:, tind]
        midpoint = lo + 0.5 * extent
        facet = np.arange(nf)
        sign = np.where(midpoint[constant, facet] > centre[constant, facet], 1.0, -1.0)
        normal = np.zeros((self.dim, nf))
        normal[constant, facet] = sign
        return np.repeat(normal[:, :, None], X.shape[-1], axis=2)
