"""B-spline spaces: values, derivatives, extraction, p = 1 equals P1/Q1."""
import numpy as np
import pytest
from scipy.interpolate import BSpline
from skfem import (BilinearForm, CellBasis, ElementLineP1, ElementQuad1, asm)
from skfem.helpers import dot, grad

from skfem_mpm import SplineGrid
from skfem_mpm.spline import ElementLineBSpline, extraction_operators, open_knot_vector

DEGREES = (1, 2, 3)


def nonuniform_breakpoints(n, seed=0):
    rng = np.random.default_rng(seed)
    steps = 0.5 + rng.random(n)
    return np.concatenate(([0.0], np.cumsum(steps))) / steps.sum() * 2.0 - 0.5


def dense_matrix(grid, x):
    dofs, values, grads = grid.shape_functions(x)
    A = np.zeros((len(x), grid.ndofs))
    G = np.zeros((len(x), grid.ndofs, grid.dim))
    rows = np.repeat(np.arange(len(x)), dofs.shape[1])
    np.add.at(A, (rows, dofs.ravel()), values.ravel())
    for d in range(grid.dim):
        np.add.at(G[:, :, d], (rows, dofs.ravel()), grads[:, :, d].ravel())
    return A, G


@pytest.mark.parametrize("p", DEGREES)
def test_values_and_derivatives_match_scipy_on_nonuniform_knots(p):
    u = nonuniform_breakpoints(9)
    grid = SplineGrid(u, p)
    x = np.random.default_rng(1).uniform(u[0], u[-1], 500)
    x = np.concatenate((x, u))  # breakpoints themselves, both ends included
    A, G = dense_matrix(grid, x)
    tau = open_knot_vector(u, p)
    ref = BSpline.design_matrix(x, tau, p).toarray()
    assert np.abs(A - ref).max() < 1e-13
    # derivative of every basis function via scipy
    dref = np.column_stack([
        BSpline(tau, np.eye(grid.ndofs)[i], p).derivative()(x) for i in range(grid.ndofs)
    ])
    assert np.abs(G[:, :, 0] - dref).max() < 1e-11 * max(1.0, np.abs(dref).max())


@pytest.mark.parametrize("p", DEGREES)
@pytest.mark.parametrize("dim", (1, 2))
def test_partition_of_unity_and_nonnegativity(p, dim):
    rng = np.random.default_rng(2)
    if dim == 1:
        grid = SplineGrid(nonuniform_breakpoints(7), p)
    else:
        grid = SplineGrid((nonuniform_breakpoints(5, 3), nonuniform_breakpoints(6, 4)), p)
    lo = np.array([b[0] for b in grid.bounds])
    hi = np.array([b[1] for b in grid.bounds])
    x = lo + (hi - lo) * rng.random((1000, dim))
    _, values, grads = grid.shape_functions(x)
    assert np.abs(values.sum(axis=1) - 1.0).max() < 1e-14
    assert values.min() >= -1e-15
    assert np.abs(grads.sum(axis=1)).max() < 1e-11


@pytest.mark.parametrize("p", DEGREES)
def test_gradients_against_finite_differences_2d(p):
    grid = SplineGrid((nonuniform_breakpoints(4, 5), nonuniform_breakpoints(5, 6)), p)
    rng = np.random.default_rng(7)
    coeffs = rng.standard_normal(grid.ndofs)
    lo = np.array([b[0] for b in grid.bounds])
    hi = np.array([b[1] for b in grid.bounds])
    x = lo + 0.05 + (hi - lo - 0.1) * rng.random((200, 2))
    _, g = grid.evaluate(coeffs, x, gradient=True)
    eps = 1e-6
    for d in range(2):
        step = np.zeros(2)
        step[d] = eps
        fd = (grid.evaluate(coeffs, x + step) - grid.evaluate(coeffs, x - step)) / (2 * eps)
        assert np.abs(fd - g[:, d]).max() < 1e-6 * max(1.0, np.abs(g).max())


@pytest.mark.parametrize("p", DEGREES)
def test_element_gbasis_matches_grid_evaluation(p):
    grid = SplineGrid((nonuniform_breakpoints(4, 8), nonuniform_breakpoints(3, 9)), p)
    basis = grid.basis()
    x = np.asarray(basis.global_coordinates())  # (2, nel, nqp)
    pts = x.reshape(2, -1).T
    coeffs = np.random.default_rng(3).standard_normal(grid.ndofs)
    via_skfem = basis.interpolate(coeffs)
    values, grads = grid.evaluate(coeffs, pts, gradient=True)
    assert np.abs(np.asarray(via_skfem).ravel() - values).max() < 1e-13
    assert np.abs(via_skfem.grad.reshape(2, -1).T - grads).max() < 1e-11


def test_extraction_interior_cells_of_uniform_cubic_are_the_known_matrix():
    C = extraction_operators(np.linspace(0.0, 1.0, 8), 3)
    # rows: the 4 local B-splines, columns: Bernstein coefficients of the
    # uniform cubic B-spline pieces (values 1/6, 4/6, 1/6 at the knots)
    expected = np.array([[1, 0, 0, 0], [4, 4, 2, 1], [1, 2, 4, 4], [0, 0, 0, 1]]) / 6.0
    for e in (3, 4):
        assert np.allclose(C[e], expected, atol=1e-15)
    # the first cell of an open knot vector starts with N_0 = B_0 (interpolation)
    assert np.allclose(C[0][0], [1, 0, 0, 0])


@BilinearForm
def laplace(u, v, _):
    return dot(grad(u), grad(v))


@BilinearForm
def mass(u, v, _):
    return u * v


def test_degree_one_equals_scikit_fem_p1_in_1d():
    u = nonuniform_breakpoints(10)
    grid = SplineGrid(u, 1)
    ours = grid.basis()
    theirs = CellBasis(grid.mesh, ElementLineP1())
    for form in (laplace, mass):
        assert abs(asm(form, ours) - asm(form, theirs)).max() < 1e-13


def test_degree_one_equals_scikit_fem_q1_in_2d():
    grid = SplineGrid((nonuniform_breakpoints(5, 1), nonuniform_breakpoints(4, 2)), 1)
    ours = grid.basis()
    theirs = CellBasis(grid.mesh, ElementQuad1(), intorder=2)
    for form in (laplace, mass):
        assert abs(asm(form, ours) - asm(form, theirs)).max() < 1e-12


def test_element_without_grid_is_the_bernstein_element_on_one_cell():
    e = ElementLineBSpline(2)
    assert e.extraction[0].shape == (1, 3, 3)
    assert np.allclose(e.extraction[0][0], np.eye(3))


@pytest.mark.parametrize("bad", [0, 4, -1, 2.0, "2", True])
def test_bad_degree(bad):
    with pytest.raises(ValueError, match="degree"):
        SplineGrid.line(0, 1, 4, bad)


@pytest.mark.parametrize("bad", [0, -3, 1.5])
def test_bad_cell_count(bad):
    with pytest.raises(ValueError, match="cells"):
        SplineGrid.line(0, 1, bad, 2)
    with pytest.raises(ValueError, match="cells"):
        SplineGrid.rectangle((0, 1), (0, 1), (4, bad), 2)


def test_decreasing_or_repeated_breakpoints():
    with pytest.raises(ValueError, match="strictly increasing"):
        SplineGrid(np.array([0.0, 0.5, 0.4, 1.0]), 2)
    with pytest.raises(ValueError, match="strictly increasing"):
        SplineGrid((np.linspace(0, 1, 3), np.array([0.0, 0.0, 1.0])), 2)
    with pytest.raises(ValueError, match="finite"):
        SplineGrid(np.array([0.0, np.nan, 1.0]), 2)


def test_unknown_side_and_component():
    grid = SplineGrid.rectangle((0, 1), (0, 1), 3, 2)
    with pytest.raises(ValueError, match="side must be one of"):
        grid.boundary_dofs("north")
    with pytest.raises(ValueError, match="side must be one of"):
        SplineGrid.line(0, 1, 3, 2).boundary_dofs("top")
    with pytest.raises(ValueError, match="component"):
        grid.boundary_dofs("left", component=2)


@pytest.mark.parametrize("p", DEGREES)
def test_boundary_dofs_are_exactly_the_functions_nonzero_on_the_side(p):
    grid = SplineGrid.rectangle((0, 2), (-1, 1), (3, 4), p)
    rng = np.random.default_rng(4)
    for side, pts in {
        "left": np.column_stack((np.zeros(50), rng.uniform(-1, 1, 50))),
        "right": np.column_stack((np.full(50, 2.0), rng.uniform(-1, 1, 50))),
        "bottom": np.column_stack((rng.uniform(0, 2, 50), np.full(50, -1.0))),
        "top": np.column_stack((rng.uniform(0, 2, 50), np.ones(50))),
    }.items():
        A, _ = dense_matrix(grid, pts)
        nonzero = np.flatnonzero(np.abs(A).max(axis=0) > 1e-14)
        assert set(nonzero) <= set(grid.boundary_dofs(side))
        # interpolation at the boundary: the side dofs alone reproduce 1
        assert np.allclose(A[:, grid.boundary_dofs(side)].sum(axis=1), 1.0)
    vec = grid.boundary_dofs("left", component=1)
    assert np.array_equal(vec, 2 * grid.boundary_dofs("left") + 1)
