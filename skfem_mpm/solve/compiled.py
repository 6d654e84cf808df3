"""The compiled executor: the operations of :mod:`skfem_mpm.solve.schemes`
on the fused numba kernels of :mod:`skfem_mpm.kernels.mpm` (spline grids).

The scheme calls the same operations as on the reference executor
(:mod:`skfem_mpm.solve.reference`, which the tests compare this one with);
this executor fuses them into few kernels:

    particles_to_grid            p2g kernel (mass, momentum, force; locate and
                                 basis fused) and, for consistent mass, the
                                 stencil assembly
    solve_grid (+ end velocity)  one grid kernel for lumped USL/CD (a and
                                 v = v^n + c dt a), else the grid system
    update_particle_velocities   deferred: fused into the next kernel
    project_velocity (MUSL)      g2p2g kernel (v_p^new and its momentum), then
                                 the velocity solve
    move_particles               g2p kernel (velocity unless already updated,
                                 positions, L; the stress of linear
                                 elasticity fused)
    update_stress                the materials' update (nothing when fused)

Consistent mass: a kernel assembles M into a fixed stencil pattern (and the
per-dof stiffness weights of the fast-dof guard; with a reconstruction the
guard's sums are the particles', Kernels.particle_coverage, whose pass is
skipped while :func:`skfem_mpm.kernels.coverage_skip.coverage_holds` shows it
cannot change the lumping); :class:`StencilSystem`
solves it by conjugate gradients, or the grid system of
:mod:`skfem_mpm.solve.grid_system` by sparse LU. Hybrid mass: the same
system solves the velocities (no fast-dof guard), the lumped solve the
acceleration.

Reconstruction (:mod:`skfem_mpm.solve.compiled_reconstruct`): the Gauss
rule and the reconstruction (timed as ``reconstruct``), then the p2g kernel
and the stencil assembly with the Gauss points as quadrature particles; the
MUSL re-projection reconstructs the updated momentum with the same rule.
``compiled_executor_applies`` names what stays on the reference executor.

Gravity costs one grid operation (g times the nodal mass); other particle
forces enter the p2g kernel as one array. The kernels write the new state
into a second set of particle arrays; it becomes current only at ``commit``
after the step's checks pass, so a failed step leaves the last good state
untouched. The p2g kernel's time is reported under ``p2g`` (it fuses
locate, basis and p2g), the g2p kernel's under ``g2p`` (locate, basis, g2p
and, for linear elasticity, constitutive).
"""
import numpy as np

from ..effects import SurfaceTraction
from ..errors import InvalidState
from ..kernels.bbar import average_dilatation
from ..kernels.constitutive import material_update
from ..kernels.records import grid_record
from ..kernels import serial
from ..kernels.mpm import Kernels, covered_stiffness, fast_row_fractions
from ..kernels.pages import lazy_zeros
from ..kernels.step_size import guard_limit
from ..kernels.traction import loads_power, side_faces
from ..materials import LinearElastic
from ..materials.state import PackedState, state_layout
from ..spline import SplineGrid
from . import steps
from .compiled_reconstruct import CompiledReconstruction, QuadraturePoints, unsupported
from .compiled_modifiers import CompiledModifiers
from .compiled_runge_kutta import CompiledRungeKutta
from .grid_system import GridSystem
from .stencil_system import StencilSystem
from .timestep import covered_parameters, coverage_bound, fast_dof_limit, lumping_fraction

__all__ = ["compiled_executor_applies", "CompiledExecutor", "side_traction"]


def side_traction(force):
    """Whether the particle force ``force`` is a traction on a side of the
    body with tau(t) (not tau(x, t)): the compiled paths compute its faces,
    grid force and work with kernels (:mod:`skfem_mpm.kernels.traction`)."""
    return isinstance(force, SurfaceTraction) and not force.effect._takes_x


def compiled_executor_applies(state):
    """(True, '') or (False, the reason the reference executor is used)."""
    m = state.method
    if state.backend != "numba":
        return False, "backend numpy"
    if not isinstance(state.grid, SplineGrid):
        return False, "not a SplineGrid"
    if m.reconstruction != "none":
        why = unsupported(m, state.grid.dim)
        if why is not None:
            return False, why
    if m.scheme not in ("usl", "cd", "musl", "rk4"):
        return False, f"scheme {m.scheme}"
    return True, ""


def one_linear_elastic(bodies):
    """Whether the bodies are one linear elastic material: each body's
    material a LinearElastic with the same E and nu (a scene of several
    bodies of one material, e.g. colliding disks), so that its stress update
    can be fused into the transfer kernels for every particle at once."""
    first = bodies[0][0]
    return all(type(m) is LinearElastic and (m.E, m.nu) == (first.E, first.nu)
               for m, _ in bodies)


class CompiledGrid:
    """What one compiled step keeps on the grid (and the new particle state)."""

    def __init__(self, mass, momentum, force, stencil, work_forces, grid_force):
        self.mass, self.momentum, self.force = mass, momentum, force
        self.stencil = stencil          # (M stencil, stiffness weights) or None
        self.work_forces = work_forces  # particle forces whose work is counted
        self.grid_force = grid_force    # grid force of side tractions
        self.side_loads = []            # (index, loads) of the side tractions (their work)
        self.system = None              # the consistent-mass system
        self.hybrid = False             # the acceleration is solved with lumped mass
        self.lumped_small = 0           # hybrid: tiny-mass dofs of the lumped solve
        self.small = 0                  # tiny-mass dofs (the general solve merges them)
        self.gravity = None             # gravity still to add as an acceleration
        self.prepared = False
        self.acceleration = None
        self.velocity = None            # grid velocity that moves the particles
        self.velocity_factor = 1.0
        self.keep_acceleration = False
        self.particle_velocities_done = False
        self.new = None                 # the new particle state (Particles)
        self.work = None                # external work when a scheme computes its own
        self.L = None
        self.outside = -1               # first particle outside the grid, or -1
        self.projection = None          # reconstruction: what the MUSL re-projection reuses
        self.coverage = None            # reconstruction: the particles' guard sums (3, dofs)


class CompiledExecutor(CompiledRungeKutta):
    """Executes the scheme operations of one simulation on the compiled kernels
    (the Runge-Kutta ones: :mod:`skfem_mpm.solve.compiled_runge_kutta`)."""

    path = "fast"

    def __init__(self, state):
        # a run below SERIAL_BELOW particles calls serial kernels only
        self.kernels = Kernels(state.grid, parallel=state.particles.n >= serial.SERIAL_BELOW)
        self.gravity = np.zeros(state.grid.dim)
        self.gravity_work = False
        self.other_forces = []
        for f in state.forces:  # uniform accelerations act on the grid: m_i g
            if f.acceleration is not None:
                self.gravity = self.gravity + f.acceleration
                self.gravity_work = True
            else:
                self.other_forces.append(f)
        # damping, walls: their compiled rules (kernels.grid_modifiers)
        self.force_modifiers = CompiledModifiers(state.force_modifiers, state.grid)
        self.velocity_modifiers = CompiledModifiers(state.velocity_modifiers, state.grid)
        self.fused = one_linear_elastic(state.bodies)
        # every material has a compiled point law: the constitutive kernel runs them
        self.point_laws = not self.fused and all(
            material.point_update is not None for material, _ in state.bodies)
        self.finite = state.scene.finite_strain
        timer = state.timer
        timer.note_fused("p2g", ("locate", "basis", "p2g"))
        timer.note_fused("g2p", ("locate", "basis", "g2p")
                         + (("constitutive",) if self.fused else ()))
        self._spare = None
        self._owned_F = []  # F arrays the constitutive kernel may write
        self._owned = set()
        self._acc = None
        self._guard_arrays = None  # the fast-dof guard's (w, mu, moving, rule scalars)
        self._coverage_bound = None  # timestep.coverage_bound of the grid (the guard's skip)
        nd, dim = state.grid.ndofs, state.grid.dim
        self._v_old = np.empty((nd, dim))
        # the grid velocity and acceleration: the one-pass USL grid step
        # writes them near the particles only (Transfers.occupied)
        self._v_new = lazy_zeros((nd, dim))
        self._a = lazy_zeros((nd, dim))
        self._no_gravity = np.zeros(dim)
        self._no_index = np.zeros(0, dtype=np.int64)
        self._first_bad = np.full(self.kernels.nthreads, -1, dtype=np.int64)
        self._state = {}  # id(material) -> its PackedState (None: no state)
        self._cell_axes = {}  # id(grid) -> its axes record (B-bar's cells)
        self.recon = None
        if state.method.reconstruction != "none":
            self.recon = CompiledReconstruction(state, self.kernels)
            self.path = f"fast (reconstruction {self.recon.name})"

    def grid_arrays(self):
        """The grid arrays of a step, {name: array}: the transfers' (mass,
        momentum, force, momentum_new) and the solves' (a, v_grid, v_old).
        The compiled loop steps in these (it and the executor never step
        at once), so a run holds one set."""
        mass, momentum, force, projected = self.kernels.transfers.grid_arrays()
        return dict(mass=mass, momentum=momentum, force=force, momentum_new=projected,
                    a=self._a, v_grid=self._v_new, v_old=self._v_old)

    # ---------------------------------------------------------------- buffers
    WRITTEN = ("x", "v", "u", "stress", "V")

    def _new_particles(self, p):
        """The arrays the kernels write the new state into: the state before
        the current one, if this stepper allocated its arrays (the scene's
        own arrays are never written), else fresh ones."""
        spare = self._spare
        owned = spare is not None and spare.n == p.n and \
            all(id(getattr(spare, k)) in self._owned for k in self.WRITTEN)
        if not owned:
            spare = p.replaced()
            for k in self.WRITTEN:
                a = np.empty_like(getattr(p, k))
                setattr(spare, k, a)
                self._owned.add(id(a))
        for name in ("m", "X", "V0", "body", "F", "state"):
            setattr(spare, name, getattr(p, name))
        if self.point_laws and self.finite:  # F is written by the constitutive kernel
            free = [F for F in self._owned_F if F is not p.F and F.shape == p.F.shape]
            if not free:
                free = [np.empty_like(p.F)]
                self._owned_F = [F for F in self._owned_F if F is p.F] + free
            spare.F = free[0]
        if not (self.fused or self.point_laws):
            spare.stress, spare.V = p.stress, p.V  # replaced by the material update
        return spare

    def hand_out(self, particles):
        """The user may keep ``particles`` (a callback receives them): their
        arrays are never written again (the kernels take fresh ones)."""
        for k in self.WRITTEN:
            self._owned.discard(id(getattr(particles, k)))
        self._owned_F = [F for F in self._owned_F if F is not particles.F]
        for packed in self._state.values():  # the material state's double buffers
            if packed is not None:
                packed.release(particles.state)
        if self._spare is particles:
            self._spare = None

    # ------------------------------------------------------------------- step
    def external(self, state, particles=None, t=None):
        """Particle forces other than gravity (effects phase), the grid force
        of side tractions, and the particle forces whose work is counted, of
        ``particles`` at time ``t`` (default: the state's)."""
        p = state.particles if particles is None else particles
        t = state.t if t is None else t
        fext, grid_force, work_forces = None, None, None
        self._side_loads = []
        if self.other_forces:
            with state.timer("effects"):
                for f in self.other_forces:
                    if side_traction(f):
                        g = self._side_traction_force(state, f, p, t)
                        grid_force = g if grid_force is None else grid_force + g
                        continue
                    term = f.forces(p, t)
                    work_forces = term if work_forces is None else work_forces + term
                    g = f.grid_forces(p, t, state.grid)
                    if g is not None:
                        grid_force = g if grid_force is None else grid_force + g
                    else:
                        fext = term if fext is None else fext + term
        return fext, grid_force, work_forces

    def _side_traction_force(self, state, f, p, t):
        """The grid force of the side traction ``f`` (a SurfaceTraction of
        tau(t)) on the particles ``p`` at time t: the p2g kernel's external
        force at its faces (:mod:`skfem_mpm.kernels.traction`); its loads
        are kept for the work of the step. Call before the particles' p2g:
        the kernels' grid buffers are shared."""
        loads = np.ascontiguousarray(f.loads(p, t))
        k, dim = loads.shape
        faces = np.empty((k, dim))
        bounds = np.array(state.grid.bounds, dtype=np.float64)
        j = side_faces(p.x, p.V, p.V0, f.index, f.size, f.axis, float(f.sign), bounds, faces)
        if j >= 0:
            i = int(f.index[j])
            raise InvalidState(f"the loaded face of particle {i} lies outside the grid; "
                               f"extend the grid beyond the body", particle=i)
        self._side_loads.append((f.index, loads))
        zeros = np.zeros(k)
        at_faces = QuadraturePoints(faces, np.zeros((k, dim)), zeros, zeros,
                                    np.zeros((k, dim, dim)))
        return self.kernels.p2g(at_faces, loads)[2].copy()

    def _small_dofs(self, state, mass):
        """Number of tiny-mass dofs this step (the reference merge takes over
        when there are any)."""
        if state.method.small_mass <= 0:
            return 0
        _, count = self.kernels.small_mass(mass, state.method.small_mass)
        state.small_dofs_max = max(state.small_dofs_max, count)
        return count

    def _reference_solve(self, state, mass, rhs, values, kind, gravity=None):
        full = rhs if gravity is None else rhs + mass[:, None] * gravity[None, :]
        system = GridSystem(mass, state.constraints, None, state.adjacency,
                            state.method.small_mass)
        return system.solve(full, np.zeros_like(rhs) if values is None else values, kind)

    def solve(self, state, mass, rhs, values, kind, out, small, gravity=None):
        """Lumped M x = rhs (+ gravity as an acceleration on free dofs) with
        the constraints, into ``out``; with tiny-mass dofs, the compiled
        merge (the reference merge when a merged row outgrows the kernel's)."""
        g = self._no_gravity if gravity is None else gravity
        if small:
            if self.kernels.merged_solve(mass, rhs, g, state.constraints.mask, values,
                                         state.method.small_mass, out) < 0:
                out[:] = self._reference_solve(state, mass, rhs, values, kind, gravity)
            return out
        return self.kernels.solve(mass, rhs, g, state.constraints.mask, values, out)

    # "auto" is conjugate gradients on the stencil (deterministic: the
    # choice never depends on timing, so identical runs and restarts agree
    # bit for bit). With the Kronecker preconditioner and its fringe
    # correction the CG beat a fresh sparse LU per step on every bench
    # scene measured (see the README's speed paragraph); "direct" forces LU.

    def _use_cg(self, state):
        return state.method.mass_solver != "direct"

    def _grid_solve(self, state, system, mass, rhs, values, kind, out, small, gravity=None):
        """M x = rhs: the consistent system when there is one, else lumped."""
        if system is None:
            return self.solve(state, mass, rhs, values, kind, out, small, gravity)
        return self._consistent_solves(state, system, mass, [(rhs, values, kind)], [out])[0]

    def _consistent_solves(self, state, system, mass, problems, outs):
        """Consistent M x = rhs for each (rhs, values or None, kind) into
        ``outs``; a stencil system solves them in one CG run."""
        if isinstance(system, StencilSystem):
            xs = system.solve_many(problems)
            for (_, _, kind), x in zip(problems, xs):
                system.keep(kind, x)  # x is the system's own new array
        else:
            problems = [(rhs, np.zeros_like(rhs) if values is None else values, kind)
                        for rhs, values, kind in problems]
            xs = [system.solve(rhs, values, kind) for rhs, values, kind in problems]
            if state.method.mass_solver == "cg":
                for (_, _, kind), x in zip(problems, xs):
                    system.remember(kind, x)
        for out, x in zip(outs, xs):
            out[:] = x
        return outs

    def _buffers(self, p):
        if self._acc is None or self._acc.shape[0] != p.n:
            self._acc = np.empty((p.n, p.dim))
            self._L = np.empty((p.n, p.dim, p.dim)) if not self.fused else np.empty((1, 1, 1))
        return self._acc, self._L

    def _guard_limit(self, state):
        """The fast-dof guard's limit of this step (None: no guard; hybrid
        mass has none, it guards a consistent-mass acceleration); makes the
        run's guard arrays (w, mu, moving as 1.0 / 0.0, the rule's scalars)
        at the first call."""
        guard = 0.0 if state.method.mass == "hybrid" else state.method.frequency_guard
        if not guard > 0:
            return None
        if self._guard_arrays is None:
            weights, ratios, moving = state.fast_dof_guard_arrays()
            self._guard_arrays = (weights, ratios, moving.astype(np.float64),
                                  *covered_parameters(state.grid, state.method.reconstruction))
        return guard_limit(guard * fast_dof_limit(state.grid.degree, state.method.scheme),
                           state.dt, state.wave_speed_now)

    def _consistent_system(self, state, mass, stencil, K, small, coverage=None):
        """The step's consistent-mass system: compiled stencil CG (with
        tiny-mass dofs, ``small`` > 0, on the merged system), or the general
        grid system (sparse LU with ``mass_solver="direct"``, and when a
        merged row outgrows the compiled merge's lists); ``small`` counts
        the tiny-mass dofs. No fast-dof guard for hybrid mass (it guards a
        consistent-mass acceleration). The guard's coverage sums are the
        particles' (K, D, m): ``coverage`` (3, dofs) with a reconstruction
        (Kernels.particle_coverage), else ``K``, the stencil's diagonal and
        ``mass``, which are the particles' own."""
        limit = self._guard_limit(state)
        if limit is not None:
            guarded = self.kernels.scratch("guard_K", K.size)
            if coverage is None:
                diagonal = self.kernels.scratch("guard_diagonal", mass.size)
                diagonal[:] = stencil[:, (stencil.shape[1] - 1) // 2]
                coverage = (K, diagonal, mass)
            K, diagonal = guarded, coverage[1]
            p, nbx, nby, _ = self.kernels.stencil_geometry
            self.kernels.kernel(covered_stiffness)(coverage[0], diagonal, coverage[2],
                                                   *self._guard_arrays, limit, p, nbx, nby,
                                                   self.kernels.scratch("guard_near",
                                                                        (2, K.size)), guarded)
        fast_rows = None if limit is None else (
            lambda _: lumping_fraction(K / (limit * np.maximum(diagonal, 1e-300))))
        if self._use_cg(state):
            fast = self.kernels.scratch("fast_rows", mass.size)
            if limit is not None:  # fast_rows of the dofs with mass, in one kernel
                self.kernels.kernel(fast_row_fractions)(K, diagonal, mass, limit, fast)
            else:
                fast[:] = 0.0
            system = StencilSystem(self.kernels, stencil, mass, state.constraints, fast,
                                   state.warm, small_mass=state.method.small_mass if small else 0.0,
                                   by_component=len(state.bodies) > 1)
            if system.mergeable:
                return system
        M = self.kernels.stencil_csr(stencil)
        solver = "cg" if state.method.mass_solver == "cg" else "direct"
        return GridSystem(mass, state.constraints, M, state.adjacency, state.method.small_mass,
                          solver, state.warm, fast_rows=fast_rows)

    # ------------------------------------------------------------ operations
    def particles_to_grid(self, state, particles=None, t=None):
        """Mass, momentum and forces of ``particles`` at time ``t`` (default:
        the state's; a Runge-Kutta stage passes its own)."""
        p = state.particles if particles is None else particles
        k = self.kernels
        if self.recon is not None:
            return self._reconstructed_to_grid(state, p, t)
        fext, grid_force, work_forces = self.external(state, p, t)
        with state.timer("p2g"):
            mass, momentum, force = k.p2g(p, fext)
        stencil = None
        if state.method.needs_consistent_mass:
            with state.timer("mass_matrix"):
                stencil = k.consistent_stencil(p)
        grid = CompiledGrid(mass, momentum, force, stencil, work_forces, grid_force)
        grid.side_loads = self._side_loads
        return grid

    def _reconstructed_to_grid(self, state, p, t=None):
        """Mass, momentum, force (and consistent mass) integrated with Gauss
        quadrature of the reconstructed particle fields, as the reference
        does it: volume forces (other than uniform accelerations, which act
        on the grid as m_i g) are reconstructed as densities; side tractions
        give their grid force, other surface loads N^T f_p at the particles."""
        t = state.t if t is None else t
        volume, surface, grid_force, work_forces = None, None, None, None
        self._side_loads = []
        if self.other_forces:
            with state.timer("effects"):
                for f in self.other_forces:
                    if side_traction(f):
                        g = self._side_traction_force(state, f, p, t)
                        grid_force = g if grid_force is None else grid_force + g
                        continue
                    term = f.forces(p, t)
                    work_forces = term if work_forces is None else work_forces + term
                    if not f.surface:
                        volume = term if volume is None else volume + term
                        continue
                    g = f.grid_forces(p, t, state.grid)
                    if g is None:
                        surface = term if surface is None else surface + term
                    else:
                        grid_force = g if grid_force is None else grid_force + g
            if surface is not None:  # N^T f_p: p2g of particles that carry only f_p
                zero = np.zeros(p.n)
                loads = p.replaced(m=zero, V=zero, stress=np.zeros_like(p.stress))
                with state.timer("p2g"):
                    g = self.kernels.p2g(loads, surface)[2].copy()
                grid_force = g if grid_force is None else grid_force + g
        mass, momentum, force, stencil, projection = self.recon.to_grid(state, p, volume)
        grid = CompiledGrid(mass, momentum, force, stencil, work_forces, grid_force)
        limit = None if stencil is None else self._guard_limit(state)
        if limit is not None:  # the guard's coverage: the particles' (a pass when it may
            with state.timer("mass_matrix"):  # change the lumping: coverage_holds)
                if self._coverage_bound is None:
                    self._coverage_bound = coverage_bound(state.grid)
                grid.coverage = self.kernels.particle_coverage(
                    p, (self._coverage_bound, *self._guard_arrays, limit))
        grid.side_loads = self._side_loads
        grid.projection = projection
        return grid

    def _prepare(self, state, grid):
        """The step's grid system (consistent mass), tiny-mass count and
        gravity: a grid acceleration on lumped free dofs, a force m g with
        consistent mass (timed as solve)."""
        if grid.prepared:
            return
        grid.prepared = True
        gravity = self.gravity if self.gravity_work else None
        with state.timer("solve"):
            if grid.grid_force is not None:
                grid.force += grid.grid_force
                self.kernels.transfers.occupy_all()  # nonzero beyond the particles' nodes
            if grid.stencil is not None:
                small = self._small_dofs(state, grid.mass)
                grid.system = self._consistent_system(state, grid.mass, *grid.stencil, small,
                                                      grid.coverage)
                grid.small = True  # solves go through the system
                grid.hybrid = state.method.mass == "hybrid"
                grid.lumped_small = small
                if gravity is not None:
                    grid.force += grid.mass[:, None] * gravity[None, :]
                    gravity = None
            else:
                grid.small = self._small_dofs(state, grid.mass)
        grid.gravity = gravity

    def solve_velocity(self, state, grid):
        raise NotImplementedError("the compiled executor has no USF step")

    def solve_grid(self, state, grid, end_velocity=None):
        self._prepare(state, grid)
        k, c, dt = self.kernels, state.constraints, state.dt
        system, mass, small = grid.system, grid.mass, grid.small
        # the acceleration's system and tiny-mass count (hybrid: lumped)
        a_system, a_small = (None, grid.lumped_small) if grid.hybrid else (system, small)
        momentum, force, gravity = grid.momentum, grid.force, grid.gravity
        with state.timer("solve"):
            t_values = c.values(state.t) if c.prescribed else None
            a_values = (c.values(state.t + dt) - t_values) / dt if c.prescribed else None
        v_old = None
        if state.force_modifiers:
            with state.timer("effects"):
                v_old = self._grid_solve(state, system, mass, momentum, t_values, "velocity",
                                         self._v_old, small)
                if gravity is not None:
                    force = force + mass[:, None] * gravity[None, :]
                    gravity = None
                force = self.force_modifiers.modify_force(force, v_old, mass, dt, state.t, 0.0)
        factor = end_velocity
        v_grid = None
        with state.timer("solve"):
            if factor is not None and not small and not state.force_modifiers:
                transfers = k.transfers
                k.usl_grid(mass, momentum, force, self._no_gravity if gravity is None
                           else gravity, c.mask, t_values, a_values, factor * dt,
                           self._a, self._v_new,
                           transfers.occupied if mass is transfers.mass else None)
                a, v_grid = self._a, self._v_new
            elif factor is not None and a_system is not None and v_old is None:
                a, v_old = self._consistent_solves(
                    state, system, mass, [(force, a_values, "acceleration"),
                                          (momentum, t_values, "velocity")],
                    [self._a, self._v_old])
                v_grid = self._v_new
                np.multiply(a, factor * dt, out=v_grid)
                v_grid += v_old
                system.remember("velocity", v_grid)  # see steps.remember_end_velocity
            else:
                a = self._grid_solve(state, a_system, mass, force, a_values, "acceleration",
                                     self._a, a_small, gravity)
                if factor is not None:
                    if v_old is None:
                        v_old = self._grid_solve(state, system, mass, momentum, t_values,
                                                 "velocity", self._v_old, small)
                    v_grid = self._v_new
                    np.multiply(a, factor * dt, out=v_grid)
                    v_grid += v_old
                    if system is not None:
                        system.remember("velocity", v_grid)
            if c.any:
                if a_system is not None:
                    state.reactions = c.reactions(a_system.residual(a, force))
                else:
                    state.defer_reactions(c, mass, a, force, gravity)
        grid.force, grid.gravity = force, gravity
        grid.acceleration, grid.velocity = a, v_grid
        return a

    def update_particle_velocities(self, state, grid, velocity_factor=1.0,
                                   keep_acceleration=False):
        """Deferred: the next kernel (g2p2g or g2p) applies it."""
        grid.velocity_factor = velocity_factor
        grid.keep_acceleration = keep_acceleration

    def project_velocity(self, state, grid):
        p, dt, c = state.particles, state.dt, state.constraints
        grid.new = self._new_particles(p)
        with state.timer("g2p"):
            momentum_new = self.kernels.g2p2g(p, grid.acceleration, grid.velocity_factor * dt,
                                              grid.new.v)
        grid.particle_velocities_done = True
        if self.recon is not None:
            momentum_new = self.recon.project(state, p, grid.new.v, grid.projection)
        with state.timer("solve"):
            if grid.system is not None:  # see steps.project_velocity
                grid.system.shift_guess("velocity", dt * grid.acceleration)
            grid.velocity = self._grid_solve(state, grid.system, grid.mass, momentum_new,
                                             c.values(state.t + dt) if c.prescribed else None,
                                             "velocity", self._v_new, grid.small)
            if self.velocity_modifiers:  # walls
                grid.velocity = self.velocity_modifiers.modify_velocity(grid.velocity, grid.mass)

    def move_particles(self, state, grid):
        p, dt = state.particles, state.dt
        if grid.new is None:
            grid.new = self._new_particles(p)
        acc, L_out = self._buffers(p)
        material = state.bodies[0][0]
        with state.timer("g2p"):
            bad, out, neg = self.kernels.g2p(
                p, grid.acceleration, grid.velocity, dt, grid.velocity_factor,
                not grid.particle_velocities_done, self.fused, material, grid.new, L_out,
                acc if grid.keep_acceleration else None)
        if neg >= 0:
            raise InvalidState(f"J = det(I + dt L) <= 0 at particle {neg}", particle=neg)
        if bad >= 0:
            raise InvalidState(f"non-finite state (NaN or Inf) at particle {bad}", particle=bad)
        grid.L, grid.outside = L_out, out

    def update_stress(self, state, grid, velocity=None):
        """Linear elasticity alone: already done in the g2p kernel; materials
        with compiled point laws: the constitutive kernel per body; others:
        their NumPy ``update``."""
        if velocity is not None:
            raise NotImplementedError("the compiled executor has no USF step")
        if self.fused:
            return
        p, new = state.particles, grid.new
        if not self.point_laws:
            with state.timer("constitutive"):
                new.stress, new.V, new.F, new_state = steps.material_updates(state, grid.L, p)
            if new_state is not None:
                new.state = new_state
            return
        with state.timer("constitutive"):
            flags = self._first_bad
            bad = -1
            no_state = self.kernels.scratch("no_state", (p.n, 0))
            F = p.F if self.finite else grid.L  # not read for small strain
            F_out = new.F if self.finite else grid.L
            written = []
            for material, index in state.bodies:
                every = isinstance(index, slice)
                if material.cell_average:  # B-bar: L_bar into L (kernels.bbar)
                    self.average_dilatation(material, index, p, grid.L)
                packed = self._packed_state(material, p.dim)
                if packed is None:
                    state_in = state_out = no_state
                elif every:
                    state_in, state_out = packed.arrays(p.state)
                else:
                    state_in = packed.layout.pack(p.state, index)
                    state_out = np.empty_like(state_in)
                self.kernels.kernel(material_update)(material.point_update.address(),
                                material.point_parameters(p.dim),
                                self._no_index if every else index, every, grid.L, state.dt,
                                self.finite, p.stress, F, p.V, p.V0, state_in, new.stress,
                                F_out, new.V, state_out, flags)
                hits = flags[flags >= 0]
                if hits.size:
                    bad = int(hits.min()) if bad < 0 else min(bad, int(hits.min()))
                if packed is not None:
                    written.append((packed, index, state_out))
            if written and bad < 0:
                new.state = self._written_state(p, written)
        if bad >= 0:
            raise InvalidState(f"J = det(I + dt L) <= 0 at particle {bad}", particle=bad)

    def average_dilatation(self, material, index, p, L):
        """L <- L_bar of the body ``index`` of ``p`` on ``material``'s grid
        (kernels.bbar.average_dilatation: B-bar's projected dilatation)."""
        key = id(material.grid)
        if key not in self._cell_axes:
            self._cell_axes[key] = grid_record(material.grid)[0]
        axes = self._cell_axes[key]
        functions = material.functions
        every = isinstance(index, slice)
        count = p.n if every else index.size
        per = (1 << p.dim) if material.vertices else 1
        average_dilatation(axes, self._no_index if every else index, every, material.vertices,
                           p.x, p.V, L, self.kernels.scratch("bbar_volume", functions),
                           self.kernels.scratch("bbar_weighted", functions),
                           self.kernels.scratch("bbar_ids", (count, per), np.int64),
                           self.kernels.scratch("bbar_values", (count, per)))

    def _packed_state(self, material, dim):
        """The material's packed state buffers, or None without state."""
        key = id(material)
        if key not in self._state:
            layout = state_layout(material, dim)
            self._state[key] = PackedState(layout) if layout else None
        return self._state[key]

    @staticmethod
    def _written_state(p, written):
        """The new state dict from the bodies' packed outputs (views of the
        double-buffered output when one body holds every particle, else
        copies of the fields with each body's rows); raises for a
        non-finite value."""
        bad = [int(rows[0] if isinstance(index, slice) else index[rows[0]])
               for _, index, out in written if not np.isfinite(out).all()
               for rows in [np.flatnonzero(~np.isfinite(out).all(axis=1))]]
        if bad:
            raise InvalidState(f"non-finite material state (NaN or Inf) at particle {min(bad)}",
                               particle=min(bad))
        new_state = dict(p.state)
        for packed, index, out in written:
            if isinstance(index, slice):
                new_state.update(packed.written(out))
                continue
            for name, values in packed.layout.views(out).items():
                if new_state[name] is p.state[name]:
                    new_state[name] = p.state[name].copy()
                new_state[name][index] = values
        return new_state

    def internal_force(self, state, grid):
        raise NotImplementedError("the compiled executor has no USF step")

    def commit(self, state, grid):
        p, new, dt = state.particles, grid.new, state.dt
        if grid.work is not None:  # a Runge-Kutta step's quadrature of the power
            state.external_work += grid.work
        else:
            if self.gravity_work and self.recon is not None:  # grid.mass is not the particles'
                state.external_work += self.kernels.gravity_work(p.m, new.u - p.u, 1.0,
                                                                 self.gravity)
            elif self.gravity_work:
                state.external_work += self.kernels.gravity_work(grid.mass, grid.velocity, dt,
                                                                 self.gravity)
            du = new.u - p.u if grid.work_forces is not None or grid.side_loads else None
            if grid.work_forces is not None:  # sum_p f_p . du_p (the compiled loop's kernel)
                state.external_work += loads_power(np.arange(p.n), grid.work_forces, du)
            if grid.side_loads:
                for index, loads in grid.side_loads:
                    state.external_work += loads_power(index, loads, du)
        if grid.keep_acceleration:
            state.particle_acceleration = self._acc
            self._acc = None  # the state keeps this one; the next step writes a new one
        if grid.outside >= 0:
            state.particles = state.without_exits(new)
            self._spare = None
        else:
            self._spare = p
            state.particles = new
        state.advance()
