"""When the fast-dof guard's coverage pass can be skipped.

The guard (:func:`skfem_mpm.solve.timestep.covered_stiffness`) lumps dof
k by theta_k = smoothstep(2 r_k - 1), r_k = k_k / (limit D_k), from the
particles' sums K_k = sum_p m_p |grad N_k(x_p)|^2, D_k = sum_p m_p N_k(x_p)^2
and m_k = sum_p m_p N_k(x_p) (:func:`skfem_mpm.kernels.mpm.particle_coverage`).
That pass over the particles costs about as much as a transfer. Where no
row is near the threshold and the particles have hardly moved, its result
cannot change the step: :func:`coverage_holds` decides from the sums of the
last pass (at positions x^0) and the particles' largest displacement since,
d = max_p |x_p - x^0_p|, whether every row is still certain to stay below
the threshold; then the guard run on the kept sums gives the same theta as
a fresh pass (all 0 where it matters: see there) and the pass is skipped.
:func:`coverage_reach` stores, at each pass, what the bound needs, unless
the pass's own sums already fail the test: coverage_holds called with
x0 = x and reach = D (every bound term is 0 at zero displacement, and D_k = 0
marks the rows no particle sees) asks whether r < 1/2 on every moving row;
where not, the bound of any later step is r+ >= r and fails as well, so
nothing is kept and the next step makes a pass.
"""
import numpy as np
from numba import njit

from .weights import locate_axis_point


@njit(cache=True, error_model="numpy")
def coverage_reach(x, m, b0, u0, ih0, C0, b1, u1, ih1, C1, b2, u2, ih2, C2, p, nbx, nby, delta,
                   out):
    """out_k = W_k: the mass of the particles whose box x_p +- ``delta`` (per
    axis) meets the support of dof k (cells k_d - p .. k_d per axis d, the
    spline numbering of :func:`skfem_mpm.kernels.mpm.particle_coverage`),
    so that every particle within ``delta`` of that support in any norm is
    counted. The axes as particle_coverage takes them (C_d not read)."""
    out[:] = 0.0
    n = x.shape[0]
    dim = x.shape[1]
    for i in range(n):
        a0 = locate_axis_point(x[i, 0] - delta, b0, u0, ih0)
        a1 = locate_axis_point(x[i, 0] + delta, b0, u0, ih0) + p
        c0, c1, e0, e1 = 0, 0, 0, 0
        if dim >= 2:
            c0 = locate_axis_point(x[i, 1] - delta, b1, u1, ih1)
            c1 = locate_axis_point(x[i, 1] + delta, b1, u1, ih1) + p
        if dim >= 3:
            e0 = locate_axis_point(x[i, 2] - delta, b2, u2, ih2)
            e1 = locate_axis_point(x[i, 2] + delta, b2, u2, ih2) + p
        mi = m[i]
        for e in range(e0, e1 + 1):
            for c in range(c0, c1 + 1):
                row = (e * nby + c) * nbx
                for a in range(a0, a1 + 1):
                    out[row + a] += mi


@njit(cache=True, inline="always", error_model="numpy")
def _variation(lipschitz, spread, d):
    """min(L d, R): how far a function with Lipschitz constant L and range
    R can move over a displacement d (0 for d = 0, also for L = inf)."""
    if d <= 0.0:
        return 0.0
    return min(lipschitz * d, spread)


@njit(cache=True, inline="always", error_model="numpy")
def _smooth(s):
    s = min(max(s, 0.0), 1.0)
    return s * s * (3.0 - 2.0 * s)


@njit(cache=True, error_model="numpy")
def coverage_holds(x, m, x0, m0, coverage, reach, bound, weights, mass_ratios, moving, lo, hi,
                   tail, floor, limit):
    """True when the guard's sums ``coverage`` (K, D, m of the pass at the
    positions ``x0`` with masses ``m0``; ``reach`` its W_k of
    :func:`coverage_reach` with delta = bound[0]) give, on the particles now
    at ``x`` with masses ``m``, the same lumping fractions as a new pass: no
    dof that particles can reach is lumped by either. ``bound`` = (delta,
    L_N, L_D, L_K, R_N, R_D, R_K) of
    :func:`skfem_mpm.solve.timestep.coverage_bound`, ``limit`` the guard's
    limit now, the rest the guard's arguments
    (:func:`skfem_mpm.kernels.mpm.covered_stiffness`). False (a pass is
    needed) when the particles differ in count or mass.

    Bound. Let d = max_p |x_p - x0_p| <= delta. A particle changes its term
    of K_k by at most min(L_K d, R_K) m_p, L_K a Lipschitz constant and R_K
    the range of |grad N_k|^2, and only if x0_p lies within d of the support
    of N_k (outside it the function is 0); so

        |K_k - K0_k| <= dK = min(L_K d, R_K) W_k,

    the same for D (N^2: L_D, R_D) and m (N: L_N, R_N). With tau = D / (m mu)
    in [tau-, tau+] = [(D0 - dD) / ((m0 + dm) mu), (D0 + dD) / ((m0 - dm) mu)]
    (tau+ = inf when m0 <= dm), s = smoothstep over (lo, hi) of tau lies in
    [s-, s+] (smoothstep is monotone), c = t + (w - t) s is at most
    max(c(s-), c(s+)) (linear in s) and (1 - s) at most 1 - s-; the guard's
    ratio of a moving dof, r = (K / D) c / limit + (1 - s) (1 - t) F / limit,
    is then at most

        r+ = (K0 + dK) / (D0 - dD) max(c(s-), c(s+)) / limit
             + (1 - s-) (1 - t) F / limit      (D0 - dD > 0).

    If r+ < 1/2 (less a relative 1e-9 for the rounding of either pass) on
    every moving dof with W_k > 0, the tail-weighted theta_j are 0 there, so
    the cut-cell withdrawal (b_k) is 0 and every guarded stiffness is T_k:
    theta_k = 0 from the kept sums and from new ones. A moving dof with
    W_k = 0 has D_k = 0 before and after (no particle can reach its
    support): k_k = inf and its own theta_j = 0 in both (lumped fully where
    it has mass, the same in both). Dofs that never move have k_k = 0 and
    theta_j = 0 in both. Hence the kept sums give the guard's lumping
    fractions of new sums bit for bit (the step's grid mass selects the
    same rows in both), and the pass can be skipped; elsewhere (d > delta,
    D0 - dD <= 0, r+ >= 1/2) it is redone.
    The Lipschitz constants and ranges: see
    :func:`skfem_mpm.solve.timestep.coverage_bound`."""
    n = x.shape[0]
    dim = x.shape[1]
    if x0.shape[0] != n or x0.shape[1] != dim or m0.shape[0] != n:
        return False
    delta = bound[0]
    d2 = 0.0
    for i in range(n):
        if m[i] != m0[i]:
            return False
        s = 0.0
        for c in range(dim):
            e = x[i, c] - x0[i, c]
            s += e * e
        d2 = max(d2, s)
    d = np.sqrt(d2)
    if not d <= delta:
        return False
    vn = _variation(bound[1], bound[4], d)
    vd = _variation(bound[2], bound[5], d)
    vk = _variation(bound[3], bound[6], d)
    K, D, M = coverage[0], coverage[1], coverage[2]
    top = 0.5 * (1.0 - 1e-9) * limit
    addend = (1.0 - tail) * floor
    for k in range(K.shape[0]):
        if moving[k] == 0.0:
            continue
        wide = reach[k]
        if wide == 0.0:  # D_k = 0 before and after: k_k = inf in both
            continue
        dlo = D[k] - vd * wide
        if not dlo > 0.0:
            return False
        mlo = M[k] - vn * wide
        tau_lo = dlo / ((M[k] + vn * wide) * mass_ratios[k])
        tau_hi = (D[k] + vd * wide) / (mlo * mass_ratios[k]) if mlo > 0.0 else np.inf
        s_lo = _smooth((tau_lo - lo) / (hi - lo))
        s_hi = _smooth((tau_hi - lo) / (hi - lo))
        w = weights[k]
        c = max(tail + (w - tail) * s_lo, tail + (w - tail) * s_hi)
        r = (K[k] + vk * wide) / dlo * c + (1.0 - s_lo) * addend
        if not r < top:
            return False
    return True
