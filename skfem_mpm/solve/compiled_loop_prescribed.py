"""Prescribed grid velocities on a compiled run (``Prescribed``): part of
the source of the generated loop modules (not imported as a module; see
:mod:`skfem_mpm.solve.compiled_loop_ops`).

The compiled executor's constraint values, on the same kernels (the lumped
solve, the USL grid pass, the tiny-mass merge and the consistent-mass CG of
:mod:`skfem_mpm.solve.compiled_loop_mass` take them as ``values``):
the constrained dofs of a prescribed item (component c, dofs, velocity(t))
get v(t) in the velocity solve, a = (v(t + dt) - v(t)) / dt in the
acceleration solve and v(t + dt) in MUSL's re-projection
(``CompiledExecutor.solve_grid``, ``project_velocity``); an rk4 stage at
t_s = t + c dt gets v(t_s) and the central difference of
:func:`skfem_mpm.solve.runge_kutta.prescribed_acceleration`. Fixed dofs
keep 0. The reactions come from the step's grid arrays as without
prescribed values.

velocity(t) is Python: :class:`~skfem_mpm.solve.compiled_loop.StepLoop`
evaluates the items' values before each call of the loop at the steps'
times (``State.time_at``) into ``table`` (steps, columns, 3, items): row
``step - first_step``, column 0 at t (rk4: 1 at t + dt/2, 2 at t + dt),
entries (the velocity, the acceleration, the velocity at t + dt, used by
MUSL); it computes them with the executor's own expressions, so the values
have the same bits. ``set_constraint_values`` writes a step's (or stage's)
into the grid arrays ``velocity``, ``acceleration``, ``end_velocity``.
"""


@structref.register
class PrescribedType(types.StructRef):
    def preprocess_fields(self, fields):
        return tuple((name, types.unliteral(t)) for name, t in fields)


PrescribedType.__name__ = PrescribedType.__qualname__ = f"PrescribedType_{VARIANT}"
globals()[PrescribedType.__name__] = PrescribedType


PRESCRIBED_FIELDS = (
    # the items: component, their dofs (item k: dofs[starts[k]:starts[k + 1]])
    "comps", "dofs", "starts",
    # the values at the steps' times (see the module); the step of row 0
    "table", "first_step",
    # the grid's constraint values of the current step or stage (dofs, dim)
    "velocity", "acceleration", "end_velocity",
)


class Prescribed(structref.StructRefProxy):
    """The prescribed velocities of a compiled run."""

    def __new__(cls, *fields):
        return structref.StructRefProxy.__new__(cls, *fields)


structref.define_proxy(Prescribed, PrescribedType, list(PRESCRIBED_FIELDS))


@njit(cache=True)
def new_prescribed(*fields):
    """A Prescribed with ``fields`` in the order of PRESCRIBED_FIELDS."""
    return Prescribed(*fields)


@njit(cache=True)
def set_prescribed_table(pv, table, first_step):
    """The items' values at the times of the steps from ``first_step`` on."""
    pv.table = table
    pv.first_step = first_step


def _prescribed(run):
    """Whether the run (its numba type) prescribes grid velocities."""
    return not isinstance(run.field_dict["prescribed"], types.NoneType)


@overload_method(RunType, "set_constraint_values")
def _set_constraint_values(run, column):
    if not _prescribed(run):
        return lambda run, column: None

    def impl(run, column):
        """The grid's constraint values at the table's ``column`` of the step."""
        pv = run.prescribed
        values = pv.table[run.step - pv.first_step, column]
        for k in range(pv.comps.shape[0]):
            c = pv.comps[k]
            for j in range(pv.starts[k], pv.starts[k + 1]):
                d = pv.dofs[j]
                pv.velocity[d, c] = values[0, k]
                pv.acceleration[d, c] = values[1, k]
                pv.end_velocity[d, c] = values[2, k]
    return impl


@overload_method(RunType, "constraint_values")
def _constraint_values(run, rhs, kind):
    if not _prescribed(run):
        return lambda run, rhs, kind: (rhs, False)

    def impl(run, rhs, kind):
        """(the constraint values of a solve, True): ``kind`` 0 the
        acceleration, 1 the velocity, 2 the velocity at t + dt."""
        pv = run.prescribed
        if kind == 0:
            return pv.acceleration, True
        if kind == 1:
            return pv.velocity, True
        return pv.end_velocity, True
    return impl
