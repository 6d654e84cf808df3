"""Particles as a quadrature rule: ``ParticleBasis`` and transfer matrices.

Every particle is its own quadrature "element": the cell that contains it,
one quadrature point at its reference coordinates, and the weight

    W_p = V_p / |det DF(cell_p)|,     so that  dx_p = V_p.

A scikit-fem form assembled over this basis is then the particle sum

    a(u, v) = sum_p  form(u, v)(x_p) V_p,

e.g. the consistent mass matrix sum_p rho_p N_i(x_p) N_j(x_p) V_p. No padding
to a common number of points per cell is used (padding costs 1.3-400x with
clustered particles), and no cache outlives the basis, so rebuilding it for
new positions costs what building it once does.

Per-particle data enter a form with a trailing quadrature axis:
``asm(form, pb, rho=rho[:, None])``; a 1-D array would be read by scikit-fem
as a dof vector and interpolated.

Transfer matrices (CSR, particles x scalar dofs, (p + 1)^dim entries per row):

    N[p, i] = N_i(x_p),      grad_N[d][p, i] = dN_i/dx_d (x_p),

so particles-to-grid is ``N.T @ (m * v)`` and grid-to-particles ``N @ v_grid``
(``pb.N_matrix`` and ``pb.grad_N``).
"""
import numpy as np
import scipy.sparse as sp
from skfem import CellBasis
from skfem.assembly.basis.abstract_basis import AbstractBasis

from .particles import Particles

__all__ = ["ParticleBasis", "transfer_matrices"]


def _csr_pattern(dofs):
    """CSR index arrays for a fixed number k of entries per row (no sorting)."""
    n, k = dofs.shape
    index_dtype = np.int32 if max(n * k, int(dofs.max(initial=0)) + 1) < 2 ** 31 else np.int64
    indptr = np.arange(0, n * k + 1, k, dtype=index_dtype)
    return dofs.reshape(-1).astype(index_dtype, copy=False), indptr


def _csr(data, pattern, shape):
    out = sp.csr_matrix(shape)  # then set the arrays directly: no format checks
    out.data, (out.indices, out.indptr) = data.reshape(-1), pattern
    return out


def transfer_matrices(grid, x):
    """``(N, grad_N)`` for points ``x`` (n, dim) on ``grid``: the CSR matrix of
    basis values and one CSR matrix of derivatives per axis (each with its
    own copy of the index arrays, so in-place edits of one leave the others)."""
    dofs, values, grads = grid.shape_functions(x)
    pattern = _csr_pattern(dofs)
    shape = (dofs.shape[0], grid.ndofs)
    N = _csr(values, pattern, shape)
    grad_N = tuple(_csr(np.ascontiguousarray(grads[:, :, d]),
                        (pattern[0].copy(), pattern[1].copy()), shape)
                   for d in range(grid.dim))
    return N, grad_N


class ParticleBasis(CellBasis):
    """A scikit-fem ``CellBasis`` whose quadrature points are particles.

    Parameters
    ----------
    grid
        A :class:`~skfem_mpm.SplineGrid` (B-splines, degree 1-3) or a
        :class:`~skfem_mpm.LagrangeGrid` (P1/Q1 on a scikit-fem mesh).
    particles
        A :class:`~skfem_mpm.Particles`; positions ``x`` are the points and
        volumes ``V`` the weights.
    vector
        Use the vector-valued space (for elasticity forms).

    The basis values (``pb.basis``) are evaluated on first use; the transfer
    matrices ``pb.N_matrix`` and ``pb.grad_N`` come from the grid's own fast
    evaluator and equal what the forms compute. (``pb.N`` stays scikit-fem's
    number of dofs.)
    """

    def __init__(self, grid, particles, vector=False):
        if not isinstance(particles, Particles):
            raise TypeError(f"particles must be a Particles object (positions, volumes: "
                            f"Particles(x, m, V) or Particles.seed), got "
                            f"{type(particles).__name__}")
        x = particles.x
        self.grid = grid
        self.particles = particles
        self.vector = bool(vector)
        self.cells, self.reference = grid.locate(x)
        mapping = grid.new_mapping() if hasattr(grid, "new_mapping") else grid.mapping
        Xq = np.ascontiguousarray(self.reference.T)[:, :, None]
        det = np.abs(mapping.detDF(Xq, tind=self.cells))[:, 0]
        W = particles.V / det
        elem = grid.vector_element if vector else grid.element
        dofs = grid.vector_dofs if vector else grid.dofs
        # CellBasis.__init__ would evaluate every basis function eagerly; the
        # same attributes are set here and ``basis`` is filled on first use.
        AbstractBasis.__init__(self, grid.mesh, elem, mapping, None, (Xq, W[:, None]),
                               grid.mesh.refdom, dofs, True)
        self.tind = self.cells
        self.nelems = len(self.cells)
        self.dx = np.asarray(particles.V, dtype=np.float64)[:, None].copy()
        self._basis = None
        self._transfer = None

    def interpolate(self, w):
        """scikit-fem's interpolation of a dof vector ``w`` (ndofs,) to the
        particles; a per-particle array of another length, passed to a form
        without its trailing quadrature axis, raises naming the fix (with as
        many particles as dofs the two cannot be told apart)."""
        w = np.asarray(w)
        if w.shape[0] != self.N:
            hint = (f"; per-particle data in a form needs a trailing quadrature axis "
                    f"(rho[:, None], shape ({self.nelems}, 1))" if w.shape[0] == self.nelems
                    else "")
            raise ValueError(f"a 1-D array passed to a form is taken as a dof vector of "
                             f"length {self.N}, got shape {w.shape}{hint}")
        return super().interpolate(w)

    @property
    def basis(self):
        if self._basis is None:
            self._basis = [self.elem.gbasis(self.mapping, self.X, j, tind=self.tind)
                           for j in range(self.Nbfun)]
        return self._basis

    @basis.setter
    def basis(self, value):
        self._basis = value

    def _matrices(self):
        if self._transfer is None:
            self._transfer = transfer_matrices(self.grid, self.particles.x)
        return self._transfer

    @property
    def N_matrix(self):
        """CSR (particles x scalar dofs): N[p, i] = N_i(x_p).

        (Not ``pb.N``: scikit-fem's ``basis.N`` is the number of dofs, which
        ``asm`` relies on.)"""
        return self._matrices()[0]

    @property
    def grad_N(self):
        """Tuple of CSR matrices, one per axis: dN_i/dx_d at x_p."""
        return self._matrices()[1]

    def with_element(self, elem):
        raise NotImplementedError("build a new ParticleBasis(grid, particles, vector=...)")
