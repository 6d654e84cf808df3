"""The 2D TLS, 2D spline and 2D mls steps' grid sums per cell, factorised
per axis (skfem_mpm.kernels.cell_integrals, CompiledReconstruction's
CELL_INTEGRALS), equal the sums over the cells' Gauss points as quadrature
particles (the path test_recon_compiled and test_executors check against
the NumPy reference) to rounding: the same quadrature summed in another
order (TLS and the spline in closed form: the p + 2 point rule is exact
for both fits (TLS: total degree 2; the spline: cubic per axis) times the
basis; mls: its values at the Gauss points, point_axis_tables).
Quadratic and cubic, uniform and graded grids (closed-form B-splines and
extraction), cells a free surface cuts (particle points), serial and
parallel kernels. The loop's copy of the path gives the executor's bits
(test_compiled_loop's tls cases run it)."""
from types import SimpleNamespace

import numpy as np
import pytest

from skfem_mpm.kernels import tls as tls_kernel
from skfem_mpm.kernels.cell_integrals import (cell_momentum, point_axis_tables,
                                              spline_axis_tables)
from skfem_mpm.kernels.stencil import axis_functions
from skfem_mpm.kernels.gauss_rule import locate_cells
from skfem_mpm.kernels.mpm import Kernels
from skfem_mpm.kernels.serial import serial
from skfem_mpm.solve.compiled_reconstruct import CompiledReconstruction
from skfem_mpm.solve.timing import PhaseTimer
from test_recon_compiled import axes_of, kernel_rule, layouts_tls

LAYOUTS_2D = [c for c in layouts_tls() if c[1].dim == 2]


def _reconstruction(grid, cells, parallel, name="tls"):
    recon = CompiledReconstruction.__new__(CompiledReconstruction)
    recon._setup(grid, name, {})
    if not cells:
        recon.cell_tables = None  # the Gauss points as quadrature particles
    recon.kernels = Kernels(grid, parallel=parallel)
    return recon


def _state():
    return SimpleNamespace(timer=PhaseTimer(), method=SimpleNamespace(needs_consistent_mass=True))


def _particles(p, seed):
    """p with a velocity, a stress and masses that vary smoothly and by noise."""
    rng = np.random.default_rng(seed)
    x = p.x
    v = np.column_stack((np.sin(3 * x[:, 0]) + x[:, 1], x[:, 0] * x[:, 1] - 0.5))
    v += 0.1 * rng.normal(size=v.shape)
    stress = rng.normal(size=(p.n, 2, 2)) + (1.0 + x[:, 0] ** 2)[:, None, None]
    m = p.V * (1.0 + 0.3 * x[:, 0] - 0.2 * x[:, 1] + 0.05 * rng.uniform(size=p.n))
    return p.replaced(v=v, stress=stress, m=m)


def _close(a, b, tol=1e-13):
    scale = np.abs(b).max()
    assert scale > 0.0
    assert np.abs(a - b).max() <= tol * scale


@pytest.mark.parametrize("fit", ("tls", "spline", "mls"))
@pytest.mark.parametrize("parallel", (False, pytest.param(True, marks=pytest.mark.slow)),
                         ids=("serial", "parallel"))
@pytest.mark.parametrize("name, grid, p", LAYOUTS_2D,
                         ids=lambda v: v if isinstance(v, str) else "")
def test_the_fitted_cells_integrals_are_the_gauss_point_sums(name, grid, p, parallel, fit):
    """Lumped mass, momentum, force (with a body force's density), the
    consistent mass stencil and sum rho_h |grad N_k|^2, and the MUSL
    projection's momentum: the cells' closed form against the Gauss points
    to 1e-13 of the largest entry."""
    p = _particles(p, 11)
    volume = np.column_stack((p.V * 2.0, -p.V * (1.0 + p.x[:, 0])))
    v_new = p.v + 0.01 * p.x
    out = {}
    for cells in (False, True):
        recon = _reconstruction(grid, cells, parallel, fit)
        mass, momentum, force, (stencil, K), projection = recon.to_grid(_state(), p, volume)
        fields = [a.copy() for a in (mass, momentum, force, stencil, K)]
        fields.append(recon.project(_state(), p, v_new, projection).copy())
        out[cells] = fields
    if name == "2D disk":
        assert projection[0].particle_points.size > 0  # cut cells' particle points
    for by_cell, by_point in zip(out[True], out[False]):
        _close(by_cell, by_point)


@pytest.mark.parametrize("name, grid, p", LAYOUTS_2D,
                         ids=lambda v: v if isinstance(v, str) else "")
def test_the_tls_coefficients_are_the_fit_at_the_gauss_points(name, grid, p):
    """tls_coefficients' monomial coefficients, evaluated at the cells'
    Gauss points in each cell's frame, are tls_apply's fit there (the same
    level per column; a noisy column takes the lower levels)."""
    rng = np.random.default_rng(4)
    values = rng.normal(size=(p.n, 4))
    values[:, 1] = 2.0 + p.x[:, 0] - 3.0 * p.x[:, 1] ** 2
    values[:, 2] = 1.0
    rule = kernel_rule(grid, p)
    pcell = locate_cells(p.x, *axes_of(grid))
    factor = serial(tls_kernel.tls_factor)(p.x, p.V, pcell, rule.x, rule.w, rule.cell,
                                           grid.ncells)
    at_points = np.empty((rule.x.shape[0], 4))
    serial(tls_kernel.tls_apply)(p.x, p.V, values, rule.x, factor, at_points)
    coef = np.empty((factor[5].shape[0], 6, 4))
    serial(tls_kernel.tls_coefficients)(p.x, p.V, values, rule.x, factor, coef)
    cells = tls_kernel.slot_cells(factor, rule.cell)
    slot = np.empty(grid.ncells, dtype=np.int64)
    slot[cells] = np.arange(cells.size)
    s = slot[rule.cell]
    frame = factor[4][s]
    xi = (rule.x[:, 0] - frame[:, 0]) / frame[:, 3]
    eta = (rule.x[:, 1] - frame[:, 1]) / frame[:, 4]
    phi = np.column_stack((np.ones_like(xi), xi, eta, xi * xi, xi * eta, eta * eta))
    evaluated = np.einsum("gr,grk->gk", phi, coef[s])
    assert np.abs(evaluated - at_points).max() <= 1e-12 * np.abs(at_points).max()
    assert np.array_equal(coef[:, 1:, 2], np.zeros_like(coef[:, 1:, 2])) or \
        np.abs(coef[:, 1:, 2]).max() < 1e-12


@pytest.mark.parametrize("name, grid, p", LAYOUTS_2D[-2:],
                         ids=lambda v: v if isinstance(v, str) else "")
def test_the_spline_tables_are_exact_with_the_cells_rule(name, grid, p):
    """spline_axis_tables' integrals of a cubic B-spline times the grid's
    functions (degree 3 + 2p per axis) with the cells' p + 2 point rule
    equal those of a rule three points longer: the rule is exact, so the
    closed form is the Gauss-point sums' own value."""
    recon = _reconstruction(grid, True, False, "spline")
    cubic = recon.spline_ls.axes
    for a in range(2):
        ref, wref = np.polynomial.legendre.leggauss(grid.degree + 5)
        longer = spline_axis_tables(recon.axes[a], recon.uniform[a], grid.extraction[a],
                                    grid.degree, cubic[a][3], 0.5 * (ref + 1), 0.5 * wref)
        for table, exact in zip(recon.cell_tables[a], longer):
            assert np.abs(table - exact).max() <= 1e-14 * np.abs(exact).max()


@pytest.mark.parametrize("name, grid, p", LAYOUTS_2D[-2:],
                         ids=lambda v: v if isinstance(v, str) else "")
def test_the_point_tables_are_the_rules_terms(name, grid, p):
    """point_axis_tables' entries are the rule's terms of each Gauss point
    of each cell, h_i w_j N_a(x_j) and so on (x_j = u_i + h_i r_j), from
    the grid's own basis functions; rows of k = p + 2 points."""
    recon = _reconstruction(grid, True, False, "mls")
    k = grid.degree + 2
    for a in range(2):
        P, D, Q, R = recon.cell_tables[a]
        u = recon.axes[a]
        n = u.size - 1
        assert P.shape == (n, k, 4) and Q.shape == (n, k, 4, 4)
        for i in range(n):
            h = u[i + 1] - u[i]
            for j in range(k):
                x = u[i] + h * recon.ref[j]
                f = axis_functions(x, u, recon.uniform[a], n / (u[-1] - u[0]),
                                   grid.extraction[a], grid.degree)
                assert f[0] == i
                w, g = np.array(f[1:5]), np.array(f[5:9])
                weight = h * recon.wref[j]
                assert np.allclose(P[i, j], weight * w, rtol=1e-14, atol=0)
                assert np.allclose(D[i, j], weight * g, rtol=1e-14, atol=0)
                assert np.allclose(R[i, j], weight * g * g, rtol=1e-14, atol=0)
                assert np.allclose(Q[i, j], weight * np.outer(w, w), rtol=1e-14, atol=0)


def test_the_cell_kernels_refuse_tables_of_the_other_fit():
    """One set of kernels serves both fits, the kind taken from coef's
    shape (TLS (ns, 6, k), 3 y terms; the spline (nbf nby, k), 4): tables
    of the other kind are refused with an error naming tx and ty, not
    summed with the wrong number of terms."""
    ncx, p, nbx = 2, 2, 4
    tls_tables = tuple(np.zeros((ncx, 3, 4)) for _ in range(2))
    spline_tables = tuple(np.zeros((ncx, 4, 4)) for _ in range(2))
    cells = np.array([0, 3])
    copies = np.zeros((1, nbx * nbx, 2))
    touched = np.array([[nbx * nbx, -1]])
    for coef, tables in ((np.zeros((2, 6, 2)), spline_tables),
                         (np.zeros(((ncx + 3) ** 2, 2)), tls_tables),
                         (np.zeros((2, 4, 4, 2)), tls_tables)):
        with pytest.raises(ValueError, match="tx, ty"):
            cell_momentum(coef, cells, ncx, (tables[0],) * 4, (tables[1],) * 4, p, nbx,
                          copies, touched)
