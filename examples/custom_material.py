"""A user material: follow the shape of skfem_mpm.materials (``update`` from
the velocity gradient, ``wave_speed``, ``strain_energy``). Here 1D
elastic-perfectly-plastic: the trial stress sigma + E dt L is returned to the
yield surface |sigma| <= sigma_y (radial return), and each particle keeps
its accumulated plastic strain eps_p += |trial - sigma| / E.

Per-particle state: ``state_fields(dim)`` declares it, ``{name: (shape,
initial)}``; the run keeps it in ``particles.state["plastic_strain"]``
(shape (n,)), ``update`` reads it there and returns the new value as a
fourth item, and it is recorded in ``result.history["plastic_strain"]``,
checkpointed, and written to ParaView with the other particle fields.

``update`` is the NumPy law (every executor can run it). Giving the same law
for one particle as ``point_update`` (a numba-compilable function, see
:mod:`skfem_mpm.materials.compiled`) lets the compiled executor run the
material without leaving compiled code: it reads the particle's state as a
vector (the declared fields flattened in order; here one value) and writes
the new values into ``state_out``. The tests check that both give the same
stress and plastic strain.

    python examples/custom_material.py
"""
import numpy as np

from skfem_mpm import Body, Fixed, Method, Particles, Scene, SplineGrid, fem, simulate
from skfem_mpm.materials import Material, det, incremental_deformation, point_update


@point_update
def elastic_plastic_law(params, L, F, dt, stress, state, stress_out, state_out):
    """One particle: sigma_(n+1) = clamp(sigma_n + E dt L, -sigma_y, sigma_y);
    state[0], the accumulated plastic strain, grows by |trial - sigma_(n+1)| / E."""
    E, yield_stress = params[0], params[1]
    trial = stress[0, 0] + E * dt * L[0, 0]
    stress_out[0, 0] = min(max(trial, -yield_stress), yield_stress)
    state_out[0] = state[0] + abs(trial - stress_out[0, 0]) / E


class ElasticPlastic1D(Material):
    """sigma_(n+1) = clamp(sigma_n + E dt L, -sigma_y, sigma_y), with the
    accumulated plastic strain eps_p += |trial - sigma_(n+1)| / E."""

    point_update = elastic_plastic_law

    def __init__(self, E, yield_stress):
        self.E, self.yield_stress = float(E), float(yield_stress)

    def check_dim(self, dim):
        if dim != 1:
            raise ValueError(f"ElasticPlastic1D models 1D bars, got dim={dim}")

    def point_parameters(self, dim):
        return np.array([self.E, self.yield_stress])

    def state_fields(self, dim):
        """One scalar per particle, starting at 0."""
        return {"plastic_strain": ((), 0.0)}

    def update(self, particles, L, dt):
        trial = particles.stress + self.E * dt * L
        stress = np.clip(trial, -self.yield_stress, self.yield_stress)  # the return mapping
        plastic = particles.state["plastic_strain"] + np.abs(trial - stress)[:, 0, 0] / self.E
        return (stress, particles.V * det(incremental_deformation(L, dt)), None,
                {"plastic_strain": plastic})

    def wave_speed(self, particles):
        return float(np.sqrt(self.E / (particles.m / particles.V).min()))

    def strain_energy(self, particles):
        """Elastic energy only (what is stored; plastic work is dissipated)."""
        return float(np.sum(0.5 * particles.stress[:, 0, 0] ** 2 / self.E * particles.V))


def main(cells=16, yield_stress=0.05):
    """Peak |stress|, total energy per save and the final plastic strain
    per particle of the MPM run (FEM alongside)."""
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
    p, q = result.particles, reference.particles
    plastic, plastic_fem = p.state["plastic_strain"], q.state["plastic_strain"]
    # the plastic work sum_p sigma_y eps_p V_p is the energy the bar lost
    print(f"plastic work {np.sum(yield_stress * plastic * p.V):.3e} "
          f"(energy lost {e[0] - e[-1]:.3e})")
    print("plastic strain along the bar:     X     MPM        FEM")
    for X in (0.0, 0.2, 0.5, 0.8, 1.0):
        k = int(np.argmin(np.abs(p.X[:, 0] - X)))  # the particle nearest to X
        print(f"{'':33s}{p.X[k, 0]:.3f}  {plastic[k]:.3e}  {plastic_fem[k]:.3e}")
    return peak, e, plastic


if __name__ == "__main__":
    main()
