"""The critical time step of explicit time integration on a grid.

The central-difference (and symplectic Euler) scheme is stable for
dt <= 2 / omega_max, omega_max^2 the largest eigenvalue of M^-1 K
(Belytschko, Liu & Moran, "Nonlinear Finite Elements", 2000, Sec. 6.3).
On a tensor grid with wave speed c (P-wave) and cell sizes h_d,

    omega_max^2 <= c^2 sum_d Lambda(p, mass) / h_d^2,
    dt_crit = 2 / (c sqrt(sum_d Lambda(p, mass) / h_d^2)),

where Lambda(p, mass) is the largest eigenvalue of the 1D problem
K v = Lambda M v (K = int N' N', M = int N N or its row sums) for B-splines
of degree p on unit cells with open knot vectors. It includes the boundary
"outlier" frequencies of open knot vectors (Cottrell, Reali, Bazilevs,
Hughes 2006, CMAME 195:5257-5296), which exceed the interior ones for p >= 2.
Lambda is computed here, once per (p, mass), with Gauss quadrature on a
64-cell grid (values: p=1 lumped 4, consistent 12; see ``spectral_radius``).
For a grid with non-uniform cells h_d is the smallest cell of axis d.

Reconstruction. The internal force of a reconstructed method is
-G_gauss^T W R(sigma_p): the fit R of the particle stresses is not the
Gauss-point stress of the grid field, and the operator is not symmetric,
so its top frequency may differ from the Gauss one. A 2D reconstructed
method therefore multiplies dt_crit by the factor of
:func:`reconstruction_factor`: min(1, sqrt(lambda_G / lambda_R)) from a
few power iterations on the reconstructed and on the Gauss scalar wave
operator of the current particles (:class:`ReconstructedOperator`). It
replaces a fixed factor 0.6 measured on one problem; measured exactly (all
eigenvalues, 8 x 8 cells, D1): tls R/G = 1.000 (3 and 2 particles per
axis: the fit reproduces the linear gradients), spline 0.993 (3 per axis)
and 1.022 (2 per axis). In 1D no factor applies. The reconstruction in the
power iterations is the compiled one wherever the compiled executor runs
it (:func:`compiled_twin`), on either executor.
"""
from functools import lru_cache

import numpy as np
from scipy.linalg import eigh
from skfem import BilinearForm, asm
from skfem.helpers import dot, grad

from ..kernels.step_size import critical_step
from .compiled_reconstruct import CompiledReconstruction, unsupported

__all__ = ["spectral_radius", "interior_rayleigh_quotient", "critical_time_step", "STABILITY_LIMIT",
           "stable_time_step", "stiffness_root",
           "fast_dof_limit", "full_grid_quotients", "full_grid_mass_ratios", "fast_dof_weights",
           "covered_stiffness", "near_maximum", "tail_weight", "covered_parameters", "lumping_fraction",
           "COVERAGE_REACH", "coverage_bound",
           "ReconstructedOperator", "power_iteration", "compiled_twin", "reconstruction_factor"]


@BilinearForm
def _stiffness(u, v, _):
    return dot(grad(u), grad(v))


@BilinearForm
def _mass(u, v, _):
    return u * v


@lru_cache(maxsize=None)
def spectral_radius(degree, mass):
    """Lambda(p, mass): the largest eigenvalue of K v = Lambda M v for the 1D
    unit-cell B-spline space of degree p ('lumped' or 'consistent' mass)."""
    from ..spline import SplineGrid

    grid = SplineGrid.line(0.0, 64.0, 64, degree)
    basis = grid.basis()
    K = asm(_stiffness, basis).toarray()
    M = asm(_mass, basis).toarray()
    if mass == "lumped":
        M = np.diag(M.sum(axis=1))
    return float(eigh(K, M, eigvals_only=True)[-1])


@lru_cache(maxsize=None)
def interior_rayleigh_quotient(degree):
    """q(p) = K_ii / M_ii of an interior dof on unit cells (consistent mass)."""
    from ..spline import SplineGrid

    grid = SplineGrid.line(0.0, 64.0, 64, degree)
    basis = grid.basis()
    i = grid.ndofs // 2
    return float(asm(_stiffness, basis)[i, i] / asm(_mass, basis)[i, i])


STABILITY_LIMIT = {"rk4": 2.0 * np.sqrt(2.0)}
"""Largest stable omega dt of a scheme on undamped oscillations where it is
not 2 (central difference, symplectic Euler): classical RK4's stability
region meets the imaginary axis at +-2 sqrt(2) (Hairer & Wanner, "Solving
ODEs II", Sec. IV.2)."""


def fast_dof_limit(degree, scheme="cd"):
    """s^2 q(p) / Lambda(p, consistent), s = 2 (s the scheme's
    STABILITY_LIMIT): a dof whose own Rayleigh quotient satisfies
    dt^2 K_ii / M_ii above this would, amplified by its coupling as an
    interior dof is, exceed the stability limit omega dt = s of the time
    step chosen from Lambda (see :mod:`skfem_mpm.solve.grid_system`)."""
    s = STABILITY_LIMIT.get(scheme, 2.0)
    return s * s * interior_rayleigh_quotient(degree) / spectral_radius(degree, "consistent")


def _axis_matrices(grid):
    """The 1D Gauss stiffness and mass matrices of each axis' breakpoints."""
    from ..spline import SplineGrid

    out = []
    for breaks in grid.breakpoints:
        basis = SplineGrid(breaks, grid.degree).basis()
        out.append((asm(_stiffness, basis), asm(_mass, basis)))
    return out


def _tensor(per_axis, combine):
    total = per_axis[0]
    for a in per_axis[1:]:
        total = combine(a[:, None], total[None, :]).ravel()
    return total


def full_grid_quotients(grid):
    """Q_i = K_ii / M_ii of dof i on the fully covered grid with Gauss
    quadrature (K = int grad N grad N, M = int N N). On a tensor grid
    M_ii = prod_d m_d and K_ii = sum_d k_d prod_(e != d) m_e, so
    Q_i = sum_d k_d(i_d) / m_d(i_d) with the 1D matrices of each axis'
    breakpoints; shape (ndofs,), x fastest."""
    return _tensor([K.diagonal() / M.diagonal() for K, M in _axis_matrices(grid)], np.add)


def full_grid_mass_ratios(grid):
    """mu_i = int N_i^2 / int N_i on the fully covered grid (the consistent
    diagonal over the lumped mass at uniform density), a product over axes."""
    return _tensor([M.diagonal() / np.asarray(M.sum(axis=1)).ravel()
                    for _, M in _axis_matrices(grid)], np.multiply)


def fast_dof_weights(grid):
    """(w, mu): w_i = min(1, q(p) sum_d h_d^-2 / Q_i) with Q_i from
    :func:`full_grid_quotients` and h_d the smallest cell of axis d, and mu
    from :func:`full_grid_mass_ratios`. See :func:`covered_stiffness`."""
    h = np.asarray(grid.h, dtype=np.float64)
    reference = interior_rayleigh_quotient(grid.degree) * np.sum(1.0 / h ** 2)
    return np.minimum(1.0, reference / full_grid_quotients(grid)), full_grid_mass_ratios(grid)


COVERED = (0.8, 0.95)


@lru_cache(maxsize=None)
def tail_weight(degree):
    """t(p) = q(p) / Q_1(p): the weight of :func:`fast_dof_weights` of the
    first function of an open knot vector (Q_1 its full-grid K_ii / M_ii on
    unit cells; 1 / 3.7 for p = 2, 1 / 9.1 for p = 3). A function the body
    covers over the last j cells of its support only (the body ends at a
    knot) is there the restriction of a uniform B-spline, and the
    restricted space is the open-knot space of the body's cells, whose top
    frequency Lambda(p) already bounds the step: over one cell the function
    is (s^p / p!), the open knot vector's first function up to scale, so
    its quotient is Q_1 and it is no faster than that function. A body
    ending a fraction l of a cell into the support gives a quotient
    ~ Q_1 / l^2 and a top frequency ~ Lambda / l^2 (the cut cell's outlier),
    so with this weight the guard's ratio r ~ cfl^2 / l^2 lumps that dof
    fully where the cut cell would break the step (l <= cfl)."""
    from ..spline import SplineGrid

    grid = SplineGrid.line(0.0, 64.0, 64, degree)
    return float(interior_rayleigh_quotient(degree) / full_grid_quotients(grid)[0])


def covered_parameters(grid, reconstruction):
    """(lo, hi, t, F): COVERED, :func:`tail_weight` of the grid's degree and
    F = q(p) (sum_d h_d^-2 - min_d h_d^-2) (h_d the smallest cell of axis
    d), the scalars of :func:`covered_stiffness` (and of its compiled twin,
    :func:`skfem_mpm.kernels.mpm.covered_stiffness`), for a method with a
    ``reconstruction``; (lo, hi, 1, 0), the plain limit on tails, without
    one (``"none"``).

    The tail weight rests on the step's system being integrated by Gauss
    quadrature (a reconstruction's density at its Gauss points): a body
    ending at a knot then restricts the space to an open-knot space, whose
    top frequency Lambda(p) the step is built on (:func:`tail_weight`).
    With particle quadrature (no reconstruction) the particles over-sample
    the steep end of that space's first function, and its mode is faster
    than Lambda by itself: omega dt_crit / 2 (the step at cfl 1) of the
    particle system 1.64 for p = 3 at 2 particles per cell (1.19 at 3, 1.09
    at 4; p = 2: 1.15 at 2, 1.06 at 3), the same for a body ending at an
    interior knot and for a grid's open end. MUSL at cfl 0.5 then runs that
    mode at omega dt = 1.64 of the limit 2, and a body cutting its end cell
    (l < 1) raises it as 1 / l: it breaks the step from l = 0.82, where the
    tail-weighted ratio, 1.29 cfl^2 / l^2 (the particles' own sums), is
    still below the 1/2 where lumping starts (a column whose top moves
    through cells, cubic, consistent MUSL: J <= 0 at step 138, with
    omega dt of the unlumped rows above 2 for the five steps before).
    The plain limit lumps such a tail fully at l = 1 (r = 2.9), as it
    lumps the open-knot end function wherever its particles' coverage
    ratio reads as a tail (tau_i below COVERED: at 2 particles per cell
    for p = 3); a Wall's rows among them: its contact force m_i d_n / dt
    (lumped mass) changes the row's normal velocity by m_i (M^-1)_ii d_n,
    d_n on a lumped row but 10.1 d_n on the first row of a cubic
    consistent mass at 2 particles per cell (3.3 for p = 2), and an
    overshoot above 2 d_n grows (a cubic bar against a wall, consistent
    MUSL: J <= 0 at step 5 with that row unlumped; the tail weight left it
    so)."""
    inv = 1.0 / np.asarray(grid.h, dtype=np.float64) ** 2
    if reconstruction == "none":
        return (COVERED[0], COVERED[1], 1.0, 0.0)
    floor = interior_rayleigh_quotient(grid.degree) * float(np.sum(inv) - np.min(inv))
    return (COVERED[0], COVERED[1], tail_weight(grid.degree), floor)


COVERAGE_REACH = 0.125
"""delta / h_min of :func:`coverage_bound`: how far the particles may move
from the guard's last coverage pass before it is redone anyway."""


def coverage_bound(grid):
    """(delta, L_N, L_D, L_K, R_N, R_D, R_K): the displacement up to which
    the guard's coverage pass may be skipped (``COVERAGE_REACH`` times the
    smallest cell of the grid) and the Lipschitz constants L and ranges R
    (largest minus smallest value) of N_k, N_k^2 and |grad N_k|^2 over the
    grid's B-splines, in the Euclidean norm; the bound of
    :func:`skfem_mpm.kernels.coverage_skip.coverage_holds`.

    Derivation. N_k = prod_d B_d(x_d), B_d a B-spline of degree p on axis
    d's knots, 0 <= B_d <= 1. From B'_(i,p) = p B_(i,p-1) / (t_(i+p) - t_i)
    - p B_(i+1,p-1) / (t_(i+p+1) - t_(i+1)) (the derivative of a B-spline:
    de Boor, "A Practical Guide to Splines", 2001), a difference of two non-negative terms, each
    at most p / h_d (a non-empty knot span holds a cell, h_d the smallest
    cell of axis d; an empty one's term is absent), |B'| <= A1_d = p / h_d;
    applying it once more, |B''| <= A2_d = 2 p (p - 1) / h_d^2 inside a
    cell. Then |grad N|^2 = sum_d B_d'^2 prod_(e != d) B_e^2 <= G =
    sum_d A1_d^2, and

        L_N = sqrt(G),  L_D = 2 sqrt(G)  (|grad N^2| = 2 N |grad N|),
        d/dx_c |grad N|^2 = 2 B_c' B_c'' prod_(e != c) B_e^2
            + sum_(d != c) 2 B_d'^2 B_c B_c' prod_(e != c, d) B_e^2,
        L_K = sqrt(sum_c (2 A1_c A2_c + 2 A1_c sum_(d != c) A1_d^2)^2),

    R_N = R_D = 1, R_K = G. These are Lipschitz constants across the
    cells too where the function is continuous: N and N^2 for p >= 1,
    |grad N|^2 for p >= 2 (B' continuous); for p = 1 L_K = inf (|grad N|^2
    jumps at the knots; its variation is then bounded by R_K only)."""
    p = int(grid.degree)
    h = np.array([float(np.min(np.diff(np.asarray(b, dtype=np.float64))))
                  for b in grid.breakpoints])
    a1 = p / h
    a2 = 2.0 * p * (p - 1) / h ** 2
    g = float(np.sum(a1 ** 2))
    if p >= 2:
        per_axis = 2.0 * a1 * a2 + 2.0 * a1 * (g - a1 ** 2)
        lk = float(np.sqrt(np.sum(per_axis ** 2)))
    else:
        lk = np.inf
    return np.array([COVERAGE_REACH * float(h.min()), np.sqrt(g), 2.0 * np.sqrt(g), lk,
                     1.0, 1.0, g])


def covered_stiffness(stiffness, diagonal, lumped, weights, mass_ratios, moving, tail, floor,
                      limit, degree, shape):
    """The fast-dof guard's stiffness k_i = (K_i c_i + a_i) moving_i, which
    it compares with its limit times M_ii (theta_i = :func:`lumping_fraction`
    of k_i / (limit M_ii)); the NumPy twin of
    :func:`skfem_mpm.kernels.mpm.covered_stiffness` (same operations). Per
    dof: K_i = sum m |grad N_i|^2, M_ii = sum m N_i^2 (``diagonal``) and
    m_i = sum m N_i (``lumped``) over the particles (see "Coverage"), w_i
    and mu_i of :func:`fast_dof_weights` (``weights``, ``mass_ratios``),
    ``moving`` 1 on dofs not constrained in every component (0: they never
    move, k_i = 0; lumping their rows only moved mass onto their free
    neighbours);

        c_i = t + (w_i - t) s_i,   a_i = (1 - s_i) (1 - t) F M_ii,
        s_i = smoothstep over COVERED of tau_i = M_ii / (m_i mu_i),

    t = :func:`tail_weight` (``tail``), F of :func:`covered_parameters`
    (``floor``; t = 1 and F = 0, the plain limit, without a
    reconstruction: see there); a moving dof that no particle sees (M_ii = 0) gets
    k_i = inf: it is lumped fully. Near a cut cell the tail weight is
    withdrawn (see "Cut cells"):

        k_i = T_i + b_i (P_i - T_i),   b_i = max_(|j - i| <= p) theta_j,
        theta_j = smoothstep(2 T_j / (``limit`` M_jj) - 1),

    T_i the stiffness above, P_i = K_i (1 + (w_i - 1) s_i) moving_i the
    plain limit's (weight 1 on tails, no addend), j over the dofs within
    ``degree`` indices of i per axis (``shape``: the dofs per axis, x
    fastest; :func:`near_maximum`) that particles see (theta_j = 0 where
    M_jj = 0): theta_j is the fraction the tail-weighted rule lumps dof j
    by (:func:`lumping_fraction`).

    Weights. The guard compares a dof's Rayleigh quotient with a limit
    built on an interior dof of the smallest cells. The first functions of
    an open knot vector have a higher quotient on a fully covered grid
    (2.2 and 3.7 q(p) for p = 2, 4.9 and 9.1 for p = 3) without being
    faster than the time step allows (Lambda includes those outlier modes),
    so a filled grid tripped the guard there at cfl 0.5 and lost accuracy.
    Such a dof gets the limit times 1 / w_i while it is covered: tau_i,
    the particles' consistent diagonal over their lumped mass relative to
    the full-grid value, is about 1 when particles cover the function
    (0.98-0.99 for the second function at 2-4 particles per cell) and drops
    when they see only its tail (0.16-0.45 measured). A tail is weighed as
    the open knot vector's first function (:func:`tail_weight`): a body
    ending at a knot (S3's free end) leaves a tail whose quotient is that
    function's and which is no faster than the step allows (with weight 1
    there the guard lumped S3's end dof, r = 2.25 at cubic, rk4, cfl 0.5,
    and cost up to 400x in accuracy); a body ending a fraction l into the
    support gives r ~ cfl^2 / l^2 and is lumped where the cut cell would
    break the step (l <= cfl) by itself. In 2D and 3D a dof is usually a tail along
    one axis only; t weighs its whole quotient, the covered axes' share
    too, so the addend puts back an interior quotient for every axis but
    one: (1 - t) F, F = q sum_(d != e) h_d^-2.

    Coverage. K_i, M_ii and m_i are the particles' own sums with a
    reconstruction too (:func:`skfem_mpm.solve.steps.particle_coverage`),
    not those of the reconstructed density at the Gauss points: the Gauss
    rule spans the body's extent, so its sums cannot tell a bar that fills
    its end cell (S3: the end function is a covered tail, not fast) from a
    free surface that cuts its top cell (S2 large: the top dofs are fast;
    with the Gauss sums the tail weight left them unlumped and a particle
    left the grid at step 1034). A dof that has mass but that no particle
    sees (the Gauss rule of a 1D body reaches the sliver of a cell beyond
    its last particle) is the limit l -> 0 of a tail, r -> inf. The
    compiled executor and loop keep the sums of their last pass while
    :func:`skfem_mpm.kernels.coverage_skip.coverage_holds` shows that new
    ones would give the same lumping (no reachable row can reach the
    threshold: the bound of :func:`coverage_bound`); this reference always
    sums anew.

    Cut cells. The tail weight holds where the body ends at a knot (the
    restricted space is an open-knot space). A body whose surface cuts a
    cell (l < 1) has a cut-cell mode on all the p + 1 functions of that
    cell, not on the sliver function alone: with the weight the guard
    lumped the slivers only and the step's top frequency rose towards the
    stability limit (omega dt of M^-1 K with the rows lumped as the guard
    lumps them, MUSL at cfl 0.5, measured when the tail weight applied
    without a reconstruction too: colliding disks at 20 x 20, t = 0.15,
    1.62 against 0.70 with the plain limit; colliding spheres at 8^3,
    t = 0.3, 1.92 against 0.54; with no guard 41 and unstable, J <= 0 at
    steps 11 and 5), and it left rows unlumped that break the Kronecker
    preconditioner's tensor structure (CG iterations a solve 18 against 12
    on the disks, 71 against 24 on the spheres). A dof the tail-weighted
    rule lumps (theta_j > 0) marks a cut cell: the dofs within p indices
    of it take the plain limit by the fraction theta_j (continuous in the
    particles' positions, as the lumping is). On the disks the guard then
    lumps the rows the plain limit lumps (at t = 0 and 0.3 with the same
    fractions, at the contact, t = 0.15, 52 of them fully against 64;
    omega dt 0.75 against 0.70), and where no dof is lumped (a body that
    fills its cells: S3 small, D2 small) the tail weight stands. A steeper
    withdrawal (fully from r_j = 2/3) matched the plain limit's rows on the
    contact scenes exactly but changed the lumping faster as the falling
    block (p = 2, consistent MUSL, tests/hard/test_free_surface) moved
    through cells: its energy rose 1.5e-2 of the work above budget (limit
    1e-2; with theta_j 8.8e-3, the plain limit 6.9e-3). Those scenes have
    no reconstruction and now take the plain limit (t = 1: the withdrawal
    changes nothing there, P_i = T_i)."""
    tau = diagonal / (np.maximum(lumped, 1e-300) * mass_ratios)
    lo, hi = COVERED
    s = np.clip((tau - lo) / (hi - lo), 0.0, 1.0)
    smooth = s * s * (3.0 - 2.0 * s)
    c = tail + (weights - tail) * smooth
    a = (1.0 - smooth) * (1.0 - tail) * floor * diagonal
    seen = stiffness * (c * moving) + a * moving
    seen = np.where(diagonal > 0.0, seen, np.where(moving > 0.0, np.inf, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.clip(2.0 * (seen / (limit * diagonal)) - 1.0, 0.0, 1.0)
    x = np.where(diagonal > 0.0, r * r * (3.0 - 2.0 * r), 0.0)
    b = near_maximum(x, degree, shape)
    plain = stiffness * ((1.0 + (weights - 1.0) * smooth) * moving)
    with np.errstate(invalid="ignore"):
        return np.where((diagonal > 0.0) & (b > 0.0), seen + b * (plain - seen), seen)


def near_maximum(x, radius, shape):
    """The largest x_j over the dofs j within ``radius`` indices of each dof
    per axis (``shape``: the dofs per axis, x fastest): a box maximum."""
    out = np.asarray(x, dtype=np.float64).reshape(tuple(shape)[::-1])
    for axis in range(out.ndim):
        n = out.shape[axis]
        padded = np.moveaxis(out, axis, 0)
        m = padded.copy()
        for o in range(1, radius + 1):
            m[o:] = np.maximum(m[o:], padded[:n - o])
            m[:n - o] = np.maximum(m[:n - o], padded[o:])
        out = np.moveaxis(m, 0, axis)
    return out.ravel()


def lumping_fraction(ratio):
    """theta = smoothstep(2 ratio - 1): 0 for ratio <= 1/2, 1 for ratio >= 1."""
    s = np.clip(2.0 * np.asarray(ratio, dtype=np.float64) - 1.0, 0.0, 1.0)
    return s * s * (3.0 - 2.0 * s)


def critical_time_step(grid, wave_speed, mass="lumped", scheme="cd"):
    """dt_crit = s / (c sqrt(sum_d Lambda(p, mass) / h_d^2)) for the grid,
    s = 2 (or the scheme's STABILITY_LIMIT). A reconstructed 2D method
    multiplies it by :func:`reconstruction_factor` (see the module
    docstring).

    ``mass="hybrid"`` (lumped acceleration, consistent velocity
    re-projection) takes the lumped Lambda: the step's frequencies are
    those of M_L^-1 K; the re-projection is an L2 projection of the
    particle velocities and adds none. Measured (S1, quadratic, 32 cells,
    2 particles per cell, velocities with 1e-3 noise, 2000 MUSL steps):
    hybrid stable up to 1.8 dt_crit(lumped), J <= 0 at 2.0 (lumped: 2.5
    and 3.0; consistent fails at 0.9 dt_crit(lumped))."""
    return float(critical_step(STABILITY_LIMIT.get(scheme, 2.0), float(wave_speed),
                               stiffness_root(grid, mass)))


def stiffness_root(grid, mass="lumped"):
    """sqrt(sum_d Lambda(p, mass) / h_d^2), the grid's factor in
    :func:`critical_time_step` (``mass="hybrid"``: the lumped Lambda)."""
    lam = spectral_radius(grid.degree, "lumped" if mass == "hybrid" else mass)
    h = np.asarray(grid.h, dtype=np.float64)
    return float(np.sqrt(np.sum(lam / h ** 2)))


def stable_time_step(method, dt_crit, what=""):
    """The step a method asks for, ``method.dt`` or ``cfl * dt_crit``;
    ValueError when it exceeds dt_crit (dt > dt_crit or cfl > 1) unless
    ``method.allow_unstable``. ``what`` describes dt_crit in the message."""
    if method.dt is not None:
        if method.dt > dt_crit and not method.allow_unstable:
            raise ValueError(
                f"dt = {method.dt:.6g} exceeds the critical time step dt_crit = "
                f"{dt_crit:.6g}{what}; use a smaller dt, dt=None (cfl * dt_crit) or "
                f"allow_unstable=True")
        return method.dt
    if method.cfl > 1.0 and not method.allow_unstable:
        raise ValueError(f"cfl = {method.cfl:.6g} puts the time step above the critical time "
                         f"step dt_crit = {dt_crit:.6g}{what} (cfl <= 1 is stable); use "
                         f"cfl <= 1 or allow_unstable=True")
    return method.cfl * dt_crit


class ReconstructedOperator:
    """The scalar wave operator of a reconstructed method on the current
    particles: for a grid field v (ndofs,),

        K v = sum_g w_g grad N(x_g) . R(rho_p grad v(x_p))_g,
        M_L = diag(sum_g w_g R(rho_p)_g N_i(x_g)),

    R the method's reconstruction onto the Gauss points g of the step's
    integration rule (weights w_g), so that c^2 M_L^-1 K is the stiffness
    of one displacement component with P-wave speed c (the scalar model of
    :func:`critical_time_step`, where the same operator with Gauss
    quadrature of the grid field itself has the top eigenvalue
    sum_d Lambda(p, lumped) / h_d^2). K is not symmetric: the
    reconstruction R is applied to particle gradients, not to the Gauss
    points' own."""

    def __init__(self, grid, particles, reconstruct, options):
        from ..quadrature import transfer_matrices
        from ..reconstruct import integration_rule

        self.grid, self.particles = grid, particles
        self.reconstruct, self.options = reconstruct, dict(options)
        self.rule = integration_rule(grid, particles, grid.degree + 2)
        Ng, self.Gg = transfer_matrices(grid, self.rule.x)
        _, self.Gp = transfer_matrices(grid, particles.x)
        self.rho = particles.m / particles.V
        rho_g = reconstruct(grid, particles, self.rho[:, None], self.rule, **self.options)[:, 0]
        self.lumped = Ng.T @ (self.rule.w * rho_g)
        self.active = self.lumped > 1e-12 * np.abs(self.lumped).max()
        self.gauss_weights = self.rule.w * rho_g

    def gauss_stiffness(self, v):
        """K_G v = sum_g w_g rho_g grad N(x_g) (grad N(x_g) . v): the same
        operator with the grid field's own gradient at the Gauss points."""
        return sum(G.T @ (self.gauss_weights * (G @ v)) for G in self.Gg)

    def apply_gauss(self, v):
        """M_L^-1 K_G v on the dofs with mass."""
        out = np.zeros_like(v)
        out[self.active] = self.gauss_stiffness(v)[self.active] / self.lumped[self.active]
        return out

    def stiffness(self, v):
        """K v (see the class docstring)."""
        g = np.column_stack([G @ v for G in self.Gp]) * self.rho[:, None]
        r = self.reconstruct(self.grid, self.particles, g, self.rule, **self.options)
        return sum(self.Gg[d].T @ (self.rule.w * r[:, d]) for d in range(self.grid.dim))

    def apply(self, v):
        """M_L^-1 K v on the dofs with mass (0 elsewhere)."""
        out = np.zeros_like(v)
        out[self.active] = self.stiffness(v)[self.active] / self.lumped[self.active]
        return out

    def start_vector(self):
        """The deterministic start: the checkerboard (-1)^(i_1 + .. + i_d) of
        the dof indices (the shape of the top grid mode)."""
        idx = np.indices(self.grid.basis_per_axis[::-1]).reshape(self.grid.dim, -1)
        v = np.where(idx.sum(axis=0) % 2 == 0, 1.0, -1.0)
        return np.where(self.active, v, 0.0)


def power_iteration(apply, weights, vector, iterations):
    """|lambda_max| of an operator by the power method: w = apply(v),
    lambda_k = ||w||_W / ||v||_W, v <- w / ||w||_W (W = diag(weights)),
    ``iterations`` times from ``vector``; returns (lambda_k, v). The ratio
    converges to the largest eigenvalue magnitude (Golub & Van Loan,
    "Matrix Computations", 4th ed., Sec. 7.3.1); every operation is
    deterministic, so the estimate is reproducible bit for bit."""
    def norm(a):
        return float(np.sqrt(np.sum(weights * a * a)))

    v = vector / norm(vector)
    lam = 0.0
    for _ in range(int(iterations)):
        w = apply(v)
        lam = norm(w)
        if lam == 0.0:
            return 0.0, v
        v = w / lam
    return lam, v


RECONSTRUCTION_ITERATIONS = 20
"""Power iterations of the first estimate of a run (later ones, in
adaptive runs, RECONSTRUCTION_ITERATIONS_NEXT from the previous vector)."""
RECONSTRUCTION_ITERATIONS_NEXT = 3
RECONSTRUCTION_EVERY = 25
"""Adaptive runs (finite strain) re-estimate the factor every this many
steps, RECONSTRUCTION_ITERATIONS_NEXT iterations from the previous vectors.
Measured on D1 at 16 x 16 cells, 3 particles per axis, load average 12 on
2 cores, with the compiled reconstructions (NumPy ones in brackets): first
estimate 0.11-0.13 s (0.48-0.49) tls, 0.13-0.18 s (1.0-1.3) spline,
0.8-1.1 s (9.1-9.7) mls; each later one 0.03-0.04 s (0.09-0.12) tls,
0.04-0.05 s (0.31-0.35) spline, 0.16-0.26 s (1.3-1.6) mls."""


def compiled_twin(grid, reconstruct, options):
    """The compiled twin of a built-in reconstruction function (of
    :data:`skfem_mpm.reconstruct.RECONSTRUCTORS`) with these options on this
    grid (:meth:`CompiledReconstruction.reconstructor`), or None where the
    compiled executor does not run it (:func:`unsupported`) or
    ``reconstruct`` is a user's callable."""
    from types import SimpleNamespace

    from ..reconstruct import RECONSTRUCTORS

    names = [n for n, f in RECONSTRUCTORS.items() if f is reconstruct]
    if not names or grid.dim == 1:
        return None
    method = SimpleNamespace(reconstruction=names[0], reconstruction_options=dict(options))
    if unsupported(method, grid.dim) is not None:
        return None
    return CompiledReconstruction.reconstructor(grid, names[0], dict(options))


def reconstruction_factor(grid, particles, reconstruct, options, vectors=None, iterations=None,
                          compiled=True):
    """(f, vectors): the factor f <= 1 on the Gauss critical step of a
    reconstructed method, and the two power-iteration vectors (kept for the
    next estimate).

        f = min(1, sqrt(lambda_G / lambda_R)),
        lambda_R ~ |lambda_max(M_L^-1 K)|,  lambda_G ~ lambda_max(M_L^-1 K_G)

    (:class:`ReconstructedOperator`: the reconstructed scalar wave operator
    and the same with Gauss quadrature of the grid field, on the same
    particles, cells and lumped reconstructed mass), each by
    :func:`power_iteration`. The ratio lambda_R / lambda_G multiplies the
    method's own dt_crit (lumped or consistent Lambda): it assumes the
    reconstruction raises the top frequency of either mass in the same
    proportion. Where the reconstructed operator is no stiffer than Gauss
    quadrature f = 1: the Gauss step applies unchanged. Both estimates start
    from the same vector and take the same number of iterations, so their
    approach from below (20 iterations: 0.96-0.98 of the exact value on D1
    at 8 x 8 cells, 3 particles per axis) largely cancels in the ratio.

    ``compiled``: a built-in reconstruction that the compiled executor runs
    is applied by its compiled twin (:func:`compiled_twin`; the 2D spline
    factorises its matrix once per estimate), on either executor, so both
    take the same step; the NumPy reconstruction (``compiled=False``) gives
    the same estimate to rounding (test_reconstruction_timestep)."""
    twin = compiled_twin(grid, reconstruct, options) if compiled else None
    if twin is not None:
        reconstruct, options = twin, {}
    op = ReconstructedOperator(grid, particles, reconstruct, options)
    if vectors is None or vectors[0].shape != op.lumped.shape:
        start = op.start_vector()
        vectors, iterations = (start, start), iterations or RECONSTRUCTION_ITERATIONS
    n = iterations or RECONSTRUCTION_ITERATIONS_NEXT
    lam_r, v_r = power_iteration(op.apply, op.lumped, np.where(op.active, vectors[0], 0.0), n)
    lam_g, v_g = power_iteration(op.apply_gauss, op.lumped, np.where(op.active, vectors[1], 0.0),
                                 n)
    return (1.0 if lam_r <= lam_g else float(np.sqrt(lam_g / lam_r))), (v_r, v_g)
