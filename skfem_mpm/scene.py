"""A scene: a grid, bodies (particles + material), effects and an end time."""
import numpy as np

from .effects import Effect
from .materials import Material
from .materials.state import state_layout
from .particles import Particles
from .validation import check_positive

__all__ = ["Body", "Scene"]


def _as_list(items):
    """A list of the items of an iterable (not a string); None otherwise."""
    if isinstance(items, (str, bytes)):
        return None
    try:
        return list(items)
    except TypeError:
        return None


class Body:
    """Particles of one material.

    The material's declared state fields (``material.state_fields``) that
    ``particles.state`` lacks are created at their initial values when a
    run starts; fields the particles carry are kept (an initial plastic
    strain, say) and must have the declared shapes."""

    def __init__(self, particles, material):
        if not isinstance(particles, Particles):
            raise ValueError(f"particles must be a Particles object, got {type(particles).__name__}")
        if not isinstance(material, Material):
            raise ValueError(f"material must be a Material (e.g. LinearElastic), got {material!r}")
        material.check_dim(particles.dim)
        state_layout(material, particles.dim).check(particles.state, particles.n)
        self.particles = particles
        self.material = material

    def state_layout(self):
        """The material's declared state (:class:`~skfem_mpm.materials.StateLayout`)."""
        return state_layout(self.material, self.particles.dim)

    def bound_particles(self):
        """The particles with every declared state field (missing ones at
        their initial values; the body's own arrays are shared, not copied)."""
        p = self.particles
        layout = self.state_layout()
        state = layout.with_initial(p.state, p.n)
        return p if state is p.state else p.replaced(state=state)

    def __repr__(self):
        return f"Body({self.particles!r}, {self.material!r})"


class Scene:
    """What to simulate: ``Scene(grid, bodies, t_end, effects=())``.

    ``bodies`` is a Body or a list of them, ``effects`` a sequence of
    :mod:`skfem_mpm.effects` objects; only declared effects are simulated.
    ``simulate`` and ``fem`` never modify a scene.
    """

    def __init__(self, grid, bodies, t_end, effects=()):
        if not all(hasattr(grid, k) for k in ("dim", "locate", "mesh", "ndofs")):
            raise TypeError(f"grid must be a SplineGrid or a LagrangeGrid, got {grid!r}")
        if isinstance(bodies, Body):
            bodies = [bodies]
        given = bodies
        bodies = _as_list(bodies)
        if not bodies or not all(isinstance(b, Body) for b in bodies):
            raise ValueError(f"bodies must be a Body or a non-empty list of Body objects, "
                             f"got {given!r}")
        for i, b in enumerate(bodies):
            if b.particles.n == 0:
                raise ValueError(f"bodies: body {i} has no particles (n = 0); a body needs at "
                                 f"least one particle")
            if b.particles.dim != grid.dim:
                raise ValueError(
                    f"body {i} has {b.particles.dim}D particles on a {grid.dim}D grid"
                )
            grid.locate(b.particles.x)  # raises for particles outside the grid
        declared = {}
        for i, b in enumerate(bodies):
            layout = b.state_layout()
            for name, shape in zip(layout.names, layout.shapes):
                seen = declared.setdefault(name, (shape, i))
                if seen[0] != shape:
                    raise ValueError(
                        f"the materials of bodies {seen[1]} and {i} both declare the state field "
                        f"{name!r}, with per-particle shapes {seen[0]} and {shape}: one name, "
                        f"one shape")
        self.grid = grid
        self.bodies = bodies
        self.t_end = check_positive("t_end", t_end)
        if isinstance(effects, Effect):
            raise ValueError(f"effects must be a list of Effect objects, got the single "
                             f"effect {effects!r}: write effects=[{effects!r}]")
        given = effects
        effects = _as_list(effects)
        if effects is None:
            raise ValueError(f"effects must be a list of Effect objects (Gravity, Fixed, ...), "
                             f"got {given!r}")
        effects = tuple(effects)
        for e in effects:
            if not isinstance(e, Effect):
                raise ValueError(f"effects must be Effect objects (Gravity, Fixed, ...), got {e!r}")
            e.check(grid)
        self.effects = effects

    @property
    def finite_strain(self):
        return any(b.material.finite_strain for b in self.bodies)

    def particles(self):
        """All bodies' particles in one set, ``body`` = body index, with F = I
        when some material needs finite strain, and every state field any
        material declares (:meth:`Body.bound_particles`; a body whose
        material does not declare a field gets that field's declared initial
        value). A single body that needs nothing added is shared, not copied:
        the solvers never write into the scene's arrays."""
        parts = [b.bound_particles() for b in self.bodies]
        only = parts[0]
        if len(parts) == 1 and not np.any(only.body) and \
                (only.F is not None or not self.finite_strain):
            return only.replaced()
        if self.finite_strain:
            parts = [p.copy() for p in parts]
            for p in parts:
                if p.F is None:
                    p.F = np.broadcast_to(np.eye(p.dim), (p.n, p.dim, p.dim)).copy()
        fill = {}
        for b in self.bodies:
            layout = b.state_layout()
            for name, value in zip(layout.names, layout.initial):
                fill.setdefault(name, value)
        out = Particles.concatenate(parts, bodies=range(len(parts)), fill=fill)
        return out

    def __repr__(self):
        return (f"Scene({self.grid!r}, bodies={len(self.bodies)}, t_end={self.t_end:g}, "
                f"effects={list(self.effects)})")
