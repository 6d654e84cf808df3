"""An affine mapping for axis-aligned rectangular cells.

    x = x_e + h_e * xi   (componentwise),   DF = diag(h_e),   det DF = prod(h_e)

scikit-fem maps quadrilaterals isoparametrically; that mapping caches every
set of evaluation points and cannot take per-element points without element
indices. On the rectangles of a tensor grid the map is affine and diagonal,
so this class evaluates it in closed form (2.4x faster, no cache).
"""
import numpy as np
from skfem.mapping import Mapping

__all__ = ["MappingRectangular"]


class MappingRectangular(Mapping):
    """Mapping of scikit-fem's reference square [0, 1]^2 onto rectangles.

    The cells of ``mesh`` (a MeshQuad1) must be axis-aligned rectangles whose
    vertices are listed counter-clockwise from the lower-left corner.
    """

    def __init__(self, mesh):
        self.mesh = mesh
        p, t = mesh.p, mesh.t
        self.lower = p[:, t[0]]
        self.size = p[:, t[2]] - self.lower
        corner1 = p[:, t[1]] - self.lower
        corner3 = p[:, t[3]] - self.lower
        ok = (
            np.all(self.size > 0)
            and np.allclose(corner1[1], 0.0) and np.allclose(corner1[0], self.size[0])
            and np.allclose(corner3[0], 0.0) and np.allclose(corner3[1], self.size[1])
        )
        if not ok:
            raise ValueError(
                "MappingRectangular needs axis-aligned rectangles with vertices "
                "listed counter-clockwise from the lower-left corner"
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

    def DF(self, X, tind=None):
        _, size = self._cell_arrays(tind)
        out = np.zeros((2, 2, size.shape[1], self._nqp(X)))
        out[0, 0] = size[0][:, None]
        out[1, 1] = size[1][:, None]
        return out

    def invDF(self, X, tind=None):
        _, size = self._cell_arrays(tind)
        out = np.zeros((2, 2, size.shape[1], self._nqp(X)))
        out[0, 0] = 1.0 / size[0][:, None]
        out[1, 1] = 1.0 / size[1][:, None]
        return out

    def detDF(self, X, tind=None):
        _, size = self._cell_arrays(tind)
        det = size[0] * size[1]
        return np.broadcast_to(det[:, None], (det.size, self._nqp(X))).copy()

    def G(self, X, find=None):
        facets = self.mesh.facets if find is None else self.mesh.facets[:, find]
        start = self.mesh.p[:, facets[0]]
        edge = self.mesh.p[:, facets[1]] - start
        if X.ndim == 2:
            return start[:, :, None] + edge[:, :, None] * X[0][None, None, :]
        return start[:, :, None] + edge[:, :, None] * X[0][None]

    def detDG(self, X, find=None):
        facets = self.mesh.facets if find is None else self.mesh.facets[:, find]
        edge = self.mesh.p[:, facets[1]] - self.mesh.p[:, facets[0]]
        length = np.sqrt((edge ** 2).sum(axis=0))
        return np.broadcast_to(length[:, None], (length.size, X.shape[-1])).copy()

    def normals(self, X, tind, find, t2f):
        facets = self.mesh.facets[:, find]
        start = self.mesh.p[:, facets[0]]
        edge = self.mesh.p[:, facets[1]] - start
        normal = np.stack((edge[1], -edge[0]))
        normal /= np.sqrt((normal ** 2).sum(axis=0))
        centre = self.lower[:, tind] + 0.5 * self.size[:, tind]
        midpoint = start + 0.5 * edge
        flip = ((midpoint - centre) * normal).sum(axis=0) < 0
        normal[:, flip] *= -1.0
        return np.repeat(normal[:, :, None], X.shape[-1], axis=2)
