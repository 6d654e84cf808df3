"""Checks of a checkpoint's arrays against the run that restarts from it.

:func:`check_checkpoint` refuses (ValueError) a checkpoint of another
scene or method (by the fingerprint of :mod:`skfem_mpm.fingerprint`,
naming the parts that differ) and any array that is not what this run
writes: dtype, shape, finiteness, sign, ranges, the invariants of a run
(reference positions, reference volumes, masses and bodies equal the
scene's), sizes bounded by the scene. It runs before anything of the file
reaches a kernel.
"""
import json

import numpy as np

from .fingerprint import fingerprint_differences, run_fingerprint
from .solve.result import ENERGY_FIELDS, HISTORY_FIELDS, OUTPUT_FIELDS
from .solve.stencil_system import StencilSystem

__all__ = ["check_checkpoint", "checkpoint_size_bound", "state_fingerprint"]


def state_fingerprint(state):
    """The run's :func:`~skfem_mpm.fingerprint.run_fingerprint` (computed
    once per run: the scene and method never change during it)."""
    if getattr(state, "_fingerprint", None) is None:
        state._fingerprint = run_fingerprint(state.scene, state.method)
    return state._fingerprint


class _Checker:
    """Checks of a checkpoint's arrays against the prepared run; each
    failure is a ValueError naming the array, what it holds and what is valid."""

    def __init__(self, data):
        self.data = data

    def fail(self, key, what):
        raise ValueError(f"the checkpoint's {key!r} {what}: refused (a damaged or crafted "
                         f"file, or one written by another version)")

    def get(self, key):
        if key not in self.data:
            self.fail(key, "is missing")
        return self.data[key]

    def array(self, key, kind, shape, finite=True, low=None, high=None, positive=False):
        """An array of dtype kind ``kind`` ('f' float64, 'i' int64, 'b' bool,
        'U' str) and ``shape`` (None matches any length)."""
        a = self.get(key)
        want = {"f": np.dtype(np.float64), "i": np.dtype(np.int64), "b": np.dtype(bool)}
        if kind == "U":
            if a.dtype.kind != "U":
                self.fail(key, f"has dtype {a.dtype}, not a string")
        elif a.dtype != want[kind]:
            self.fail(key, f"has dtype {a.dtype}, expected {want[kind]}")
        if a.ndim != len(shape) or any(w is not None and w != g for w, g in zip(shape, a.shape)):
            self.fail(key, f"has shape {a.shape}, expected "
                      f"({', '.join('any' if w is None else str(w) for w in shape)})")
        if kind in "fi" and a.size:
            if finite and kind == "f" and not np.isfinite(a).all():
                self.fail(key, "holds NaN or Inf")
            if low is not None and a.min() < low:
                self.fail(key, f"holds {a.min()}, below {low}")
            if high is not None and a.max() > high:
                self.fail(key, f"holds {a.max()}, above {high}")
            if positive and a.min() <= 0:
                self.fail(key, f"holds {a.min()}, which must be > 0")
        return a

    def scalar(self, key, kind, **bounds):
        return self.array(key, kind, (), **bounds)[()]

    def json(self, key):
        try:
            return json.loads(str(self.array(key, "U", ())))
        except ValueError:
            self.fail(key, "is not valid JSON")


def _finite_vectors(check, key, value, dim):
    """{name: dim numbers} of a reactions record."""
    if not isinstance(value, dict) or not all(isinstance(k, str) for k in value):
        check.fail(key, "is not a mapping of names to force vectors")
    for name, vec in value.items():
        try:
            a = np.asarray(vec, dtype=np.float64)
        except (TypeError, ValueError):
            check.fail(key, f"holds {vec!r} for {name!r}, not a vector of numbers")
        if a.shape != (dim,) or not np.isfinite(a).all():
            check.fail(key, f"holds {vec!r} for {name!r}, not {dim} finite numbers")


def checkpoint_size_bound(state, save_every=None):
    """A bound on the bytes a checkpoint of this run can hold: its arrays
    at every save it can record (the particle arrays of one save times the
    saves a run of ``state.n_steps`` steps makes with ``save_every``; 10^4
    saves for an adaptive run), twice over, plus 64 MiB for the rest."""
    p = state.particles
    per_particle = sum(a[0].nbytes for a in p._arrays().values() if a is not None and a.size) \
        + sum(a[0].nbytes for a in p.state.values())
    snapshot = p.n * (per_particle + 8 * (3 * p.dim + p.dim * p.dim + 2))
    if state.n_steps is None:
        saves = 10 ** 4
    else:
        saves = (state.n_steps // save_every if save_every else 1) + 3
    return 2 * snapshot * (saves + 2) + (64 << 20)


def check_checkpoint(state, data):
    """Refuse (ValueError) a checkpoint that does not belong to this run
    (naming the parts of scene or method that differ) or whose arrays are
    not what this run writes: dtype, shape, finiteness, sign, ranges and
    sizes bounded by the scene, all before anything reaches a kernel."""
    c = _Checker(data)
    method_saved = c.json("method")
    given = state.method.as_dict()
    if method_saved != given:
        differ = [f"{k}={method_saved.get(k)!r} (given {given.get(k)!r})"
                  for k in dict.fromkeys(list(method_saved) + list(given))
                  if method_saved.get(k) != given.get(k)] \
            if isinstance(method_saved, dict) else [repr(method_saved)]
        raise ValueError(f"the checkpoint was written with a different method: "
                         f"{', '.join(differ)}")
    saved = c.json("fingerprint")
    if not isinstance(saved, dict):
        c.fail("fingerprint", "is not a mapping")
    differ = fingerprint_differences(saved, state_fingerprint(state))
    if differ:
        raise ValueError(f"the checkpoint belongs to a different scene or method: "
                         f"{', '.join(differ)} differ{'s' if len(differ) == 1 else ''} from "
                         f"the ones given (a checkpoint continues only the run that wrote it; "
                         f"a callable is compared by its name, not its body)")
    fresh = state.particles
    n0, dim, grid = state.initial_count, state.grid.dim, state.grid
    if c.scalar("initial_particles", "i") != n0 or c.scalar("ndofs", "i") != grid.ndofs:
        raise ValueError("the checkpoint belongs to a different scene "
                         "(particle or dof counts differ)")
    x = c.array("x", "f", (None, dim))
    n = x.shape[0]
    if not 1 <= n <= n0:
        c.fail("x", f"holds {n} particles; this scene has 1 to {n0}")
    if not grid.inside(x).all():
        c.fail("x", "holds positions outside the grid")
    for key in ("X", "u", "v"):
        c.array(key, "f", (n, dim))
    for key in ("m", "V", "V0"):
        c.array(key, "f", (n,), positive=True)
    c.array("stress", "f", (n, dim, dim))
    c.array("body", "i", (n,), low=0, high=len(state.scene.bodies) - 1)
    index = c.array("index", "i", (n,), low=0, high=n0 - 1)
    if n > 1 and not (np.diff(index) > 0).all():
        c.fail("index", "is not strictly increasing")
    # what a run never changes: each particle's reference position,
    # reference volume, mass and body are the scene's
    for key in ("X", "V0", "m", "body"):
        if not np.array_equal(data[key], getattr(fresh, key)[index]):
            c.fail(key, "differs from the scene's particles (it never changes in a run)")
    extent, volume = _grid_extent(grid)
    if data["V"].max() > volume:
        c.fail("V", f"holds a volume {data['V'].max():.6g} above the grid's {volume:.6g}")
    drift = np.abs(x - data["X"] - data["u"]).max()
    if not drift <= 1e-6 * extent:
        c.fail("u", f"is not x - X (they differ by {drift:.3g})")
    has_F = bool(c.scalar("has_F", "b"))
    if has_F != (fresh.F is not None):
        c.fail("has_F", f"is {has_F}, but this scene {'needs' if fresh.F is not None else 'has no'}"
               f" deformation gradients")
    c.array("F", "f", (n, dim, dim) if has_F else (0,))
    if c.scalar("removed", "i") != n0 - n:
        c.fail("removed", f"is not {n0 - n} (initial minus current particles)")
    t_end = state.scene.t_end
    t = c.scalar("t", "f", low=0.0, high=t_end)
    step = c.scalar("step", "i", low=0)
    n_steps = c.scalar("n_steps", "i", low=-1)
    want_steps = -1 if state.n_steps is None else state.n_steps
    if n_steps != want_steps:
        c.fail("n_steps", f"is {n_steps}, this run takes {want_steps} (-1: adaptive)")
    if n_steps >= 0 and step > n_steps:
        c.fail("step", f"is {step}, beyond the run's {n_steps} steps")
    if step == 0 and t != 0.0 or step > 0 and t == 0.0:
        c.fail("t", f"is {t} at step {step}")
    dt = c.scalar("dt", "f", positive=True, high=t_end)
    dt_crit = c.scalar("dt_crit", "f", positive=True)
    if n_steps >= 0 and (dt != state.dt or dt_crit != state.dt_crit):
        c.fail("dt", f"and dt_crit ({dt}, {dt_crit}) are not this run's fixed "
               f"{state.dt}, {state.dt_crit}")
    c.scalar("external_work", "f")
    c.scalar("small_dofs_max", "i", low=0, high=grid.ndofs)
    has_pacc = bool(c.scalar("has_pacc", "b"))
    c.array("pacc", "f", (n, dim) if has_pacc else (0,))
    _finite_vectors(c, "reactions", c.json("reactions"), dim)
    timer = c.json("timer")
    if not isinstance(timer, dict) or not all(
            isinstance(timer.get(k), dict) for k in ("seconds", "counts")) or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool)
            for k in ("seconds", "counts") for v in timer[k].values()) or \
            not isinstance(timer.get("fused", {}), dict):
        c.fail("timer", "is not a table of phase seconds and counts")
    names = c.json("state_names")
    if not isinstance(names, list) or not all(isinstance(k, str) for k in names) or \
            sorted(names) != sorted(fresh.state):
        c.fail("state_names", f"are {names!r}, this scene's materials declare "
               f"{sorted(fresh.state)}")
    for name in names:
        c.array(f"state.{name}", "f", (n,) + fresh.state[name].shape[1:])
    # warm data: CG warm starts, fringe blocks, kept band factors (rows x (band + 1))
    bound_size = grid.ndofs * max(max(dim, 1) * (2 * grid.degree + 2) ** dim,
                                  StencilSystem.BAND_MAX + 1)
    for key in [k for k in data if k.startswith("warm_")]:
        a = data[key]
        if a.dtype not in (np.float64, np.int64) or a.ndim > 2 or a.size > bound_size or \
                (a.dtype == np.float64 and not np.isfinite(a).all()):
            c.fail(key, f"(dtype {a.dtype}, shape {a.shape}) is not a finite float64 or int64 "
                   f"array of at most {bound_size} entries")
        if a.dtype == np.int64 and a.size and (a.min() < 0 or a.max() > bound_size):
            c.fail(key, f"holds indices outside [0, {bound_size}]")
    known = {"format", "fingerprint", "method", "initial_particles", "ndofs", "x", "X", "u",
             "v", "m", "V", "V0", "stress", "body", "index", "has_F", "F", "removed", "t",
             "step", "n_steps", "dt", "dt_crit", "external_work", "small_dofs_max", "has_pacc",
             "pacc", "reactions", "timer", "state_names", "rec_reactions", "rec_times",
             "rec_last_step", "rec_state_names"}
    known |= {f"state.{name}" for name in names}
    for i, f in enumerate(state.forces):
        arrays = f.checkpoint_arrays()
        length = None
        for name, value in arrays.items():
            key = f"force{i}_{name}"
            kind = "i" if value.dtype.kind in "iu" else "f"
            a = c.array(key, kind, (None,), low=0 if kind == "i" else None,
                        high=n - 1 if kind == "i" else None, positive=kind == "f")
            if a.size > value.size or length is not None and a.size != length:
                c.fail(key, f"has {a.size} entries, not those of the other arrays of force "
                       f"{i} (at most {value.size})")
            length = a.size
            if kind == "f" and not np.isin(a, value).all():
                c.fail(key, f"holds values that force {i} does not bind on this scene")
            known.add(key)
    _check_records(c, data, state, fresh, n0, dim, known)
    unknown = sorted(k for k in data if k not in known and not k.startswith("warm_"))
    if unknown:
        c.fail(unknown[0], "is not an array this version writes")


def _grid_extent(grid):
    """The grid's largest side and its volume (bounds of positions and
    particle volumes)."""
    sides = np.ptp(grid.mesh.p, axis=1)
    return float(np.max(sides)), float(np.prod(sides))


def _check_records(c, data, state, fresh, n0, dim, known):
    """The saves recorded before the checkpoint."""
    times = c.array("rec_times", "f", (None,), low=0.0, high=state.scene.t_end)
    k = times.size
    if k < 1 or (k > 1 and not (np.diff(times) > 0).all()):
        c.fail("rec_times", "is not an increasing sequence of at least one time")
    c.scalar("rec_last_step", "i", low=-1, high=int(c.scalar("step", "i")))
    rec_names = c.json("rec_state_names")
    if not isinstance(rec_names, list) or sorted(rec_names) != sorted(fresh.state):
        c.fail("rec_state_names", f"are {rec_names!r}, not {sorted(fresh.state)}")
    shapes = {"index": (), "X": (dim,), "x": (dim,), "u": (dim,), "v": (dim,),
              "stress": (dim, dim)}
    # the output fields (mass, volume, body id) of checkpoints that hold them
    shapes.update({name: () for name in OUTPUT_FIELDS if f"rec_n_{name}" in data})
    shapes.update({name: fresh.state[name].shape[1:] for name in rec_names})
    extent, volume = _grid_extent(state.grid)
    sizes0 = None
    for name, shape in shapes.items():
        prefix = ("rec_n_", "rec_") if name in HISTORY_FIELDS + OUTPUT_FIELDS \
            else ("rec_state_n.", "rec_state.")
        sizes = c.array(prefix[0] + name, "i", (k,), low=1, high=n0)
        if sizes0 is not None and not np.array_equal(sizes, sizes0):
            c.fail(prefix[0] + name, "differs from the other fields' save sizes")
        sizes0 = sizes
        total = int(sizes.sum())
        if name == "index":
            values = c.array(prefix[1] + name, "i", (total,), low=0, high=n0 - 1)
        elif name == "body":
            values = c.array(prefix[1] + name, "i", (total,), low=0,
                             high=len(state.scene.bodies) - 1)
        elif name in ("m", "V"):
            values = c.array(prefix[1] + name, "f", (total,), positive=True)
        else:
            values = c.array(prefix[1] + name, "f", (total,) + shape)
        known.update(prefix[0] + name for _ in (0,))
        known.add(prefix[1] + name)
        # what a run never changes (reference positions, masses, bodies)
        # and the bounds of the current state hold at every save too
        if name in ("X", "m", "body") and \
                not np.array_equal(values, getattr(fresh, name)[data["rec_index"]]):
            c.fail(prefix[1] + name, "differs from the scene's particles (it never changes "
                   "in a run)")
        if name == "x" and not state.grid.inside(values).all():
            c.fail("rec_x", "holds positions outside the grid")
        if name == "V" and values.max() > volume:
            c.fail("rec_V", f"holds a volume {values.max():.6g} above the grid's "
                   f"{volume:.6g}")
    drift = np.abs(data["rec_x"] - data["rec_X"] - data["rec_u"]).max()
    if not drift <= 1e-6 * extent:
        c.fail("rec_u", f"is not x - X at every save (they differ by {drift:.3g})")
    for name in ENERGY_FIELDS:
        c.array(f"rec_e_{name}", "f", (k,))
        known.add(f"rec_e_{name}")
    reactions = c.json("rec_reactions")
    if not isinstance(reactions, list) or len(reactions) != k:
        c.fail("rec_reactions", f"is not a list of {k} reaction records")
    for r in reactions:
        _finite_vectors(c, "rec_reactions", r, dim)
