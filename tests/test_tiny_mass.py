"""The compiled tiny-mass merge against the reference one (grid_system)."""
import numpy as np
import pytest

from skfem_mpm import Fixed, Gravity, LinearElastic, Method, Particles, Scene, SplineGrid, simulate
from skfem_mpm.kernels.mpm import Kernels
from skfem_mpm.solve.grid_system import Constraints, GridSystem, dof_adjacency


def _masses(grid, rng, ties):
    """Lumped masses with empty dofs, tiny dofs at the edge of the mass and,
    with ``ties``, tiny dofs whose heaviest neighbours tie."""
    m = rng.uniform(0.5, 1.5, grid.ndofs)
    m[rng.random(grid.ndofs) < 0.15] = 0.0
    tiny = rng.random(grid.ndofs) < 0.25
    m[tiny] = rng.uniform(1e-9, 5e-4, tiny.sum()) * (rng.random(tiny.sum()) < 0.5) + \
        rng.uniform(1e-12, 1e-10, tiny.sum())  # chains: tiny next to tinier
    if ties:
        m[m > 0.1] = 1.0
    return m


@pytest.mark.parametrize("dim", [1, 2])
@pytest.mark.parametrize("degree", [1, 2, 3])
@pytest.mark.parametrize("ties", [False, True])
def test_compiled_merge_equals_the_reference_merge(dim, degree, ties):
    rng = np.random.default_rng(7 * dim + degree + 100 * ties)
    grid = (SplineGrid.line(0.0, 1.0, 12, degree) if dim == 1
            else SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (7, 5), degree))
    effects = [Fixed("left")] if dim == 1 else [Fixed("left"), Fixed("bottom", component=1)]
    constraints = Constraints(grid, effects)
    adjacency = dof_adjacency(grid)
    k = Kernels(grid)
    checked = 0
    for trial in range(50):
        if checked == 5:
            break
        m = _masses(grid, rng, ties)
        rhs = rng.normal(size=(grid.ndofs, dim))
        g = rng.normal(size=dim)
        values = rng.normal(size=(grid.ndofs, dim))
        reference = GridSystem(m, constraints, None, adjacency, 1e-3)
        if reference.small_dofs == 0:
            continue
        checked += 1
        expected = reference.solve(rhs + m[:, None] * g[None, :], values, "acceleration")
        out = np.full((grid.ndofs, dim), np.nan)
        count = k.merged_solve(m, rhs, g, constraints.mask, values, 1e-3, out)
        assert count == reference.small_dofs
        assert np.allclose(out, expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())
    assert checked == 5


def test_a_body_with_tiny_masses_runs_without_the_reference_solve(monkeypatch):
    """A block sliding into cells it barely touches makes tiny-mass dofs;
    the compiled executor no longer calls the SciPy merge for them."""
    from skfem_mpm.solve import compiled

    grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), 10, 2)
    p = Particles.seed(grid, 2, 1.0, region=((0.2, 0.615), (0.0, 0.4)),
                       velocity=lambda x: np.stack([0.3 + 0 * x[:, 0], 0 * x[:, 0]], axis=1))
    from skfem_mpm import Body

    scene = Scene(grid, [Body(p, LinearElastic(1e3, 0.3))], 0.05,
                  effects=[Gravity((0.0, -1.0)), Fixed("bottom")])
    calls = []
    original = compiled.CompiledExecutor._reference_solve
    monkeypatch.setattr(compiled.CompiledExecutor, "_reference_solve",
                        lambda *a, **kw: calls.append(1) or original(*a, **kw))
    r = simulate(scene, Method(scheme="musl"))
    assert r.path.startswith("fast")
    assert r.counts["small_dofs_max"] > 0
    assert calls == []


@pytest.mark.parametrize("degree", [1, 2])
def test_a_tiny_dof_whose_heaviest_neighbour_is_tiny_follows_it_to_a_kept_dof(degree):
    """m = (1, 1, ..., 1e-4, 1e-9, 0, ...): the 1e-9 dof's heaviest
    neighbour (1e-4) is itself small, so both move with the last heavy dof,
    and both right-hand sides reach it (a merge that stops at the first
    master loses the second one's)."""
    grid = SplineGrid.line(0.0, 1.0, 10, degree)
    nd = grid.ndofs
    m = np.zeros(nd)
    m[:5] = 1.0
    m[5], m[5 + degree] = 1e-4, 1e-9
    rhs = np.arange(1.0, nd + 1.0)[:, None]
    constraints = Constraints(grid, [])
    reference = GridSystem(m, constraints, None, dof_adjacency(grid), 1e-3)
    assert reference.small_dofs == 2
    expected = reference.solve(rhs, np.zeros_like(rhs), "acceleration")
    out = np.empty_like(rhs)
    assert Kernels(grid).merged_solve(m, rhs, np.zeros(1), constraints.mask, None, 1e-3,
                                      out) == 2
    assert np.allclose(out, expected, rtol=1e-13)
    assert out[5, 0] == out[5 + degree, 0]


def test_heaviest_first_is_the_stable_descending_argsort():
    """kernels.tiny_mass._heaviest_first (a hand-written merge sort, cheap
    to compile) orders as a stable argsort of -mass, ties included."""
    from skfem_mpm.kernels.tiny_mass import _heaviest_first

    rng = np.random.default_rng(0)
    for n in (0, 1, 2, 3, 5, 8, 17, 100, 1000):
        for _ in range(10):
            mass = rng.integers(0, 5, size=2 * n + 3) * rng.choice([1.0, 0.5])
            dofs = np.sort(rng.choice(mass.size, size=n, replace=False)).astype(np.int64)
            expected = dofs[np.argsort(-mass[dofs], kind="stable")]
            np.testing.assert_array_equal(_heaviest_first(dofs, mass), expected)


def _consistent_case(dim, degree, seed):
    """(kernels, stencil, lumped mass, constraints, fast-row fractions) of
    randomly seeded particles whose free surface cuts cells (tiny masses),
    fixed and prescribed sides, random fast-row lumping."""
    rng = np.random.default_rng(seed)
    if dim == 1:
        grid = SplineGrid.line(0.0, 1.0, 10, degree)
        region, effects = ((0.0, 0.61),), [Fixed("left")]
    elif dim == 2:
        grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (8, 7), degree)
        region = lambda X: ((X - 0.45) ** 2).sum(axis=1) < 0.33 ** 2  # noqa: E731
        effects = [Fixed("left"), Fixed("bottom", component=1)]
    else:
        grid = SplineGrid.box((0.0, 1.0), (0.0, 1.0), (0.0, 1.0), (4, 4, 3), degree)
        region = lambda X: ((X - 0.45) ** 2).sum(axis=1) < 0.4 ** 2  # noqa: E731
        effects = [Fixed("xmin"), Fixed("zmin", component=2)]
    p = Particles.seed(grid, 3 if dim < 3 else 2, 1.0, region=region, layout="random",
                       seed=seed)
    k = Kernels(grid, parallel=False)  # the serial kernels small runs compile
    mass = k.p2g(p, None)[0].copy()
    stencil = k.consistent_stencil(p)[0].copy()
    fast = rng.uniform(0.0, 0.5, mass.size) * (rng.random(mass.size) < 0.3) * (mass > 0)
    return k, stencil, mass, Constraints(grid, effects), fast


CONSISTENT_MERGE = [(d, p, s) for d in (1, 2) for p in (1, 2, 3) for s in (0, 1)] + [
    pytest.param(3, p, 0, marks=pytest.mark.slow(reason="3D consistent stencil kernels"))
    for p in (1, 2)]


@pytest.mark.parametrize("dim,degree,seed", CONSISTENT_MERGE)
def test_merged_consistent_mass_equals_the_reference_merge(dim, degree, seed):
    """StencilSystem with tiny masses (the merged system of
    kernels.merged_mass, its CG to rtol 1e-13) solves GridSystem's merged
    equations T^T M' T x_r = T^T rhs (sparse LU), fast rows lumped,
    constrained dofs (some prescribed, nonzero) moved to the right-hand
    side: the same solution and the same count of merged dofs."""
    from skfem_mpm.solve.stencil_system import StencilSystem

    k, stencil, mass, constraints, fast = _consistent_case(dim, degree, seed)
    rng = np.random.default_rng(seed + 10)
    rhs = rng.normal(size=(mass.size, dim))
    values = rng.normal(size=(mass.size, dim)) * constraints.mask * (mass > 0)[:, None]
    system = StencilSystem(k, stencil, mass, constraints, fast, {}, small_mass=1e-3)
    reference = GridSystem(mass, constraints, k.stencil_csr(stencil), dof_adjacency(k.grid),
                           1e-3, "direct", fast_rows=lambda diagonal: fast)
    assert system.mergeable
    assert system.small_dofs == reference.small_dofs
    x = system.solve(rhs, values, "velocity")
    expected = reference.solve(rhs, values, "velocity")
    assert np.abs(x - expected).max() <= 1e-11 * np.abs(expected).max()


def test_the_consistent_merge_cases_have_tiny_masses():
    """Each default case above of degree 2 or 3 merges dofs (else it would
    test the plain stencil CG)."""
    from skfem_mpm.solve.stencil_system import StencilSystem

    for dim, degree, seed in [c for c in CONSISTENT_MERGE if not hasattr(c, "marks")]:
        k, stencil, mass, constraints, fast = _consistent_case(dim, degree, seed)
        system = StencilSystem(k, stencil, mass, constraints, fast, {}, small_mass=1e-3)
        assert system.small_dofs > 0 or degree == 1, (dim, degree, seed)
