"""The fast-dof guard of consistent mass (skfem_mpm.solve.grid_system): it
lumps the rows of dofs whose frequency would outgrow the time step, and
nothing on a grid the particles fill."""
import numpy as np
import pytest
from skfem import asm

from skfem_mpm import Method, SplineGrid, simulate
from skfem_mpm.benchmarks import get_benchmark
from skfem_mpm.solve.timestep import (_mass, _stiffness, covered_stiffness, fast_dof_weights,
                                      full_grid_mass_ratios, full_grid_quotients,
                                      interior_rayleigh_quotient, tail_weight)


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_full_grid_quotients_are_the_gauss_diagonal_quotients_in_2d(degree):
    grid = SplineGrid((np.array([0.0, 0.3, 0.5, 1.0, 1.2]), np.linspace(0.0, 2.0, 6)), degree)
    basis = grid.basis()
    M = asm(_mass, basis)
    expected = asm(_stiffness, basis).diagonal() / M.diagonal()
    assert np.allclose(full_grid_quotients(grid), expected, rtol=1e-12, atol=0)
    ratios = M.diagonal() / np.asarray(M.sum(axis=1)).ravel()
    assert np.allclose(full_grid_mass_ratios(grid), ratios, rtol=1e-12, atol=0)


def test_interior_dofs_keep_the_old_threshold_and_boundary_dofs_get_their_own():
    w, _ = fast_dof_weights(SplineGrid.line(0.0, 2.0, 16, 3))
    assert np.all(w[4:-4] == 1.0)
    first = full_grid_quotients(SplineGrid.line(0.0, 64.0, 64, 3))[:3] / \
        interior_rayleigh_quotient(3)
    assert np.allclose(w[:3], 1 / first, rtol=1e-12) and np.all(w[:3] < 0.7)


@pytest.mark.parametrize("backend", ["numpy", "numba"])
@pytest.mark.parametrize("scheme", ["cd", "musl"])
def test_a_filled_grid_trips_no_guard_at_the_default_cfl(backend, scheme):
    """S1 small, cubic, consistent mass, cfl 0.5: the guard lumps nothing, so
    the run equals the one without the guard. Before the per-dof threshold
    it lumped the rows next to the fixed ends (their full-grid quotient is
    4.9 and 9.1 times an interior one) and the error at 8 cells grew from
    2.9e-4 to 1.65e-2 (CD, spline) and from 1.8e-3 to 9.7e-3 (MUSL, p = 2)."""
    b = get_benchmark("vibrating-string", "small")
    scene = b.scene(8, 3, 2)
    guarded = simulate(scene, Method(scheme=scheme, mass="consistent", backend=backend))
    free = simulate(scene, Method(scheme=scheme, mass="consistent", backend=backend,
                                  frequency_guard=0.0))
    assert np.array_equal(guarded.particles.u, free.particles.u)


def test_a_dof_its_particles_see_only_at_the_tail_gets_the_first_functions_weight():
    """tau = M_ii / (m_i mu_i): about 1 on covered functions (their own
    full-grid weight), small where particles sit only at the tail, which is
    weighed as the open knot vector's first function (tail_weight: q / Q_1;
    the plain limit, weight 1, lumped S3's end dof and cost up to 400x)."""
    from skfem_mpm import Particles
    from skfem_mpm.quadrature import transfer_matrices

    grid = SplineGrid.line(0.0, 1.0, 16, 3)
    w, mu = fast_dof_weights(grid)
    assert tail_weight(3) == pytest.approx(w[0], rel=1e-12)  # the first function's
    # Q_1 = int (3 s^2)^2 / int (s^3)^2 = 63 / 5 on a unit cell
    assert tail_weight(3) == pytest.approx(interior_rayleigh_quotient(3) / 12.6, rel=1e-9)
    for region, relaxed in (((0.0, 1.0), True), ((0.0, 0.93), False)):
        p = Particles.seed(grid, 2, 1.0, region=(region,))
        N = transfer_matrices(grid, p.x)[0].tocsr()
        lumped, diagonal = N.T @ p.m, N.multiply(N).T @ p.m
        ones = np.ones(grid.ndofs)  # 1D: F = 0, no covered axis to put back
        scale = covered_stiffness(ones, diagonal, lumped, w, mu, ones, tail_weight(3), 0.0,
                                  np.inf, 3, grid.basis_per_axis)  # (no dof near a lumped one)
        expected = w[-2] if relaxed else tail_weight(3)  # 0.93: tau = 0.16 at dof -2
        assert scale[-2] == pytest.approx(expected, rel=1e-6), (region, scale[-2], w[-2])
        assert scale[1] == pytest.approx(w[1], rel=1e-6)  # the left end stays covered


@pytest.mark.parametrize("dim, p", [(1, 3), (2, 2), (3, 1)])
def test_the_particle_coverage_kernel_is_its_numpy_twin(dim, p):
    """Kernels.particle_coverage (kernels.mpm.particle_coverage and
    reduce_coverage: K = sum m |grad N|^2, D = sum m N^2, m = sum m N per
    dof) against steps.particle_coverage on the transfer matrices, to
    1e-12, on uniform (interior cells: the closed form) and graded axes
    (Bezier extraction) with particles in part of the grid (the serial
    copies other default tests compile: one type for every dim and p)."""
    from types import SimpleNamespace

    from skfem_mpm.kernels.mpm import Kernels
    from skfem_mpm.solve.steps import particle_coverage


    rng = np.random.default_rng(7)
    axes = [np.linspace(0.0, 1.0, 13), np.array([0.0, 0.2, 0.45, 0.7, 1.0]),
            np.linspace(0.0, 1.0, 4)][:dim]
    grid = SplineGrid(tuple(axes), p)
    x = rng.uniform(0.05, 0.8, (300, dim))
    m = rng.uniform(0.5, 2.0, 300)
    out = Kernels(grid, parallel=False).particle_coverage(SimpleNamespace(x=x, m=m))
    from skfem_mpm.quadrature import transfer_matrices

    N, G = transfer_matrices(grid, x)
    twin = particle_coverage(SimpleNamespace(N=N.tocsr(), grad_N=[g.tocsr() for g in G],
                                             to_grid=lambda a: N.T @ a), m)
    for row, expected in zip(out, twin):
        assert np.abs(row - expected).max() <= 1e-12 * np.abs(expected).max()
    assert np.all(out[2] == 0.0) == np.all(twin[2] == 0.0) and np.any(out[2] == 0.0)



def test_one_copy_reductions_are_the_held_copies_sums():
    """reduce_coverage and reduce_stencil (their serial copies) of one
    per-thread copy (a run on one thread: the one-copy path, which the
    default tests' two threads do not take) give the bits of the same copy
    beside a second, empty one (the holders' sums), on a touched range
    inside the rows (the rows outside it, stale entries of the copy
    included, 0), and that sum is the copy's entries there."""
    from skfem_mpm.kernels.mpm import reduce_coverage, reduce_stencil
    from skfem_mpm.kernels.serial import serial

    rng = np.random.default_rng(11)
    nd, p = 19, 3
    t0, t1 = 4, 15
    copies = rng.uniform(0.1, 1.0, (1, 3, nd))  # entries outside t0..t1 must not count
    two = np.concatenate([copies, np.zeros_like(copies)])
    one_out, two_out = np.empty((3, nd)), np.empty((3, nd))
    serial(reduce_coverage)(copies, np.array([[t0, t1]]), one_out)
    serial(reduce_coverage)(two, np.array([[t0, t1], [0, 0]]), two_out)
    assert np.array_equal(one_out, two_out)
    assert np.array_equal(one_out[:, t0:t1], copies[0, :, t0:t1])
    assert not one_out[:, :t0].any() and not one_out[:, t1:].any()
    mass = rng.uniform(0.1, 1.0, (1, nd, p + 1))
    mass[0, 9, 0] = 0.0  # a zero row: its other entries 0
    stiff = rng.uniform(0.1, 1.0, (1, nd))
    out = []
    for mc, sc, touched in ((mass, stiff, np.array([[t0, t1]])),
                            (np.concatenate([mass, np.zeros_like(mass)]),
                             np.concatenate([stiff, np.zeros_like(stiff)]),
                             np.array([[t0, t1], [0, 0]]))):
        M, K = np.zeros((nd, 2 * p + 1)), np.zeros(nd)  # (rows beyond lo..hi: 0)
        serial(reduce_stencil)(mc, sc, touched, t0 - 2, t1 + 2, p, nd, 1, 1, M, K)
        out.append((M[t0 - 2:t1 + 2], K[t0 - 2:t1 + 2]))
    assert np.array_equal(out[0][0], out[1][0]) and np.array_equal(out[0][1], out[1][1])
    M, K = out[0]
    assert np.array_equal(K[2:-2], stiff[0, t0:t1]) and not K[:2].any() and not K[-2:].any()
    assert np.array_equal(M[2:-2, p:], np.where(mass[0, t0:t1, :1] == 0.0, 0.0,
                                                mass[0, t0:t1]))

def test_the_guard_kernel_is_its_numpy_twin():
    """kernels.mpm.covered_stiffness (its serial copy, which other default
    tests compile) against timestep.covered_stiffness, bit for bit, on
    covered, tail and unseen dofs (D = 0: inf where the dof moves, 0 where
    it never does)."""
    from skfem_mpm.kernels import mpm
    from skfem_mpm.kernels.serial import for_threads
    from skfem_mpm.solve.timestep import COVERED

    kernel = for_threads(mpm.covered_stiffness, False)  # the copy small runs call

    rng = np.random.default_rng(5)
    shape = (20, 20)  # 400 dofs on a quadratic 2D grid's layout
    n = 400
    lumped = rng.uniform(0.1, 1.0, n)
    mu = rng.uniform(0.3, 0.6, n)
    diagonal = lumped * mu * rng.uniform(0.0, 1.2, n)  # tau from 0 to 1.2
    diagonal[::17] = 0.0
    moving = np.where(rng.uniform(size=n) < 0.2, 0.0, 1.0)
    K, w = rng.uniform(0.0, 5.0, n), rng.uniform(0.1, 1.0, n)
    out = np.empty(n)
    tailed = covered_stiffness(K, diagonal, lumped, w, mu, moving, tail_weight(3), 2.5, np.inf,
                               2, shape)  # (no dof lumped: nothing withdrawn)
    seen = (diagonal > 0) & (moving > 0)
    # a limit that lumps ~3% of the dofs (r = k / (limit D) > 1/2), some partly:
    # the withdrawal reaches p = 2 indices from each, a box of 5 x 5
    limit = 2.0 * np.quantile(tailed[seen] / diagonal[seen], 0.97)
    kernel(K, diagonal, lumped, w, mu, moving, *COVERED, tail_weight(3), 2.5, limit, 2, *shape,
           np.empty((2, n)), out)
    expected = covered_stiffness(K, diagonal, lumped, w, mu, moving, tail_weight(3), 2.5, limit,
                                 2, shape)
    assert np.array_equal(out, expected)
    plain = covered_stiffness(K, diagonal, lumped, w, mu, moving, 1.0, 0.0, limit, 2, shape)
    assert np.any(out != tailed) and np.any(out == tailed) and np.any(out == plain)
    assert np.any((out != tailed) & (out != plain))  # partly withdrawn
    assert np.isinf(out[(diagonal == 0) & (moving > 0)]).all()
    assert np.all(out[moving == 0] == 0.0)


@pytest.mark.parametrize("backend", ["numpy", "numba"])
def test_a_bar_ending_at_a_knot_trips_no_guard_with_a_reconstruction(backend):
    """S3 small (cubic, 2 particles per cell, spline, consistent mass, rk4,
    the default cfl; the variant test_compiled_loop compiles): the last
    function, which the bar covers over one cell of its support, is a
    tail weighed as the open knot vector's first function (r = 0.25 from
    the particles' own sums), so the guard lumps nothing and the run equals
    the one without the guard. With weight 1 on tails (the plain limit) it
    lumped that dof (r = 2.25) and the error grew 400-fold."""
    b = get_benchmark("traction-bar", "small")
    scene = b.scene(8, 3, 2, t_end=0.04)
    runs = [simulate(scene, Method(scheme="rk4", mass="consistent", reconstruction="spline",
                                   backend=backend, frequency_guard=g)) for g in (1.0, 0.0)]
    assert runs[0].counts["steps"] >= 10
    assert np.array_equal(runs[0].particles.u, runs[1].particles.u)


def test_without_a_reconstruction_a_tail_takes_the_plain_limit():
    """A cubic bar ending at an interior knot, 2 particles per cell, fixed
    at its base (the sliver column's top, S3's end). With particle
    quadrature its end mode is faster than the Gauss Lambda the step is
    built on (omega dt_crit / 2 = 1.64: the particles over-sample the end
    function's steep end), so the guard weighs that tail with the plain
    limit and lumps its row fully (r = 2.9); with a reconstruction the step's
    system is Gauss-integrated, the tail is weighed as the open knot
    vector's first function and nothing is lumped (r = 0.32)
    (timestep.covered_parameters). With the tail weight without a
    reconstruction the end row stayed unlumped and a column whose top cut
    its end cell failed (tests/hard/test_near_empty, J <= 0 at step 138)."""
    import scipy.linalg as sl

    from skfem_mpm import Body, Fixed, LinearElastic, Particles, Scene
    from skfem_mpm.kernels.step_size import guard_limit
    from skfem_mpm.quadrature import transfer_matrices
    from skfem_mpm.solve.state import prepare
    from skfem_mpm.solve.timestep import critical_time_step, fast_dof_limit, lumping_fraction

    grid = SplineGrid.line(0.0, 1.5, 12, 3)
    parts = Particles.seed(grid, 2, 1.0, region=((0.0, 1.0),))  # ends at knot 8: dof 10's tail
    scene = Scene(grid, Body(parts, LinearElastic(100.0)), 0.1, effects=[Fixed("left")])
    N, G = transfer_matrices(grid, parts.x)
    m = parts.m
    M = (N.T @ N.multiply(m[:, None])).toarray()
    K = (G[0].T @ G[0].multiply(m[:, None])).toarray()
    seen = np.flatnonzero(np.diag(M) > 0)[1:]  # dof 0 fixed
    top = sl.eigh(K[np.ix_(seen, seen)], M[np.ix_(seen, seen)], eigvals_only=True)[-1]
    assert np.sqrt(top) * critical_time_step(grid, 1.0, "consistent") / 2 > 1.6
    sums = (np.diag(K).copy(), np.diag(M).copy(), np.asarray(N.T @ m).ravel())
    fractions = {}
    for reconstruction in ("none", "spline"):
        state = prepare(scene, Method(mass="consistent", reconstruction=reconstruction,
                                      backend="numpy"))
        limit = guard_limit(fast_dof_limit(3, state.method.scheme), state.dt,
                            state.wave_speed_now)
        k = state.guard_stiffness(*sums, limit)
        fractions[reconstruction] = np.where(sums[1] > 0, lumping_fraction(
            k / (limit * np.maximum(sums[1], 1e-300))), 0.0)
    assert fractions["none"][10] == 1.0 and np.count_nonzero(fractions["none"]) == 1
    assert np.all(fractions["spline"] == 0.0)
