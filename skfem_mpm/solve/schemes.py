"""Time-stepping schemes: the one place where each scheme's sequence is written.

A scheme is a function ``step(ops, state)`` that calls the named operations
of an executor ``ops``; it never knows which executor runs it. Two
executors implement the same operations: the reference one
(:mod:`skfem_mpm.solve.reference`: NumPy/scikit-fem transfer matrices, any
mesh, every option; the oracle) and the compiled one
(:mod:`skfem_mpm.solve.compiled`: fused numba kernels on spline grids). An
executor may fuse consecutive operations into one kernel (the compiled one
moves the particles in the same pass that updates their velocities), but
each operation's result is what its docstring in the reference executor
says by the time the next one needs it.

The operations (particles p, grid dofs i, N_ip = N_i(x_p)):

    particles_to_grid      m_i, P_i = sum_p m_p v_p N_ip, f_i (internal + external),
                           the consistent mass M when the method uses it
    solve_velocity         M v^n = P (constrained dofs: their velocity at t)
    solve_grid             M a = f (damping applied to f if declared; constrained
                           dofs: a = (v(t + dt) - v(t)) / dt); reactions; with
                           ``end_velocity=c``: v = v^n + c dt a
    update_particle_velocities   v_p += c dt sum_i N_ip a_i
    project_velocity       M v = sum_p N_ip m_p v_p (the updated v_p) at t + dt
    move_particles         x_p += dt sum_i N_ip v_i,  u_p likewise,  L_p = grad N v
    update_stress          each body's material: stress, V (and F) from L_p
    internal_force         f_i from the updated stress (USF)
    commit                 work of the external forces, checks (finite, inside the
                           grid), the new state becomes current, t += dt

MUSL (Al-Kafaji 2013, Sec. 3.3; the seed's algorithm): the grid velocity
that moves the particles is re-projected from the updated particle momentum.
USL: v = v^n + dt a with v^n from M v^n = P (no re-projection).
USF: v^n from M v^n = P; the stress is updated with L = grad N v^n first,
then f from the new stress, a, v = v^n + dt a and the particle update.
CD: central difference with staggered velocities: the particles carry
v^(n-1/2); the first step is a half step v^(1/2) = v^0 + dt/2 N a^0, then
USL. Second order in time; reported velocities are v^(n+1/2) + dt/2 N a^n.
RK4: classical fourth-order Runge-Kutta on the particle system; each stage
evaluates the rates k = R(t, y) with a whole particles-to-grid, grid solve
and grid-to-particles pass (:mod:`skfem_mpm.solve.runge_kutta`). Its own
operations:

    stage_rates            k = (N v, N a, the stress or F rate, dV/dt) of the
                           given particles at time t (v: M v = P, a: M a = f);
                           the first stage's call (``reactions``) sets the reactions
    stage                  the particles y_n + dt sum_s w_s k_s (rates and
                           weights: tuples, one entry per stage)
    combine                the step's new state y_n + dt sum_s b_s k_s and its
                           external work
"""

from numba.extending import register_jitable

__all__ = ["step_musl", "step_usl", "step_usf", "step_cd", "step_rk4", "SCHEME_STEPS"]

# ``register_jitable``: a scheme is a plain Python function for the
# executors of skfem_mpm.solve, and numba compiles the same function
# against a compiled run's operations (skfem_mpm.solve.compiled_loop).


@register_jitable
def step_musl(ops, state):
    grid = ops.particles_to_grid(state)
    ops.solve_grid(state, grid)
    ops.update_particle_velocities(state, grid)
    ops.project_velocity(state, grid)
    ops.move_particles(state, grid)
    ops.update_stress(state, grid)
    ops.commit(state, grid)
    return grid


@register_jitable
def _usl(ops, state, velocity_factor, keep_acceleration=False):
    grid = ops.particles_to_grid(state)
    ops.solve_grid(state, grid, end_velocity=velocity_factor)
    ops.update_particle_velocities(state, grid, velocity_factor, keep_acceleration)
    ops.move_particles(state, grid)
    ops.update_stress(state, grid)
    ops.commit(state, grid)
    return grid


@register_jitable
def step_usl(ops, state):
    return _usl(ops, state, 1.0)


@register_jitable
def step_cd(ops, state):
    half_step = state.step == 0
    return _usl(ops, state, 0.5 if half_step else 1.0, keep_acceleration=True)


@register_jitable
def step_usf(ops, state):
    grid = ops.particles_to_grid(state)
    ops.solve_velocity(state, grid)
    ops.update_stress(state, grid, velocity=grid.velocity_old)
    ops.internal_force(state, grid)
    ops.solve_grid(state, grid, end_velocity=1.0)
    ops.update_particle_velocities(state, grid)
    ops.move_particles(state, grid)
    ops.commit(state, grid)
    return grid


@register_jitable
def step_rk4(ops, state):
    k1 = ops.stage_rates(state, state.particles, 0.0, True)
    k2 = ops.stage_rates(state, ops.stage(state, (k1,), (0.5,)), 0.5, False)
    k3 = ops.stage_rates(state, ops.stage(state, (k2,), (0.5,)), 0.5, False)
    k4 = ops.stage_rates(state, ops.stage(state, (k3,), (1.0,)), 1.0, False)
    step = ops.combine(state, (k1, k2, k3, k4), (1 / 6, 1 / 3, 1 / 3, 1 / 6))
    ops.commit(state, step)
    return step


SCHEME_STEPS = {"musl": step_musl, "usl": step_usl, "usf": step_usf, "cd": step_cd,
                "rk4": step_rk4}
