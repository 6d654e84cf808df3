"""Per-particle material state: what a material declares, how it is checked,
and how the compiled executor lays it out.

A material declares its state with ``state_fields(dim)`` (see
:class:`~skfem_mpm.materials.base.Material`): ``{name: (shape, initial)}``,
each field an array ``particles.state[name]`` of shape ``(n, *shape)``
(float64) starting at ``initial`` (a number, or an array of that shape).
``shape`` is ``()`` for a scalar per particle, ``(k,)`` or ``(a, b)``
otherwise.

The compiled point law sees one particle's fields flattened into one
vector ``state`` of ``n_state`` values: the fields in their declared order,
each in C order (:class:`StateLayout` gives the offsets). ``state_out``
arrives holding the same values, so a law writes only what changes.
"""
import numbers

import numpy as np

from ..particles import check_state_name

__all__ = ["StateLayout", "state_layout", "split_update", "PackedState"]


class StateLayout:
    """The state fields one material declares in one dimension.

    ``names``, ``shapes`` (per particle), ``initial`` (arrays of those
    shapes), ``offsets`` and ``sizes`` (in the packed vector of the point
    law) and ``size`` = n_state, the total."""

    def __init__(self, owner, fields):
        self.owner = owner
        self.names, self.shapes, self.initial, self.offsets, self.sizes = [], [], [], [], []
        offset = 0
        for name, (shape, initial) in fields.items():
            self.names.append(name)
            self.shapes.append(shape)
            self.initial.append(initial)
            size = int(np.prod(shape, dtype=np.int64))
            self.offsets.append(offset)
            self.sizes.append(size)
            offset += size
        self.size = offset

    def __bool__(self):
        return bool(self.names)

    def __repr__(self):
        fields = ", ".join(f"{n}{s}" for n, s in zip(self.names, self.shapes))
        return f"StateLayout({self.owner}: {fields or 'no state'}, n_state={self.size})"

    def shape_of(self, name):
        return self.shapes[self.names.index(name)]

    def initial_arrays(self, n, names=None):
        """{name: array (n, *shape) filled with the initial value}."""
        out = {}
        for name, shape, value in zip(self.names, self.shapes, self.initial):
            if names is None or name in names:
                out[name] = np.broadcast_to(value, (n,) + shape).copy()
        return out

    def check(self, state, n, where="particles.state"):
        """Raise ValueError for a declared field of ``state`` with the wrong
        shape (absent fields are allowed: they are initialised)."""
        for name, shape in zip(self.names, self.shapes):
            if name not in state:
                continue
            a = state[name]
            want = (n,) + shape
            if np.shape(a) != want:
                raise ValueError(
                    f"{where}[{name!r}] has shape {np.shape(a)}, but {self.owner} declares "
                    f"{name!r} with shape {shape} per particle: expected {want} "
                    f"(n = {n} particles)")

    def with_initial(self, state, n):
        """``state`` (a dict) with every declared field that is missing added
        at its initial value; fields already there are kept as they are."""
        self.check(state, n)
        missing = [name for name in self.names if name not in state]
        if not missing:
            return state
        return {**self.initial_arrays(n, missing), **state}

    def pack(self, state, index=None):
        """The declared fields as one array (rows, n_state), rows = every
        particle or those of ``index``."""
        first = state[self.names[0]]
        rows = first.shape[0] if index is None else len(index)
        out = np.empty((rows, self.size))
        for name, offset, size in zip(self.names, self.offsets, self.sizes):
            a = state[name]
            if index is not None:
                a = a[index]
            out[:, offset:offset + size] = a.reshape(rows, size)
        return out

    def views(self, packed):
        """{name: view of ``packed`` (rows, n_state) with shape (rows, *shape)}."""
        rows = packed.shape[0]
        return {name: packed[:, offset:offset + size].reshape((rows,) + shape)
                if shape else packed[:, offset]
                for name, shape, offset, size in zip(self.names, self.shapes, self.offsets,
                                                     self.sizes)}


def _shape(owner, name, shape):
    if isinstance(shape, numbers.Integral) and not isinstance(shape, bool):
        shape = (shape,)
    try:
        shape = tuple(shape)
    except TypeError:
        shape = None
    if shape is None or not all(isinstance(s, numbers.Integral) and not isinstance(s, bool)
                                and s >= 1 for s in shape):
        raise ValueError(f"{owner}.state_fields: the shape of {name!r} must be a tuple of "
                         f"positive integers (() for a scalar per particle)")
    return tuple(int(s) for s in shape)


def state_layout(material, dim):
    """The checked :class:`StateLayout` of ``material.state_fields(dim)``."""
    owner = type(material).__name__
    fields = material.state_fields(dim)
    if fields is None:
        fields = {}
    if not isinstance(fields, dict):
        raise ValueError(f"{owner}.state_fields({dim}) must return a dict "
                         f"{{name: (shape, initial)}}, got {type(fields).__name__}")
    checked = {}
    for name, spec in fields.items():
        check_state_name(name, f"{owner}.state_fields")
        try:
            shape, initial = spec
        except (TypeError, ValueError):
            raise ValueError(f"{owner}.state_fields: {name!r} must map to (shape, initial), "
                             f"got {spec!r}") from None
        shape = _shape(owner, name, shape)
        try:
            value = np.broadcast_to(np.asarray(initial, dtype=np.float64), shape).copy()
        except (TypeError, ValueError):
            raise ValueError(f"{owner}.state_fields: the initial value of {name!r} must be a "
                             f"number or an array of shape {shape}, got {initial!r}") from None
        if not np.all(np.isfinite(value)):
            raise ValueError(f"{owner}.state_fields: the initial value of {name!r} must be "
                             f"finite, got {initial!r}")
        checked[name] = (shape, value)
    return StateLayout(owner, checked)


def split_update(material, result, n, layout=None):
    """(stress, V, F, state) of a material's ``update`` result: the
    3-tuple (stress, V, F) of a material without state, or the 4-tuple with
    a dict of the new values of (some of) its declared fields."""
    if not isinstance(result, tuple) or len(result) not in (3, 4):
        raise ValueError(f"{type(material).__name__}.update must return (stress, V, F) or "
                         f"(stress, V, F, state), got {type(result).__name__}"
                         + (f" of length {len(result)}" if isinstance(result, tuple) else ""))
    if len(result) == 3:
        return result + ({},)
    stress, V, F, state = result
    if not state:
        return stress, V, F, {}
    if layout is None:
        layout = state_layout(material, np.shape(stress)[-1])
    for name, a in state.items():
        if name not in layout.names:
            raise ValueError(
                f"{type(material).__name__}.update returned the state field {name!r}, which its "
                f"state_fields does not declare (declared: {layout.names})")
        want = (n,) + layout.shape_of(name)
        if np.shape(a) != want:
            raise ValueError(
                f"{type(material).__name__}.update returned state[{name!r}] of shape "
                f"{np.shape(a)}, expected {want}")
    return stress, V, F, state


class PackedState:
    """The compiled executor's packed state of one material over all the
    particles, double-buffered like the stress: the new state is written into
    an array the current state does not use, and ``particles.state`` holds
    views of it (so the next step reads it without packing again)."""

    def __init__(self, layout):
        self.layout = layout
        self._buffers = []
        self._last = None  # (buffer, views) of the last output

    def arrays(self, state):
        """(state_in, state_out) for every particle, each (n, n_state)."""
        layout = self.layout
        state_in = None
        if self._last is not None:
            buffer, views = self._last
            if all(state.get(name) is view for name, view in views.items()):
                state_in = buffer
        if state_in is None:
            state_in = layout.pack(state)
        shape = state_in.shape
        free = [b for b in self._buffers if b is not state_in and b.shape == shape]
        if not free:
            free = [np.empty(shape)]
            self._buffers = [b for b in self._buffers if b is state_in] + free
        return state_in, free[0]

    def release(self, state):
        """The arrays of ``state`` were handed out (to a callback or a
        Result): forget the buffers they view, so that no later step writes
        into them."""
        arrays = list(state.values())
        self._buffers = [b for b in self._buffers
                         if not any(np.shares_memory(a, b) for a in arrays)]
        if self._last is not None and any(np.shares_memory(a, self._last[0]) for a in arrays):
            self._last = None

    def written(self, state_out):
        """The views of ``state_out`` that become ``particles.state``."""
        views = self.layout.views(state_out)
        self._last = (state_out, views)
        return views

