"""The state of a run: particles, time, step size, bound effects, timers."""
import math
import time

import numpy as np

from ..errors import InvalidState
from ..kernels import resolve_backend
from ..kernels.step_size import adaptive_step, finished_after_step, reached_end, time_after_step
from ..materials.compiled import max_point_wave_speed
from ..spline import SplineGrid
from .grid_system import Constraints, dof_adjacency
from .runge_kutta import check_staged
from ..reconstruct import RECONSTRUCTORS
from .timestep import (RECONSTRUCTION_EVERY, covered_parameters, covered_stiffness,
                       critical_time_step, fast_dof_weights, reconstruction_factor,
                       stable_time_step)
from .timing import PhaseTimer

__all__ = ["State", "prepare"]


class State:
    """Everything one step reads and writes (see :func:`prepare`).

    Attributes a user's own loop may read: ``particles`` (current), ``t``,
    ``step``, ``dt``, ``dt_crit``, ``timer``, ``reactions`` (last step's
    constraint reactions per effect), ``external_work``, ``removed``.
    """

    def __init__(self, scene, method, particles=None):
        self.scene = scene
        self.grid = scene.grid
        self.method = method
        self.backend = resolve_backend(method.backend)
        self.timer = PhaseTimer()
        self.particles = scene.particles() if particles is None else particles
        self.index = np.arange(self.particles.n)
        self.initial_count = self.particles.n
        self.small_dofs_max = 0
        self.t = 0.0
        self.step = 0
        self.removed = 0
        self.external_work = 0.0
        self._reactions = {}
        self._reaction_source = None
        self.warm = {}
        self.particle_acceleration = None
        self.materials = [b.material for b in scene.bodies]
        if method.scheme == "rk4":
            check_staged(self.materials, self.grid.dim)
        self.force_modifiers = [m for e in scene.effects for m in e.force_modifiers()]
        self.velocity_modifiers = [m for e in scene.effects for m in e.velocity_modifiers()]
        self.constraints = Constraints(self.grid, scene.effects)
        self.forces = []
        self.bodies = []
        self._bind_forces()
        self._bind_bodies()
        self._adjacency = None
        self._adaptive = None
        self._fast_dof_weights = None
        self._factor_step = None  # the step of the last re-estimate of the reconstruction factor
        solver = method.mass_solver
        if solver == "auto":
            solver = "direct" if self.grid.ndofs < 20000 else "cg"
        self.mass_solver = solver
        self._choose_time_step()

    # --------------------------------------------------------------- binding
    def _bind_forces(self):
        """The particle forces of the effects (timed as effects when there
        are any: a scene without forces never enters that phase)."""
        t0 = time.perf_counter()
        self.forces = [f for e in self.scene.effects for f in e.bind(self.particles, self.grid)]
        if self.forces:
            self.timer.add("effects", time.perf_counter() - t0)

    def _bind_bodies(self):
        if len(self.materials) == 1:  # all particles: no index array needed
            self.bodies = [(self.materials[0], slice(None))]
            return
        body = self.particles.body
        self.bodies = [(m, np.flatnonzero(body == b)) for b, m in enumerate(self.materials)]
        self.bodies = [(m, idx) for m, idx in self.bodies if idx.size] or \
            [(self.materials[0], np.arange(0))]

    def without_exits(self, particles):
        """``particles`` (the step's new state) minus those outside the grid:
        raises :class:`InvalidState` for ``on_exit="raise"`` (or when none
        would be left), else removes them, counts them, makes the survivors
        the current particles and rebinds the forces and bodies to them."""
        outside = ~self.grid.inside(particles.x)
        if not outside.any():
            return particles
        k = int(np.flatnonzero(outside)[0])
        if self.method.on_exit == "raise":
            raise InvalidState(
                f"particle {k} left the grid at {particles.x[k].tolist()} "
                f"({int(outside.sum())} outside); use Method(on_exit='remove') to drop them",
                particle=k)
        keep = ~outside
        if not keep.any():
            raise InvalidState("every particle has left the grid", particle=k)
        self.removed += int(outside.sum())
        self.index = self.index[keep]
        self.particle_acceleration = None
        self.particles = particles.subset(keep)
        self.rebind(keep)
        return self.particles

    def rebind(self, keep):
        """After particles were removed (``keep`` is the mask of survivors)."""
        for f in self.forces:
            f.rebind(keep)
        self._bind_bodies()

    @property
    def adjacency(self):
        """Dofs sharing a cell (for the tiny-mass merge), built on first use."""
        if self._adjacency is None and self.method.small_mass > 0:
            self._adjacency = dof_adjacency(self.grid)
        return self._adjacency

    # ------------------------------------------------------------ time step
    def guard_stiffness(self, stiffness, diagonal, lumped, limit):
        """The fast-dof guard's stiffness k_i from the particles' coverage
        sums (K_i, M_ii, m_i: :func:`skfem_mpm.solve.steps.particle_coverage`)
        on a spline grid (:func:`skfem_mpm.solve.timestep.covered_stiffness`,
        ``limit`` the guard's); K_i itself off spline grids."""
        if not isinstance(self.grid, SplineGrid):
            return stiffness
        w, mu, moving = self.fast_dof_guard_arrays()
        _, _, tail, floor = covered_parameters(self.grid, self.method.reconstruction)
        return covered_stiffness(stiffness, diagonal, lumped, w, mu, moving.astype(np.float64),
                                 tail, floor, limit, self.grid.degree, self.grid.basis_per_axis)

    def fast_dof_guard_arrays(self):
        """(w, mu, moving) of :meth:`guard_stiffness` on a spline grid: the
        full-grid weights and mass ratios of
        :func:`skfem_mpm.solve.timestep.fast_dof_weights`, and the dofs not
        constrained in every component."""
        if self._fast_dof_weights is None:
            # a dof constrained in every component does not move: never fast
            moving = ~self.constraints.mask.all(axis=1)
            self._fast_dof_weights = (*fast_dof_weights(self.grid), moving)
        return self._fast_dof_weights

    @property
    def adaptive(self):
        """The step size follows the current wave speed (no fixed dt and a
        finite-strain material without a wave speed bound); fixed for the run."""
        if self._adaptive is None:
            self._adaptive = self.method.dt is None and any(
                m.finite_strain and bound is None for m, bound in self._bounds())
        return self._adaptive

    def _bounds(self):
        """(material, its wave_speed_bound of its particles) per body."""
        p = self.particles
        return [(m, m.wave_speed_bound(p if len(self.bodies) == 1 else p.subset(idx)))
                for m, idx in self.bodies]

    def wave_speed(self):
        """The largest wave speed of the bodies: a finite-strain material's
        bound where it has one (the step it sets holds for the whole run),
        else its compiled point wave speed where it declares one (the one
        the compiled loop computes: :func:`~skfem_mpm.materials.compiled.max_point_wave_speed`),
        else its ``wave_speed``."""
        p = self.particles
        speeds = [bound if m.finite_strain and bound is not None else
                  _current_wave_speed(m, p if len(self.bodies) == 1 else p.subset(idx))
                  for (m, bound), (_, idx) in zip(self._bounds(), self.bodies)]
        return max(speeds)

    def _choose_time_step(self):
        m = self.method
        self.wave_speed_now = self.wave_speed()
        self.dt_crit = critical_time_step(self.grid, self.wave_speed_now, m.mass, m.scheme)
        self._reconstruction_vectors = None
        self.dt_crit *= self.reconstruction_factor()
        t_end = self.scene.t_end
        dt = stable_time_step(m, self.dt_crit,
                              f" (degree {self.grid.degree}, {m.mass} mass)")
        check_step_count(dt, t_end, self.wave_speed_now, self.dt_crit)
        if self.adaptive:
            self.dt = min(dt, t_end)
            self.n_steps = None
        else:
            self.n_steps = max(1, math.ceil(t_end / dt * (1 - 1e-12)))
            self.dt = t_end / self.n_steps

    def reconstruction_factor(self):
        """The factor on dt_crit of a reconstructed 2D method
        (:func:`skfem_mpm.solve.timestep.reconstruction_factor`), estimated
        at the start and, in adaptive runs, every RECONSTRUCTION_EVERY steps
        from the previous power-iteration vectors; 1 otherwise."""
        m = self.method
        if m.reconstruction == "none" or self.grid.dim < 2:
            return 1.0
        if getattr(self, "_reconstruction_factor", None) is None:
            recon = RECONSTRUCTORS[m.reconstruction] if isinstance(m.reconstruction, str) \
                else m.reconstruction
            with self.timer("reconstruct"):
                self._reconstruction_factor, self._reconstruction_vectors = \
                    reconstruction_factor(self.grid, self.particles, recon,
                                          m.reconstruction_options,
                                          self._reconstruction_vectors)
        return self._reconstruction_factor

    def step_reconstruction_factor(self):
        """The reconstruction factor of the coming step of an adaptive run:
        re-estimated at each step that is a multiple of RECONSTRUCTION_EVERY
        (once: a second call at the same step, the compiled loop's and then
        the executor's, gives the same), else the last estimate."""
        if self.step % RECONSTRUCTION_EVERY == 0 and self._factor_step != self.step:
            self._reconstruction_factor = None
            self._factor_step = self.step
        return self.reconstruction_factor()

    def next_step_size(self):
        """Set ``dt`` for the coming step (finite strain: from the current
        wave speed; the last step ends exactly at t_end); the rule is
        :mod:`skfem_mpm.kernels.step_size`, which the compiled loop runs too."""
        if not self.adaptive:
            return self.dt
        self.wave_speed_now = self.wave_speed()
        self.dt_crit = critical_time_step(self.grid, self.wave_speed_now, self.method.mass,
                                          self.method.scheme)
        self.dt_crit *= self.step_reconstruction_factor()
        self.dt = adaptive_step(self.method.cfl, self.dt_crit, self.t, self.scene.t_end)
        return self.dt

    def advance(self):
        """The step is done: count it and move the time on."""
        self.step += 1
        self.t = self.t_next()

    def t_next(self):
        if self.adaptive:
            return time_after_step(self.t, self.dt, self.scene.t_end)
        return self.time_at(self.step)

    def time_at(self, step):
        """The time after ``step`` steps of a fixed dt: step dt, the end
        time exactly after the last (the compiled loop's ``_advance``
        computes the same)."""
        return step * self.dt if step < self.n_steps else self.scene.t_end

    def finished_after_step(self):
        return finished_after_step(self.t, self.dt, self.scene.t_end)

    @property
    def done(self):
        if self.adaptive:
            return reached_end(self.t, self.scene.t_end)
        return self.step >= self.n_steps

    # ------------------------------------------------------------- reactions
    @property
    def reactions(self):
        """{constraint effect: total reaction force (dim,)} of the last step."""
        if self._reaction_source is not None:
            self._reactions = self._reaction_source()
            self._reaction_source = None
        for e in self.scene.effects:  # walls: contact forces, not constraints
            self._reactions.update(e.reactions())
        return self._reactions

    @reactions.setter
    def reactions(self, value):
        self._reactions = value
        self._reaction_source = None

    def defer_reactions(self, constraints, mass, a, force, gravity):
        """Remember what the reactions are computed from (lumped mass); they
        are evaluated only when read (at saves), before the arrays change."""
        self.defer_reaction_rule(lambda: constraints.reactions_at(mass, a, force, gravity))

    def defer_reaction_rule(self, rule):
        """The reactions are ``rule()`` ({effect: force}), evaluated only
        when read (at saves; the compiled loop's steps so leave them to
        the save, as with lumped mass)."""
        self._reaction_source = rule

    # --------------------------------------------------------------- output
    def reported_velocity(self):
        """Particle velocities at the current time (the central-difference
        scheme stores v at half steps and adds dt/2 of the last acceleration)."""
        v = self.particles.v
        if self.method.scheme == "cd" and self.particle_acceleration is not None:
            return v + 0.5 * self.dt * self.particle_acceleration
        return v

    def energies(self):
        """(kinetic, strain) energy, in blocks of particles (bounded memory)."""
        p = self.particles
        v = self.reported_velocity()
        kinetic = 0.5 * float(np.einsum("i,ij,ij->", p.m, v, v))
        strain = 0.0
        block = 1 << 15
        for material, idx in self.bodies:
            sub = p if len(self.bodies) == 1 else p.subset(idx)
            for start in range(0, sub.n, block):
                strain += material.strain_energy(sub.subset(slice(start, start + block))
                                                 if sub.n > block else sub)
        return kinetic, strain


def _current_wave_speed(material, particles):
    """``material``'s wave speed of ``particles``: its compiled point wave
    speed where it declares one, else its ``wave_speed``."""
    if material.point_wave_speed is not None:
        return max_point_wave_speed(material, particles)
    return material.wave_speed(particles)


MAX_STEPS = 10 ** 9
"""The most steps a run may take: more is a mistake of units or values (a
volume of 1e300 or E = 1e300 would ask for ~1e148 steps)."""


def check_step_count(dt, t_end, wave_speed, dt_crit):
    """ValueError when the time step is not a finite positive number or the
    run would take more than MAX_STEPS steps, naming the wave speed and
    dt_crit it came from."""
    why = (f"(P-wave speed c = {wave_speed:.6g} from the materials' E, nu and the "
           f"particles' density m / V; dt_crit = {dt_crit:.6g})")
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"the time step dt = {dt!r} is not a finite positive number {why}: "
                         f"check the particle masses, volumes and the material's moduli")
    if t_end / dt > MAX_STEPS:
        raise ValueError(f"t_end = {t_end:.6g} with dt = {dt:.6g} would take "
                         f"{t_end / dt:.3g} steps, more than {MAX_STEPS:.0e} {why}: check "
                         f"the units of t_end, the moduli and the density")


def prepare(scene, method):
    """A new State for ``scene`` (which is never modified) and ``method``;
    raises ValueError for a time step above the stable limit."""
    return State(scene, method)
