"""Gauss-quadrature FEM on the B-spline spaces converges at the theoretical
rates: L2 order p + 1 and H1 order p (Poisson, 1D and 2D; plane strain)."""
import numpy as np
import pytest
from skfem import BilinearForm, Functional, LinearForm, asm, condense, solve
from skfem.helpers import ddot, dot, grad, sym_grad, trace, eye

from skfem_mpm import SplineGrid
from skfem_mpm.testing import assert_order

CELLS = (4, 8, 16, 32)


@BilinearForm
def laplace(u, v, _):
    return dot(grad(u), grad(v))


def exact_1d(x):
    return np.sin(np.pi * x[0]) * np.exp(x[0])


def exact_1d_grad(x):
    return np.exp(x[0]) * (np.pi * np.cos(np.pi * x[0]) + np.sin(np.pi * x[0]))


def source_1d(x):
    # -(u'') for u = sin(pi x) e^x
    s, c, e = np.sin(np.pi * x[0]), np.cos(np.pi * x[0]), np.exp(x[0])
    return -e * (s + 2 * np.pi * c - np.pi ** 2 * s)


def exact_2d(x):
    return np.sin(np.pi * x[0]) * np.sin(2 * np.pi * x[1])


def exact_2d_grad(x):
    return np.array([np.pi * np.cos(np.pi * x[0]) * np.sin(2 * np.pi * x[1]),
                     2 * np.pi * np.sin(np.pi * x[0]) * np.cos(2 * np.pi * x[1])])


def source_2d(x):
    return 5 * np.pi ** 2 * exact_2d(x)


def poisson_errors(dim, p, n):
    grid = (SplineGrid.line(0, 1, n, p) if dim == 1
            else SplineGrid.rectangle((0, 1), (0, 1), n, p))
    basis = grid.basis()
    f = source_1d if dim == 1 else source_2d

    @LinearForm
    def load(v, w):
        return f(w.x) * v

    sides = ("left", "right") if dim == 1 else ("left", "right", "bottom", "top")
    D = np.unique(np.concatenate([grid.boundary_dofs(s) for s in sides]))
    u = solve(*condense(asm(laplace, basis), asm(load, basis), D=D))
    fine = grid.basis(intorder=2 * p + 6)
    uh = fine.interpolate(u)
    ue, ge = (exact_1d, exact_1d_grad) if dim == 1 else (exact_2d, exact_2d_grad)

    @Functional
    def l2(w):
        return (w.u - ue(w.x)) ** 2

    @Functional
    def h1(w):
        g = ge(w.x)
        if dim == 1:
            g = g[None]
        return sum((w.u.grad[i] - g[i]) ** 2 for i in range(dim))

    return np.sqrt(l2.assemble(fine, u=uh)), np.sqrt(h1.assemble(fine, u=uh))


@pytest.mark.parametrize("p", (1, 2, 3))
@pytest.mark.parametrize("dim", (1, 2))
def test_poisson_rates(dim, p):
    errors = np.array([poisson_errors(dim, p, n) for n in CELLS])
    sizes = 1.0 / np.array(CELLS)
    assert_order(errors[:, 0], sizes, expected=p + 1, tol=0.15)
    assert_order(errors[:, 1], sizes, expected=p, tol=0.15)


LAM, MU = 1.5, 1.0


def elasticity_errors(p, n):
    grid = SplineGrid.rectangle((0, 1), (0, 1), n, p)
    basis = grid.basis(vector=True)

    def epsilon(w):
        return sym_grad(w)

    @BilinearForm
    def stiffness(u, v, _):
        eu = sym_grad(u)
        return ddot(LAM * trace(eu) * eye(np.ones_like(u[0]), 2) + 2 * MU * eu, sym_grad(v))

    @LinearForm
    def load(v, w):
        x, y = w.x
        s = np.sin(np.pi * x) * np.sin(np.pi * y)
        c = np.cos(np.pi * x) * np.cos(np.pi * y)
        # u = (s, s); f = -((lam + mu) grad div u + mu lap u)
        gdiv = np.pi ** 2 * (c - s)
        f = -((LAM + MU) * gdiv - MU * 2 * np.pi ** 2 * s)
        return f * v[0] + f * v[1]

    D = np.unique(np.concatenate([
        grid.boundary_dofs(s, component=c)
        for s in ("left", "right", "bottom", "top") for c in (0, 1)
    ]))
    u = solve(*condense(asm(stiffness, basis), asm(load, basis), D=D))
    fine = grid.basis(intorder=2 * p + 6, vector=True)
    uh = fine.interpolate(u)

    @Functional
    def l2(w):
        s = np.sin(np.pi * w.x[0]) * np.sin(np.pi * w.x[1])
        return (w.u[0] - s) ** 2 + (w.u[1] - s) ** 2

    return np.sqrt(l2.assemble(fine, u=uh))


@pytest.mark.parametrize("p", (1, 2, 3))
def test_plane_strain_elasticity_rates(p):
    cells = (4, 8, 16)
    errors = [elasticity_errors(p, n) for n in cells]
    assert_order(errors, 1.0 / np.array(cells), expected=p + 1, tol=0.2)
