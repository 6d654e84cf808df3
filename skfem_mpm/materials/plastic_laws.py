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

from ..kernels.constitutive import determinant
from .compiled import POINT_SIGNATURE

__all__ = ["von_mises_law", "drucker_prager_law", "mohr_coulomb_law", "von_mises",
           "drucker_prager", "mohr_coulomb", "eigh3"]

_LAW = dict(inline="always", error_model="numpy", cache=True)
_HELPER = dict(error_model="numpy", cache=True)
_CALLBACK = dict(cache=True, error_model="numpy")


@njit(**_LAW)
def trial(params, L, dt, stress, state):
    """The elastic trial stress of :mod:`.plastic` as six scalars (xx, yy,
    zz, xy, xz, yz): sigma_zz from the state in 2D, the Hughes-Winget
    rotation Q sigma Q^T when params[2] = 1 (Q = I + f (A + A^2), A = dt
    skew(L) / 2 with entries a = A_xy, b = A_xz, c = A_yz, f = 2 / (1 + a^2 +
    b^2 + c^2)), then + lambda tr(d_eps) I + 2 mu d_eps."""
    dim = L.shape[0]
    lam, mu = params[0], params[1]
    sxx, syy, sxy = stress[0, 0], stress[1, 1], stress[0, 1]
    if dim == 3:
        szz, sxz, syz = stress[2, 2], stress[0, 2], stress[1, 2]
    else:
        szz, sxz, syz = state[1], 0.0, 0.0
    if params[2] != 0.0:
        a = 0.25 * dt * (L[0, 1] - L[1, 0])
        b = c = 0.0
        if dim == 3:
            b = 0.25 * dt * (L[0, 2] - L[2, 0])
            c = 0.25 * dt * (L[1, 2] - L[2, 1])
        f = 2.0 / (1.0 + a * a + b * b + c * c)
        Q = (1.0 + f * (-a * a - b * b), f * (a - b * c), f * (b + a * c),
             f * (-a - b * c), 1.0 + f * (-a * a - c * c), f * (c - a * b),
             f * (-b + a * c), f * (-c - a * b), 1.0 + f * (-b * b - c * c))
        S = (sxx, sxy, sxz, sxy, syy, syz, sxz, syz, szz)
        sxx = _qsq(Q, S, 0, 0)
        syy = _qsq(Q, S, 1, 1)
        szz = _qsq(Q, S, 2, 2)
        sxy = _qsq(Q, S, 0, 1)
        sxz = _qsq(Q, S, 0, 2)
        syz = _qsq(Q, S, 1, 2)
    exx, eyy, exy = dt * L[0, 0], dt * L[1, 1], 0.5 * dt * (L[0, 1] + L[1, 0])
    ezz = exz = eyz = 0.0
    if dim == 3:
        ezz = dt * L[2, 2]
        exz = 0.5 * dt * (L[0, 2] + L[2, 0])
        eyz = 0.5 * dt * (L[1, 2] + L[2, 1])
    t = lam * (exx + eyy + ezz)
    return (sxx + t + 2.0 * mu * exx, syy + t + 2.0 * mu * eyy, szz + t + 2.0 * mu * ezz,
            sxy + 2.0 * mu * exy, sxz + 2.0 * mu * exz, syz + 2.0 * mu * eyz)


@njit(**_LAW)
def _qsq(Q, S, i, j):
    """(Q S Q^T)_ij of 3x3 matrices stored row by row in tuples."""
    out = 0.0
    for k in range(3):
        row = 0.0
        for m in range(3):
            row += S[3 * k + m] * Q[3 * j + m]
        out += Q[3 * i + k] * row
    return out


@njit(**_LAW)
def finish(params, T, S, state, stress_out, state_out):
    """stress_out, state_out <- the six components S, its sigma_zz in 2D,
    and plastic_strain + sqrt(2/3 |C^-1 (T - S)|^2) (T the trial)."""
    dim = stress_out.shape[0]
    lam, mu = params[0], params[1]
    K = lam + 2.0 * mu / 3.0
    dxx, dyy, dzz = T[0] - S[0], T[1] - S[1], T[2] - S[2]
    dxy, dxz, dyz = T[3] - S[3], T[4] - S[4], T[5] - S[5]
    volumetric = (dxx + dyy + dzz) * (1.0 / (9.0 * K) - 1.0 / (6.0 * mu))
    exx = dxx / (2.0 * mu) + volumetric
    eyy = dyy / (2.0 * mu) + volumetric
    ezz = dzz / (2.0 * mu) + volumetric
    norm2 = exx * exx + eyy * eyy + ezz * ezz \
        + 2.0 * (dxy * dxy + dxz * dxz + dyz * dyz) / (4.0 * mu * mu)
    state_out[0] = state[0] + math.sqrt(2.0 / 3.0 * norm2)
    stress_out[0, 0], stress_out[1, 1] = S[0], S[1]
    stress_out[0, 1] = stress_out[1, 0] = S[3]
    if dim == 3:
        stress_out[2, 2] = S[2]
        stress_out[0, 2] = stress_out[2, 0] = S[4]
        stress_out[1, 2] = stress_out[2, 1] = S[5]
    else:
        state_out[1] = S[2]


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
def _deviator(T):
    """(mean, the six deviator components, sqrt(J2)) of six components."""
    mean = (T[0] + T[1] + T[2]) / 3.0
    d = (T[0] - mean, T[1] - mean, T[2] - mean, T[3], T[4], T[5])
    j2 = 0.5 * (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) + d[3] * d[3] + d[4] * d[4] \
        + d[5] * d[5]
    return mean, d, math.sqrt(j2)


@njit(**_LAW)
def _scaled(d, scale, mean):
    return (d[0] * scale + mean, d[1] * scale + mean, d[2] * scale + mean, d[3] * scale,
            d[4] * scale, d[5] * scale)


@njit(**_LAW)
def von_mises_law(params, L, F, dt, stress, state, stress_out, state_out):
    """Radial return (materials/von_mises.py); params (lambda, mu, rotate,
    sigma_y, H)."""
    mu, yield_stress, hardening = params[1], params[3], params[4]
    T = trial(params, L, dt, stress, state)
    mean, d, root = _deviator(T)
    q = math.sqrt(3.0) * root
    f = q - (yield_stress + hardening * state[0])
    S = T
    if f > 0.0:
        S = _scaled(d, 1.0 - 3.0 * mu * (f / (3.0 * mu + hardening)) / q, mean)
    finish(params, T, S, state, stress_out, state_out)


@njit(**_LAW)
def drucker_prager_law(params, L, F, dt, stress, state, stress_out, state_out):
    """Cone or apex return (materials/drucker_prager.py); params (lambda, mu,
    rotate, eta, xi c, eta_bar, K)."""
    mu, eta, xc, eta_bar, K = params[1], params[3], params[4], params[5], params[6]
    T = trial(params, L, dt, stress, state)
    p_t, d, root = _deviator(T)
    f = root + eta * p_t - xc
    S = T
    if f > 0.0:
        gamma = f / (mu + K * eta * eta_bar)
        if root - mu * gamma >= 0.0:
            S = _scaled(d, 1.0 - mu * gamma / root, p_t - K * eta_bar * gamma)
        else:
            S = _scaled(d, 0.0, xc / eta)
    finish(params, T, S, state, stress_out, state_out)


@njit(**_LAW)
def mohr_coulomb_principal(params, s1, s2, s3):
    """The Mohr-Coulomb return of principal stresses s1 >= s2 >= s3
    (materials/mohr_coulomb.py); params (lambda, mu, rotate, sin phi,
    sin psi, c cos phi, K, T or -1). Returns the new (s1, s2, s3)."""
    G, sp, ss, ccp, K, cutoff = params[1], params[3], params[4], params[5], params[6], params[7]
    fa = (s1 - s3) + (s1 + s3) * sp - 2.0 * ccp
    if fa > 0.0:
        lam2 = 2.0 * (K - 2.0 * G / 3.0) * ss
        a = 4.0 * G * (1.0 + sp * ss / 3.0) + 4.0 * K * sp * ss
        g = fa / a
        m1 = s1 - g * (lam2 + 2.0 * G * (1.0 + ss))
        m2 = s2 - g * lam2
        m3 = s3 - g * (lam2 + 2.0 * G * (ss - 1.0))
        if m1 >= m2 and m2 >= m3:
            s1, s2, s3 = m1, m2, m3
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
                s1, s2, s3 = e1, e2, e3
            else:
                s1 = s2 = s3 = ccp / sp
    if cutoff >= 0.0 and s1 > cutoff:
        lam = K - 2.0 * G / 3.0
        M = lam + 2.0 * G
        d1 = (s1 - cutoff) / M
        o2, o3 = s2 - lam * d1, s3 - lam * d1
        if o2 > cutoff:
            dsum = (s1 - cutoff + s2 - cutoff) / (M + lam)
            o2, o3 = cutoff, s3 - lam * dsum
            if o3 > cutoff:
                o3 = cutoff
        s1, s2, s3 = cutoff, o2, o3
    return s1, s2, s3


@njit(**_LAW)
def _yields(params, s1, s3):
    return (s1 - s3) + (s1 + s3) * params[3] - 2.0 * params[5] > 0.0 or \
        (params[7] >= 0.0 and s1 > params[7])


@njit(**_LAW)
def mohr_coulomb_law(params, L, F, dt, stress, state, stress_out, state_out):
    """Principal-stress return (materials/mohr_coulomb.py). 2D: the in-plane
    principal stresses c +- r (c = (sxx + syy) / 2, r = |((sxx - syy) / 2,
    sxy)|) and sigma_zz in closed form, the new in-plane stress
    (q_hi + q_lo) / 2 I + (q_hi - q_lo) / 2 (cos 2t, sin 2t; sin 2t, -cos 2t);
    3D: Jacobi eigen-decomposition (eigh3). Disconnected grains
    (params[8] = J_c > 0 and det F > J_c, F the deformation gradient after
    the step): zero stress and sigma_zz, the plastic strain kept."""
    if params[8] > 0.0 and determinant(F, F.shape[0]) > params[8]:
        dim = L.shape[0]
        for i in range(dim):
            for j in range(dim):
                stress_out[i, j] = 0.0
        if dim == 2:
            state_out[1] = 0.0
        return
    T = trial(params, L, dt, stress, state)
    S = T
    if L.shape[0] == 2:
        c = 0.5 * (T[0] + T[1])
        dx = 0.5 * (T[0] - T[1])
        r = math.sqrt(dx * dx + T[3] * T[3])
        hi, lo, z = c + r, c - r, T[2]
        # sort (hi, lo, z) descending: hi >= lo always, z goes first, middle or last
        if z > hi:
            s1, s2, s3 = z, hi, lo
        elif z > lo:
            s1, s2, s3 = hi, z, lo
        else:
            s1, s2, s3 = hi, lo, z
        if _yields(params, s1, s3):
            q1, q2, q3 = mohr_coulomb_principal(params, s1, s2, s3)
            if z > hi:
                qz, qhi, qlo = q1, q2, q3
            elif z > lo:
                qhi, qz, qlo = q1, q2, q3
            else:
                qhi, qlo, qz = q1, q2, q3
            cos2, sin2 = (dx / r, T[3] / r) if r > 0.0 else (1.0, 0.0)
            mean, half = 0.5 * (qhi + qlo), 0.5 * (qhi - qlo)
            S = (mean + half * cos2, mean - half * cos2, qz, half * sin2, 0.0, 0.0)
    else:
        work = np.empty((7, 3))  # A (3x3), V (3x3), values: one allocation
        A, V, values = work[0:3], work[3:6], work[6]
        A[0, 0], A[1, 1], A[2, 2] = T[0], T[1], T[2]
        A[0, 1] = A[1, 0] = T[3]
        A[0, 2] = A[2, 0] = T[4]
        A[1, 2] = A[2, 1] = T[5]
        eigh3(A, values, V)
        if _yields(params, values[0], values[2]):
            q = mohr_coulomb_principal(params, values[0], values[1], values[2])

            def entry(i, j):
                return V[i, 0] * q[0] * V[j, 0] + V[i, 1] * q[1] * V[j, 1] \
                    + V[i, 2] * q[2] * V[j, 2]
            S = (entry(0, 0), entry(1, 1), entry(2, 2), entry(0, 1), entry(0, 2), entry(1, 2))
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
