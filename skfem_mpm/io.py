"""Output and restart: ParaView time series (meshio) and checkpoints (.npz).

A checkpoint is a plain NumPy ``.npz`` (no pickle) holding everything the
next step depends on: the particle arrays, time, step count, dt, the
accumulated external work, the conjugate-gradient warm starts, the central
difference half-step data, the bound traction layers, the materials'
per-particle state (``state.<name>``) and the saves recorded so far.
``simulate(scene, method, restart=path)`` continues from it and ends
bit-for-bit equal to an uninterrupted run. It also holds the fingerprint
of its scene and method (:mod:`skfem_mpm.fingerprint`); reading one checks
each member's size before inflating it, and
:mod:`skfem_mpm.checkpoint_check` validates every array before a restart
uses it.
"""
import json
import os
from pathlib import Path

import numpy as np

from .checkpoint_check import check_checkpoint, checkpoint_size_bound, state_fingerprint
from .solve.result import HISTORY_FIELDS, OUTPUT_FIELDS

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
