"""The built-in materials' compiled point laws and their cached C callbacks
(the NumPy ``update`` of each material is in its own file).

This module is imported on the first compiled use of a built-in material
(:class:`skfem_mpm.materials.compiled.PointUpdate`); its callbacks compile
once per installation and load from numba's cache afterwards. A law and its
callback sit in this one file so that editing a law invalidates the cached
callback that inlines it. Every callback has the signature
:data:`~skfem_mpm.materials.compiled.POINT_SIGNATURE` and the same few
lines: it views the pointers as arrays and calls its law.
"""
import numpy as np
from numba import carray, cfunc, njit

from .compiled import POINT_SIGNATURE

__all__ = ["linear_elastic_law", "neo_hookean_law", "linear_elastic", "neo_hookean"]

_LAW = dict(inline="always", error_model="numpy", cache=True)
_CALLBACK = dict(cache=True, error_model="numpy")


@njit(**_LAW)
def linear_elastic_law(params, L, F, dt, stress, state, stress_out, state_out):
    """One particle: sigma + lambda tr(d_eps) I + 2 mu d_eps, d_eps = dt sym(L)
    (1D: sigma + E dt L); params (E,) in 1D, (lambda, mu) otherwise."""
    dim = L.shape[0]
    if dim == 1:
        stress_out[0, 0] = stress[0, 0] + params[0] * (dt * L[0, 0])
        return
    lam, mu = params[0], params[1]
    trace = 0.0
    for i in range(dim):
        trace += dt * L[i, i]
    for i in range(dim):
        for j in range(dim):
            d_sigma = 2.0 * mu * (0.5 * dt * (L[i, j] + L[j, i]))
            if i == j:
                d_sigma += lam * trace
            stress_out[i, j] = stress[i, j] + d_sigma


@cfunc(POINT_SIGNATURE, **_CALLBACK)
def linear_elastic(params, n_params, L, F, dim, dt, stress, state, n_state, stress_out,
                   state_out):
    linear_elastic_law(carray(params, (n_params,)), carray(L, (dim, dim)),
                       carray(F, (dim, dim)), dt, carray(stress, (dim, dim)),
                       carray(state, (n_state,)), carray(stress_out, (dim, dim)),
                       carray(state_out, (n_state,)))


@njit(**_LAW)
def neo_hookean_law(params, L, F, dt, stress, state, stress_out, state_out):
    """One particle: sigma = (mu (F F^T - I) + lambda ln(J) I) / J with F the
    deformation gradient after the step; params (lambda, mu)."""
    dim = F.shape[0]
    lam, mu = params[0], params[1]
    if dim == 1:
        J = F[0, 0]
    elif dim == 2:
        J = F[0, 0] * F[1, 1] - F[0, 1] * F[1, 0]
    else:
        J = (F[0, 0] * (F[1, 1] * F[2, 2] - F[1, 2] * F[2, 1])
             - F[0, 1] * (F[1, 0] * F[2, 2] - F[1, 2] * F[2, 0])
             + F[0, 2] * (F[1, 0] * F[2, 1] - F[1, 1] * F[2, 0]))
    pressure = lam * np.log(J)
    for i in range(dim):
        for j in range(dim):
            b = 0.0
            for k in range(dim):
                b += F[i, k] * F[j, k]
            if i == j:
                stress_out[i, j] = (mu * (b - 1.0) + pressure) / J
            else:
                stress_out[i, j] = mu * b / J


@cfunc(POINT_SIGNATURE, **_CALLBACK)
def neo_hookean(params, n_params, L, F, dim, dt, stress, state, n_state, stress_out,
                state_out):
    neo_hookean_law(carray(params, (n_params,)), carray(L, (dim, dim)), carray(F, (dim, dim)),
                    dt, carray(stress, (dim, dim)), carray(state, (n_state,)),
                    carray(stress_out, (dim, dim)), carray(state_out, (n_state,)))
