"""The reference executor: the operations of :mod:`skfem_mpm.solve.schemes`
with NumPy/scikit-fem transfer matrices (:mod:`skfem_mpm.solve.steps`).

It runs on any grid (spline or Lagrange), every scheme, mass, reconstruction,
material and effect; it is the oracle the compiled executor is tested
against.
"""
from . import runge_kutta, steps

__all__ = ["ReferenceExecutor"]


class ReferenceExecutor:
    """Executes the scheme operations with the step functions of
    :mod:`skfem_mpm.solve.steps`; ``why`` says why this executor was chosen
    (shown in ``Result.path``)."""

    def __init__(self, state, why=""):
        self.path = f"reference ({why})" if why else "reference"

    def hand_out(self, particles):
        """Nothing to do: the reference steps write new arrays every step."""

    def particles_to_grid(self, state):
        return steps.particles_to_grid(state)

    def solve_velocity(self, state, grid):
        return steps.solve_velocity(state, grid)

    def solve_grid(self, state, grid, end_velocity=None):
        return steps.solve_grid(state, grid, end_velocity=end_velocity)

    def update_particle_velocities(self, state, grid, velocity_factor=1.0,
                                   keep_acceleration=False):
        steps.update_particle_velocities(state, grid, velocity_factor, keep_acceleration)

    def project_velocity(self, state, grid):
        steps.project_velocity(state, grid)

    def move_particles(self, state, grid):
        steps.move_particles(state, grid)

    def update_stress(self, state, grid, velocity=None):
        """The materials' update with L = grad N v: v the grid velocity that
        moved the particles, or ``velocity`` (USF: v^n, before they move)."""
        if velocity is None:
            L = grid.L
        else:
            with state.timer("g2p"):
                L = grid.transfer.gradient_to_particles(velocity)
        steps.update_stress(state, L, grid)

    def internal_force(self, state, grid):
        """USF: the grid force recomputed from the updated stress and volume
        (reconstructed again when the method reconstructs)."""
        p = state.particles
        new = grid.new
        updated = p.replaced(stress=new["stress"], V=new["V"], F=new["F"])
        if state.method.reconstruction != "none":
            saved, state.particles = state.particles, updated
            try:
                force = steps.particles_to_grid(state).force
            finally:
                state.particles = saved
        else:
            with state.timer("p2g"):
                force = steps.internal_force(state, grid.transfer, updated)
                if grid.external_grid is not None:
                    force += grid.external_grid
        grid.force = force

    def stage_rates(self, state, particles, c, reactions=False):
        """R(t + c dt, particles) of a Runge-Kutta stage."""
        return runge_kutta.stage_rates(state, particles, c, reactions)

    def stage(self, state, rates, weights):
        return runge_kutta.staged_particles(state, rates, weights)

    def combine(self, state, rates, weights):
        return runge_kutta.combined_step(state, rates, weights)

    def commit(self, state, grid):
        steps.commit(state, grid)
