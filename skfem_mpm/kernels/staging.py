"""Runge-Kutta staging: the particle state y_n + sum_s c_s k_s, compiled.

For the stage (or step) weights c_s = w_s dt of up to four stages s and the
rates k_s of each field (:mod:`skfem_mpm.solve.runge_kutta`; Hairer,
Norsett, Wanner, "Solving Ordinary Differential Equations I", Sec. II.1):

    dx = sum_s c_s kx_s,   x <- x_n + dx,   u <- u_n + dx,
    v <- v_n + sum_s c_s kv_s,
    sigma <- sigma_n + sum_s c_s ksigma_s,   V <- V_n + sum_s c_s kV_s
                                             (with ``small``: small strain),
    F <- F_n + sum_s c_s kF_s                (with ``finite``),

summed in the order of s, stages with c_s = 0 skipped (the order of the
NumPy reference). A finite-strain material's stress and volume follow
from F afterwards (sigma(F), V0 det F).
"""
from numba import njit, prange

__all__ = ["combine_stages", "deformation_rate"]


@njit(cache=True, inline="always")
def _sum(start, c, k, i, a, b):
    total = start
    for s in range(c.shape[0]):
        if c[s] != 0.0:
            total += c[s] * k[s, i, a, b]
    return total


@njit(cache=True, parallel=True, error_model="numpy")
def combine_stages(c, x, u, v, stress, V, F, kx, kv, ks, kV, kF, small, finite,
                   x_out, u_out, v_out, stress_out, V_out, F_out, nt):
    """See the module docstring; the rates have a leading stage axis (kx,
    kv (stages, n, dim); ks, kF (stages, n, dim, dim); kV (stages, n)),
    ``c`` (stages,) the weights times dt; ``nt`` blocks of particles."""
    n, dim = x.shape
    for t in prange(nt):
        for i in range(t * n // nt, (t + 1) * n // nt):
            for a in range(dim):
                dx = 0.0
                dv = v[i, a]
                for s in range(c.shape[0]):
                    if c[s] != 0.0:
                        dx += c[s] * kx[s, i, a]
                        dv += c[s] * kv[s, i, a]
                x_out[i, a] = x[i, a] + dx
                u_out[i, a] = u[i, a] + dx
                v_out[i, a] = dv
            if small:
                w = V[i]
                for s in range(c.shape[0]):
                    if c[s] != 0.0:
                        w += c[s] * kV[s, i]
                V_out[i] = w
                for a in range(dim):
                    for b in range(dim):
                        stress_out[i, a, b] = _sum(stress[i, a, b], c, ks, i, a, b)
            if finite:
                for a in range(dim):
                    for b in range(dim):
                        F_out[i, a, b] = _sum(F[i, a, b], c, kF, i, a, b)


@njit(cache=True, parallel=True, error_model="numpy")
def deformation_rate(L, F, out, nt):
    """out_i = L_i F_i (n, dim, dim) for every particle i, in ``nt`` blocks:
    the rate of the deformation gradient, dF/dt = L F."""
    n, dim = L.shape[0], L.shape[1]
    for t in prange(nt):
        for i in range(t * n // nt, (t + 1) * n // nt):
            for a in range(dim):
                for b in range(dim):
                    s = 0.0
                    for c in range(dim):
                        s += L[i, a, c] * F[i, c, b]
                    out[i, a, b] = s
