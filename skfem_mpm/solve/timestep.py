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

Reconstruction in 2D. The internal force of a reconstructed method is
-G_gauss^T W R(sigma_p): the least-squares fit R of the particle stresses
is not the Gauss-point stress of the grid field, and the operator is not
symmetric, so its largest frequency exceeds the Gauss-FEM one. Measured on
D1 large (p = 2, consistent mass, MUSL): stable at 0.35 dt_crit, J -> 0.56
at 8 cells and J <= 0 at 16 cells with 0.5 dt_crit. The critical step of a
2D reconstructed method is therefore RECONSTRUCTION_2D (0.6) times the
Gauss one, so the default cfl 0.5 runs at 0.3. In 1D the seed's spline
runs at 0.5 dt_crit on the hardest case (S2 large) and no factor applies.
"""
from functools import lru_cache

import numpy as np
from scipy.linalg import eigh
from skfem import BilinearForm, asm
from skfem.helpers import dot, grad

__all__ = ["spectral_radius", "interior_rayleigh_quotient", "critical_time_step",
           "stable_time_step",
           "fast_dof_limit", "lumping_fraction"]


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


def fast_dof_limit(degree):
    """4 q(p) / Lambda(p, consistent): a dof whose own Rayleigh quotient
    satisfies dt^2 K_ii / M_ii above this would, amplified by its coupling
    as an interior dof is, exceed the stability limit omega dt = 2 of the
    time step chosen from Lambda (see :mod:`skfem_mpm.solve.grid_system`)."""
    return 4.0 * interior_rayleigh_quotient(degree) / spectral_radius(degree, "consistent")


def lumping_fraction(ratio):
    """theta = smoothstep(2 ratio - 1): 0 for ratio <= 1/2, 1 for ratio >= 1."""
    s = np.clip(2.0 * np.asarray(ratio, dtype=np.float64) - 1.0, 0.0, 1.0)
    return s * s * (3.0 - 2.0 * s)


RECONSTRUCTION_2D = 0.6


def critical_time_step(grid, wave_speed, mass="lumped", reconstruction="none"):
    """dt_crit = 2 / (c sqrt(sum_d Lambda(p, mass) / h_d^2)) for the grid,
    times RECONSTRUCTION_2D for a reconstructed method on a 2D grid.

    ``mass="hybrid"`` (lumped acceleration, consistent velocity
    re-projection) takes the lumped Lambda: the step's frequencies are
    those of M_L^-1 K; the re-projection is an L2 projection of the
    particle velocities and adds none. Measured (S1, quadratic, 32 cells,
    2 particles per cell, velocities with 1e-3 noise, 2000 MUSL steps):
    hybrid stable up to 1.8 dt_crit(lumped), J <= 0 at 2.0 (lumped: 2.5
    and 3.0; consistent fails at 0.9 dt_crit(lumped))."""
    lam = spectral_radius(grid.degree, "lumped" if mass == "hybrid" else mass)
    h = np.asarray(grid.h, dtype=np.float64)
    factor = RECONSTRUCTION_2D if (grid.dim == 2 and reconstruction != "none") else 1.0
    return float(factor * 2.0 / (wave_speed * np.sqrt(np.sum(lam / h ** 2))))


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
