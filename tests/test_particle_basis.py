"""Particles as quadrature points: ParticleBasis and transfer matrices."""
import numpy as np
import pytest
from skfem import (BilinearForm, ElementQuad1, ElementTriP1, LinearForm, MeshQuad1,
                   MeshTri1, asm)
from skfem.helpers import dot, grad, sym_grad, ddot

from skfem_mpm import LagrangeGrid, ParticleBasis, Particles, SplineGrid


@BilinearForm
def mass(u, v, w):
    return w.rho * u * v


@BilinearForm
def stiffness(u, v, _):
    return dot(grad(u), grad(v))


@LinearForm
def load(v, w):
    return np.sin(3 * w.x[0]) * np.cos(w.x[-1]) * v


def make_grid(dim, p):
    if dim == 1:
        return SplineGrid(np.array([0.0, 0.2, 0.5, 0.6, 1.0]), p)
    if dim == 3:
        return SplineGrid((np.array([0.0, 0.4, 1.0]), np.array([-1.0, -0.2, 1.0]),
                           np.array([0.0, 0.3, 0.5])), p)
    return SplineGrid((np.array([0.0, 0.4, 1.0, 1.5]), np.array([-1.0, -0.2, 0.0, 1.0])), p)


@pytest.mark.parametrize("p", (1, 2, 3))
@pytest.mark.parametrize("dim", (1, 2, 3))
def test_gauss_layout_particles_reproduce_gauss_quadrature(dim, p):
    grid = make_grid(dim, p)
    k = p + 1  # exact to degree 2p + 1 >= the mass integrand's 2p
    particles = Particles.seed(grid, k, 2.5, layout="gauss")
    pb = ParticleBasis(grid, particles)
    gb = grid.basis(intorder=2 * k - 1)
    rho_p = (particles.m / particles.V)[:, None]
    M_p = asm(mass, pb, rho=rho_p)
    M_g = asm(mass, gb, rho=2.5)
    assert abs(M_p - M_g).max() < 1e-12 * abs(M_g).max()
    K_p, K_g = asm(stiffness, pb), asm(stiffness, gb)
    assert abs(K_p - K_g).max() < 1e-12 * abs(K_g).max()
    # a smooth (non-polynomial) load: same points and weights, same sums
    assert np.abs(asm(load, pb) - asm(load, gb)).max() < 1e-12


@pytest.mark.parametrize("p", (1, 2, 3))
@pytest.mark.parametrize("dim", (1, 2, 3))
def test_forms_equal_explicit_particle_sums(dim, p):
    grid = make_grid(dim, p)
    particles = Particles.seed(grid, 2, 1.7, layout="random", seed=3)
    rng = np.random.default_rng(4)
    stress = rng.standard_normal((particles.n, dim, dim))
    particles.stress = 0.5 * (stress + stress.transpose(0, 2, 1))
    pb = ParticleBasis(grid, particles)
    N = pb.N_matrix.toarray()
    G = [g.toarray() for g in pb.grad_N]

    @LinearForm
    def mass_vector(v, w):
        return w.rho * v

    lumped = asm(mass_vector, pb, rho=(particles.m / particles.V)[:, None])
    assert np.abs(lumped - N.T @ particles.m).max() < 1e-13 * particles.m.max()
    # internal force, component c: sum_p sigma_p[c, d] dN_i/dx_d V_p
    vb = ParticleBasis(grid, particles, vector=True)

    @LinearForm
    def internal(v, w):
        return ddot(w.sigma, sym_grad(v))

    sigma = np.moveaxis(particles.stress, 0, -1)[:, :, :, None]
    f = asm(internal, vb, sigma=sigma).reshape(-1, dim)
    for c in range(dim):
        explicit = sum(G[d].T @ (particles.stress[:, c, d] * particles.V) for d in range(dim))
        assert np.abs(f[:, c] - explicit).max() < 1e-13 * max(1.0, np.abs(explicit).max())


@pytest.mark.parametrize("p", (1, 2, 3))
@pytest.mark.parametrize("dim", (2, 3))
def test_transfer_matrices_equal_what_forms_compute(dim, p):
    grid = make_grid(dim, p)
    particles = Particles.seed(grid, 2, 1.0, layout="random", seed=1)
    pb = ParticleBasis(grid, particles)
    N = pb.N_matrix.toarray()
    for j in range(pb.Nbfun):
        dofs = pb.element_dofs[j]
        vals = np.asarray(pb.basis[j][0])[:, 0]
        grads = np.asarray(pb.basis[j][0].grad)[:, :, 0]
        assert np.abs(N[np.arange(particles.n), dofs] - vals).max() < 1e-14
        for d in range(dim):
            G = pb.grad_N[d].toarray()
            assert np.abs(G[np.arange(particles.n), dofs] - grads[d]).max() < 1e-12
    assert pb.N_matrix.shape == (particles.n, grid.ndofs)
    assert np.all(np.diff(pb.N_matrix.indptr) == (p + 1) ** dim)


@pytest.mark.parametrize("p", (1, 2, 3))
@pytest.mark.parametrize("dim", (1, 2))
def test_linear_completeness(dim, p):
    grid = make_grid(dim, p)
    particles = Particles.seed(grid, 3, 1.0, layout="random", seed=2)
    lin = lambda x: 0.3 + 1.5 * x[:, 0] - 0.7 * x[:, -1]
    coeffs = grid.interpolate(lin)
    pb = ParticleBasis(grid, particles)
    assert np.abs(pb.N_matrix @ coeffs - lin(particles.x)).max() < 1e-12
    slope = np.array([1.5, -0.7]) if dim == 2 else np.array([0.8])
    for d in range(dim):
        assert np.allclose(pb.grad_N[d] @ coeffs, slope[d], atol=1e-10)


def test_numba_and_numpy_backends_agree():
    for breaks in (np.linspace(0, 1, 41), np.sort(np.r_[0, 1, np.random.default_rng(0).random(30)])):
        for p in (1, 2, 3):
            grid = SplineGrid(breaks, p)
            x = np.concatenate((np.random.default_rng(1).random(5000), breaks))
            a = grid.axis_functions(0, x, backend="numba")
            b = grid.axis_functions(0, x, backend="numpy")
            assert np.array_equal(a[0], b[0])
            assert np.abs(a[1] - b[1]).max() < 1e-13
            assert np.abs(a[2] - b[2]).max() < 1e-13 * 41 * 3


def test_lagrange_p1_on_triangles_and_q1_on_quads():
    tri = MeshTri1.init_sqsymmetric().refined(3)
    quad = MeshQuad1.init_tensor(np.linspace(0, 1, 6), np.linspace(0, 1, 5))
    for mesh, elem in ((tri, ElementTriP1()), (quad, ElementQuad1())):
        grid = LagrangeGrid(mesh, elem)
        particles = Particles.from_mesh(mesh, 1.0, intorder=2)
        pb = ParticleBasis(grid, particles)
        gb = grid.basis(intorder=2)
        M_p = asm(mass, pb, rho=1.0)
        M_g = asm(mass, gb, rho=1.0)
        assert abs(M_p - M_g).max() < 1e-12
        assert abs(asm(stiffness, pb) - asm(stiffness, gb)).max() < 1e-10
        coeffs = 1.0 + 2.0 * mesh.p[0] - mesh.p[1]
        assert np.allclose(pb.N_matrix @ coeffs, 1 + 2 * particles.x[:, 0] - particles.x[:, 1])
        assert np.allclose(pb.grad_N[0] @ coeffs, 2.0)


def test_particles_outside_the_grid_are_named():
    grid = make_grid(2, 2)
    particles = Particles(np.array([[0.5, 0.0], [2.0, 0.0]]), np.ones(2), np.ones(2))
    with pytest.raises(ValueError, match=r"1 point\(s\) lie outside.*index 1"):
        ParticleBasis(grid, particles)
    tri = LagrangeGrid(MeshTri1.init_sqsymmetric())
    with pytest.raises(ValueError, match=r"outside the mesh.*index 1"):
        tri.locate(np.array([[0.5, 0.5], [1.5, 0.5]]))


def test_rebuilding_for_moved_particles_keeps_no_growing_state():
    grid = LagrangeGrid(MeshQuad1.init_tensor(np.linspace(0, 1, 5), np.linspace(0, 1, 5)))
    particles = Particles.seed(SplineGrid.rectangle((0, 1), (0, 1), 4, 1), 2, 1.0)
    mapping_before = grid.mapping
    for shift in np.linspace(0.0, 0.1, 5):
        moved = particles.copy()
        moved.x[:, 0] = np.minimum(moved.x[:, 0] + shift, 1.0)
        pb = ParticleBasis(grid, moved)
        asm(mass, pb, rho=1.0)
    assert grid.mapping is mapping_before
    assert not hasattr(grid.mapping, "_cache")  # the grid's own mapping was never used
