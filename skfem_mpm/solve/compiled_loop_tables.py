"""The Python side of the compiled loop's tabulated effects: a body force's
f_p, the prescribed velocities and a side traction's tau, evaluated ahead at the times of the
steps a call of the loop may take (the effects' functions are Python;
the loop reads the tables: :mod:`skfem_mpm.solve.compiled_loop_body_force`,
:mod:`skfem_mpm.solve.compiled_loop_prescribed`,
:mod:`skfem_mpm.solve.compiled_loop_traction`).

Each table covers the steps from ``first`` to ``first + rows``; a loop that
stopped early is called again on steps the table holds, which it keeps.
The times are the executor's: a step's t is ``State.time_at`` (the state's
own t for the current step), an rk4 stage's t + c dt (c = 0, 1/2, 1). With
an adaptive step the times of later steps are not known before the loop
has taken the steps: a table then holds the current step only, and a
table that reads dt has it set first (``State.next_step_size``, the dt the
loop computes by the same rule from the same particles). An
evaluation that raises ends the table before that step: the executor then
takes the step and raises as it does without the loop.
"""
import numpy as np

from .runge_kutta import velocity_rate

__all__ = ["ForceTable", "PrescribedTable", "TractionTable", "reference_forces"]

STAGE_TIMES = {"rk4": (0.0, 0.5, 1.0)}
"""The fractions c of dt at which a scheme evaluates its forces (others: t only)."""


def reference_forces(forces):
    """The particle forces among ``forces`` whose ``reference_only`` is True
    (see :class:`skfem_mpm.effects.ParticleForce`), in order."""
    return [f for f in forces if f.reference_only]


def _step_times(state, n):
    """The times of the next n steps (the executor's)."""
    return [state.t if j == 0 else state.time_at(state.step + j) for j in range(n)]


class _Table:
    """Rows of a table of the steps from ``first`` on (see the module)."""

    def __init__(self, scheme):
        self.stages = STAGE_TIMES.get(scheme, (0.0,))
        self.first, self.rows = 0, 0

    def held(self, step):
        """The steps from ``step`` on that the table holds (0: none)."""
        if self.first <= step < self.first + self.rows:
            return self.first + self.rows - step
        return 0

    @property
    def reads_dt(self):
        """Whether an evaluation reads the step's dt (a stage after the first)."""
        return len(self.stages) > 1

    def cover(self, state, n):
        """The number of steps (<= n) from the state's on that the table
        holds, evaluating it when it holds none of them (adaptive: the
        current step's row only)."""
        held = self.held(state.step)
        if held:
            return min(n, held)
        if state.adaptive:
            n = 1
            if self.reads_dt:
                state.next_step_size()
        n = min(n, self.chunk)
        times = _step_times(state, n)
        table = self.empty(n)
        for j, t in enumerate(times):
            try:
                for column, c in enumerate(self.stages):
                    self.evaluate(state, t, c, table[j, column])
            except Exception:  # the executor takes this step and raises
                n = j
                break
        if n:
            self.set(np.ascontiguousarray(table[:n]), int(state.step))
        self.first, self.rows = int(state.step), n
        return n


class ForceTable(_Table):
    """f_p of the reference-configuration forces, summed in order as
    ``CompiledExecutor.external`` sums them, at each step's times; a chunk
    of at most BYTES per evaluation."""

    BYTES = 1 << 25

    def __init__(self, module, forces, state):
        super().__init__(state.method.scheme)
        p = state.particles
        self.module, self.forces = module, forces
        self.shape = (len(self.stages), p.n, p.dim)
        self.chunk = max(1, self.BYTES // (8 * int(np.prod(self.shape))))
        self.record = module.new_body_force(np.zeros((1,) + self.shape), 0,
                                            np.arange(p.n, dtype=np.int64))

    def empty(self, n):
        return np.empty((n,) + self.shape)

    def evaluate(self, state, t, c, out):
        total = None
        for f in self.forces:
            term = f.forces(state.particles, t + c * state.dt)
            total = term if total is None else total + term
        out[...] = total

    def set(self, table, first):
        self.module.set_body_force_table(self.record, table, first)

    def compile(self):
        self.set(np.zeros((1,) + self.shape), 0)


class PrescribedTable(_Table):
    """Each prescribed item's velocity, acceleration and velocity at t + dt
    (rk4: velocity and acceleration at each stage's time), by the
    executor's expressions (``CompiledExecutor.solve_grid``,
    :func:`skfem_mpm.solve.runge_kutta.prescribed_acceleration`)."""

    chunk = 1 << 62  # a few numbers per step
    reads_dt = True  # v(t + dt), (v(t + dt) - v(t)) / dt

    def __init__(self, module, state):
        super().__init__(state.method.scheme)
        c = state.constraints
        self.module, self.constraints = module, c
        nd, dim = state.grid.ndofs, state.grid.dim
        items = c.prescribed
        self.shape = (len(self.stages), 3, len(items))
        dofs = [np.asarray(d, dtype=np.int64).ravel() for _, d, _ in items]
        zeros = np.zeros
        self.record = module.new_prescribed(
            np.array([comp for comp, _, _ in items], dtype=np.int64),
            np.concatenate(dofs), np.cumsum([0] + [d.size for d in dofs]).astype(np.int64),
            zeros((1,) + self.shape), 0, zeros((nd, dim)), zeros((nd, dim)), zeros((nd, dim)))

    def empty(self, n):
        return np.zeros((n,) + self.shape)

    def evaluate(self, state, t, c, out):
        values, dt = self.constraints.item_values, state.dt
        if len(self.stages) > 1:  # a Runge-Kutta stage at t + c dt
            t = t + c * dt
            out[0] = values(t)
            out[1] = velocity_rate(values, t, dt)
            return
        v = values(t)
        end = values(t + dt)
        out[0], out[1], out[2] = v, (end - v) / dt, end

    def set(self, table, first):
        self.module.set_prescribed_table(self.record, table, first)

    def compile(self):
        self.set(np.zeros((1,) + self.shape), 0)


class TractionTable(_Table):
    """tau(t) of a side traction (the loop's SideTraction reads column 0 at
    t, 1 at t + dt/2, 2 at t + dt); a tau that is not one vector of the
    grid's dimension ends the table there (the executor takes the step)."""

    chunk = 1 << 62  # a few numbers per step

    def __init__(self, module, side, record, state):
        super().__init__(state.method.scheme)
        self.module, self.side, self.record = module, side, record
        self.dim = state.grid.dim

    def empty(self, n):
        return np.zeros((n, 3, self.dim))

    def evaluate(self, state, t, c, out):
        tau = np.asarray(self.side.effect.traction(None, t + c * state.dt), dtype=np.float64)
        if tau.size != self.dim:
            raise ValueError(f"tau(t) must give {self.dim} components, got {tau.size}")
        out[...] = tau.reshape(self.dim)

    def set(self, table, first):
        self.module.set_traction_table(self.record, table, first)

    def compile(self):
        self.set(np.zeros((1, 3, self.dim)), 0)
