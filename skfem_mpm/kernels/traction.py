"""A traction on a side of the body, on the compiled paths: where its loaded
faces are, and the work its loads do.

:class:`skfem_mpm.effects.SurfaceTraction` puts the load of each outermost
particle p on its outer face, x_p + sign (s_p / 2) (V_p / V0_p)^(1/dim)
e_axis (s_p the particle's reference size), with the force a_p tau(t); the
grid force is f_i = sum_p a_p tau N_i(face_p), the p2g kernel's external
force of "particles" at the faces that carry nothing else. The compiled
executor and the compiled loop both compute the faces and the work here,
so they agree bit for bit (the reference executor keeps the effect's NumPy
version, the oracle).
"""
import numpy as np
from numba import njit

__all__ = ["loads_power", "side_faces"]


@njit(cache=True, error_model="numpy")
def side_faces(x, V, V0, index, size, axis, sign, bounds, faces):
    """faces[j] = the outer face of particle index[j] (see the module),
    clipped into the grid's ``bounds`` (dim, 2); returns the first j whose
    face lies beyond them by more than 1e-12 of the grid's extent (the
    caller raises), else -1."""
    k = index.shape[0]
    dim = x.shape[1]
    for j in range(k):
        i = index[j]
        ratio = V[i] / V0[i]
        if dim == 1:
            stretch = ratio
        elif dim == 2:
            stretch = np.sqrt(ratio)
        else:
            stretch = ratio ** (1.0 / 3.0)
        for c in range(dim):
            faces[j, c] = x[i, c]
        faces[j, axis] += sign * 0.5 * size[j] * stretch
    for a in range(dim):
        lo = bounds[a, 0]
        hi = bounds[a, 1]
        tol = 1e-12 * (hi - lo)
        for j in range(k):
            if faces[j, a] < lo - tol or faces[j, a] > hi + tol:
                return j
            faces[j, a] = min(max(faces[j, a], lo), hi)
    return -1


@njit(cache=True, error_model="numpy")
def loads_power(index, loads, rates):
    """sum_j loads[j] . rates[index[j]]: with the particles' displacements
    of a step, the work of the loads; with dx_p/dt, their power."""
    total = 0.0
    for j in range(index.shape[0]):
        i = index[j]
        for c in range(loads.shape[1]):
            total += loads[j, c] * rates[i, c]
    return total
