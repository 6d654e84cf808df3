"""Classical fourth-order Runge-Kutta on the semi-discrete particle system
(the reference executor's operations of the ``rk4`` scheme).

Between two grid solves the particles' state y = (x_p, u_p, v_p, sigma_p,
V_p, F_p) obeys the ordinary differential equations

    dx_p/dt = sum_i N_ip v_i,   du_p/dt = dx_p/dt,   dv_p/dt = sum_i N_ip a_i,
    L_p = sum_i v_i (x) grad N_i(x_p),
    small strain:   d sigma_p/dt = material.stress_rate(L_p),  dV_p/dt = V_p tr L_p,
    finite strain:  dF_p/dt = L_p F_p,  sigma_p = material.cauchy_stress(F_p),
                    V_p = V0_p det F_p,

with the grid velocity from the particle momentum, M v = P (constrained dofs:
their velocity at t), and M a = f (constrained dofs: the time derivative of
their velocity at t), both at the particles' current positions, with the
method's mass and reconstruction. One evaluation of the right-hand side
R(t, y) is therefore a whole particles-to-grid, grid solve and
grid-to-particles pass (:func:`stage_rates`). Classical RK4 (Kutta 1901;
Hairer, Norsett, Wanner, "Solving Ordinary Differential Equations I",
Sec. II.1):

    k1 = R(t, y),              k2 = R(t + dt/2, y + dt/2 k1),
    k3 = R(t + dt/2, y + dt/2 k2),   k4 = R(t + dt, y + dt k3),
    y(t + dt) = y + dt/6 (k1 + 2 k2 + 2 k3 + k4).

Stability: on y' = i omega y the classical method is stable for
|omega dt| <= 2 sqrt(2) (its stability region meets the imaginary axis at
+-2 sqrt(2)), against 2 for central difference, so its critical time step is
sqrt(2) times the one of :mod:`skfem_mpm.solve.timestep` and ``cfl`` is a
fraction of that. Below the limit RK4 damps the highest frequencies slightly
(|amplification| < 1); its error is fourth order in dt.

Smoothness limits the order when particles cross knots: R(t, y) has the
smoothness of grad N in x, so a degree-p basis (C^(p-1)) gives RK4 its full
order only while no particle crosses a knot, or for p >= 3. Measured on S4
large (the neo-Hookean bar, 8 cells, particles moving across cells), time
error orders at fixed dt halved three times: p = 3: 4.2, 4.2, 4.1;
p = 2: 4.2, 2.6, 2.3; S4 small (no crossing), p = 2: 4.1, 4.1, 4.1.

A material can be staged when a stage's stress follows from the stage's
kinematic state alone: a small-strain material through its stress rate
(linear hypoelasticity: ``stress_rate(particles, L)``), a finite-strain one
through sigma(F) (hyperelasticity: ``cauchy_stress(F)``). Path-dependent
materials (plasticity, per-particle state fields) are refused by
:func:`check_staged`: their return mapping is not a rate the stages can
combine. The compiled executor and loop stage one finite-strain body with
a compiled point law through that law, called at the staged F with
dt = 0: a stageable material's law must then return its sigma(F), the
``cauchy_stress`` this module calls.

The external work of a step is the RK4 quadrature of the power of the
particle forces, dt sum_s b_s sum_p f_p(stage s) . dx_p/dt(stage s); the
reactions reported are those of the first stage (time t), like the other
schemes' (their grid solve at t).
"""
import numpy as np

from ..effects import modified_force
from ..errors import InvalidState
from ..materials.base import Material, det
from . import steps

__all__ = ["StageRates", "RungeKuttaStep", "check_staged", "staging_error",
           "prescribed_acceleration", "stage_rates", "staged_particles", "combined_step"]


def staging_error(material, dim):
    """Why ``material`` cannot be staged by a Runge-Kutta scheme, or None."""
    name = type(material).__name__
    fields = material.state_fields(dim)
    if fields:
        return (f"{name} keeps per-particle state {sorted(fields)}: a path-dependent "
                f"update cannot be staged by scheme 'rk4'")
    if material.finite_strain:
        if type(material).cauchy_stress is Material.cauchy_stress:
            return (f"{name} is a finite-strain material without cauchy_stress(F) "
                    f"(sigma as a function of F): scheme 'rk4' cannot stage it")
    elif type(material).stress_rate is Material.stress_rate:
        return (f"{name} is a small-strain material without stress_rate(particles, L) "
                f"(a rate law): scheme 'rk4' cannot stage it")
    return None


def check_staged(materials, dim):
    """ValueError naming the first material a Runge-Kutta scheme cannot stage."""
    for material in materials:
        why = staging_error(material, dim)
        if why is not None:
            raise ValueError(f"{why}; use scheme 'cd', 'musl', 'usl' or 'usf', or give the "
                             f"material that method (see skfem_mpm.solve.runge_kutta)")


def prescribed_acceleration(constraints, t, h):
    """dv/dt of the prescribed velocities at t by the fourth-order central
    difference (v(t - 2h) - 8 v(t - h) + 8 v(t + h) - v(t + 2h)) / (12 h)
    (exact for velocities polynomial of degree <= 4 in t); zeros when nothing
    is prescribed."""
    if not constraints.prescribed:
        return constraints.values(t)
    return velocity_rate(constraints.values, t, h)


def velocity_rate(values, t, h):
    """(values(t - 2h) - 8 values(t - h) + 8 values(t + h) - values(t + 2h)) / (12 h),
    the rate of :func:`prescribed_acceleration` of any ``values(t)`` (the
    grid's, or the compiled loop's per prescribed item)."""
    return (values(t - 2 * h) - 8 * values(t - h) + 8 * values(t + h)
            - values(t + 2 * h)) / (12 * h)


class StageRates:
    """R(t, y) at one stage: rates of positions (N v), velocities (N a),
    stress (small-strain particles), F (finite strain) and V (small strain),
    the power of the particle forces and, for the first stage, the
    reactions."""

    __slots__ = ("x", "v", "stress", "F", "V", "power")

    def __init__(self, x, v, stress, F, V, power):
        self.x, self.v, self.stress, self.F, self.V, self.power = x, v, stress, F, V, power


class RungeKuttaStep:
    """The new particle state of one Runge-Kutta step, for ``commit``."""

    def __init__(self, new, work):
        self.new = new                   # arrays of the new particle state
        self.work = work                 # external work of the step
        self.external = None
        self.keep_acceleration = False
        self.system = None               # the stages count their tiny-mass dofs


def _material_rates(state, particles, L):
    """(stress rate or None, F rate or None, V rate) of every body."""
    p = state.particles if particles is None else particles
    n, dim = p.n, p.dim
    stress_rate = F_rate = None
    V_rate = np.zeros(n)
    single = len(state.bodies) == 1
    with state.timer("constitutive"):
        for material, index in state.bodies:
            sub = p if single else p.subset(index)
            L_b = L if single else L[index]
            if material.finite_strain:
                if F_rate is None:
                    F_rate = np.zeros((n, dim, dim))
                F_rate[index] = L_b @ sub.F
            else:
                if stress_rate is None:
                    stress_rate = np.zeros((n, dim, dim))
                stress_rate[index] = material.stress_rate(sub, L_b)
                V_rate[index] = sub.V * np.trace(L_b, axis1=1, axis2=2)
    return stress_rate, F_rate, V_rate


def stage_rates(state, particles, stage, reactions=False):
    """R(t, y) for the particles ``particles`` (a stage state) at the
    stage's time t = state.t + stage dt: particles to grid, M v = P and M a = f
    (force modifiers such as damping applied with that v, at that time:
    see :mod:`skfem_mpm.effects`), grid to particles. ``reactions``: set
    the state's reactions from this stage's acceleration solve."""
    t = state.t + stage * state.dt
    data = steps.particles_to_grid(state, particles, t)
    c = state.constraints
    with state.timer("solve"):
        system = steps.step_system(state, data)
        v = system.solve(data.momentum, c.values(t), "velocity")
        system.remember("velocity", v)
    force = data.force
    if state.force_modifiers:
        with state.timer("effects"):
            for modifier in state.force_modifiers:
                force = modified_force(modifier, force, v, data.lumped, state.dt, state.t,
                                       stage)
    with state.timer("solve"):
        a = system.solve(force, prescribed_acceleration(c, t, state.dt), "acceleration")
        system.remember("acceleration", a)
        if reactions and c.any:
            state.reactions = c.reactions(system.residual(a, force))
    state.small_dofs_max = max(state.small_dofs_max, system.small_dofs)
    transfer = data.transfer
    with state.timer("g2p"):
        x_rate = transfer.to_particles(v)
        v_rate = transfer.to_particles(a)
        L = transfer.gradient_to_particles(v)
    stress_rate, F_rate, V_rate = _material_rates(state, particles, L)
    power = 0.0 if data.external is None else float(np.sum(data.external * x_rate))
    return StageRates(x_rate, v_rate, stress_rate, F_rate, V_rate, power)


def _advanced(state, rates, weights):
    """The arrays of y_n + dt sum_s w_s k_s (y_n the state's particles)."""
    p, dt = state.particles, state.dt

    def combined(name, start):
        total = start.copy()
        for k, w in zip(rates, weights):
            if w != 0.0:
                total += (w * dt) * getattr(k, name)
        return total

    dx = combined("x", np.zeros_like(p.x))
    new = {"x": p.x + dx, "u": p.u + dx, "v": combined("v", p.v)}
    stress, V = p.stress.copy(), p.V.copy()
    F = None if p.F is None else p.F
    finite = [b for b in state.bodies if b[0].finite_strain]
    small = [b for b in state.bodies if not b[0].finite_strain]
    if small:
        stress_all, V_all = combined("stress", p.stress), combined("V", p.V)
        for _, index in small:
            stress[index], V[index] = stress_all[index], V_all[index]
    if finite:
        F = combined("F", p.F)
        finite_strain_stage(state, F, stress, V)
    check_stage_volumes(V)
    new.update(stress=stress, V=V, F=F)
    return new


def finite_strain_stage(state, F, stress, V):
    """The finite-strain bodies' stage state from their staged F, written
    into ``stress`` and ``V``: sigma = cauchy_stress(F), V = V0 det F
    (both executors call this); InvalidState at the first J <= 0."""
    V0 = state.particles.V0
    with state.timer("constitutive"):
        for material, index in state.bodies:
            if not material.finite_strain:
                continue
            F_b = F[index]
            J = det(F_b)
            if not np.all(J > 0):
                k = int(np.arange(V0.shape[0])[index][np.flatnonzero(~(J > 0))[0]])
                raise InvalidState(f"J = det F <= 0 at particle {k} in a Runge-Kutta "
                                   f"stage", particle=k)
            stress[index] = material.cauchy_stress(F_b)
            V[index] = V0[index] * J


def check_stage_volumes(V):
    """InvalidState at the first staged volume V <= 0 (or NaN)."""
    bad = ~(V > 0)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise InvalidState(f"volume {V[k]:.3g} <= 0 at particle {k} in a Runge-Kutta stage",
                           particle=k)


def staged_particles(state, rates, weights):
    """The stage state y_n + dt sum_s w_s k_s as Particles."""
    return state.particles.replaced(**_advanced(state, rates, weights))


def combined_step(state, rates, weights):
    """The step's result y_n + dt sum_s b_s k_s and its external work
    dt sum_s b_s P_s (P_s the stage's power of the particle forces)."""
    work = state.dt * sum(w * k.power for k, w in zip(rates, weights))
    return RungeKuttaStep(_advanced(state, rates, weights), work)
