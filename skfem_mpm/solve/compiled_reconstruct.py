"""Reconstructed particles-to-grid on the compiled executor.

The reference step (:func:`skfem_mpm.solve.steps.reconstructed_grid_data`)
integrates the reconstructed per-volume fields h = [rho, rho v, sigma,
rho b] with the Gauss rule over the body (points x_g, weights w_g):

    m_i = sum_g w_g rho_h(x_g) N_i(x_g),    P_i = sum_g w_g (rho v)_h(x_g) N_i(x_g),
    M_ij = sum_g w_g rho_h(x_g) N_i(x_g) N_j(x_g),
    f_i = - sum_g w_g sigma_h(x_g) grad N_i(x_g) + sum_g w_g (rho b)_h(x_g) N_i(x_g)

(Tielen et al. 2017; the module docstring of :mod:`skfem_mpm.reconstruct`).
These are the particle sums of p2g and of the consistent mass with the
Gauss points as "quadrature particles" of mass m_g = w_g rho_h, velocity
(rho v)_h / rho_h, volume w_g, stress sigma_h and force w_g (rho b)_h, so
the generated scatter kernels and the stencil assembly compute them. The
MUSL re-projection P_i = sum_g w_g (rho v^new)_h N_i reconstructs the
updated particle momentum with the same rule (g2p2g on points of mass w_g).

The TLS fit and the spline fit in 2D (:data:`CELL_INTEGRALS`) are a
polynomial per cell (TLS: total degree 2; the spline: cubic per axis), so
these sums over a whole cell's Gauss points are taken in closed form per
axis from their coefficients instead (:mod:`skfem_mpm.kernels.cell_integrals`,
the same quadrature summed in another order; the rule is exact for both
fits times the basis): the fit is never evaluated at the points but for
TLS's bound test, and p2g and the consistent mass run over the particle
points of the rule alone (cells a free surface cuts). The 2D mls fit is
not a polynomial per cell, but its Gauss points are fixed points of whole
cells: its values there are summed per cell by the same kernels against
per-axis tables of the rule's terms (point_axis_tables), with no basis
evaluation and no scatter of the Gauss points.

The rule: in 1D the body's pieces (:func:`skfem_mpm.kernels.gauss_rule.gauss_rule_1d`),
in 2D and 3D the part of each cell holding particles that the body covers
(:func:`skfem_mpm.kernels.gauss_rule.body_boxes`,
:func:`skfem_mpm.kernels.gauss_rule.gauss_rule_cells`), p + 2 points per
axis, both bit for bit those of :func:`skfem_mpm.reconstruct.integration_rule`.
The reconstructions: the particle-knot spline in 1D
(:mod:`skfem_mpm.kernels.spline_1d`), the published TLS (default
options) in 1D, 2D and 3D (:mod:`skfem_mpm.kernels.tls`) and mls in 1D, 2D
and 3D (:mod:`skfem_mpm.kernels.mls`); the spline in 1D and 2D. Which run here is
:func:`unsupported`'s answer; the rest stays on the reference executor.
"""
import numpy as np
from numba import get_num_threads

from ..errors import InvalidState
from ..kernels.gauss_rule import (body_boxes, cut_cell_particles, gauss_rule_1d,
                                  gauss_rule_cells, locate_cells)
from ..kernels.band_factor import apply_band_factor, factor_columns, fit_band_factor
from ..kernels.kronecker import KroneckerData, axis_mass_bands
from ..kernels.mls import mls_fit
from ..kernels.mpm import ell_pcg
from ..kernels.spline_1d import not_a_knot_spline
from ..kernels.spline_2d import WIDTH, spline_ell_columns, spline_evaluate, spline_ls_system
from ..kernels.serial import SERIAL_BELOW, for_threads
from ..kernels.tls import slot_cells, tls_apply, tls_coefficients, tls_factor
from ..kernels.cell_integrals import (axis_tables, cell_mass, cell_momentum, cell_p2g,
                                      point_axis_tables, spline_axis_tables)

TLS_DEFAULTS = {"degree": 2, "neighbour_weight": 0.0}

CELL_INTEGRALS = True
"""2D TLS, 2D spline and 2D mls: the step's grid sums per cell, factorised
per axis (see the module); False: over the Gauss points as quadrature
particles (tests compare the two). Read when a run is set up."""

__all__ = ["CompiledReconstruction", "unsupported"]


def unsupported(method, dim):
    """None when the compiled executor runs ``method``'s reconstruction in
    ``dim`` dimensions, else the reason it does not."""
    recon = method.reconstruction
    if callable(recon):
        return "reconstruction: a user's callable"
    options = dict(method.reconstruction_options)
    if recon == "spline" and dim == 2:
        if set(options) - {"knots", "penalty"}:
            return "reconstruction options"
        return None
    if recon == "spline" and dim == 1:
        if options.get("knots", "particles") != "particles":
            return "reconstruction spline with knots='grid'"
        if set(options) - {"knots", "penalty"}:
            return "reconstruction options"
        return None
    if recon == "mls":
        if set(options) - {"radius"}:
            return "reconstruction mls options other than radius"
        return None
    if recon == "tls":
        for name, value in options.items():
            if name not in TLS_DEFAULTS or value != TLS_DEFAULTS[name]:
                return f"reconstruction tls with {name}={value!r} (compiled: the published default)"
        return None
    return f"reconstruction {recon} in {dim}D (compiled: 1D and 2D)"


class QuadraturePoints:
    """Gauss points as the particle record of the scatter kernels
    (x, v, u, m, V, stress: see :data:`skfem_mpm.kernels.records.ParticleArrays`)."""

    def __init__(self, x, v, m, V, stress):
        self.x, self.v, self.m, self.V, self.stress = x, v, m, V, stress
        self.u = v  # not read by p2g or g2p2g


class Rule:
    """The step's Gauss rule: points ``x``, weights ``w``, their cells
    ``cell``, the particles' cells ``pcell`` (TLS) and what the 1D spline
    needs (sorted order and piece bounds; None in 2D)."""

    def __init__(self, x, w, cell, pcell=None, order=None, piece_particles=None,
                 piece_points=None):
        self.x, self.w, self.cell, self.pcell = x, w, cell, pcell
        self.order, self.piece_particles, self.piece_points = order, piece_particles, piece_points


DIRECT_DOFS = 4000
"""The 2D spline solves its least-squares system by a direct factorisation
below this many cubic dofs (:class:`BandedCholesky`), by
Kronecker-preconditioned CG from the last solution above
(:class:`KroneckerCG`)."""


class BandedCholesky:
    """(A + P)^-1 by its banded Cholesky factor
    (:func:`~skfem_mpm.kernels.band_factor.fit_band_factor` of the lower
    half of the stencil array A, as ELL rows with the columns ``cols`` of
    :func:`~skfem_mpm.kernels.spline_2d.spline_ell_columns`; applied by
    :func:`~skfem_mpm.kernels.band_factor.apply_band_factor`, whose
    triangular solves are axpys along contiguous runs): A + P is symmetric
    and, where every dof is seen by a particle or held by the penalty,
    positive definite; its band is w = 3 nbx + 3 (the cubic stencil's
    reach). None when a pivot is not positive (the caller then takes
    SuperLU)."""

    def __new__(cls, A, nbx, cols=None):
        if cols is None:
            cols = spline_ell_columns(nbx, A.shape[0] // nbx)
        C = np.empty((A.shape[0], factor_columns(3 * nbx + 3)))
        if not fit_band_factor(A, cols, C):  # NaN or 0: not positive definite
            return None
        self = super().__new__(cls)
        self.C = C
        return self

    def solve(self, rhs):
        r = np.ascontiguousarray(rhs, dtype=np.float64)
        z = np.empty_like(r)
        apply_band_factor(self.C, r, z)
        return z


class KroneckerCG:
    """Solves (A + P) c = b by the consistent mass's CG
    (:func:`skfem_mpm.kernels.mpm.ell_pcg`) with its Kronecker
    preconditioner (:mod:`skfem_mpm.kernels.kronecker`): A is the cubic
    space's mass matrix of unit density integrated by the particles, which
    the Kronecker product of the 1D Gauss mass matrices approximates where
    particles fill cells. Started from the previous solution with the same
    number of columns; rtol per column (``problem`` = column)."""

    def __init__(self, fit, A, previous, rtol):
        self.fit, self.A, self.rtol = fit, A, rtol
        lumped = A.sum(axis=1)
        self.kron = KroneckerData(fit.bands, fit.row_sums, (3, fit.nbx, fit.nby, 2),
                                  fit.rows, lumped, previous=previous)
        self.inv_diag = 1.0 / A[:, WIDTH * WIDTH // 2]
        self.iterations = 0

    def solve(self, rhs):
        nd, nc = rhs.shape
        fit = self.fit
        x = fit.warm.get(nc)
        x = np.zeros((nd, nc)) if x is None else x.copy()
        work = np.empty((6, nd, nc))
        nt = get_num_threads()
        its = ell_pcg(self.A, fit.ell_cols, self.inv_diag, self.kron.pcg_args(nc, nt), None,
                      np.ascontiguousarray(rhs), x, np.arange(nc), self.rtol, 10 * nd + 100,
                      nt, work)
        if its < 0:
            raise InvalidState(f"2D spline reconstruction: CG stopped above its tolerance "
                               f"{self.rtol:g} after {-its} iterations")
        self.iterations += its
        fit.warm[nc] = x
        return x


class SplineLeastSquares:
    """The 2D spline reconstruction (:mod:`skfem_mpm.kernels.spline_2d`):
    the compiled assembly of (A + P) c = B^T W f in the cubic B-spline
    space of the grid, its factorisation (:class:`BandedCholesky`; SuperLU
    as the reference's ``splu``, with a minimum-degree ordering, where a
    pivot is not positive; one per set of particle positions and volumes,
    reused by every reconstruction on them: a step's fields and its MUSL
    projection, a power iteration's products) or above DIRECT_DOFS the CG
    of :class:`KroneckerCG`, and the compiled evaluation at the Gauss
    points."""

    def __init__(self, grid, penalty=1e-6, iterative=None):
        from ..spline import SplineGrid

        cubic = SplineGrid(grid.breakpoints, 3)
        self.axes = tuple((np.ascontiguousarray(u, dtype=np.float64), bool(cubic._uniform[a]),
                           (u.size - 1) / (u[-1] - u[0]), cubic.extraction[a])
                          for a, u in enumerate(cubic.breakpoints))
        self.nbx, self.nby = cubic.basis_per_axis
        self.penalty = float(penalty)
        nd = self.nbx * self.nby
        dof = np.arange(nd)
        a, b = dof % self.nbx, dof // self.nbx
        offsets = np.arange(WIDTH) - WIDTH // 2
        aa = a[:, None] + np.tile(offsets, WIDTH)[None, :]
        bb = b[:, None] + np.repeat(offsets, WIDTH)[None, :]
        valid = (aa >= 0) & (aa < self.nbx) & (bb >= 0) & (bb < self.nby)
        self.slots = np.flatnonzero(valid.ravel())
        self.cols = (bb * self.nbx + aa).ravel()[self.slots].astype(np.int32)
        self.indptr = np.concatenate(([0], np.cumsum(valid.sum(axis=1)))).astype(np.int32)
        self.A = np.zeros((nd, WIDTH * WIDTH))
        self.ndofs = nd
        self._basis = None  # (the last factorisation, its particles' basis values)
        self.iterative = nd >= DIRECT_DOFS if iterative is None else bool(iterative)
        self.rtol = 1e-13
        self.ell_cols = spline_ell_columns(self.nbx, self.nby)
        if self.iterative:
            pairs = [axis_mass_bands(cubic, axis) for axis in range(2)]
            self.bands = [bnd for bnd, _ in pairs]
            self.row_sums = [rs for _, rs in pairs]
            self.rows = dof.astype(np.int64)
            self.warm = {}
            self._kron = None

    def _system(self, x, V, values, with_matrix, basis):
        """B^T W f (and, ``with_matrix``, A + P into self.A) with the
        particles' cubic B-spline values ``basis`` (cells, W) of
        kernels.spline_2d.spline_ls_system, made here when None; returns
        (rhs, basis)."""
        fresh = basis is None
        if fresh:
            basis = (np.empty((x.shape[0], 2), dtype=np.int64), np.empty((x.shape[0], 8)))
        rhs = np.empty((self.ndofs, values.shape[1]))
        spline_ls_system(x, V, values, *self.axes, self.nbx, self.nby, self.penalty, fresh,
                         with_matrix, *basis, self.A, rhs)
        return rhs, basis

    def factor(self, x, V, values):
        """(LU of A + P, B^T W f) for the particles (x, V); the particles'
        basis values are kept with it (self._basis) for
        :meth:`coefficients` of other values on them."""
        rhs, basis = self._system(x, V, values, True, None)
        solver = self._factor()
        self._basis = (solver, basis)
        return solver, rhs

    def _factor(self):
        """A factorisation of self.A (see the class)."""
        import scipy.sparse as sp
        import scipy.sparse.linalg as spla

        if self.iterative:
            solver = KroneckerCG(self, self.A, self._kron, self.rtol)
            self._kron = solver.kron
            return solver
        solver = BandedCholesky(self.A, self.nbx, self.ell_cols)
        if solver is not None:
            return solver
        # A + P is symmetric: its CSR arrays are those of its CSC form
        matrix = sp.csc_matrix((self.A.ravel()[self.slots], self.cols, self.indptr),
                               shape=(self.ndofs, self.ndofs))
        # minimum degree on A^T + A (the matrix is symmetric): 16 x 16 quadratic
        # cells (361 cubic dofs) 1.9 ms against 12.5 ms with splu's default
        # COLAMD; 128 x 128 (17,161 dofs) 1.6 s against 8.2 s
        return spla.splu(matrix, permc_spec="MMD_AT_PLUS_A")

    def coefficients(self, x, V, values, lu=None):
        """(the fit's cubic coefficients c (ndofs, k), the factorisation):
        ``lu`` a factorisation of the same particles (x, V) to reuse (with
        their basis values when it is the last made here), or None."""
        if lu is None:
            lu, rhs = self.factor(x, V, values)
        else:
            kept = self._basis[1] if self._basis is not None and self._basis[0] is lu else None
            rhs = self._system(x, V, values, False, kept)[0]
        return np.ascontiguousarray(lu.solve(rhs)), lu

    def __call__(self, x, V, values, xg, out, lu=None):
        """out = the fit at xg; returns the factorisation (pass it back as
        ``lu`` for other values on the same particles)."""
        coef, lu = self.coefficients(x, V, values, lu)
        spline_evaluate(xg, coef, *self.axes, self.nbx, out)
        return lu


class CompiledReconstruction:
    """The Gauss rule, the reconstruction and the Gauss-side integration of
    one run on a :class:`skfem_mpm.kernels.mpm.Kernels` set."""

    def __init__(self, state, kernels):
        self._setup(state.grid, state.method.reconstruction, state.method.reconstruction_options)
        self.kernels = kernels

    @classmethod
    def reconstructor(cls, grid, name, options):
        """The compiled reconstruction ``name`` with the reference's
        signature ``(grid, particles, values, rule)`` on a reference
        :class:`~skfem_mpm.reconstruct.IntegrationRule` of a 2D grid (what
        :class:`skfem_mpm.solve.timestep.ReconstructedOperator` applies;
        the 2D spline factorises once per rule)."""
        self = cls.__new__(cls)
        self._setup(grid, name, options)
        self.kernels = None
        def reconstruct(grid, particles, values, rule):
            if getattr(rule, "pcell", None) is None:
                rule.pcell = locate_cells(particles.x, self.axes, self.uniform)
            return self.reconstruct(particles, np.asarray(values, dtype=np.float64), rule)

        return reconstruct

    def _setup(self, grid, name, options):
        self.dim = grid.dim
        self.name = name
        ref, wref = np.polynomial.legendre.leggauss(grid.degree + 2)
        self.ref, self.wref = 0.5 * (ref + 1), 0.5 * wref
        self.axes = tuple(np.ascontiguousarray(b, dtype=np.float64) for b in grid.breakpoints)
        self.breaks = self.axes[0]
        self.uniform = tuple(bool(u) for u in grid._uniform)
        self.ncells = int(grid.ncells)
        self.gap = float(grid.cell_sizes[0].max())
        self._zero_a = np.zeros((grid.ndofs, grid.dim))
        if self.name == "spline" and self.dim == 2:
            self.spline_ls = SplineLeastSquares(grid, options.get("penalty", 1e-6))
        # 2D TLS, spline and mls: kernels.cell_integrals' tables per axis and kernels
        self.cell_tables = None
        if self.name in ("tls", "spline", "mls") and self.dim == 2 and CELL_INTEGRALS:
            self.degree = int(grid.degree)
            self.ncx = int(self.axes[0].size - 1)
            self.nbx = int(grid.basis_per_axis[0])
            if self.name == "tls":
                self.cell_tables = tuple(
                    axis_tables(self.axes[a], self.uniform[a], grid.extraction[a], self.degree,
                                self.ref, self.wref) for a in range(2))
            elif self.name == "mls":  # over the cells' Gauss points
                self.cell_tables = tuple(
                    point_axis_tables(self.axes[a], self.uniform[a], grid.extraction[a],
                                      self.degree, self.ref, self.wref) for a in range(2))
            else:  # over the cubic space's functions (SplineLeastSquares' axes)
                self.cell_tables = tuple(
                    spline_axis_tables(self.axes[a], self.uniform[a], grid.extraction[a],
                                       self.degree, self.spline_ls.axes[a][3], self.ref,
                                       self.wref) for a in range(2))
            self.cell_kernels = (cell_p2g, cell_momentum, cell_mass)
        if self.name == "mls":  # the reference's kernel radius: radius cells of the smallest
            self.radius = float(options.get("radius", 1.5)) * min(grid.h)

    def rule(self, p):
        pcell = None
        if self.name == "tls" or self.dim >= 2:
            pcell = locate_cells(p.x, self.axes, self.uniform)
        if self.dim == 1:
            order, pp, pg, xg, wg, cell = gauss_rule_1d(p.x[:, 0], p.V, self.gap, self.breaks,
                                                        self.ref, self.wref)
            return Rule(xg[:, None], wg, cell, pcell, order, pp, pg)
        lo, hi = body_boxes(p.x, p.V, pcell, self.axes)
        own, kept = cut_cell_particles(pcell, lo, hi, self.axes)
        xg, wg, cell = gauss_rule_cells(kept, lo, hi, self.ref, self.wref)
        if own.size == 0:
            return Rule(xg, wg, cell, pcell)
        # the particles are the rule of the cells a free surface cuts (as the reference)
        rule = Rule(np.concatenate((xg, p.x[own])), np.concatenate((wg, p.V[own])),
                    np.concatenate((cell, pcell[own])), pcell)
        rule.particle_points, rule.ngauss = own, wg.size
        return rule

    def reconstruct(self, p, values, rule):
        """The reconstructed ``values`` (n, k) at the rule's points (ng, k):
        the fit at the Gauss points, the particles' own values at the
        rule's particle points (``rule.particle_points``, after the
        ``rule.ngauss`` Gauss points)."""
        values = np.ascontiguousarray(values)
        own = getattr(rule, "particle_points", None)
        if own is None:
            return self._fit(p, values, rule)
        gauss = rule.__class__.__new__(rule.__class__)
        gauss.__dict__.update(rule.__dict__)
        n = rule.ngauss
        gauss.x, gauss.w, gauss.cell = rule.x[:n], rule.w[:n], rule.cell[:n]
        gauss.particle_points = None
        out = np.concatenate((self._fit(p, values, gauss), values[own]))
        for name in ("lu", "alpha", "tls"):  # what the fit keeps (see _fit)
            if hasattr(gauss, name):
                setattr(rule, name, getattr(gauss, name))
        return out

    def _fit(self, p, values, rule):
        """The fit of ``values`` at the points of a rule of Gauss points
        alone; what depends only on the particles' positions is kept on the
        rule for the next fit on it (a step's MUSL projection, a power
        iteration's products): the 2D spline's factorisation (``lu``), the
        mls points' M_g^-1 e_0 (``alpha``, see kernels.mls.mls_fit), the TLS cells' factorised
        Lagrange systems (``tls``: kernels.tls.tls_factor)."""
        out = np.empty((rule.x.shape[0], values.shape[1]))
        parallel = self.kernels.parallel if self.kernels is not None else p.n >= SERIAL_BELOW
        if self.name == "tls":  # the position half once per rule
            factor = getattr(rule, "tls", None)
            if factor is None:
                factor = rule.tls = for_threads(tls_factor, parallel)(
                    p.x, p.V, rule.pcell, rule.x, rule.w, rule.cell, self.ncells)
            for_threads(tls_apply, parallel)(p.x, p.V, values, rule.x, factor, out)
            return out
        if self.name == "mls":  # M_g^-1 e_0 once per rule (the positions)
            alpha = getattr(rule, "alpha", None)
            if alpha is None:
                rule.alpha = np.empty((rule.x.shape[0], self.dim + 1))
            for_threads(mls_fit, parallel)(p.x, values, rule.x, rule.cell, self.radius,
                                           rule.alpha, out, alpha is None)
            return out
        if self.dim == 2:  # spline: one factorisation per rule (the particles' positions)
            rule.lu = self.spline_ls(p.x, p.V, values, rule.x, out, getattr(rule, "lu", None))
            return out
        not_a_knot_spline(p.x[:, 0], values, rule.order, rule.piece_particles,
                          rule.piece_points, rule.x[:, 0], out)
        return out

    def to_grid(self, state, p, volume):
        """(lumped mass, momentum, force, consistent stencil or None, the
        projection data): ``volume`` the particle volume forces (n, dim)
        other than uniform accelerations, or None."""
        if self.cell_tables is not None:
            return self._cells_to_grid(state, p, volume)
        k, dim = self.kernels, self.dim
        with state.timer("reconstruct"):
            rule = self.rule(p)
            rho, values = self._fields(p, volume)
            h = self.reconstruct(p, values, rule)
        with state.timer("p2g"):
            w = rule.w
            rho_h = h[:, 0]
            ng = rho_h.shape[0]
            positive = bool(np.all(rho_h != 0.0))
            v = h[:, 1:1 + dim] / rho_h[:, None] if positive else np.zeros((ng, dim))
            stress = np.ascontiguousarray(h[:, 1 + dim:1 + dim + dim * dim]).reshape(ng, dim, dim)
            points = QuadraturePoints(rule.x, v, w * rho_h, w, stress)
            fext = None if volume is None else w[:, None] * h[:, 1 + dim + dim * dim:]
            mass, momentum, force = k.p2g(points, fext)
            if not positive:  # rho_h = 0 somewhere: the momentum from points of mass w_g
                momentum = self._momentum(rule, np.ascontiguousarray(h[:, 1:1 + dim])).copy()
        stencil = None
        if state.method.needs_consistent_mass:
            with state.timer("mass_matrix"):
                stencil = k.consistent_stencil(points, *self.tensor_cells(rule))
        return mass, momentum, force, stencil, (rule, rho)

    def _fields(self, p, volume):
        """(rho (n,), the fitted per-volume fields [rho, rho v, sigma] and
        with a body force rho b = volume / V (n, k))."""
        dim = self.dim
        rho = p.m / p.V
        fields = [rho[:, None], rho[:, None] * p.v, p.stress.reshape(p.n, dim * dim)]
        if volume is not None:
            fields.append(volume / p.V[:, None])
        return rho, np.ascontiguousarray(np.concatenate(fields, axis=1))

    def _cell_fit(self, p, values, rule):
        """(coefficients, cells): TLS: the fit of ``values`` per cell of the
        rule's Gauss points (cells, 6, k) (kernels.tls.tls_coefficients; the
        position half kept on the rule, as _fit), and each slot's cell; the
        2D spline: its cubic coefficients (ndofs, k) (the factorisation kept
        on the rule, as _fit) and the cells of the rule's Gauss points (its
        k x k blocks, ascending); mls: the fit at the rule's Gauss points
        (cells, k, k, columns) (kernels.cell_integrals.point_axis_tables;
        the points' M_g^-1 e_0 kept on the rule, as _fit) and those cells."""
        parallel = self.kernels.parallel
        n = getattr(rule, "ngauss", rule.w.shape[0])
        if self.name == "mls":
            alpha = getattr(rule, "alpha", None)
            if alpha is None:
                rule.alpha = np.empty((n, self.dim + 1))
            out = np.empty((n, values.shape[1]))
            for_threads(mls_fit, parallel)(p.x, values, rule.x[:n], rule.cell[:n], self.radius,
                                           rule.alpha, out, alpha is None)
            k = self.ref.shape[0]
            return (out.reshape(n // (k * k), k, k, values.shape[1]),
                    np.ascontiguousarray(rule.cell[:n:k * k]))
        if self.name == "spline":
            coef, rule.lu = self.spline_ls.coefficients(p.x, p.V, values,
                                                        getattr(rule, "lu", None))
            k = self.ref.shape[0]
            return coef, np.ascontiguousarray(rule.cell[:n:k * k])
        if getattr(rule, "tls", None) is None:
            rule.tls = for_threads(tls_factor, parallel)(
                p.x, p.V, rule.pcell, rule.x[:n], rule.w[:n], rule.cell[:n], self.ncells)
            rule.slot_cells = slot_cells(rule.tls, rule.cell[:n])
        coef = np.empty((rule.slot_cells.shape[0], 6, values.shape[1]))
        for_threads(tls_coefficients, parallel)(p.x, p.V, values, rule.x[:n], rule.tls, coef)
        return coef, rule.slot_cells

    def _own_points(self, p, rule):
        """The particles that are points of the rule themselves (cells a
        free surface cuts; none if no cell is cut)."""
        own = getattr(rule, "particle_points", None)
        return np.zeros(0, dtype=np.int64) if own is None else own

    def _cells_to_grid(self, state, p, volume):
        """to_grid of the 2D TLS, spline and mls with the cells' integrals
        factorised per axis (:data:`CELL_INTEGRALS`): p2g and the consistent mass of
        the rule's particle points, plus kernels.cell_integrals of the
        fitted coefficients added into the same per-thread copies."""
        k, dim = self.kernels, self.dim
        tx, ty = self.cell_tables
        cell_p2g, _, cell_mass = self.cell_kernels
        kernel = k.kernel
        with state.timer("reconstruct"):
            rule = self.rule(p)
            rho, values = self._fields(p, volume)
            coef, cells = self._cell_fit(p, values, rule)
        with state.timer("p2g"):
            own = self._own_points(p, rule)
            h = values[own]
            w = p.V[own]
            rho_h = h[:, 0]
            stress = np.ascontiguousarray(h[:, 1 + dim:1 + dim + dim * dim]).reshape(-1, dim, dim)
            points = QuadraturePoints(p.x[own], h[:, 1:1 + dim] / rho_h[:, None], w * rho_h, w,
                                      stress)
            fext = None if volume is None else w[:, None] * h[:, 1 + dim + dim * dim:]

            def add(copies, touched):
                kernel(cell_p2g)(coef, cells, self.ncx, tx, ty, self.degree, self.nbx,
                                 volume is not None, copies, touched)
            mass, momentum, force = k.p2g(points, fext, add)
        stencil = None
        if state.method.needs_consistent_mass:
            with state.timer("mass_matrix"):
                def add_mass(mass_copies, stiff_copies, touched):
                    kernel(cell_mass)(coef, cells, self.ncx, tx, ty, self.degree, self.nbx,
                                      mass_copies, stiff_copies, touched)
                stencil = k.consistent_stencil(points, 0, self.ref.shape[0], add_mass)
        return mass, momentum, force, stencil, (rule, rho)

    def _cells_project(self, state, p, v_new, rule, rho):
        """project of the 2D TLS, spline and mls with the cells' integrals
        factorised per axis."""
        k = self.kernels
        tx, ty = self.cell_tables
        cell_momentum = self.cell_kernels[1]
        with state.timer("reconstruct"):
            density = np.ascontiguousarray(rho[:, None] * v_new)
            coef, cells = self._cell_fit(p, density, rule)
        with state.timer("p2g"):
            own = self._own_points(p, rule)

            def add(copies, touched):
                k.kernel(cell_momentum)(coef, cells, self.ncx, tx, ty, self.degree, self.nbx,
                                        copies, touched)
            return self._points_momentum(p.x[own], p.V[own], density[own], add)

    def tensor_cells(self, rule):
        """(cells, k): in 2D the rule's first ``cells`` blocks of k x k points
        are whole cells' tensor rules (gauss_rule_cells), which the
        consistent mass sums per axis (kernels.mpm.consistent_cells_2d);
        (0, 0) in 1D."""
        if self.dim != 2:
            return 0, 0
        k = self.ref.shape[0]
        return getattr(rule, "ngauss", rule.w.shape[0]) // (k * k), k

    def _momentum(self, rule, momentum_density):
        """sum_g w_g (rho v)_h(x_g) N_i(x_g) by g2p2g (a = 0) on points of mass w_g."""
        return self._points_momentum(rule.x, rule.w, momentum_density)

    def _points_momentum(self, x, w, momentum_density, cells=None):
        """sum_g w_g (rho v)_g N_i(x_g) by g2p2g (a = 0) on points of mass w_g
        (``cells``: Transfers.g2p2g's)."""
        ng = w.shape[0]
        points = QuadraturePoints(x, momentum_density, w, w, np.zeros((ng, self.dim, self.dim)))
        scratch = self.kernels.scratch("projected_v", (ng, self.dim))
        return self.kernels.g2p2g(points, self._zero_a, 0.0, scratch, cells)

    def project(self, state, p, v_new, projection):
        """MUSL: the grid momentum of the reconstructed rho v^new."""
        rule, rho = projection
        if self.cell_tables is not None:
            return self._cells_project(state, p, v_new, rule, rho)
        with state.timer("reconstruct"):
            h = self.reconstruct(p, rho[:, None] * v_new, rule)
        with state.timer("p2g"):
            return self._momentum(rule, h)
