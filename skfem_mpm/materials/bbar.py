"""B-bar for particles: any material with the volumetric part of each
particle's velocity gradient averaged over the particles of its cell."""
import numpy as np

from ..spline import SplineGrid
from .base import Material

__all__ = ["BBar"]


class BBar(Material):
    """``BBar(material, grid)``: ``material`` with its volumetric strain rate
    taken as the volume-weighted mean over the particles of the grid cell
    each particle lies in (the B-bar idea of Hughes 1980, Int. J. Numer.
    Meth. Eng. 15, 1413-1418, with the cell's particles as its quadrature;
    the MPM form of Coombs, Charlton, Cortis and Augarde 2018, Comput.
    Methods Appl. Mech. Eng. 333, 1-21, who average det F over a cell,
    F-bar)::

        theta_p   = tr L_p                                    (dilatation rate)
        theta_c   = sum_{q in c} V_q theta_q / sum_{q in c} V_q
        L_bar_p   = L_p + (theta_c(p) - theta_p) / dim  I

    and the wrapped material's ``update`` runs with L_bar (stress, volume
    and state alike, so the volume change of a particle is its cell's).
    Why: an isochoric plastic flow (von Mises, Mohr-Coulomb without
    dilation) asks every particle's velocity field to be divergence-free,
    which low-order grids cannot give without locking (the footing's
    pressure climbs past the limit load); with one volumetric constraint
    per cell instead of one per particle the flow is free again. The
    deviatoric part is untouched.

    On the compiled paths (the compiled executor and the compiled step
    loop) the average is a pass over the particles before the constitutive
    kernel (:func:`skfem_mpm.kernels.bbar.average_dilatation`, which gives
    this ``averaged`` to the last bit: ``cell_average`` is True), and the
    wrapped material's compiled point law (``point_update``,
    ``point_parameters``) then runs with L_bar; a wrapped material without
    one, or a grid that is not a SplineGrid, leaves ``point_update`` None
    (the compiled executor then calls ``update``: Python per step,
    vectorised). ``grid`` must be the scene's grid (the particles are
    located in its cells).
    """

    cell_average = True

    def __init__(self, material, grid):
        if not isinstance(material, Material) or isinstance(material, BBar):
            raise ValueError(f"material must be a Material (not already a BBar), "
                             f"got {material!r}")
        if not hasattr(grid, "locate") or not hasattr(grid, "ncells"):
            raise ValueError(f"grid must be the scene's SplineGrid (or LagrangeGrid), "
                             f"got {grid!r}")
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

    def averaged(self, particles, L):
        """L_bar (class docstring) of the particles' velocity gradients L."""
        dim = L.shape[-1]
        cells, _ = self.grid.locate(particles.x)
        theta = np.trace(L, axis1=1, axis2=2)
        volume = np.bincount(cells, weights=particles.V, minlength=self.grid.ncells)
        mean = np.bincount(cells, weights=particles.V * theta, minlength=self.grid.ncells)
        mean = mean[cells] / volume[cells]
        return L + ((mean - theta) / dim)[:, None, None] * np.eye(dim)

    def update(self, particles, L, dt):
        return self.material.update(particles, self.averaged(particles, L), dt)
