"""SplineGrid as a scikit-fem user meets it: locate, evaluate, project,
boundary integrals, saving."""
import numpy as np
import pytest
from skfem import BilinearForm, LinearForm, asm, condense, solve
from skfem.helpers import dot, grad

from skfem_mpm import SplineGrid


def test_locate_matches_element_finder_and_reference_coordinates():
    grid = SplineGrid((np.array([0.0, 0.3, 0.5, 1.0]), np.array([-1.0, 0.0, 0.2, 2.0])), 2)
    rng = np.random.default_rng(0)
    x = np.column_stack((rng.uniform(0, 1, 300), rng.uniform(-1, 2, 300)))
    cells, ref = grid.locate(x)
    finder = grid.mesh.element_finder()
    assert np.array_equal(cells, finder(x[:, 0], x[:, 1]))
    assert ref.shape == (300, 2) and ref.min() >= 0 and ref.max() <= 1
    back = grid.mapping.F(ref.T[:, :, None], tind=cells)[:, :, 0].T
    assert np.allclose(back, x, atol=1e-14)


def test_locate_1d_accepts_flat_and_column_points_and_the_end_point():
    grid = SplineGrid.line(0.0, 2.0, 4, 3)
    cells, ref = grid.locate(np.array([0.0, 0.5, 1.99, 2.0]))
    assert cells.tolist() == [0, 1, 3, 3]
    assert np.allclose(ref[:, 0], [0.0, 0.0, 0.98, 1.0])
    cells2, _ = grid.locate(np.array([[0.0], [0.5], [1.99], [2.0]]))
    assert np.array_equal(cells, cells2)


def test_locate_outside_raises_with_count_index_and_coordinate():
    grid = SplineGrid.rectangle((0, 1), (0, 1), 4, 2)
    x = np.array([[0.5, 0.5], [1.2, 0.1], [0.3, -0.1]])
    with pytest.raises(ValueError, match=r"2 point\(s\) lie outside.*index 1 at \[1.2, 0.1\]"):
        grid.locate(x)
    with pytest.raises(ValueError, match="finite"):
        grid.locate(np.array([[0.5, np.nan]]))
    with pytest.raises(ValueError, match="shape"):
        grid.locate(np.zeros((3, 3)))


@pytest.mark.parametrize("p", (1, 2, 3))
def test_interpolate_reproduces_polynomials_of_degree_p(p):
    grid = SplineGrid((np.array([0.0, 0.2, 0.7, 1.0]), np.linspace(0, 2, 5)), p)
    f = lambda x: (1 + x[:, 0] - 2 * x[:, 1]) ** p
    coeffs = grid.interpolate(f)
    x = np.random.default_rng(1).uniform([0, 0], [1, 2], (100, 2))
    assert np.abs(grid.evaluate(coeffs, x) - f(x)).max() < 1e-11


def test_evaluate_vector_field_in_interleaved_numbering():
    grid = SplineGrid.rectangle((0, 1), (0, 1), 3, 2)
    c = np.random.default_rng(2).standard_normal((grid.ndofs, 2))
    x = np.random.default_rng(3).random((20, 2))
    v1, g1 = grid.evaluate(c, x, gradient=True)
    v2, g2 = grid.evaluate(c.ravel(), x, gradient=True)  # dim * s + c order
    assert np.allclose(v1, v2) and np.allclose(g1, g2)
    assert v1.shape == (20, 2) and g1.shape == (20, 2, 2)
    with pytest.raises(ValueError, match="coeffs must have shape"):
        grid.evaluate(np.zeros(5), x)


def test_neumann_problem_with_facet_basis_and_project():
    # -lap u = 0 on [0,1]^2, u = 0 left, du/dn = 1 right, insulated top/bottom: u = x
    p = 2
    grid = SplineGrid.rectangle((0, 1), (0, 1), 4, p)
    basis = grid.basis()
    right = grid.facet_basis("right")

    @BilinearForm
    def laplace(u, v, _):
        return dot(grad(u), grad(v))

    @LinearForm
    def flux(v, w):
        return 1.0 * v

    f = asm(flux, right)
    assert np.isclose(f.sum(), 1.0)  # length of the side
    u = solve(*condense(asm(laplace, basis), f, D=grid.boundary_dofs("left")))
    x = np.random.default_rng(4).random((50, 2))
    assert np.abs(grid.evaluate(u, x) - x[:, 0]).max() < 1e-12
    # scikit-fem's own projection agrees
    proj = basis.project(lambda x: x[0])
    assert np.abs(proj - u).max() < 1e-12


def test_facet_basis_normals_point_outward():
    grid = SplineGrid.rectangle((0, 2), (0, 1), (3, 2), 3)
    for side, n in {"left": (-1, 0), "right": (1, 0), "bottom": (0, -1), "top": (0, 1)}.items():
        fb = grid.facet_basis(side)
        normals = np.asarray(fb.normals)
        assert np.allclose(normals[0], n[0]) and np.allclose(normals[1], n[1])


def test_mesh_save_of_an_interpolated_field(tmp_path):
    meshio = pytest.importorskip("meshio")
    grid = SplineGrid.rectangle((0, 1), (0, 1), 3, 2)
    coeffs = grid.interpolate(lambda x: x[:, 0] * x[:, 1])
    path = tmp_path / "field.vtk"
    grid.mesh.save(str(path), point_data={"u": grid.vertex_values(coeffs)})
    back = meshio.read(str(path))
    assert np.allclose(back.point_data["u"], grid.mesh.p[0] * grid.mesh.p[1])


def test_repr_and_counts():
    grid = SplineGrid.rectangle((0, 1), (0, 2), (3, 5), 2)
    assert grid.ndofs == 5 * 7 and grid.ncells == 15 and grid.dim == 2
    assert "degree=2" in repr(grid)
    assert grid.basis(vector=True).N == 2 * grid.ndofs
