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
           "covered_weights", "tail_weight", "covered_parameters", "TAIL_RULE",
           "EFFECTIVE_MASS_RULE", "effective_mass_ratio",
           "guarded_stiffness", "lumping_fraction", "ReconstructedOperator", "power_iteration",
           "compiled_twin", "reconstruction_factor"]


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
    from :func:`full_grid_mass_ratios`. See :func:`covered_weights`."""
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


TAIL_RULE = False
"""Whether the fast-dof guard weighs a dof its particles see only at the
tail as the open knot vector's first function (:func:`tail_weight`), or
with weight 1, the plain limit (the default; see :func:`covered_parameters`
for what the rule fixes and what it breaks)."""


def covered_parameters(grid):
    """(lo, hi, t, F): COVERED, :func:`tail_weight` of the grid's degree and
    F = q(p) (sum_d h_d^-2 - min_d h_d^-2) (h_d the smallest cell of axis
    d), the scalars of :func:`covered_weights` (and of its compiled twin,
    :func:`skfem_mpm.kernels.mpm.covered_stiffness`); (lo, hi, 1, 0), the
    plain limit on tails, while TAIL_RULE is off.

    With the plain limit the guard fires on S3 (the bar's free end is a
    knot; cubic, 2 particles per cell, consistent mass, cfl 0.5): the last
    function, which the bar covers over one cell of its support, has the
    Gauss quotient of the open knot vector's first function (12.6, 9.1
    q(p)), r = 2.25 against the threshold 1/2 with either scheme, and its
    rows are lumped: spline + rk4 5.2e-3, 4.5e-3, 2.2e-3 at 8-16-32 cells
    (1.2e-5, 5.1e-7, 9.6e-8 with the rule). What the rule breaks: with a
    reconstruction the guard's K_ii and M_ii are integrated at the Gauss
    points of every cell the body touches, so the cell S3's bar fills and
    the cell S2's free top cuts give the same quotient; on S2 large (cubic,
    spline, consistent CD, 40 cells; tests/hard/test_free_surface) the rule
    then never lumps the moving top and a particle leaves the grid. A rule
    for reconstructed methods needs the particles' own coverage of the
    cell, which the guard does not measure yet."""
    if not TAIL_RULE:
        return (COVERED[0], COVERED[1], 1.0, 0.0)
    inv = 1.0 / np.asarray(grid.h, dtype=np.float64) ** 2
    floor = interior_rayleigh_quotient(grid.degree) * float(np.sum(inv) - np.min(inv))
    return (COVERED[0], COVERED[1], tail_weight(grid.degree), floor)


def covered_weights(weights, mass_ratios, lumped, diagonal, tail=1.0, floor=0.0):
    """The fast-dof guard's per-dof scale c_i and addend a_i (its stiffness
    is K_i c_i + a_i): c_i = t + (w_i - t) s_i (``tail`` t:
    :func:`tail_weight`, or 1), a_i = (1 - s_i) (1 - t) F M_ii
    (``floor``: F of :func:`covered_parameters`), s_i = smoothstep over
    COVERED of tau_i = M_ii / (m_i mu_i).

    The guard compares a dof's Rayleigh quotient with a limit built on an
    interior dof of the smallest cells. The first functions of an open knot
    vector have a higher quotient on a fully covered grid (2.2 and 3.7 q(p)
    for p = 2, 4.9 and 9.1 for p = 3) without being faster than the time
    step allows (Lambda includes those outlier modes), so a filled grid
    tripped the guard there at cfl 0.5 and lost accuracy. Such a dof gets
    the limit times 1 / w_i while it is covered: tau_i, the particles'
    consistent diagonal over their lumped mass relative to the full-grid
    value, is about 1 when particles cover the function (0.98-0.99 for the
    second function at 2-4 particles per cell) and drops when they see only
    its tail (0.16-0.45 measured). With TAIL_RULE a tail is weighed as the
    open knot vector's first function (see :func:`tail_weight`): a body ending at a
    knot (S3's free end) leaves a tail whose quotient is that function's
    and which is no faster than the step allows; with weight 1 there (the
    plain limit) the guard lumped S3's end dof (r = 2.25 at cubic, rk4,
    cfl 0.5) and cost up to 400x in accuracy. In 2D and 3D a dof is
    usually a tail along one axis only; t weighs its whole quotient, the
    covered axes' share too, so the addend puts back an interior quotient
    for every axis but one: (1 - t) F, F = q sum_(d != e) h_d^-2."""
    tau = diagonal / (np.maximum(lumped, 1e-300) * mass_ratios)
    lo, hi = COVERED
    s = np.clip((tau - lo) / (hi - lo), 0.0, 1.0)
    smooth = s * s * (3.0 - 2.0 * s)
    return tail + (weights - tail) * smooth, (1.0 - smooth) * (1.0 - tail) * floor * diagonal


EFFECTIVE_MASS_RULE = False
"""Whether the fast-dof guard also applies the effective-mass rule of
:func:`guarded_stiffness` (off by default: see there for what it fixes and
what it breaks)."""


def effective_mass_ratio(degree):
    """q(p) / Lambda(p, consistent): K_kk / S_k times this, over the guard's
    limit (which holds Lambda / q), is dt^2 c^2 K_kk / S_k / s^2 (see
    :func:`guarded_stiffness`); inf while EFFECTIVE_MASS_RULE is off (the
    rule then never lowers a dof's guarded stiffness)."""
    if not EFFECTIVE_MASS_RULE:
        return np.inf
    return interior_rayleigh_quotient(degree) / spectral_radius(degree, "consistent")


def _patch_offsets(dim, radius):
    """The patch of :mod:`skfem_mpm.kernels.fast_dof`: offsets
    ((2 radius + 1)^dim, 3), the neighbours in slot order (x fastest), the
    dof itself last."""
    r = [tuple(range(-radius, radius + 1)) if d < dim else (0,) for d in range(3)]
    out = [(a, b, c) for c in r[2] for b in r[1] for a in r[0] if (a, b, c) != (0, 0, 0)]
    return np.array(out + [(0, 0, 0)], dtype=np.int64)


def effective_masses(grid, consistent, lumped, dofs):
    """S_k = M_kk - M_kN M_NN^+ M_Nk for the dofs ``dofs`` of a spline grid
    (N: the dofs with mass within PATCH_RADIUS (default p) indices per axis; the NumPy twin of
    :func:`skfem_mpm.kernels.fast_dof.effective_mass`, same order of
    operations, vectorised over the dofs). ``consistent`` is the sparse
    consistent mass, ``lumped`` the lumped one."""
    from ..kernels.fast_dof import DROP, PATCH_RADIUS

    dofs = np.asarray(dofs, dtype=np.int64)
    shape = tuple(grid.basis_per_axis) + (1,) * (3 - grid.dim)
    idx = np.stack(np.unravel_index(dofs, shape[::-1])[::-1], axis=1)  # (a, b, c)
    offsets = _patch_offsets(grid.dim, PATCH_RADIUS if PATCH_RADIUS > 0 else grid.degree)
    at = idx[:, None, :] + offsets[None, :, :]
    inside = np.all((at >= 0) & (at < np.array(shape)), axis=2)
    j = np.where(inside, np.ravel_multi_index(tuple(np.clip(at, 0, np.array(shape) - 1)
                                                    .transpose(2, 0, 1))[::-1], shape[::-1]), 0)
    present = inside & (np.asarray(lumped)[j] > 0)
    present[:, -1] = True
    n = offsets.shape[0]
    rows = np.repeat(j, n, axis=1)
    cols = np.tile(j, (1, n))
    A = np.asarray(consistent.tocsr()[rows.ravel(), cols.ravel()]).reshape(len(dofs), n, n)
    A = A * (present[:, :, None] & present[:, None, :])
    pivot = np.zeros(len(dofs))
    indefinite = np.zeros(len(dofs), dtype=bool)
    for u in range(n):  # Cholesky, dependent neighbours left out
        pivot = A[:, u, u] - np.sum(A[:, u, :u] * A[:, u, :u], axis=1) if u else A[:, u, u].copy()
        if u == n - 1:
            break
        indefinite |= pivot < -DROP * A[:, u, u]
        keep = pivot > DROP * A[:, u, u]
        root = np.sqrt(np.where(keep, pivot, 1.0))
        s = A[:, u + 1:, u] - np.einsum("kiq,kq->ki", A[:, u + 1:, :u], A[:, u, :u])
        A[:, u, u] = np.where(keep, root, 0.0)
        A[:, u + 1:, u] = np.where(keep[:, None], s / root[:, None], 0.0)
    return np.where(indefinite, -1.0, pivot)


def guarded_stiffness(grid, stiffness, weights, limit, consistent, lumped, addend=0.0):
    """K_k w'_k (+ ``addend``, the a_k of :func:`covered_weights`), the stiffness the fast-dof guard compares with ``limit``
    M_kk (``fast_row_fractions``): w'_k = min(w_k, (q / Lambda) M_kk / S_k)
    on the dofs where K_k w_k > limit M_kk / 2 (those the plain rule would
    lump; w_k from :func:`covered_weights`, times 0 on dofs that never
    move), w_k elsewhere; S_k the effective mass of
    :mod:`skfem_mpm.kernels.fast_dof`, and K_k = sum_p m_p |grad N_k(x_p)|^2.

    The plain rule r_k = w_k dt^2 c^2 (K_kk / M_kk) (Lambda / q) / s^2
    assumes each dof is coupled as an interior one, whose own quotient the
    coupled spectrum exceeds by Lambda / q (33.9 for p = 3); the effective
    mass rule r_k = dt^2 c^2 (K_kk / S_k) / s^2 estimates the frequency of a
    mode localised at k directly. Taking the smaller keeps the guard off
    wherever it was off and lets it fire only where the localised estimate
    agrees: on S3 (a bar whose free end is a knot, cubic, spline
    reconstruction, rk4 at cfl 0.5) the plain rule lumped the end dof
    (r = 2.25; the exact top eigenvalue is Lambda's, i.e. not fast), the
    effective-mass rule gives r = 0.21 (radius-1 patch; 0.35 with the
    default patch of radius p), and S3's orders reach the issue's targets
    (cubic spline + rk4: 1.229e-5, 5.055e-7 at 8, 16 cells, order 4.60). A
    body ending half-way into its last cell is still lumped.

    Why it is off (EFFECTIVE_MASS_RULE): on S2 large (40 cells, cubic,
    spline reconstruction, consistent MUSL; tests/hard/test_free_surface)
    the column's top moves through cells, the rule un-lumps the top dofs
    (M_kk / S_k only 1.3-12 there) and the run fails at step 1234 (J <= 0),
    where the plain rule runs (without any guard it fails at step 149). The
    estimate uses the Gauss stiffness diagonal K_kk; the reconstructed
    operator's stiffness at a moving free end is not K (its operator is
    not symmetric), and the plain rule's 34-fold amplification was the
    margin that covered it. The falling block (p2 consistent MUSL) gained
    1.03% of the work with the radius-1 patch (limit 1%), 0.87% with
    radius p."""
    w = np.broadcast_to(np.asarray(weights, dtype=np.float64), np.shape(stiffness))
    guarded = stiffness * w + addend
    ratio = effective_mass_ratio(grid.degree) if hasattr(grid, "degree") else np.inf
    if not ratio < np.inf:
        return guarded
    diagonal = consistent.diagonal()
    lumped = np.asarray(lumped)
    candidates = np.flatnonzero((lumped > 0) & (guarded > 0.5 * limit * diagonal))
    if candidates.size == 0 or not hasattr(grid, "basis_per_axis"):
        return guarded
    S = effective_masses(grid, consistent, lumped, candidates)
    ok = S > 0.0
    k = candidates[ok]
    bound = ratio * stiffness[k] * (diagonal[k] / S[ok])
    guarded[k] = np.minimum(guarded[k], bound)
    return guarded


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
