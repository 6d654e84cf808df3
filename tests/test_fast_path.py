"""The compiled fast path agrees with the NumPy reference to 1e-12."""
import numpy as np
import pytest

from skfem_mpm import (Body, Fixed, Gravity, LinearElastic, Method, NeoHookean, Particles,
                       Scene, SimulationError, SplineGrid, Traction, simulate)
from skfem_mpm.benchmarks import get_benchmark


def both(scene, **method):
    ref = simulate(scene, Method(backend="numpy", **method), save_every=7)
    fast = simulate(scene, Method(backend="numba", **method), save_every=7)
    assert fast.path.startswith("fast") and ref.path.startswith("reference")
    return ref, fast


def close(a, b, tol=1e-12):
    scale = max(np.abs(a).max(), 1e-300)
    return np.abs(a - b).max() <= tol * scale


@pytest.mark.parametrize("scheme", ("usl", "musl", "cd"))
@pytest.mark.parametrize("degree", (1, 2, 3))
def test_1d_soil_column_with_gravity_and_top_load(scheme, degree):
    b = get_benchmark("soil-column", "small", p0=5e3)
    ref, fast = both(b.scene(12, degree, 2), scheme=scheme)
    for k in ("u", "v", "stress"):
        assert close(ref.history[k], fast.history[k]), k
    assert close(ref.energies["external_work"], fast.energies["external_work"])
    r_ref = ref.reactions[-1]["Fixed('left', component=None)"]
    r_fast = fast.reactions[-1]["Fixed('left', component=None)"]
    assert close(r_ref, r_fast)


def block_grid(kind, degree):
    if kind == "uniform":
        return SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (9, 8), degree)
    return SplineGrid((np.array([0.0, 0.1, 0.35, 0.5, 0.8, 1.0]),
                       np.array([0.0, 0.2, 0.3, 0.6, 0.75, 1.0])), degree)


@pytest.mark.parametrize("scheme", ("usl", "musl", "cd"))
@pytest.mark.parametrize("degree", (1, 2, 3))
@pytest.mark.parametrize("kind", ("nonuniform", "uniform"))
def test_2d_block(kind, degree, scheme):
    """Non-uniform grids take the extraction path everywhere; uniform ones
    the closed-form weights (and, for p = 2, the unrolled interior
    stencil). The block spans interior and boundary cells."""
    grid = block_grid(kind, degree)
    region = ((0.12, 0.78), (0.05, 0.7)) if kind == "nonuniform" else ((0.05, 0.9), (0.03, 0.8))
    parts = Particles.seed(grid, 2, 2.0, region=region,
                           velocity=lambda X: np.column_stack((0.1 * X[:, 1], -0.05 * X[:, 0])))
    scene = Scene(grid, Body(parts, LinearElastic(1e3, 0.3)), 0.05,
                  effects=[Gravity((0.0, -9.81)), Fixed("bottom"), Fixed("left", 0)])
    ref, fast = both(scene, scheme=scheme)
    for k in ("u", "v", "stress"):
        assert close(ref.history[k], fast.history[k]), k


def test_finite_strain_material_through_the_velocity_gradient():
    b = get_benchmark("axis-aligned-2d")
    ref, fast = both(b.scene(4, 2, 2), scheme="usl")
    assert close(ref.particles.F, fast.particles.F)
    assert close(ref.history["u"], fast.history["u"])


def test_side_traction_and_removal_on_the_fast_path():
    b = get_benchmark("traction-bar", "large")
    ref, fast = both(b.scene(8, 2, 2), scheme="musl")
    assert close(ref.history["u"], fast.history["u"])
    grid = SplineGrid.rectangle((0, 1), (0, 1), 4, 2)
    parts = Particles.seed(grid, 2, 1.0, region=((0.7, 0.95), (0.4, 0.6)),
                           velocity=np.array([5.0, 0.0]))
    scene = Scene(grid, Body(parts, LinearElastic(1e2, 0.3)), 0.05)
    ref, fast = both(scene, on_exit="remove")
    assert ref.counts["removed"] == fast.counts["removed"] > 0
    assert close(ref.particles.x, fast.particles.x)
    with pytest.raises(SimulationError, match="left the grid"):
        simulate(scene, Method(backend="numba"))


def test_fast_path_failure_keeps_the_last_good_state():
    b = get_benchmark("vibrating-string", "small", L=1.0)
    scene = b.scene(8, 2, 2, t_end=100 * 2 * np.pi / b.omega)
    dt = 10 * simulate(b.scene(8, 2, 2), Method()).dt_crit
    with pytest.raises(SimulationError) as info:
        simulate(scene, Method(dt=dt, allow_unstable=True, scheme="usl", backend="numba"))
    p = info.value.result.particles
    assert all(np.all(np.isfinite(a)) for a in (p.x, p.v, p.stress, p.V))


@pytest.mark.parametrize("solver", ("cg", "direct", "auto", "cg-lumped-preconditioner"))
def test_consistent_mass_fast_path_matches_reference(solver, monkeypatch):
    from skfem_mpm.solve.stencil_system import StencilSystem

    if solver == "cg-lumped-preconditioner":
        monkeypatch.setattr(StencilSystem, "preconditioner", "lumped")
        solver = "cg"
    b = get_benchmark("vibrating-plate-2d", "small")
    scene = b.scene(6, 2, 2)
    ref = simulate(scene, Method(mass="consistent", backend="numpy", mass_solver="direct"))
    fast = simulate(scene, Method(mass="consistent", mass_solver=solver))
    assert fast.path.startswith("fast")
    assert close(ref.particles.u, fast.particles.u, 1e-11)
    assert close(ref.particles.stress, fast.particles.stress, 1e-11)


def test_consistent_mass_kernel_equals_transfer_matrices():
    from skfem_mpm.kernels.mpm import Kernels
    from skfem_mpm.solve.steps import Transfer
    from skfem_mpm.solve.timing import PhaseTimer

    for grid in (SplineGrid.line(0, 1, 7, 2),
                 SplineGrid((np.array([0, 0.3, 0.5, 1.0]), np.linspace(0, 1, 5)), 3),
                 SplineGrid.rectangle((0, 1), (0, 2), (7, 8), 2)):  # unrolled interior cells
        p = Particles.seed(grid, 3, 1.0, layout="random", seed=2)
        M, K = Kernels(grid, parallel=False).consistent_mass(p)
        tr = Transfer(grid, p.x, PhaseTimer())
        assert abs(M - tr.consistent_mass(p.m)).max() < 1e-15
        assert np.abs(K - sum(G.multiply(G).T @ p.m for G in tr.grad_N)).max() < 1e-12


_P3_NONUNIFORM = SplineGrid((np.array([0, .2, .5, .6, 1.0]), np.array([0, .3, 1.0])), 3)


# 2D cubic: the serial copies (the same thread blocks in a loop, the same
# bits), whose parallel kernels only the slow tier compiles (see
# test_kernels_generic.PARALLEL_DEFAULT)
@pytest.mark.parametrize("grid, parallel", [
    (SplineGrid.line(0, 1, 40, 2), True), (SplineGrid.line(0, 1, 30, 3), True),
    (SplineGrid.rectangle((0, 1), (0, 2), (12, 10), 2), True), (_P3_NONUNIFORM, False),
    pytest.param(_P3_NONUNIFORM, True, marks=pytest.mark.slow(
        reason="the 2D cubic parallel transfers compile only here; the default tier runs "
               "their serial copies"))],
    ids=["1d-p2", "1d-p3", "2d-p2", "2d-p3-nonuniform-serial", "2d-p3-nonuniform"])
def test_scatter_kernels_in_any_particle_order(grid, parallel):
    """p2g, the MUSL re-scatter and the consistent mass equal the
    transfer-matrix products for sorted, shuffled, fewer particles and
    particles in one half of the grid then the other, called in turn on the
    same kernels: the register runs (1D) and the per-thread touched ranges
    hold for any order, and no call leaves anything behind for the next."""
    from skfem_mpm.kernels.mpm import Kernels
    from skfem_mpm.solve.steps import Transfer
    from skfem_mpm.solve.timing import PhaseTimer

    rng = np.random.default_rng(4)
    seeded = Particles.seed(grid, 3, 1.0)
    dim = grid.dim
    seeded.v = rng.standard_normal((seeded.n, dim))
    S = rng.standard_normal((seeded.n, dim, dim))
    seeded.stress = S + S.transpose(0, 2, 1)  # the kernels read a symmetric stress
    k = Kernels(grid, parallel=parallel)
    grid_a = rng.standard_normal((grid.ndofs, dim))
    order = rng.permutation(seeded.n)
    left = seeded.x[:, 0] < 0.5
    for p in (seeded, seeded.subset(order), seeded.subset(order[: seeded.n // 3]),
              seeded.subset(np.flatnonzero(left)), seeded.subset(np.flatnonzero(~left)), seeded):
        tr = Transfer(grid, p.x, PhaseTimer())
        M, K = k.consistent_mass(p)
        assert close(M.toarray(), tr.consistent_mass(p.m).toarray())
        assert close(K, sum(G.multiply(G).T @ p.m for G in tr.grad_N))
        fext = rng.standard_normal((p.n, dim))
        mass, momentum, force = k.p2g(p, fext)
        assert close(mass, tr.to_grid(p.m))
        assert close(momentum, tr.to_grid(p.m[:, None] * p.v))
        assert close(force, tr.to_grid(fext) - tr.divergence_to_grid(p.V[:, None, None] * p.stress))
        v_new = np.empty_like(p.v)
        momentum_new = k.g2p2g(p, grid_a, 0.1, v_new)
        assert close(v_new, p.v + 0.1 * tr.to_particles(grid_a))
        assert close(momentum_new, tr.to_grid(p.m[:, None] * v_new))


def _dense_bands(bands):
    n, w = bands.shape
    A = np.zeros((n, n))
    for i in range(n):
        for d in range(min(w, i + 1)):
            A[i, i - d] = A[i - d, i] = bands[i, d]
    return A


@pytest.mark.parametrize("grid", [SplineGrid.line(0, 1, 9, 2),
                                  SplineGrid.rectangle((0, 1), (0, 2), (7, 9), 2),
                                  SplineGrid((np.array([0, .2, .5, .6, 1.0]),
                                              np.array([0, .3, 1.0])), 3)],
                         ids=["1d-p2", "2d-p2", "2d-p3-nonuniform"])
def test_kronecker_preconditioner(grid):
    """The axis factors give the Gauss mass matrix (scikit-fem assembly);
    with the Gauss row sums as lumped mass the preconditioner is its exact
    inverse; on a subset of dofs it is symmetric positive definite."""
    from skfem import BilinearForm, asm

    from skfem_mpm.kernels.kronecker import KroneckerData, apply_kronecker, axis_mass_bands
    from skfem_mpm.kernels.mpm import Kernels
    from skfem_mpm.kernels.serial import serial

    apply_kronecker = serial(apply_kronecker)

    @BilinearForm
    def mass(u, v, w):
        return u * v

    gauss = asm(mass, grid.basis()).toarray()
    pairs = [axis_mass_bands(grid, axis) for axis in range(grid.dim)]
    bands, sums = [b for b, _ in pairs], [s for _, s in pairs]
    kron = _dense_bands(bands[0])
    if grid.dim == 2:
        kron = np.kron(_dense_bands(bands[1]), kron)
    assert np.abs(kron - gauss).max() < 1e-14 * np.abs(gauss).max()
    geometry = Kernels(grid, parallel=False).stencil_geometry
    rows = np.arange(grid.ndofs)
    data = KroneckerData(bands, sums, geometry, rows, 3.0 * gauss.sum(axis=1))
    r = np.random.default_rng(0).random((grid.ndofs, 3))
    z = np.empty_like(r)
    apply_kronecker(*data.args(3, 2), r, z)
    assert np.abs(3.0 * gauss @ z - r).max() < 1e-12
    subset = rows[rows % 3 != 0]
    data = KroneckerData(bands, sums, geometry, subset, 3.0 * gauss.sum(axis=1))
    P = np.empty((subset.size, subset.size))
    for j in range(subset.size):
        e = np.zeros((subset.size, 1))
        e[j] = 1.0
        out = np.empty_like(e)
        apply_kronecker(*data.args(1, 2), e, out)
        P[:, j] = out[:, 0]
    assert np.abs(P - P.T).max() < 1e-12 * np.abs(P).max()
    assert np.linalg.eigvalsh(P).min() > 0


# The kernels the solver tests build or call directly are the serial copies
# (Kernels(grid, parallel=False), kernels.serial.serial: the same thread
# blocks in a loop, the same bits; what a run below SERIAL_BELOW particles
# calls): the parallel consistent-mass CG, Kronecker and fringe kernels
# compile for about a minute of CPU and no default-tier run calls them
# (test_scatter_kernels_in_any_particle_order keeps the parallel transfers
# and consistent mass; tests/test_kernels_generic.py compares the two kinds).
def _block_system(cells=32):
    """The consistent mass of the 2D benchmark's particle block on a
    ``cells`` x ``cells`` grid: (kernels, stencil, lumped mass, constraints)."""
    from skfem_mpm.bench import scene_2d
    from skfem_mpm.kernels.mpm import Kernels
    from skfem_mpm.solve.grid_system import Constraints

    scene, _ = scene_2d(cells=cells, steps=1)
    p = scene.bodies[0].particles
    k = Kernels(scene.grid, parallel=False)
    mass = k.p2g(p, None)[0].copy()
    stencil, _ = k.consistent_stencil(p)
    constraints = Constraints(scene.grid, [e for e in scene.effects if type(e).__name__ == "Fixed"])
    return k, stencil.copy(), mass, constraints


def _edge_lumping(mass):
    """Fast-row lumping fractions on the block's edge (the frequency guard
    lumps the dofs of partly filled supports: theta = 1 - m_k / (0.1 max m)
    where positive, the block's corners). Without them the block's particle
    mass is a Kronecker product, which the fitted Kronecker preconditioner
    inverts exactly, and the fringe correction has nothing to correct."""
    return np.clip(1.0 - mass / (0.1 * mass.max()), 0.0, 1.0) * (mass > 0)


def _preconditioned_system(k, stencil, mass, constraints, fast):
    """(P^-1 A, A) dense on the first constraint group's free dofs, P the
    Kronecker preconditioner StencilSystem fits to A."""
    from skfem_mpm.kernels.kronecker import apply_kronecker
    from skfem_mpm.kernels.serial import serial
    from skfem_mpm.solve.stencil_system import StencilSystem

    apply_kronecker = serial(apply_kronecker)
    system = StencilSystem(k, stencil, mass, constraints, fast, {})
    A, cols, _, _, _, kron, _, _ = system._compact(next(iter(system.groups.values())))
    n = A.shape[0]
    dense = np.zeros((n, n))
    np.add.at(dense, (np.repeat(np.arange(n), A.shape[1]), cols.ravel()), A.ravel())
    inverse = np.empty((n, n))
    apply_kronecker(*kron.args(n, 2), np.eye(n), inverse)
    return inverse @ dense, dense


def _random_line_system(seed, fast_seed):
    """(grid, kernels, stencil, lumped mass, fast-row fractions in [0, 0.6])
    of 3 randomly placed particles per cell on 12 quadratic cells."""
    from skfem_mpm.kernels.mpm import Kernels

    grid = SplineGrid.line(0.0, 1.0, 12, 2)
    particles = Particles.seed(grid, 3, 1.0, layout="random", seed=seed)
    k = Kernels(grid, parallel=False)
    mass = k.p2g(particles, None)[0].copy()
    stencil, _ = k.consistent_stencil(particles)
    return grid, k, stencil, mass, np.random.default_rng(fast_seed).uniform(0.0, 0.6, mass.size)


def test_fitted_kronecker_is_exact_where_the_mass_is_a_kronecker_product():
    """The factors are the axis marginals of the free-dof matrix A, so P = A
    (a) in 1D for any particle layout and fast-row lumping (P is A's banded
    factorisation) and (b) on the 2D block of uniformly seeded particles
    without lumping (its particle mass is M_y (x) M_x); (c) with the
    block's corners lumped, P^-1 A is not I, but all its eigenvalues other
    than the corners' four lie in [0.7, 1.2]."""
    from skfem_mpm.solve.grid_system import Constraints

    grid, k, stencil, mass, fast = _random_line_system(4, 6)
    constraints = Constraints(grid, [Fixed("left")])
    product, _ = _preconditioned_system(k, stencil.copy(), mass, constraints, fast)
    assert np.abs(product - np.eye(len(product))).max() < 1e-12
    k, stencil, mass, constraints = _block_system(cells=12)
    product, _ = _preconditioned_system(k, stencil.copy(), mass, constraints,
                                        np.zeros(mass.size))
    assert np.abs(product - np.eye(len(product))).max() < 1e-12
    product, _ = _preconditioned_system(k, stencil.copy(), mass, constraints,
                                        _edge_lumping(mass))
    eigenvalues = np.sort(np.linalg.eigvals(product).real)
    lumped = np.count_nonzero(_edge_lumping(mass))
    assert lumped == 4
    assert 0.7 < eigenvalues[0] and eigenvalues[-lumped - 1] < 1.2


def test_a_1d_consistent_solve_is_direct_whatever_the_warm_start():
    """In 1D P = A (above), so StencilSystem solves directly, x = P^-1 b: one
    application for both right-hand sides, the solution to round-off
    (relative residual <= 1e-14, where CG stops at 1e-13) for random
    particles, fast-row lumping and a nonzero prescribed value (its fixed
    column moved to the right-hand side), and the same bits from a wrong
    warm start as from none."""
    from skfem_mpm import Prescribed
    from skfem_mpm.solve.grid_system import Constraints
    from skfem_mpm.solve.stencil_system import StencilSystem

    grid, k, stencil, mass, fast = _random_line_system(5, 7)
    constraints = Constraints(grid, [Fixed("left"), Prescribed("right", 0, lambda t: 0.3)])
    values = constraints.values(0.0)
    rng = np.random.default_rng(8)
    force, momentum = rng.normal(size=(mass.size, 1)), rng.normal(size=(mass.size, 1))
    solutions = []
    for warm in ({}, {"acceleration": rng.normal(size=(mass.size, 1)),
                      "velocity": rng.normal(size=(mass.size, 1))}):
        system = StencilSystem(k, stencil.copy(), mass, constraints, fast, warm)
        solutions.append(system.solve_many([(force, None, "acceleration"),
                                            (momentum, values, "velocity")]))
        assert system.iterations == 1
    for a, b in zip(*solutions):
        assert np.array_equal(a, b)
    A, cols, F, fcols, *_ = system._compact(next(iter(system.groups.values())), True)
    rows = next(iter(system.groups.values()))[1]
    for x, rhs, fixed in zip(solutions[0], (force, momentum), (None, values)):
        fixed_part = np.zeros(rows.size) if fixed is None else (F * fixed[fcols, 0]).sum(axis=1)
        residual = (A * x[rows][cols, 0]).sum(axis=1) + fixed_part - rhs[rows, 0]
        assert np.abs(residual).max() <= 1e-14 * np.abs(rhs[rows, 0]).max()
        if fixed is not None:
            assert np.array_equal(x[constraints.mask[:, 0]], fixed[constraints.mask[:, 0]])


@pytest.mark.parametrize("rows", [300, 2100])
def test_kronecker_marginals_in_blocks_and_in_one_agree(rows):
    """fit_kronecker sums its axis marginals in kronecker.FIT_BLOCKS blocks
    in parallel from FIT_BLOCKS_FROM rows on and in one block below: on
    the same ELL rows (2D slots, p = 2, some diagonal rows) both give the
    bands, axis sums and row sums to round-off, so each size's tests check
    the other path too."""
    from skfem_mpm.kernels.kronecker import _axis_marginals, _one_block_marginals
    from skfem_mpm.kernels.serial import serial

    _axis_marginals = serial(_axis_marginals)  # (the same blocks in a loop)

    p, n = 2, 40
    rng = np.random.default_rng(rows)
    A = rng.random((rows, (2 * p + 1) ** 2))
    coords = np.column_stack((rng.integers(0, n, rows), rng.integers(0, n, rows),
                              np.zeros(rows, dtype=np.int64)))
    coords[rng.random(rows) < 0.05] = -1  # diagonal rows: a row sum only
    got = []
    for marginals in (_axis_marginals, _one_block_marginals):
        bands, sums = np.zeros((3, n, p + 1)), np.zeros((3, n))
        row_sums = marginals(A, coords, p, bands, sums)
        got.append((bands, sums, row_sums))
    for a, b in zip(*got):
        assert np.abs(a - b).max() <= 1e-13 * np.abs(a).max()
    assert np.abs(got[0][2] - A.sum(axis=1)).max() <= 1e-13 * A.sum(axis=1).max()


def test_kronecker_preconditioner_cuts_cg_iterations():
    """On a block of particles (the 2D benchmark's layout, 32 x 32 cells)
    the Kronecker preconditioner needs far fewer CG iterations than the
    lumped-mass one, and its fringe correction far fewer again, all to the
    same solution."""
    from skfem_mpm.solve.stencil_system import StencilSystem

    k, stencil, mass, constraints = _block_system()
    rhs = np.random.default_rng(1).standard_normal((mass.size, 2)) * mass[:, None]
    solutions, iterations = [], []
    for pre, layers in (("lumped", 0), ("kronecker", 0), ("kronecker", 3)):
        system = StencilSystem(k, stencil.copy(), mass, constraints, _edge_lumping(mass), {})
        system.preconditioner = pre
        system.FRINGE_LAYERS = layers
        system.FRINGE_FROM = 0  # from the first solve
        solutions.append(system.solve(rhs, np.zeros_like(rhs), "velocity"))
        iterations.append(system.iterations)
    print("CG iterations, lumped / Kronecker / Kronecker + fringe:", iterations)
    assert iterations[1] < 0.3 * iterations[0]
    assert iterations[2] <= 0.5 * iterations[1]
    for other in solutions[1:]:
        assert np.abs(solutions[0] - other).max() < 1e-9 * np.abs(solutions[0]).max()


def test_fringe_rows_are_the_layers_next_to_non_free_dofs():
    from skfem_mpm.kernels.fringe import fringe_rows

    nbx, nby = 12, 10
    free = np.zeros((nby, nbx), dtype=bool)
    free[1:9, 2:11] = True
    free[5, 6] = False  # a hole
    rows = np.flatnonzero(free.ravel())
    for layers in (1, 2):
        got = np.zeros(free.size, dtype=bool)
        got[rows[fringe_rows(rows, (2, nbx, nby, 2), layers)]] = True
        expected = np.zeros_like(free)
        for b, a in zip(*np.nonzero(free)):  # brute force: a non-free dof within reach
            window = np.ones((nby + 2 * layers, nbx + 2 * layers), dtype=bool)
            window[layers:-layers, layers:-layers] = free
            near = window[b:b + 2 * layers + 1, a:a + 2 * layers + 1]
            expected[b, a] = not near.all()
        assert np.array_equal(got.reshape(free.shape), expected)
    line = np.arange(3, 20)  # 1D: the ends
    assert np.array_equal(line[fringe_rows(line, (2, 25, 1, 1), 2)], [3, 4, 18, 19])
    for bad in (-1, 1.5):
        with pytest.raises(ValueError, match="layers must be a non-negative integer"):
            fringe_rows(line, (2, 25, 1, 1), bad)


def _fringe_block(cells=12, layers=2):
    """The 12 x 12 block's free-dof system with edge lumping: its ELL rows
    A, cols, Kronecker preconditioner, dense M and the fringe factor."""
    from skfem_mpm.kernels.fringe import FringeFactor, FringePattern
    from skfem_mpm.solve.stencil_system import StencilSystem

    k, stencil, mass, constraints = _block_system(cells=cells)
    system = StencilSystem(k, stencil, mass, constraints, _edge_lumping(mass), {})
    group = next(iter(system.groups.values()))
    A, cols, _, _, _, kron, _, _ = system._compact(group)
    n = A.shape[0]
    M = np.zeros((n, n))
    np.add.at(M, (np.repeat(np.arange(n), A.shape[1]), cols.ravel()), A.ravel())
    pattern = FringePattern(group[1], cols, k.stencil_geometry, layers)
    return A, cols, kron, M, FringeFactor(pattern.block_values(A), pattern)


def test_fringe_correction_matches_its_formula():
    """The compiled fringe solve is M_FF^-1 (dense NumPy reference) and the
    corrected preconditioner is z1 = R^T M_FF^-1 R r, z2 = z1 + P^-1 (r -
    M z1), z = z2 + R^T M_FF^-1 R (r - M z2), symmetric positive definite,
    with a far smaller condition number of B M than of P^-1 M (the fringe
    holds the outliers of P^-1 M)."""
    from skfem_mpm.kernels.fringe import apply_corrected, fringe_solve
    from skfem_mpm.kernels.kronecker import apply_kronecker
    from skfem_mpm.kernels.serial import serial

    apply_corrected, fringe_solve, apply_kronecker = (
        serial(apply_corrected), serial(fringe_solve), serial(apply_kronecker))

    A, cols, kron, M, factor = _fringe_block()
    n = A.shape[0]
    F = factor.pattern.fringe
    assert 0 < F.size < n
    rng = np.random.default_rng(3)
    nc = 4
    rf = rng.standard_normal((F.size, nc))
    fr = factor.args(nc)
    zf = np.empty_like(rf)
    fringe_solve(*factor.arrays()[6:], fr[-2], rf, zf)
    MFF = M[np.ix_(F, F)]
    assert np.abs(MFF @ zf - rf).max() < 1e-12 * np.abs(rf).max()

    def kronecker(r):
        out = np.empty_like(r)
        apply_kronecker(*kron.args(r.shape[1], 2), np.ascontiguousarray(r), out)
        return out

    def fringe(r):
        z = np.zeros_like(r)
        z[F] = np.linalg.solve(MFF, r[F])
        return z

    r = rng.standard_normal((n, nc))
    z1 = fringe(r)
    z2 = z1 + kronecker(r - M @ z1)
    expected = z2 + fringe(r - M @ z2)
    z = np.empty_like(r)
    apply_corrected(A, cols, *kron.args(nc, 2), *fr, r, z, np.empty_like(r))
    assert np.abs(z - expected).max() < 1e-10 * np.abs(expected).max()
    B = np.empty((n, n))
    for j in range(0, n, nc):
        e = np.zeros((n, nc))
        m = min(nc, n - j)
        e[j + np.arange(m), np.arange(m)] = 1.0
        apply_corrected(A, cols, *kron.args(nc, 2), *fr, e, z, np.empty_like(e))
        B[:, j:j + m] = z[:, :m]
    assert np.abs(B - B.T).max() < 1e-10 * np.abs(B).max()
    corrected = np.linalg.eigvals(B @ M).real
    plain = np.linalg.eigvals(kronecker(np.eye(n)) @ M).real
    print("eigenvalues of P^-1 M in [%.3f, %.3f], of B M in [%.3f, %.3f]"
          % (plain.min(), plain.max(), corrected.min(), corrected.max()))
    assert corrected.min() > 0
    assert corrected.max() / corrected.min() < 0.5 * plain.max() / plain.min()


def test_fringe_solve_gives_each_column_the_same_bits_in_any_company():
    """fringe_solve (rows of L and U, sums in registers) solves M_FF x = b,
    and a column's bits do not depend on the columns solved with it (one to
    four, four or two lanes) nor on one or two thread blocks."""
    from skfem_mpm.kernels.fringe import fringe_solve
    from skfem_mpm.kernels.serial import serial

    fringe_solve = serial(fringe_solve)  # (the same thread blocks in a loop)
    _, _, _, M, factor = _fringe_block()
    F = factor.pattern.fringe
    MFF = M[np.ix_(F, F)]
    b = np.random.default_rng(4).standard_normal((F.size, 4))
    alone = []
    for c in range(4):
        fr = factor.args(1)
        x = np.empty((F.size, 1))
        fringe_solve(*factor.arrays()[6:], fr[-2], np.ascontiguousarray(b[:, c:c + 1]), x)
        alone.append(x[:, 0])
    assert np.abs(MFF @ np.array(alone).T - b).max() < 1e-12 * np.abs(b).max()
    for nc in (2, 3, 4):
        for threads in (1, 2):
            fr = factor.args(nc)
            x = np.empty((F.size, nc))
            fringe_solve(*factor.arrays()[6:], fr[-2], np.ascontiguousarray(b[:, :nc]), x, threads)
            for c in range(nc):
                assert np.array_equal(x[:, c], alone[c]), (nc, threads, c)


def test_fringe_residuals_skip_only_zero_terms_in_slot_order():
    """The correction's residuals read only the entries that can be nonzero
    (FringePattern: the fringe rows' free columns, the near rows' fringe
    columns), and give the bits of the whole ELL rows' products in slot
    order: r - M z on the fringe rows, r - M z1 (z1 zero off the fringe) on
    exactly the rows where M z1 can be nonzero."""
    from skfem_mpm.kernels.fringe import _residual_rows

    A, cols, _, M, factor = _fringe_block()
    pattern = factor.pattern
    n, ns = A.shape
    F, near = pattern.fringe, pattern.near
    assert np.array_equal(near, np.flatnonzero(np.isin(cols, F).any(axis=1)))
    assert pattern.fringe_entries.shape[0] < F.size * ns
    assert pattern.near_entries.shape[0] < near.size * ns

    def whole(which):  # every slot of the rows, in order
        ptr = np.arange(which.size + 1, dtype=np.int64) * ns
        slots = np.broadcast_to(np.arange(ns), (which.size, ns))
        return ptr, np.stack((slots.ravel(), cols[which].ravel()), axis=1).astype(np.int64)

    rng = np.random.default_rng(5)
    for nc in (4, 2):  # four running sums, or one column at a time
        r, z = rng.standard_normal((n, nc)), rng.standard_normal((n, nc))
        z1 = np.zeros((n, nc))
        z1[F] = rng.standard_normal((F.size, nc))
        for which, ptr, entries, vector, reads in (
                (F, pattern.fringe_ptr, pattern.fringe_entries, z, z),
                (near, pattern.near_ptr, pattern.near_entries, z1, np.ascontiguousarray(z1[F]))):
            got, expected = np.empty((which.size, nc)), np.empty((which.size, nc))
            _residual_rows(A, which, ptr, entries, r, reads, got)
            _residual_rows(A, which, *whole(which), r, vector, expected)
            assert np.array_equal(got, expected)
            dense = (r - M @ vector)[which]
            assert np.abs(got - dense).max() < 1e-12 * np.abs(dense).max()
        off = np.setdiff1d(np.arange(n), near)
        assert np.array_equal((M @ z1)[off], np.zeros((off.size, nc)))
    # exact products whose sums round by their order: subtracted in slot order
    big = rng.choice([2.0 ** 53, -(2.0 ** 53), 1.0, 3.0], size=A.shape)
    ones = np.ones((n, 4))
    got = np.empty((F.size, 4))
    _residual_rows(big, F, pattern.fringe_ptr, pattern.fringe_entries, ones, ones, got)
    for k, i in enumerate(F):
        expected = 1.0
        for e in range(pattern.fringe_ptr[k], pattern.fringe_ptr[k + 1]):
            expected = expected - big[i, pattern.fringe_entries[e, 0]]
        assert np.all(got[k] == expected), k


@pytest.mark.parametrize("band", (1, 2, 3, 4))
def test_kronecker_banded_solves_of_any_band(band):
    """apply_kronecker with the box's rows in order and unit scaling is
    (M_y (x) M_x)^-1, M = L L^T of the banded factors (1 / L_ii in column
    0, L_i,i-d in column d), for bands 1-3 (written out) and 4 (the
    one-term-at-a-time loop), one to four columns."""
    from skfem_mpm.kernels.kronecker import apply_kronecker
    from skfem_mpm.kernels.serial import serial

    apply_kronecker = serial(apply_kronecker)
    rng = np.random.default_rng(band)
    ny, nx = 6, 9

    def factor(n):
        L = np.concatenate([rng.uniform(0.5, 2.0, (n, 1)), rng.uniform(-0.3, 0.3, (n, band))],
                           axis=1)
        dense = np.diag(1.0 / L[:, 0])
        for d in range(1, band + 1):
            dense += np.diag(L[d:, d], -d)
        return L, dense @ dense.T

    (Lx, Mx), (Ly, My) = factor(nx), factor(ny)
    local = np.arange(ny * nx, dtype=np.int64)
    for nc in (1, 2, 3, 4):
        r = rng.standard_normal((ny * nx, nc))
        z = np.empty_like(r)
        apply_kronecker(Lx, Ly, local, np.ones(ny * nx), np.empty((ny, nx, nc)), 2, r, z)
        expected = np.linalg.solve(np.kron(My, Mx), r)
        assert np.abs(z - expected).max() < 1e-10 * np.abs(expected).max(), nc


def test_stale_fringe_factors_are_replaced_when_cg_fails():
    """Factors kept from an earlier step that no longer fit (here: of -M_FF,
    which makes the preconditioner indefinite) do not end the solve above
    its tolerance: CG retries with the current block's factors, which are
    then kept. A CG that cannot reach its tolerance raises."""
    from skfem_mpm.errors import InvalidState
    from skfem_mpm.solve.stencil_system import StencilSystem

    k, stencil, mass, constraints = _block_system(cells=16)
    rhs = np.random.default_rng(2).standard_normal((mass.size, 2)) * mass[:, None]
    zeros = np.zeros_like(rhs)
    reference = StencilSystem(k, stencil.copy(), mass, constraints, _edge_lumping(mass), {})
    expected = reference.solve(rhs, zeros, "velocity")
    warm = {"fringe0_on": np.array([1])}  # the correction from the first solve on
    StencilSystem(k, stencil.copy(), mass, constraints, _edge_lumping(mass), warm).solve(
        rhs, zeros, "velocity")
    good = warm["fringe0_block"].copy()
    warm["fringe0_block"] = -good
    system = StencilSystem(k, stencil.copy(), mass, constraints, _edge_lumping(mass), warm)
    system.max_iterations = 20  # the current block's factors need 5; the stale ones 39
    warm.pop("velocity", None)
    got = system.solve(rhs, zeros, "velocity")
    assert np.abs(got - expected).max() < 1e-9 * np.abs(expected).max()
    assert np.array_equal(warm["fringe0_block"], good)
    failing = StencilSystem(k, stencil.copy(), mass, constraints, _edge_lumping(mass), {})
    failing.preconditioner = "lumped"
    failing.max_iterations = 3
    with pytest.raises(InvalidState, match="stopped above its tolerance"):
        failing.solve(rhs, zeros, "velocity")


@pytest.mark.parametrize("min_rows", [0, 325])
def test_fringe_correction_turns_on_where_kronecker_alone_iterates_long(min_rows):
    """A CG run with the Kronecker preconditioner alone that takes at least
    FRINGE_FROM iterations turns the fringe correction on for the next
    solves (through the warm data), on a group of at least FRINGE_MIN_ROWS
    free dofs (the block has 324); fewer iterations leave it off."""
    from skfem_mpm.solve.stencil_system import StencilSystem

    k, stencil, mass, constraints = _block_system()
    rhs = np.random.default_rng(5).standard_normal((mass.size, 2)) * mass[:, None]
    zeros = np.zeros_like(rhs)
    for threshold, switched in ((100, False), (StencilSystem.FRINGE_FROM, min_rows == 0)):
        warm, counts = {}, []
        for _ in range(2):
            system = StencilSystem(k, stencil.copy(), mass, constraints, _edge_lumping(mass), warm)
            system.FRINGE_FROM = threshold
            system.FRINGE_MIN_ROWS = min_rows
            system.BAND_MAX = 0  # (the band factor would take this narrow block first)
            system.solve(rhs, zeros, "acceleration")  # cold both times (no warm start kept)
            counts.append(system.iterations)
        assert ("fringe0_on" in warm) == switched
        assert (counts[1] <= 0.5 * counts[0]) == switched, counts


def _dense_free_solve(k, stencil, mass, constraints, rhs, values):
    """Reference for StencilSystem.solve with no fast rows: a dense solve on
    each component's free dofs, fixed dofs at their values."""
    M = k.stencil_csr(stencil).toarray()
    x = np.array(values, dtype=float)
    for c in range(rhs.shape[1]):
        free = np.flatnonzero(~constraints.mask[:, c] & (mass > 0))
        fixed = np.setdiff1d(np.arange(mass.size), free)
        b = rhs[free, c] - M[np.ix_(free, fixed)] @ x[fixed, c]
        x[free, c] = np.linalg.solve(M[np.ix_(free, free)], b)
    return x


@pytest.mark.parametrize("pre, layers", [("lumped", 0), ("kronecker", 0), ("kronecker", 3)])
def test_cg_columns_converge_per_problem_and_leave_the_iteration(pre, layers):
    """One CG run on three problems (six columns): a cold one whose second
    component is round-off beside its first, one warm started from a
    slightly perturbed solution (converges early, so the others are packed
    mid-run) and a zero right-hand side with a nonzero warm start, in the
    order zero, warm, cold (the last column left is not the first). Each
    problem meets rtol measured over the whole problem, matches the dense
    solve and the same problem solved alone; the zero problem gives x = 0;
    a warm start that already solves the system takes no iteration."""
    from skfem_mpm.solve.stencil_system import StencilSystem

    k, stencil, mass, constraints = _block_system(cells=16)
    rng = np.random.default_rng(7)
    zeros = np.zeros((mass.size, 2))
    rhs0 = rng.standard_normal((mass.size, 2)) * mass[:, None]
    rhs0[:, 0] *= 1e-15
    rhs1 = rng.standard_normal((mass.size, 2)) * mass[:, None]
    exact0 = _dense_free_solve(k, stencil, mass, constraints, rhs0, zeros)
    exact1 = _dense_free_solve(k, stencil, mass, constraints, rhs1, zeros)

    def system(warm):
        s = StencilSystem(k, stencil.copy(), mass, constraints, np.zeros(mass.size), warm)
        s.preconditioner, s.FRINGE_LAYERS, s.FRINGE_FROM = pre, layers, 0
        return s

    def warm_starts():
        return {"w1": exact1 * (1 + 1e-6 * rng.standard_normal(exact1.shape)),
                "w2": rng.standard_normal((mass.size, 2))}

    warm = warm_starts()
    together = system(warm)
    x2, x1, x0 = together.solve_many([(zeros, zeros, "w2"), (rhs1, zeros, "w1"),
                                      (rhs0, zeros, "cold")])
    alone = []
    for rhs, kind in ((rhs0, "cold"), (rhs1, "w1")):
        s = system({"w1": warm["w1"]})
        alone.append(s.solve(rhs, zeros, kind))
    assert not np.any(x2)
    for x, exact, single in ((x0, exact0, alone[0]), (x1, exact1, alone[1])):
        scale = np.abs(exact).max()
        assert np.abs(x - exact).max() < 1e-10 * scale
        assert np.abs(x - single).max() < 1e-12 * scale
    # the round-off component is solved to the problem's accuracy, not its own
    assert np.abs(x0[:, 0] - exact0[:, 0]).max() > 1e-6 * np.abs(exact0[:, 0]).max()
    converged = system({"acceleration": x1.copy()})
    converged.solve(rhs1, zeros, "acceleration")
    assert converged.iterations == 0


@pytest.mark.parametrize("scheme", ("usl", "musl"))
def test_velocity_warm_start_is_the_last_end_velocity(scheme):
    """A block in free fall is stress free, so its grid acceleration is g
    and its velocity v(t) + dt g every step: the warm starts (the last
    acceleration; the last end-of-step velocity, plus dt a for MUSL's
    second solve) already meet the tolerance and CG takes no iteration
    after the start-up steps (5 per step with the last step's v_old)."""
    from skfem_mpm.bench import scene_2d
    from skfem_mpm.solve.stencil_system import StencilSystem

    scene, _ = scene_2d(cells=16, steps=12)
    log = []
    StencilSystem.iteration_log = log
    try:
        result = simulate(scene, Method(scheme=scheme, mass="consistent", mass_solver="cg"))
    finally:
        StencilSystem.iteration_log = None
    runs = 2 if scheme == "musl" else 1
    assert len(log) >= result.counts["steps"] * runs >= 12 * runs
    assert sum(log[5 * runs:]) <= 2, log


def test_fast_row_fractions_kernel_matches_lumping_fraction():
    from skfem_mpm.kernels.mpm import fast_row_fractions
    from skfem_mpm.kernels.serial import serial

    fast_row_fractions = serial(fast_row_fractions)
    from skfem_mpm.solve.timestep import lumping_fraction

    rng = np.random.default_rng(3)
    n = 500
    stencil = rng.uniform(0.1, 1.0, (n, 25))
    stiffness = rng.uniform(0.0, 3.0, n)
    mass = np.where(rng.uniform(size=n) < 0.2, 0.0, 1.0)
    out = np.empty(n)
    count = fast_row_fractions(stiffness, stencil[:, 12].copy(), mass, 2.0, out)
    expected = np.where(mass > 0, lumping_fraction(stiffness / (2.0 * stencil[:, 12])), 0.0)
    assert np.abs(out - expected).max() < 1e-14
    assert count == np.count_nonzero(expected) and 0 < count < n


def test_compact_system_rows_beyond_the_lumping_take_the_stencil_as_it_is():
    """The rows that lumped_reach leaves unmarked (no theta_kj = max(fast_k,
    fast_j) != 0 in their stencil) take compact_system's short paths (by
    the free columns of ``cols`` when it holds this set's, interior and
    edge rows alike, else by ``index`` for interior rows); their rows, with
    and without the fixed-column part, are those of the full path (every
    row marked) bit for bit, and the marks are the rows whose stencil holds
    a fast dof."""
    from skfem_mpm.kernels.mpm import compact_system, lumped_reach
    from skfem_mpm.kernels.serial import serial

    p, nbx, nby, dim, ns = 2, 14, 12, 2, 25
    nd = nbx * nby
    rng = np.random.default_rng(5)
    a, b = np.arange(nd) % nbx, np.arange(nd) // nbx
    da, db = np.arange(ns) % 5 - p, np.arange(ns) // 5 - p
    inside = ((0 <= a[:, None] + da) & (a[:, None] + da < nbx)
              & (0 <= b[:, None] + db) & (b[:, None] + db < nby))
    M = np.where(inside, rng.uniform(-0.1, 1.0, (nd, ns)), 0.0)
    fast = np.zeros(nd)
    fast[[0, 5, 61, 62, 167]] = [0.3, 1.0, 0.5, 0.2, 0.7]
    near = np.empty(nd, dtype=np.bool_)
    lumped_reach(fast, p, nbx, nby, dim, ns, near)
    j = np.where(inside, np.arange(nd)[:, None] + db * nbx + da, 0)
    assert np.array_equal(near, (inside & ((fast[:, None] != 0) | (fast[j] != 0))).any(axis=1))
    assert 0 < near.sum() < nd // 2
    interior = (p <= a) & (a < nbx - p) & (p <= b) & (b < nby - p)
    assert (~near & interior).sum() >= 5 and (~near & ~interior).sum() >= 5
    free = np.flatnonzero(rng.uniform(size=nd) < 0.85)
    index = np.full(nd, -1, dtype=np.int64)
    index[free] = np.arange(free.size)
    kernel = serial(compact_system)
    for write_fixed in (False, True):
        out = []
        for marks, write_cols in ((np.ones(nd, dtype=np.bool_), True), (near, True),
                                  (near, False)):
            A, F = np.zeros((free.size, ns)), np.zeros((free.size, ns))
            # not written: this set's columns, as the full path wrote them
            cols = np.zeros((free.size, ns), dtype=np.int32) if write_cols else \
                out[0][1].copy()
            fcols = np.zeros((free.size, ns), dtype=np.int32)
            kernel(M, p, nbx, nby, dim, free, index, fast, marks, A, cols, F, fcols,
                   write_cols, write_fixed)
            out.append((A, cols, F, fcols))
        for short in out[1:]:
            for got, full in zip(short, out[0]):
                assert np.array_equal(got, full)


def test_stencil_systems_reuse_what_depends_on_the_free_dofs_only():
    """Systems built in turn on the same kernels for different free-dof
    sets (the kept columns, groups and Kronecker factors are rebuilt when
    the set changes and reused when it comes back) and a solve with
    nonzero fixed values after one without (the fixed-column part is added
    to the built system) all match the dense solve."""
    from skfem_mpm.bench import scene_2d
    from skfem_mpm.kernels.mpm import Kernels
    from skfem_mpm.solve.stencil_system import StencilSystem
    from skfem_mpm.solve.grid_system import Constraints

    scene, _ = scene_2d(cells=12, steps=1)
    grid = scene.grid
    k = Kernels(grid, parallel=False)
    constraints = Constraints(grid, [e for e in scene.effects if type(e).__name__ == "Fixed"])
    full = Particles.seed(grid, 3, 1.0, region=((0.0, 1.0), (0.0, 1.0)))
    part = full.subset(np.flatnonzero(full.x[:, 0] < 0.6))
    rng = np.random.default_rng(8)
    values = np.zeros((grid.ndofs, 2))
    values[constraints.mask] = rng.standard_normal(np.count_nonzero(constraints.mask))
    zeros = np.zeros_like(values)
    for p in (full, part, part, full):
        mass = k.p2g(p, None)[0].copy()
        stencil = k.consistent_stencil(p)[0].copy()
        rhs = rng.standard_normal((grid.ndofs, 2)) * mass[:, None]
        system = StencilSystem(k, stencil, mass, constraints, np.zeros(grid.ndofs), {})
        for vals in (zeros, values):
            got = system.solve(rhs, vals, "velocity")
            exact = _dense_free_solve(k, stencil, mass, constraints, rhs, vals)
            assert np.abs(got - exact).max() < 1e-10 * np.abs(exact).max()


def test_auto_mass_solver_never_times_a_direct_solve(monkeypatch):
    """'auto' picks the stencil CG without timing it against a sparse LU (a
    timing-based choice made identical runs and restarts differ): no
    general grid system is built, although the first CG solves of this
    scene need more than the 20 iterations that used to trigger the timing."""
    from skfem_mpm.solve import compiled
    from skfem_mpm.solve.stencil_system import StencilSystem

    def no_lu(*args, **kwargs):
        raise AssertionError("a direct solve was built")

    monkeypatch.setattr(compiled, "GridSystem", no_lu)
    log = []
    monkeypatch.setattr(StencilSystem, "iteration_log", log)
    # the Kronecker preconditioner alone, whose iterations the old timing
    # rule saw (the band factor would take this narrow block after them)
    monkeypatch.setattr(StencilSystem, "BAND_MAX", 0)
    grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), 24, 2)
    parts = Particles.seed(grid, 2, 1.0, region=((0.25, 0.75), (0.25, 0.75)),
                           velocity=lambda X: X - 0.5)
    scene = Scene(grid, Body(parts, LinearElastic(1e3, 0.3)), 0.01,
                  effects=[Fixed("left"), Fixed("right"), Fixed("bottom"), Fixed("top")])
    result = simulate(scene, Method(mass="consistent", scheme="usl", mass_solver="auto"))
    assert result.path.startswith("fast")
    assert max(log) >= 20
