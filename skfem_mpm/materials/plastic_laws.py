"""The elastoplastic materials' compiled point laws and their cached C
callbacks (:class:`~skfem_mpm.materials.VonMises`,
:class:`~skfem_mpm.materials.DruckerPrager`,
:class:`~skfem_mpm.materials.MohrCoulomb`; their NumPy updates, formulas and
sources are in their own files and :mod:`.plastic`).

Imported on the first compiled use of one of them (like :mod:`.laws`). Each
law: the 3x3 elastic trial stress (sigma_zz from the state in 2D; the
Hughes-Winget rotation when params[2] = 1), the material's return map, then
the new stress, sigma_zz and accumulated plastic strain. params start with
(lambda, mu, rotate); the state is (plastic_strain,) in 3D and
(plastic_strain, sigma_zz) in 2D.
"""
import math

import numpy as np
from numba import carray, cfunc, njit

from .compiled import POINT_SIGNATURE

__all__ = ["von_mises_law", "drucker_prager_law", "mohr_coulomb_law", "von_mises",
           "drucker_prager", "mohr_coulomb", "eigh3"]

_LAW = dict(inline="always", error_model="numpy", cache=True)
_HELPER = dict(error_model="numpy", cache=True)
_CALLBACK = dict(cache=True, error_model="numpy")


@njit(**_HELPER)
def trial3(params, L, dt, stress, state, T):
    """T <- the elastic trial stress (3x3) of :mod:`.plastic`."""
    dim = L.shape[0]
    lam, mu = params[0], params[1]
    for i in range(3):
        for j in range(3):
            T[i, j] = 0.0
    for i in range(dim):
        for j in range(dim):
            T[i, j] = stress[i, j]
    if dim == 2:
        T[2, 2] = state[1]
    if params[2] != 0.0:
        A = np.zeros((3, 3))
        for i in range(dim):
            for j in range(dim):
                A[i, j] = 0.25 * dt * (L[i, j] - L[j, i])
        factor = 2.0 / (1.0 + A[0, 1] ** 2 + A[0, 2] ** 2 + A[1, 2] ** 2)
        Q = np.empty((3, 3))
        for i in range(3):
            for j in range(3):
                a2 = A[i, 0] * A[0, j] + A[i, 1] * A[1, j] + A[i, 2] * A[2, j]
                Q[i, j] = (1.0 if i == j else 0.0) + factor * (A[i, j] + a2)
        QT = np.empty((3, 3))
        for i in range(3):
            for j in range(3):
                QT[i, j] = Q[i, 0] * T[0, j] + Q[i, 1] * T[1, j] + Q[i, 2] * T[2, j]
        for i in range(3):
            for j in range(3):
                T[i, j] = QT[i, 0] * Q[j, 0] + QT[i, 1] * Q[j, 1] + QT[i, 2] * Q[j, 2]
    trace = 0.0
    for i in range(dim):
        trace += dt * L[i, i]
    for i in range(dim):
        for j in range(dim):
            T[i, j] += mu * dt * (L[i, j] + L[j, i])
        T[i, i] += lam * trace
    if dim == 2:
        T[2, 2] += lam * trace


@njit(**_HELPER)
def finish(params, T, S, state, stress_out, state_out):
    """stress_out, state_out <- S (3x3), its sigma_zz in 2D, and
    plastic_strain + sqrt(2/3 |C^-1 (T - S)|^2)."""
    dim = stress_out.shape[0]
    lam, mu = params[0], params[1]
    K = lam + 2.0 * mu / 3.0
    trace = (T[0, 0] - S[0, 0]) + (T[1, 1] - S[1, 1]) + (T[2, 2] - S[2, 2])
    norm2 = 0.0
    for i in range(3):
        for j in range(3):
            e = (T[i, j] - S[i, j]) / (2.0 * mu)
            if i == j:
                e += trace / (9.0 * K) - trace / (6.0 * mu)
            norm2 += e * e
    state_out[0] = state[0] + math.sqrt(2.0 / 3.0 * norm2)
    for i in range(dim):
        for j in range(dim):
            stress_out[i, j] = S[i, j]
    if dim == 2:
        state_out[1] = S[2, 2]


@njit(**_HELPER)
def eigh3(A, values, V):
    """Eigenvalues (descending) and eigenvectors (columns of V) of the
    symmetric 3x3 A (overwritten) by cyclic Jacobi rotations (Golub and
    Van Loan, "Matrix Computations", sec. 8.5)."""
    for i in range(3):
        for j in range(3):
            V[i, j] = 1.0 if i == j else 0.0
    for sweep in range(30):
        off = A[0, 1] ** 2 + A[0, 2] ** 2 + A[1, 2] ** 2
        scale = A[0, 0] ** 2 + A[1, 1] ** 2 + A[2, 2] ** 2
        if off <= 1e-36 * scale or off == 0.0:
            break
        for pq in range(3):
            p = 0 if pq < 2 else 1
            q = 1 if pq == 0 else 2
            apq = A[p, q]
            if apq == 0.0:
                continue
            theta = (A[q, q] - A[p, p]) / (2.0 * apq)
            t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
            if theta < 0.0:
                t = -t
            c = 1.0 / math.sqrt(t * t + 1.0)
            s = t * c
            for k in range(3):
                akp, akq = A[k, p], A[k, q]
                A[k, p] = c * akp - s * akq
                A[k, q] = s * akp + c * akq
            for k in range(3):
                apk, aqk = A[p, k], A[q, k]
                A[p, k] = c * apk - s * aqk
                A[q, k] = s * apk + c * aqk
            for k in range(3):
                vkp, vkq = V[k, p], V[k, q]
                V[k, p] = c * vkp - s * vkq
                V[k, q] = s * vkp + c * vkq
    # sort descending (three compare-and-swaps of values and columns)
    for i in range(3):
        values[i] = A[i, i]
    for i, j in ((0, 1), (1, 2), (0, 1)):
        if values[i] < values[j]:
            values[i], values[j] = values[j], values[i]
            for k in range(3):
                V[k, i], V[k, j] = V[k, j], V[k, i]


@njit(**_LAW)
def von_mises_law(params, L, F, dt, stress, state, stress_out, state_out):
    """Radial return (materials/von_mises.py); params (lambda, mu, rotate,
    sigma_y, H)."""
    mu, yield_stress, hardening = params[1], params[3], params[4]
    T = np.empty((3, 3))
    trial3(params, L, dt, stress, state, T)
    S = T.copy()
    mean = (T[0, 0] + T[1, 1] + T[2, 2]) / 3.0
    norm2 = 0.0
    for i in range(3):
        for j in range(3):
            d = T[i, j] - (mean if i == j else 0.0)
            norm2 += d * d
    q = math.sqrt(1.5 * norm2)
    f = q - (yield_stress + hardening * state[0])
    if f > 0.0:
        scale = 1.0 - 3.0 * mu * (f / (3.0 * mu + hardening)) / q
        for i in range(3):
            for j in range(3):
                S[i, j] = (T[i, j] - (mean if i == j else 0.0)) * scale + \
                    (mean if i == j else 0.0)
    finish(params, T, S, state, stress_out, state_out)


@njit(**_LAW)
def drucker_prager_law(params, L, F, dt, stress, state, stress_out, state_out):
    """Cone or apex return (materials/drucker_prager.py); params (lambda, mu,
    rotate, eta, xi c, eta_bar, K)."""
    mu, eta, xc, eta_bar, K = params[1], params[3], params[4], params[5], params[6]
    T = np.empty((3, 3))
    trial3(params, L, dt, stress, state, T)
    S = T.copy()
    p_t = (T[0, 0] + T[1, 1] + T[2, 2]) / 3.0
    norm2 = 0.0
    for i in range(3):
        for j in range(3):
            d = T[i, j] - (p_t if i == j else 0.0)
            norm2 += d * d
    root = math.sqrt(0.5 * norm2)
    f = root + eta * p_t - xc
    if f > 0.0:
        gamma = f / (mu + K * eta * eta_bar)
        if root - mu * gamma >= 0.0:
            scale = 1.0 - mu * gamma / root
            p = p_t - K * eta_bar * gamma
        else:
            scale = 0.0
            p = xc / eta
        for i in range(3):
            for j in range(3):
                S[i, j] = (T[i, j] - (p_t if i == j else 0.0)) * scale + (p if i == j else 0.0)
    finish(params, T, S, state, stress_out, state_out)


@njit(**_HELPER)
def mohr_coulomb_principal(params, s):
    """The Mohr-Coulomb return of principal stresses s (3,), descending, in
    place (materials/mohr_coulomb.py); params (lambda, mu, rotate, sin phi,
    sin psi, c cos phi, K, T or -1)."""
    G, sp, ss, ccp, K, cutoff = params[1], params[3], params[4], params[5], params[6], params[7]
    s1, s2, s3 = s[0], s[1], s[2]
    fa = (s1 - s3) + (s1 + s3) * sp - 2.0 * ccp
    if fa > 0.0:
        lam2 = 2.0 * (K - 2.0 * G / 3.0) * ss
        a = 4.0 * G * (1.0 + sp * ss / 3.0) + 4.0 * K * sp * ss
        g = fa / a
        m1 = s1 - g * (lam2 + 2.0 * G * (1.0 + ss))
        m2 = s2 - g * lam2
        m3 = s3 - g * (lam2 + 2.0 * G * (ss - 1.0))
        if m1 >= m2 and m2 >= m3:
            s[0], s[1], s[2] = m1, m2, m3
        else:
            if (1.0 - ss) * (s1 - s2) > (1.0 + ss) * (s2 - s3):  # edge s2 = s3
                fx = (s1 - s2) + (s1 + s2) * sp - 2.0 * ccp
                b = 4.0 * K * sp * ss + 2.0 * G * (1.0 + sp + ss - sp * ss / 3.0)
                det = a * a - b * b
                ga, gx = (a * fa - b * fx) / det, (a * fx - b * fa) / det
                e1 = s1 - ga * (lam2 + 2.0 * G * (1.0 + ss)) - gx * (lam2 + 2.0 * G * (1.0 + ss))
                e2 = s2 - ga * lam2 - gx * (lam2 + 2.0 * G * (ss - 1.0))
                e3 = s3 - ga * (lam2 + 2.0 * G * (ss - 1.0)) - gx * lam2
                ok = e1 >= e2
            else:  # edge s1 = s2
                fx = (s2 - s3) + (s2 + s3) * sp - 2.0 * ccp
                b = 4.0 * K * sp * ss + 2.0 * G * (1.0 - sp - ss - sp * ss / 3.0)
                det = a * a - b * b
                ga, gx = (a * fa - b * fx) / det, (a * fx - b * fa) / det
                e1 = s1 - ga * (lam2 + 2.0 * G * (1.0 + ss)) - gx * lam2
                e2 = s2 - ga * lam2 - gx * (lam2 + 2.0 * G * (1.0 + ss))
                e3 = s3 - ga * (lam2 + 2.0 * G * (ss - 1.0)) - gx * (lam2 + 2.0 * G * (ss - 1.0))
                ok = e2 >= e3
            if ok or sp <= 0.0:
                s[0], s[1], s[2] = e1, e2, e3
            else:
                apex = ccp / sp
                s[0], s[1], s[2] = apex, apex, apex
    if cutoff >= 0.0 and s[0] > cutoff:
        lam = K - 2.0 * G / 3.0
        M = lam + 2.0 * G
        d1 = (s[0] - cutoff) / M
        o2, o3 = s[1] - lam * d1, s[2] - lam * d1
        if o2 > cutoff:
            dsum = (s[0] - cutoff + s[1] - cutoff) / (M + lam)
            o2, o3 = cutoff, s[2] - lam * dsum
            if o3 > cutoff:
                o3 = cutoff
        s[0], s[1], s[2] = cutoff, o2, o3


@njit(**_LAW)
def mohr_coulomb_law(params, L, F, dt, stress, state, stress_out, state_out):
    """Principal-stress return (materials/mohr_coulomb.py)."""
    T = np.empty((3, 3))
    trial3(params, L, dt, stress, state, T)
    A = T.copy()
    values = np.empty(3)
    V = np.empty((3, 3))
    eigh3(A, values, V)
    s1, s3 = values[0], values[2]
    S = T.copy()
    if (s1 - s3) + (s1 + s3) * params[3] - 2.0 * params[5] > 0.0 or \
            (params[7] >= 0.0 and s1 > params[7]):
        mohr_coulomb_principal(params, values)
        for i in range(3):
            for j in range(3):
                S[i, j] = (V[i, 0] * values[0] * V[j, 0] + V[i, 1] * values[1] * V[j, 1]
                           + V[i, 2] * values[2] * V[j, 2])
    finish(params, T, S, state, stress_out, state_out)


@cfunc(POINT_SIGNATURE, **_CALLBACK)
def von_mises(params, n_params, L, F, dim, dt, stress, state, n_state, stress_out, state_out):
    von_mises_law(carray(params, (n_params,)), carray(L, (dim, dim)), carray(F, (dim, dim)), dt,
                  carray(stress, (dim, dim)), carray(state, (n_state,)),
                  carray(stress_out, (dim, dim)), carray(state_out, (n_state,)))


@cfunc(POINT_SIGNATURE, **_CALLBACK)
def drucker_prager(params, n_params, L, F, dim, dt, stress, state, n_state, stress_out,
                   state_out):
    drucker_prager_law(carray(params, (n_params,)), carray(L, (dim, dim)),
                       carray(F, (dim, dim)), dt, carray(stress, (dim, dim)),
                       carray(state, (n_state,)),
                       carray(stress_out, (dim, dim)), carray(state_out, (n_state,)))


@cfunc(POINT_SIGNATURE, **_CALLBACK)
def mohr_coulomb(params, n_params, L, F, dim, dt, stress, state, n_state, stress_out, state_out):
    mohr_coulomb_law(carray(params, (n_params,)), carray(L, (dim, dim)), carray(F, (dim, dim)), dt,
                     carray(stress, (dim, dim)), carray(state, (n_state,)),
                     carray(stress_out, (dim, dim)), carray(state_out, (n_state,)))
