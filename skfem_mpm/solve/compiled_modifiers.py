"""The grid modifiers of a run on the compiled paths (damping, walls, footings).

Each modifier of the scene (``State.force_modifiers``,
``State.velocity_modifiers``: :class:`skfem_mpm.effects.GridModifier`)
that gives a compiled form (``grid_rule(grid)``) is applied by the kernels of
:mod:`skfem_mpm.kernels.grid_modifiers`; one without a compiled form by
its own NumPy method. The order is the scene's, as on the reference
executor. The compiled executor calls :meth:`CompiledModifiers.modify_force`
and :meth:`~CompiledModifiers.modify_velocity`; the compiled step loop
takes the same rules packed (:meth:`~CompiledModifiers.packed`), starts
each call from the modifiers' states (:meth:`~CompiledModifiers.load_states`)
and hands the states and reactions of the steps it took back
(:meth:`~CompiledModifiers.take_steps`). A rule's state (a footing's clock)
lives in its modifier between calls: each call of a kernel here starts
from it and gives it back, so the executor and the loop take turns.
"""
import numpy as np

from ..effects import modified_force
from ..kernels.grid_modifiers import modify_forces, modify_velocities, pack_rules

__all__ = ["CompiledModifiers"]


class CompiledModifiers:
    """The modifiers ``modifiers`` (in order) of a run on ``grid``."""

    def __init__(self, modifiers, grid):
        dim = grid.dim
        self.modifiers = list(modifiers)
        self.rules = [m.grid_rule(grid) for m in self.modifiers]
        self._one = [None if rule is None else pack_rules([rule], dim) for rule in self.rules]
        self.dim = dim

    def __bool__(self):
        return bool(self.modifiers)

    @property
    def compiled(self):
        """Whether every modifier has a compiled form (the loop can run them)."""
        return all(rule is not None for rule in self.rules)

    def without_rule(self):
        """The first modifier without a compiled form, or None."""
        return next((m for m, rule in zip(self.modifiers, self.rules) if rule is None), None)

    def packed(self):
        """(codes, parameters, offsets, dofs, reactions, data_offsets, data,
        states) of every rule (kernels.grid_modifiers.pack_rules); call when
        :attr:`compiled`."""
        return pack_rules(self.rules, self.dim)

    def load_states(self, states):
        """Each modifier's ``rule_state()`` into its row of ``states`` (R, RULE_STATE)."""
        for modifier, row in zip(self.modifiers, states):
            row[:] = modifier.rule_state()

    def take_steps(self, states, reactions):
        """Hand the steps a compiled loop took back: ``states`` (k, R,
        RULE_STATE) and ``reactions`` (k, R, dim), one row per step taken
        (each reacting rule's ``take_rule_steps``)."""
        for r, (modifier, rule) in enumerate(zip(self.modifiers, self.rules)):
            if rule.reacts:
                modifier.take_rule_steps(states[:, r], reactions[:, r])

    def modify_force(self, force, velocity, mass, dt, t, stage):
        """The grid force (a new array) changed by every modifier in order,
        at time t + stage dt (stage 0 records the step: the protocol of
        :mod:`skfem_mpm.effects`)."""
        force = force.copy()
        for modifier, rule, one in zip(self.modifiers, self.rules, self._one):
            if one is None:
                force = modified_force(modifier, force, velocity, mass, dt, t, stage)
                continue
            codes, parameters, offsets, dofs, reactions, data_offsets, data, states = one
            states[0] = modifier.rule_state()
            modify_forces(codes, parameters, offsets, dofs, force, velocity, mass, float(dt),
                          float(t), float(stage), reactions, data_offsets, data, states)
            if rule.reacts and stage == 0.0:
                modifier.take_rule_steps(states.copy(), reactions.copy())
        return force

    def modify_velocity(self, velocity, mass):
        """A grid velocity (a new array) changed by every modifier in order."""
        velocity = velocity.copy()
        for modifier, one in zip(self.modifiers, self._one):
            if one is None:
                velocity = modifier.modify_velocity(velocity, mass)
                continue
            codes, parameters, offsets, dofs, _, data_offsets, data, states = one
            states[0] = modifier.rule_state()
            modify_velocities(codes, parameters, offsets, dofs, velocity, mass, data_offsets,
                              data, states)
        return velocity
