"""Grid modifiers on the compiled paths: local damping and the frictional
rigid wall, as rules that change the grid force before the solve and the
grid velocity that MUSL re-projects.

The formulas are those of :class:`skfem_mpm.effects.Damping` and
:class:`skfem_mpm.effects.Wall` (their docstrings give them and their
sources; their NumPy ``modify_force`` / ``modify_velocity`` are the
reference executor's oracle). The compiled executor and the compiled step
loop both apply them here, so the two agree bit for bit.

A modifier gives its compiled form as a :class:`GridRule` (``grid_rule(grid)``
of :class:`skfem_mpm.effects.GridModifier`): a rule code, its parameters
and the dofs it acts on. :func:`pack_rules` packs the rules of a run in
their order into flat arrays; :func:`modify_forces` and
:func:`modify_velocities` apply them in that order, in place:

    LOCAL_DAMPING    parameters (alpha,), every dof:
                     f_i <- f_i - alpha |f_i| sign(v_i)   (Cundall 1987)
    FRICTIONAL_WALL  parameters (mu, n_1 .. n_dim) (n the outward normal),
                     the wall's dofs (Bardenhagen et al. 2000):
                     v* = v + dt f / m, d_n = v* . n; contact (d_n > 0):
                     f <- f - (m d_n / dt) n - min(mu m d_n / dt, m |t| / dt) t / |t|
                     (t = v* - d_n n); the velocity form (v* = v):
                     v <- t (1 - min(mu d_n, |t|) / |t|)

A rule with a reaction (the wall) writes the total force it exerted on the
bodies into its row of ``reactions``; a rule without a velocity form
(damping) leaves the velocity alone.
"""
from typing import NamedTuple

import numpy as np
from numba import njit

__all__ = ["LOCAL_DAMPING", "FRICTIONAL_WALL", "GridRule", "pack_rules", "local_damping",
           "wall_force", "wall_velocity", "modify_forces", "modify_velocities"]

LOCAL_DAMPING = 1
FRICTIONAL_WALL = 2
_PARAMETERS = {LOCAL_DAMPING: lambda dim: 1, FRICTIONAL_WALL: lambda dim: 1 + dim}


class GridRule(NamedTuple):
    """The compiled form of a grid modifier (see the module)."""

    code: int             # LOCAL_DAMPING or FRICTIONAL_WALL
    parameters: tuple     # the rule's numbers (see the module)
    dofs: np.ndarray      # the (node) dofs it acts on; empty: every dof
    reacts: bool          # it records the total force it exerted (``reaction``)


def pack_rules(rules, dim):
    """(codes (R,), parameters (R, 1 + dim), offsets (R + 1,), dofs, reactions
    (R, dim)) of ``rules`` in their order: rule r acts on
    dofs[offsets[r]:offsets[r + 1]]."""
    count = len(rules)
    codes = np.zeros(count, dtype=np.int64)
    parameters = np.zeros((count, 1 + dim))
    offsets = np.zeros(count + 1, dtype=np.int64)
    for r, rule in enumerate(rules):
        if rule.code not in _PARAMETERS:
            raise ValueError(f"unknown grid rule code {rule.code!r}; valid: "
                             f"{sorted(_PARAMETERS)}")
        values = np.asarray(rule.parameters, dtype=np.float64)
        if values.shape != (_PARAMETERS[rule.code](dim),):
            raise ValueError(f"grid rule {rule.code} needs {_PARAMETERS[rule.code](dim)} "
                             f"parameters in {dim}D, got {values.shape}")
        codes[r] = rule.code
        parameters[r, :values.size] = values
        offsets[r + 1] = offsets[r] + len(rule.dofs)
    dofs = np.zeros(offsets[-1], dtype=np.int64)
    for r, rule in enumerate(rules):
        dofs[offsets[r]:offsets[r + 1]] = rule.dofs
    return codes, parameters, offsets, dofs, np.zeros((count, dim))


@njit(cache=True, error_model="numpy")
def local_damping(alpha, force, velocity):
    """force <- force - alpha |force| sign(velocity) (np.sign: 0 at 0, NaN at NaN)."""
    nd, dim = force.shape
    for k in range(nd):
        for c in range(dim):
            v = velocity[k, c]
            if v > 0.0:
                s = 1.0
            elif v < 0.0:
                s = -1.0
            elif v == 0.0:
                s = 0.0
            else:
                s = v
            f = force[k, c]
            force[k, c] = f - alpha * abs(f) * s


@njit(cache=True, error_model="numpy")
def wall_force(dofs, normal, mu, force, velocity, mass, dt, reaction):
    """The wall's contact force added to ``force`` on its dofs (see the
    module); ``reaction`` (dim,) the sum of the contact forces."""
    dim = force.shape[1]
    v_free = np.empty(dim)
    for c in range(dim):
        reaction[c] = 0.0
    for j in range(dofs.shape[0]):
        k = dofs[j]
        m = mass[k]
        if not m > 0.0:
            continue
        d_n = 0.0
        for c in range(dim):
            v_free[c] = velocity[k, c] + dt * force[k, c] / m
            d_n += v_free[c] * normal[c]
        if not d_n > 0.0:
            continue
        speed2 = 0.0
        for c in range(dim):
            v_free[c] = v_free[c] - d_n * normal[c]  # the tangential velocity
            speed2 += v_free[c] * v_free[c]
        speed = np.sqrt(speed2)
        normal_force = m * d_n / dt
        friction = min(mu * normal_force, m * speed / dt)
        scale = speed if speed > 0.0 else 1.0
        for c in range(dim):
            contact = -normal_force * normal[c] - friction * (v_free[c] / scale)
            force[k, c] += contact
            reaction[c] += contact


@njit(cache=True, error_model="numpy")
def wall_velocity(dofs, normal, mu, velocity, mass):
    """The wall's rule on a grid velocity no force produced (see the module)."""
    dim = velocity.shape[1]
    for j in range(dofs.shape[0]):
        k = dofs[j]
        if not mass[k] > 0.0:
            continue
        d_n = 0.0
        for c in range(dim):
            d_n += velocity[k, c] * normal[c]
        if not d_n > 0.0:
            continue
        speed2 = 0.0
        for c in range(dim):
            t = velocity[k, c] - d_n * normal[c]
            speed2 += t * t
        speed = np.sqrt(speed2)
        keep = 1.0 - min(mu * d_n, speed) / (speed if speed > 0.0 else 1.0)
        for c in range(dim):
            velocity[k, c] = (velocity[k, c] - d_n * normal[c]) * keep


@njit(cache=True, error_model="numpy")
def modify_forces(codes, parameters, offsets, dofs, force, velocity, mass, dt, reactions):
    """Every rule's force form in order, in place (see the module); the
    rules with a reaction write theirs into ``reactions[r]``."""
    dim = force.shape[1]
    for r in range(codes.shape[0]):
        if codes[r] == LOCAL_DAMPING:
            local_damping(parameters[r, 0], force, velocity)
        elif codes[r] == FRICTIONAL_WALL:
            wall_force(dofs[offsets[r]:offsets[r + 1]], parameters[r, 1:1 + dim],
                       parameters[r, 0], force, velocity, mass, dt, reactions[r])


@njit(cache=True, error_model="numpy")
def modify_velocities(codes, parameters, offsets, dofs, velocity, mass):
    """Every rule's velocity form in order, in place (see the module)."""
    dim = velocity.shape[1]
    for r in range(codes.shape[0]):
        if codes[r] == FRICTIONAL_WALL:
            wall_velocity(dofs[offsets[r]:offsets[r + 1]], parameters[r, 1:1 + dim],
                          parameters[r, 0], velocity, mass)
