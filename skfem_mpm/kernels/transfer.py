"""The particle-grid transfers of one tensor B-spline grid, any dimension.

:class:`Transfers` binds the generated kernels of
:mod:`skfem_mpm.kernels.scatter` and :mod:`skfem_mpm.kernels.gather` to a
grid (its :data:`~skfem_mpm.kernels.records.Grid` record), the thread
count and the per-thread grid copies, and returns NumPy arrays.
"""
import numpy as np
from numba import get_num_threads

from .gather import g2p_kernel, rates_kernel
from .pages import lazy_zeros
from .records import grid_record, particle_record
from .scatter import g2p2g_kernel, p2g_kernel, reduce_copies, reduce_fields
from .serial import for_threads

__all__ = ["Transfers"]


class Transfers:
    """p2g, g2p2g, g2p and the Runge-Kutta stage rates on one grid.

    ``grid`` is a :class:`skfem_mpm.SplineGrid` or any object with its
    ``dim``, ``degree``, ``ndofs``, ``breakpoints``, ``_uniform``,
    ``extraction`` and ``basis_per_axis`` (one entry per axis, in any
    dimension). ``window``: the run window of the scatter kernels (None:
    where it pays, see :func:`skfem_mpm.kernels.scatter.p2g_kernel`).
    ``mass`` and ``mass_range`` hold the lumped mass of the last p2g call
    and each reduction chunk's (smallest positive, largest) entry;
    ``occupied`` the node ranges where p2g's arrays and the grid
    acceleration and velocity may be nonzero (see
    :func:`~skfem_mpm.kernels.scatter.reduce_fields`): p2g's arrays and
    the per-thread copies take memory only near the particles.
    ``parallel`` False: the serial kernels (the same blocks, the same bits)."""

    def __init__(self, grid, nthreads=None, window=None, parallel=True):
        self.dim = grid.dim
        self.p = grid.degree
        self.ndofs = grid.ndofs
        self.record = grid_record(grid)
        self.nthreads = get_num_threads() if nthreads is None else nthreads
        self.window = window
        self.parallel = bool(parallel)
        self._reduce_fields = for_threads(reduce_fields, self.parallel)
        self._reduce_copies = for_threads(reduce_copies, self.parallel)
        self._copies = {}
        nd, dim = self.ndofs, self.dim
        # p2g's arrays: written near the particles only (see reduce_fields)
        self.mass = lazy_zeros(nd)
        self._momentum = lazy_zeros((nd, dim))
        self._force = lazy_zeros((nd, dim))
        self.occupied = np.zeros(4, dtype=np.int64)
        self._projected = np.empty((nd, dim))
        self.mass_range = np.zeros((self.nthreads, 2))
        self._no_force = np.zeros((1, dim))
        self._no_acc = np.zeros((1, dim))
        self.flags = np.full((self.nthreads, 3), -1, dtype=np.int64)

    def grid_arrays(self):
        """The grid arrays the transfers write (mass, momentum, force, the
        re-projected momentum), for a caller that steps in their place (the
        compiled loop: the two never step at once)."""
        return self.mass, self._momentum, self._force, self._projected

    def occupy_all(self):
        """Mark every node of (mass, momentum, force) as possibly nonzero
        (``occupied``, see reduce_fields): after a write of nonzero values
        outside the particles' nodes (a side traction's grid force)."""
        self.occupied[0] = 0
        self.occupied[1] = self.ndofs

    def copies(self, nfields):
        """Per-thread grid copies with ``nfields`` fields (zero outside their
        touched ranges) and those ranges."""
        if nfields not in self._copies:
            self._copies[nfields] = (lazy_zeros((self.nthreads, self.ndofs, nfields)),
                                     np.zeros((self.nthreads, 2), dtype=np.int64))
        return self._copies[nfields]

    def p2g(self, particles, fext=None, cells=None):
        """(mass (dofs,), momentum (dofs, dim), force (dofs, dim)); the
        arrays are reused by the next call. ``cells(copies, touched)``, if
        given, adds more into the per-thread copies before they are summed
        (kernels.cell_integrals)."""
        copies, touched = self.copies(1 + 2 * self.dim)
        has = fext is not None
        p2g_kernel(self.dim, self.p, self.window, self.parallel)(
            particle_record(particles), self.record, fext if has else self._no_force, has,
            copies, touched)
        if cells is not None:
            cells(copies, touched)
        self._reduce_fields(copies, touched, self.mass, self._momentum, self._force,
                            self.mass_range, self.occupied)
        return self.mass, self._momentum, self._force

    def g2p2g(self, particles, grid_a, dt, v_new, cells=None):
        """MUSL: v_new = v + dt N a; returns the grid momentum of m v_new
        (``cells`` as in :meth:`p2g`)."""
        copies, touched = self.copies(self.dim)
        g2p2g_kernel(self.dim, self.p, self.window, self.parallel)(
            particle_record(particles), self.record, grid_a, float(dt), v_new, copies, touched)
        if cells is not None:
            cells(copies, touched)
        self._reduce_copies(copies, touched, self._projected)
        return self._projected

    def g2p(self, particles, grid_a, grid_v, dt, vfactor, flip, new, L_out, acc_out=None,
            lame=None):
        """The particle update into the arrays of ``new``; ``lame`` = (lambda,
        mu) fuses linear elasticity (in 1D (E, 0)), else L is stored in
        ``L_out``. Returns the first non-finite particle, the first outside
        the grid and the first with J <= 0 (each -1 for none)."""
        fused = lame is not None
        lam, mu = (float(lame[0]), float(lame[1])) if fused else (0.0, 0.0)
        store = acc_out is not None
        update = (float(dt), float(vfactor), bool(flip), fused, lam, mu, store)  # Update
        g2p_kernel(self.dim, self.p, self.parallel)(
            particle_record(particles), self.record, grid_a, grid_v, update,
            particle_record(new), L_out, acc_out if store else self._no_acc, self.flags)
        found = [-1, -1, -1]
        for row in self.flags.tolist():  # first hit over the threads' blocks
            for j, first in enumerate(row):
                if first >= 0 and (found[j] < 0 or first < found[j]):
                    found[j] = first
        return found

    def rates(self, particles, grid_a, grid_v, x_rate, v_rate, L_out, stress_rate, V_rate,
              lame=None):
        """A Runge-Kutta stage's particle rates into the given arrays: N v,
        N a, V tr L and, with ``lame`` = (lambda, mu) (1D: (E, 0)), the
        linear elastic stress rate, else L (see
        :mod:`skfem_mpm.kernels.gather`)."""
        fused = lame is not None
        lam, mu = (float(lame[0]), float(lame[1])) if fused else (0.0, 0.0)
        rates_kernel(self.dim, self.p, self.parallel)(
            particle_record(particles), self.record, grid_a, grid_v, (fused, lam, mu),
            self.nthreads, x_rate, v_rate, L_out, stress_rate, V_rate)
