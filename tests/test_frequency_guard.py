"""The fast-dof guard of consistent mass (skfem_mpm.solve.grid_system): it
lumps the rows of dofs whose frequency would outgrow the time step, and
nothing on a grid the particles fill."""
import numpy as np
import pytest
from skfem import asm

from skfem_mpm import Method, SplineGrid, simulate
from skfem_mpm.benchmarks import get_benchmark
from skfem_mpm.solve.timestep import (_mass, _stiffness, covered_weights, fast_dof_weights,
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
        scale, addend = covered_weights(w, mu, lumped, diagonal, tail_weight(3))
        assert np.all(addend == 0.0)  # 1D: no covered axis to put back
        expected = w[-2] if relaxed else tail_weight(3)  # 0.93: tau = 0.16 at dof -2
        assert scale[-2] == pytest.approx(expected, rel=1e-6), (region, scale[-2], w[-2])
        assert scale[1] == pytest.approx(w[1], rel=1e-6)  # the left end stays covered
