"""The Runge-Kutta operations of the compiled executor (scheme ``rk4``):
``stage_rates``, ``stage`` and ``combine`` of
:mod:`skfem_mpm.solve.schemes` on compiled kernels.

The method is :mod:`skfem_mpm.solve.runge_kutta` (its NumPy version is
the reference executor's, which the tests compare this one with). One
stage, R(t, y) at the staged particles y:

    particles to grid       the executor's own ``particles_to_grid`` at the
                            stage particles and time (p2g kernel, consistent
                            stencil)
    M v = P, M a = f        the executor's lumped or consistent solves
                            (tiny-mass merge, fast-dof guard, hybrid mass),
                            constrained dofs: v(t) and dv/dt(t)
                            (:func:`runge_kutta.prescribed_acceleration`);
                            force modifiers (damping, walls, footings)
                            applied with that v at the stage's time
    rates                   one gather kernel: N v, N a, V tr L and, for
                            linear elasticity, its stress rate, else L
                            (:mod:`skfem_mpm.kernels.gather`); other
                            small-strain materials' ``stress_rate``; L F
                            (:func:`~skfem_mpm.kernels.staging.deformation_rate`
                            for one body)

The rates of the stages sit in preallocated arrays with a leading stage
axis; ``stage`` and ``combine`` form y_n + dt sum_s w_s k_s in one kernel
(:mod:`skfem_mpm.kernels.staging`), then a finite-strain material's
sigma(F) and V0 det F: for one body with a compiled point law, the
constitutive kernel with dt = 0 (A = I, so F stays and the law is called at
the staged F; a stageable material's law is its sigma(F), see
:func:`~skfem_mpm.solve.runge_kutta.staging_error`), as the compiled loop
does; else its NumPy ``cauchy_stress``. A stage's particles live in one reused set of
arrays; the step's result goes into the executor's second set of particle
arrays, current only after ``commit``.
"""
import numpy as np

from ..errors import InvalidState
from ..kernels.constitutive import material_update
from ..kernels.staging import combine_stages, deformation_rate
from ..kernels.traction import loads_power
from .runge_kutta import check_stage_volumes, finite_strain_stage, prescribed_acceleration

__all__ = ["CompiledRungeKutta"]

STAGES = 4


class CompiledStageRates:
    """One stage's rates: their row ``slot`` in the executor's rate arrays
    and the power of the particle forces."""

    __slots__ = ("slot", "power")

    def __init__(self, slot, power):
        self.slot, self.power = slot, power


class CompiledRungeKuttaStep:
    """The new particle state of a Runge-Kutta step, for ``commit``."""

    def __init__(self, new, work, outside):
        self.new, self.work, self.outside = new, work, outside
        self.keep_acceleration = False
        self.system = None  # the stages count their tiny-mass dofs


class RateArrays:
    """The rates of up to four stages of n particles, the stage state and
    L (zeros where a body has no such rate: F of small-strain particles)."""

    def __init__(self, n, dim, finite):
        self.n, self.finite = n, finite
        self.x = np.zeros((STAGES, n, dim))
        self.v = np.zeros((STAGES, n, dim))
        self.stress = np.zeros((STAGES, n, dim, dim))
        self.V = np.zeros((STAGES, n))
        self.F = np.zeros((STAGES, n, dim, dim) if finite else (1, 1, 1, 1))
        self.L = np.zeros((n, dim, dim))
        self.stage = dict(x=np.empty((n, dim)), u=np.empty((n, dim)), v=np.empty((n, dim)),
                          stress=np.empty((n, dim, dim)), V=np.empty(n),
                          F=np.empty((n, dim, dim)) if finite else None)
        self.weights = np.zeros(STAGES)
        self.next = 0


class CompiledRungeKutta:
    """The ``stage_rates``, ``stage`` and ``combine`` operations (a mixin of
    :class:`skfem_mpm.solve.compiled.CompiledExecutor`)."""

    _rk = None

    def _rate_arrays(self, state):
        p = state.particles
        finite = p.F is not None and self.finite
        if self._rk is None or self._rk.n != p.n or self._rk.finite != finite:
            self._rk = RateArrays(p.n, p.dim, finite)
        return self._rk

    def stage_rates(self, state, particles, c, reactions=False):
        """R(t + c dt, particles): see the module docstring."""
        rk = self._rate_arrays(state)
        if particles is state.particles:  # the step's first stage
            rk.next = 0
        slot = rk.next
        rk.next += 1
        t = state.t + c * state.dt
        grid = self.particles_to_grid(state, particles, t)
        self._prepare(state, grid)
        con = state.constraints
        system, mass, small = grid.system, grid.mass, grid.small
        a_system, a_small = (None, grid.lumped_small) if grid.hybrid else (system, small)
        momentum, force, gravity = grid.momentum, grid.force, grid.gravity
        with state.timer("solve"):
            v_values = con.values(t) if con.prescribed else None
            a_values = prescribed_acceleration(con, t, state.dt) if con.prescribed else None
        if state.force_modifiers or a_system is None or system is None:
            with state.timer("solve"):
                v = self._grid_solve(state, system, mass, momentum, v_values, "velocity",
                                     self._v_old, small)
            if state.force_modifiers:
                with state.timer("effects"):
                    if gravity is not None:
                        force = force + mass[:, None] * gravity[None, :]
                        gravity = None
                    force = self.force_modifiers.modify_force(force, v, mass, state.dt,
                                                              state.t, c)
            with state.timer("solve"):
                a = self._grid_solve(state, a_system, mass, force, a_values, "acceleration",
                                     self._a, a_small, gravity)
        else:  # consistent mass: both solves in one CG run
            with state.timer("solve"):
                a, v = self._consistent_solves(
                    state, system, mass, [(force, a_values, "acceleration"),
                                          (momentum, v_values, "velocity")],
                    [self._a, self._v_old])
        if system is not None:
            state.small_dofs_max = max(state.small_dofs_max, system.small_dofs)
        if reactions and con.any:
            with state.timer("solve"):
                if a_system is not None:
                    state.reactions = con.reactions(a_system.residual(a, force))
                else:  # the arrays are reused by the next stages
                    state.defer_reactions(con, mass.copy(), a.copy(), force.copy(), gravity)
        with state.timer("g2p"):
            self.kernels.rates(particles, a, v, self.fused, state.bodies[0][0], rk.x[slot],
                               rk.v[slot], rk.L, rk.stress[slot], rk.V[slot])
        if not self.fused:
            self._material_rates(state, particles, rk, slot)
        power = 0.0
        if self.gravity_work and self.recon is not None:  # mass is not the particles'
            power += self.kernels.gravity_work(particles.m, rk.x[slot], 1.0, self.gravity)
        elif self.gravity_work:
            power += self.kernels.gravity_work(mass, v, 1.0, self.gravity)
        if grid.work_forces is not None:  # sum_p f_p . dx_p/dt (the compiled loop's kernel)
            power += loads_power(np.arange(particles.n), grid.work_forces, rk.x[slot])
        for index, loads in grid.side_loads:
            power += loads_power(index, loads, rk.x[slot])
        return CompiledStageRates(slot, power)

    def _material_rates(self, state, particles, rk, slot):
        """Stress rates of small-strain materials other than the fused linear
        elasticity (their ``stress_rate``) and L F of finite-strain ones."""
        L, single = rk.L, len(state.bodies) == 1
        with state.timer("constitutive"):
            for material, index in state.bodies:
                if material.finite_strain:
                    if single:
                        self.kernels.kernel(deformation_rate)(L, particles.F, rk.F[slot],
                                                              self.kernels.nthreads)
                    else:
                        rk.F[slot][index] = L[index] @ particles.F[index]
                else:
                    sub = particles if single else particles.subset(index)
                    rk.stress[slot][index] = material.stress_rate(sub, L if single else L[index])

    def _advance(self, state, rates, weights, out):
        """out (dict of arrays) = y_n + dt sum_s w_s k_s; finite-strain
        bodies' stress and volume from F; raises for J <= 0 or V <= 0."""
        rk, p = self._rk, state.particles
        c = rk.weights
        c[:] = 0.0
        for k, w in zip(rates, weights):
            c[k.slot] += w * state.dt
        finite = rk.finite
        small = not finite or any(not m.finite_strain for m, _ in state.bodies)
        F = p.F if finite else rk.L
        F_out = out["F"] if finite else rk.L
        with state.timer("g2p"):
            combine = self.kernels.kernel(combine_stages)
            combine(c, p.x, p.u, p.v, p.stress, p.V, F, rk.x, rk.v, rk.stress, rk.V, rk.F, small,
                    finite, out["x"], out["u"], out["v"], out["stress"], out["V"], F_out,
                    self.kernels.nthreads)
        if finite and self.point_laws and len(state.bodies) == 1:
            self._law_stage(state, F_out, out["stress"], out["V"])
        elif finite:
            finite_strain_stage(state, F_out, out["stress"], out["V"])
        check_stage_volumes(out["V"])

    def _law_stage(self, state, F, stress, V):
        """sigma = law(F) and V = V0 det F of one finite-strain body with a
        compiled point law at the staged F (the constitutive kernel with
        dt = 0: A = I leaves F as it is); InvalidState at the first J <= 0."""
        material, p = state.bodies[0][0], state.particles
        flags = self._first_bad
        no_state = self.kernels.scratch("no_state", (p.n, 0))
        with state.timer("constitutive"):
            self.kernels.kernel(material_update)(
                material.point_update.address(), material.point_parameters(p.dim),
                self._no_index, True, self._rk.L, 0.0, True, stress, F, V, p.V0, no_state,
                stress, F, V, no_state, flags)
        hits = flags[flags >= 0]
        if hits.size:
            k = int(hits.min())
            raise InvalidState(f"J = det F <= 0 at particle {k} in a Runge-Kutta stage",
                               particle=k)

    def stage(self, state, rates, weights):
        """The stage particles y_n + dt sum_s w_s k_s (in reused arrays)."""
        stage = self._rk.stage
        self._advance(state, rates, weights, stage)
        return state.particles.replaced(**{k: a for k, a in stage.items()
                                           if a is not None})

    def combine(self, state, rates, weights):
        """The step's new state y_n + dt sum_s b_s k_s (in the executor's
        second set of particle arrays) and its external work
        dt sum_s b_s P_s."""
        p = state.particles
        new = self._new_particles(p)
        for name in ("stress", "V") + (("F",) if self._rk.finite else ()):
            if getattr(new, name) is getattr(p, name):  # not a buffer of this executor
                setattr(new, name, np.empty_like(getattr(p, name)))
        out = {k: getattr(new, k) for k in ("x", "u", "v", "stress", "V", "F")}
        self._advance(state, rates, weights, out)
        with state.timer("g2p"):
            for name in ("x", "v", "stress") + (("F",) if self._rk.finite else ()):
                a = out[name].reshape(p.n, -1)
                finite = np.isfinite(a).all(axis=1)
                if not finite.all():
                    k = int(np.flatnonzero(~finite)[0])
                    raise InvalidState(f"non-finite state (NaN or Inf) at particle {k}",
                                       particle=k)
            outside = 0 if not state.grid.inside(new.x).all() else -1
        work = state.dt * sum(w * k.power for k, w in zip(rates, weights))
        return CompiledRungeKuttaStep(new, work, outside)
