"""Time-stepping schemes, each written as the method's own steps.

MUSL (Al-Kafaji 2013, Sec. 3.3; the seed's algorithm):
    1. particles to grid: m, P, f at x^n
    2. solve M a = f
    3. v_p^{n+1} = v_p^n + dt N a                         (grid to particles)
    4. solve M v^{n+1} = N^T (m v_p^{n+1})                 (momentum re-projected)
    5. x_p^{n+1} = x_p^n + dt N v^{n+1};  L = grad N v^{n+1}; update stress

USL:  as MUSL but v^{n+1} = v^n + dt a with v^n from M v^n = P (no re-projection).
USF:  v^n from M v^n = P; stress updated with L = grad N v^n first; then f from
      the new stress, a, v^{n+1} = v^n + dt a and the particle update.
CD:   central difference with staggered velocities: the particles carry
      v^(n-1/2); the first step is a half step v^(1/2) = v^0 + dt/2 N a^0,
      then USL. Second order in time; reported velocities are
      v^(n+1/2) + dt/2 N a^n.
"""
import numpy as np

from .steps import (commit, grid_to_particles, grid_velocity, internal_force, particles_to_grid,
                    remember_end_velocity, solve_grid, update_stress)

__all__ = ["step_musl", "step_usl", "step_usf", "step_cd", "SCHEME_STEPS"]


def _external_work(state, data):
    """Work of the particle forces over the step: sum_p f_p . (x_p^(n+1) - x_p^n),
    the displacement the scheme actually gives the particles."""
    f_p = data.external
    if f_p is not None:
        state.external_work += float(np.sum(f_p * (data.new["u"] - state.particles.u)))


def step_musl(state):
    data = particles_to_grid(state)
    solve_grid(state, data)
    L = grid_to_particles(state, data)
    update_stress(state, L, data)
    _external_work(state, data)
    commit(state, data)
    return data


def _usl(state, first_half_step):
    data = particles_to_grid(state)
    solve_grid(state, data, need_old_velocity=True)
    factor = 0.5 if first_half_step else 1.0
    data.velocity = data.velocity_old + (factor * state.dt) * data.acceleration
    remember_end_velocity(data)
    L = grid_to_particles(state, data, velocity_factor=factor)
    update_stress(state, L, data)
    _external_work(state, data)
    commit(state, data)
    return data


def step_usl(state):
    return _usl(state, first_half_step=False)


def step_cd(state):
    data = _usl(state, first_half_step=state.step == 0)
    if state.particles.n == data.particle_acceleration.shape[0]:
        state.particle_acceleration = data.particle_acceleration
    return data


def step_usf(state):
    p = state.particles
    data = particles_to_grid(state)
    v_old = grid_velocity(state, data, data.momentum, state.t)
    with state.timer("g2p"):
        L = data.transfer.gradient_to_particles(v_old)
    stress, V, F = update_stress(state, L, data)
    updated = p.replaced(stress=stress, V=V, F=F)
    if state.method.reconstruction != "none":
        saved, state.particles = state.particles, updated
        try:
            force = particles_to_grid(state).force
        finally:
            state.particles = saved
    else:
        with state.timer("p2g"):
            force = internal_force(state, data.transfer, updated)
            if data.external_grid is not None:
                force += data.external_grid
    data.force = force
    data.velocity_old = v_old
    solve_grid(state, data)
    data.velocity = v_old + state.dt * data.acceleration
    remember_end_velocity(data)
    grid_to_particles(state, data)
    _external_work(state, data)
    commit(state, data)
    return data


SCHEME_STEPS = {"musl": step_musl, "usl": step_usl, "usf": step_usf, "cd": step_cd}
