"""Particle forces of the reference configuration on a compiled run (a
``BodyForce``): part of the source of the generated loop modules (not
imported as a module; see :mod:`skfem_mpm.solve.compiled_loop_ops`).

The compiled executor's particle forces other than gravity and side
tractions (``CompiledExecutor.external``) in the same order on the same
kernels: their sum f_p (a BodyForce: f_p = m_p b(X_p, t)) is the p2g
kernel's external force of the particles, and their work over a step is
sum_p f_p . du_p (the step's displacements; rk4: each stage's power
sum_p f_p . dx_p/dt), :func:`skfem_mpm.kernels.traction.loads_power` over
every particle, counted after gravity's and before a side traction's.

A force qualifies by its ``reference_only`` (see
:class:`skfem_mpm.effects.ParticleForce`): ``forces(particles, t)`` reads
the particles' reference data and t only, so
:class:`~skfem_mpm.solve.compiled_loop.StepLoop` evaluates it (Python)
before a call of the loop at the times of a chunk of the steps it may take
(the executor's times: ``State.time_at``; rk4 also t + dt/2 and t + dt)
into ``forces``, row ``step - first_step``, column 0 at t, 1 at t + dt/2,
2 at t + dt. The chunk is bounded by a memory budget
(``StepLoop.BODY_FORCE_BYTES``); the loop returns to Python at its end.
"""


@structref.register
class BodyForceType(types.StructRef):
    def preprocess_fields(self, fields):
        return tuple((name, types.unliteral(t)) for name, t in fields)


BodyForceType.__name__ = BodyForceType.__qualname__ = f"BodyForceType_{VARIANT}"
globals()[BodyForceType.__name__] = BodyForceType


BODY_FORCE_FIELDS = (
    # f_p at the steps' times: (steps, columns, n, dim); the step of row 0
    "forces", "first_step",
    # every particle's index (loads_power's index)
    "every",
)


class BodyForce(structref.StructRefProxy):
    """The reference-configuration particle forces of a compiled run."""

    def __new__(cls, *fields):
        return structref.StructRefProxy.__new__(cls, *fields)


structref.define_proxy(BodyForce, BodyForceType, list(BODY_FORCE_FIELDS))


@njit(cache=True)
def new_body_force(*fields):
    """A BodyForce with ``fields`` in the order of BODY_FORCE_FIELDS."""
    return BodyForce(*fields)


@njit(cache=True)
def set_body_force_table(bf, forces, first_step):
    """f_p at the times of the steps from ``first_step`` on (see the module)."""
    bf.forces = forces
    bf.first_step = first_step


def _body_force(run):
    """Whether the run (its numba type) carries reference-configuration particle forces."""
    return not isinstance(run.field_dict["body_force"], types.NoneType)


@overload_method(RunType, "particle_forces")
def _particle_forces(run, column):
    if not _body_force(run):
        return lambda run, column: (run.no_force, False)

    def impl(run, column):
        """(f_p of the step at the table's ``column``, True): the p2g
        kernel's external force."""
        bf = run.body_force
        return bf.forces[run.step - bf.first_step, column], True
    return impl


@overload_method(RunType, "particle_forces_power")
def _particle_forces_power(run, column, rates):
    def impl(run, column, rates):
        """sum_p f_p . rates_p (rates: the step's displacements, or a
        stage's dx_p/dt)."""
        bf = run.body_force
        return LOADS_POWER(bf.every, bf.forces[run.step - bf.first_step, column], rates)
    return impl
