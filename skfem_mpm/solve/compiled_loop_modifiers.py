"""Grid modifiers on a compiled run (damping, walls, footings): part of the source of
the generated loop modules (not imported as a module; see
:mod:`skfem_mpm.solve.compiled_loop_ops`).

The compiled executor's grid modifiers (``CompiledExecutor.solve_grid``
and ``project_velocity``, :mod:`skfem_mpm.solve.compiled_modifiers`) in
the same order on the same kernels (:mod:`skfem_mpm.kernels.grid_modifiers`):

    modify_force      before the acceleration solve (rk4: each stage's, at
                      the stage's time t + c dt; a step's own at t):
                      the grid velocity at the start of the step,
                      M v^n = P (lumped, or consistent: one CG run of its
                      own, kept as the velocity's warm start), gravity
                      into the force (lumped mass: f + m g; consistent
                      mass: prepare_grid did it), then every force rule in
                      the scene's order with the lumped mass and v^n
                      (MODIFY_FORCES); the acceleration solve then adds no
                      gravity (``acceleration_gravity``); the rules' states
                      and reactions of a step's first force evaluation
                      (stage c = 0) go into the next row of the log
    modify_velocity   MUSL: every velocity rule on the re-projected grid
                      velocity (MODIFY_VELOCITIES), each from the state its
                      force form left this step (``shared``)

``run.force_rules`` and ``run.velocity_rules`` are None (a run without
them compiles none of this) or :class:`GridRules`, the packed rules of
``kernels.grid_modifiers.pack_rules`` and a log: a rule with a reaction
(a wall, a footing) writes the total force it exerted into its row of
``reactions``, a rule with a state (a footing's clock) its state into its
row of ``states``; after each step's first force evaluation both go into
row ``logged`` of ``log_states`` and ``log_reactions`` (one row per step,
rk4's later stages record nothing: the protocol of :mod:`skfem_mpm.effects`), which
:class:`~skfem_mpm.solve.compiled_loop.StepLoop` hands back to the
modifiers for the steps taken after a call of the loop (a step the loop
stopped is taken again by the executor from the modifiers' own state).
``shared[r]``: the row of the force rules whose state velocity rule r
reads (-1: none). The executor times all of ``modify_force`` as effects
(``run.phase_ns[6]``).
"""


@structref.register
class GridRulesType(types.StructRef):
    def preprocess_fields(self, fields):
        return tuple((name, types.unliteral(t)) for name, t in fields)


GridRulesType.__name__ = GridRulesType.__qualname__ = f"GridRulesType_{VARIANT}"
globals()[GridRulesType.__name__] = GridRulesType


# kernels.grid_modifiers.pack_rules: codes (R,), parameters (R, P),
# offsets (R + 1,), dofs, reactions (R, dim), data_offsets (R + 1,), data,
# states (R, RULE_STATE); the log: states (rows, R, RULE_STATE), reactions
# (rows, R, dim), the rows written; the force rule whose state each rule reads
RULE_FIELDS = ("codes", "parameters", "offsets", "dofs", "reactions", "data_offsets", "data",
               "states", "log_states", "log_reactions", "logged", "shared")


class GridRules(structref.StructRefProxy):
    """The packed grid rules of a compiled run."""

    def __new__(cls, *fields):
        return structref.StructRefProxy.__new__(cls, *fields)


structref.define_proxy(GridRules, GridRulesType, list(RULE_FIELDS))


@njit(cache=True)
def new_grid_rules(*fields):
    """GridRules with ``fields`` in the order of RULE_FIELDS."""
    return GridRules(*fields)


@njit(cache=True)
def rule_log(rules):
    """The log of the last call: its rows written, states and reactions."""
    return rules.logged, rules.log_states, rules.log_reactions


@njit(cache=True)
def reset_rule_log(rules):
    """A call of the loop starts writing the log at its first row."""
    rules.logged = 0


def _force_rules(run):
    """Whether the run (its numba type) modifies the grid force."""
    return not isinstance(run.field_dict["force_rules"], types.NoneType)


def _velocity_rules(run):
    """Whether the run (its numba type) modifies MUSL's re-projected velocity."""
    return not isinstance(run.field_dict["velocity_rules"], types.NoneType)


@overload_attribute(RunType, "acceleration_gravity")
def _acceleration_gravity(run):
    """The gravity the lumped acceleration solve adds: none when
    modify_force has put it into the force."""
    if _force_rules(run):
        return lambda run: run.no_gravity
    return lambda run: run.gravity


@overload_method(RunType, "modify_force")
def _modify_force(run, stage):
    if not _force_rules(run):
        return lambda run, stage: None
    consistent = _consistent(run)

    def impl(run, stage):
        """v^n, gravity into the force, the force rules at time
        t + stage dt (see the module)."""
        if run.stop:
            return
        t0 = monotonic_ns()
        if consistent:
            run.mass_solve(1, run.momentum, 1, run.v_old, run.momentum, 1, run.v_old)
        else:
            run.lumped_solve(run.momentum, run.no_gravity, run.v_old, 1)
            run.gravity_into_force()
        if not run.stop:
            r = run.force_rules
            MODIFY_FORCES(r.codes, r.parameters, r.offsets, r.dofs, run.force, run.v_old,
                          run.mass, run.dt, run.t, stage, r.reactions, r.data_offsets, r.data,
                          r.states)
            row = r.logged
            if stage != 0.0:
                pass  # a later rk4 stage: the step's record is its first stage's
            elif row < r.log_states.shape[0]:
                copy_into(r.log_states[row], r.states)
                copy_into(r.log_reactions[row], r.reactions)
                r.logged = row + 1
            else:  # StepLoop sizes the log for every call of a run: never
                run.stop = 2
        elapsed = monotonic_ns() - t0
        run.phase_ns[6] += elapsed  # effects, not the solve that encloses it
        run.phase_ns[1] -= elapsed
    return impl


@overload_method(RunType, "modify_velocity")
def _modify_velocity(run):
    if not _velocity_rules(run):
        return lambda run: None
    forced = _force_rules(run)

    def impl(run):
        """The velocity rules on MUSL's re-projected grid velocity (lumped
        mass), from the states their force forms left this step."""
        if run.stop:
            return
        r = run.velocity_rules
        if forced:
            for i in range(r.shared.shape[0]):
                if r.shared[i] >= 0:
                    copy_into(r.states[i], run.force_rules.states[r.shared[i]])
        MODIFY_VELOCITIES(r.codes, r.parameters, r.offsets, r.dofs, run.v_grid, run.mass,
                          r.data_offsets, r.data, r.states)
    return impl
