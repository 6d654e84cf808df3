"""A content hash of what determines a run: scene and method.

A checkpoint stores one SHA-256 digest per part of the run (the grid, each
body's particles and material, each effect, the end time, the method) and a
restart compares them with the scene and method it is given, naming the
parts that differ.

What a digest covers: every array by its dtype, shape and bytes; numbers and
strings by type and ``repr``; lists, tuples and dicts by their items; other
objects (materials, effects) by their class's qualified name and their public
attributes, recursively, except those a class names in ``run_records`` (what a
run writes into an effect: a wall's reaction, a footing's history). A callable (a ``Traction`` tau(t), a ``BodyForce``
b(X, t), a ``Prescribed`` velocity, a custom reconstruction) is identified by
its module, qualified name and default argument values only: **a changed
function body under the same name is not detected.**
"""
import hashlib
import numbers

import numpy as np

__all__ = ["run_fingerprint", "fingerprint_differences"]


def _update(h, obj, seen):
    if obj is None or isinstance(obj, (bool, numbers.Number, str, bytes)) \
            and not isinstance(obj, np.generic):
        h.update(f"{type(obj).__name__}:{obj!r};".encode())
        return
    if isinstance(obj, (np.ndarray, np.generic)):
        a = np.ascontiguousarray(obj)
        h.update(f"array:{a.dtype.str}:{a.shape};".encode())
        if a.dtype.hasobject:
            for item in a.ravel():
                _update(h, item, seen)
        else:
            h.update(a.tobytes())
        return
    if isinstance(obj, (list, tuple)):
        h.update(f"{type(obj).__name__}[{len(obj)}]".encode())
        for item in obj:
            _update(h, item, seen)
        return
    if isinstance(obj, dict):
        h.update(f"dict[{len(obj)}]".encode())
        for key in sorted(obj, key=repr):
            _update(h, key, seen)
            _update(h, obj[key], seen)
        return
    if callable(obj) and (not hasattr(obj, "__dict__") or hasattr(obj, "__code__")
                          or hasattr(obj, "py_func") or isinstance(obj, type)):
        # functions, lambdas, builtins, classes: by name (not by body)
        func = getattr(obj, "py_func", getattr(obj, "__func__", obj))
        h.update(f"callable:{getattr(func, '__module__', '')}."
                 f"{getattr(func, '__qualname__', type(func).__qualname__)};".encode())
        _update(h, getattr(func, "__defaults__", None), seen)
        _update(h, getattr(func, "__kwdefaults__", None), seen)
        return
    if id(obj) in seen:
        h.update(b"cycle;")
        return
    seen.add(id(obj))
    h.update(f"object:{type(obj).__module__}.{type(obj).__qualname__};".encode())
    records = getattr(type(obj), "run_records", ())
    public = {k: v for k, v in vars(obj).items() if not k.startswith("_") and k not in records} \
        if hasattr(obj, "__dict__") else {}
    _update(h, public, seen)


def digest(obj):
    """The SHA-256 hex digest of ``obj`` (see the module docstring)."""
    h = hashlib.sha256()
    _update(h, obj, set())
    return h.hexdigest()


def _grid_digest(grid):
    breaks = getattr(grid, "breakpoints", None)
    if breaks is not None:
        return digest((type(grid).__qualname__, int(grid.degree), list(breaks)))
    mesh = grid.mesh  # a Lagrange grid: its mesh's points and cells
    return digest((type(grid).__qualname__, getattr(grid, "degree", None),
                   np.asarray(mesh.p), np.asarray(mesh.t)))


def _particles_digest(particles):
    return digest(({k: a for k, a in particles._arrays().items()}, dict(particles.state)))


def run_fingerprint(scene, method):
    """{part: digest} of the parts of a run: ``grid``, ``t_end``,
    ``bodies`` (their count), ``body i particles``, ``body i material``,
    ``effects`` (their count), ``effect i (Name)``, ``method`` (its
    options, reconstruction options included)."""
    out = {"grid": _grid_digest(scene.grid), "t_end": digest(float(scene.t_end)),
           "bodies": digest(len(scene.bodies)), "effects": digest(len(scene.effects))}
    for i, body in enumerate(scene.bodies):
        out[f"body {i} particles"] = _particles_digest(body.particles)
        out[f"body {i} material ({type(body.material).__name__})"] = digest(body.material)
    for i, effect in enumerate(scene.effects):
        out[f"effect {i} ({type(effect).__name__})"] = digest(effect)
    out["method"] = digest((method.as_dict(), method.reconstruction,
                            method.reconstruction_options))
    return out


def fingerprint_differences(saved, current):
    """The part names whose digests differ (or exist on one side only)."""
    return [k for k in dict.fromkeys(list(saved) + list(current))
            if saved.get(k) != current.get(k)]
