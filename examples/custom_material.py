"""A user material: follow the shape of skfem_mpm.materials (``update`` from
the velocity gradient, ``wave_speed``, ``strain_energy``). Here 1D
elastic-perfectly-plastic: the trial stress sigma + E dt L is returned to the
yield surface |sigma| <= sigma_y (radial return).

    python examples/custom_material.py
"""
import numpy as np

from skfem_mpm import Body, Fixed, Method, Particles, Scene, SplineGrid, simulate
from skfem_mpm.materials import Material, det, incremental_deformation


class ElasticPlastic1D(Material):
    """sigma_(n+1) = clamp(sigma_n + E dt L, -sigma_y, sigma_y)."""

    def __init__(self, E, yield_stress):
        self.E, self.yield_stress = float(E), float(yield_stress)

    def check_dim(self, dim):
        if dim != 1:
            raise ValueError(f"ElasticPlastic1D models 1D bars, got dim={dim}")

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
    e = result.energies["total"]
    peak = np.abs(result.history["stress"]).max()
    print(f"peak |stress| {peak:.4f} (yield {yield_stress}); energy {e[0]:.3e} -> {e[-1]:.3e}")
    return peak, e


if __name__ == "__main__":
    main()
