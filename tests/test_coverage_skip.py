"""The fast-dof guard's coverage pass is skipped only where it changes nothing.

kernels.coverage_skip.coverage_holds keeps the sums of the last pass when
a bound shows that no row can reach the lumping threshold; the guard's
lumping fractions of the kept sums must then be those of a new pass, bit
for bit (all zero), on particles moved by up to the bound's delta. The
limits put the pass's largest ratio from 1e-9 to 0.4999 of the threshold,
and the body's end from 1e-3 delta to 2 delta short of a cell face.
"""
from types import SimpleNamespace

import numpy as np
import pytest

from skfem_mpm.kernels.coverage_skip import coverage_holds, coverage_reach
from skfem_mpm.kernels.mpm import Kernels
from skfem_mpm.solve.timestep import (coverage_bound, covered_parameters, covered_stiffness,
                                      fast_dof_weights, lumping_fraction)
from skfem_mpm.spline import SplineGrid


def _block(grid, gap):
    """A body of about 3 particles per cell and axis (12 per axis, from h / 6
    into cell 1) whose last particles sit ``gap`` short of a cell face (the
    next cell's functions are reached by a shift of ``gap``)."""
    h = 1.0 / 8
    axes = [np.linspace(h + h / 6, 5 * h - gap, 12)] * grid.dim
    x = np.stack([a.ravel() for a in np.meshgrid(*axes, indexing="ij")], axis=1)
    return x, np.full(x.shape[0], 0.01)


def _theta(grid, sums, mass, guard, limit):
    """The guard's lumping fractions (the executor's fast_row_fractions)."""
    weights, ratios, moving, lo, hi, tail, floor = guard
    K, D, m = sums
    k = covered_stiffness(K, D, m, weights, ratios, moving, tail, floor, limit, grid.degree,
                          grid.basis_per_axis)
    with np.errstate(invalid="ignore"):
        theta = lumping_fraction(k / (limit * np.maximum(D, 1e-300)))
    return np.where(mass > 0.0, theta, 0.0)


def _setting(dim):
    """A quadratic 8-cell grid in ``dim`` dimensions, its serial kernels, the
    skip's bound and the guard's arguments (tls)."""
    grid = (SplineGrid.line(0.0, 1.0, 8, 2) if dim == 1 else
            SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), 8, 2))
    weights, ratios = fast_dof_weights(grid)
    guard = (weights, ratios, np.ones(grid.ndofs), *covered_parameters(grid, "tls"))
    return grid, Kernels(grid, parallel=False), coverage_bound(grid), guard


def _first_pass(grid, k, bound, guard, gap):
    """The block ``gap`` short of a face: its particles (x0, m), the pass's
    sums, their reach W_k and the pass's largest ratio T_k / D_k (limit inf:
    no withdrawal)."""
    x0, m = _block(grid, gap)
    kept = k.particle_coverage(SimpleNamespace(x=x0, m=m)).copy()
    axes = list(k.args) + [k.args[0]] * (3 - grid.dim)
    nby = grid.basis_per_axis[1] if grid.dim > 1 else 1
    reach = np.zeros(grid.ndofs)
    coverage_reach(x0, m, *axes[0], *axes[1], *axes[2], grid.degree, grid.basis_per_axis[0],
                   nby, bound[0], reach)
    unit = covered_stiffness(*kept, *guard[:3], *guard[5:], np.inf, grid.degree,
                             grid.basis_per_axis)
    top = np.max(np.where(kept[1] > 0, unit / np.maximum(kept[1], 1e-300), 0.0))
    return x0, m, kept, reach, top


@pytest.mark.parametrize("dim", [1, 2])
def test_kept_coverage_gives_the_lumping_of_a_new_pass(dim):
    grid, k, bound, guard = _setting(dim)
    delta = bound[0]
    rng = np.random.default_rng(1)
    kept_right = skipped = wrong_if_skipped = 0
    # the body's end within delta of a face (a sliver of the next cell's
    # functions from a shift of 1e-3 delta on), or not
    for gap in (1e-3 * delta, 0.6 * delta, 2.0 * delta):
        # limits that put the pass's largest ratio at 1e-9 .. 0.4999 of the
        # threshold 0.5
        x0, m, kept, reach, top = _first_pass(grid, k, bound, guard, gap)
        for trial in range(60):
            d = delta * 10.0 ** rng.uniform(-7.0, 0.2) * (0.0 if trial == 0 else 1.0)
            shift = rng.normal(size=dim)
            jitter = rng.normal(size=x0.shape) * (0.3 * d / np.sqrt(dim))
            x = x0 + d * 0.6 * shift / np.linalg.norm(shift) + jitter
            if np.max(np.linalg.norm(x - x0, axis=1)) > 1.5 * delta:
                continue
            fresh = k.particle_coverage(SimpleNamespace(x=x, m=m)).copy()
            mass = fresh[2]
            for share in (1e-9, 0.1, 0.3, 0.45, 0.49, 0.4999):
                limit = top / share
                old = _theta(grid, kept, mass, guard[:7], limit)
                new = _theta(grid, fresh, mass, guard[:7], limit)
                holds = coverage_holds(x, m, x0, m, kept, reach, bound, *guard, limit)
                if holds:
                    skipped += 1
                    assert np.array_equal(old, new), (gap, trial, share)
                    kept_right += 1
                elif not np.array_equal(old, new) and \
                        np.max(np.linalg.norm(x - x0, axis=1)) <= delta:
                    wrong_if_skipped += 1
    # the check is not empty: passes were skipped, and within delta some
    # moves changed the lumping (a bound that ignored the motion would skip them)
    assert skipped > 20 and wrong_if_skipped > 5, (skipped, wrong_if_skipped)


def test_the_bound_asks_for_a_pass_when_the_particles_change():
    grid = SplineGrid.line(0.0, 1.0, 8, 2)
    k = Kernels(grid, parallel=False)
    x0, m = _block(grid, 0.05)
    kept = k.particle_coverage(SimpleNamespace(x=x0, m=m)).copy()
    reach = np.zeros(grid.ndofs)
    axes = list(k.args) * 3
    coverage_reach(x0, m, *axes[0], *axes[1], *axes[2], 2, grid.ndofs, 1, coverage_bound(grid)[0],
                   reach)
    weights, ratios = fast_dof_weights(grid)
    guard = (weights, ratios, np.ones(grid.ndofs), *covered_parameters(grid, "tls"), 1e9)
    bound = coverage_bound(grid)
    assert coverage_holds(x0, m, x0, m, kept, reach, bound, *guard)
    assert not coverage_holds(x0[1:], m[1:], x0, m, kept, reach, bound, *guard)
    assert not coverage_holds(x0, 2 * m, x0, m, kept, reach, bound, *guard)
    far = x0 + 1.01 * bound[0]
    assert not coverage_holds(far, m, x0, m, kept, reach, bound, *guard)


@pytest.mark.parametrize("dim", [1, 2])
def test_a_pass_that_fails_its_own_test_is_not_kept(dim):
    """coverage_holds at zero displacement with reach = D (the question a
    pass asks of its own sums before it stores the reach) fails only where
    the bound of every later move fails too, and Kernels.particle_coverage
    keeps nothing after such a pass."""
    grid, k, bound, guard = _setting(dim)
    x0, m, kept, reach, top = _first_pass(grid, k, bound, guard, 2.0 * bound[0])
    rng = np.random.default_rng(2)
    own_failed = later_held = 0
    for share in (0.3, 0.49, 0.4999, 0.5001, 0.6, 2.0):
        limit = top / share
        own = coverage_holds(x0, m, x0, m, kept, kept[1], bound, *guard, limit)
        own_failed += not own
        for trial in range(40):
            d = bound[0] * 10.0 ** rng.uniform(-7.0, 0.0)
            x = x0 + rng.normal(size=x0.shape) * (d / np.sqrt(2 * dim))
            holds = coverage_holds(x, m, x0, m, kept, reach, bound, *guard, limit)
            assert own or not holds, (share, trial)
            later_held += holds
        # the executor stores the reach and the positions only after a pass
        # that passes its own test
        k.particle_coverage(SimpleNamespace(x=x0, m=m), (bound, *guard, limit))
        assert (k._coverage[4][0] is not None) == own, share
    assert own_failed >= 3 and later_held > 20, (own_failed, later_held)
