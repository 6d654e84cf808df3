"""Effects: the opt-in terms of a scene. Each contributes one term.

    Gravity(g)                        f_p = m_p g
    BodyForce(b)                      f_p = m_p b(X_p, t)         (b per unit reference mass)
    Traction(where, tau)              f_p = a_p tau(t)            (a_p: the particle's share
                                                                   of the loaded surface)
    Fixed(side, component=None)       v_i = 0 on the side's dofs
    Prescribed(side, component, velocity)   v_i = velocity(t) on the side's dofs
    Damping(alpha)                    f_i <- f_i - alpha |f_i| sign(v_i)   (local damping)
    Wall(side, friction=mu)           rigid wall with Coulomb friction on the side's dofs
    Footing(span, base, speed)        rigid footing pushed into the body at a prescribed
                                      speed, on the dofs under its current base

A scene that does not declare an effect never evaluates it: there is no
default gravity, no boundary search without a traction, no damping pass.
Forces on particles reach the grid through the same transfer as every other
particle quantity (N^T f_p); constraints act on grid dofs.

The protocol (what an executor asks of every effect; the defaults of
:class:`Effect` contribute nothing, so an effect overrides only its own):

    bind(particles, grid)       -> [particle forces]  (see ParticleForce)
    constraints(grid)           -> [(component, dofs, velocity(t) or None)]
    velocity_modifiers()        -> [GridModifier: modify_velocity(v, m) -> v]
                                   (MUSL's re-projected grid velocity)
    force_modifiers()           -> [GridModifier: modify_force(f, v, m, dt, t, stage) -> f]
                                   (f, v (dofs, dim): grid force and velocity at
                                   the start of the step, or of an rk4 stage;
                                   m (dofs,) the lumped nodal mass; dt the step;
                                   t the time at the start of the step; stage
                                   the fraction c of the step at which the force
                                   is evaluated: the time is t + c dt; c = 0 for
                                   every scheme's step and rk4's first stage,
                                   c = 1/2, 1/2, 1 for rk4's later stages, which
                                   leave a modifier's record (reaction, history)
                                   as the first stage left it: see
                                   :func:`modified_force`)
    side_traction()             -> (side, traction(x, t)) or None  (fem loads
                                   the grid side with Gauss quadrature)

A grid modifier (:class:`GridModifier`) may also give its compiled form,
``grid_rule(grid)``: a :class:`~skfem_mpm.kernels.grid_modifiers.GridRule`
(a rule of that kernel module and its data), which the compiled executor
and the compiled step loop apply instead of the NumPy methods (None: the
compiled executor calls the NumPy methods each step, and the compiled loop
does not run the scene). A modifier that exerts a force on the bodies
keeps its total of the last step in ``reaction``. A rule that keeps a
state between steps (the footing's record of its last step) starts each compiled call from
``rule_state()`` and hands what its steps did back through
``take_rule_steps(states, reactions)`` (its state and reaction after each
step taken), so that the executor and the compiled loop can take turns.

A particle force (:class:`ParticleForce`) gives ``forces(particles, t)``
(n, dim) and may give ``grid_forces`` (where it is not applied at the
particle centres), ``acceleration`` (a uniform acceleration g with
f_p = m_p g: an executor may apply it on the grid as m_i g), ``surface``
(a load on the body's surface, not a volume force), ``reference_only``
(its forces depend on the particles' reference data and t only: they can
be evaluated ahead for the times of coming steps), and the state it keeps
about particles (``rebind`` after removals, ``checkpoint_arrays`` /
``restore`` for restarts).
"""
import functools
import inspect

import numpy as np

from .errors import InvalidState
from .kernels.grid_modifiers import FOOTING, FRICTIONAL_WALL, LOCAL_DAMPING, RULE_STATE, GridRule
from .spline.grid import SIDE_AXES, side_axis
from .validation import _short, check_finite_array, check_positive

__all__ = ["Effect", "ParticleForce", "GridModifier", "Gravity", "BodyForce", "Traction", "Fixed",
           "Prescribed", "Damping", "Wall", "Footing"]


class Effect:
    """Base class of the effects of a scene: each contributes through the
    protocol of the module docstring and inherits nothing elsewhere."""

    def check(self, grid):
        """Validate against the scene's grid (raise ValueError)."""

    def bind(self, particles, grid):
        """The particle forces of this effect for a run (none by default)."""
        return []

    def constraints(self, grid):
        """[(component, scalar dofs, velocity(t) or None)] (none by default)."""
        return []

    def force_modifiers(self):
        """Objects whose ``modify_force(force, velocity, mass, dt)`` changes
        the grid force before the solve (none by default)."""
        return []

    def side_traction(self):
        """(side, traction(x, t)) for a load on a named side (fem), or None."""
        return None

    def velocity_modifiers(self):
        """Objects whose ``modify_velocity(velocity, mass)`` corrects a grid
        velocity that no force produced: MUSL's re-projected velocity, which
        moves the particles (none by default)."""
        return []

    def reactions(self):
        """{name: total force (dim,)} this effect exerted on the bodies in
        the last step, for effects that are not constraints (a Wall); the
        constraints' reactions come from the grid solve. None by default."""
        return {}


class ParticleForce:
    """A force on particles for one run (what ``Effect.bind`` returns)."""

    surface = False      # a load on the body's surface (not a volume force)
    acceleration = None  # a uniform acceleration g with f_p = m_p g, or None
    # True when ``forces(particles, t)`` reads only the particles' reference
    # data (X, m, V0, body: never changed by a step) and t, and the force
    # reaches the grid as N^T f_p (no ``grid_forces``): the compiled loop
    # then evaluates it ahead at the times of the steps it takes
    # (solve/compiled_loop_body_force.py)
    reference_only = False

    def forces(self, particles, t):  # pragma: no cover - interface
        """f_p, shape (n, dim)."""
        raise NotImplementedError

    def grid_forces(self, particles, t, grid):
        """The grid force when it is not N^T f_p (side tractions), or None."""
        return None

    def rebind(self, keep):
        """After particles were removed (``keep``: the survivors' mask)."""

    def checkpoint_arrays(self):
        """The arrays a restart needs to rebuild this force ({name: array})."""
        return {}

    def restore(self, arrays):
        """Take back what :meth:`checkpoint_arrays` gave."""


class GridModifier:
    """A change of the grid force before the solve or of MUSL's re-projected
    grid velocity (what ``Effect.force_modifiers`` and
    ``Effect.velocity_modifiers`` return); the defaults change nothing."""

    reaction = None  # (dim,): the total force exerted on the bodies in the last step
    # what a run writes into the modifier (not part of the scene: a
    # checkpoint's fingerprint leaves them out, skfem_mpm.fingerprint)
    run_records = ("reaction",)

    def modify_force(self, force, velocity, mass, dt, t=0.0, stage=0.0):
        """The grid force (dofs, dim) changed at time t + stage dt (see the
        module docstring); a stage > 0 leaves the record of the step."""
        return force

    def modify_velocity(self, velocity, mass):
        """A grid velocity (dofs, dim) that no force produced, changed."""
        return velocity

    def grid_rule(self, grid):
        """The compiled form on ``grid`` (a kernels.grid_modifiers.GridRule),
        or None."""
        return None

    def rule_state(self):
        """The state (kernels.grid_modifiers.RULE_STATE numbers) its compiled
        rule starts the next step from (none kept by default: zeros)."""
        return np.zeros(RULE_STATE)

    def take_rule_steps(self, states, reactions):
        """After compiled steps of a reacting rule: its state (k, RULE_STATE)
        and reaction (k, dim) after each step taken; the last reaction
        becomes ``reaction``."""
        if len(reactions):
            self.reaction = np.array(reactions[-1], dtype=np.float64)


def modified_force(modifier, force, velocity, mass, dt, t, stage):
    """``modifier.modify_force`` at time t + stage dt (the module's
    protocol); a modifier whose ``modify_force`` takes four arguments
    (force, velocity, mass, dt: one that ignores the time) is called
    with those."""
    if _takes_time(type(modifier)):
        return modifier.modify_force(force, velocity, mass, dt, t, stage)
    return modifier.modify_force(force, velocity, mass, dt)


@functools.lru_cache(maxsize=None)
def _takes_time(cls):
    """Whether ``cls.modify_force`` takes (self, force, velocity, mass, dt, t, stage)."""
    return _positional_count(cls.modify_force) >= 7


def _numbers(name, value, what):
    """value as a float64 array, or a ValueError naming the argument."""
    try:
        return np.atleast_1d(np.asarray(value, dtype=np.float64))
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be {what}, got {value!r}") from None


def _vector(name, value, dim):
    a = np.atleast_1d(np.asarray(value, dtype=np.float64))
    if a.shape != (dim,):
        raise ValueError(f"{name} must have {dim} component(s) for a {dim}D grid, got {a.shape}")
    return check_finite_array(name, a)


class Gravity(Effect, ParticleForce):
    """Gravitational acceleration in the user's axes: ``Gravity((0.0, -9.81))``
    in 2D, ``Gravity(-9.81)`` in 1D (negative points toward -x)."""

    def __init__(self, g):
        self.g = _numbers("g", g, "a number (1D) or a vector of numbers")
        check_finite_array("g", self.g)

    def __repr__(self):
        return f"Gravity({self.g.tolist()})"

    def check(self, grid):
        self.g = _vector("g", self.g, grid.dim)

    @property
    def acceleration(self):
        return self.g

    def bind(self, particles, grid):
        return [self]

    def forces(self, particles, t):
        return particles.m[:, None] * self.g[None, :]


class BodyForce(Effect, ParticleForce):
    """A body force per unit reference mass ``b(X, t)``, X of shape (n, dim);
    returns (n, dim) (or (n,) in 1D). Used by manufactured solutions."""

    def __init__(self, b):
        if not callable(b):
            raise ValueError(f"BodyForce needs a callable b(X, t), got {b!r}")
        self.b = b

    reference_only = True  # b(X, t) of the reference positions

    def __repr__(self):
        return f"BodyForce({getattr(self.b, '__name__', 'b')})"

    def bind(self, particles, grid):
        return [self]

    def forces(self, particles, t):
        n, dim = particles.n, particles.dim
        b = np.asarray(self.b(particles.X, t), dtype=np.float64)
        if dim == 1 and b.shape == (n,):
            b = b[:, None]
        if b.shape != (n, dim):
            raise ValueError(f"BodyForce b(X, t) must return shape ({n}, {dim}), got {b.shape}")
        return particles.m[:, None] * b


def _positional_count(fn):
    try:
        params = inspect.signature(fn).parameters.values()
    except (TypeError, ValueError):
        return 1
    return sum(p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD) for p in params)


SIDES = tuple(SIDE_AXES)


class Traction(Effect):
    """A force per unit area of the body's surface (per unit cross-section in 1D).

    ``where`` is a side of the body (``'xmin'``, ``'xmax'``, ``'ymin'``,
    ``'ymax'``, ``'zmin'``, ``'zmax'``, or the aliases ``'left'``,
    ``'right'``, ``'bottom'``, ``'top'``) or a boolean particle mask. ``tau(t)`` or ``tau(x, t)``
    returns the traction vector (a float in 1D); a normal pressure p on the
    top side is ``Traction('top', lambda t: (0.0, -p))``.

    How the particles carry it:

    * side name: the outermost particles on that side carry it at their
      outer faces (see :class:`SurfaceTraction`): in 1D exactly at the
      body's moving end, as FEM applies it, so the traction costs no order
      of accuracy (a layer one cell deep would smear the load and limit the
      displacement error to O(h^2));
    * mask: the masked particles as a layer (f_p = a_p tau with
      a_p = V0_p / depth); ``depth`` defaults (1D only) to their total
      volume, so the total force is tau.

    With ``fem`` a side name loads the grid's side with Gauss quadrature.
    """

    def __init__(self, where, tau, depth=None, body=None):
        if isinstance(where, str):
            if where not in SIDES:
                raise ValueError(f"where must be one of {SIDES} or a boolean mask, got {where!r}")
        else:
            given, where = where, np.asarray(where)
            if where.dtype != bool or where.ndim != 1:
                raise ValueError(f"where must be one of {SIDES} or a 1-D boolean particle mask, "
                                 f"got {_short(given)} (dtype {where.dtype}, shape {where.shape})")
            if not where.any():
                raise ValueError(f"where: the traction mask selects no particle (all "
                                 f"{where.size} entries are False)")
        if not callable(tau):
            value = check_finite_array("tau", _numbers(
                "tau", tau, "a number, a vector or a callable tau(t) / tau(x, t)"))
            tau = (lambda t, *, _v=value: _v)  # keyword-only: not read as tau(x, t)
        self.where = where
        self.tau = tau
        self._takes_x = _positional_count(tau) >= 2
        if depth is not None:
            depth = check_positive("depth", depth)
        self.depth = depth
        self.body = body

    def __repr__(self):
        where = self.where if isinstance(self.where, str) else f"mask({int(self.where.sum())})"
        return f"Traction({where!r})"

    def check(self, grid):
        if isinstance(self.where, str) and grid.dim == 1 and self.where not in ("left", "right", "xmin", "xmax"):
            raise ValueError(f"where must be 'left' or 'right' in 1D, got {self.where!r}")
        if isinstance(self.where, str):
            side_axis(self.where, grid.dim)

    def traction(self, x, t):
        return self.tau(x, t) if self._takes_x else self.tau(t)

    def side_traction(self):
        if not isinstance(self.where, str):
            raise ValueError("fem applies tractions on named sides; this scene loads "
                             "a particle mask (use a side name such as 'right')")
        return self.where, self.traction

    def bind(self, particles, grid):
        """Bind to the particles once per run (reference configuration)."""
        dim = particles.dim
        if isinstance(self.where, str):
            axis, end = side_axis(self.where, dim)
            sign = 1.0 if end else -1.0
            size = particles.V0 ** (1.0 / dim)  # reference extent along the normal
            coord = sign * particles.X[:, axis]
            candidates = np.ones(particles.n, dtype=bool) if self.body is None \
                else particles.body == self.body
            if not candidates.any():
                raise ValueError(f"the traction's body {self.body} has no particles")
            outer = coord + 0.5 * size
            edge = outer[candidates].max()
            if dim == 1:
                # the body's end is one point, carried by the particle whose
                # face it is: a particle of a cut cell (smaller than its
                # neighbours) ends the body within half the size of its
                # neighbour, which must not carry the load a second time
                index = np.flatnonzero(candidates & (outer == edge))[:1]
            else:
                index = np.flatnonzero(candidates & (outer > edge - 0.5 * size))
            return [SurfaceTraction(self, index, particles.V0[index] / size[index],
                                    size[index], axis, sign)]
        mask = self.where
        if mask.shape != (particles.n,):
            raise ValueError(
                f"the traction mask has {mask.shape[0]} entries for {particles.n} particles")
        depth = self.depth
        if depth is None:
            if dim != 1:
                raise ValueError("a traction on a particle mask in 2D needs depth= "
                                 "(the thickness of the loaded layer)")
            depth = float(particles.V0[mask].sum())
        return [BoundTraction(self, np.flatnonzero(mask), particles.V0[mask] / depth)]


class BoundTraction(ParticleForce):
    """A traction carried by a layer of particles (a mask): f_p = a_p tau."""

    surface = True

    def __init__(self, effect, index, share):
        self.effect = effect
        self.index = index
        self.share = share

    def rebind(self, keep):
        alive = keep[self.index]
        self.index = (np.cumsum(keep) - 1)[self.index[alive]]
        self.share = self.share[alive]

    def checkpoint_arrays(self):
        return {"index": self.index, "share": self.share}

    def restore(self, arrays):
        self.index = arrays["index"].copy()
        self.share = arrays["share"].copy()

    def loads(self, particles, t):
        """(index, forces (k, dim)) of the loaded particles."""
        dim, k = particles.dim, self.index.size
        x = self.points(particles)
        tau = np.asarray(self.effect.traction(x, t), dtype=np.float64)
        if tau.ndim == 2 or (dim == 1 and tau.shape == (k,) and k > 1):
            tau = tau.reshape(k, dim)
        elif tau.size == dim:
            tau = np.broadcast_to(tau.reshape(dim), (k, dim))
        else:
            raise ValueError(f"tau must return {dim} component(s) (or ({k}, {dim})), got {tau.shape}")
        return self.share[:, None] * tau

    def points(self, particles):
        return particles.x[self.index]

    def forces(self, particles, t):
        out = np.zeros((particles.n, particles.dim))
        out[self.index] = self.loads(particles, t)
        return out


class SurfaceTraction(BoundTraction):
    """A traction on a side of the body, applied where it acts: at the outer
    face of each outermost particle, x_p + sign (s_p / 2) (V_p / V0_p)^(1/dim)
    e_axis (in 1D exactly the moving end x_p + V_p / 2), with the face area
    a_p = V0_p / s_p (s_p = V0_p^(1/dim) the particle's reference size).
    The grid force is f_i = sum_p a_p tau N_i(face_p), as FEM's surface
    integral with the faces as quadrature points."""

    def __init__(self, effect, index, share, size, axis, sign):
        super().__init__(effect, index, share)
        self.size = size
        self.axis = axis
        self.sign = sign

    def rebind(self, keep):
        self.size = self.size[keep[self.index]]
        super().rebind(keep)

    def checkpoint_arrays(self):
        return dict(super().checkpoint_arrays(), size=self.size)

    def restore(self, arrays):
        super().restore(arrays)
        self.size = arrays["size"].copy()

    def points(self, particles):
        i = self.index
        stretch = (particles.V[i] / particles.V0[i]) ** (1.0 / particles.dim)
        x = particles.x[i].copy()
        x[:, self.axis] += self.sign * 0.5 * self.size * stretch
        return x

    def grid_forces(self, particles, t, grid):
        """f_i = sum_p a_p tau(t) N_i(face_p), shape (dofs, dim)."""
        from .quadrature import transfer_matrices

        faces = self.points(particles)
        for axis, (lo, hi) in enumerate(grid.bounds):
            tol = 1e-12 * (hi - lo)  # a face on the grid's edge, up to round-off
            beyond = (faces[:, axis] < lo - tol) | (faces[:, axis] > hi + tol)
            if beyond.any():
                k = int(self.index[np.flatnonzero(beyond)[0]])
                raise InvalidState(f"the loaded face of particle {k} lies outside the grid "
                                   f"(axis {axis}); extend the grid beyond the body", particle=k)
            np.clip(faces[:, axis], lo, hi, out=faces[:, axis])
        N, _ = transfer_matrices(grid, faces)
        return N.T @ self.loads(particles, t)


def _check_component(component, dim):
    if component is None:
        return tuple(range(dim))
    if isinstance(component, bool) or not isinstance(component, (int, np.integer)) \
            or not 0 <= component < dim:
        raise ValueError(f"component must be None or an integer in [0, {dim - 1}], got {component!r}")
    return (int(component),)


class Fixed(Effect):
    """Zero velocity (and displacement) of the spline dofs on a grid side:
    ``component`` 0/1 fixes one component (a sliding wall fixes the normal
    one), None all of them."""

    def __init__(self, side, component=None):
        _check_component(component, 3)  # the grid's dimension is checked in the scene
        self.side = side
        self.component = component

    def __repr__(self):
        return f"Fixed({self.side!r}, component={self.component})"

    def check(self, grid):
        grid.boundary_dofs(self.side)
        _check_component(self.component, grid.dim)

    def constraints(self, grid):
        """[(component, scalar dofs, velocity(t) or None)]"""
        dofs = grid.boundary_dofs(self.side)
        return [(c, dofs, None) for c in _check_component(self.component, grid.dim)]



def prescribed_value(velocity, t):
    """``velocity(t)`` of a Prescribed effect as a float; ValueError unless
    it is one finite real number."""
    value = velocity(t)
    a = np.asarray(value)
    if a.size != 1 or a.dtype.kind not in "iuf" or not np.isfinite(a).all():
        raise ValueError(f"Prescribed velocity(t) must return one finite real number (the "
                         f"velocity of its component), got {value!r} at t = {t!r}")
    return float(a.reshape(()))


class Prescribed(Effect):
    """A prescribed velocity ``velocity(t)`` of one component on a grid side
    (moving walls, loading plates)."""

    def __init__(self, side, component, velocity):
        if component is not None:
            _check_component(component, 3)
        if not callable(velocity):
            value = _numbers("velocity", velocity, "a number or a callable velocity(t)")
            if value.shape != (1,):
                raise ValueError(f"velocity must be one number (of the prescribed component) "
                                 f"or a callable velocity(t), got {velocity!r}")
            value = float(value[0])
            if not np.isfinite(value):
                raise ValueError(f"velocity must be finite or a callable velocity(t), got {value}")
            velocity = (lambda t, _v=value: _v)
        self.side = side
        self.component = component
        self.velocity = velocity

    def __repr__(self):
        return f"Prescribed({self.side!r}, component={self.component})"

    def check(self, grid):
        grid.boundary_dofs(self.side)
        if self.component is None:
            raise ValueError(f"Prescribed needs a component (0 to {grid.dim - 1}), got None")
        _check_component(self.component, grid.dim)
        prescribed_value(self.velocity, 0.0)  # its kind of value, before the first step

    def constraints(self, grid):
        return [(int(self.component), grid.boundary_dofs(self.side), self.velocity)]


class Damping(Effect, GridModifier):
    """Local (non-viscous) damping of geomechanics codes (Cundall 1987;
    Al-Kafaji 2013, Sec. 3.5): every grid force component is reduced by
    alpha times its magnitude against the direction of the grid velocity,

        f_i <- f_i - alpha |f_i| sign(v_i),      0 <= alpha < 1.
    """

    def __init__(self, alpha):
        if isinstance(alpha, bool) or not isinstance(alpha, (int, float, np.floating)) \
                or not 0.0 <= float(alpha) < 1.0:
            raise ValueError(f"alpha must be a number in [0, 1), got {alpha!r}")
        self.alpha = float(alpha)

    def __repr__(self):
        return f"Damping({self.alpha:g})"

    def force_modifiers(self):
        return [self]

    def modify_force(self, force, velocity, mass=None, dt=None, t=0.0, stage=0.0):
        return force - self.alpha * np.abs(force) * np.sign(velocity)

    def grid_rule(self, grid):
        """The same rule compiled (kernels.grid_modifiers.local_damping)."""
        return GridRule(LOCAL_DAMPING, (self.alpha,), np.zeros(0, dtype=np.int64), False)


class Wall(Effect, GridModifier):
    """A rigid wall at a grid side with Coulomb friction, applied on the
    side's dofs (the functions that are non-zero there) as a contact force
    of the step (Bardenhagen, Brackbill, Sulsky 2000, Comput. Methods Appl.
    Mech. Eng. 187, 529-541: their frictional contact, with a rigid
    partner at rest). With n the
    outward normal of the side, m_i the lumped mass, f_i the grid force
    (gravity included) and v_i the grid velocity at the start of the step:

        v*_i = v_i + dt f_i / m_i                       the velocity without the wall
        d_n  = v*_i . n                                 > 0: the node would enter the wall
        contact (d_n > 0):
            f_i <- f_i - (m_i d_n / dt) n               no penetration: v_i . n = 0 after
            t   = v*_i - d_n n  (the tangential velocity)
            f_i <- f_i - min(mu m_i d_n / dt, m_i |t| / dt) t / |t|
                                                        friction: at most mu times
                                                        the normal force; sticks when
                                                        that stops the sliding
        separation (d_n <= 0): nothing.

    So a node in contact ends the step with zero normal velocity and its
    tangential velocity reduced by at most mu d_n (the Coulomb bound on the
    impulse). Only the side's functions are touched (with open knot
    vectors, the first row); a particle near the wall also moves with the
    next rows, which follow through the body's stress: a sliding body
    loses tangential momentum at mu times the normal impulse however thin
    it is, unless its own shear strength on planes parallel to the wall is
    below mu (a Mohr-Coulomb material without dilation: sin(phi) in steady
    simple shear), when it shears above the wall instead. MUSL's re-projected grid velocity (which moves the particles)
    gets the same rule with v* = v (``modify_velocity``). ``friction=0`` is a smooth (sliding) wall; ``Fixed`` stays the
    no-slip wall. The contact force is computed with the lumped mass, so
    the no-penetration condition is exact with ``mass="lumped"`` and
    approximate with consistent mass. ``reaction`` holds the total force
    the wall exerted on the bodies in the last step (dim,), the same sign
    convention as the reactions of ``Fixed`` (``Result.reactions``).
    """

    def __init__(self, side, friction=0.0):
        if not isinstance(side, str) or side not in SIDE_AXES:
            raise ValueError(f"side must be one of {', '.join(map(repr, SIDE_AXES))}, "
                             f"got {side!r}")
        if isinstance(friction, bool) or not isinstance(friction, (int, float, np.floating)) \
                or not (np.isfinite(friction) and friction >= 0):
            raise ValueError(f"friction must be a finite number >= 0 (the Coulomb "
                             f"coefficient mu), got {friction!r}")
        self.side = side
        self.friction = float(friction)
        self.reaction = None
        self._dofs = None

    def __repr__(self):
        return f"Wall({self.side!r}, friction={self.friction:g})"

    def check(self, grid):
        self._dofs, self._normal = self._geometry(grid)
        self._ndofs = grid.ndofs

    def _geometry(self, grid):
        """(the side's dofs, its outward normal) on ``grid``."""
        axis, end = side_axis(self.side, grid.dim)
        normal = np.zeros(grid.dim)
        normal[axis] = 1.0 if end == 1 else -1.0
        return np.asarray(grid.boundary_dofs(self.side)), normal

    def bind(self, particles, grid):
        """A run starts without a reaction (an earlier run's is not reported
        before its first step)."""
        self.reaction = None
        return []

    def force_modifiers(self):
        return [self]

    def reactions(self):
        return {} if self.reaction is None else {repr(self): self.reaction.copy()}

    def velocity_modifiers(self):
        return [self]

    def grid_rule(self, grid):
        """The same contact rule compiled (kernels.grid_modifiers.wall_force and
        wall_velocity) on ``grid``'s side: parameters (mu, the outward normal)."""
        dofs, normal = self._geometry(grid)
        return GridRule(FRICTIONAL_WALL, (self.friction, *normal),
                        np.asarray(dofs, dtype=np.int64), True)

    def modify_velocity(self, velocity, mass):
        """The same contact rule on a grid velocity that no force produced
        (MUSL's re-projection): d_n = v . n > 0 is removed and the
        tangential velocity t reduced by min(mu d_n, |t|)."""
        d = self._dofs
        v = velocity[d]
        n = self._normal
        d_n = np.where(mass[d] > 0, v @ n, 0.0)
        contact = d_n > 0
        tangent = v - d_n[:, None] * n[None, :]
        speed = np.sqrt(np.einsum("ij,ij->i", tangent, tangent))
        keep = np.where(contact, 1 - np.minimum(self.friction * d_n, speed)
                        / np.where(speed > 0, speed, 1.0), 1.0)
        out = velocity.copy()
        out[d] = np.where(contact[:, None], tangent * keep[:, None], v)
        return out

    def modify_force(self, force, velocity, mass, dt, t=0.0, stage=0.0):
        """The grid force with the wall's contact force added (class
        docstring); ``reaction`` is the step's (stage 0: an rk4 stage
        leaves the first stage's)."""
        if self._dofs is None or force.shape[0] != self._ndofs:
            raise ValueError(f"{self!r} was checked against another grid (call "
                             f"Scene(...) with this grid first)")
        d = self._dofs
        m = mass[d]
        has_mass = m > 0
        m_safe = np.where(has_mass, m, 1.0)
        v_free = velocity[d] + dt * force[d] / m_safe[:, None]
        n = self._normal
        d_n = np.where(has_mass, v_free @ n, 0.0)
        contact = d_n > 0
        tangent = v_free - d_n[:, None] * n[None, :]
        speed = np.sqrt(np.einsum("ij,ij->i", tangent, tangent))
        normal_force = np.where(contact, m * d_n / dt, 0.0)
        friction = np.minimum(self.friction * normal_force, m * speed / dt)
        direction = tangent / np.where(speed > 0, speed, 1.0)[:, None]
        contact_force = -normal_force[:, None] * n[None, :] \
            - np.where(contact, friction, 0.0)[:, None] * direction
        out = force.copy()
        out[d] += contact_force
        if stage == 0.0:
            self.reaction = contact_force.sum(axis=0)
        return out


class Footing(Effect, GridModifier):
    """A rigid footing pushed vertically into the body at a prescribed speed
    (a plate-load or bearing-capacity test), applied on the grid along its
    current base, which is found anew each step (a fixed dof set would lose
    contact once the footing has settled about a cell).

    ``span`` is the footing's horizontal extent (x0, x1) in 2D (in 3D a
    pair of such ranges, for x and y); ``base`` the height of its base at
    t = 0 (the ground surface); ``speed`` the settlement rate (> 0, down),
    reached linearly over ``ramp`` (so the settlement is
    s(t) = speed t^2 / (2 ramp) while t < ramp, speed (t - ramp / 2) after).
    ``rough=True`` also holds the horizontal velocity at 0 (no slip under
    the footing); ``rough=False`` prescribes the vertical velocity only (a
    smooth footing).

    The constraint: along the current base y_b = base - s(t) the grid
    velocity is the footing's. With tensor-product B-splines the velocity
    on the line y = y_b of column i (the functions N_i(x) whose Greville
    abscissa lies in ``span``) is sum_j w_j v_ij, w_j = N_j(y_b) the
    vertical functions there; each column gets the contact force
    f_ij = w_j lambda_i that makes it the footing's velocity v_F at the
    end of the step (lumped mass m_ij, v*_ij = v_ij + dt f_ij / m_ij the
    velocity without the footing; the least-squares correction of a
    linear constraint)::

        lambda_i = (v_F(t + dt) - sum_j w_j v*_ij) / (dt sum_j w_j^2 / m_ij)

    (rough: each component, the horizontal target 0; smooth: the vertical
    one). Only that one combination is set, so the soil under the base
    deforms freely (fixing every dof that is non-zero at the base would
    also set the velocity gradient there to zero: a rigid layer about a
    cell thick, measured 44% too stiff on an oedometer with 4 cells).
    MUSL's re-projected velocity gets the same correction with dt f / m
    replaced by a velocity change. With a span that ends on a knot, the
    velocity at its edge is the mean of the footing's and the soil's (the
    Greville rule puts the edge halfway). Dofs without mass are left out.

    ``reaction`` is the total force the footing exerted on the bodies in
    the last step (dim,), sum_ij w_j lambda_i; the bearing pressure is its
    vertical component over the footing's width, q = -reaction_y /
    ``width``. ``settlement`` (the current s) and ``history`` (a list of
    (t, s, reaction) per step) record the load-settlement curve.

    The footing moves with the scene's time: a force evaluated at time
    tau (a step's start t, or an rk4 stage's t + c dt: ``modify_force``'s
    t and stage) acts along y_b = base - s(tau) toward v_F(tau + dt), so
    every stage sees the footing where it is at the stage's time. A step's
    record (``reaction``, ``history``, ``settlement``) is that of its
    first force evaluation (c = 0), as every reaction of an rk4 step is
    its first stage's, and advances once per step. A run restarted from a
    checkpoint at time t goes on from s(t) (its ``history`` holds the
    steps of that run). Its compiled rule (``grid_rule``:
    kernels.grid_modifiers FOOTING) is the same constraint, chosen anew
    each step in compiled code, so that the compiled step loop runs a
    footing scene.
    """

    run_records = ("reaction", "history")

    def __init__(self, span, base, speed, rough=True, ramp=0.0):
        span = _numbers("span", span, "a pair (x0, x1) or a pair of such pairs in 3D")
        if span.size not in (2, 4) or not np.all(np.isfinite(span)):
            raise ValueError(f"span must be (x0, x1) (2D) or ((x0, x1), (y0, y1)) (3D) of "
                             f"finite numbers, got {span.tolist()}")
        span = span.reshape(-1, 2)
        if not np.all(span[:, 1] > span[:, 0]):
            raise ValueError(f"span must have x0 < x1, got {span.tolist()}")
        self.span = span
        self.base = float(check_finite_array("base", _numbers("base", base, "a number"))[0])
        self.speed = check_positive("speed", speed)
        self.ramp = check_positive("ramp", ramp, allow_zero=True)
        if not isinstance(rough, (bool, np.bool_)):
            raise ValueError(f"rough must be True or False, got {rough!r}")
        self.rough = bool(rough)
        self.reaction = None
        self._grid = None
        self._active = None
        self._t = 0.0  # the time at the end of the last step recorded
        self._base_now = np.nan  # the base height of the last step recorded
        self.history = []

    def __repr__(self):
        return (f"Footing(span={self.span.tolist()}, base={self.base:g}, "
                f"speed={self.speed:g}, rough={self.rough})")

    @property
    def width(self):
        """The loaded length (2D) or area (3D): the product of the spans."""
        return float(np.prod(self.span[:, 1] - self.span[:, 0]))

    def settlement_at(self, t):
        """s(t) (class docstring)."""
        if t < self.ramp:
            return self.speed * t * t / (2 * self.ramp)
        return self.speed * (t - 0.5 * self.ramp)

    def velocity_at(self, t):
        """The footing's vertical velocity -ds/dt."""
        return -self.speed * (min(1.0, t / self.ramp) if self.ramp > 0 else 1.0)

    @property
    def settlement(self):
        """s at the end of the last step (0 before the first)."""
        return self.settlement_at(self._t)

    def check(self, grid):
        if grid.dim < 2:
            raise ValueError(f"a Footing needs a 2D or 3D grid, got dim={grid.dim}")
        if self.span.shape[0] != grid.dim - 1:
            raise ValueError(f"span must have {grid.dim - 1} range(s) (x0, x1) on a "
                             f"{grid.dim}D grid, got {self.span.tolist()}")
        lo, hi = grid.bounds[-1]
        if not lo < self.base <= hi:
            raise ValueError(f"base must lie in the grid's vertical range ({lo:g}, {hi:g}], "
                             f"got {self.base:g}")
        self._columns, self._stride = self._geometry(grid)
        self._grid = grid
        self._ndofs = grid.ndofs

    def _geometry(self, grid):
        """(the columns: the horizontal functions whose Greville abscissa
        lies in ``span``, as dofs of the lowest layer; the dofs per layer)."""
        stride = int(np.prod(grid.basis_per_axis[:-1]))  # dofs per horizontal layer
        greville = grid.doflocs()[:, :stride]
        tol = 1e-9 * max(grid.h)
        inside = np.ones(stride, dtype=bool)
        for axis, (a, b) in enumerate(self.span):
            inside &= (greville[axis] >= a - tol) & (greville[axis] <= b + tol)
        if not inside.any():
            raise ValueError(f"span {self.span.tolist()} contains no Greville abscissa of the "
                             f"grid: make it at least a cell wide")
        return np.flatnonzero(inside), stride

    def grid_rule(self, grid):
        """The same constraint compiled (kernels.grid_modifiers.footing_force
        and footing_velocity) on ``grid``: parameters (base, speed, ramp,
        rough, dofs per layer, the vertical axis's cells, degree and
        uniform), the columns, the vertical axis (breakpoints, extraction)."""
        columns, stride = self._geometry(grid)
        breaks = np.asarray(grid.breakpoints[-1], dtype=np.float64)
        extraction = np.asarray(grid.extraction[-1], dtype=np.float64)
        parameters = (self.base, self.speed, self.ramp, float(self.rough), float(stride),
                      float(breaks.size - 1), float(grid.degree), float(grid._uniform[-1]))
        return GridRule(FOOTING, parameters, columns.astype(np.int64), True,
                        np.concatenate((breaks, extraction.ravel())))

    def rule_state(self):
        """(the time at the end of its last step, the base height it acted
        on in that step)."""
        return np.array([self._t, self._base_now])

    def take_rule_steps(self, states, reactions):
        """The record (end time, base, reaction, history) of compiled steps."""
        for state, reaction in zip(states, reactions):
            t = float(state[0])
            self.history.append((t, self.settlement_at(t), np.array(reaction, dtype=np.float64)))
        if len(reactions):
            self._t, self._base_now = float(states[-1][0]), float(states[-1][1])
            self.reaction = np.array(reactions[-1], dtype=np.float64)

    def bind(self, particles, grid):
        """A run starts the footing's record again."""
        self._t = 0.0
        self._base_now = np.nan
        self.history = []
        self.reaction = None
        self._active = None
        return []

    def force_modifiers(self):
        return [self]

    def velocity_modifiers(self):
        return [self]

    def reactions(self):
        return {} if self.reaction is None else {repr(self): self.reaction.copy()}

    def _base_line(self, mass, time):
        """(y_b, and along it: dofs (columns, p + 1), weights w_j masked by
        mass, sum w^2 / m per column, mass safe for division) at ``time``."""
        grid = self._grid
        y_b = min(max(self.base - self.settlement_at(time), grid.bounds[-1][0]),
                  grid.bounds[-1][1])
        first, values, _ = grid.axis_functions(grid.dim - 1, np.array([y_b]), backend="numpy")
        rows = int(first[0]) + np.arange(grid.degree + 1)
        dofs = self._columns[:, None] + self._stride * rows[None, :]
        m = mass[dofs]
        weights = np.where(m > 0, values[0][None, :], 0.0)
        m_safe = np.where(m > 0, m, 1.0)
        return y_b, (dofs, weights, (weights ** 2 / m_safe).sum(axis=1), m_safe)

    def _targets(self, t, dim):
        target = np.zeros(dim)
        target[-1] = self.velocity_at(t)
        return target, (range(dim) if self.rough else (dim - 1,))

    def modify_force(self, force, velocity, mass, dt, t=0.0, stage=0.0):
        """The grid force with the footing's contact force added at time
        tau = t + stage dt (class docstring); stage 0 (a step, or rk4's
        first stage) records the step: reaction, rule state (t + dt, y_b)
        and history (t + dt, s(t + dt), reaction)."""
        if self._grid is None or force.shape[0] != self._ndofs:
            raise ValueError(f"{self!r} was checked against another grid (call "
                             f"Scene(...) with this grid first)")
        time = t + stage * dt
        y_b, active = self._base_line(mass, time)
        dofs, w, S, m = active
        dim = force.shape[1]
        target, comps = self._targets(time + dt, dim)
        out = force.copy()
        reaction = np.zeros(dim)
        loaded = S > 0
        for c in comps:
            v_free = velocity[dofs, c] + dt * force[dofs, c] / m
            lam = np.where(loaded, (target[c] - (w * v_free).sum(axis=1))
                           / (dt * np.where(loaded, S, 1.0)), 0.0)
            contact = w * lam[:, None]
            np.add.at(out[:, c], dofs.ravel(), contact.ravel())
            reaction[c] = contact.sum()
        if stage == 0.0:
            self._active, self._base_now, self._t = active, y_b, time + dt
            self.reaction = reaction
            self.history.append((self._t, self.settlement_at(self._t), reaction.copy()))
        return out

    def modify_velocity(self, velocity, mass):
        """MUSL's re-projected velocity: the base line of the step's force
        at the footing's velocity at the step's end, by the same
        correction (class docstring)."""
        if self._active is None:
            return velocity
        dofs, w, S, m = self._active
        dim = velocity.shape[1]
        target, comps = self._targets(self._t, dim)
        out = velocity.copy()
        loaded = S > 0
        for c in comps:
            mu = np.where(loaded, (target[c] - (w * velocity[dofs, c]).sum(axis=1))
                          / np.where(loaded, S, 1.0), 0.0)
            np.add.at(out[:, c], dofs.ravel(), (w * mu[:, None] / m).ravel())
        return out
