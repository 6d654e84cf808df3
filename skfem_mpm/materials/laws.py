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

from ..kernels.constitutive import determinant
from .compiled import POINT_SIGNATURE, WAVE_SPEED_SIGNATURE

__all__ = ["linear_elastic_law", "neo_hookean_law", "linear_elastic", "neo_hookean",
           "neo_hookean_wave_speed_law", "neo_hookean_wave_speed"]

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
def _jacobi_rotation(app, aqq, apq, arp, arq):
    """The rotation of a symmetric 3x3 matrix in the (p, q) plane that
    annihilates a_pq: (a_pp, a_qq, 0, a_rp, a_rq) after it (r the third
    index); a_pq negligible beside both a_pp and a_qq is set to 0 (Press et
    al., "Numerical Recipes", 3rd ed., Sec. 11.1)."""
    g = 100.0 * abs(apq)
    if apq == 0.0 or (abs(app) + g == abs(app) and abs(aqq) + g == abs(aqq)):
        return app, aqq, 0.0, arp, arq
    h = aqq - app
    if abs(h) + g == abs(h):
        t = apq / h
    else:
        theta = 0.5 * h / apq
        t = 1.0 / (abs(theta) + np.sqrt(1.0 + theta * theta))
        if theta < 0.0:
            t = -t
    c = 1.0 / np.sqrt(1.0 + t * t)
    s = t * c
    return app - t * apq, aqq + t * apq, 0.0, c * arp - s * arq, s * arp + c * arq


@njit(**_LAW)
def _right_cauchy_green_eigenvalues(F, J):
    """The eigenvalues (l_0, l_1, l_2) of C = F^T F (dim of them used):
    1D F^2; 2D (a + d)/2 + hypot((a - d)/2, b) and J^2 over it (no
    cancellation); 3D cyclic Jacobi rotations until the off-diagonal
    entries vanish (Golub & Van Loan, "Matrix Computations", 4th ed.,
    Sec. 8.5)."""
    dim = F.shape[0]
    if dim == 1:
        return F[0, 0] * F[0, 0], 0.0, 0.0
    if dim == 2:
        a = F[0, 0] * F[0, 0] + F[1, 0] * F[1, 0]
        d = F[0, 1] * F[0, 1] + F[1, 1] * F[1, 1]
        b = F[0, 0] * F[0, 1] + F[1, 0] * F[1, 1]
        top = 0.5 * (a + d) + np.hypot(0.5 * (a - d), b)
        return top, J * J / top, 0.0
    a00 = F[0, 0] * F[0, 0] + F[1, 0] * F[1, 0] + F[2, 0] * F[2, 0]
    a11 = F[0, 1] * F[0, 1] + F[1, 1] * F[1, 1] + F[2, 1] * F[2, 1]
    a22 = F[0, 2] * F[0, 2] + F[1, 2] * F[1, 2] + F[2, 2] * F[2, 2]
    a01 = F[0, 0] * F[0, 1] + F[1, 0] * F[1, 1] + F[2, 0] * F[2, 1]
    a02 = F[0, 0] * F[0, 2] + F[1, 0] * F[1, 2] + F[2, 0] * F[2, 2]
    a12 = F[0, 1] * F[0, 2] + F[1, 1] * F[1, 2] + F[2, 1] * F[2, 2]
    for _ in range(50):
        if a01 == 0.0 and a02 == 0.0 and a12 == 0.0:
            break
        a00, a11, a01, a02, a12 = _jacobi_rotation(a00, a11, a01, a02, a12)
        a00, a22, a02, a01, a12 = _jacobi_rotation(a00, a22, a02, a01, a12)
        a11, a22, a12, a01, a02 = _jacobi_rotation(a11, a22, a12, a01, a02)
    return a00, a11, a22


@njit(**_LAW)
def neo_hookean_law(params, L, F, dt, stress, state, stress_out, state_out):
    """One particle: sigma = (mu (F F^T - I) + lambda ln(J) I) / J with F the
    deformation gradient after the step; params (lambda, mu)."""
    dim = F.shape[0]
    lam, mu = params[0], params[1]
    J = determinant(F, F.shape[0])
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


@njit(**_LAW)
def neo_hookean_wave_speed_law(params, F, m, V0, state):
    """One particle's largest uniaxial tangent wave speed over its principal
    stretches s_k (s_k^2 the eigenvalues of C = F^T F):

        c^2 = max_k (mu (1 + 1/s_k^2) + lambda (1 - ln J) / s_k^2) / rho0,

    rho0 = m / V0; params (lambda, mu). NeoHookean.wave_speed is the
    largest over the particles (the material's only copy of the formula)."""
    dim = F.shape[0]
    lam, mu = params[0], params[1]
    J = determinant(F, F.shape[0])
    stretch2 = _right_cauchy_green_eigenvalues(F, J)
    volumetric = lam * (1.0 - np.log(J))
    top = -np.inf
    for k in range(dim):
        tangent = mu * (1.0 + 1.0 / stretch2[k]) + volumetric / stretch2[k]
        if tangent > top or tangent != tangent:
            top = tangent
    return np.sqrt(top / (m / V0))


@cfunc(WAVE_SPEED_SIGNATURE, **_CALLBACK)
def neo_hookean_wave_speed(params, n_params, F, dim, m, V0, state, n_state):
    return neo_hookean_wave_speed_law(carray(params, (n_params,)), carray(F, (dim, dim)), m, V0,
                                      carray(state, (n_state,)))
