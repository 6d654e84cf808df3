"""A user material: follow the shape of skfem_mpm.materials (``update`` from
the velocity gradient, ``wave_speed``, ``strain_energy``). Here 1D
elastic-perfectly-plastic: the trial stress sigma + E dt L is returned to the
yield surface |sigma| <= sigma_y (radial return).

``update`` is the NumPy law (every executor can run it). Giving the same law
for one particle as ``point_update`` (a numba-compilable function, see
:mod:`skfem_mpm.materials.compiled`) lets the compiled executor run the
material without leaving compiled code; the tests check that both give the
same stress.

    python examples/custom_material.py
"""
import numpy as np

from skfem_mpm import Body, Fixed, Method, Particles, Scene, SplineGrid, fem, simulate
from skfem_mpm.materials import Material, det, incremental_deformation, point_update


@point_update
def elastic_plastic_law(params, L, F, dt, stress, state, stress_out, state_out):
    """One particle: sigma_(n+1) = clamp(sigma_n + E dt L, -sigma_y, sigma_y)."""
    E, yield_stress = params[0], params[1]
    trial = stress[0, 0] + E * dt * L[0, 0]
    stress_out[0, 0] = min(max(trial, -yield_stress), yield_stress)


class ElasticPlastic1D(Material):
    """sigma_(n+1) = clamp(sigma_n + E dt L, -sigma_y, sigma_y)."""

    point_update = elastic_plastic_law

    def __init__(self, E, yield_stress):
        self.E, self.yield_stress = float(E), float(yield_stress)

    def check_dim(self, dim):
        if dim != 1:
            raise ValueError(f"ElasticPlastic1D models 1D bars, got dim={dim}")

    def point_parameters(self, dim):
        return np.array([self.E, self.yield_stress])

    def update(self, particles, L, dt):
        trial = particles.stress + self.E * dt * L
        stress = np.clip(trial, -self.yield_stress, self.yield_stress)  # the return mapping
        return stress, particles.V * det(incremental_deformation(L, dt)), None

    def wave_speed(self, particles):
        return float(np.sqrt(self.E / (particles.m / particles.V).min()))

    def strain_energy(self, particles):
        """Elastic energy only (what is stored; plastic work is dissipated)."""
        return float(np.sum(0.5 * particles.stress[:, 0, 0] ** 2 / self.E * particles.V))


def main(cells=16, yield_stress=0.05):
    grid = SplineGrid.line(0.0, 1.0, cells, 2)
    particles = Particles.seed(grid, 2, 1.0, velocity=lambda X: 1e-2 * np.sin(np.pi * X))
    scene = Scene(grid, Body(particles, ElasticPlastic1D(100.0, yield_stress)), 0.5,
                  effects=[Fixed("left"), Fixed("right")])
    result = simulate(scene, Method(mass="consistent"), save_every=10)
    reference = fem(scene, Method(mass="consistent"), save_every=10)
    e = result.energies["total"]
    peak = np.abs(result.history["stress"]).max()
    peak_fem = np.abs(reference.history["stress"]).max()
    print(f"peak |stress| MPM {peak:.4f}, FEM {peak_fem:.4f} (yield {yield_stress}); "
          f"energy {e[0]:.3e} -> {e[-1]:.3e}")
    return peak, e


if __name__ == "__main__":
    main()
