"""A traction on a side of the body on a compiled run: part of the source of
the generated loop modules (not imported as a module; see
:mod:`skfem_mpm.solve.compiled_loop_ops`).

The compiled executor's side traction (``CompiledExecutor._side_traction_force``,
:mod:`skfem_mpm.kernels.traction`) in the same order on the same kernels:
the loaded faces of the outermost particles (``side_faces``), their loads
a_p tau(t), and the grid force f_i = sum_p a_p tau N_i(face_p) as the p2g
kernel's external force of points at the faces that carry nothing else,
added to the particles' force before gravity. tau(t) is a Python function:
:class:`~skfem_mpm.solve.compiled_loop.StepLoop` evaluates it before each
call of the loop at the times of the steps it may take (rk4: at t, t + dt/2
and t + dt of each step) into ``tau``, row ``step - first_step``. The work
of the loads over a step (the step's displacements; rk4: each stage's
power) is ``loads_power``. A face outside the grid stops the loop: the
executor takes the step and raises.
"""


@structref.register
class SideTractionType(types.StructRef):
    def preprocess_fields(self, fields):
        return tuple((name, types.unliteral(t)) for name, t in fields)


SideTractionType.__name__ = SideTractionType.__qualname__ = f"SideTractionType_{VARIANT}"
globals()[SideTractionType.__name__] = SideTractionType


TRACTION_FIELDS = (
    # the loaded particles, their share a_p of the load, reference size,
    # the side's axis and sign, the grid's bounds (dim, 2)
    "index", "share", "size", "axis", "sign", "bounds",
    # tau at the steps' times: (steps, 3, dim), column 0 at t, 1 at t + dt/2,
    # 2 at t + dt; the step of row 0
    "tau", "first_step",
    # the faces and loads of the last evaluation; the faces as particles
    # that carry nothing else (zero velocity, mass, volume, stress)
    "faces", "loads", "zero_v", "zero_m", "zero_stress",
    # the grid force and the p2g kernel's other outputs (not read), the
    # node range of the force (kernels.scatter.reduce_fields)
    "mass", "momentum", "force", "mass_range", "occupied",
)


class SideTraction(structref.StructRefProxy):
    """The side traction of a compiled run."""

    def __new__(cls, *fields):
        return structref.StructRefProxy.__new__(cls, *fields)


structref.define_proxy(SideTraction, SideTractionType, list(TRACTION_FIELDS))


@njit(cache=True)
def new_side_traction(*fields):
    """A SideTraction with ``fields`` in the order of TRACTION_FIELDS."""
    return SideTraction(*fields)


@njit(cache=True)
def set_traction_table(st, tau, first_step):
    """tau(t) at the times of the steps from ``first_step`` on (see the module)."""
    st.tau = tau
    st.first_step = first_step


@njit(cache=True)
def traction_loads(st, x, V, V0, row, column):
    """The faces and loads a_p tau of the particles (x, V) at the time of
    table row ``row``, column ``column``; False when a face lies outside the
    grid."""
    if SIDE_FACES(x, V, V0, st.index, st.size, st.axis, st.sign, st.bounds, st.faces) >= 0:
        return False
    tau = st.tau[row, column]
    for j in range(st.loads.shape[0]):
        for c in range(st.loads.shape[1]):
            st.loads[j, c] = st.share[j] * tau[c]
    return True
