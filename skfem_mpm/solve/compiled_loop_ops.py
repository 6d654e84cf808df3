"""The scheme operations on a compiled run: the source of the generated loop
modules (not imported as a module).

:mod:`skfem_mpm.solve.compiled_loop` writes this text, after a prelude that
binds the kernel names used below (``P2G``, ``G2P2G``, ``G2P``,
``REDUCE_FIELDS``, ``REDUCE_COPIES``, ``LUMPED_SOLVE``, ``MERGED_SOLVE``, ``USL_GRID``,
``MASS_WEIGHTED_SUM``, ``WORK_INCREMENT``, ``SMALL_MASS``, ``MATERIAL_UPDATE``,
``monotonic_ns``; the
reconstruction's ``GAUSS_RULE_1D``, ``LOCATE_CELLS``, ``TLS_FACTOR``...; ``DIM``, the
grid dimension) to the compiled
kernels of one grid dimension and threading (serial copies for small
problems), into one generated file per variant that numba caches. The
transfer kernels (``P2G``, ``G2P2G``, ``G2P``) are called through the
addresses the run holds (``run.p2g_at``...: ``call_at``), so one compiled
loop serves every degree.
The kernels, and the heavy mass-system functions below, are called by
symbol (``call``, :mod:`skfem_mpm.kernels.by_symbol`): each compiles once,
on its own, instead of again inside every function above it.

A run (:class:`Run`, a numba ``structref``) holds the particle arrays (the
current state and the one the step writes), the grid arrays and the step's
scalars. Its methods are the operations of :mod:`skfem_mpm.solve.schemes`,
with the meaning the reference executor's docstrings give them; the scheme
functions themselves are compiled against them (``schemes.step_musl(run,
run)``: the run is both the executor and the state) and looped over steps
by :func:`run_musl` and its siblings, without Python between the steps.

What a compiled run covers
(:func:`skfem_mpm.solve.compiled_loop.loop_applies` says which runs):
the schemes MUSL, USL, CD and rk4 in 1D, 2D and 3D (the operations and
kernels are the same source in every dimension); lumped, consistent and
hybrid mass (``run.cm``: None, or the consistent-mass system of
:mod:`skfem_mpm.solve.compiled_loop_mass`); particle quadrature, the 1D
particle-knot spline reconstruction, the published TLS reconstruction
(default options) and mls in 1D and 2D, the 2D spline reconstruction
with its direct solve (``run.rc``: None, or the data of
:mod:`skfem_mpm.solve.compiled_loop_reconstruct`, a Reconstruction or a
RuleReconstruction); a run of each kind compiles only its own operations;
one body, or several of one linear elastic material: linear elastic (its stress update fused into g2p, its stress
rate into the rk4 rates gather; ``run.law_at`` None), or with MUSL, USL
and CD (rk4: finite strain, the law at each stage's F) a material with a
compiled point law (``run.law_at``: the address of its C callback;
B-bar's projected dilatation rate before it,
``run.cell_average``): g2p stores L and the executor's constitutive kernel
(``MATERIAL_UPDATE``, :mod:`skfem_mpm.kernels.constitutive`) writes the
new stress, V, F (finite strain) and packed material state into the
second set of arrays, swapped at commit like x and v; gravity, fixed
constraints, a traction on a side of the body with tau(t)
(``run.traction``: None, or the data of
:mod:`skfem_mpm.solve.compiled_loop_traction`), particle forces of the
reference configuration such as a BodyForce (``run.body_force``: None, or
the data of :mod:`skfem_mpm.solve.compiled_loop_body_force`), prescribed
grid velocities (``run.prescribed``: None, or the data of
:mod:`skfem_mpm.solve.compiled_loop_prescribed`), grid modifiers with a
compiled rule (local damping, frictional walls, rigid footings: ``run.force_rules``,
``run.velocity_rules``, None or the packed rules of
:mod:`skfem_mpm.solve.compiled_loop_modifiers`); a fixed dt, or with a
point law an adaptive one (``run.adaptive``: before each step
``begin_step`` takes the particles' largest wave speed from the current F
by the material's compiled point wave speed, ``run.wave_at``, and sets dt
by :mod:`skfem_mpm.kernels.step_size`, the rule ``State.next_step_size``
runs). A step that would need
anything else stops the loop before it writes the current state
(``run.stop``): a non-finite value or material state, J <= 0, a volume
<= 0 or a particle outside the grid (2), a tiny-mass merge the lumped kernel
cannot do (1), a tiny-mass merge of consistent mass whose rows outgrow the
compiled merge's lists (4), a CG run above
its tolerance (3), a fitted density 0 at a Gauss point or a 2D spline
system whose banded Cholesky meets a pivot <= 0 (5). The Python
step then takes that step and says what happened. A step with tiny-mass
dofs before the merge kernels were compiled (6): the merge is called
through addresses (``run.merged_solve_at``, ``run.cm.merge_at``), 0 until
:class:`~skfem_mpm.solve.compiled_loop.StepLoop` compiles the kernels at
that first need and calls the loop again from the same state. A step with
the fringe correction on and no factor loaded for its free rows (7): the
executor takes it and makes the factor (compiled_loop_mass). ``run.handover``: the
step was taken, and the next one needs the executor (the fringe
correction turned on, or its factor dropped: the executor makes one).

Phase times (nanoseconds of the monotonic clock) add up in ``run.phase_ns``:
0 p2g, 1 solve, 2 g2p, 3 mass_matrix, 4 reconstruct, 5 constitutive, 6 effects.
"""
import numpy as np
from numba import njit, types
from numba.core.extending import overload, overload_attribute, overload_method
from numba.experimental import structref

from skfem_mpm.kernels.scatter import node_hull
from skfem_mpm.solve import schemes


@structref.register
class RunType(types.StructRef):
    def preprocess_fields(self, fields):
        return tuple((name, types.unliteral(t)) for name, t in fields)


# Each variant's run type has its own name (VARIANT, from the prelude): numba
# names compiled specialisations after their argument types' names, so two
# variants' runs of the same fields would share the symbol of the one scheme
# function compiled for both, and the second would call the first's kernels.
RunType.__name__ = RunType.__qualname__ = f"RunType_{VARIANT}"
globals()[RunType.__name__] = RunType  # pickled by name in numba's cache index


FIELDS = (
    # particles: the current state and the arrays the step writes
    "x", "v", "u", "m", "V", "stress", "x_new", "v_new", "u_new", "V_new", "stress_new",
    "acc", "L",
    # grid: record, lumped mass, momentum, force, per-thread copies, the
    # node ranges those arrays and (a, v_grid) may be nonzero in
    # (kernels.scatter.reduce_fields)
    "grid", "mass", "momentum", "force", "mass_range", "occupied", "copies_p2g", "touched_p2g",
    "copies_g2p2g", "touched_g2p2g", "momentum_new", "a", "v_grid", "v_old", "mask", "gravity",
    "no_gravity", "no_force", "small", "small_tol", "small_count", "small_max", "nbx", "nby",
    "degree", "flags",
    # the material (fused linear elasticity: its Lame parameters; 1D: (E, 0))
    "lam", "mu",
    # the step
    "dt", "t", "step", "n_steps", "t_end", "vfactor", "store_acc", "velocities_done",
    "gravity_work", "work", "work_sum", "stop", "handover", "phase_ns",
    # an adaptive step (finite strain, a point law; else placeholders):
    # adaptive or not, the address of the material's compiled point wave
    # speed, cfl, the scheme's stability limit s, sqrt(sum_d Lambda /
    # h_d^2), the coming step's wave speed and dt_crit, the kernel's block
    # maxima, the fast-dof guard's q (consistent mass: cm.limit = q / (dt
    # c)^2), (dt, dt_crit, c) of the last step taken, and a 2D
    # reconstruction's factor on dt_crit (State.step_reconstruction_factor,
    # set before each call: the call stops before its next re-estimate)
    "adaptive", "wave_at", "cfl", "stability_limit", "stiffness_root", "wave_speed", "dt_crit",
    "block_max", "guard_q", "taken_step", "recon_factor",
    # consistent or hybrid mass: a MassSystem (None: lumped mass)
    "cm", "nthreads",
    # the native entry points of the run's degree's transfer kernels (call_at)
    "p2g_at", "g2p2g_at", "g2p_at", "rates_at",
    # that of the lumped tiny-mass merge, 0 until a step needs it (STOP 6)
    "merged_solve_at",
    # rk4 (placeholders of one particle for the other schemes): the stage
    # particles, the rates of the four stages (leading stage axis; F's and
    # the stage F only for a finite-strain point law), each
    # stage's power of the external forces, the weights times dt of a
    # combination, the next stage's slot
    "x_stage", "v_stage", "u_stage", "V_stage", "stress_stage", "rate_x", "rate_v",
    "rate_stress", "rate_V", "rate_F", "F_stage", "power", "stage_weights", "next_stage",
    # the grid arrays the reactions come from: the step's own (mass, a,
    # force), or with rk4 copies of its first stage's
    "reaction_mass", "reaction_a", "reaction_force",
    # reconstruction: a Reconstruction (None: particle quadrature), zero
    # grid accelerations, the particle displacements of a step (the work of
    # gravity); both placeholders of one row without reconstruction
    "rc", "no_acceleration", "displacement",
    # a material's compiled point law (kernels.constitutive.material_update;
    # ``law_at`` None: linear elasticity fused into g2p, and the rest are
    # placeholders of one row): the address of its C callback, its
    # parameters, finite strain or not, the deformation gradient (current
    # and new; small strain: placeholders, the kernel is given L), the
    # reference volumes, the packed material state (current and new, (n,
    # n_state)), the kernel's flags (first J <= 0 of each thread's block),
    # an empty index (the body holds every particle)
    "law_at", "law_params", "finite", "F", "F_new", "V0", "mstate", "mstate_new",
    "law_flags", "no_index",
    # B-bar (a material with ``cell_average``): None, or (its grid's axes,
    # the vertex functions or the cells', work arrays: the functions'
    # volumes and weighted dilatations, the particles' function ids and
    # values) of kernels.bbar.average_dilatation
    "cell_average",
    # a side traction: a SideTraction (None: none; compiled_loop_traction)
    "traction",
    # particle forces of the reference configuration: a BodyForce (None:
    # none; compiled_loop_body_force)
    "body_force",
    # prescribed grid velocities: a Prescribed (None: none; compiled_loop_prescribed)
    "prescribed",
    # grid modifiers (damping, walls): GridRules of the force and of MUSL's
    # re-projected velocity (None: none; compiled_loop_modifiers)
    "force_rules", "velocity_rules",
)


def _consistent(run):
    """Whether the run (its numba type) has a consistent-mass system."""
    return not isinstance(run.field_dict["cm"], types.NoneType)


def _reconstructed(run):
    """Whether the run (its numba type) reconstructs its particle data."""
    return not isinstance(run.field_dict["rc"], types.NoneType)


def _traction(run):
    """Whether the run (its numba type) carries a side traction."""
    return not isinstance(run.field_dict["traction"], types.NoneType)


def _point_law(run):
    """Whether the run (its numba type) updates the stress by a material's
    compiled point law (else linear elasticity is fused into g2p)."""
    return not isinstance(run.field_dict["law_at"], types.NoneType)


def _cell_average(run):
    """Whether the run (its numba type) averages the dilatation rate over
    each cell before the point law (B-bar)."""
    return not isinstance(run.field_dict["cell_average"], types.NoneType)


def cells_integrated_type(run):
    """Whether a ruled run's fit is integrated per cell in closed form (the
    2D TLS: compiled_loop_reconstruct's cells_integrated), from its type."""
    return not isinstance(run.field_dict["rc"].field_dict["tables"], types.NoneType)


def _ruled(run):
    """Whether the run (its numba type) reconstructs on the rule of
    CompiledReconstruction.rule (tls, mls, the 2D spline; else, when it
    reconstructs, by the 1D spline): see compiled_loop_reconstruct."""
    return isinstance(run.field_dict["rc"], RuleReconstructionType)


class Run(structref.StructRefProxy):
    """A compiled run (see the module); built by
    :class:`skfem_mpm.solve.compiled_loop.StepLoop`."""

    def __new__(cls, *fields):
        return structref.StructRefProxy.__new__(cls, *fields)


structref.define_proxy(Run, RunType, list(FIELDS))


@njit(cache=True)
def copy_into(dst, src):
    """dst[...] = src, both C-contiguous of one size: an explicit loop
    (numba's slice assignment between arrays compiles its broadcasting and
    error-message machinery, seconds per signature)."""
    d = dst.reshape(dst.size)
    s = src.reshape(src.size)
    for i in range(d.size):
        d[i] = s[i]


@njit(cache=True)
def new_run(*fields):
    """A run with ``fields`` in the order of FIELDS (built in compiled code,
    which numba caches: the proxy's own constructor compiles in every
    process)."""
    return Run(*fields)


@njit(cache=True)
def set_transfers(run, p2g_at, g2p2g_at, g2p_at, rates_at):
    """Point the run at its degree's transfer kernels (native entry points:
    kernels.by_symbol.native_address)."""
    run.p2g_at = p2g_at
    run.g2p2g_at = g2p2g_at
    run.g2p_at = g2p_at
    run.rates_at = rates_at


@njit(cache=True)
def load_state(run, x, v, u, V, stress, t, step, work):
    """Copy a particle state (its time, step and external work) into the
    run's current arrays (the run never writes arrays it did not allocate)."""
    copy_into(run.x, x)
    copy_into(run.v, v)
    copy_into(run.u, u)
    copy_into(run.V, V)
    copy_into(run.stress, stress)
    run.t = t
    run.step = step
    run.work = work


@njit(cache=True)
def load_law_state(run, F, V0, mstate):
    """Copy the point law's particle data into the run: the deformation
    gradient (finite strain), the reference volumes and the packed state."""
    if run.finite:
        copy_into(run.F, F)
    copy_into(run.V0, V0)
    copy_into(run.mstate, mstate)


@njit(cache=True)
def law_state(run):
    """The run's current deformation gradient and packed material state."""
    return run.F, run.mstate


@njit(cache=True)
def set_work(run, work):
    run.work = work


@njit(cache=True)
def reset_step_records(run):
    """Clear what a call of the loop reports: the stop flag, the most
    tiny-mass dofs of a step and the phase times (and an rk4 step's stage
    count, which a stopped step leaves behind)."""
    run.stop = 0
    run.next_stage = 0
    run.handover = False
    run.small_max = 0
    run.phase_ns[:] = 0


@njit(cache=True)
def set_reconstruction_factor(run, factor):
    run.recon_factor = factor


@njit(cache=True)
def clock(run):
    """The run's time and step, the stop code of its last call (0: none)
    and whether it handed over."""
    return run.t, run.step, run.stop, run.handover


@njit(cache=True)
def set_merged_solve(run, address):
    """Point the run at the compiled lumped tiny-mass merge."""
    run.merged_solve_at = address


@njit(cache=True)
def taken_step(run):
    """(dt, dt_crit, wave speed) of the last adaptive step taken."""
    return run.taken_step


@njit(cache=True)
def current(run):
    """The run's current particle arrays, time, step, external work and
    the CD particle acceleration."""
    return run.x, run.v, run.u, run.V, run.stress, run.t, run.step, run.work, run.acc


@njit(cache=True)
def grid_arrays(run):
    """The lumped mass, acceleration and force of the last step's reactions
    (rk4: of its first stage)."""
    return run.reaction_mass, run.reaction_a, run.reaction_force


@njit(cache=True)
def records(run):
    """The phase times (ns), the most tiny-mass dofs of a step, and whether
    the executor takes the next steps."""
    return run.phase_ns, run.small_max, run.handover


# ------------------------------------------------------------- operations
@overload_attribute(RunType, "particles")
def _particles(run):
    """The current particles as the transfer kernels' record (x, v, u, m, V, stress)."""
    return lambda run: (run.x, run.v, run.u, run.m, run.V, run.stress)


@overload_method(RunType, "particles_to_grid")
def _particles_to_grid(run, state):
    return lambda run, state: run.scatter(run.particles, 0)


@overload_method(RunType, "scatter")
def _scatter(run, particles, column):
    consistent = _consistent(run)
    reconstructed = _reconstructed(run)
    ruled = _ruled(run)
    traction = _traction(run)
    cells = ruled and DIM == 2  # the rule's tensor cells: CompiledReconstruction.tensor_cells
    fitted_cells = ruled and cells_integrated_type(run)  # 2D TLS: closed-form cell integrals

    def impl(run, particles, column):
        """Lumped mass, momentum, force (and the consistent mass) of
        ``particles``, or with reconstruction of the quadrature points of
        their fitted fields, plus a side traction's grid force and a body
        force at their tables' ``column`` (0: t, 1: t + dt/2, 2: t + dt);
        the tiny-mass dofs counted; the constraint values of that time."""
        t0 = monotonic_ns()
        if traction:  # its grid force first: the p2g kernel's copies are shared
            st = run.traction
            if not call(traction_loads, st, particles[0], particles[4], run.V0,
                        run.step - st.first_step, column):
                run.stop = 2  # a face outside the grid: the executor raises
                return run
            faces = (st.faces, st.zero_v, st.zero_v, st.zero_m, st.zero_m, st.zero_stress)
            P2G(run.p2g_at, faces, run.grid, st.loads, True, run.copies_p2g, run.touched_p2g)
            REDUCE_FIELDS(run.copies_p2g, run.touched_p2g, st.mass, st.momentum, st.force,
                          st.mass_range, st.occupied)
        fext, has_fext = run.particle_forces(column)  # (a body force: compiled_loop_body_force)
        if reconstructed:  # (a body force: its density rho b = f_p / V_p fitted too)
            if fitted_cells:
                fitted = call(cell_rule_points, run.rc, particles[0], particles[1], run.m,
                              particles[4], particles[5], fext)
            elif ruled:
                fitted = call(rule_points, run.rc, particles[0], particles[1], run.m,
                              particles[4], particles[5], fext)
            else:
                fitted = call(reconstruct_points, run.rc, particles[0], particles[1], run.m,
                              particles[4], particles[5], fext)
            if not fitted:
                run.stop = 5  # a fitted density 0, a spline system the banded Cholesky
                return run    # refuses: the executor takes the step
            rc = run.rc
            points = (rc.xq, rc.vq, rc.vq, rc.mq, rc.Vq, rc.sq)
            if has_fext:  # the points' forces w_g (rho b)_h
                fext = rc.fq
            t_fit = monotonic_ns()
            run.phase_ns[4] += t_fit - t0
            t0 = t_fit
        else:
            points = particles
        P2G(run.p2g_at, points, run.grid, fext, has_fext, run.copies_p2g, run.touched_p2g)
        if fitted_cells:  # the fitted cells' integrals (kernels.cell_integrals)
            call(cell_p2g, run.rc, has_fext, run.copies_p2g, run.touched_p2g)
        REDUCE_FIELDS(run.copies_p2g, run.touched_p2g, run.mass, run.momentum, run.force,
                      run.mass_range, run.occupied)
        run.set_constraint_values(column)  # (prescribed velocities: compiled_loop_prescribed)
        if traction:  # its force is zero outside its nodes (the range occupied[0:2])
            lo, hi = run.traction.occupied[0], run.traction.occupied[1]
            for k in range(lo, hi):
                for c in range(run.force.shape[1]):
                    run.force[k, c] = run.force[k, c] + run.traction.force[k, c]
            run.occupied[0], run.occupied[1] = node_hull(run.occupied[0], run.occupied[1], lo,
                                                         hi)
        run.small_count = 0  # tiny-mass dofs (see Kernels.small_mass): merged solves
        if run.small_tol > 0.0:
            smallest = np.inf
            largest = 0.0
            for r in range(run.mass_range.shape[0]):
                smallest = min(smallest, run.mass_range[r, 0])
                largest = max(largest, run.mass_range[r, 1])
            if smallest < run.small_tol * largest:
                run.small_count = SMALL_MASS(run.mass, run.small_tol, run.small, run.nbx,
                                             run.nby, run.degree)
                run.small_max = max(run.small_max, run.small_count)
        run.velocities_done = False
        t1 = monotonic_ns()
        run.phase_ns[0] += t1 - t0
        if consistent:
            if fitted_cells:  # the particle points, then the fitted cells
                call(assemble_mass_fitted_cells, run.cm, run.rc, points[0], points[3],
                     run.rc.ref.shape[0], run.nbx, run.nby)
            elif cells:  # the rule's whole cells summed per axis (Kernels.consistent_stencil)
                k = run.rc.ref.shape[0]
                call(assemble_mass_cells, run.cm, points[0], points[3],
                     run.rc.wg.shape[0] // (k * k), k, run.degree, run.nbx, run.nby)
            else:
                call(assemble_mass, run.cm, points[0], points[3], run.degree, run.nbx, run.nby,
                     run.x.shape[1])
            if reconstructed and run.cm.by_particles:  # the guard's sums: the particles'
                call(cover_particles, run.cm, particles[0], particles[3], run.degree, run.nbx,
                     run.nby)
            run.phase_ns[3] += monotonic_ns() - t1
        return run
    return impl


@overload_method(RunType, "lumped_solve")
def _lumped_solve(run, rhs, gravity, out, kind):
    def impl(run, rhs, gravity, out, kind):
        """out = M_lumped^-1 rhs (+ gravity), constrained dofs their values
        of ``kind`` (0 acceleration, 1 velocity, 2 velocity at t + dt:
        run.constraint_values) or 0; with tiny-mass dofs the compiled merge
        (a merge it cannot do stops the loop)."""
        values, has_values = run.constraint_values(rhs, kind)
        if run.small_count == 0:
            LUMPED_SOLVE(run.mass, rhs, gravity, run.mask, values, has_values, out)
        elif run.merged_solve_at == 0:  # not compiled yet: StepLoop.run compiles it
            run.stop = 6
        elif MERGED_SOLVE(run.merged_solve_at, run.mass, rhs, gravity, run.mask, values,
                          has_values, run.nbx, run.nby,
                          run.mass.shape[0] // (run.nbx * run.nby), run.degree, run.small_tol,
                          out) < 0:
            run.stop = 1
    return impl


@overload_method(RunType, "mass_solve")
def _mass_solve(run, count, rhs0, kind0, out0, rhs1, kind1, out1):
    def impl(run, count, rhs0, kind0, out0, rhs1, kind1, out1):
        """Consistent M x = rhs for 1 or 2 problems (see compiled_loop_mass);
        ``kind`` 0 acceleration, 1 velocity, 2 velocity at t + dt: the
        constraint values (run.constraint_values) and the warm start
        (0 acceleration, else velocity)."""
        if run.stop:
            return
        values0, has0 = run.constraint_values(rhs0, kind0)
        values1, has1 = run.constraint_values(rhs1, kind1)
        if not call(mass_solve, run.cm, run.nthreads, count, rhs0, min(kind0, 1), values0, has0,
                    out0, rhs1, min(kind1, 1), values1, has1, out1):
            run.stop = 3
    return impl


@overload_method(RunType, "gravity_into_force")
def _gravity_into_force(run):
    def impl(run):
        """f_k += m_k g (with gravity; the solves then add none)."""
        if run.gravity_work:
            for k in range(run.force.shape[0]):
                for c in range(run.force.shape[1]):
                    run.force[k, c] = run.force[k, c] + run.mass[k] * run.gravity[c]
    return impl


@overload_method(RunType, "prepare_grid")
def _prepare_grid(run):
    if not _consistent(run):
        return lambda run: None
    prescribed = _prescribed(run)  # the system's fixed columns are needed

    def impl(run):
        """Consistent mass: gravity as the force m g, then the step's system."""
        run.gravity_into_force()
        # 4: a merged row outgrew the lists (the general grid system takes
        # the step); 6: the merge kernels are not compiled yet; 7: no
        # fringe factor loaded for the free rows (the executor makes it)
        run.stop = call(prepare_mass, run.cm, run.mass, run.mask, run.degree, run.nbx,
                        run.nby, run.x.shape[1], prescribed,
                        run.small_tol if run.small_count > 0 else 0.0)
    return impl


@overload_method(RunType, "solve_acceleration")
def _solve_acceleration(run):
    if not _consistent(run):
        return lambda run: run.lumped_solve(run.force, run.acceleration_gravity, run.a, 0)

    def impl(run):
        if run.cm.hybrid:  # lumped acceleration (gravity is in the force)
            run.lumped_solve(run.force, run.no_gravity, run.a, 0)
        else:
            run.mass_solve(1, run.force, 0, run.a, run.force, 0, run.a)
    return impl


@overload_method(RunType, "solve_grid")
def _solve_grid(run, state, grid, end_velocity=None):
    consistent = _consistent(run)
    modified = _force_rules(run)
    if end_velocity is None or isinstance(end_velocity, (types.NoneType, types.Omitted)):
        def impl(run, state, grid, end_velocity=None):  # MUSL: a only
            if run.stop:
                return run.a
            t0 = monotonic_ns()
            run.prepare_grid()
            run.modify_force(0.0)  # damping, walls, footings (compiled_loop_modifiers)
            run.solve_acceleration()
            run.phase_ns[1] += monotonic_ns() - t0
            return run.a
        return impl

    if consistent:
        def impl(run, state, grid, end_velocity=None):  # USL, CD: a and v = v^n + c dt a
            if run.stop:
                return run.a
            t0 = monotonic_ns()
            vdt = end_velocity * run.dt
            run.prepare_grid()
            if modified:  # v^n, the modified force, then a (compiled_loop_modifiers)
                run.modify_force(0.0)
                run.solve_acceleration()
            elif run.cm.hybrid:
                run.lumped_solve(run.force, run.no_gravity, run.a, 0)
                run.mass_solve(1, run.momentum, 1, run.v_old, run.momentum, 1, run.v_old)
            else:
                run.mass_solve(2, run.force, 0, run.a, run.momentum, 1, run.v_old)
            if not run.stop:
                for k in range(run.a.shape[0]):
                    for c in range(run.a.shape[1]):
                        run.v_grid[k, c] = run.a[k, c] * vdt + run.v_old[k, c]
                copy_into(run.cm.warm[1], run.v_grid)  # see steps.remember_end_velocity
            run.phase_ns[1] += monotonic_ns() - t0
            return run.a
        return impl

    def impl(run, state, grid, end_velocity=None):  # USL, CD: a and v = v^n + c dt a
        if run.stop:
            return run.a
        t0 = monotonic_ns()
        vdt = end_velocity * run.dt
        if run.small_count == 0 and not modified:  # one pass
            v_values, has_values = run.constraint_values(run.momentum, 1)
            a_values, has_values = run.constraint_values(run.force, 0)
            USL_GRID(run.mass, run.momentum, run.force, run.gravity, run.mask, v_values,
                     a_values, has_values, vdt, run.a, run.v_grid, run.occupied)
        else:
            if modified:  # v^n and the modified force (compiled_loop_modifiers)
                run.modify_force(0.0)
            else:
                run.lumped_solve(run.momentum, run.no_gravity, run.v_old, 1)
            run.lumped_solve(run.force, run.acceleration_gravity, run.a, 0)
            for k in range(run.a.shape[0]):
                for c in range(run.a.shape[1]):
                    run.v_grid[k, c] = run.a[k, c] * vdt + run.v_old[k, c]
        run.phase_ns[1] += monotonic_ns() - t0
        return run.a
    return impl


@overload_method(RunType, "update_particle_velocities")
def _update_particle_velocities(run, state, grid, velocity_factor=1.0,
                                keep_acceleration=False):
    def impl(run, state, grid, velocity_factor=1.0, keep_acceleration=False):
        run.vfactor = velocity_factor  # fused into the next gather kernel
        run.store_acc = keep_acceleration
    return impl


@overload_method(RunType, "solve_projected_velocity")
def _solve_projected_velocity(run):
    if not _consistent(run):
        return lambda run: run.lumped_solve(run.momentum_new, run.no_gravity, run.v_grid, 2)

    def impl(run):  # see steps.project_velocity: the warm start moves by dt a
        shift_warm(run.cm, 1, run.dt, run.a)
        run.mass_solve(1, run.momentum_new, 2, run.v_grid, run.momentum_new, 2, run.v_grid)
    return impl


@overload_method(RunType, "project_velocity")
def _project_velocity(run, state, grid):
    reconstructed = _reconstructed(run)
    ruled = _ruled(run)
    fitted_cells = ruled and cells_integrated_type(run)

    def impl(run, state, grid):
        if run.stop:
            return
        t0 = monotonic_ns()
        G2P2G(run.g2p2g_at, run.particles, run.grid, run.a, run.vfactor * run.dt, run.v_new,
              run.copies_g2p2g, run.touched_g2p2g)
        if reconstructed:  # the momentum of the fitted rho v^new at the step's points
            t_fit = monotonic_ns()
            if fitted_cells:
                call(cell_rule_project, run.rc, run.x, run.V, run.v_new)
            elif ruled:
                call(rule_project, run.rc, run.x, run.V, run.v_new)
            else:
                call(project_points, run.rc, run.x, run.v_new)
            rc = run.rc
            t_points = monotonic_ns()
            run.phase_ns[4] += t_points - t_fit
            t0 += t_points - t_fit
            points = (rc.xq, rc.momentum_fit, rc.momentum_fit, rc.Vq, rc.Vq, rc.no_stress)
            G2P2G(run.g2p2g_at, points, run.grid, run.no_acceleration, 0.0,
                  rc.point_velocities, run.copies_g2p2g, run.touched_g2p2g)
            if fitted_cells:  # the fitted cells' momentum (kernels.cell_integrals)
                call(cell_momentum, run.rc, run.copies_g2p2g, run.touched_g2p2g)
        REDUCE_COPIES(run.copies_g2p2g, run.touched_g2p2g, run.momentum_new)
        run.velocities_done = True
        t1 = monotonic_ns()
        run.solve_projected_velocity()
        run.modify_velocity()  # walls (compiled_loop_modifiers)
        run.phase_ns[2] += t1 - t0
        run.phase_ns[1] += monotonic_ns() - t1
    return impl


@overload_method(RunType, "move_particles")
def _move_particles(run, state, grid):
    fused = not _point_law(run)  # else g2p stores L (n, dim, dim) for the point law

    def impl(run, state, grid):
        if run.stop:
            return
        t0 = monotonic_ns()
        particles = (run.x, run.v, run.u, run.m, run.V, run.stress)
        new = (run.x_new, run.v_new, run.u_new, run.m, run.V_new, run.stress_new)
        update = (run.dt, run.vfactor, not run.velocities_done, fused, run.lam, run.mu,
                  run.store_acc)  # kernels.records.Update
        G2P(run.g2p_at, particles, run.grid, run.a, run.v_grid, update, new, run.L, run.acc,
            run.flags)
        for t in range(run.flags.shape[0]):  # non-finite, outside, J <= 0
            for j in range(3):
                if run.flags[t, j] >= 0:
                    run.stop = 2
        run.phase_ns[2] += monotonic_ns() - t0
    return impl


@overload_method(RunType, "update_stress")
def _update_stress(run, state, grid, velocity=None):
    if not _point_law(run):
        def impl(run, state, grid, velocity=None):
            pass  # linear elasticity: fused into the g2p kernel
        return impl
    bbar = _cell_average(run)

    def impl(run, state, grid, velocity=None):
        """The material's point law over every particle (the executor's
        material_update call; B-bar: L_bar into L first, the executor's
        average_dilatation call): stress, V (and F) from L into the new
        arrays, the packed state into the new state; a J <= 0 or a
        non-finite state stops the loop (the executor raises)."""
        if run.stop:
            return
        t0 = monotonic_ns()
        if bbar:
            ca = run.cell_average
            AVERAGE_DILATATION(ca[0], run.no_index, True, ca[1], run.x, run.V, run.L, ca[2],
                               ca[3], ca[4], ca[5])
        if run.finite:
            F = run.F
            F_out = run.F_new
        else:  # not read: the executor passes L
            F = run.L
            F_out = run.L
        MATERIAL_UPDATE(run.law_at, run.law_params, run.no_index, True, run.L, run.dt,
                        run.finite, run.stress, F, run.V, run.V0, run.mstate, run.stress_new,
                        F_out, run.V_new, run.mstate_new, run.law_flags)
        for t in range(run.law_flags.shape[0]):  # J <= 0
            if run.law_flags[t] >= 0:
                run.stop = 2
        out = run.mstate_new
        if not run.stop:
            for i in range(out.shape[0]):  # a non-finite material state
                for c in range(out.shape[1]):
                    if not np.isfinite(out[i, c]):
                        run.stop = 2
        run.phase_ns[5] += monotonic_ns() - t0
    return impl


@overload_method(RunType, "begin_step")
def _begin_step(run):
    if not _point_law(run):  # linear elasticity: never adaptive
        return lambda run: run.step >= run.n_steps
    consistent = _consistent(run)

    def impl(run):
        """Whether the run is done (State.done); an adaptive run sets the
        coming step's dt from the current wave speed as
        State.next_step_size does (kernels.step_size: the one copy of the
        rule; times a 2D reconstruction's factor, 1 otherwise)."""
        if not run.adaptive:
            return run.step >= run.n_steps
        if reached_end(run.t, run.t_end):
            return True
        c = MAX_WAVE_SPEED(run.wave_at, run.law_params, run.F, run.m, run.V0, run.mstate,
                           run.block_max)
        run.wave_speed = c
        run.dt_crit = critical_step(run.stability_limit, c, run.stiffness_root) * \
            run.recon_factor
        run.dt = adaptive_step(run.cfl, run.dt_crit, run.t, run.t_end)
        if consistent:
            if run.cm.guard:
                run.cm.limit = guard_limit(run.guard_q, run.dt, c)
        return False
    return impl


@njit(cache=True)
def _advance(run):
    """The new state becomes current; t += dt (the end time exactly at the
    last step: State.time_at of a fixed dt, computed alike; adaptive:
    kernels.step_size.time_after_step, State.t_next's rule)."""
    run.x, run.x_new = run.x_new, run.x
    run.v, run.v_new = run.v_new, run.v
    run.u, run.u_new = run.u_new, run.u
    run.V, run.V_new = run.V_new, run.V
    run.stress, run.stress_new = run.stress_new, run.stress
    run.F, run.F_new = run.F_new, run.F
    run.mstate, run.mstate_new = run.mstate_new, run.mstate
    run.step += 1
    if run.adaptive:
        run.t = time_after_step(run.t, run.dt, run.t_end)
        run.taken_step[0] = run.dt
        run.taken_step[1] = run.dt_crit
        run.taken_step[2] = run.wave_speed
    else:
        run.t = run.step * run.dt if run.step < run.n_steps else run.t_end


@overload_method(RunType, "gravity_power")
def _gravity_power(run, mass, velocity):
    def impl(run, mass, velocity):
        """g . sum_k m_k v_k (kernels.mpm.mass_weighted_sum, work_increment)."""
        MASS_WEIGHTED_SUM(mass, velocity, run.work_sum)
        return WORK_INCREMENT(run.work_sum, 1.0, run.gravity)
    return impl


@overload_method(RunType, "commit")
def _commit(run, state, grid):
    consistent = _consistent(run)
    reconstructed = _reconstructed(run)
    traction = _traction(run)
    body_force = _body_force(run)
    if isinstance(grid, types.Float):  # rk4: ``grid`` is the step's external work
        def impl(run, state, grid):
            if run.stop:
                return
            if consistent and commit_mass(run.cm):  # a fringe factor to make
                run.handover = True
            run.work += grid
            _advance(run)
        return impl

    def impl(run, state, grid):
        if run.stop:
            return
        if consistent and commit_mass(run.cm):  # a fringe factor to make
            run.handover = True
        du = run.displacement
        if traction or body_force or (run.gravity_work and reconstructed):
            for i in range(du.shape[0]):
                for c in range(du.shape[1]):
                    du[i, c] = run.u_new[i, c] - run.u[i, c]
        if run.gravity_work and reconstructed:  # the grid mass is not the particles'
            run.work += run.gravity_power(run.m, du)
        elif run.gravity_work:  # see Kernels.gravity_work
            MASS_WEIGHTED_SUM(run.mass, run.v_grid, run.work_sum)
            run.work += WORK_INCREMENT(run.work_sum, run.dt, run.gravity)
        if body_force:  # the work of the body force over the step
            run.work += run.particle_forces_power(0, du)
        if traction:  # the work of the loads over the step
            run.work += LOADS_POWER(run.traction.index, run.traction.loads, du)
        _advance(run)
    return impl


# ------------------------------------------------------------- rk4 stages
# The Runge-Kutta operations of skfem_mpm.solve.compiled_runge_kutta (its
# docstring gives the method): a stage's rates are an int, their slot in
# the rate arrays; the stage particles a record like ``run.particles``.
@overload_method(RunType, "stage_rates")
def _stage_rates(run, state, particles, c, reactions=False):
    consistent = _consistent(run)
    reconstructed = _reconstructed(run)
    traction = _traction(run)
    body_force = _body_force(run)
    modified = _force_rules(run)
    point_law = _point_law(run)

    def impl(run, state, particles, c, reactions=False):
        """R(t + c dt, particles): particles to grid, M v = P and M a = f,
        the rates gather; the first stage keeps its grid arrays for the
        reactions."""
        slot = run.next_stage
        run.next_stage += 1
        if run.stop:
            return slot
        column = 0 if c == 0.0 else (1 if c == 0.5 else 2)  # of the traction's and forces' tables
        run.scatter(particles, column)
        if run.stop:
            return slot
        t0 = monotonic_ns()
        run.prepare_grid()
        if modified:  # v, the modified force at the stage's time, then a
            run.modify_force(c)
            run.solve_acceleration()
        elif not consistent:
            run.lumped_solve(run.momentum, run.no_gravity, run.v_old, 1)
            run.lumped_solve(run.force, run.gravity, run.a, 0)
        elif run.cm.hybrid:  # lumped acceleration (gravity is in the force)
            run.mass_solve(1, run.momentum, 1, run.v_old, run.momentum, 1, run.v_old)
            run.lumped_solve(run.force, run.no_gravity, run.a, 0)
        else:
            run.mass_solve(2, run.force, 0, run.a, run.momentum, 1, run.v_old)
        if run.stop:
            return slot
        if reactions:
            copy_into(run.reaction_mass, run.mass)
            copy_into(run.reaction_a, run.a)
            copy_into(run.reaction_force, run.force)
            if consistent:
                keep_stage_mass(run.cm)
        t1 = monotonic_ns()
        # fused linear elasticity: its stress rate; a point law: L, and with
        # finite strain dF/dt = L F at the stage's F (the current one first)
        RATES(run.rates_at, particles, run.grid, run.a, run.v_old,
              (not point_law, run.lam, run.mu), run.nthreads, run.rate_x[slot],
              run.rate_v[slot], run.L, run.rate_stress[slot], run.rate_V[slot])
        if point_law and run.finite:
            DEFORMATION_RATE(run.L, run.F if slot == 0 else run.F_stage, run.rate_F[slot],
                             run.nthreads)
        power = 0.0
        if run.gravity_work and reconstructed:  # the particles' m_p dx_p/dt . g
            power = run.gravity_power(run.m, run.rate_x[slot])
        elif run.gravity_work:  # see Kernels.gravity_work: the power m v . g
            power = run.gravity_power(run.mass, run.v_old)
        if body_force:
            power += run.particle_forces_power(column, run.rate_x[slot])
        if traction:
            power += LOADS_POWER(run.traction.index, run.traction.loads, run.rate_x[slot])
        run.power[slot] = power
        t2 = monotonic_ns()
        run.phase_ns[1] += t1 - t0
        run.phase_ns[2] += t2 - t1
        return slot
    return impl


@njit(cache=True)
def _stage_weights(run, rates, weights):
    """run.stage_weights = dt w_s at the rates' slots (0 elsewhere)."""
    c = run.stage_weights
    for s in range(c.shape[0]):
        c[s] = 0.0
    for s in range(len(rates)):
        c[rates[s]] += weights[s] * run.dt


@overload_method(RunType, "combine_into")
def _combine_into(run, x, u, v, stress, V, F):
    point_law = _point_law(run)

    def impl(run, x, u, v, stress, V, F):
        """(x, u, v, stress, V) = y_n + sum_s c_s k_s with c =
        run.stage_weights (kernels.staging; one compiled body for the
        stages and the step, whatever their number of rates);
        a finite-strain point law: F likewise, then sigma = law(F) and
        V = V0 det F (the constitutive kernel with dt = 0, as the
        executor's CompiledRungeKutta._law_stage); J <= 0 stops. Returns
        the nanoseconds of the law (the constitutive phase)."""
        c = run.stage_weights
        finite = point_law and run.finite
        COMBINE_STAGES(c, run.x, run.u, run.v, run.stress, run.V,
                       run.F if finite else run.L, run.rate_x, run.rate_v, run.rate_stress,
                       run.rate_V, run.rate_F, not finite, finite, x, u, v, stress, V,
                       F if finite else run.L, run.nthreads)
        if not finite:
            return 0
        t0 = monotonic_ns()
        MATERIAL_UPDATE(run.law_at, run.law_params, run.no_index, True, run.L, 0.0, True,
                        stress, F, V, run.V0, run.mstate, stress, F, V, run.mstate_new,
                        run.law_flags)
        for t in range(run.law_flags.shape[0]):
            if run.law_flags[t] >= 0:
                run.stop = 2
        return monotonic_ns() - t0
    return impl


@overload_method(RunType, "stage")
def _stage(run, state, rates, weights):
    def impl(run, state, rates, weights):
        """The stage particles y_n + dt sum_s w_s k_s; a volume <= 0 stops."""
        stage = (run.x_stage, run.v_stage, run.u_stage, run.m, run.V_stage, run.stress_stage)
        if run.stop:
            return stage
        t0 = monotonic_ns()
        _stage_weights(run, rates, weights)
        law = run.combine_into(run.x_stage, run.u_stage, run.v_stage, run.stress_stage,
                               run.V_stage, run.F_stage)
        for i in range(run.V_stage.shape[0]):
            if not run.V_stage[i] > 0.0:
                run.stop = 2
        run.phase_ns[2] += monotonic_ns() - t0 - law
        run.phase_ns[5] += law
        return stage
    return impl


@overload_method(RunType, "combine")
def _combine(run, state, rates, weights):
    def impl(run, state, rates, weights):
        """The step's new state y_n + dt sum_s b_s k_s and its external work
        dt sum_s b_s P_s; a volume <= 0, a non-finite value or a particle
        outside the grid stops (the executor takes the step)."""
        run.next_stage = 0
        if run.stop:
            return 0.0
        t0 = monotonic_ns()
        _stage_weights(run, rates, weights)
        law = run.combine_into(run.x_new, run.u_new, run.v_new, run.stress_new, run.V_new,
                               run.F_new)
        if not _valid_state(run.x_new, run.v_new, run.stress_new, run.V_new, run.grid[0]):
            run.stop = 2
        run.phase_ns[2] += monotonic_ns() - t0 - law
        run.phase_ns[5] += law
        power = 0.0
        for s in range(len(rates)):
            power += weights[s] * run.power[rates[s]]
        return run.dt * power
    return impl


@njit(cache=True)
def _valid_state(x, v, stress, V, axes):
    """All volumes > 0, positions, velocities and stresses finite, every
    particle inside the grid (breakpoints[0] <= x <= breakpoints[-1])."""
    n, dim = x.shape
    for i in range(n):
        if not V[i] > 0.0:
            return False
        for a in range(dim):
            lo = axes[a][0][0]
            hi = axes[a][0][-1]
            if not (x[i, a] >= lo and x[i, a] <= hi and np.isfinite(v[i, a])):
                return False
            for b in range(dim):
                if not np.isfinite(stress[i, a, b]):
                    return False
    return True


# ------------------------------------------------------------------ loops
# One loop per scheme: each compiles only the scheme it runs.
@njit(cache=True)
def run_musl(run, n):
    """Up to n MUSL steps; returns the number taken (fewer when one stopped)."""
    for k in range(n):
        if run.begin_step():  # the end (adaptive: the step's dt set)
            return k
        schemes.step_musl(run, run)
        if run.stop:
            return k
        if run.handover:
            return k + 1
    return n


@njit(cache=True)
def run_usl(run, n):
    """Up to n USL steps; returns the number taken."""
    for k in range(n):
        if run.begin_step():  # the end (adaptive: the step's dt set)
            return k
        schemes.step_usl(run, run)
        if run.stop:
            return k
        if run.handover:
            return k + 1
    return n


@njit(cache=True)
def run_cd(run, n):
    """Up to n central-difference steps; returns the number taken."""
    for k in range(n):
        if run.begin_step():  # the end (adaptive: the step's dt set)
            return k
        schemes.step_cd(run, run)
        if run.stop:
            return k
        if run.handover:
            return k + 1
    return n


@njit(cache=True)
def run_rk4(run, n):
    """Up to n classical Runge-Kutta steps; returns the number taken."""
    for k in range(n):
        if run.begin_step():  # the end (adaptive: the step's dt set)
            return k
        schemes.step_rk4(run, run)
        if run.stop:
            return k
        if run.handover:
            return k + 1
    return n


LOOPS = {"musl": run_musl, "usl": run_usl, "cd": run_cd, "rk4": run_rk4}
