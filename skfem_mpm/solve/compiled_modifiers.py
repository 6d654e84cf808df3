"""The grid modifiers of a run on the compiled paths (damping, walls).

Each modifier of the scene (``State.force_modifiers``,
``State.velocity_modifiers``: :class:`skfem_mpm.effects.GridModifier`)
that gives a compiled form (``grid_rule(grid)``) is applied by the kernels of
:mod:`skfem_mpm.kernels.grid_modifiers`; one without a compiled form by
its own NumPy method. The order is the scene's, as on the reference
executor. The compiled executor calls :meth:`CompiledModifiers.modify_force`
and :meth:`~CompiledModifiers.modify_velocity`; the compiled step loop
takes the same rules packed (:meth:`~CompiledModifiers.packed`) and hands
the reactions of its last step back (:meth:`~CompiledModifiers.take_reactions`).
"""
import numpy as np

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
        """(codes, parameters, offsets, dofs, reactions) of every rule
        (kernels.grid_modifiers.pack_rules); call when :attr:`compiled`."""
        return pack_rules(self.rules, self.dim)

    def take_reactions(self, reactions):
        """Each reacting rule's row of ``reactions`` (R, dim) becomes its
        modifier's ``reaction`` (a new array)."""
        for modifier, rule, row in zip(self.modifiers, self.rules, reactions):
            if rule.reacts:
                modifier.reaction = row.copy()

    def modify_force(self, force, velocity, mass, dt):
        """The grid force (a new array) changed by every modifier in order."""
        force = force.copy()
        for modifier, rule, one in zip(self.modifiers, self.rules, self._one):
            if one is None:
                force = modifier.modify_force(force, velocity, mass, dt)
                continue
            codes, parameters, offsets, dofs, reactions = one
            modify_forces(codes, parameters, offsets, dofs, force, velocity, mass, float(dt),
                          reactions)
            if rule.reacts:
                modifier.reaction = reactions[0].copy()
        return force

    def modify_velocity(self, velocity, mass):
        """A grid velocity (a new array) changed by every modifier in order."""
        velocity = velocity.copy()
        for modifier, one in zip(self.modifiers, self._one):
            if one is None:
                velocity = modifier.modify_velocity(velocity, mass)
                continue
            codes, parameters, offsets, dofs, _ = one
            modify_velocities(codes, parameters, offsets, dofs, velocity, mass)
        return velocity
