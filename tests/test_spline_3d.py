"""The hexahedral B-spline space (``ElementHexBSpline`` on ``MeshHex1``,
``SplineGrid.box``): values, derivatives, the scikit-fem bases built on it,
sides, bad input, and Poisson convergence at order p + 1."""
import numpy as np
import pytest
from skfem import BilinearForm, Functional, LinearForm, asm, condense, solve
from skfem.helpers import dot, grad

from skfem_mpm import SplineGrid
from skfem_mpm.spline import ElementHexBSpline
from skfem_mpm.testing import assert_order

DEGREES = (1, 2, 3)
SIDES_3D = ("xmin", "xmax", "ymin", "ymax", "zmin", "zmax")
# non-uniform on every axis, different cell counts per axis
BREAKS = (np.array([0.0, 0.3, 0.5, 1.2]),
          np.array([-1.0, -0.4, 0.0, 0.7, 1.0]),
          np.array([0.0, 0.25, 1.0]))


def grid_3d(p):
    return SplineGrid(BREAKS, p)


def random_points(grid, n, seed):
    rng = np.random.default_rng(seed)
    lo = np.array([b[0] for b in grid.bounds])
    hi = np.array([b[1] for b in grid.bounds])
    return lo + (hi - lo) * rng.random((n, grid.dim))


@pytest.mark.parametrize("p", DEGREES)
def test_partition_of_unity_and_nonnegative(p):
    grid = grid_3d(p)
    x = random_points(grid, 200, 1)
    dofs, values, grads = grid.shape_functions(x)
    assert values.shape == (200, (p + 1) ** 3)
    assert np.allclose(values.sum(axis=1), 1.0, rtol=0, atol=1e-13)
    assert np.allclose(grads.sum(axis=1), 0.0, rtol=0, atol=1e-11)
    assert values.min() >= -1e-15
    # every dof of a point is distinct and in range
    assert np.all(np.sort(dofs, axis=1)[:, 1:] > np.sort(dofs, axis=1)[:, :-1])
    assert dofs.min() >= 0 and dofs.max() < grid.ndofs == np.prod([n + p for n in (3, 4, 2)])


@pytest.mark.parametrize("p", DEGREES)
def test_gradients_match_finite_differences(p):
    grid = grid_3d(p)
    coeffs = np.random.default_rng(2).standard_normal(grid.ndofs)
    # keep the points a step away from breakpoints so both sides of the
    # difference lie in one polynomial piece
    x = random_points(grid, 60, 3)
    step = 1e-6
    for axis, b in enumerate(grid.breakpoints):
        near = np.abs(x[:, axis, None] - b[None, :]).min(axis=1) < 10 * step
        x[near, axis] += 20 * step
    values, gradient = grid.evaluate(coeffs, x, gradient=True)
    for axis in range(3):
        shift = np.zeros(3)
        shift[axis] = step
        fd = (grid.evaluate(coeffs, x + shift) - grid.evaluate(coeffs, x - shift)) / (2 * step)
        assert np.allclose(gradient[:, axis], fd, rtol=0, atol=1e-6 * np.abs(coeffs).max())


@pytest.mark.parametrize("p", DEGREES)
def test_element_agrees_with_grid_evaluator(p):
    """The scikit-fem basis (element gbasis, spline dofs, affine mapping) and
    the grid's own evaluator give the same field and gradient at the Gauss
    points: the element's local numbering matches the dof table."""
    grid = grid_3d(p)
    coeffs = np.random.default_rng(5).standard_normal(grid.ndofs)
    basis = grid.basis()
    field = basis.interpolate(coeffs)
    x = np.asarray(basis.global_coordinates()).reshape(3, -1).T
    values, gradient = grid.evaluate(coeffs, x, gradient=True)
    assert np.allclose(field.value.ravel(), values, rtol=0, atol=1e-12)
    for axis in range(3):
        assert np.allclose(field.grad[axis].ravel(), gradient[:, axis], rtol=0, atol=1e-10)
    # the affine map's measure: the integral of x^2 y^2 z^2 over the box
    exact = np.prod([(b[-1] ** 3 - b[0] ** 3) / 3 for b in BREAKS])
    moment = Functional(lambda w: (w.x[0] * w.x[1] * w.x[2]) ** 2).assemble(basis)
    assert np.isclose(moment, exact, rtol=1e-13)


def test_element_class_and_defaults():
    elem = ElementHexBSpline(2)
    assert elem.interior_dofs == 27 and elem.maxdeg == 6
    with pytest.raises(ValueError, match="3 breakpoint arrays"):
        ElementHexBSpline(2, ((0.0, 1.0), (0.0, 1.0)))


@pytest.mark.parametrize("p", DEGREES)
def test_interpolate_reproduces_the_space_and_gauss_rule_integrates(p):
    grid = grid_3d(p)

    def f(x):  # in Q_p on every cell
        return x[:, 0] ** p * x[:, 1] - x[:, 2] ** p + x[:, 0] * x[:, 1] * x[:, 2]

    coeffs = grid.interpolate(f)
    x = random_points(grid, 50, 6)
    assert np.allclose(grid.evaluate(coeffs, x), f(x), rtol=0, atol=1e-11)
    X, W, cells = grid.gauss_rule(p + 1)
    assert X.shape == (grid.ncells * (p + 1) ** 3, 3)
    located, _ = grid.locate(X)
    assert np.array_equal(located, cells)
    volume = np.prod([b[-1] - b[0] for b in BREAKS])
    assert np.isclose(W.sum(), volume, rtol=1e-14)
    # integral of x^2 y^2 z^2 over the box, exact for p + 1 >= 2 points
    exact = np.prod([(b[-1] ** 3 - b[0] ** 3) / 3 for b in BREAKS])
    k = max(p + 1, 2)
    X, W, _ = grid.gauss_rule(k)
    assert np.isclose((W * np.prod(X ** 2, axis=1)).sum(), exact, rtol=1e-13)


@pytest.mark.parametrize("p", DEGREES)
def test_sides_boundary_dofs_and_facet_bases(p):
    grid = grid_3d(p)
    lo = np.array([b[0] for b in grid.bounds])
    hi = np.array([b[1] for b in grid.bounds])
    for axis in range(3):
        for end, side in enumerate(SIDES_3D[2 * axis:2 * axis + 2]):
            fb = grid.facet_basis(side)
            area = np.prod(np.delete(hi - lo, axis))
            assert np.isclose(asm(LinearForm(lambda v, w: v), fb).sum(), area, rtol=1e-13)
            normal = np.asarray(fb.normals)  # (3, facets, points)
            expected = np.zeros(3)
            expected[axis] = 1.0 if end else -1.0
            assert np.allclose(normal, expected[:, None, None])
            x = np.asarray(fb.global_coordinates()).reshape(3, -1).T
            assert np.allclose(x[:, axis], (hi if end else lo)[axis])
            # the side's dofs are exactly the functions that do not vanish there
            dofs = grid.boundary_dofs(side)
            assert dofs.size == np.prod([n for a, n in enumerate(grid.basis_per_axis) if a != axis])
            sd, sv, _ = grid.shape_functions(x)
            on_side = np.unique(sd[np.abs(sv) > 1e-12])
            assert np.array_equal(np.sort(dofs), on_side)
            for c in range(3):
                assert np.array_equal(grid.boundary_dofs(side, c), 3 * dofs + c)
    vb = grid.facet_basis("zmax", vector=True)
    assert vb.N == 3 * grid.ndofs


def test_side_aliases_in_every_dimension():
    line = SplineGrid.line(0, 1, 3, 2)
    rect = SplineGrid.rectangle((0, 1), (0, 2), (3, 4), 2)
    box = SplineGrid.box((0, 1), (0, 2), (0, 3), (3, 4, 2), 2)
    for grid in (line, rect, box):
        assert np.array_equal(grid.boundary_dofs("xmin"), grid.boundary_dofs("left"))
        assert np.array_equal(grid.boundary_dofs("xmax"), grid.boundary_dofs("right"))
    for grid in (rect, box):
        assert np.array_equal(grid.boundary_dofs("ymin"), grid.boundary_dofs("bottom"))
        assert np.array_equal(grid.boundary_dofs("ymax"), grid.boundary_dofs("top"))
    assert np.array_equal(rect.boundary_dofs("ymin", 1), rect.boundary_dofs("bottom", 1))
    for bad, grid in (("zmin", rect), ("ymax", line), ("top", line), ("front", box)):
        with pytest.raises(ValueError, match=f"side must be one of .* got '{bad}'"):
            grid.boundary_dofs(bad)


def test_bad_input_is_refused_clearly():
    axis = np.linspace(0, 1, 3)
    with pytest.raises(ValueError, match="1, 2 or 3 axes, got 4"):
        SplineGrid((axis, axis, axis, axis), 2)
    with pytest.raises(ValueError, match=r"degree must be one of \(1, 2, 3\), got 4"):
        SplineGrid.box((0, 1), (0, 1), (0, 1), 2, 4)
    with pytest.raises(ValueError, match=r"cells must be an int or 3 ints"):
        SplineGrid.box((0, 1), (0, 1), (0, 1), (2, 2), 2)
    with pytest.raises(ValueError, match="zlim must satisfy lo < hi"):
        SplineGrid.box((0, 1), (0, 1), (1, 0), 2, 2)
    with pytest.raises(ValueError, match=r"breakpoints\[2\] must be strictly increasing"):
        SplineGrid((axis, axis, np.array([0.0, 0.0, 1.0])), 2)
    box = SplineGrid.box((0, 1), (0, 1), (0, 1), 2, 2)
    with pytest.raises(ValueError, match="component"):
        box.boundary_dofs("zmin", component=3)
    with pytest.raises(ValueError, match="outside the grid"):
        box.locate(np.array([[0.5, 0.5, 1.5]]))


def test_locate_numbers_cells_x_fastest():
    grid = SplineGrid(BREAKS, 2)
    x = np.array([[0.4, 0.1, 0.5], [1.2, 1.0, 1.0], [0.0, -1.0, 0.0]])
    cells, xi = grid.locate(x)
    # cell (1, 2, 1) -> 1 + 3 * 2 + 12 * 1; the upper corner in the last cell
    assert cells.tolist() == [19, 23, 0]
    assert np.allclose(xi[0], [0.5, 0.1 / 0.7, 0.25 / 0.75])
    assert np.allclose(xi[1], 1.0) and np.allclose(xi[2], 0.0)
    # the mesh cell holds the point: its lower and upper corners bracket it
    mesh = grid.mesh
    corners = mesh.p[:, mesh.t[:, cells]]
    assert np.all(corners.min(axis=1) <= x.T + 1e-15) and np.all(corners.max(axis=1) >= x.T - 1e-15)


def exact_poisson(x):
    return np.sin(np.pi * x[0]) * np.sin(np.pi * x[1]) * np.sin(np.pi * x[2])


def poisson_l2_error(p, n):
    """-lap u = 3 pi^2 u on the unit cube, u = 0 on the boundary, Gauss
    quadrature of order 2p; the L2 error by a finer Gauss rule."""
    grid = SplineGrid.box((0, 1), (0, 1), (0, 1), n, p)
    basis = grid.basis()
    K = asm(BilinearForm(lambda u, v, _: dot(grad(u), grad(v))), basis)
    f = asm(LinearForm(lambda v, w: 3 * np.pi ** 2 * exact_poisson(w.x) * v), basis)
    D = np.unique(np.concatenate([grid.boundary_dofs(s) for s in SIDES_3D]))
    u = solve(*condense(K, f, D=D))
    fine = grid.basis(intorder=2 * p + 4)
    error = Functional(lambda w: (w.u - exact_poisson(w.x)) ** 2)
    return np.sqrt(error.assemble(fine, u=fine.interpolate(u)))


@pytest.mark.parametrize("p, cells", [(1, (2, 4, 8)), (2, (4, 8)), (3, (4, 8))])
def test_poisson_on_the_unit_cube_converges_at_order_p_plus_1(p, cells):
    """Measured: p1 9.29e-2, 2.30e-2, 5.75e-3 (2, 4, 8 cells; orders 2.01,
    2.00); p2 2.00e-3, 2.22e-4 (4, 8; 3.17); p3 2.69e-4, 1.42e-5 (4, 8;
    4.24). At 2 cells p2 and p3 are pre-asymptotic (orders 3.57, 2.92)."""
    errors = [poisson_l2_error(p, n) for n in cells]
    assert_order(errors, 1.0 / np.array(cells), expected=p + 1, tol=0.3)
