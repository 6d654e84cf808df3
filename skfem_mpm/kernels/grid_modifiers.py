"""Grid modifiers on the compiled paths: local damping, the frictional
rigid wall and the rigid footing, as rules that change the grid force
before the solve and the grid velocity that MUSL re-projects.

The formulas are those of :class:`skfem_mpm.effects.Damping`,
:class:`skfem_mpm.effects.Wall` and :class:`skfem_mpm.effects.Footing`
(their docstrings give them and their sources; their NumPy
``modify_force`` / ``modify_velocity`` are the reference executor's
oracle). The compiled executor and the compiled step
loop both apply them here, so the two agree bit for bit.

A modifier gives its compiled form as a :class:`GridRule` (``grid_rule(grid)``
of :class:`skfem_mpm.effects.GridModifier`): a rule code, its parameters,
the dofs it acts on, the numbers it reads (``data``: the footing's
vertical grid axis) and the state it keeps between steps (``state``,
:data:`RULE_STATE` numbers). :func:`pack_rules` packs the rules of a run in
their order into flat arrays; :func:`modify_forces` (at time t + stage dt:
t the step's start, stage the fraction c of an rk4 stage, 0 for a step)
and :func:`modify_velocities` apply them in that order, in place:

    LOCAL_DAMPING    parameters (alpha,), every dof:
                     f_i <- f_i - alpha |f_i| sign(v_i)   (Cundall 1987)
    FRICTIONAL_WALL  parameters (mu, n_1 .. n_dim) (n the outward normal),
                     the wall's dofs (Bardenhagen et al. 2000):
                     v* = v + dt f / m, d_n = v* . n; contact (d_n > 0):
                     f <- f - (m d_n / dt) n - min(mu m d_n / dt, m |t| / dt) t / |t|
                     (t = v* - d_n n); the velocity form (v* = v):
                     v <- t (1 - min(mu d_n, |t|) / |t|)
    FOOTING          parameters (base, speed, ramp, rough, stride, the
                     vertical axis's cells, degree and uniform), the
                     dofs of its columns (the horizontal functions whose
                     Greville abscissa lies under it, in the lowest layer),
                     data the vertical axis (its breakpoints, then its
                     extraction matrices), state (the end time of the
                     step recorded, y_b): at tau = t + stage dt,
                     y_b = base - s(tau) (clamped to the axis), w_j the
                     vertical functions at y_b, dofs c + stride j of each
                     column c; per column and each held component
                     (rough: all, smooth: the vertical one)
                     lambda = (v_F(tau + dt) - sum_j w_j v*_j) / (dt sum_j w_j^2 / m_j),
                     f_j <- f_j + w_j lambda (dofs without mass: w_j = 0);
                     stage 0 records the step: state (tau + dt, y_b); the
                     velocity form at the state's y_b and v_F(its time)
                     (v* = v, f / m a velocity change)

A rule with a reaction (the wall, the footing) writes the total force it
exerted on the bodies into its row of ``reactions`` at stage 0 (a step's
first force evaluation; an rk4 stage's later ones leave the first
stage's, as every reaction of an rk4 step); a rule without a velocity
form (damping) leaves the velocity alone. A rule's ``state`` row is
written by its force form at stage 0 (the footing records the step's end
time and the base it acted on) and read by its velocity form.
"""
from typing import NamedTuple

import numpy as np
from numba import njit

from .weights import extracted_functions, locate_axis_point

__all__ = ["LOCAL_DAMPING", "FRICTIONAL_WALL", "FOOTING", "RULE_STATE", "GridRule",
           "pack_rules", "local_damping", "wall_force", "wall_velocity", "footing_columns",
           "footing_force", "footing_velocity", "modify_forces", "modify_velocities"]

LOCAL_DAMPING = 1
FRICTIONAL_WALL = 2
FOOTING = 3
_PARAMETERS = {LOCAL_DAMPING: lambda dim: 1, FRICTIONAL_WALL: lambda dim: 1 + dim,
               FOOTING: lambda dim: 8}
RULE_STATE = 2
"""Numbers of a rule's state (the footing: the end time of the last step
it recorded and the height of the base it acted on in that step, NaN
before the first)."""


class GridRule(NamedTuple):
    """The compiled form of a grid modifier (see the module)."""

    code: int             # LOCAL_DAMPING, FRICTIONAL_WALL or FOOTING
    parameters: tuple     # the rule's numbers (see the module)
    dofs: np.ndarray      # the (node) dofs it acts on; empty: every dof
    reacts: bool          # it records the total force it exerted (``reaction``)
    data: np.ndarray = np.zeros(0)  # the arrays it reads, flat (the footing's axis)


def pack_rules(rules, dim):
    """(codes (R,), parameters (R, P), offsets (R + 1,), dofs, reactions
    (R, dim), data_offsets (R + 1,), data, states (R, RULE_STATE)) of
    ``rules`` in their order: rule r acts on dofs[offsets[r]:offsets[r + 1]]
    and reads data[data_offsets[r]:data_offsets[r + 1]]; P the most
    parameters of a rule in ``dim`` (at least 1 + dim); the states start at
    0 (the owner loads them: :class:`skfem_mpm.effects.GridModifier`
    ``rule_state``)."""
    count = len(rules)
    codes = np.zeros(count, dtype=np.int64)
    width = max([1 + dim] + [_PARAMETERS[r.code](dim) for r in rules if r.code in _PARAMETERS])
    parameters = np.zeros((count, width))
    offsets = np.zeros(count + 1, dtype=np.int64)
    data_offsets = np.zeros(count + 1, dtype=np.int64)
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
        data_offsets[r + 1] = data_offsets[r] + len(rule.data)
    dofs = np.zeros(offsets[-1], dtype=np.int64)
    data = np.zeros(data_offsets[-1])
    for r, rule in enumerate(rules):
        dofs[offsets[r]:offsets[r + 1]] = rule.dofs
        data[data_offsets[r]:data_offsets[r + 1]] = rule.data
    return (codes, parameters, offsets, dofs, np.zeros((count, dim)), data_offsets, data,
            np.zeros((count, RULE_STATE)))


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


@njit(cache=True, inline="always", error_model="numpy")
def footing_settlement(t, speed, ramp):
    """s(t) = speed t^2 / (2 ramp) while t < ramp, speed (t - ramp / 2) after
    (:meth:`skfem_mpm.effects.Footing.settlement_at`)."""
    if t < ramp:
        return speed * t * t / (2 * ramp)
    return speed * (t - 0.5 * ramp)


@njit(cache=True, inline="always", error_model="numpy")
def footing_velocity_at(t, speed, ramp):
    """The footing's vertical velocity -ds/dt (Footing.velocity_at)."""
    if ramp > 0:
        return -speed * min(1.0, t / ramp)
    return -speed


@njit(cache=True, error_model="numpy")
def footing_base(parameters, data, y_b, w, dw):
    """The first row of the vertical functions non-zero at the base height
    y_b and their values w (p + 1,) (kernels.weights, as SplineGrid.axis_functions)."""
    ncells = int(parameters[5])
    p = int(parameters[6])
    breaks = data[:ncells + 1]
    C = data[ncells + 1:ncells + 1 + ncells * (p + 1) * (p + 1)].reshape((ncells, p + 1, p + 1))
    inv_h = ncells / (breaks[ncells] - breaks[0])
    e = locate_axis_point(y_b, breaks, parameters[7] != 0.0, inv_h)
    extracted_functions(y_b, e, breaks, C, p, w, dw)
    return e


@njit(cache=True, error_model="numpy")
def footing_columns(columns, stride, first, w, rough, target, mass, velocity, force, dt,
                    forced, reaction):
    """The footing's correction on each column's dofs c + stride (first + a)
    with the vertical weights w (see the module). ``forced``: the force
    form (v* = v + dt f / m; f += w lambda, lambda = (v_F - sum w v*) /
    (dt S), ``reaction`` the sum); else the velocity form (v* = v;
    v += w mu / m, mu = (v_F - sum w v) / S; ``force`` and ``reaction`` not
    used). v_F = ``target`` vertically, 0 horizontally (rough); dofs
    without mass are left out (S = sum w^2 / m over the others)."""
    dim = velocity.shape[1]
    p = w.shape[0] - 1
    for c in range(dim):
        reaction[c] = 0.0
    for j in range(columns.shape[0]):
        S = 0.0
        for a in range(p + 1):
            m = mass[columns[j] + stride * (first + a)]
            if m > 0.0:
                S += w[a] * w[a] / m
        if not S > 0.0:
            continue
        for c in range(dim):
            if not rough and c != dim - 1:
                continue
            goal = target if c == dim - 1 else 0.0
            moved = 0.0
            for a in range(p + 1):
                k = columns[j] + stride * (first + a)
                m = mass[k]
                if m > 0.0:
                    v = velocity[k, c] + dt * force[k, c] / m if forced else velocity[k, c]
                    moved += w[a] * v
            if forced:
                lam = (goal - moved) / (dt * S)
            else:
                lam = (goal - moved) / S
            for a in range(p + 1):
                k = columns[j] + stride * (first + a)
                m = mass[k]
                if m > 0.0:
                    if forced:
                        contact = w[a] * lam
                        force[k, c] += contact
                        reaction[c] += contact
                    else:
                        velocity[k, c] += w[a] * lam / m


@njit(cache=True, error_model="numpy")
def footing_force(columns, parameters, data, state, force, velocity, mass, dt, t, stage,
                  reaction):
    """The footing's contact force at time t + stage dt added to ``force``
    (see the module); ``reaction`` (dim,) the sum of the contact forces;
    stage 0 records the step in ``state`` (its end time, the base)."""
    speed, ramp = parameters[1], parameters[2]
    ncells = int(parameters[5])
    p = int(parameters[6])
    time = t + stage * dt
    y_b = min(max(parameters[0] - footing_settlement(time, speed, ramp), data[0]),
              data[ncells])
    w = np.empty(p + 1)
    dw = np.empty(p + 1)
    first = footing_base(parameters, data, y_b, w, dw)
    footing_columns(columns, int(parameters[4]), first, w, parameters[3] != 0.0,
                    footing_velocity_at(time + dt, speed, ramp), mass, velocity, force, dt, True,
                    reaction)
    if stage == 0.0:
        state[0] = time + dt
        state[1] = y_b


@njit(cache=True, error_model="numpy")
def footing_velocity(columns, parameters, data, state, velocity, mass):
    """The footing's rule on a grid velocity no force produced, at the
    base of its last force step and the velocity of its clock (see the
    module); nothing before a force step (y_b NaN)."""
    y_b = state[1]
    if not np.isfinite(y_b):
        return
    p = int(parameters[6])
    w = np.empty(p + 1)
    dw = np.empty(p + 1)
    first = footing_base(parameters, data, y_b, w, dw)
    footing_columns(columns, int(parameters[4]), first, w, parameters[3] != 0.0,
                    footing_velocity_at(state[0], parameters[1], parameters[2]), mass,
                    velocity, velocity, 0.0, False, np.empty(velocity.shape[1]))


@njit(cache=True, error_model="numpy")
def modify_forces(codes, parameters, offsets, dofs, force, velocity, mass, dt, t, stage,
                  reactions, data_offsets, data, states):
    """Every rule's force form at time t + stage dt in order, in place (see
    the module); at stage 0 the rules with a reaction write theirs into
    ``reactions[r]`` and the footing its state into ``states[r]``."""
    dim = force.shape[1]
    spare = np.empty(dim)  # a later rk4 stage's reactions (not recorded)
    for r in range(codes.shape[0]):
        reaction = reactions[r] if stage == 0.0 else spare
        if codes[r] == LOCAL_DAMPING:
            local_damping(parameters[r, 0], force, velocity)
        elif codes[r] == FRICTIONAL_WALL:
            wall_force(dofs[offsets[r]:offsets[r + 1]], parameters[r, 1:1 + dim],
                       parameters[r, 0], force, velocity, mass, dt, reaction)
        elif codes[r] == FOOTING:
            footing_force(dofs[offsets[r]:offsets[r + 1]], parameters[r],
                          data[data_offsets[r]:data_offsets[r + 1]], states[r], force,
                          velocity, mass, dt, t, stage, reaction)


@njit(cache=True, error_model="numpy")
def modify_velocities(codes, parameters, offsets, dofs, velocity, mass, data_offsets, data,
                      states):
    """Every rule's velocity form in order, in place (see the module)."""
    dim = velocity.shape[1]
    for r in range(codes.shape[0]):
        if codes[r] == FRICTIONAL_WALL:
            wall_velocity(dofs[offsets[r]:offsets[r + 1]], parameters[r, 1:1 + dim],
                          parameters[r, 0], velocity, mass)
        elif codes[r] == FOOTING:
            footing_velocity(dofs[offsets[r]:offsets[r + 1]], parameters[r],
                             data[data_offsets[r]:data_offsets[r + 1]], states[r], velocity,
                             mass)
