"""Reconstruction on a compiled run: part of the source of the generated loop
modules (not imported as a module; see
:mod:`skfem_mpm.solve.compiled_loop_ops`).

The compiled executor's reconstructed particles-to-grid
(:mod:`skfem_mpm.solve.compiled_reconstruct`, whose docstring gives the
formulas), in the same order on the same kernels (called by symbol, with
the argument types of the executor's calls), so that a run gives the same
bits on either path. Covered: the particle-knot spline in 1D
(:class:`Reconstruction`), and on the rule of CompiledReconstruction.rule
(:class:`RuleReconstruction`) the published TLS with its default options
and mls in 1D, 2D and 3D and the 2D spline with its direct solve; the run's
reconstruction type (and in a RuleReconstruction the types of its
kind-specific fields) says which, so a run compiles only its own kind's
functions.

The 1D spline:

    reconstruct_points   the step's Gauss rule over the body (x_g, w_g:
                         kernels.gauss_rule.gauss_rule_1d), the fit of the
                         per-volume fields h = [rho, rho v, sigma] (and
                         with a body force rho b = f_p / V_p) at its
                         points (kernels.spline_1d.not_a_knot_spline), and
                         the points as "quadrature particles" of mass
                         w_g rho_h, velocity (rho v)_h / rho_h, volume w_g,
                         stress sigma_h (and force w_g (rho b)_h), which the
                         p2g kernel and the consistent-mass assembly integrate
    project_points       MUSL: the fit of rho v^new at the same points, as
                         points of mass w_g and velocity (rho v^new)_h (the
                         g2p2g kernel with a = 0 integrates their momentum)

tls, mls, the 2D spline (CompiledReconstruction.rule, reconstruct and
project):

    rule_points          the particles' cells (kernels.gauss_rule.locate_cells)
                         and the step's rule: in 1D gauss_rule_1d; in 2D and
                         3D the tensor rule on the body's box of each cell
                         holding particles (body_boxes, gauss_rule_cells), except
                         in the cells a free surface cuts (the box is not
                         the whole cell), whose particles are points of the
                         rule themselves (``own``, after the Gauss points,
                         with weight V_p and their own values); the fit at
                         the Gauss points (fit_points), which first computes
                         and keeps for the step what depends on the
                         positions alone (tls: kernels.tls.tls_factor, then
                         tls_apply; mls: M_g^-1 e_0 in kernels.mls.mls_fit;
                         the 2D spline: kernels.spline_2d's system and
                         kernels.band_factor's banded Cholesky factor, then
                         its solves and spline_evaluate); the points as quadrature
                         particles, as above
    rule_project         MUSL: the fit of rho v^new at the Gauss points on
                         what the step's fit kept, the particles' own
                         rho v^new at the particle points

A step whose fitted density is 0 at a point (the executor then integrates
the momentum apart), or whose 2D spline system the banded Cholesky refuses
(the executor then factorises by SuperLU), stops the loop: the executor
takes it.
"""


@structref.register
class ReconstructionType(types.StructRef):
    def preprocess_fields(self, fields):
        return tuple((name, types.unliteral(t)) for name, t in fields)


ReconstructionType.__name__ = ReconstructionType.__qualname__ = \
    f"ReconstructionType_{VARIANT}"
globals()[ReconstructionType.__name__] = ReconstructionType


RECONSTRUCTION_FIELDS = (
    # the rule: Gauss-Legendre points and weights on [0, 1], the largest
    # gap inside one piece of the body (a cell), the breakpoints
    "ref", "wref", "gap", "breaks",
    # per particle: the fitted fields [rho, rho v, sigma] (n, 1 + dim + dim^2)
    # and with a body force its density rho b = f_p / V_p (dim more columns), rho
    "values", "rho",
    # the step's rule (sorted order, pieces, points) and the fit at its
    # points; the spline's work space (kernels.spline_1d.spline_work_size
    # of every particle and the fitted fields' columns)
    "order", "piece_particles", "piece_points", "xg", "fit", "spline_work",
    # the rule's arrays (kernels.gauss_rule.gauss_rule_1d_into: starts,
    # lows, highs, first, piece_points, xg, wg, cell), kept over the steps
    "rule_starts", "rule_lows", "rule_highs", "rule_first", "rule_points", "rule_xg",
    "rule_wg", "rule_cell",
    # the points as quadrature particles (x, v, m, V, stress) and, with a
    # body force, their forces w_g (rho b)_h (else not set)
    "xq", "vq", "mq", "Vq", "sq", "fq",
    # the MUSL projection: rho v^new per particle, its fit at the points,
    # zero stresses, the g2p2g kernel's (unused) point velocities
    "momentum_values", "momentum_fit", "no_stress", "point_velocities",
)


class Reconstruction(structref.StructRefProxy):
    """The reconstruction data of a compiled run."""

    def __new__(cls, *fields):
        return structref.StructRefProxy.__new__(cls, *fields)


structref.define_proxy(Reconstruction, ReconstructionType, list(RECONSTRUCTION_FIELDS))


@njit(cache=True)
def new_reconstruction(*fields):
    """A Reconstruction with ``fields`` in the order of RECONSTRUCTION_FIELDS."""
    return Reconstruction(*fields)


@njit(cache=True)
def _per_volume_fields(rc, v, m, V, stress, forces):
    """rc.values = the fitted per-volume fields [rho, rho v, sigma] of the
    particles (n, 1 + dim + dim^2) and, where rc.values has dim more
    columns (a body force), the force density f_p / V_p of the particle
    forces ``forces`` (the executor's volume forces); rc.rho = rho = m / V;
    returns rc.values (a Reconstruction or a RuleReconstruction)."""
    n, dim = v.shape
    values = rc.values
    base = 1 + dim + dim * dim
    for i in range(n):
        rho = m[i] / V[i]
        rc.rho[i] = rho
        values[i, 0] = rho
        for c in range(dim):
            values[i, 1 + c] = rho * v[i, c]
        for a in range(dim):
            for b in range(dim):
                values[i, 1 + dim + a * dim + b] = stress[i, a, b]
        if values.shape[1] > base:
            for c in range(dim):
                values[i, base + c] = forces[i, c] / V[i]
    return values


@njit(cache=True)
def _quadrature_points(rc, fit):
    """The rule's points (rc.xq, weights rc.Vq) as quadrature particles of
    the fitted fields ``fit`` (ng, 1 + dim + dim^2 (+ dim)): mass w_g rho_h,
    velocity (rho v)_h / rho_h, stress sigma_h (rc.mq, rc.vq, rc.sq), the
    force w_g (rho b)_h with a body force (rc.fq), and
    the projection's work arrays sized for them (kept from the last step
    while the count of points stays); False when rho_h is 0 at a point
    (nothing is divided then)."""
    ng = fit.shape[0]
    dim = rc.xq.shape[1]
    w = rc.Vq
    if rc.mq.shape[0] != ng:  # else the last step's (every entry is written again)
        rc.vq = np.empty((ng, dim))
        rc.mq = np.empty(ng)
        rc.sq = np.empty((ng, dim, dim))
        rc.momentum_fit = np.empty((ng, dim))
        rc.no_stress = np.zeros((ng, dim, dim))  # (read only)
        rc.point_velocities = np.empty((ng, dim))
    for g in range(ng):
        if fit[g, 0] == 0.0:
            return False
    for g in range(ng):
        rho = fit[g, 0]
        rc.mq[g] = w[g] * rho
        for c in range(dim):
            rc.vq[g, c] = fit[g, 1 + c] / rho
        for a in range(dim):
            for b in range(dim):
                rc.sq[g, a, b] = fit[g, 1 + dim + a * dim + b]
    base = 1 + dim + dim * dim
    if fit.shape[1] > base:  # a body force: w_g (rho b)_h
        if rc.fq.shape[0] != ng:
            rc.fq = np.empty((ng, dim))
        for g in range(ng):
            for c in range(dim):
                rc.fq[g, c] = w[g] * fit[g, base + c]
    return True


@njit(cache=True)
def reconstruct_points(rc, x, v, m, V, stress, forces):
    """The step's rule and the quadrature points of the fitted fields (see
    the module; ``forces`` a body force's f_p); False when the fitted
    density is 0 at a point."""
    n, dim = x.shape
    values = _per_volume_fields(rc, v, m, V, stress, forces)
    positions = x.reshape(n)  # 1D: x is (n, 1)
    order = rc.order  # (of n particles: kept over the steps)
    npieces, ng = GAUSS_RULE_1D_INTO(positions, V, rc.gap, rc.breaks, rc.ref, rc.wref, order,
                                     rc.rule_starts, rc.rule_lows, rc.rule_highs, rc.rule_first,
                                     rc.rule_points, rc.rule_xg, rc.rule_wg, rc.rule_cell)
    # the views of the rule's arrays the fit and the points use: the last
    # step's while the counts of pieces and points stay (set anew only when
    # they change: each set costs reference counts, the reshape a call)
    if rc.piece_particles.shape[0] != npieces + 1:
        rc.piece_particles = rc.rule_starts[:npieces + 1]
        rc.piece_points = rc.rule_points[:npieces + 1]
    if rc.xg.shape[0] != ng:
        xg = rc.rule_xg[:ng]
        rc.xg = xg
        rc.xq = xg.reshape((ng, 1))
        rc.Vq = rc.rule_wg[:ng]
        rc.fit = np.empty((ng, values.shape[1]))
    fit = rc.fit
    NOT_A_KNOT_SPLINE_INTO(positions, values, order, rc.piece_particles, rc.piece_points, rc.xg,
                           fit, rc.spline_work)
    return _quadrature_points(rc, fit)


@njit(cache=True)
def project_points(rc, x, v_new):
    """MUSL: the fit of rho v^new at the step's points (rc.momentum_fit)."""
    n, dim = v_new.shape
    for i in range(n):
        for c in range(dim):
            rc.momentum_values[i, c] = rc.rho[i] * v_new[i, c]
    NOT_A_KNOT_SPLINE_INTO(x.reshape(n), rc.momentum_values, rc.order, rc.piece_particles,
                           rc.piece_points, rc.xg, rc.momentum_fit, rc.spline_work)


# ------------------------------------------- the rule's fits: tls, mls, 2D spline
# The reconstructions on the rule of CompiledReconstruction.rule (in 1D the
# body's Gauss rule, in 2D and 3D the cells' rule with the particles of cut
# cells as points): the published TLS (kernels.tls, default options) and
# mls (kernels.mls) in 1D, 2D and 3D, the 2D spline (kernels.spline_2d,
# the direct solve). One type whose kind-specific fields (``factor``,
# ``alpha``, ``spline``) are None in the other kinds: the fit
# (:func:`fit_points`) is chosen from those fields' types, so that a run
# compiles only its kind's functions (compiled_loop_ops: _ruled).
@structref.register
class RuleReconstructionType(types.StructRef):
    def preprocess_fields(self, fields):
        return tuple((name, types.unliteral(t)) for name, t in fields)


RuleReconstructionType.__name__ = RuleReconstructionType.__qualname__ = \
    f"RuleReconstructionType_{VARIANT}"
globals()[RuleReconstructionType.__name__] = RuleReconstructionType


RULED_FIELDS = (
    # the rule: Gauss-Legendre points and weights on [0, 1], the largest
    # gap inside one piece of the 1D body, the first axis's breakpoints,
    # the breakpoints per axis and whether each axis is uniform (tuples:
    # locate_cells) and the number of cells
    "ref", "wref", "gap", "breaks", "axes", "uniform", "ncells",
    # per particle: the fitted fields [rho, rho v, sigma] (n, 1 + dim + dim^2)
    # and with a body force its density rho b = f_p / V_p (dim more columns), rho
    "values", "rho",
    # the step's rule: the particles' cells, the Gauss points (ngauss, dim),
    # their weights and cells, and the particles that are points of the
    # rule themselves (2D, 3D: those in cells a free surface cuts; after the
    # Gauss points, in particle order)
    "pcell", "xg", "wg", "gcell", "own",
    # what a fit keeps for the next fit on the same particles and rule (a
    # step's MUSL projection), None in the other kinds: tls the position
    # half of its fits (kernels.tls.tls_factor); mls the kernel radius and
    # the points' M_g^-1 e_0 (kernels.mls.mls_fit); the 2D spline the cubic
    # space's axes and sizes, its penalty and the stencil, band and banded
    # the stencil's ELL columns and banded Cholesky factor of A + P
    # (SplineLeastSquares, BandedCholesky)
    "factor", "radius", "alpha", "spline",
    # the 2D spline: the particles' cubic B-spline values of the step's
    # positions (kernels.spline_2d.spline_ls_system's cells, W)
    "spline_cells", "spline_basis",
    # the 2D TLS with its grid sums in closed form per cell
    # (CompiledReconstruction.cell_tables: kernels.cell_integrals), else None:
    # the axes' tables, (cells along x, functions along x, degree), the
    # step's fitted coefficients per cell slot, each slot's cell, and the
    # MUSL projection's coefficients
    "tables", "cell_shape", "coef", "slot_cell", "momentum_coef",
    # the points as quadrature particles (x, v, m, V, stress) and, with a
    # body force, their forces w_g (rho b)_h (else not set)
    "xq", "vq", "mq", "Vq", "sq", "fq",
    # the MUSL projection: rho v^new per particle, its fit at the points,
    # zero stresses, the g2p2g kernel's (unused) point velocities
    "momentum_values", "momentum_fit", "no_stress", "point_velocities",
)


class RuleReconstruction(structref.StructRefProxy):
    """The reconstruction data of a compiled run on the rule of
    CompiledReconstruction.rule (tls, mls, the 2D spline)."""

    def __new__(cls, *fields):
        return structref.StructRefProxy.__new__(cls, *fields)


structref.define_proxy(RuleReconstruction, RuleReconstructionType, list(RULED_FIELDS))


@njit(cache=True)
def new_rule_reconstruction(*fields):
    """A RuleReconstruction with ``fields`` in the order of RULED_FIELDS."""
    return RuleReconstruction(*fields)


@njit(cache=True)
def _rule_1d(rc, x, V):
    """The body's Gauss rule (kernels.gauss_rule.gauss_rule_1d) and the
    particles' cells, as CompiledReconstruction.rule."""
    n = x.shape[0]
    rc.pcell = LOCATE_CELLS(x, rc.axes, rc.uniform)
    _, _, _, xg, wg, gcell = GAUSS_RULE_1D(x.reshape(n), V, rc.gap, rc.breaks, rc.ref, rc.wref)
    rc.xg = xg.reshape((xg.shape[0], 1))
    rc.wg = wg
    rc.gcell = gcell
    rc.own = np.empty(0, dtype=np.int64)


@njit(cache=True)
def _rule_cells(rc, x, V):
    """The rule of CompiledReconstruction.rule in 2D and 3D: the tensor
    Gauss rule on the body's box of each cell holding particles
    (kernels.gauss_rule.body_boxes, gauss_rule_cells), except the cells
    a free surface cuts (their box is not the whole cell), whose particles
    are points of the rule themselves (``own``)."""
    axes = rc.axes
    pcell = LOCATE_CELLS(x, axes, rc.uniform)
    lo, hi = BODY_BOXES(x, V, pcell, axes)
    own, kept = CUT_CELL_PARTICLES(pcell, lo, hi, axes)
    xg, wg, gcell = GAUSS_RULE_CELLS(kept, lo, hi, rc.ref, rc.wref)
    rc.pcell = pcell
    rc.xg = xg
    rc.wg = wg
    rc.gcell = gcell
    rc.own = own


_RULE = _rule_1d if DIM == 1 else _rule_cells


def fit_points(rc, x, V, values, out, fresh):
    """out = the fit of ``values`` at the rule's Gauss points rc.xg; with
    ``fresh`` the position half first (kept in rc for the next fits on the
    same particles and rule). False when the fit cannot be made here (the
    2D spline: a pivot of the banded Cholesky not positive; the executor
    then factorises by SuperLU)."""


@overload(fit_points)
def _fit_points(rc, x, V, values, out, fresh):
    fields = rc.field_dict
    if not isinstance(fields["factor"], types.NoneType):
        def tls(rc, x, V, values, out, fresh):  # CompiledReconstruction._fit's tls
            if fresh:
                rc.factor = TLS_FACTOR(x, V, rc.pcell, rc.xg, rc.wg, rc.gcell, rc.ncells)
            TLS_APPLY(x, V, values, rc.xg, rc.factor, out)
            return True
        return tls
    if not isinstance(fields["alpha"], types.NoneType):
        def mls(rc, x, V, values, out, fresh):  # CompiledReconstruction._fit's mls
            if fresh:
                rc.alpha = np.empty((rc.xg.shape[0], x.shape[1] + 1))
            MLS_FIT(x, values, rc.xg, rc.gcell, rc.radius, rc.alpha, out, fresh)
            return True
        return mls

    def spline(rc, x, V, values, out, fresh):  # SplineLeastSquares.__call__
        done, coef = _spline_coefficients(rc, x, V, values, fresh)
        if done:
            axes, nbx = rc.spline[0], rc.spline[1]
            SPLINE_EVALUATE(rc.xg, coef, axes[0], axes[1], nbx, out)
        return done
    return spline


@njit(cache=True)
def _spline_coefficients(rc, x, V, values, fresh):
    """(done, the 2D spline's cubic coefficients (ndofs, k) of ``values``):
    its least-squares system (kernels.spline_2d) solved by the banded
    Cholesky factor of A + P, which ``fresh`` first makes (and keeps in
    rc.spline; the particles' basis values in rc.spline_cells and
    rc.spline_basis) as SplineLeastSquares.coefficients and BandedCholesky; done
    False when a pivot is not positive (the executor then factorises by
    SuperLU)."""
    axes, nbx, nby, penalty, A, cols, C = rc.spline
    rhs = np.empty((nbx * nby, values.shape[1]))
    if fresh and rc.spline_cells.shape[0] != x.shape[0]:  # the particles' basis values
        rc.spline_cells = np.empty((x.shape[0], 2), dtype=np.int64)
        rc.spline_basis = np.empty((x.shape[0], 8))
    SPLINE_LS_SYSTEM(x, V, values, axes[0], axes[1], nbx, nby, penalty, fresh, fresh,
                     rc.spline_cells, rc.spline_basis, A, rhs)
    if fresh:
        if not FIT_BAND_FACTOR(A, cols, C):
            return False, rhs
    coef = np.empty_like(rhs)
    APPLY_BAND_FACTOR(C, rhs, coef)
    return True, coef


@njit(cache=True)
def _own_points(rc, x, V, values):
    """The rule's particle points (rc.own: cells a free surface cuts) as the
    step's quadrature points with their own values (rc.xq, rc.Vq and
    _quadrature_points')."""
    own = rc.own
    dim = x.shape[1]
    k = values.shape[1]
    ng = own.shape[0]
    xq = np.empty((ng, dim))
    Vq = np.empty(ng)
    points = np.empty((ng, k))
    for j in range(ng):
        i = own[j]
        Vq[j] = V[i]
        for c in range(dim):
            xq[j, c] = x[i, c]
        for c in range(k):
            points[j, c] = values[i, c]
    rc.xq = xq
    rc.Vq = Vq
    return _quadrature_points(rc, points)


# The fitted cells' closed-form integrals (CompiledReconstruction's
# cell_tables: kernels.cell_integrals) of the 2D TLS (rc.spline None: its
# monomial coefficients per cell slot, kernels.tls) or the 2D spline (its
# cubic coefficients, the cells of the rule's Gauss blocks): each step
# below takes its kind's kernels, chosen from the type of rc.spline.
def _spline_type(rc):
    """Whether a RuleReconstruction (its numba type) is the 2D spline's."""
    return not isinstance(rc.field_dict["spline"], types.NoneType)


def _mls_type(rc):
    """Whether a RuleReconstruction (its numba type) is mls's."""
    return not isinstance(rc.field_dict["alpha"], types.NoneType)


@njit(cache=True)
def _mls_cells(rc, x, values, coef, fresh):
    """The mls fit of ``values`` at the rule's Gauss points into coef
    (cells, k, k, columns; M_g^-1 e_0 first with ``fresh``, kept in
    rc.alpha) as CompiledReconstruction._cell_fit's mls."""
    ng = rc.xg.shape[0]
    if fresh:
        rc.alpha = np.empty((ng, x.shape[1] + 1))
    MLS_FIT(x, values, rc.xg, rc.gcell, rc.radius, rc.alpha,
            coef.reshape((ng, values.shape[1])), fresh)


def fit_cells(rc, x, V, values):
    """The coefficients of the fit of ``values`` per fitted cell (rc.coef,
    rc.slot_cell), what depends on the positions alone first (kept in rc);
    False when the fit cannot be made here (see fit_points)."""


@overload(fit_cells)
def _fit_cells(rc, x, V, values):
    if _mls_type(rc):
        def mls(rc, x, V, values):
            k = rc.ref.shape[0]
            block = k * k  # the Gauss blocks' cells
            ncell = rc.wg.shape[0] // block
            if rc.coef.shape[0] != ncell:
                rc.coef = np.empty((ncell, k, k, values.shape[1]))
                rc.momentum_coef = np.empty((ncell, k, k, x.shape[1]))
            if rc.slot_cell.shape[0] != ncell:
                rc.slot_cell = np.empty(ncell, dtype=np.int64)
            for j in range(ncell):
                rc.slot_cell[j] = rc.gcell[j * block]
            _mls_cells(rc, x, values, rc.coef, True)
            return True
        return mls
    if _spline_type(rc):
        def spline(rc, x, V, values):  # CompiledReconstruction._cell_fit's spline
            done, coef = _spline_coefficients(rc, x, V, values, True)
            if not done:
                return False
            rc.coef = coef
            block = rc.ref.shape[0] * rc.ref.shape[0]  # the Gauss blocks' cells
            cells = np.empty(rc.wg.shape[0] // block, dtype=np.int64)
            for j in range(cells.shape[0]):
                cells[j] = rc.gcell[j * block]
            rc.slot_cell = cells
            return True
        return spline

    def tls(rc, x, V, values):
        rc.factor = TLS_FACTOR(x, V, rc.pcell, rc.xg, rc.wg, rc.gcell, rc.ncells)
        rc.slot_cell = SLOT_CELLS(rc.factor, rc.gcell)
        nact = rc.slot_cell.shape[0]
        if rc.coef.shape[0] != nact:
            rc.coef = np.empty((nact, 6, values.shape[1]))
            rc.momentum_coef = np.empty((nact, 6, x.shape[1]))
        TLS_COEFFICIENTS(x, V, values, rc.xg, rc.factor, rc.coef)
        return True
    return tls


def refit_cells(rc, x, V, values):
    """rc.momentum_coef = the coefficients of the fit of ``values`` on what
    fit_cells kept."""


@overload(refit_cells)
def _refit_cells(rc, x, V, values):
    if _mls_type(rc):
        def mls(rc, x, V, values):
            _mls_cells(rc, x, values, rc.momentum_coef, False)
        return mls
    if _spline_type(rc):
        def spline(rc, x, V, values):
            rc.momentum_coef = _spline_coefficients(rc, x, V, values, False)[1]
        return spline

    def tls(rc, x, V, values):
        TLS_COEFFICIENTS(x, V, values, rc.xg, rc.factor, rc.momentum_coef)
    return tls


@njit(cache=True)
def cell_rule_points(rc, x, v, m, V, stress, forces):
    """The 2D TLS or spline with closed-form cell integrals
    (CompiledReconstruction._cells_to_grid): the step's rule, the fit's
    coefficients (fit_cells: rc.coef, rc.slot_cell) and the rule's particle
    points as quadrature points; False when the fit cannot be made here."""
    values = _per_volume_fields(rc, v, m, V, stress, forces)
    _RULE(rc, x, V)
    if not fit_cells(rc, x, V, values):
        return False
    return _own_points(rc, x, V, values)


@njit(cache=True)
def cell_rule_project(rc, x, V, v_new):
    """MUSL (the 2D TLS or spline with closed-form cell integrals): the
    coefficients of the fitted rho v^new (rc.momentum_coef) and the
    particles' own rho v^new at the rule's particle points (rc.momentum_fit)."""
    n, dim = v_new.shape
    for i in range(n):
        for c in range(dim):
            rc.momentum_values[i, c] = rc.rho[i] * v_new[i, c]
    refit_cells(rc, x, V, rc.momentum_values)
    own = rc.own
    for j in range(own.shape[0]):
        for c in range(dim):
            rc.momentum_fit[j, c] = rc.momentum_values[own[j], c]


@njit(cache=True)
def cell_p2g(rc, has_fext, copies, touched):
    """Add p2g's fields of the fitted cells into the copies (kernels.cell_integrals)."""
    ncx, nbx, p = rc.cell_shape
    tx, ty = rc.tables
    CELL_P2G(rc.coef, rc.slot_cell, ncx, tx, ty, p, nbx, has_fext, copies, touched)


@njit(cache=True)
def cell_momentum(rc, copies, touched):
    """Add the fitted cells' projected momentum into the copies."""
    ncx, nbx, p = rc.cell_shape
    tx, ty = rc.tables
    CELL_MOMENTUM(rc.momentum_coef, rc.slot_cell, ncx, tx, ty, p, nbx, copies, touched)


@njit(cache=True)
def assemble_mass_fitted_cells(cm, rc, x, m, k, nbx, nby):
    """2D: the consistent mass stencil and K of the rule's particle points
    (kernels.mpm.consistent_cells_2d with no cell blocks) plus the fitted
    cells' closed-form integrals (kernels.cell_integrals.cell_mass), as
    Kernels.consistent_stencil with ``add``."""
    ncx, _, p = rc.cell_shape
    ASSEMBLE_CELLS(x, m, cm.axes, 0, k, p, nbx, cm.copies, cm.stiff_copies, cm.touched)
    tx, ty = rc.tables
    CELL_MASS(rc.coef, rc.slot_cell, ncx, tx, ty, p, nbx, cm.copies, cm.stiff_copies,
              cm.touched)
    _reduce_mass(cm, p, nbx, nby, 2)


@njit(cache=True)
def rule_points(rc, x, v, m, V, stress, forces):
    """The step's rule, the fit of the per-volume fields at its Gauss
    points (fit_points, fresh), the particles' own values at its particle
    points, and the points as quadrature particles (see
    reconstruct_points; ``forces`` a body force's f_p); False when the fit
    cannot be made here or the density is 0 at a point."""
    dim = x.shape[1]
    values = _per_volume_fields(rc, v, m, V, stress, forces)
    k = values.shape[1]
    _RULE(rc, x, V)
    xg, wg, own = rc.xg, rc.wg, rc.own
    ngauss = wg.shape[0]
    ng = ngauss + own.shape[0]
    fit = np.empty((ngauss, k))
    if not fit_points(rc, x, V, values, fit, True):
        return False
    if own.shape[0] == 0:
        rc.xq = xg
        rc.Vq = wg
    else:  # the Gauss points, then the particle points with their own values
        xq = np.empty((ng, dim))
        Vq = np.empty(ng)
        points = np.empty((ng, k))
        for g in range(ngauss):
            Vq[g] = wg[g]
            for c in range(dim):
                xq[g, c] = xg[g, c]
            for c in range(k):
                points[g, c] = fit[g, c]
        for j in range(own.shape[0]):
            i = own[j]
            Vq[ngauss + j] = V[i]
            for c in range(dim):
                xq[ngauss + j, c] = x[i, c]
            for c in range(k):
                points[ngauss + j, c] = values[i, c]
        rc.xq = xq
        rc.Vq = Vq
        fit = points
    return _quadrature_points(rc, fit)


@njit(cache=True)
def rule_project(rc, x, V, v_new):
    """MUSL: the fit of rho v^new at the step's Gauss points on what the
    step's fit kept (fit_points, not fresh), the particles' own rho v^new
    at its particle points (rc.momentum_fit)."""
    n, dim = v_new.shape
    for i in range(n):
        for c in range(dim):
            rc.momentum_values[i, c] = rc.rho[i] * v_new[i, c]
    own = rc.own
    if own.shape[0] == 0:
        fit_points(rc, x, V, rc.momentum_values, rc.momentum_fit, False)
        return
    ngauss = rc.wg.shape[0]
    fit = np.empty((ngauss, dim))
    fit_points(rc, x, V, rc.momentum_values, fit, False)
    for g in range(ngauss):
        for c in range(dim):
            rc.momentum_fit[g, c] = fit[g, c]
    for j in range(own.shape[0]):
        for c in range(dim):
            rc.momentum_fit[ngauss + j, c] = rc.momentum_values[own[j], c]
