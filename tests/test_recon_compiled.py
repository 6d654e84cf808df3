"""Reconstruction on the compiled executor agrees with the NumPy reference.

The reference reconstructions (skfem_mpm.reconstruct) are the oracle: the
compiled Gauss rule equals theirs bit for bit, the compiled reconstruction
agrees to 1e-12 relative, and whole runs agree as in test_executors: 1e-12
relative with lumped mass, 1e-9 with consistent or hybrid mass (the
compiled executor solves by CG to rtol 1e-13, the reference by sparse LU);
those are test_executors' RECONSTRUCTED cases.
"""
import numpy as np
import pytest

from skfem_mpm import Method, Particles, SplineGrid
from skfem_mpm import reconstruct
from skfem_mpm.kernels import tls as tls_kernel
from skfem_mpm.kernels.gauss_rule import (body_boxes, gauss_rule_1d, gauss_rule_cells,
                                         locate_cells, stable_order)
from skfem_mpm.kernels import mls as mls_kernel
from skfem_mpm.kernels.spline_2d import WIDTH, spline_ls_system
from skfem_mpm.kernels.spline_1d import not_a_knot_spline
from skfem_mpm.kernels.serial import serial
from skfem_mpm.reconstruct import (integration_rule, reconstruct_mls, reconstruct_spline,
                                   reconstruct_tls)
from skfem_mpm.solve.compiled import compiled_executor_applies
from skfem_mpm.solve.compiled_reconstruct import (BandedCholesky, CompiledReconstruction,
                                                  SplineLeastSquares)
from skfem_mpm.solve.state import prepare
from test_executors import scene_for

# the serial copies (what runs below SERIAL_BELOW particles: the same bits)
tls_reconstruct = serial(tls_kernel.tls_reconstruct)
tls_factor = serial(tls_kernel.tls_factor)
tls_apply = serial(tls_kernel.tls_apply)
mls_reconstruct = serial(mls_kernel.mls_reconstruct)


def layouts_1d():
    """(name, grid, particles): one body, several pieces, coincident
    positions, a body ending inside a cell, 1-3 particles per piece."""
    rng = np.random.default_rng(3)
    grid = SplineGrid(np.array([0.0, 0.1, 0.25, 0.3, 0.5, 0.62, 0.8, 1.0]), 2)
    out = []
    x = np.sort(rng.uniform(0.02, 0.93, 40))
    out.append(("one piece", x, np.full(x.size, 0.9 / x.size)))
    x = np.concatenate((rng.uniform(0.05, 0.2, 12), rng.uniform(0.55, 0.97, 20)))
    out.append(("two pieces", x, np.full(x.size, 0.012)))
    x = np.array([0.05, 0.42, 0.44, 0.81, 0.83, 0.85])
    out.append(("pieces of 1, 2 and 3", x, np.full(x.size, 0.02)))
    x = rng.uniform(0.1, 0.6, 30)
    x[[4, 9, 10]] = x[3]
    out.append(("coincident", x, np.full(x.size, 0.5 / 27)))
    return [(name, grid, Particles(x[:, None], np.ones(x.size), V)) for name, x, V in out]


def compiled_rule(grid, p):
    ref, wref = np.polynomial.legendre.leggauss(grid.degree + 2)
    return gauss_rule_1d(p.x[:, 0], p.V, float(grid.cell_sizes[0].max()), grid.breakpoints[0],
                         0.5 * (ref + 1), 0.5 * wref)


@pytest.mark.parametrize("name, grid, p", layouts_1d(), ids=lambda v: v if isinstance(v, str) else "")
def test_compiled_gauss_rule_equals_the_reference_bit_for_bit(name, grid, p):
    rule = integration_rule(grid, p, grid.degree + 2)
    order, pp, pg, xg, wg, cell = compiled_rule(grid, p)
    assert np.array_equal(xg, rule.x[:, 0]) and np.array_equal(wg, rule.w)
    assert np.array_equal(cell, rule.cell)
    assert [(b - a) for a, b in zip(pg[:-1], pg[1:])] == [idx.size for _, _, idx in rule.pieces]


@pytest.mark.parametrize("name, grid, p", layouts_1d(), ids=lambda v: v if isinstance(v, str) else "")
def test_compiled_particle_spline_agrees_with_the_reference(name, grid, p):
    values = np.random.default_rng(5).normal(size=(p.n, 4))
    rule = integration_rule(grid, p, grid.degree + 2)
    expected = reconstruct_spline(grid, p, values, rule)
    order, pp, pg, xg, _, _ = compiled_rule(grid, p)
    out = np.empty((xg.size, 4))
    not_a_knot_spline(p.x[:, 0], values, order, pp, pg, xg, out)
    assert np.abs(out - expected).max() <= 1e-12 * np.abs(expected).max()


def layouts_tls():
    """(name, grid, particles): random layouts in 1D, 2D and 3D, uniform and
    graded grids, with cells of every fallback level (quadratic: >= 3 per
    cell in 1D, 3 x 3 in 2D; linear; constant: one particle, or particles
    on a line), particles on cell boundaries and on the grid's upper end,
    unequal volumes."""
    rng = np.random.default_rng(11)
    out = [(name, grid, p) for name, grid, p in layouts_1d()]
    line = SplineGrid.line(0.0, 2.0, 10, 3)
    x = np.concatenate((rng.uniform(0.0, 0.6, 12), rng.uniform(0.6, 1.0, 3),  # 3, 1-2 per cell
                        [1.0, 1.2, 1.2, 1.4, 2.0], rng.uniform(1.6, 2.0, 9)))
    out.append(("1D fallbacks", line, Particles(x[:, None], np.ones(x.size),
                                                rng.uniform(0.01, 0.05, x.size))))
    square = SplineGrid.rectangle((0.0, 1.0), (0.0, 2.0), (5, 6), 2)
    p = Particles.seed(square, 3, 1.0, region=((0.0, 0.8), (0.0, 1.4)))
    x = p.x + rng.uniform(-0.02, 0.02, p.x.shape)
    out.append(("2D 3 x 3 jittered", square, Particles(x, np.ones(p.n), p.V)))
    cut = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (6, 5), 2)  # free surfaces inside cells
    out.append(("2D cut cells", cut, Particles.seed(cut, 3, 1.0, region=((0.1, 0.7), (0.0, 0.62)))))
    p = Particles.seed(cut, 3, 1.0, region=lambda X: np.hypot(X[:, 0] - 0.5, X[:, 1] - 0.45) < 0.3)
    x = p.x + rng.uniform(-0.01, 0.01, p.x.shape)
    out.append(("2D disk", cut, Particles(x, np.ones(p.n), p.V)))
    x = np.column_stack((rng.uniform(0.0, 1.0, 70), rng.uniform(0.0, 2.0, 70)))
    x[:4] = [[0.2, 0.0], [0.4, 1.0], [1.0, 2.0], [0.6, 0.5]]  # on cell boundaries, the corner
    x[4:8] = np.column_stack((np.linspace(0.61, 0.79, 4), np.linspace(0.71, 0.89, 4)))  # a line
    out.append(("2D random", square, Particles(x, np.ones(70), rng.uniform(0.5, 1.5, 70) / 35)))
    graded = SplineGrid((np.array([0.0, 0.1, 0.35, 0.5, 0.9, 1.0]),
                         np.array([-1.0, -0.2, 0.0, 0.7, 1.0])), 3)
    x = np.column_stack((rng.uniform(0.0, 1.0, 90), rng.uniform(-1.0, 1.0, 90)))
    out.append(("2D graded", graded, Particles(x, np.ones(90), np.full(90, 2.0 / 90))))
    return out + layouts_3d()


def layouts_3d():
    """(name, grid, particles) in 3D: a jittered block of 3 x 3 x 3 per cell
    ending inside cells (cut cells on three faces), a ball (every cut), a
    graded random cloud with particles on cell faces and the grid's corner
    and unequal volumes."""
    rng = np.random.default_rng(17)
    out = []
    box = SplineGrid.box((0.0, 1.0), (0.0, 1.0), (0.0, 2.0), (4, 3, 5), 2)
    p = Particles.seed(box, 3, 1.0, region=((0.0, 0.8), (0.0, 1.0), (0.0, 1.3)))
    x = p.x + rng.uniform(-0.02, 0.02, p.x.shape)
    out.append(("3D 3 x 3 x 3 jittered", box, Particles(x, np.ones(p.n), p.V)))
    cube = SplineGrid.box((0.0, 1.0), (0.0, 1.0), (0.0, 1.0), 5, 2)
    out.append(("3D ball", cube, Particles.seed(
        cube, 2, 1.0, region=lambda X: np.linalg.norm(X - 0.45, axis=1) < 0.3)))
    graded = SplineGrid((np.array([0.0, 0.1, 0.35, 0.5, 1.0]), np.array([-1.0, 0.0, 0.7, 1.0]),
                         np.array([0.0, 0.3, 1.0])), 3)
    x = np.column_stack((rng.uniform(0.0, 1.0, 150), rng.uniform(-1.0, 1.0, 150),
                         rng.uniform(0.0, 1.0, 150)))
    x[:3] = [[0.1, 0.0, 0.3], [1.0, 1.0, 1.0], [0.5, -1.0, 0.0]]
    out.append(("3D graded", graded, Particles(x, np.ones(150), rng.uniform(0.5, 1.5, 150) / 75)))
    return out


def kernel_rule(grid, p):
    """The Gauss rule on the body box of every held cell (in 1D the
    body's rule): what the kernels are checked on, cut boxes included
    (the step's rule takes the particles of cut cells instead, see
    test_compiled_2d_gauss_rule_equals_the_reference_bit_for_bit)."""
    if grid.dim == 1:
        return integration_rule(grid, p, grid.degree + 2)
    cells, _ = grid.locate(p.x)
    held = np.unique(cells)
    lo, hi = reconstruct.body_boxes(grid, p, cells, held)
    return reconstruct._box_rule(grid, held, lo, hi, grid.degree + 2)


def axes_of(grid):
    """(breakpoints, uniform): the grid's axes as the kernels take them."""
    return (tuple(np.ascontiguousarray(b, dtype=np.float64) for b in grid.breakpoints),
            tuple(bool(u) for u in grid._uniform))


def compiled_tls(grid, p, values, rule):
    out = np.empty((rule.x.shape[0], values.shape[1]))
    pcell = locate_cells(p.x, *axes_of(grid))
    tls_reconstruct(p.x, p.V, values, pcell, rule.x, rule.w, rule.cell, grid.ncells, out)
    return out


def test_the_compiled_tls_tolerances_are_the_reference_ones():
    assert tls_kernel.TLS_RANK_TOL == reconstruct.TLS_RANK_TOL
    assert tls_kernel.TLS_BOUND_TOL == reconstruct.TLS_BOUND_TOL
    assert tls_kernel.TLS_BOUND_ABS == reconstruct.TLS_BOUND_ABS


@pytest.mark.parametrize("name, grid, p", [c for c in layouts_tls() if c[1].dim >= 2],
                         ids=lambda v: v if isinstance(v, str) else "")
def test_compiled_2d_gauss_rule_equals_the_reference_bit_for_bit(name, grid, p):
    """The executor's rule (Gauss points of the whole cells, then the
    particles of the cut cells) is the reference's, bit for bit, in 2D and
    3D (in 3D the particles' box sizes take cube roots, libm's in the
    kernel and NumPy's own in the reference, which differ by up to an ulp:
    they only decide which faces of a cell are closed, and the cut boxes
    of the kernel rule, compared below only without cut cells)."""
    rule = integration_rule(grid, p, grid.degree + 2)
    pcell = locate_cells(p.x, *axes_of(grid))
    assert np.array_equal(pcell, grid.locate(p.x)[0])
    executor = CompiledReconstruction.__new__(CompiledReconstruction)
    executor._setup(grid, "tls", {})
    got = executor.rule(p)
    assert np.array_equal(got.x, rule.x) and np.array_equal(got.w, rule.w)
    assert np.array_equal(got.cell, rule.cell)
    own = getattr(got, "particle_points", None)
    assert (own is None) == (rule.particle_points is None)
    if own is not None:
        assert np.array_equal(own, rule.particle_points) and got.ngauss == rule.ngauss
    else:  # no cut cell: the kernels' rule on every held cell
        ref, wref = np.polynomial.legendre.leggauss(grid.degree + 2)
        lo, hi = body_boxes(p.x, p.V, pcell, axes_of(grid)[0])
        xg, wg, cell = gauss_rule_cells(pcell, lo, hi, 0.5 * (ref + 1), 0.5 * wref)
        assert np.array_equal(xg, rule.x) and np.array_equal(wg, rule.w)


@pytest.mark.parametrize("name, grid, p", layouts_tls(),
                         ids=lambda v: v if isinstance(v, str) else "")
def test_compiled_tls_agrees_with_the_reference(name, grid, p):
    values = np.random.default_rng(7).normal(size=(p.n, 5))
    values[:, 1] = 2.0 + p.x[:, 0] - 3.0 * p.x[:, -1] ** 2  # a quadratic column
    rule = kernel_rule(grid, p)
    expected = reconstruct_tls(grid, p, values, rule)
    out = compiled_tls(grid, p, values, rule)
    assert np.abs(out - expected).max() <= 1e-12 * np.abs(expected).max()


@pytest.mark.parametrize("name, grid, p", [c for c in layouts_tls() if c[1].dim >= 2],
                         ids=lambda v: v if isinstance(v, str) else "")
def test_one_tls_factor_serves_every_field_fitted_on_it(name, grid, p):
    """The position half of the fit (tls_factor: the cells' factorised
    Lagrange systems), computed once, gives each field the bits of a fit of
    that field alone (tls_reconstruct), also when it is used again (a
    step's MUSL projection reuses the step's): tls_apply does not change
    it."""
    rng = np.random.default_rng(5)
    rule = kernel_rule(grid, p)
    pcell = locate_cells(p.x, *axes_of(grid))
    factor = tls_factor(p.x, p.V, pcell, rule.x, rule.w, rule.cell, grid.ncells)
    for k in (5, 2, 5):
        values = rng.normal(size=(p.n, k))
        alone = compiled_tls(grid, p, values, rule)
        reused = np.empty_like(alone)
        tls_apply(p.x, p.V, values, rule.x, factor, reused)
        assert np.array_equal(reused, alone)


@pytest.mark.parametrize("radius", (1.5, 0.7))
@pytest.mark.parametrize("name, grid, p", layouts_tls(),
                         ids=lambda v: v if isinstance(v, str) else "")
def test_compiled_mls_agrees_with_the_reference(name, grid, p, radius):
    """Every level (linear fit, Shepard mean where fewer than d + 1
    particles or a line are in reach, 0 where none) on the TLS layouts; the
    small radius leaves points with no or one particle in reach. Agreement
    to 1e-12 of the largest value where the moment matrix M_g has
    condition number <= 100; the two solves (the reference's LU, the
    kernel's Cholesky) may differ by rounding times cond(M_g) elsewhere
    (points at the body's edge that see a few particles near the kernel's
    rim: cond up to 1e9 here; measured differences <= 6e-15 cond(M_g))."""
    values = np.random.default_rng(9).normal(size=(p.n, 4))
    values[:, 1] = 1.0 + 2.0 * p.x[:, 0] - p.x[:, -1]  # a linear column
    rule = kernel_rule(grid, p)
    expected = reconstruct_mls(grid, p, values, rule, radius=radius)
    r = radius * min(grid.h)
    out = np.empty((rule.x.shape[0], 4))
    mls_reconstruct(p.x, values, rule.x, rule.cell, r, out)
    cond = np.ones(rule.x.shape[0])
    for g, xg in enumerate(rule.x):  # the moment matrices, written out
        s = np.linalg.norm(p.x - xg, axis=1) / r
        near = s < 1
        if near.sum() > p.dim:
            w = np.where(s[near] <= 0.5, 1 - 6 * s[near] ** 2 + 6 * s[near] ** 3,
                         2 * (1 - s[near]) ** 3)
            phi = np.column_stack((np.ones(near.sum()), (p.x[near] - xg) / r))
            cond[g] = np.linalg.cond((w[:, None] * phi).T @ phi)
    tol = np.maximum(1e-12, 1e-14 * cond) * np.abs(expected).max()
    assert (np.abs(out - expected).max(axis=1) <= tol).all()
    assert np.abs(out - expected)[cond <= 100].max() <= 1e-12 * np.abs(expected).max()


@pytest.mark.parametrize("parallel", (False, True), ids=("serial", "parallel"))
@pytest.mark.parametrize("name, grid, p", [c for c in layouts_tls() if c[1].dim == 2],
                         ids=lambda v: v if isinstance(v, str) else "")
def test_the_cells_mass_summed_per_axis_is_the_point_sums(name, grid, p, parallel):
    """The consistent mass of the step's 2D rule with its whole cells'
    tensor rules summed per axis (Kernels.consistent_stencil with
    CompiledReconstruction.tensor_cells: kernels.mpm.consistent_cells_2d)
    equals the sum over its points one by one (consistent_2d) to rounding:
    quadratic and cubic, uniform and graded grids (closed form and
    extraction), cut cells' particle points after the cells."""
    from skfem_mpm.kernels.mpm import Kernels
    from skfem_mpm.solve.compiled_reconstruct import QuadraturePoints

    recon = CompiledReconstruction.__new__(CompiledReconstruction)
    recon._setup(grid, "tls", {})
    rule = recon.rule(p)
    cells, k = recon.tensor_cells(rule)
    assert cells > 0 and k == grid.degree + 2
    ng = rule.w.shape[0]
    m = rule.w * np.random.default_rng(5).uniform(0.5, 2.0, ng)
    points = QuadraturePoints(rule.x, np.zeros((ng, 2)), m, rule.w, np.zeros((ng, 2, 2)))
    kernels = Kernels(grid, parallel=parallel)
    by_point, K_point = (a.copy() for a in kernels.consistent_stencil(points))
    by_cell, K_cell = kernels.consistent_stencil(points, cells, k)
    assert np.abs(by_cell - by_point).max() <= 1e-14 * np.abs(by_point).max()
    assert np.abs(K_cell - K_point).max() <= 1e-14 * np.abs(K_point).max()
    assert np.abs(by_point).max() > 0.0


@pytest.mark.parametrize("name, grid, p", layouts_tls(),
                         ids=lambda v: v if isinstance(v, str) else "")
def test_the_mls_groups_give_each_points_own_bits(name, grid, p):
    """mls_fit runs the points in groups (consecutive points of one cell, at
    most LANES: the cubic cells' 25 points are split) over the particles in
    reach of any of the group's points: each point's fit and alpha have the
    bits of that point fitted alone (every point its own cell, groups of
    one), serial and parallel; a fit without coefficients on the alpha of
    an earlier fit (a step's MUSL projection) has the bits of a fit with
    them."""
    rng = np.random.default_rng(4)
    rule = kernel_rule(grid, p)
    ng = rule.x.shape[0]
    assert np.bincount(rule.cell).max() > 1  # groups of more than one point
    r = 1.5 * min(grid.h)
    values = rng.normal(size=(p.n, 5))
    fit = serial(mls_kernel.mls_fit)
    alone, alpha_alone = np.empty((ng, 5)), np.empty((ng, p.dim + 1))
    fit(p.x, values, rule.x, np.arange(ng), r, alpha_alone, alone, True)
    for kernel in (fit, mls_kernel.mls_fit):
        out, alpha = np.empty((ng, 5)), np.empty((ng, p.dim + 1))
        kernel(p.x, values, rule.x, rule.cell, r, alpha, out, True)
        assert np.array_equal(out, alone) and np.array_equal(alpha, alpha_alone)
        for k in (2, 5):
            later = rng.normal(size=(p.n, k))
            fresh, reused = np.empty((ng, k)), np.empty((ng, k))
            kernel(p.x, later, rule.x, rule.cell, r, np.empty_like(alpha), fresh, True)
            kernel(p.x, later, rule.x, rule.cell, r, alpha, reused, False)
            assert np.array_equal(reused, fresh)


def test_the_mls_2d_rows_of_a_group_are_the_scalar_solves_bits():
    """kernels.mls._constant_rows_2d (a group's M_g^-1 e_0 at once, 2D) has
    the bits of _constant_row point by point: well-posed moment matrices
    (random, and scaled by 1e-8 and 1e8), nearly singular ones (smallest
    eigenvalue over the mean diagonal between 0 and MLS_RANK_TOL: Shepard;
    or above it: fitted) with the small pivot in each place, singular and
    indefinite ones (Shepard, or 0 where M_00 <= 0) and M = 0 (alpha =
    0)."""
    rng = np.random.default_rng(8)
    mats = []
    for scale in (1.0, 1e-8, 1e8):
        for _ in range(3):
            B = rng.normal(size=(3, 6))
            mats.append(scale * B @ B.T)
    unit = np.eye(3) + np.tril(rng.uniform(0.3, 0.6, (3, 3)), -1)
    for low in (3e-7, 1e-5, 0.0, -1e-3):  # pivot j of M = unit diag(d) unit^T is d_j = low
        for j in range(3):
            d = np.ones(3)
            d[j] = low
            mats.append(unit @ np.diag(d) @ unit.T)
    mats.append(np.zeros((3, 3)))
    lanes = mls_kernel.LANES
    A = np.zeros((len(mats), 3))
    for first in range(0, len(mats), lanes):
        chunk = mats[first:first + lanes]
        sums = np.zeros((10, lanes))
        for g, M in enumerate(chunk):
            sums[:6, g] = M[0, 0], M[1, 0], M[1, 1], M[2, 0], M[2, 1], M[2, 2]
        rows = np.zeros((4, lanes))
        mls_kernel._constant_rows_2d(sums, len(chunk), rows)
        A[first:first + len(chunk)] = rows[:3, :len(chunk)].T
    fitted = {}
    for g, M in enumerate(mats):
        expected = np.zeros(4)
        if M[0, 0] > 0.0:
            work = np.zeros((4, 4))
            work[:3, :3] = np.tril(M)
            mls_kernel._constant_row(work, 3, np.empty((4, 4)), np.empty((4, 4)), expected)
        assert np.array_equal(A[g], expected[:3]), g
        fitted[g] = expected[1] != 0.0  # (Shepard: e_0 / M_00)
    assert [fitted[9 + g] for g in range(12)] == [False] * 3 + [True] * 3 + [False] * 6


@pytest.mark.parametrize("iterative", (False, True), ids=("lu", "cg"))
@pytest.mark.parametrize("penalty", (1e-6, 1e-3))
@pytest.mark.parametrize("name, grid, p", [c for c in layouts_tls() if c[1].dim == 2]
                         + [("2D 3 x 3 filled", SplineGrid.rectangle((0, 1), (0, 1), (6, 5), 2),
                             Particles.seed(SplineGrid.rectangle((0, 1), (0, 1), (6, 5), 2), 3,
                                            1.0))],
                         ids=lambda v: v if isinstance(v, str) else "")
def test_compiled_2d_spline_agrees_with_the_reference(name, grid, p, penalty, iterative):
    """The least squares in the cubic space, with the penalty on weak dofs
    (the partly filled layouts) and without (the filled grid): both sides
    factorise the same matrix A + P (assembled in a different order; the
    reference by SuperLU, the compiled side by a banded Cholesky), so they
    agree to rounding times its condition number: here
    1.6e3 filled, up to 2.3e9 partly filled with the default penalty;
    measured differences <= 7e-15 relative filled and <= 1.7e-18 cond(A + P)
    (1.1e-11) otherwise; asserted: max(1e-13, 1e-16 cond). The reused
    factorisation gives the same fit. The Kronecker-preconditioned CG of
    large grids (forced here; rtol 1e-13 per column): measured <= 6.3e-13
    filled, <= 3.6e-11 partly filled; asserted max(1e-11, 1e-16 cond).
    Below DIRECT_DOFS the compiled banded Cholesky factorises (every layout
    here: SuperLU only where a pivot is not positive, which would hide a
    wrong band)."""
    values = np.random.default_rng(13).normal(size=(p.n, 4))
    values[:, 1] = 1.0 + p.x[:, 0] ** 3 - 2.0 * p.x[:, 0] * p.x[:, 1] ** 2  # a cubic column
    rule = kernel_rule(grid, p)
    expected = reconstruct_spline(grid, p, values, rule, penalty=penalty)
    fit = SplineLeastSquares(grid, penalty, iterative=iterative)
    out = np.empty((rule.x.shape[0], 4))
    lu = fit(p.x, p.V, values, rule.x, out)
    assert iterative or isinstance(lu, BandedCholesky)  # (SuperLU: a pivot not positive)
    matrix = np.zeros((fit.ndofs, fit.ndofs))
    matrix[np.repeat(np.arange(fit.ndofs), np.diff(fit.indptr)), fit.cols] = \
        fit.A.ravel()[fit.slots]
    tol = max(1e-11 if iterative else 1e-13, 1e-16 * np.linalg.cond(matrix))
    assert np.abs(out - expected).max() <= tol * np.abs(expected).max()
    again = np.empty_like(out)
    fit(p.x, p.V, values, rule.x, again, lu)
    if iterative:  # warm started from the first solution
        assert np.abs(again - out).max() <= tol * np.abs(expected).max()
    else:
        assert np.array_equal(again, out)


# whole runs: tests/test_executors.py (RECONSTRUCTED)


@pytest.mark.parametrize("method, reason", [
    (Method(reconstruction="spline", reconstruction_options={"knots": "grid"}), "knots='grid'"),
    (Method(reconstruction=lambda grid, p, values, rule: values[:0]), "callable"),
    (Method(reconstruction="tls", reconstruction_options={"degree": 1}), "degree=1"),
    (Method(reconstruction="tls", reconstruction_options={"neighbour_weight": 1e-3}),
     "neighbour_weight=0.001"),
])
def test_what_stays_on_the_reference_executor_says_why(method, reason):
    case = dict(scheme="musl", mass="lumped", degree=2, dim=1, material="linear", effect="none")
    state = prepare(scene_for(case), method)
    ok, why = compiled_executor_applies(state)
    assert not ok and reason in why


def test_compiled_tls_in_partly_filled_cells_reconstructs_a_constant_density():
    """The compiled twin of test_reconstruct's partly-filled-cell test: the
    executor's own rule (cut boxes) and fit give rho_h = rho."""
    grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (6, 5), 2)
    p = Particles.seed(grid, 3, 2.5, region=((0.1, 0.7), (0.0, 0.62)))
    pcell = locate_cells(p.x, *axes_of(grid))
    ref, wref = np.polynomial.legendre.leggauss(grid.degree + 2)
    lo, hi = body_boxes(p.x, p.V, pcell, axes_of(grid)[0])
    xg, wg, cell = gauss_rule_cells(pcell, lo, hi, 0.5 * (ref + 1), 0.5 * wref)
    assert wg.sum() == pytest.approx(p.V.sum(), rel=1e-13)
    out = np.empty((wg.size, 1))
    tls_reconstruct(p.x, p.V, (p.m / p.V)[:, None], pcell, xg, wg, cell, grid.ncells, out)
    assert np.abs(out - 2.5).max() < 1e-12


def test_compiled_tls_bound_test_keeps_a_constant_density_positive():
    """On whole cells (a rule that is not the body's part) the compiled fit
    of a constant density takes the conserving constant, as the oracle."""
    grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (6, 5), 2)
    p = Particles.seed(grid, 3, 2.5, region=((0.1, 0.7), (0.0, 0.62)))
    pcell = locate_cells(p.x, *axes_of(grid))
    xg, wg, cell = grid.gauss_rule(grid.degree + 2, np.unique(pcell))
    out = np.empty((wg.size, 1))
    tls_reconstruct(p.x, p.V, (p.m / p.V)[:, None], pcell, xg, wg, cell, grid.ncells, out)
    assert out.min() > 0.0 and out.max() <= 2.5 * (1 + 1e-12)
    expected = reconstruct_tls(grid, p, (p.m / p.V)[:, None],
                               reconstruct.IntegrationRule(xg, wg, cell))
    assert np.abs(out - expected).max() <= 1e-12 * 2.5


def test_a_falling_block_with_tls_falls_freely():
    """Issue 18's falling block (16 x 16 quadratic cells, a 0.4 x 0.2 block
    whose free surfaces cut cells, 3 x 3 ppc, consistent MUSL, tls on the
    compiled executor) falls freely for 0.06 s: every particle's velocity is
    -g t to 1e-3 of it. On whole-cell rules without the bound test (the
    old tls) the run failed at t = 0.028: the consistent-mass CG stopped on
    the indefinite matrix of negative reconstructed densities."""
    from skfem_mpm import Body, Fixed, Gravity, LinearElastic, Scene, simulate

    grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), 16, 2)
    parts = Particles.seed(grid, 3, 1000.0, region=((0.3, 0.7), (0.45, 0.65)))
    scene = Scene(grid, Body(parts, LinearElastic(1e6, 0.3)), 0.06,
                  effects=[Gravity((0.0, -9.81)), Fixed("bottom")])
    r = simulate(scene, Method(mass="consistent", scheme="musl", reconstruction="tls"))
    assert "fast" in r.path
    v = r.particles.v
    assert np.abs(v[:, 1] + 9.81 * r.final_time).max() < 1e-3 * 9.81 * r.final_time
    assert np.abs(v[:, 0]).max() < 1e-3 * 9.81 * r.final_time


def test_a_block_hitting_a_floor_with_tls_gains_no_energy():
    """Issue 18's falling block (as above) hits the fixed floor at t = 0.284
    with 312 J of kinetic energy; by t = 0.30 the impact has turned most of
    it into strain energy. The total (kinetic + strain + potential) must
    not grow by more than 5% of the impact's 312 J; particle quadrature
    loses 21 J there. Measured: with the Gauss rule on the boxes of the
    cells the contact front cuts (fits extrapolated there) the impact
    gained 487 J by t = 0.30 (the run failed at t = 0.42);
    with the particles as the rule of the cut cells it loses 21 J."""
    from skfem_mpm import Body, Fixed, Gravity, LinearElastic, Scene, simulate

    grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), 16, 2)
    parts = Particles.seed(grid, 3, 1000.0, region=((0.3, 0.7), (0.45, 0.65)))
    material = LinearElastic(1e6, 0.3)
    scene = Scene(grid, Body(parts, material), 0.30,
                  effects=[Gravity((0.0, -9.81)), Fixed("bottom")])
    r = simulate(scene, Method(mass="consistent", scheme="musl", reconstruction="tls"))
    assert "fast" in r.path

    def energy(p):
        return (0.5 * np.sum(p.m[:, None] * p.v ** 2) + material.strain_energy(p)
                + 9.81 * np.sum(p.m * p.x[:, 1]))

    p = r.particles
    assert p.x[:, 1].min() < 0.035  # in contact
    assert energy(p) - energy(parts) < 0.05 * 312.0


def test_cholesky_factorises_and_tests_the_smallest_eigenvalue():
    """kernels.cholesky: L L^T = M - shift I where that is positive
    definite (also in place), False where the smallest eigenvalue of M is
    not above the shift."""
    from skfem_mpm.kernels.cholesky import cholesky

    rng = np.random.default_rng(5)
    Q, _ = np.linalg.qr(rng.normal(size=(5, 5)))
    M = Q @ np.diag([3.0, 1.0, 0.5, 0.1, 5e-9]) @ Q.T
    L = np.zeros((6, 6))
    assert cholesky(M, 5, 1e-9, L)
    low = np.tril(L[:5, :5])
    assert np.abs(low @ low.T - (M - 1e-9 * np.eye(5))).max() < 1e-14
    assert not cholesky(M, 5, 1e-8, L)  # smallest eigenvalue 5e-9 <= 1e-8
    work = M.copy()
    assert cholesky(work, 4, 0.0, work)  # in place, leading 4 x 4 block
    low = np.tril(work[:4, :4])
    assert np.abs(low @ low.T - M[:4, :4]).max() < 1e-14


def test_compiled_fits_fall_back_where_particles_are_nearly_on_a_line():
    """The particles of a cell within 1e-5 of a cell of a line off the
    cell's centre: the linear TLS block scaled to unit diagonal and the
    MLS moment matrices have smallest eigenvalues of 1e-10 and 3e-11,
    above 0 but below TLS_RANK_TOL and MLS_RANK_TOL, so both compiled
    fits take the lower level as the reference does. Planted: the
    Cholesky test without its shift (run with NUMBA_DISABLE_JIT=1, the
    callers' cache keeps the old callee) gives differences of 0.23 (tls)
    and 405 (mls)."""
    grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), 2, 2)
    rng = np.random.default_rng(11)
    n = 9
    x = np.column_stack((rng.uniform(0.05, 0.45, n), 0.45 + 5e-6 * rng.uniform(-1, 1, n)))
    p = Particles(x, np.ones(n), np.full(n, 0.25 / n))
    values = np.column_stack((1.0 + x[:, 0] ** 2, np.sin(40 * x[:, 1]) + x[:, 0]))
    rule = kernel_rule(grid, p)
    expected = reconstruct_tls(grid, p, values, rule)
    assert np.abs(compiled_tls(grid, p, values, rule) - expected).max() <= 1e-12 * np.abs(
        expected).max()
    expected = reconstruct_mls(grid, p, values, rule)
    out = np.empty_like(expected)
    mls_reconstruct(p.x, values, rule.x, rule.cell, 1.5 * min(grid.h), out)
    assert np.abs(out - expected).max() <= 1e-12 * np.abs(expected).max()


@pytest.mark.parametrize("order", ["seeded", "shuffled"])
def test_the_2d_spline_system_is_the_particle_sum_and_bitwise_symmetric(order):
    """spline_ls_system sums the lower half of A = sum_p V_p N(x_p) N(x_p)^T
    (cell by cell, the particles sorted by cell: also when they come in no
    order of cells) and copies the upper half from it: A equals the dense
    product B^T diag(V) B of the particles' cubic B-spline values (kept in
    cells, W) to rounding, bitwise symmetric; B^T W f likewise (no weak dof
    here: no penalty), and bitwise again from the kept values (other
    positions passed: not read)."""
    grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (5, 4), 2)
    p = Particles.seed(grid, 3, 1.0)
    if order == "shuffled":
        p = p.subset(np.random.default_rng(8).permutation(p.n))
    fit = SplineLeastSquares(grid, iterative=False)
    cells = np.empty((p.n, 2), dtype=np.int64)
    W = np.empty((p.n, 8))
    values = np.random.default_rng(5).normal(size=(p.n, 3))
    A = np.full_like(fit.A, np.nan)
    rhs = np.empty((fit.ndofs, 3))
    spline_ls_system(p.x, p.V, values, *fit.axes, fit.nbx, fit.nby, 1e-6, True, True, cells, W,
                     A, rhs)
    again = np.empty_like(rhs)  # from the kept basis values
    spline_ls_system(p.x + 0.1, p.V, values, *fit.axes, fit.nbx, fit.nby, 1e-6, False, False,
                     cells, W, A, again)
    assert np.array_equal(again, rhs)
    B = np.zeros((p.n, fit.ndofs))
    for a in range(4):
        for b in range(4):
            dof = (cells[:, 1] + b) * fit.nbx + cells[:, 0] + a
            B[np.arange(p.n), dof] = W[:, a] * W[:, 4 + b]
    dense = B.T @ (p.V[:, None] * B)
    rows = np.repeat(np.arange(fit.ndofs), np.diff(fit.indptr))
    stencil = A.ravel()[fit.slots]
    assert np.abs(stencil - dense[rows, fit.cols]).max() <= 1e-14 * np.abs(dense).max()
    assert np.abs(rhs - B.T @ (p.V[:, None] * values)).max() <= 1e-14 * np.abs(rhs).max()
    matrix = np.zeros((fit.ndofs, fit.ndofs))
    matrix[rows, fit.cols] = stencil
    assert np.array_equal(matrix, matrix.T)


def test_the_banded_cholesky_of_the_2d_spline_solves_and_refuses_an_indefinite_matrix():
    """BandedCholesky on a stencil array of the cubic space: a symmetric,
    diagonally dominant matrix is solved as the dense solve does; with a
    negative diagonal entry it gives None (SplineLeastSquares.factor then
    takes SuperLU)."""
    grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (4, 3), 2)
    fit = SplineLeastSquares(grid, iterative=False)
    rows = np.repeat(np.arange(fit.ndofs), np.diff(fit.indptr))
    rng = np.random.default_rng(2)
    dense = np.zeros((fit.ndofs, fit.ndofs))
    dense[rows, fit.cols] = rng.uniform(0.5, 1.0, rows.size)
    dense = dense + dense.T + 100.0 * np.eye(fit.ndofs)
    stencil = np.zeros_like(fit.A)
    stencil.ravel()[fit.slots] = dense[rows, fit.cols]
    rhs = rng.normal(size=(fit.ndofs, 2))
    expected = np.linalg.solve(dense, rhs)
    got = BandedCholesky(stencil, fit.nbx).solve(rhs)
    assert np.abs(got - expected).max() <= 1e-13 * np.abs(expected).max()
    stencil[5, WIDTH * WIDTH // 2] = -3.0
    assert BandedCholesky(stencil, fit.nbx) is None


@pytest.mark.parametrize("skew", [0.0, 0.3])
def test_the_2d_tls_fit_takes_the_fallback_levels_of_the_reference(skew):
    """2D cells at every fallback level (whole cells, the rule of the held
    cells, its weights also skewed so that the frame's G_1, G_2 are not 0,
    as in the cut cells' rules): 9 jittered particles (quadratic), 3 not
    on a line and 6 on two vertical lines (xi^2 a combination of 1 and xi:
    linear), 4 on a diagonal, 2, and 1 at the cell's centre (A_11 = 0: the
    conserving constant). The 2D fit (the constant eliminated, a Cholesky
    factor per level) marks exactly these levels well posed, agrees with
    the reference to 1e-12, and each cell's Gauss integral of the fit is
    its particle integral."""
    grid = SplineGrid.rectangle((0.0, 3.0), (0.0, 2.0), (3, 2), 2)
    rng = np.random.default_rng(5)
    q = (np.arange(3) + 0.5) / 3
    nine = np.column_stack((np.repeat(q, 3), np.tile(q, 3))) + rng.uniform(-0.05, 0.05, (9, 2))
    cells = [(0, 0, nine, (True, True)),
             (1, 0, np.array([[0.2, 0.3], [0.7, 0.4], [0.4, 0.8]]), (False, True)),
             (2, 0, np.column_stack((np.linspace(0.1, 0.8, 4), np.linspace(0.2, 0.9, 4))),
              (False, False)),
             (0, 1, np.array([[0.3, 0.4], [0.6, 0.7]]), (False, False)),
             (1, 1, np.array([[0.5, 0.5]]), (False, False)),  # at the frame's centre: A_11 = 0
             (2, 1, np.column_stack((np.repeat([0.25, 0.7], 3), np.tile([0.2, 0.5, 0.85], 2))),
              (False, True))]
    x = np.concatenate([c[2] + [c[0], c[1]] for c in cells])
    p = Particles(x, np.ones(len(x)), rng.uniform(0.5, 1.5, len(x)) / 9)
    values = np.column_stack((1.0 + x[:, 0] ** 2 - x[:, 0] * x[:, 1],
                              np.sin(3 * x[:, 1]) + x[:, 0]))
    pcell = locate_cells(p.x, *axes_of(grid))
    xg, wg, cell = grid.gauss_rule(grid.degree + 2, np.unique(pcell))
    wg = wg * (1.0 + skew * np.sin(7.0 * xg[:, 0] + 3.0 * xg[:, 1]))
    factor = tls_factor(p.x, p.V, pcell, xg, wg, cell, grid.ncells)
    assert skew == 0.0 or np.abs(factor[5][:, 1:3]).min() > 1e-3 * factor[5][:, 0].min()
    posed = dict(zip(tls_kernel.slot_cells(factor, cell), factor[6].tolist()))
    assert posed == {ix + 3 * iy: list(levels) for ix, iy, _, levels in cells}
    out = np.empty((wg.size, 2))
    tls_apply(p.x, p.V, values, xg, factor, out)
    expected = reconstruct_tls(grid, p, values, reconstruct.IntegrationRule(xg, wg, cell))
    assert np.abs(out - expected).max() <= 1e-12 * np.abs(expected).max()
    for e in range(grid.ncells):
        integral = (wg[cell == e, None] * out[cell == e]).sum(axis=0)
        assert np.abs(integral - (p.V[pcell == e, None] * values[pcell == e]).sum(axis=0)).max() \
            <= 1e-13 * np.abs(values).max()


@pytest.mark.parametrize("kind", ["sorted", "swapped", "random", "ties", "reversed", "nan"])
def test_the_rule_order_is_the_stable_argsort(kind):
    """gauss_rule_1d's order (kernels.gauss_rule.stable_order: by insertion,
    np.argsort past 8 n moves or at a NaN) is np.argsort(x, kind="mergesort")'s,
    ties in index order, on inputs of every kind and size."""
    rng = np.random.default_rng(7)
    for n in (0, 1, 2, 7, 40, 3000):
        x = np.sort(rng.random(n))
        if kind == "swapped" and n > 2:
            x[[1, 2]] = x[[2, 1]]
        elif kind == "random":
            x = rng.random(n)
        elif kind == "ties":
            x = np.round(rng.random(n) * 4) / 4
        elif kind == "reversed":
            x = x[::-1].copy()
        elif kind == "nan" and n:
            x[n // 2] = np.nan
        order = np.empty(n, dtype=np.int64)
        stable_order(x, order)
        assert np.array_equal(order, np.argsort(x, kind="mergesort")), (kind, n)
