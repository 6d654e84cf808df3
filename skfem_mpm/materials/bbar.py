"""B-bar for particles: any material with the volumetric part of each
particle's velocity gradient projected over the particles onto the grid's
vertex functions (or its cells)."""
import numpy as np

from ..spline import SplineGrid
from .base import Material

__all__ = ["BBar"]


class BBar(Material):
    """``BBar(material, grid, average=None)``: ``material`` with its
    volumetric strain rate replaced by its lumped (volume-weighted)
    projection over the particles onto a space of dilatations one order
    below the velocity's (the B-bar method of Hughes 1980, Int. J. Numer.
    Meth. Eng. 15, 1413-1418, with the particles as its quadrature; the
    projection spaces of Elguedj, Bazilevs, Calo and Hughes 2008, Comput.
    Methods Appl. Mech. Eng. 197, 2732-2762, for splines of degree p:
    splines of degree p - 1; the lumped, nodal form of Mast et al. 2012,
    J. Comput. Phys. 231, 5351-5373, for MPM)::

        theta_p   = tr L_p                                    (dilatation rate)
        theta_A   = sum_q H_A(x_q) V_q theta_q / sum_q H_A(x_q) V_q
        theta_bar = sum_A H_A(x_p) theta_A
        L_bar_p   = L_p + (theta_bar - theta_p) / dim  I

    with H_A (``average``):

    * ``"vertex"`` (the default on a SplineGrid of degree >= 2): the
      continuous piecewise-(bi/tri)linear functions of the knot grid's
      vertices, H_A(x) the product over the axes of (1 - t) or t, t the
      point's place in its cell (for quadratic splines the degree p - 1 =
      1, C0 space of Elguedj et al.); theta_A is the hat-weighted mean over
      the particles of the cells around vertex A, theta_bar its continuous
      interpolant;
    * ``"cell"`` (the default on linear grids and non-spline grids, where
      the vertex space would be the velocity's own and lock): the cells'
      indicators, theta_bar the volume-weighted mean over the particles of
      the particle's cell (degree p - 1 = 0; the cell average of Coombs,
      Charlton, Cortis and Augarde 2018, Comput. Methods Appl. Mech. Eng.
      333, 1-21, who average det F over a cell, F-bar).

    Both keep each function's volume-weighted dilatation
    (sum_p V_p theta_bar_p = sum_p V_p theta_p over the body), and
    theta_bar is a convex combination of the particles' theta (no guard
    is needed for nearly empty cells or vertices: a function no particle
    touches is never read). The wrapped material's ``update`` runs with
    L_bar (stress, volume and state alike). Why: an isochoric plastic
    flow (von Mises, Mohr-Coulomb without dilation) asks every particle's
    velocity field to be divergence-free, which low-order grids cannot
    give without locking (the footing's pressure climbs past the limit
    load); with one volumetric constraint per cell or vertex instead of
    one per particle the flow is free again. Why vertices for quadratic
    splines: cell averages (a discontinuous, piecewise-constant pressure)
    are not stable against the C1 quadratic velocity (no inf-sup bound,
    like Q1-P0): in the yielded zone under a footing they leave velocity
    modes with zero cell-mean dilatation unresisted, the particles drift
    into rows (1 to 6 particles in cells that held 4) once the footing has
    settled about a cell and a half, the cell means are then taken over a
    row or two, and the pressure alternates from row to row (0.3 to 25
    c_u on G1); the continuous vertex space does not allow that. The
    deviatoric part is untouched.

    On the compiled paths (the compiled executor and the compiled step
    loop) the projection is a pass over the particles before the
    constitutive kernel (:func:`skfem_mpm.kernels.bbar.average_dilatation`,
    which gives this ``averaged`` to the last bit: ``cell_average`` is
    True), and the wrapped material's compiled point law
    (``point_update``, ``point_parameters``) then runs with L_bar; a
    wrapped material without one, or a grid that is not a SplineGrid,
    leaves ``point_update`` None (the compiled executor then calls
    ``update``: Python per step, vectorised). ``grid`` must be the scene's
    grid (the particles are located in its cells).
    """

    cell_average = True

    AVERAGES = ("cell", "vertex")

    def __init__(self, material, grid, average=None):
        if not isinstance(material, Material) or isinstance(material, BBar):
            raise ValueError(f"material must be a Material (not already a BBar), "
                             f"got {material!r}")
        if not hasattr(grid, "locate") or not hasattr(grid, "ncells"):
            raise ValueError(f"grid must be the scene's SplineGrid (or LagrangeGrid), "
                             f"got {grid!r}")
        spline = isinstance(grid, SplineGrid)
        if average is None:
            average = "vertex" if spline and grid.degree >= 2 else "cell"
        if average not in self.AVERAGES or (average == "vertex" and not spline):
            raise ValueError(f"average must be one of {self.AVERAGES} ('vertex' on a "
                             f"SplineGrid only) or None, got {average!r}")
        self.average = average
        self.material = material
        self.grid = grid
        self.finite_strain = material.finite_strain
        self.point_update = material.point_update if isinstance(grid, SplineGrid) else None

    def point_parameters(self, dim):
        """The wrapped material's (its point law runs with L_bar)."""
        return self.material.point_parameters(dim)

    def __repr__(self):
        return f"BBar({self.material!r})"

    def state_fields(self, dim):
        return self.material.state_fields(dim)

    def check_dim(self, dim):
        self.material.check_dim(dim)

    def wave_speed(self, particles):
        return self.material.wave_speed(particles)

    def wave_speed_bound(self, particles):
        return self.material.wave_speed_bound(particles)

    def strain_energy(self, particles):
        return self.material.strain_energy(particles)

    @property
    def vertices(self):
        """Whether the dilatation space is the vertex functions' (else the cells')."""
        return self.average == "vertex"

    @property
    def functions(self):
        """The number of dilatation functions: cells or vertices."""
        if not self.vertices:
            return self.grid.ncells
        return int(np.prod([b.size for b in self.grid.breakpoints]))

    def dilatation_functions(self, x):
        """(ids (n, k), values (n, k)) of the dilatation functions at points
        x: k = 1 (the cell, value 1) or 2^dim vertex functions (the first
        axis fastest)."""
        cells, _ = self.grid.locate(x)
        if not self.vertices:
            return cells[:, None], np.ones((x.shape[0], 1))
        grid, n, dim = self.grid, x.shape[0], x.shape[1]
        ids = np.zeros((n, 1 << dim), dtype=np.int64)
        values = np.ones((n, 1 << dim))
        cell_stride, stride = 1, 1
        for a in range(dim):
            breaks = np.asarray(grid.breakpoints[a], dtype=np.float64)
            e = (cells // cell_stride) % (breaks.size - 1)
            t = (x[:, a] - breaks[e]) / (breaks[e + 1] - breaks[e])
            for j in range(1 << dim):
                upper = (j >> a) & 1
                ids[:, j] += stride * (e + upper)
                values[:, j] = values[:, j] * (t if upper else 1.0 - t)
            cell_stride *= breaks.size - 1
            stride *= breaks.size
        return ids, values

    def averaged(self, particles, L):
        """L_bar (class docstring) of the particles' velocity gradients L."""
        dim = L.shape[-1]
        ids, values = self.dilatation_functions(particles.x)
        theta = np.trace(L, axis1=1, axis2=2)
        w = values * particles.V[:, None]
        volume = np.bincount(ids.ravel(), weights=w.ravel(), minlength=self.functions)
        weighted = np.bincount(ids.ravel(), weights=(w * theta[:, None]).ravel(),
                               minlength=self.functions)
        mean = np.zeros(theta.shape)
        for j in range(ids.shape[1]):
            used = values[:, j] != 0.0
            term = values[:, j] * (weighted[ids[:, j]] / np.where(used, volume[ids[:, j]], 1.0))
            mean = mean + np.where(used, term, 0.0)
        return L + ((mean - theta) / dim)[:, None, None] * np.eye(dim)

    def update(self, particles, L, dt):
        return self.material.update(particles, self.averaged(particles, L), dt)
