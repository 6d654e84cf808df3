"""Output and restart: ParaView time series (meshio) and checkpoints (.npz).

A checkpoint is a plain NumPy ``.npz`` (no pickle) holding everything the
next step depends on: the particle arrays, time, step count, dt, the
accumulated external work, the conjugate-gradient warm starts, the central
difference half-step data, the bound traction layers, the materials'
per-particle state (``state.<name>``) and the saves recorded so far.
``simulate(scene, method, restart=path)`` continues from it and ends
bit-for-bit equal to an uninterrupted run.
"""
import json
import os
from pathlib import Path

import numpy as np

from .fingerprint import fingerprint_differences, run_fingerprint
from .solve.result import ENERGY_FIELDS, HISTORY_FIELDS, OUTPUT_FIELDS

__all__ = ["save_result", "write_checkpoint", "read_checkpoint", "check_checkpoint",
           "restore_state", "checkpoint_size_bound", "nodal_mass_and_velocity"]

FORMAT = "skfem-mpm-checkpoint-2"


def _points3(x):
    out = np.zeros((x.shape[0], 3))
    out[:, : x.shape[1]] = x
    return out


def _vector3(a):
    return _points3(a)


def _tensor9(s):
    out = np.zeros((s.shape[0], 9))
    dim = s.shape[1]
    for i in range(dim):
        for j in range(dim):
            out[:, 3 * i + j] = s[:, i, j]
    return out


def _state_names(history):
    return [k for k in history if k not in HISTORY_FIELDS + OUTPUT_FIELDS]


def _saved(history, name, k, saves):
    """Save k of an output field, or None when the run did not record it at
    every save (a run restarted from a checkpoint written before it was)."""
    values = history.get(name)
    return None if values is None or len(values) != saves else np.asarray(values[k])


def _write_series(out, entries, name):
    """A ParaView collection ``out/name`` of (time, file) entries."""
    lines = ['<?xml version="1.0"?>',
             '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">',
             "  <Collection>"]
    lines += [f'    <DataSet timestep="{t!r}" part="0" file="{f}"/>' for t, f in entries]
    lines += ["  </Collection>", "</VTKFile>", ""]
    path = out / name
    path.write_text("\n".join(lines))
    return path


def nodal_mass_and_velocity(grid, x, m, v):
    """The particles' lumped nodal mass and velocity on ``grid``:
    m_i = sum_p N_i(x_p) m_p and v_i = sum_p N_i(x_p) m_p v_p / m_i (0 where
    m_i = 0), the particle-to-grid transfer of MPM (e.g. Sulsky, Chen and
    Schreyer 1994, eqs. 20-21) applied to a saved particle state."""
    from .quadrature import transfer_matrices

    N = transfer_matrices(grid, x)[0]
    mass = N.T @ m
    momentum = N.T @ (m[:, None] * v)
    velocity = np.zeros_like(momentum)
    has = mass > 0
    velocity[has] = momentum[has] / mass[has, None]
    return mass, velocity


def _control_net(grid):
    """(points (ndofs, 3), cells) of the grid's dofs: a spline grid's
    Greville abscissae joined as the tensor control net (lines, quads or
    hexahedra); a Lagrange grid's mesh itself."""
    if not hasattr(grid, "basis_per_axis"):
        from skfem.io.meshio import to_meshio

        m = grid.mesh
        return _points3(m.p.T), [(b.type, b.data.astype(np.int64))
                                 for b in to_meshio(m, encode_cell_data=False).cells]
    n = list(grid.basis_per_axis)
    index = np.arange(grid.ndofs).reshape(n[::-1])  # [.., b, a], a fastest
    if grid.dim == 1:
        cells = [("line", np.stack([index[:-1], index[1:]], axis=1))]
    elif grid.dim == 2:
        cells = [("quad", np.stack([index[:-1, :-1], index[:-1, 1:], index[1:, 1:],
                                    index[1:, :-1]], axis=-1).reshape(-1, 4))]
    else:
        i = index
        corners = [i[:-1, :-1, :-1], i[:-1, :-1, 1:], i[:-1, 1:, 1:], i[:-1, 1:, :-1],
                   i[1:, :-1, :-1], i[1:, :-1, 1:], i[1:, 1:, 1:], i[1:, 1:, :-1]]
        cells = [("hexahedron", np.stack(corners, axis=-1).reshape(-1, 8))]
    return _points3(grid.doflocs().T), cells


def _components(a):
    """A state field as VTU point data: (n,) for a scalar, else (n, comps)."""
    a = np.asarray(a, dtype=np.float64)
    return a.reshape(a.shape[0]) if a[0].size == 1 else a.reshape(a.shape[0], -1)


def save_result(result, path, grid=True):
    """Write ``path/particles_XXXX.vtu`` for every save and
    ``path/particles.pvd`` (open it in ParaView), plus ``path/grid.vtu``
    with the background mesh and, per save, ``path/grid_XXXX.vtu`` with
    ``path/grid.pvd``: the grid's dofs (a spline grid's control net at its
    Greville abscissae) with the saved particles' ``nodal_mass`` and
    ``nodal_velocity`` (:func:`nodal_mass_and_velocity`).

    Particle point data: displacement, velocity, stress (9 components),
    reference_position, index, mass, volume, density (mass / volume), body
    (the body id), and each material state field under its own name (a
    scalar per particle, or its values flattened as components). Returns
    the .pvd path."""
    import meshio

    out = Path(path)
    out.mkdir(parents=True, exist_ok=True)
    h = result.history
    saves = len(result.times)
    mesh_grid = getattr(result, "grid", None) if grid else None
    net = _control_net(mesh_grid) if mesh_grid is not None else None
    entries, grid_entries = [], []
    for k, t in enumerate(result.times):
        x = h["x"][k]
        n = x.shape[0]
        m, V, body = (_saved(h, name, k, saves) for name in OUTPUT_FIELDS)
        extra = {}
        if m is not None and V is not None:
            extra.update(mass=m.astype(np.float64), volume=V.astype(np.float64),
                         density=m / V)
        if body is not None:
            extra["body"] = body.astype(np.float64)
        mesh = meshio.Mesh(
            _points3(x), [("vertex", np.arange(n, dtype=np.int64)[:, None])],
            point_data={
                "displacement": _vector3(h["u"][k]),
                "velocity": _vector3(h["v"][k]),
                "stress": _tensor9(h["stress"][k]),
                "reference_position": _vector3(h["X"][k]),
                "index": h["index"][k].astype(np.float64),
                **extra,
                **{name: _components(h[name][k]) for name in _state_names(h)},
            },
        )
        name = f"particles_{k:04d}.vtu"
        meshio.write(str(out / name), mesh, file_format="vtu")
        entries.append((float(t), name))
        if net is not None and m is not None:
            mass, velocity = nodal_mass_and_velocity(mesh_grid, x, m, h["v"][k])
            name = f"grid_{k:04d}.vtu"
            meshio.write(str(out / name), meshio.Mesh(
                net[0], net[1], point_data={"nodal_mass": mass,
                                            "nodal_velocity": _vector3(velocity)}),
                file_format="vtu")
            grid_entries.append((float(t), name))
    pvd = _write_series(out, entries, "particles.pvd")
    if grid_entries:
        _write_series(out, grid_entries, "grid.pvd")
    if mesh_grid is not None:
        from skfem.io.meshio import to_meshio

        # scikit-fem's own conversion: it knows each cell type's vertex order
        # (a hexahedron's differs from VTK's)
        m = mesh_grid.mesh
        cells = [(block.type, block.data.astype(np.int64))
                 for block in to_meshio(m, encode_cell_data=False).cells]
        meshio.write(str(out / "grid.vtu"), meshio.Mesh(_points3(m.p.T), cells),
                     file_format="vtu")
    return pvd


def state_fingerprint(state):
    """The run's :func:`~skfem_mpm.fingerprint.run_fingerprint` (computed
    once per run: the scene and method never change during it)."""
    if getattr(state, "_fingerprint", None) is None:
        state._fingerprint = run_fingerprint(state.scene, state.method)
    return state._fingerprint


def write_checkpoint(path, state, recorder):
    """Save the run state after ``state.step`` steps (atomically)."""
    p = state.particles
    arrays = {
        "format": np.array(FORMAT),
        "x": p.x, "X": p.X, "u": p.u, "v": p.v, "m": p.m, "V": p.V, "V0": p.V0, "stress": p.stress,
        "body": p.body, "index": state.index,
        "has_F": np.array(p.F is not None),
        "F": p.F if p.F is not None else np.zeros(0),
        "t": np.array(state.t), "step": np.array(state.step), "dt": np.array(state.dt),
        "dt_crit": np.array(state.dt_crit),
        "n_steps": np.array(-1 if state.n_steps is None else state.n_steps),
        "external_work": np.array(state.external_work), "removed": np.array(state.removed),
        "has_pacc": np.array(state.particle_acceleration is not None),
        "pacc": state.particle_acceleration if state.particle_acceleration is not None
        else np.zeros(0),
        "method": np.array(json.dumps(state.method.as_dict())),
        "initial_particles": np.array(state.initial_count),
        "ndofs": np.array(state.grid.ndofs),
        "reactions": np.array(json.dumps({k: v.tolist() for k, v in state.reactions.items()})),
        "rec_reactions": np.array(json.dumps(
            [{k: v.tolist() for k, v in r.items()} for r in recorder.reactions])),
        "timer": np.array(json.dumps(state.timer.state())),
        "small_dofs_max": np.array(getattr(state, "small_dofs_max", 0)),
        "state_names": np.array(json.dumps(list(p.state))),
        "fingerprint": np.array(json.dumps(state_fingerprint(state))),
    }
    for name, values in p.state.items():  # a dot: no other key has one
        arrays[f"state.{name}"] = values
    for key, value in state.warm.items():
        arrays[f"warm_{key}"] = value
    for i, f in enumerate(state.forces):
        for name, value in f.checkpoint_arrays().items():
            arrays[f"force{i}_{name}"] = value
    arrays.update(recorder.state_arrays())
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp.npz")
    try:
        np.savez(tmp, **arrays)
        os.replace(tmp, path)
    except BaseException:  # a full disk, an interrupt: no half-written file stays
        tmp.unlink(missing_ok=True)
        raise
    return path


MAX_CHECKPOINT_BYTES = 1 << 30
"""Default bound on a checkpoint's inflated size when no scene bounds it."""


def _read_member(zf, info, budget):
    """One ``.npy`` member of the archive, its size checked against
    ``budget`` from its header before any data is inflated; (array, bytes)."""
    fmt = np.lib.format
    with zf.open(info) as f:
        version = fmt.read_magic(f)
        if version == (1, 0):
            shape, fortran, dtype = fmt.read_array_header_1_0(f)
        elif version in ((2, 0), (3, 0)):
            shape, fortran, dtype = fmt.read_array_header_2_0(f)
        else:
            raise ValueError(f"member {info.filename!r}: unknown .npy version {version}")
        if dtype.hasobject:
            raise ValueError(f"member {info.filename!r} holds Python objects (dtype "
                             f"{dtype}); a checkpoint holds plain arrays only")
        count = int(np.prod(shape, dtype=np.int64)) if shape else 1
        nbytes = count * dtype.itemsize
        if nbytes > budget:
            raise ValueError(f"member {info.filename!r} would inflate to {nbytes} bytes "
                             f"(shape {shape}, {dtype}), beyond the bound of {budget} bytes "
                             f"left for this checkpoint")
        raw = f.read(nbytes)
        if len(raw) != nbytes:
            raise ValueError(f"member {info.filename!r} is truncated: {len(raw)} of "
                             f"{nbytes} bytes")
        if f.read(1):
            raise ValueError(f"member {info.filename!r} has data beyond its header's "
                             f"shape {shape}")
    a = np.frombuffer(raw, dtype=dtype, count=count)
    a = a.reshape(shape[::-1]).T if fortran else a.reshape(shape)
    return a.copy(), nbytes


def read_checkpoint(path, max_bytes=MAX_CHECKPOINT_BYTES):
    """The arrays of a checkpoint (a dict); raises ValueError if it is not
    one, or if its arrays would inflate beyond ``max_bytes`` in total (each
    member's size is read from its header before its data is inflated, so a
    small file that would inflate to gigabytes is refused without reading it)."""
    import zipfile

    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"restart must be the path of a checkpoint (str or os.PathLike), "
                        f"got {path!r}")
    out = {}
    budget = int(max_bytes)
    try:
        with zipfile.ZipFile(path) as zf:
            for info in zf.infolist():
                name = info.filename
                if not name.endswith(".npy") or name[:-4] in out:
                    raise ValueError(f"member {name!r} is not a uniquely named .npy array")
                out[name[:-4]], used = _read_member(zf, info, budget)
                budget -= used
    except ValueError as exc:
        raise ValueError(f"cannot read checkpoint {str(path)!r}: {exc}") from None
    except (OSError, EOFError, zipfile.BadZipFile, zipfile.LargeZipFile, RuntimeError,
            NotImplementedError) as exc:
        raise ValueError(f"cannot read checkpoint {str(path)!r}: "
                         f"{type(exc).__name__}: {exc}") from None
    fmt = out.get("format")
    if fmt is None or fmt.shape != () or fmt.dtype.kind != "U" or str(fmt) != FORMAT:
        raise ValueError(f"{str(path)!r} is not a skfem-mpm checkpoint ({FORMAT})")
    return out


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
    extent = float(np.max(np.ptp(grid.mesh.p, axis=1)))
    volume = float(np.prod(np.ptp(grid.mesh.p, axis=1)))
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
    bound_size = grid.ndofs * max(dim, 1) * (2 * grid.degree + 2) ** dim
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
        if name == "X" and not np.array_equal(values, fresh.X[data["rec_index"]]):
            c.fail("rec_X", "differs from the scene's reference positions")
        if name == "x" and not state.grid.inside(values).all():
            c.fail("rec_x", "holds positions outside the grid")
    for name in ENERGY_FIELDS:
        c.array(f"rec_e_{name}", "f", (k,))
        known.add(f"rec_e_{name}")
    reactions = c.json("rec_reactions")
    if not isinstance(reactions, list) or len(reactions) != k:
        c.fail("rec_reactions", f"is not a list of {k} reaction records")
    for r in reactions:
        _finite_vectors(c, "rec_reactions", r, dim)


def restore_state(state, data):
    """Load checkpoint arrays into a freshly prepared State; returns the
    Recorder with the saves made before the checkpoint."""
    from .particles import Particles
    from .solve.result import Recorder
    from .solve.timing import PhaseTimer

    check_checkpoint(state, data)
    F = data["F"] if bool(data["has_F"]) else None
    p = Particles.__new__(Particles)
    for k in ("x", "X", "u", "v", "m", "V", "V0", "stress", "body"):
        setattr(p, k, data[k].copy())
    p.F = None if F is None else F.copy()
    names = json.loads(str(data["state_names"])) if "state_names" in data else []
    p.state = {name: data[f"state.{name}"].copy() for name in names}
    for b, body in enumerate(state.scene.bodies):
        layout = body.state_layout()
        rows = int(np.count_nonzero(p.body == b))
        missing = [name for name in layout.names if name not in p.state]
        if missing:
            raise ValueError(f"the checkpoint holds no state field {missing[0]!r}, which the "
                             f"material of body {b} declares: it was written for another scene")
        layout.check({k: v[p.body == b] for k, v in p.state.items()}, rows,
                     where="the checkpoint's state")
    p.info = {}
    state.particles = p
    state.index = data["index"].copy()
    state.t = float(data["t"])
    state.step = int(data["step"])
    state.dt = float(data["dt"])
    state.dt_crit = float(data["dt_crit"])
    n_steps = int(data["n_steps"])
    state.n_steps = None if n_steps < 0 else n_steps
    state.external_work = float(data["external_work"])
    state.removed = int(data["removed"])
    state.particle_acceleration = data["pacc"].copy() if bool(data["has_pacc"]) else None
    state.reactions = {k: np.array(v) for k, v in json.loads(str(data["reactions"])).items()}
    state.warm = {k[5:]: data[k].copy() for k in data if k.startswith("warm_")}
    state.timer = PhaseTimer.from_state(json.loads(str(data["timer"])))
    state.small_dofs_max = int(data["small_dofs_max"])
    for i, f in enumerate(state.forces):
        prefix = f"force{i}_"
        kept = {k[len(prefix):]: data[k] for k in data if k.startswith(prefix)}
        if kept:
            f.restore(kept)
    state._bind_bodies()
    reactions = [{k: np.array(v) for k, v in r.items()}
                 for r in json.loads(str(data["rec_reactions"]))]
    return Recorder.from_arrays(data, reactions)
