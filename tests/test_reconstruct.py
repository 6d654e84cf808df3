"""Reconstruction of particle data (spline, TLS, MLS) and its effect on MPM."""
import numpy as np
import pytest

from skfem_mpm import Method, Particles, SplineGrid, simulate
from skfem_mpm.solve import prepare
from skfem_mpm.benchmarks import get_benchmark
from skfem_mpm.reconstruct import (integration_rule, reconstruct_mls, reconstruct_spline,
                                   reconstruct_tls)
from skfem_mpm.testing import assert_order, observed_orders


def grid1d():
    return SplineGrid(np.array([0.0, 0.15, 0.3, 0.55, 0.7, 1.0]), 2)


def grid2d():
    return SplineGrid((np.linspace(0, 1, 5), np.array([0.0, 0.2, 0.5, 0.8, 1.0])), 2)


def poly(degree, dim):
    if dim == 1:
        return lambda x: 0.5 + x[:, 0] - 2 * x[:, 0] ** 2 * (degree >= 2) + 3 * x[:, 0] ** 3 * (degree >= 3)
    return lambda x: (0.5 + x[:, 0] - 0.7 * x[:, 1]
                      + (degree >= 2) * (x[:, 0] * x[:, 1] - x[:, 1] ** 2)
                      + (degree >= 3) * (x[:, 0] ** 3 - 2 * x[:, 0] * x[:, 1] ** 2))


def check(reconstruct, particles, grid, f, tol, **options):
    rule = integration_rule(grid, particles, grid.degree + 2)
    values = np.column_stack((f(particles.x), 2 * f(particles.x)))
    out = reconstruct(grid, particles, values, rule, **options)
    exact = f(rule.x)
    assert np.abs(out[:, 0] - exact).max() < tol
    assert np.abs(out[:, 1] - 2 * exact).max() < 2 * tol


@pytest.mark.parametrize("knots", ("particles", "grid"))
@pytest.mark.parametrize("layout", ("uniform", "random"))
def test_spline_1d_reproduces_cubics(layout, knots):
    g = grid1d()
    p = Particles.seed(g, 5, 1.0, layout=layout, seed=3)
    check(reconstruct_spline, p, g, poly(3, 1), 1e-11, knots=knots)


def test_spline_2d_reproduces_cubics():
    g = grid2d()
    p = Particles.seed(g, 4, 1.0, layout="uniform")
    check(reconstruct_spline, p, g, poly(3, 2), 1e-10)


@pytest.mark.parametrize("dim", (1, 2))
def test_tls_reproduces_linear_and_quadratic(dim):
    g = grid1d() if dim == 1 else grid2d()
    check(reconstruct_tls, Particles.seed(g, 2, 1.0), g, poly(1, dim), 1e-12)
    # quadratic TLS: the cell constraint uses the particle integral, exact
    # for quadratics with 3 Gauss-layout particles per axis
    check(reconstruct_tls, Particles.seed(g, 3, 1.0, layout="gauss"), g, poly(2, dim), 1e-11,
          degree=2)


@pytest.mark.parametrize("dim", (1, 2))
def test_mls_reproduces_linear(dim):
    g = grid1d() if dim == 1 else grid2d()
    p = Particles.seed(g, 3, 1.0, layout="random", seed=1)
    check(reconstruct_mls, p, g, poly(1, dim), 1e-11)


@pytest.mark.parametrize("dim", (1, 2))
def test_tls_conserves_mass_and_momentum(dim):
    g = grid1d() if dim == 1 else grid2d()
    region = ((0.1, 0.83),) if dim == 1 else ((0.1, 0.83), (0.05, 0.66))
    p = Particles.seed(g, 3, 1.0, layout="random", region=region, seed=5,
                       velocity=lambda X: np.sin(3 * X) + 0.2)
    p.m *= 1 + 0.5 * np.sin(7 * p.x[:, 0])  # non-uniform density
    rule = integration_rule(g, p, g.degree + 2)
    rho = p.m / p.V
    values = np.column_stack((rho, rho[:, None] * p.v))
    out = reconstruct_tls(g, p, values, rule)
    mass = rule.w @ out[:, 0]
    momentum = rule.w @ out[:, 1:]
    assert abs(mass - p.m.sum()) < 1e-12 * p.m.sum()
    assert np.abs(momentum - p.m @ p.v).max() < 1e-12 * np.abs(p.m @ p.v).max()


def test_sparse_cells_fall_back_without_nan():
    g = SplineGrid.rectangle((0, 1), (0, 1), 6, 2)
    rng = np.random.default_rng(0)
    x = np.vstack((rng.uniform(0.0, 0.5, (40, 2)), [[0.9, 0.9]], [[0.6, 0.1]]))  # lone ones
    p = Particles(x, np.ones(len(x)), np.full(len(x), 1.0 / len(x)))
    rule = integration_rule(g, p, 4)
    for f in (reconstruct_spline, reconstruct_tls, reconstruct_mls):
        out = f(g, p, np.column_stack((np.ones(len(x)), x)), rule)
        assert np.all(np.isfinite(out))
    g1 = SplineGrid.line(0, 1, 8, 2)
    p1 = Particles(np.array([[0.05], [0.1], [0.55], [0.95]]), np.ones(4), np.full(4, 0.02))
    rule1 = integration_rule(g1, p1, 4)
    for f in (reconstruct_spline, reconstruct_tls, reconstruct_mls):
        assert np.all(np.isfinite(f(g1, p1, np.ones((4, 1)), rule1)))


def test_bad_reconstruction_options():
    g = grid1d()
    p = Particles.seed(g, 2, 1.0)
    rule = integration_rule(g, p, 4)
    with pytest.raises(ValueError, match="tls degree must be 1 or 2"):
        reconstruct_tls(g, p, np.ones((p.n, 1)), rule, degree=3)
    with pytest.raises(ValueError, match="knots must be"):
        reconstruct_spline(g, p, np.ones((p.n, 1)), rule, knots="cells")
    with pytest.raises(ValueError, match="tls constraint must be 'integral', 'mean' or 'none', got 'sum'"):
        reconstruct_tls(g, p, np.ones((p.n, 1)), rule, constraint="sum")


def test_a_custom_reconstruction_callable_is_used():
    calls = []

    def nearest(grid, particles, values, rule):
        calls.append(rule.x.shape[0])
        from scipy.spatial import cKDTree
        return values[cKDTree(particles.x).query(rule.x)[1]]

    b = get_benchmark("vibrating-string", "small", L=1.0)
    r = simulate(b.scene(8, 2, 4), Method(mass="consistent", reconstruction=nearest))
    assert calls and r.phase_counts["reconstruct"] > 0
    assert r.method["reconstruction"] == "nearest"


# The small variants of BENCHMARKS.md carry a model error of about 0.09 x
# strain (S1: 9e-8, S3: 2e-8 relative) that spline MPM reaches at 32-64 cells;
# the order tests use amplitudes 1e-4 of those (displacements are tracked
# exactly, so tiny amplitudes keep their digits).
AMPLITUDE = {"vibrating-string": {"L": 1.0, "v0": 1e-10 * 10.0}, "traction-bar": {"A": 1e-11}}


def s_errors(name, p, ppc, reconstruction, cells, **options):
    """The benchmark's primary error (S1: RMS at t_end; S3: the largest RMS
    over 20 saves, since t_end is a zero of its exact displacement)."""
    b = get_benchmark(name, "small", **AMPLITUDE[name])
    out = []
    for n in cells:
        scene = b.scene(n, p, ppc)
        method = Method(mass="consistent", scheme="cd", cfl=0.1, reconstruction=reconstruction,
                        reconstruction_options=options)
        steps = prepare(scene, method).n_steps
        r = simulate(scene, method, save_every=max(1, steps // b.saves))
        out.append(b.errors(r)[b.primary_error])
    return out


def test_quadratic_spline_reconstruction_is_third_order_on_s1():
    # measured (8 ppc, 16-32-64 cells): 2.93, 2.74
    cells = [16, 32, 64]
    errors = s_errors("vibrating-string", 2, 8, "spline", cells)
    assert_order(errors, 1.0 / np.array(cells), expected=2.7, tol=0.0)


@pytest.mark.slow(reason="a convergence study (22 s of runs)")
def test_quadratic_spline_reconstruction_beats_particle_quadrature_order_on_s3():
    # measured (8 ppc, 16-32-64 cells): grid-knot spline 2.71, 2.38; particles 2.01, 2.00
    cells = [16, 32, 64]
    spline = s_errors("traction-bar", 2, 8, "spline", cells, knots="grid")
    plain = s_errors("traction-bar", 2, 8, "none", cells)
    assert_order(spline, 1.0 / np.array(cells), expected=2.3, tol=0.0)
    assert spline[-1] < plain[-1] / 5


def test_cubic_with_reconstruction_is_ten_times_more_accurate_at_64_cells():
    plain = s_errors("vibrating-string", 3, 8, "none", [64])[0]
    spline = s_errors("vibrating-string", 3, 8, "spline", [64])[0]
    assert plain / spline >= 10.0, (plain, spline)


def test_tls_reconstruction_in_a_simulation_is_third_order_on_s1():
    """S1, cubic splines, 2 particles per cell, consistent mass, CD: with
    particles as quadrature points the error stalls (measured 8.98e-3,
    3.24e-3, 1.29e-3 at 8-16-32 cells: orders 1.5, 1.3); with the TLS
    reconstruction the run is third order and two to three orders of
    magnitude more accurate (measured 1.58e-4, 1.46e-5, 1.44e-6: orders
    3.4, 3.3). A reconstruction that does nothing, or fits only the
    conserving constant per cell, fails the bound."""
    cells = [8, 16, 32]
    tls = s_errors("vibrating-string", 3, 2, "tls", cells)
    assert_order(tls, 1.0 / np.array(cells), expected=3.0, tol=0.0)
    assert tls[-1] < 3e-6, tls
    plain = s_errors("vibrating-string", 3, 2, "none", [16])[0]
    assert plain > 100 * tls[1], (plain, tls[1])  # the bound is one quadrature cannot meet


def test_grid_knots_lift_the_four_ppc_cap():
    cells = [16, 32, 64]
    seed = s_errors("vibrating-string", 2, 4, "spline", cells)  # knots="particles"
    knots = s_errors("vibrating-string", 2, 4, "spline", cells, knots="grid")
    assert observed_orders(seed, 1.0 / np.array(cells))[-1] < 2.3  # the seed's cap
    assert_order(knots, 1.0 / np.array(cells), expected=2.7, tol=0.0)


@pytest.mark.slow
def test_spline_reconstruction_converges_under_large_deformation():
    """S4 with G = 0.05, cubic, 4 ppc, rk4 at the default cfl: measured
    1.0e-6, 1.2e-7, 1.4e-8 at 16, 32, 64 cells (orders 3.1, 3.1). With CD the
    same runs give 1.5e-4, 4.7e-5, 1.7e-5, 6.6e-6 at 16-128 cells (orders
    1.7, 1.5, 1.3; 1.3, 1.2 at cfl 0.125): CD's own error dominates once the
    fast-dof guard no longer lumps the filled grid's boundary rows (before,
    1.8e-2, 2.2e-3, ... converged at order 3 from 100x higher)."""
    b = get_benchmark("neo-hookean-bar", "large")
    cells = [16, 32, 64]
    errors = [b.errors(simulate(b.scene(n, 3, 4), Method(mass="consistent", scheme="rk4",
                                                           reconstruction="spline")))["error_rms"]
              for n in cells]
    assert errors[0] < 2e-6
    assert_order(errors, 1.0 / np.array(cells), expected=2.8, tol=0.0)


def test_central_difference_is_second_order_in_time_where_musl_is_first():
    # gravity switched on from rest: a(0) != 0, so the symplectic Euler start
    # of MUSL costs O(dt); CD starts with a half step
    b = get_benchmark("soil-column", "small")
    scene = b.scene(8, 2, 2)
    # consistent mass: with lumped mass the lossy velocity projection of
    # every step competes with the time error (no clean order in dt)
    ref = simulate(scene, Method(scheme="cd", mass="consistent", cfl=0.0125)).particles.u
    dts = []
    errs = {"cd": [], "musl": []}
    for cfl in (0.2, 0.1, 0.05):
        for scheme in errs:
            r = simulate(scene, Method(scheme=scheme, mass="consistent", cfl=cfl))
            errs[scheme].append(np.sqrt(np.mean((r.particles.u - ref) ** 2)))
        dts.append(r.dt)
    assert_order(errs["cd"], dts, expected=2.0, tol=0.2)
    assert observed_orders(errs["musl"], dts)[-1] < 1.3  # measured 1.38, 1.24: first order
    assert errs["cd"][-1] < errs["musl"][-1] / 4  # measured 7.2e-12 vs 3.6e-11


def cell_integrals(grid, particles, values, rule, out):
    """(Gauss integral of the reconstruction, particle integral) per cell."""
    pcell, _ = grid.locate(particles.x)
    gauss = np.zeros((grid.ncells, values.shape[1]))
    np.add.at(gauss, rule.cell, rule.w[:, None] * out)
    part = np.zeros_like(gauss)
    np.add.at(part, pcell, particles.V[:, None] * values)
    return gauss, part


@pytest.mark.parametrize("dim", (1, 2))
def test_published_tls_reproduces_quadratics_cell_by_cell(dim):
    """The default tls is the published per-cell constrained quadratic: exact
    on quadratics where the particle sum integrates them (Gauss layout, 3 per
    axis), with no help from the neighbours (each cell's own particles
    alone), and on randomly placed particles its cell integrals equal the
    particle integrals to round-off."""
    g = grid1d() if dim == 1 else grid2d()
    check(reconstruct_tls, Particles.seed(g, 3, 1.0, layout="gauss"), g, poly(2, dim), 1e-11)
    # a cell-wise quadratic that jumps between cells is reproduced too (no coupling)
    jump = lambda x: poly(2, dim)(x) + 3.0 * g.locate(x)[0]
    check(reconstruct_tls, Particles.seed(g, 3, 1.0, layout="gauss"), g, jump, 1e-10)
    p = Particles.seed(g, 3, 1.0, layout="random", seed=2)
    rule = integration_rule(g, p, g.degree + 2)
    values = np.column_stack((np.cos(4 * p.x[:, 0]), p.x[:, -1] ** 3))
    gauss, part = cell_integrals(g, p, values, rule, reconstruct_tls(g, p, values, rule))
    assert np.abs(gauss - part).max() < 1e-14 * np.abs(part).max() * g.ncells


def test_tls_falls_back_on_under_populated_cells():
    """Cells with too few particles for the quadratic (or on a line) take
    the linear constrained fit, then the conserving constant: no singular
    solve, finite values, the cell constraint still exact, and linear data
    reproduced wherever the linear fit is determined."""
    g = SplineGrid.rectangle((0, 1), (0, 1), 4, 2)
    h = 0.25
    x = np.array([[0.1, 0.1],                                  # 1 particle: constant
                  [0.3, 0.05], [0.45, 0.2],                    # 2: constant
                  [0.55, 0.05], [0.7, 0.1], [0.625, 0.225],    # 3 (not on a line): linear
                  [0.8, 0.05], [0.85, 0.1], [0.9, 0.15], [0.95, 0.2],  # 4 on a line: constant
                  [0.05, 0.3], [0.2, 0.3], [0.05, 0.45], [0.2, 0.45], [0.125, 0.375]])  # 5: linear
    # volumes whose particle sum integrates linears over the 3- and 5-particle cells
    V = np.full(len(x), h * h / 3)
    V[10:] = h * h / 5
    p = Particles(x, np.ones(len(x)), V)
    rule = integration_rule(g, p, 4)
    lin = 0.5 + x[:, 0] - 0.7 * x[:, 1]
    values = np.column_stack((lin, np.sin(5 * x[:, 0])))
    out = reconstruct_tls(g, p, values, rule)
    assert np.all(np.isfinite(out))
    gauss, part = cell_integrals(g, p, values, rule, out)
    assert np.abs(gauss - part).max() < 1e-15 * g.ncells
    linear_cells = np.isin(rule.cell, g.locate(x[[3, 10]])[0])
    exact = 0.5 + rule.x[:, 0] - 0.7 * rule.x[:, 1]
    assert np.abs(out[linear_cells, 0] - exact[linear_cells]).max() < 1e-12
    # the under-determined cells hold the conserving constant
    const_cells = np.isin(rule.cell, g.locate(x[[0, 1, 6]])[0])
    per_cell = out[const_cells, 1].reshape(-1, 16)
    assert np.abs(per_cell - per_cell[:, :1]).max() < 1e-15


def cut_cells():
    """6 x 5 cells with the body's free surfaces inside cells: x = 0.1 and
    0.7 cut columns to 0.4 and 0.2 of a cell, y = 0.62 the top row to 0.1
    (ppc 3: the cut parts are seeded 3 x 3 too, with thinner particles)."""
    g = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (6, 5), 2)
    return g, Particles.seed(g, 3, 2.5, region=((0.1, 0.7), (0.0, 0.62)))


def test_tls_in_partly_filled_cells_reconstructs_a_constant_density():
    """Where a free surface parallel to a grid line crosses a cell, the rule
    covers the body's part of the cell (body_boxes) and a constant density
    is the fit there: rho_h = rho at every Gauss point, the rule's volume is
    the particles' volume. On whole cells the conserving quadratic dipped to
    rho_h = -1.7 rho (negative lumped masses)."""
    g, p = cut_cells()
    rule = integration_rule(g, p, g.degree + 2)
    assert rule.w.sum() == pytest.approx(p.V.sum(), rel=1e-13)
    rho = p.m / p.V
    out = reconstruct_tls(g, p, np.column_stack((rho, 3.0 * rho)), rule)
    assert np.abs(out - [2.5, 7.5]).max() < 1e-12


def test_tls_bound_test_keeps_a_constant_density_positive_on_a_mismatched_rule():
    """The bound test: on a rule over whole cells (not the body's part, as
    where a surface cuts a cell diagonally) the quadratic and linear fits of
    a constant density leave the particles' range and the conserving
    constant is taken: rho_h > 0 and cell integrals still exact."""
    g, p = cut_cells()
    cells = np.unique(g.locate(p.x)[0])
    x, w, cell = g.gauss_rule(g.degree + 2, cells)
    from skfem_mpm.reconstruct import IntegrationRule
    rule = IntegrationRule(x, w, cell)
    rho = (p.m / p.V)[:, None]
    out = reconstruct_tls(g, p, rho, rule)
    assert out.min() > 0.0 and out.max() <= 2.5 * (1 + 1e-12)
    gauss, part = cell_integrals(g, p, rho, rule, out)
    assert np.abs(gauss - part).max() < 1e-13


def test_tls_mean_constraint_matches_cell_means_not_integrals():
    """constraint="mean": each cell's Gauss mean of the fit is the particles'
    volume-weighted mean, (1/|e|) int_e f_h = sum V_p f_p / sum V_p, so a
    cell holding more particle volume than its size (particles crossing in)
    does not raise the field; "integral" (published) keeps int_e f_h =
    sum V_p f_p. On 3 x 3 particles per cell with one extra particle moved
    into cell 0 the two differ by that particle's share."""
    g = grid2d()
    p = Particles.seed(g, 3, 1.0, layout="random", seed=4)
    x = p.x.copy()
    x[-1] = [0.1, 0.1]  # from the last cell into cell 0
    p = Particles(x, p.m, p.V)
    rule = integration_rule(g, p, g.degree + 2)
    values = np.column_stack((np.ones(p.n), np.cos(3 * x[:, 0]) + x[:, 1]))
    out = reconstruct_tls(g, p, values, rule, constraint="mean")
    gauss, part = cell_integrals(g, p, values, rule, out)
    cells = g.locate(x)[0]
    volume = np.bincount(cells, weights=p.V, minlength=g.ncells)
    size = np.bincount(rule.cell, weights=rule.w, minlength=g.ncells)
    held = volume > 0
    assert np.abs(gauss[held] / size[held, None] - part[held] / volume[held, None]).max() < 1e-13
    assert np.abs(out[:, 0] - 1.0).max() < 1e-12  # a constant is kept whatever the volumes
    published = reconstruct_tls(g, p, values, rule)
    gauss, part = cell_integrals(g, p, values, rule, published)
    assert np.abs(gauss - part).max() < 1e-13


def test_tls_without_constraint_reproduces_quadratics_on_random_layouts():
    """constraint="none" is the plain least-squares quadratic per cell: it
    reproduces a quadratic from randomly placed particles (whose sums do not
    integrate it), where the published constraint, a particle quadrature of
    the cell integral, does not."""
    g = grid2d()
    p = Particles.seed(g, 3, 1.0, layout="random", seed=6)
    rule = integration_rule(g, p, g.degree + 2)
    f = poly(2, 2)
    values = f(p.x)[:, None]
    exact = f(rule.x)
    free = reconstruct_tls(g, p, values, rule, constraint="none")[:, 0]
    assert np.abs(free - exact).max() < 1e-10
    published = reconstruct_tls(g, p, values, rule)[:, 0]
    assert np.abs(published - exact).max() > 1e-4


@pytest.mark.parametrize("dim", (1, 2))
def test_mls_with_a_quadratic_basis_reproduces_quadratics(dim):
    """mls degree=2 reproduces quadratics where the moment matrix is well
    conditioned everywhere (radius 2.5 cells here; the linear default does not)."""
    g = grid1d() if dim == 1 else grid2d()
    p = Particles.seed(g, 3, 1.0)
    check(reconstruct_mls, p, g, poly(2, dim), 1e-9, degree=2, radius=2.5)  # 1D: wide end cell
    rule = integration_rule(g, p, g.degree + 2)
    linear = reconstruct_mls(g, p, poly(2, dim)(p.x)[:, None], rule)[:, 0]
    assert np.abs(linear - poly(2, dim)(rule.x)).max() > 1e-4
    with pytest.raises(ValueError, match="mls degree must be 1 or 2, got 3"):
        reconstruct_mls(g, p, np.ones((p.n, 1)), rule, degree=3)
