"""Material points: plain NumPy arrays, row per particle.

Names and shapes (the project's conventions):

    x      (n, dim)        current positions
    X      (n, dim)        reference (initial) positions
    u      (n, dim)        displacements, accumulated on their own (x - X
                           would lose the digits of small amplitudes)
    v      (n, dim)        velocities
    m      (n,)            masses
    V      (n,)            current volumes
    V0     (n,)            reference volumes
    stress (n, dim, dim)   Cauchy stress, symmetric
    F      (n, dim, dim)   deformation gradient, only for finite strain (else None)
    body   (n,)            integer body id
    state  {name: (n, ...)} the materials' per-particle state (plastic strain,
                           sigma_zz, ...): a dict of float64 arrays, one row
                           per particle, empty for materials without state

A material declares its state fields (``Material.state_fields``); a scene
adds the declared fields a body's particles lack at their initial values and
keeps the ones a user supplied (``Particles(..., state={...})``).
"""
import numbers

import numpy as np

from .validation import check_choice, check_finite_array, check_positive

__all__ = ["Particles"]

LAYOUTS = ("uniform", "gauss", "random")

# names a state field cannot take: the particle arrays, and the names the
# history, checkpoints and ParaView output already use
RESERVED_STATE_NAMES = frozenset(("x", "X", "u", "v", "m", "V", "V0", "stress", "F", "body",
                                  "state", "index", "displacement", "velocity",
                                  "reference_position"))


def check_state_name(name, where="particles.state"):
    """A state field name: an identifier not used by another particle array."""
    if not isinstance(name, str) or not name.isidentifier():
        raise ValueError(f"{where}: a state field name must be a Python identifier "
                         f"(e.g. 'plastic_strain'), got {name!r}")
    if name in RESERVED_STATE_NAMES:
        raise ValueError(f"{where}: {name!r} cannot name a state field (reserved names: "
                         f"{', '.join(sorted(RESERVED_STATE_NAMES))})")
    return name


def _check_state(state, n):
    """A new dict of float64 arrays (n, ...) from a mapping of state fields."""
    if state is None:
        return {}
    if not isinstance(state, dict):
        raise ValueError(f"state must be a dict {{name: array (n, ...)}}, "
                         f"got {type(state).__name__}")
    out = {}
    for name, values in state.items():
        check_state_name(name)
        a = check_finite_array(f"state[{name!r}]", values)
        if a.ndim < 1 or a.shape[0] != n:
            raise ValueError(f"state[{name!r}] must have shape (n, ...) with one row per "
                             f"particle (n = {n}), got {a.shape}")
        out[name] = a.copy()
    return out


def _column(values, n, dim):
    """A 1D per-particle vector given as (n,) made (n, 1); anything else as given."""
    a = np.asarray(values)
    return a.reshape(n, 1) if dim == 1 and a.shape == (n,) else a


def _positive_array(name, values, n):
    a = check_finite_array(name, values, shape=(n,))
    if np.any(a <= 0):
        bad = int(np.flatnonzero(a <= 0)[0])
        raise ValueError(f"{name} must be > 0 for every particle, got {a[bad]} at index {bad}")
    return a


class Particles:
    """A set of material points (see the module docstring for the arrays).

    ``Particles(x, m, V)`` validates shapes, finiteness and positivity;
    optional arrays default to: ``X = x``, ``u = x - X``, ``v = 0``, ``V0 = V``,
    ``stress = 0``, ``F = None`` (small strain), ``body = 0``, ``state = {}``
    (``state`` is a dict {name: array (n, ...)}; see the module docstring).
    Build them with :meth:`seed`, :meth:`from_mesh` or :meth:`from_meshio`.
    """

    FIELDS = ("x", "X", "u", "v", "m", "V", "V0", "stress", "F", "body")

    def __init__(self, x, m, V, v=None, X=None, stress=None, F=None, body=None, V0=None,
                 u=None, state=None):
        x = check_finite_array("x", x)
        if x.ndim == 1:
            x = x[:, None]
        if x.ndim != 2 or x.shape[1] not in (1, 2, 3):
            raise ValueError(f"x must have shape (n, dim) with dim in 1..3, got {x.shape}")
        n, dim = x.shape
        self.x = check_finite_array("x", x).copy()
        self.X = (self.x.copy() if X is None
                  else check_finite_array("X", _column(X, n, dim), shape=(n, dim)).copy())
        self.u = (self.x - self.X if u is None
                  else check_finite_array("u", u, shape=(n, dim)).copy())
        self.v = (np.zeros((n, dim)) if v is None
                  else check_finite_array("v", _column(v, n, dim), shape=(n, dim)).copy())
        self.m = _positive_array("m", m, n).copy()
        self.V = _positive_array("V", V, n).copy()
        self.V0 = self.V.copy() if V0 is None else _positive_array("V0", V0, n).copy()
        self.stress = (np.zeros((n, dim, dim)) if stress is None
                       else check_finite_array("stress", stress, shape=(n, dim, dim)).copy())
        if F is None:
            self.F = None
        else:
            self.F = check_finite_array("F", F, shape=(n, dim, dim)).copy()
        if body is None:
            self.body = np.zeros(n, dtype=np.int64)
        else:
            body = np.asarray(body)
            if body.shape != (n,) or not np.issubdtype(body.dtype, np.integer):
                raise ValueError(f"body must be an integer array of shape ({n},), got "
                                 f"{body.dtype} {body.shape}")
            self.body = body.astype(np.int64).copy()
        self.state = _check_state(state, n)
        self.info = {}

    # ----------------------------------------------------------------- basics
    @property
    def n(self):
        """Number of particles."""
        return self.x.shape[0]

    @property
    def dim(self):
        return self.x.shape[1]

    def __len__(self):
        return self.n

    def __repr__(self):
        strain = "finite strain" if self.F is not None else "small strain"
        state = f", state={sorted(self.state)}" if self.state else ""
        return f"Particles(n={self.n}, dim={self.dim}, mass={self.m.sum():.6g}, {strain}{state})"

    def _arrays(self):
        return {k: getattr(self, k) for k in self.FIELDS}

    def copy(self):
        """A deep copy."""
        out = Particles.__new__(Particles)
        for k, a in self._arrays().items():
            setattr(out, k, None if a is None else a.copy())
        out.state = {k: a.copy() for k, a in self.state.items()}
        out.info = dict(self.info)
        return out

    def replaced(self, **arrays):
        """A new Particles object with some arrays replaced (the others are
        shared, not copied: the solver never edits arrays in place);
        ``state=`` replaces the whole state dict (its arrays are not checked:
        see :meth:`validate`)."""
        out = Particles.__new__(Particles)
        for k, a in self._arrays().items():
            setattr(out, k, a)
        out.state = dict(self.state)
        for k, a in arrays.items():
            if k == "state":
                out.state = dict(a)
                continue
            if k not in self.FIELDS:
                raise ValueError(f"unknown particle array {k!r}; valid: {self.FIELDS + ('state',)}")
            setattr(out, k, a)
        out.info = self.info
        return out

    def subset(self, which):
        """The particles selected by a boolean mask or an index array (copies),
        or by a slice (views)."""
        if isinstance(which, slice):
            out = Particles.__new__(Particles)
            for k, a in self._arrays().items():
                setattr(out, k, None if a is None else a[which])
            out.state = {k: a[which] for k, a in self.state.items()}
            out.info = dict(self.info)
            return out
        which = np.asarray(which)
        if which.dtype == bool and which.shape != (self.n,):
            raise ValueError(f"a mask must have shape ({self.n},), got {which.shape}")
        out = Particles.__new__(Particles)
        for k, a in self._arrays().items():
            setattr(out, k, None if a is None else a[which].copy())
        out.state = {k: a[which].copy() for k, a in self.state.items()}
        out.info = dict(self.info)
        return out

    @classmethod
    def concatenate(cls, parts, bodies=None, fill=None):
        """Join particle sets (same dim; all or none with F). ``bodies``
        optionally gives each part's body id.

        The state of the result has every field of any part (the union; a
        field must have the same per-particle shape in every part that has
        it). A part without a field gets ``fill[name]`` there (a number or
        an array of the field's per-particle shape), 0 when ``fill`` does not
        name it. A scene joins its bodies with each field's declared
        initial value as ``fill``."""
        parts = list(parts)
        if not parts:
            raise ValueError("concatenate needs at least one Particles object")
        dims = {p.dim for p in parts}
        if len(dims) != 1:
            raise ValueError(f"all parts must have the same dim, got {sorted(dims)}")
        has_F = {p.F is not None for p in parts}
        if len(has_F) != 1:
            raise ValueError("either all parts carry a deformation gradient F or none does")
        out = Particles.__new__(Particles)
        for k in cls.FIELDS:
            arrays = [getattr(p, k) for p in parts]
            setattr(out, k, None if arrays[0] is None else np.concatenate(arrays))
        if bodies is not None:
            if len(bodies) != len(parts):
                raise ValueError(f"bodies must give one id per part ({len(parts)}), got {len(bodies)}")
            out.body = np.concatenate([np.full(p.n, int(b)) for p, b in zip(parts, bodies)])
        out.state = _concatenate_state(parts, {} if fill is None else fill)
        out.info = {}
        return out

    def validate(self):
        """Check every array again (after user edits), the state fields
        included; raises ValueError."""
        Particles(self.x, self.m, self.V, v=self.v, X=self.X, stress=self.stress,
                  F=self.F, body=self.body, V0=self.V0, u=self.u, state=self.state)
        return self

    @property
    def momentum(self):
        """Total linear momentum sum_p m_p v_p, shape (dim,)."""
        return self.m @ self.v

    # --------------------------------------------------------------- seeding
    @classmethod
    def seed(cls, grid, ppc, density, layout="uniform", region=None, velocity=None,
             stress=None, seed=None):
        """Seed particles in the cells of ``grid``.

        Parameters
        ----------
        grid
            A SplineGrid (or LagrangeGrid on a tensor mesh) whose cells are filled.
        ppc
            Particles per cell per axis: an int or one int per axis.
        density
            Mass density, a number or a callable of X (n, dim) -> (n,).
        layout
            ``"uniform"``: at (2k - 1) / (2 ppc), k = 1..ppc, of each axis of a
            cell, volume = cell volume / ppc^dim. ``"gauss"``: at the ppc Gauss
            points per axis with the Gauss weights times the cell volume as
            volumes (exact quadrature to degree 2 ppc - 1). ``"random"``:
            ppc^dim uniformly random points per cell (``seed`` for the RNG).
        region
            None (the whole grid), a box ``((x0, x1),)`` / ``((x0, x1), (y0, y1))``
            (particles fill exactly the box: the cells it cuts are seeded on their
            part inside the box, so the total volume is exact), or a callable
            mask ``region(X) -> bool (n,)`` (the volume error of the particles,
            against a seeding eight times finer per axis in the cut cells, is
            reported in ``particles.info["volume_error"]``).
        velocity, stress
            Initial fields: a callable of X or an array broadcastable to
            (n, dim) / (n, dim, dim).
        """
        dim = grid.dim
        ppc = _check_ppc(ppc, dim)
        check_choice("layout", layout, LAYOUTS)
        breaks = _grid_breakpoints(grid)
        box = None
        mask = None
        if region is None:
            box = tuple(grid.bounds)
        elif callable(region):
            box = tuple(grid.bounds)
            mask = region
        else:
            box = _check_box(region, grid)
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, numbers.Integral)
                                 or seed < 0):
            raise ValueError(f"seed must be None or an integer >= 0 (the random layout's "
                             f"generator seed), got {seed!r}")
        rng = np.random.default_rng(seed)
        x, V = _seed_box(breaks, box, ppc, layout, rng)
        info = {"layout": layout, "ppc": ppc, "region": "box" if mask is None else "callable"}
        if mask is not None:
            keep = _mask_values(mask, x)
            x, V = x[keep], V[keep]
            if x.shape[0] == 0:
                raise ValueError("the region callable selects no particle")
            info["volume_error"] = _callable_volume_error(breaks, box, ppc, mask, V.sum())
        else:
            info["volume_error"] = 0.0
        info["volume"] = float(V.sum())
        particles = cls._with_fields(x, V, density, velocity, stress)
        particles.info = info
        return particles

    @classmethod
    def from_mesh(cls, mesh, density, intorder=2, velocity=None, stress=None):
        """Particles at the Gauss points of a scikit-fem mesh describing a
        body (any shape), volumes = Gauss weights times |det DF|."""
        from skfem import CellBasis

        basis = CellBasis(mesh, mesh.elem(), intorder=intorder)
        pts = np.asarray(basis.global_coordinates())  # (dim, nel, nqp)
        x = pts.reshape(pts.shape[0], -1).T
        V = np.asarray(basis.dx).reshape(-1)
        particles = cls._with_fields(x, V, density, velocity, stress)
        particles.info = {"layout": "mesh-gauss", "intorder": intorder,
                          "volume": float(V.sum()), "volume_error": 0.0}
        return particles

    @classmethod
    def from_meshio(cls, mesh_or_path, density, intorder=2, velocity=None, stress=None):
        """Particles from a meshio mesh or a file meshio reads (e.g. Gmsh
        ``.msh``), through scikit-fem's meshio import."""
        from skfem.io.meshio import from_meshio
        import meshio

        m = meshio.read(mesh_or_path) if isinstance(mesh_or_path, (str, bytes)) or hasattr(
            mesh_or_path, "__fspath__") else mesh_or_path
        return cls.from_mesh(from_meshio(m), density, intorder=intorder,
                             velocity=velocity, stress=stress)

    @classmethod
    def _with_fields(cls, x, V, density, velocity, stress):
        n, dim = x.shape
        if callable(density):
            rho = check_finite_array("density(X)", density(x.copy()))
            if rho.shape not in ((n,), (n, 1)):
                raise ValueError(f"density(X) must return one value per particle, shape "
                                 f"({n},), got {rho.shape}")
            rho = rho.reshape(n)
        else:
            rho = np.full(n, check_positive("density", density))
        rho = _positive_array("density", rho, n)
        v = _field("velocity", velocity, x, (n, dim))
        s = _field("stress", stress, x, (n, dim, dim))
        return cls(x, rho * V, V, v=v, stress=s)


def _concatenate_state(parts, fill):
    shapes = {}
    for i, p in enumerate(parts):
        for name, a in p.state.items():
            shape = a.shape[1:]
            if shapes.setdefault(name, shape) != shape:
                raise ValueError(f"state[{name!r}] has per-particle shape {shapes[name]} in one "
                                 f"part and {shape} in part {i}: concatenate needs one shape "
                                 f"per field")
    out = {}
    for name, shape in shapes.items():
        value = fill.get(name, 0.0)
        try:
            value = np.broadcast_to(np.asarray(value, dtype=np.float64), shape)
        except ValueError:
            raise ValueError(f"fill[{name!r}] must be a number or an array of shape {shape}, "
                             f"got {np.shape(value)}") from None
        out[name] = np.concatenate([
            p.state[name] if name in p.state else np.broadcast_to(value, (p.n,) + shape)
            for p in parts])
    return out


def _check_ppc(ppc, dim):
    values = ppc if isinstance(ppc, (tuple, list, np.ndarray)) else (ppc,) * dim
    if len(values) != dim:
        raise ValueError(f"ppc must be an int or {dim} ints (one per axis), got {ppc!r}")
    out = []
    for v in values:
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, numbers.Integral) or v < 1:
            raise ValueError(f"ppc must be a positive integer (per axis), got {v!r}")
        out.append(int(v))
    return tuple(out)


def _grid_breakpoints(grid):
    breaks = getattr(grid, "breakpoints", None)
    if breaks is None:
        raise ValueError(
            "Particles.seed needs a grid with breakpoints (SplineGrid or a tensor "
            "LagrangeGrid); for other meshes use Particles.from_mesh"
        )
    return breaks


def _check_box(region, grid):
    try:
        box = tuple((float(lo), float(hi)) for lo, hi in region)
    except (TypeError, ValueError):
        raise ValueError(
            f"region must be None, a box ((x0, x1), ...) or a callable, got {region!r}"
        ) from None
    if len(box) != grid.dim:
        raise ValueError(f"region box must have {grid.dim} (lo, hi) pairs, got {len(box)}")
    for axis, ((lo, hi), (glo, ghi)) in enumerate(zip(box, grid.bounds)):
        if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
            raise ValueError(f"region box axis {axis} must satisfy lo < hi, got ({lo}, {hi})")
        if lo < glo or hi > ghi:
            raise ValueError(
                f"region box axis {axis} ({lo}, {hi}) must lie inside the grid ({glo}, {ghi})"
            )
    return box


def _axis_intervals(breaks, lo, hi):
    """Non-empty intersections of the cells of one axis with [lo, hi]."""
    left = np.maximum(breaks[:-1], lo)
    right = np.minimum(breaks[1:], hi)
    keep = right > left
    return left[keep], right[keep]


def _axis_rule(ppc, layout):
    if layout == "gauss":
        pts, wts = np.polynomial.legendre.leggauss(ppc)
        return 0.5 * (pts + 1.0), 0.5 * wts
    k = np.arange(1, ppc + 1)
    return (2 * k - 1) / (2.0 * ppc), np.full(ppc, 1.0 / ppc)


def _seed_box(breaks, box, ppc, layout, rng):
    """Positions (n, dim) and volumes (n,) filling ``box`` cell by cell."""
    dim = len(breaks)
    intervals = [_axis_intervals(np.asarray(b), lo, hi) for b, (lo, hi) in zip(breaks, box)]
    if layout == "random":
        # every (cell intersect box) rectangle gets prod(ppc) random points
        lefts = np.meshgrid(*[iv[0] for iv in intervals], indexing="ij")
        widths = np.meshgrid(*[iv[1] - iv[0] for iv in intervals], indexing="ij")
        lefts = np.stack([a.ravel() for a in lefts], axis=1)
        widths = np.stack([a.ravel() for a in widths], axis=1)
        count = int(np.prod(ppc))
        u = rng.random((lefts.shape[0], count, dim))
        x = (lefts[:, None, :] + widths[:, None, :] * u).reshape(-1, dim)
        V = np.repeat(np.prod(widths, axis=1) / count, count)
        return x, V
    per_axis_x, per_axis_w = [], []
    for (left, right), k in zip(intervals, ppc):
        r, w = _axis_rule(k, layout)
        width = right - left
        per_axis_x.append((left[:, None] + width[:, None] * r[None, :]).ravel())
        per_axis_w.append((width[:, None] * w[None, :]).ravel())
    grids_x = np.meshgrid(*per_axis_x, indexing="ij")
    grids_w = np.meshgrid(*per_axis_w, indexing="ij")
    x = np.stack([g.ravel() for g in grids_x], axis=1)
    V = np.prod(np.stack([g.ravel() for g in grids_w], axis=1), axis=1)
    return x, V


def _mask_values(mask, x):
    keep = np.asarray(mask(x.copy()))
    if keep.shape != (x.shape[0],) or keep.dtype != bool:
        raise ValueError(
            f"region callable must return a boolean array of shape ({x.shape[0]},), "
            f"got {keep.dtype} {keep.shape}"
        )
    return keep


def _callable_volume_error(breaks, box, ppc, mask, volume):
    """|particle volume - volume of an 8x finer seeding| (an estimate)."""
    fine = tuple(8 * k for k in ppc)
    x, V = _seed_box(breaks, box, fine, "uniform", None)
    return float(abs(volume - V[_mask_values(mask, x)].sum()))


def _field(name, value, x, shape):
    if value is None:
        return None
    if callable(value):
        out = check_finite_array(f"{name}(X)", value(x.copy()))
        if shape[1] == 1 and out.shape == (shape[0],):
            out = out[:, None]
        if len(shape) == 3 and shape[1] == 1 and out.shape == (shape[0],):
            out = out[:, None, None]
    else:
        out = check_finite_array(name, value)
    try:
        out = np.broadcast_to(out, shape).copy()
    except ValueError:
        raise ValueError(f"{name} must give shape {shape}, got {out.shape}") from None
    return check_finite_array(name, out)
