"""The records the transfer kernels take as arguments.

Each record is a plain tuple whose fields are named, in order, by the
namedtuple of the same name below; the generated kernels unpack them by
those names (:func:`unpack`). The kernels are called with plain tuples,
not the namedtuples themselves: numba types a plain tuple of arrays in its
compiled dispatcher, a namedtuple in Python (several microseconds a call).
"""
from collections import namedtuple

import numpy as np

__all__ = ["Axis", "Grid", "ParticleArrays", "Update", "grid_record", "particle_record",
           "unpack"]

# One grid axis: breakpoints u_0 < ... < u_cells, whether they are uniform,
# cells / (u_cells - u_0), the Bezier extraction matrices (cells, p+1, p+1).
Axis = namedtuple("Axis", "breaks uniform inv_h extraction")

# The grid: one Axis per dimension and the flat node strides s_d
# (s_0 = 1, s_d = s_(d-1) times the number of functions on axis d - 1).
Grid = namedtuple("Grid", "axes strides")

# Particle arrays: positions x (n, dim), velocities v (n, dim),
# displacements u (n, dim), masses m (n,), volumes V (n,), stresses
# (n, dim, dim).
ParticleArrays = namedtuple("ParticleArrays", "x v u m V stress")

# The scalars of one g2p call: time step, FLIP factor c, whether v_p^new is
# computed (else read from the output), whether linear elasticity is fused
# and its Lame parameters, whether a_p is stored.
Update = namedtuple("Update", "dt vfactor flip fused lam mu store_acc")


def unpack(record, name, names=None):
    """Source line unpacking the record variable ``name`` into its fields
    (or into ``names``, one per field)."""
    return f"{', '.join(names or record._fields)} = {name}"


def grid_record(grid):
    """The Grid record (plain tuples) of a :class:`skfem_mpm.SplineGrid` or
    any object with its ``breakpoints``, ``_uniform``, ``extraction`` and
    ``basis_per_axis`` (one entry per axis, in any dimension)."""
    axes = []
    for d, u in enumerate(grid.breakpoints):
        u = np.ascontiguousarray(u, dtype=np.float64)
        axes.append((u, bool(grid._uniform[d]), float((u.size - 1) / (u[-1] - u[0])),
                     np.ascontiguousarray(grid.extraction[d], dtype=np.float64)))
    strides = [1]
    for n in grid.basis_per_axis[:-1]:
        strides.append(strides[-1] * int(n))
    return (tuple(axes), tuple(strides))


def particle_record(particles):
    """The ParticleArrays record (a plain tuple) of an object with those
    attributes."""
    p = particles
    return (p.x, p.v, p.u, p.m, p.V, p.stress)
