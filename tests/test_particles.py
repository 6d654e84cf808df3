"""Particles: container, validation, seeding."""
import numpy as np
import pytest

from skfem_mpm import Particles, SplineGrid


def grid2d():
    return SplineGrid.rectangle((0, 2), (0, 1), (4, 2), 2)


def test_uniform_seeding_positions_volumes_and_fields():
    g = SplineGrid.line(0.0, 1.0, 2, 2)
    p = Particles.seed(g, 2, 3.0, velocity=lambda X: 2 * X, stress=lambda X: X[:, :, None])
    assert np.allclose(p.x[:, 0], [0.125, 0.375, 0.625, 0.875])
    assert np.allclose(p.V, 0.25) and np.allclose(p.m, 0.75)
    assert np.allclose(p.v[:, 0], 2 * p.x[:, 0])
    assert p.stress.shape == (4, 1, 1) and np.allclose(p.stress[:, 0, 0], p.x[:, 0])
    assert p.F is None and p.X is not p.x and np.array_equal(p.X, p.x)


def test_ppc_per_axis_and_counts():
    p = Particles.seed(grid2d(), (3, 1), 1.0)
    assert p.n == 8 * 3 and p.dim == 2
    assert np.isclose(p.V.sum(), 2.0)


def test_gauss_layout_weights_integrate_polynomials_exactly():
    g = SplineGrid(np.array([0.0, 0.3, 1.0]), 2)
    p = Particles.seed(g, 3, 1.0, layout="gauss")
    # 3 Gauss points per cell: exact to degree 5
    assert np.isclose((p.V * p.x[:, 0] ** 5).sum(), 1.0 / 6.0, atol=1e-15)


def test_box_region_gives_exact_volume_even_when_it_cuts_cells():
    g = grid2d()
    p = Particles.seed(g, 2, 1.0, region=((0.1, 1.3), (0.0, 0.77)))
    assert np.isclose(p.V.sum(), 1.2 * 0.77, rtol=1e-14)
    assert p.x[:, 0].min() > 0.1 and p.x[:, 0].max() < 1.3
    assert p.info["volume_error"] == 0.0


def test_callable_region_reports_volume_error():
    g = SplineGrid.rectangle((0, 1), (0, 1), 10, 2)
    disk = lambda X: (X[:, 0] - 0.5) ** 2 + (X[:, 1] - 0.5) ** 2 < 0.3 ** 2
    p = Particles.seed(g, 2, 1.0, region=disk)
    assert 0 < p.info["volume_error"] < 0.02
    assert abs(p.V.sum() - np.pi * 0.09) < 3 * p.info["volume_error"] + 1e-3


def test_random_layout_is_reproducible_and_fills_cells():
    g = grid2d()
    a = Particles.seed(g, 2, 1.0, layout="random", seed=5)
    b = Particles.seed(g, 2, 1.0, layout="random", seed=5)
    assert np.array_equal(a.x, b.x) and a.n == 8 * 4
    assert np.isclose(a.V.sum(), 2.0)
    cells, _ = g.locate(a.x)
    assert np.array_equal(np.bincount(cells, minlength=8), np.full(8, 4))


def test_density_callable():
    g = SplineGrid.line(0, 1, 4, 1)
    p = Particles.seed(g, 1, lambda X: 1.0 + X[:, 0])
    assert np.allclose(p.m, (1.0 + p.x[:, 0]) * 0.25)


def test_copy_subset_concatenate():
    g = grid2d()
    p = Particles.seed(g, 1, 1.0)
    q = p.copy()
    q.x[0, 0] = 99.0
    assert p.x[0, 0] != 99.0
    s = p.subset(p.x[:, 0] < 1.0)
    assert s.n == 4
    both = Particles.concatenate([s, p.subset([0, 1])], bodies=[0, 1])
    assert both.n == 6 and both.body.tolist() == [0, 0, 0, 0, 1, 1]
    with pytest.raises(ValueError, match="same dim"):
        Particles.concatenate([p, Particles.seed(SplineGrid.line(0, 1, 2, 1), 1, 1.0)])


def test_from_mesh_and_from_meshio(tmp_path):
    from skfem import MeshTri
    import meshio

    mesh = MeshTri.init_circle(3)
    p = Particles.from_mesh(mesh, 2.0, intorder=2)
    area = np.sum(np.abs(np.linalg.det(
        np.stack([mesh.p[:, mesh.t[1]] - mesh.p[:, mesh.t[0]],
                  mesh.p[:, mesh.t[2]] - mesh.p[:, mesh.t[0]]], axis=-1).transpose(1, 0, 2)))) / 2
    assert np.isclose(p.V.sum(), area)
    path = tmp_path / "disk.vtk"
    mesh.save(str(path))
    q = Particles.from_meshio(str(path), 2.0)
    assert np.isclose(q.V.sum(), area) and q.n == p.n


@pytest.mark.parametrize("kwargs, match", [
    (dict(m=np.array([1.0, -1.0]), V=np.ones(2)), "m must be > 0.*index 1"),
    (dict(m=np.ones(2), V=np.array([0.0, 1.0])), "V must be > 0.*index 0"),
    (dict(m=np.ones(3), V=np.ones(2)), r"m must have shape \(2,\)"),
    (dict(m=np.ones(2), V=np.ones(2), v=np.ones((3, 1))), r"v must have shape"),
    (dict(m=np.array([1.0, np.nan]), V=np.ones(2)), "m must be finite"),
])
def test_bad_arrays(kwargs, match):
    with pytest.raises(ValueError, match=match):
        Particles(np.array([[0.1], [0.2]]), **kwargs)


def test_nan_positions_and_bad_seeding_arguments():
    with pytest.raises(ValueError, match="x must be finite"):
        Particles(np.array([[0.1], [np.nan]]), np.ones(2), np.ones(2))
    g = grid2d()
    with pytest.raises(ValueError, match="ppc must be a positive integer"):
        Particles.seed(g, 0, 1.0)
    with pytest.raises(ValueError, match="ppc must be an int or 2 ints"):
        Particles.seed(g, (1, 2, 3), 1.0)
    with pytest.raises(ValueError, match="layout must be one of"):
        Particles.seed(g, 1, 1.0, layout="hexagonal")
    with pytest.raises(ValueError, match="density must be finite and > 0"):
        Particles.seed(g, 1, -1.0)
    with pytest.raises(ValueError, match="inside the grid"):
        Particles.seed(g, 1, 1.0, region=((0, 3), (0, 1)))
    with pytest.raises(ValueError, match="velocity must give shape"):
        Particles.seed(g, 1, 1.0, velocity=np.ones(3))
