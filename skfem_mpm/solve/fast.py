"""The compiled fast path of the MPM step on spline grids.

Same method as the reference step functions of :mod:`skfem_mpm.solve.steps`
(which the tests compare it with), executed by the fused kernels of
:mod:`skfem_mpm.kernels.mpm`:

    USL / CD   p2g kernel -> grid solve -> g2p kernel (FLIP velocity, positions,
               velocity gradient; linear elasticity fused)
    MUSL       p2g kernel -> grid solve (a) -> g2p2g kernel (v_p^new and its
               grid momentum) -> grid solve (v) -> g2p kernel (positions, L)

Consistent mass: a kernel assembles M into a fixed stencil pattern (and the
per-dof stiffness weights of the fast-dof guard); the grid system of
:mod:`skfem_mpm.solve.grid_system` solves it (sparse LU or CG).

It applies to SplineGrid scenes with no reconstruction and the schemes usl,
cd, musl (``Method(backend="numpy")`` or any other combination
uses the reference path). Gravity costs one grid operation (g times the
nodal mass); other particle forces enter the p2g kernel as one array.
The kernels write the new state into a second set of particle arrays; it
becomes current only when the step's checks pass, so a failed step leaves
the last good state untouched. The p2g kernel's time is reported under
``p2g`` (it fuses locate, basis and p2g), the g2p kernel's under ``g2p``
(locate, basis, g2p and, for linear elasticity, constitutive).
"""
import numpy as np

from ..errors import InvalidState
from ..materials import LinearElastic
from ..spline import SplineGrid

__all__ = ["fast_path_applies", "FastStepper", "StencilSystem"]


class StencilSystem:
    """Consistent-mass solves on the grid's fixed stencil, compiled.

    Same equations as :class:`~skfem_mpm.solve.grid_system.GridSystem`
    without tiny-mass merging (a step with tiny masses uses that class):
    the fast-dof rows are lumped, constrained and massless dofs keep their
    known values (moved to the right-hand side), and conjugate gradients
    preconditioned with the lumped mass, warm started from the previous
    step, solve all components (and several right-hand sides, see
    :meth:`solve_many`) at once. Only the free dofs enter the iteration:
    for each constraint pattern a kernel copies their rows of the stencil
    into a compact row-by-row (ELL) matrix. The preconditioner is the
    Kronecker one of :mod:`skfem_mpm.kernels.kronecker` (``"kronecker"``,
    default), with the fringe correction of :mod:`skfem_mpm.kernels.fringe`
    on ``FRINGE_LAYERS`` layers of the free-dof set's edge once the
    Kronecker step alone has needed ``FRINGE_FROM`` iterations (0 layers:
    never), or the inverse lumped mass (``"lumped"``).
    """

    preconditioner = "kronecker"
    FRINGE_LAYERS = 3
    max_iterations = None  # per CG run; None: 10 x the free dofs + 100
    iteration_log = None  # a list: each CG run appends its iterations (benchmarks)
    LUMPED_ROW = 0.2
    _no_kronecker = (np.ones((1, 1)), np.ones((1, 1)), np.zeros(1, dtype=np.int64), np.ones(1),
                     np.zeros((1, 1, 1)), 1)

    def __init__(self, kernels, stencil, lumped, constraints, fast, warm, rtol=1e-13):
        self.k = kernels
        self.geometry = kernels.stencil_geometry
        self.stencil = stencil
        self.constraints = constraints
        self.warm = warm
        self.rtol = rtol
        self.small_dofs = 0
        self.lumped = lumped
        self.inactive = lumped <= 0
        self.fast = np.ascontiguousarray(fast, dtype=np.float64)
        mask = constraints.mask
        # what depends only on the free-dof sets is kept on the kernels
        # between steps (it changes only when particles enter or leave a
        # support or the constraints change)
        self.memo = kernels.__dict__.setdefault("stencil_memo", {})
        key = mask.tobytes() + self.inactive.tobytes()
        kept = self.memo.get("groups")
        if kept is None or kept[0] != key:
            groups = {}  # constraint pattern -> (components, free rows, dof -> row)
            for c in range(mask.shape[1]):
                pattern = mask[:, c].tobytes()
                if pattern not in groups:
                    rows = np.flatnonzero(~(mask[:, c] | self.inactive))
                    index = np.full(lumped.size, -1, dtype=np.int64)
                    index[rows] = np.arange(rows.size)
                    groups[pattern] = ([], rows, index)
                groups[pattern][0].append(c)
            reaction_rows = np.flatnonzero(np.logical_or.reduce(list(mask.T)))  # 20x any(axis=1)
            kept = self.memo["groups"] = (key, groups, reaction_rows)
        self.groups = {pattern: [comps, rows, index, None]
                       for pattern, (comps, rows, index) in kept[1].items()}
        self.reaction_rows = kept[2]
        self._stale_fringe = {}
        self.iterations = 0

    def _compact(self, group, need_fixed=False):
        """The group's free-dof matrix (built once per step and pattern; its
        fixed-column part F only when ``need_fixed``: nonzero fixed values)."""
        from ..kernels.mpm import compact_system

        comps, rows, index, built = group
        if built is not None and (built[7] or not need_fixed):
            return built
        ns = self.stencil.shape[1]
        g = list(self.groups.values()).index(group)  # scratch arrays per group
        A, F = self.k.scratch(f"A{g}", (rows.size, ns)), self.k.scratch(f"F{g}", (rows.size, ns))
        cols = self.k.scratch(f"cols{g}", (rows.size, ns), np.int32)
        fcols = self.k.scratch(f"fcols{g}", (rows.size, ns), np.int32)
        key = rows.tobytes()
        write_cols = self.memo.get(f"cols{g}") != key  # cols{g} holds this set's columns
        compact_system(self.stencil, *self.geometry, rows, index, self.fast, A, cols, F,
                       fcols, write_cols, need_fixed)
        self.memo[f"cols{g}"] = key
        if built is not None:  # F added to this step's system (A rewritten, equal)
            built = group[3] = built[:7] + (True,)
            return built
        inv_diag = 1.0 / self.lumped[rows]
        kron = fringe = None
        if self.preconditioner == "kronecker" and rows.size:
            from ..kernels.kronecker import KroneckerData

            centre = (ns - 1) // 2
            kron = KroneckerData(*self.k.axis_mass(), self.geometry, rows, self.lumped,
                                 self.fast[rows] >= self.LUMPED_ROW, A[:, centre].copy(),
                                 previous=self.memo.get(f"kronecker{g}"))
            self.memo[f"kronecker{g}"] = kron
            if self.FRINGE_LAYERS > 0 and (self.FRINGE_FROM <= 0
                                           or f"fringe{g}_on" in self.warm):
                fringe = self._fringe(g, rows, A, cols)
        built = group[3] = (A, cols, F, fcols, inv_diag, kron, fringe, need_fixed)
        return built

    # The particles move little in a step, so the fringe factors of an
    # earlier step's M_FF stay a close symmetric positive definite
    # approximation of M_FF^-1: they are kept while CG needs at most
    # FRINGE_SLACK iterations more than in the first solve with them (the
    # factorisation with its set-up costs about as much as three CG
    # iterations at 128 x 128 cells). The block they came from is kept in
    # the warm data, so a restart from a checkpoint factorises the same
    # block and continues bit for bit.
    FRINGE_SLACK = 1
    # The fringe correction costs two sparse triangular solves and two
    # partial products per iteration, worth it where the Kronecker
    # preconditioner alone needs many iterations (25 on the 2D bench block,
    # 6 with the correction) but not where it needs few (8 on the small soil
    # column, 6 with it, and 25% more solve time). A group turns it on, for
    # the rest of the run, after a CG run with the Kronecker preconditioner
    # alone took at least FRINGE_FROM iterations (the switch is warm data,
    # so restarts follow it).
    FRINGE_FROM = 12

    def _fringe(self, g, rows, A, cols):
        """The fringe correction's factors for group g, or None (the
        pattern is kept on the kernels while the free-dof set stays)."""
        from ..kernels.fringe import FringeFactor, FringePattern

        cache = self.k.__dict__.setdefault("fringe_patterns", {})
        pattern = cache.get(g)
        if pattern is None or pattern.key != rows.tobytes() or \
                pattern.layers != self.FRINGE_LAYERS:
            pattern = cache[g] = FringePattern(rows, cols, self.geometry, self.FRINGE_LAYERS)
        if not pattern.fringe.size:
            return None
        key = f"fringe{g}"
        stored_rows, data = self.warm.get(key + "_rows"), self.warm.get(key + "_block")
        self._stale_fringe[g] = True  # factors of an earlier step's block
        if stored_rows is None or not np.array_equal(stored_rows, rows) or \
                data.size != pattern.indices.size:
            self._stale_fringe[g] = False
            data = pattern.block_values(A)
            for name in [k for k in self.warm if k.startswith(key + "_fresh")]:
                del self.warm[name]
            self.warm.update({key + "_rows": rows.copy(), key + "_block": data})
        if pattern.factor is None or pattern.factor.data is not data:
            pattern.factor = FringeFactor(data, pattern)
        return pattern.factor

    def _keep_fringe(self, g, kinds, iterations):
        """After a CG run with group g's fringe factors (on the right-hand
        sides ``kinds``): drop them (the next step factorises anew) when it
        took more than FRINGE_SLACK iterations beyond the first run with
        them on the same kinds."""
        name = f"fringe{g}_fresh_" + "+".join(kinds)
        fresh = self.warm.get(name)
        if fresh is None:
            self.warm[name] = np.array([iterations])
        elif iterations > fresh[0] + self.FRINGE_SLACK:
            self.warm.pop(f"fringe{g}_rows", None)

    def solve(self, rhs, values, kind):
        """x with M x = rhs on the free dofs and x = values on the fixed ones."""
        return self.solve_many([(rhs, values, kind)])[0]

    def solve_many(self, problems):
        """Several solves with this matrix in one CG run: ``problems`` is a
        list of (rhs, values, kind) (kind names the warm start); returns the
        solutions in order."""
        from numba import get_num_threads

        from ..kernels.fringe import FringeFactor
        from ..kernels.mpm import compact_problem, ell_pcg, expand_problem

        outs = []
        for rhs, values, kind in problems:
            out = np.array(values, dtype=np.float64, copy=True)  # fixed dofs keep theirs
            outs.append(out)
        has_values = [bool(values.any()) for _, values, _ in problems]
        for g, group in enumerate(self.groups.values()):
            comps, rows, index, _ = group
            A, cols, F, fcols, inv_diag, kron, fringe, _ = self._compact(group, any(has_values))
            comps = np.asarray(comps, dtype=np.int64)
            nc = len(problems) * comps.size
            b = self.k.scratch(f"b{g}", (rows.size, nc))
            x = self.k.scratch(f"x{g}", (rows.size, nc))
            for i, (rhs, values, kind) in enumerate(problems):
                prev = self.warm.get(kind)
                has_prev = prev is not None and prev.shape == rhs.shape
                compact_problem(rows, rhs, values, has_values[i],
                                prev if has_prev else rhs, has_prev, comps, i * comps.size,
                                F, fcols, b, x)
            if rows.size:
                before = self.iterations
                nt = get_num_threads()
                mode = 0 if kron is None else 1 if fringe is None else 2
                pre = kron.args(b.shape[1], nt) if kron is not None else self._no_kronecker
                extra = fringe.args(b.shape[1]) if fringe is not None else FringeFactor.no_args()
                work = self.k.scratch("cg", (6,) + b.shape)
                limit = self.max_iterations or 10 * rows.size + 100
                problem = np.repeat(np.arange(len(problems)), comps.size)
                its = ell_pcg(A, cols, inv_diag, mode, pre, extra, b, x, problem, self.rtol,
                              limit, nt, work)
                if its < 0 and fringe is not None and self._stale_fringe[g]:
                    # factors of an earlier step: retry with the current block's
                    self.warm.pop(f"fringe{g}_rows", None)
                    fringe = self._fringe(g, rows, A, cols)
                    group[3] = group[3][:6] + (fringe,) + group[3][7:]
                    more = ell_pcg(A, cols, inv_diag, mode, pre, fringe.args(b.shape[1]), b, x,
                                   problem, self.rtol, limit, nt, work)
                    its = -its + more if more > 0 else its - abs(more)
                if its < 0:
                    raise InvalidState(f"consistent-mass CG stopped above its tolerance "
                                       f"{self.rtol:g} after {-its} iterations")
                self.iterations += its
                if mode == 1 and self.FRINGE_LAYERS > 0 and its >= self.FRINGE_FROM:
                    self.warm[f"fringe{g}_on"] = np.array([1])
                if fringe is not None:
                    self._keep_fringe(g, [kind for _, _, kind in problems],
                                      self.iterations - before)
                if self.iteration_log is not None:
                    self.iteration_log.append(self.iterations - before)
            for i, out in enumerate(outs):
                expand_problem(rows, x, comps, i * comps.size, out)
        return outs

    def remember(self, kind, x):
        self.warm[kind] = x.copy()

    def shift_guess(self, kind, dx):
        from .grid_system import shift_guess

        shift_guess(self.warm, kind, dx)

    def residual(self, x, rhs):
        """M x - rhs with the fast rows lumped, on the constrained dofs (the
        rows the reactions read; zero elsewhere)."""
        from ..kernels.mpm import stencil_rows_product

        rows = self.reaction_rows
        y = np.empty((rows.size, x.shape[1]))
        stencil_rows_product(self.stencil, *self.geometry, rows, self.inactive, self.fast,
                             np.ascontiguousarray(x), y)
        out = np.zeros_like(rhs)
        out[rows] = y - rhs[rows]
        return out


def fast_path_applies(state):
    """(True, '') or (False, the reason the reference path is used)."""
    m = state.method
    if state.backend != "numba":
        return False, "backend numpy"
    if not isinstance(state.grid, SplineGrid):
        return False, "not a SplineGrid"
    if m.reconstruction != "none":
        return False, "reconstruction"
    if m.scheme not in ("usl", "cd", "musl"):
        return False, f"scheme {m.scheme}"
    return True, ""


class FastStepper:
    """Runs the steps of one simulation on the compiled kernels."""

    def __init__(self, state):
        from ..kernels.mpm import Kernels

        self.kernels = Kernels(state.grid)
        self.gravity = np.zeros(state.grid.dim)
        self.gravity_work = False
        self.other_forces = []
        for f in state.forces:
            if f.__class__.__name__ == "Gravity":
                self.gravity = self.gravity + f.g
                self.gravity_work = True
            else:
                self.other_forces.append(f)
        self.fused = len(state.bodies) == 1 and type(state.bodies[0][0]) is LinearElastic
        timer = state.timer
        timer.note_fused("p2g", ("locate", "basis", "p2g"))
        timer.note_fused("g2p", ("locate", "basis", "g2p")
                         + (("constitutive",) if self.fused else ()))
        self._spare = None
        self._owned = set()
        self._acc = None
        nd, dim = state.grid.ndofs, state.grid.dim
        self._v_old = np.empty((nd, dim))
        self._v_new = np.empty((nd, dim))
        self._a = np.empty((nd, dim))
        self._no_gravity = np.zeros(dim)

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
        for name in ("m", "X", "V0", "body", "F"):
            setattr(spare, name, getattr(p, name))
        if not self.fused:
            spare.stress, spare.V = p.stress, p.V  # replaced by the material update
        return spare

    # ------------------------------------------------------------------- step
    def external(self, state):
        """Particle forces other than gravity (effects phase), the grid force
        of side tractions, and the particle forces whose work is counted."""
        p = state.particles
        fext, grid_force, work_forces = None, None, None
        if self.other_forces:
            with state.timer("effects"):
                for f in self.other_forces:
                    term = f.forces(p, state.t)
                    work_forces = term if work_forces is None else work_forces + term
                    if hasattr(f, "grid_forces"):
                        g = f.grid_forces(p, state.t, state.grid)
                        grid_force = g if grid_force is None else grid_force + g
                    else:
                        fext = term if fext is None else fext + term
        return fext, grid_force, work_forces

    def _small_dofs(self, state, mass):
        """Number of tiny-mass dofs this step (the reference merge takes over
        when there are any)."""
        if state.method.small_mass <= 0:
            return 0
        _, count = self.kernels.small_mass(mass, state.method.small_mass)
        state.small_dofs_max = max(state.small_dofs_max, count)
        return count

    def _reference_solve(self, state, mass, rhs, values, kind, gravity=None):
        from .grid_system import GridSystem

        full = rhs if gravity is None else rhs + mass[:, None] * gravity[None, :]
        system = GridSystem(mass, state.constraints, None, state.adjacency,
                            state.method.small_mass)
        return system.solve(full, np.zeros_like(rhs) if values is None else values, kind)

    def solve(self, state, mass, rhs, values, kind, out, small, gravity=None):
        """Lumped M x = rhs (+ gravity as an acceleration on free dofs) with
        the constraints, into ``out``."""
        if small:
            out[:] = self._reference_solve(state, mass, rhs, values, kind, gravity)
            return out
        g = self._no_gravity if gravity is None else gravity
        return self.kernels.solve(mass, rhs, g, state.constraints.mask, values, out)

    # Which consistent-mass solver is faster depends on the scene. When the
    # CG iterated over the whole grid with a lumped preconditioner (about
    # 150 iterations at rtol 1e-13), a floating block at 128 x 128 took
    # CG 341 ms against LU 99 ms per step. The CG now runs on the free dofs
    # with the Kronecker preconditioner and its fringe correction: on the
    # 2D bench block 6 iterations per step where it carries stress waves
    # (14 ms per step; a fresh LU costs 129 ms on the falling block).
    # "auto" times one CG and one LU acceleration solve on the first step
    # whose CG solve needs at least 20 iterations and keeps the faster for
    # the run (CG stays when no solve is that hard); the choice is kept in
    # the checkpoint's warm data.

    def _use_cg(self, state):
        solver = state.method.mass_solver
        if solver == "direct":
            return False
        if solver == "cg":
            return True
        choice = state.warm.get("auto_solver")
        return choice is None or int(choice[0]) == 0

    def _choose_solver(self, state, mass, problems, stencil, K):
        """'auto', first step: time the CG solves just made against LU."""
        import time

        from .grid_system import GridSystem

        M = self.kernels.stencil_csr(stencil)
        t0 = time.perf_counter()
        lu = GridSystem(mass, state.constraints, M, state.adjacency, state.method.small_mass,
                        "direct", {}, fast_rows=self._fast_rows_fn)
        for rhs, values, kind in problems:
            lu.solve(rhs, values, kind)
        state.warm["auto_solver"] = np.array([1 if time.perf_counter() - t0 < self._cg_time
                                              else 0])

    def _grid_solve(self, state, system, mass, rhs, values, kind, out, small, gravity=None):
        """M x = rhs: the consistent system when there is one, else lumped."""
        if system is None:
            return self.solve(state, mass, rhs, values, kind, out, small, gravity)
        return self._consistent_solves(state, system, mass, [(rhs, values, kind)], [out])[0]

    def _consistent_solves(self, state, system, mass, problems, outs):
        """Consistent M x = rhs for each (rhs, values or None, kind) into
        ``outs``; a stencil system solves them in one CG run."""
        import time

        problems = [(rhs, np.zeros_like(rhs) if values is None else values, kind)
                    for rhs, values, kind in problems]
        if isinstance(system, StencilSystem):
            t0 = time.perf_counter()
            before = system.iterations
            xs = system.solve_many(problems)
            for (_, _, kind), x in zip(problems, xs):
                system.remember(kind, x)
            representative = system.iterations - before >= 20  # not a trivial early solve
            if state.method.mass_solver == "auto" and "auto_solver" not in state.warm and \
                    representative and any(kind == "acceleration" for _, _, kind in problems):
                self._cg_time = time.perf_counter() - t0
                self._choose_solver(state, mass, problems, *self._stencil_K)
        else:
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

    def _consistent_system(self, state, mass, stencil, K):
        """The step's consistent-mass system: compiled stencil CG, or the
        general grid system (sparse LU with ``mass_solver="direct"``, and
        whenever tiny-mass dofs must be merged)."""
        from .grid_system import GridSystem
        from .timestep import fast_dof_limit, lumping_fraction

        guard = state.method.frequency_guard
        limit = None
        if guard > 0:
            limit = guard * fast_dof_limit(state.grid.degree) / (state.dt * state.wave_speed_now) ** 2
        small = self._small_dofs(state, mass)
        fast_rows = None if limit is None else (
            lambda diag: lumping_fraction(K / (limit * np.maximum(diag, 1e-300))))
        self._fast_rows_fn = fast_rows
        self._stencil_K = (stencil, K)
        if self._use_cg(state) and not small:
            from ..kernels.mpm import fast_row_fractions

            fast = self.kernels.scratch("fast_rows", mass.size)
            if limit is not None:  # fast_rows of the dofs with mass, in one kernel
                fast_row_fractions(K, stencil, mass, limit, fast)
            else:
                fast[:] = 0.0
            return StencilSystem(self.kernels, stencil, mass, state.constraints, fast, state.warm)
        M = self.kernels.stencil_csr(stencil)
        solver = "cg" if state.method.mass_solver == "cg" else "direct"
        return GridSystem(mass, state.constraints, M, state.adjacency, state.method.small_mass,
                          solver, state.warm, fast_rows=fast_rows)

    def step(self, state):
        p, dt = state.particles, state.dt
        c = state.constraints
        k = self.kernels
        consistent = state.method.mass == "consistent"
        fext, grid_force, work_forces = self.external(state)
        with state.timer("p2g"):
            mass, momentum, force = k.p2g(p, fext)
        if consistent:
            with state.timer("mass_matrix"):
                M, K = k.consistent_stencil(p)
        scheme = state.method.scheme
        gravity = self.gravity if self.gravity_work else None
        with state.timer("solve"):
            if grid_force is not None:
                force += grid_force
            if consistent:
                system = self._consistent_system(state, mass, M, K)
                small = True  # solves go through the system
                if gravity is not None:
                    force += mass[:, None] * gravity[None, :]
                    gravity = None
            else:
                system = None
                small = self._small_dofs(state, mass)
            t_values = c.values(state.t) if c.prescribed else None
            a_values = (c.values(state.t + dt) - t_values) / dt if c.prescribed else None
        v_old = None
        if state.damping:
            with state.timer("effects"):
                v_old = self._grid_solve(state, system, mass, momentum, t_values, "velocity",
                                         self._v_old, small)
                if gravity is not None:
                    force = force + mass[:, None] * gravity[None, :]
                    gravity = None
                for d in state.damping:
                    force = d.apply(force, v_old)
        factor = 0.5 if (scheme == "cd" and state.step == 0) else 1.0
        with state.timer("solve"):
            if scheme != "musl" and not small and not state.damping:
                k.usl_grid(mass, momentum, force, self._no_gravity if gravity is None
                           else gravity, c.mask, t_values, a_values, factor * dt,
                           self._a, self._v_new)
                a, v_grid = self._a, self._v_new
            elif scheme != "musl" and system is not None and v_old is None:
                a, v_old = self._consistent_solves(
                    state, system, mass, [(force, a_values, "acceleration"),
                                          (momentum, t_values, "velocity")],
                    [self._a, self._v_old])
                v_grid = self._v_new
                np.multiply(a, factor * dt, out=v_grid)
                v_grid += v_old
                system.remember("velocity", v_grid)  # see steps.remember_end_velocity
            else:
                a = self._grid_solve(state, system, mass, force, a_values, "acceleration",
                                     self._a, small, gravity)
                if scheme != "musl":
                    if v_old is None:
                        v_old = self._grid_solve(state, system, mass, momentum, t_values,
                                                 "velocity", self._v_old, small)
                    v_grid = self._v_new
                    np.multiply(a, factor * dt, out=v_grid)
                    v_grid += v_old
                    if system is not None:
                        system.remember("velocity", v_grid)
            if c.any:
                if system is not None:
                    state.reactions = c.reactions(system.residual(a, force))
                else:
                    state.defer_reactions(c, mass, a, force, gravity)
        new = self._new_particles(p)
        acc, L_out = self._buffers(p)
        if scheme == "musl":
            with state.timer("g2p"):
                momentum_new = k.g2p2g(p, a, dt, new.v)
            with state.timer("solve"):
                if system is not None:  # see steps.grid_to_particles
                    system.shift_guess("velocity", dt * a)
                v_grid = self._grid_solve(state, system, mass, momentum_new,
                                          c.values(state.t + dt) if c.prescribed else None,
                                          "velocity", self._v_new, small)
            flip = False
        else:
            flip = True
        material = state.bodies[0][0]
        with state.timer("g2p"):
            bad, out, neg = k.g2p(p, a, v_grid, dt, factor, flip, self.fused, material, new,
                                  L_out, acc if scheme == "cd" else None)
        if neg >= 0:
            raise InvalidState(f"J = det(I + dt L) <= 0 at particle {neg}", particle=neg)
        if bad >= 0:
            raise InvalidState(f"non-finite state (NaN or Inf) at particle {bad}", particle=bad)
        if not self.fused:
            from .steps import update_stress

            new.stress, new.V, new.F = update_stress(state, L_out, particles=p)
        if self.gravity_work:
            state.external_work += float(k.mass_times_displacement(mass, v_grid, dt) @ self.gravity)
        if work_forces is not None:
            state.external_work += float(np.sum(work_forces * (new.u - p.u)))
        if scheme == "cd":
            state.particle_acceleration = acc
            self._acc = None  # the state keeps this one; the next step writes a new one
        if out >= 0:
            self._finish_with_exits(state, new)
        else:
            self._spare = p
            state.particles = new
        state.step += 1
        state.t = state.t_next()

    def _finish_with_exits(self, state, new):
        state.particles = state.without_exits(new)
        self._spare = None
