"""The particle-grid kernels generated from one source for 1D, 2D and 3D
(skfem_mpm.kernels.scatter / gather) against the transfer-matrix reference,
directly and through the compiled executor's binding (kernels.mpm.Kernels)."""
import os
from types import SimpleNamespace

import numpy as np
import pytest
import scipy.sparse as sp

from skfem_mpm import SplineGrid, transfer_matrices
from skfem_mpm.kernels import mpm
from skfem_mpm.kernels.serial import for_threads, serial
from skfem_mpm.kernels.transfer import Transfers

TOL = 1e-13


def tensor_grid(breakpoints, degree):
    """What the kernels read of a spline grid, for any number of axes, from
    1D spline lines (a 3D SplineGrid does not exist yet)."""
    lines = [SplineGrid(np.asarray(b, dtype=float), degree) for b in breakpoints]
    nb = tuple(g.basis_per_axis[0] for g in lines)
    return SimpleNamespace(dim=len(lines), degree=degree, ndofs=int(np.prod(nb)),
                           basis_per_axis=nb, lines=lines,
                           breakpoints=tuple(g.breakpoints[0] for g in lines),
                           _uniform=tuple(g._uniform[0] for g in lines),
                           extraction=tuple(g.extraction[0] for g in lines),
                           bounds=tuple(g.bounds[0] for g in lines))


def reference_matrices(grid, x):
    """(N, [dN/dx_d]): sparse (particles, nodes) matrices, the tensor
    products of the 1D B-splines of each axis evaluated by the NumPy
    reference of SplineGrid (node index sum_d i_d s_d, axis 0 fastest)."""
    n, dim = x.shape
    p = grid.degree
    dofs = np.zeros((n, 1), dtype=np.int64)
    values = np.ones((n, 1))
    grads = [np.ones((n, 1)) for _ in range(dim)]
    stride = 1
    for d, line in enumerate(grid.lines):
        first, w, g = line.axis_functions(0, x[:, d], backend="numpy")
        axis_dofs = (first[:, None] + np.arange(p + 1)[None, :]) * stride
        dofs = (axis_dofs[:, :, None] + dofs[:, None, :]).reshape(n, -1)
        values_new = (w[:, :, None] * values[:, None, :]).reshape(n, -1)
        grads = [((g if c == d else w)[:, :, None] * grads[c][:, None, :]).reshape(n, -1)
                 for c in range(dim)]
        values = values_new
        stride *= grid.basis_per_axis[d]
    rows = np.repeat(np.arange(n), dofs.shape[1])

    def matrix(a):
        return sp.csr_matrix((a.ravel(), (rows, dofs.ravel())), shape=(n, grid.ndofs))
    return matrix(values), [matrix(g) for g in grads]


def reference_p2g(grid, p, fext):
    N, G = reference_matrices(grid, p.x)
    dim = p.x.shape[1]
    S = p.V[:, None, None] * 0.5 * (p.stress + p.stress.transpose(0, 2, 1))
    mass = N.T @ p.m
    momentum = N.T @ (p.m[:, None] * p.v)
    force = N.T @ fext if fext is not None else np.zeros((grid.ndofs, dim))
    for c in range(dim):
        for d in range(dim):
            force[:, c] -= G[d].T @ S[:, c, d]
    return mass, momentum, force


def reference_g2p(grid, p, ga, gv, dt, vfactor, lame):
    N, G = reference_matrices(grid, p.x)
    dim = p.x.shape[1]
    acc = N @ ga
    U = N @ gv
    L = np.stack([np.stack([G[d] @ gv[:, c] for d in range(dim)], axis=-1)
                  for c in range(dim)], axis=1)
    F = np.eye(dim) + dt * L
    J = np.linalg.det(F)
    out = {"acc": acc, "v": p.v + vfactor * dt * acc, "x": p.x + dt * U, "u": p.u + dt * U,
           "L": L, "J": J}
    if lame is not None:
        D = 0.5 * dt * (L + L.transpose(0, 2, 1))
        tr = np.trace(D, axis1=1, axis2=2)
        out["stress"] = p.stress + lame[0] * tr[:, None, None] * np.eye(dim) + 2 * lame[1] * D
        out["V"] = p.V * J
    return out


def particles(grid, n, rng, order):
    """Random particles over the whole grid (boundary and interior cells),
    a few on breakpoints and on the grid's upper end (last cell)."""
    dim = grid.dim
    lo = np.array([b[0] for b in grid.bounds])
    hi = np.array([b[1] for b in grid.bounds])
    x = lo + (hi - lo) * rng.random((n, dim))
    for d in range(dim):
        x[:4, d] = hi[d]                    # the last cell's far end
        x[4:8, d] = grid.breakpoints[d][rng.integers(0, grid.breakpoints[d].size, 4)]
        x[8:10, d] = lo[d]
    if order == "cells":  # runs of particles sharing a cell (as seeded scenes)
        cells = np.zeros(n, dtype=np.int64)
        for d in reversed(range(dim)):
            e = np.clip(np.searchsorted(grid.breakpoints[d], x[:, d], side="right") - 1, 0,
                        grid.breakpoints[d].size - 2)
            cells = cells * grid.breakpoints[d].size + e
        x = x[np.argsort(cells, kind="stable")]
    else:
        x = x[rng.permutation(n)]
    V = 0.5 + rng.random(n)
    return SimpleNamespace(n=n, dim=dim, x=x, v=rng.standard_normal((n, dim)),
                           u=rng.standard_normal((n, dim)), m=1.0 + rng.random(n), V=V,
                           stress=rng.standard_normal((n, dim, dim)))


def expected_flags(grid, ref):
    """First non-finite particle, first outside the grid, first with J <= 0."""
    lo = np.array([b[0] for b in grid.bounds])
    hi = np.array([b[1] for b in grid.bounds])
    bad = ~(np.isfinite(ref["x"]).all(axis=1) & np.isfinite(ref["v"]).all(axis=1))
    out = ((ref["x"] < lo) | (ref["x"] > hi)).any(axis=1)
    return [int(np.flatnonzero(f)[0]) if f.any() else -1 for f in (bad, out, ref["J"] <= 0)]


def new_state(p):
    return SimpleNamespace(x=np.empty_like(p.x), v=np.empty_like(p.v), u=np.empty_like(p.u),
                           m=p.m, V=np.empty_like(p.V), stress=np.empty_like(p.stress))


def close(a, b, tol=TOL):
    scale = max(np.abs(a).max(), 1e-300)
    return np.abs(a - b).max() <= tol * scale


def breakpoints(kind, dim, cells, rng):
    axes = []
    for d in range(dim):
        if kind == "uniform":
            axes.append(np.linspace(-0.3, 0.9 + 0.1 * d, cells + 1))
        else:
            axes.append(np.concatenate(([0.0], np.cumsum(0.5 + rng.random(cells)))))
    return axes


# 3D cubic kernels are the costliest to compile (64 nodes a particle, the
# loops unrolled; minutes on a fresh install): their cases run in the slow
# tier; the default tier checks the same template at 3D p = 1 and 2 and at
# p = 3 in 1D and 2D.
SLOW_3D_CUBIC = pytest.mark.slow(reason="3D p = 3 compiles for minutes; the template is "
                                 "checked at 3D p <= 2 and at p = 3 in 1D/2D")
# A parallel kernel (prange over the thread blocks) compiles 3-5x slower than
# its serial copy (the same blocks in a loop, the same bits). The default
# tier checks each (dim, p, grid kind) once: the parallel template at 1D
# p = 1, 2, 3, 2D p = 2 and 3D p = 1 (every dimension and every degree
# parallel; in 3D at p = 1, whose 8 nodes a particle compile for a fraction
# of p = 2's 27: no default-tier run calls a parallel 3D kernel, runs below
# SERIAL_BELOW particles call the serial copies), the serial copies at the
# rest and at 1D p = 2 on the non-uniform grid (every dimension and degree
# serial too); the slow tier runs the other kind of each.
PARALLEL_DEFAULT = {(1, 1), (1, 2), (1, 3), (2, 2), (3, 1)}
SERIAL_DEFAULT = {(1, 2, "nonuniform")}


def _parallel_in_default(dim, p, kind):
    return (dim, p) in PARALLEL_DEFAULT and (dim, p, kind) not in SERIAL_DEFAULT


SLOW_OTHER_THREADS = pytest.mark.slow(reason="the default tier checks this (dim, p) with the "
                                      "other kind of kernel (parallel or its serial copy) "
                                      "and each kind at every dimension and degree")


def _grid_cases():
    cases = []
    for dim in (1, 2, 3):
        for p in (1, 2, 3):
            for kind in ("uniform", "nonuniform"):
                for parallel in (True, False):
                    default = (dim, p) != (3, 3) and parallel == _parallel_in_default(dim, p,
                                                                                     kind)
                    marks = () if default else \
                        SLOW_3D_CUBIC if (dim, p) == (3, 3) else SLOW_OTHER_THREADS
                    cases.append(pytest.param(dim, p, kind, parallel, marks=marks))
    return cases


GRIDS = _grid_cases()


def make(dim, p, kind, seed=0):
    rng = np.random.default_rng(seed + 100 * dim + 10 * p)
    cells = (11, 9, 8)[dim - 1]  # interior cells exist for p = 3 (p <= e < cells - p)
    return tensor_grid(breakpoints(kind, dim, cells, rng), p), rng


def test_the_default_transfer_cases_cover_every_pair():
    """Every (dim, p) but 3D cubic, both kinds of grid with each, and the
    parallel kernels and their serial copies at every dimension and every
    degree occur in the default tier; the slow tier holds the rest of the
    product."""
    default = [c.values for c in GRIDS if not c.marks]
    assert {(d, p) for d, p, _, _ in default} == {(d, p) for d in (1, 2, 3) for p in (1, 2, 3)
                                                  } - {(3, 3)}
    assert {(d, p, k) for d, p, k, _ in default} == {(d, p, k) for d, p, _, _ in default
                                                     for k in ("uniform", "nonuniform")}
    for parallel in (True, False):
        assert {d for d, _, _, par in default if par == parallel} == {1, 2, 3}
        assert {p for _, p, _, par in default if par == parallel} == {1, 2, 3}
        assert {k for _, _, k, par in default if par == parallel} == {"uniform", "nonuniform"}
    assert len(GRIDS) == 36 and len({c.values for c in GRIDS}) == 36


@pytest.mark.parametrize("dim,p,kind,parallel", GRIDS)
def test_transfers_match_the_transfer_matrices(dim, p, kind, parallel):
    """p2g, g2p2g and g2p against N and grad N of the tensor products of
    the 1D B-splines, in any order of the particles, on three thread blocks
    (overlapping node ranges), twice (the copies are cleared in between);
    the parallel kernels or their serial copies."""
    grid, rng = make(dim, p, kind)
    t = Transfers(grid, nthreads=3, parallel=parallel)
    n = (400, 600, 800)[dim - 1]
    for order in ("cells", "random"):
        p_ = particles(grid, n, rng, order)
        fext = rng.standard_normal((n, dim))
        for forces in (fext, None):
            got = t.p2g(p_, forces)
            for a, b in zip(reference_p2g(grid, p_, forces), got):
                assert close(a, b)
        ga = rng.standard_normal((grid.ndofs, dim))
        gv = rng.standard_normal((grid.ndofs, dim))
        dt = 1e-3
        v_new = np.empty_like(p_.v)
        momentum = t.g2p2g(p_, ga, dt, v_new)
        N, _ = reference_matrices(grid, p_.x)
        v_ref = p_.v + dt * (N @ ga)
        assert close(v_ref, v_new)
        assert close(N.T @ (p_.m[:, None] * v_ref), momentum)
        lame = (2.0, 0.0) if dim == 1 else (1.5, 0.7)
        ref = reference_g2p(grid, p_, ga, gv, dt, 0.5, lame)
        new = new_state(p_)
        L = np.empty((n, dim, dim))
        acc = np.empty((n, dim))
        flags = t.g2p(p_, ga, gv, dt, 0.5, True, new, L, acc, lame=lame)
        for k in ("x", "v", "u", "stress", "V"):
            assert close(ref[k], getattr(new, k)), k
        assert close(ref["acc"], acc)
        # L stored (not fused), v^new given
        new.v[:] = 7.0
        t.g2p(p_, ga, gv, dt, 0.5, False, new, L)
        assert close(ref["L"], L)
        assert np.all(new.v == 7.0)
        assert flags == expected_flags(grid, ref)


def test_the_reference_is_the_2d_spline_space():
    """The tensor-product reference above equals the transfer matrices of a
    2D SplineGrid (scikit-fem's element and dofs)."""
    rng = np.random.default_rng(3)
    for kind in ("uniform", "nonuniform"):
        axes = breakpoints(kind, 2, 6, rng)
        grid2 = SplineGrid(tuple(axes), 2)
        grid = tensor_grid(axes, 2)
        x = particles(grid, 200, rng, "random").x
        N, G = transfer_matrices(grid2, x)
        Nt, Gt = reference_matrices(grid, x)
        assert abs(N - Nt).max() < 1e-14
        for a, b in zip(G, Gt):
            assert abs(a - b).max() < 1e-12 * abs(a).max()


# 3D p = 2: the serial copies, as 3D runs call them (PARALLEL_DEFAULT)
BY_DIMENSION = [(1, True), (2, True), (3, False),
                pytest.param(3, True, marks=SLOW_OTHER_THREADS)]


@pytest.mark.parametrize("dim, parallel", BY_DIMENSION)
def test_flags_name_the_first_bad_particle_of_each_kind(dim, parallel):
    """A NaN velocity, particles moved out of the grid and a compression
    to J <= 0 are each reported at their first particle."""
    grid, rng = make(dim, 2, "uniform")
    n = 300
    p_ = particles(grid, n, rng, "random")
    t = Transfers(grid, nthreads=2, parallel=parallel)
    ga = np.zeros((grid.ndofs, dim))
    p_.v[:] = 0.0
    p_.v[n - 40] = np.nan
    index = np.arange(grid.ndofs) % grid.basis_per_axis[0]  # node index along axis 0
    cases = (np.zeros((grid.ndofs, dim)),                      # only the NaN
             np.ones((grid.ndofs, dim)),                       # everything moves by dt
             -np.outer(index, np.ones(dim)) / grid.lines[0].h[0])  # dv_x/dx ~ -1 / h^2
    seen = set()
    for gv in cases:
        for dt in (0.05, 1.0):
            ref = reference_g2p(grid, p_, ga, gv, dt, 1.0, None)
            expected = expected_flags(grid, ref)
            new = new_state(p_)
            assert t.g2p(p_, ga, gv, dt, 1.0, True, new, np.empty((n, dim, dim))) == expected
            seen.update(k for k, f in enumerate(expected) if f >= 0)
    assert seen == {0, 1, 2}


# ------------------------------------------------ the executor's binding
@pytest.mark.parametrize("dim, parallel", BY_DIMENSION)
def test_executor_kernels_run_the_generated_transfers(dim, parallel):
    """kernels.mpm.Kernels (what the compiled executor calls) on the
    generated transfers: p2g, g2p2g and g2p with the fused linear elastic
    update (1D: sigma += E dt L; else the Lame parameters) and the kept
    acceleration, against the transfer matrices, in 1D, 2D and 3D."""
    grid, rng = make(dim, 2, "nonuniform", seed=5)
    k = mpm.Kernels(grid, parallel)
    n = 300
    p_ = particles(grid, n, rng, "cells")
    fext = rng.standard_normal((n, dim))
    for a, b in zip(reference_p2g(grid, p_, fext), k.p2g(p_, fext)):
        assert close(a, b)
    ga = rng.standard_normal((grid.ndofs, dim))
    gv = rng.standard_normal((grid.ndofs, dim))
    v_new = np.empty_like(p_.v)
    N, _ = reference_matrices(grid, p_.x)
    momentum = k.g2p2g(p_, ga, 1e-3, v_new)
    assert close(N.T @ (p_.m[:, None] * (p_.v + 1e-3 * (N @ ga))), momentum)
    material = SimpleNamespace(E=3.0, lam=1.5, mu=0.7)
    lame = (material.E, 0.0) if dim == 1 else (material.lam, material.mu)
    ref = reference_g2p(grid, p_, ga, gv, 1e-3, 0.5, lame)
    new, acc = new_state(p_), np.empty((n, dim))
    flags = k.g2p(p_, ga, gv, 1e-3, 0.5, True, True, material, new, np.empty((1, 1, 1)), acc)
    assert flags == expected_flags(grid, ref)
    for name in ("x", "v", "u", "stress", "V"):
        assert close(ref[name], getattr(new, name)), name
    assert close(ref["acc"], acc)


# ------------------------------------------------ Runge-Kutta stage rates
@pytest.mark.parametrize("dim,p,kind,parallel", [
    (1, 1, "uniform", True), (1, 2, "nonuniform", True), (1, 3, "uniform", True),
    (2, 2, "uniform", True), (2, 3, "nonuniform", False), (3, 2, "nonuniform", False),
    pytest.param(2, 3, "nonuniform", True, marks=SLOW_OTHER_THREADS),
    pytest.param(3, 2, "nonuniform", True, marks=SLOW_OTHER_THREADS)])
def test_stage_rates_match_the_transfer_matrices(dim, p, kind, parallel):
    """The rates gather (one Runge-Kutta right-hand side) against N and
    grad N: N v, N a, V tr L, and the linear elastic stress rate
    lambda tr(D) I + 2 mu D (D = sym L; 1D: E L) or L, on three blocks
    (the parallel kernel or its serial copy: PARALLEL_DEFAULT)."""
    grid, rng = make(dim, p, kind, seed=7)
    t = Transfers(grid, nthreads=3, parallel=parallel)
    n = (300, 500, 700)[dim - 1]
    p_ = particles(grid, n, rng, "random")
    ga = rng.standard_normal((grid.ndofs, dim))
    gv = rng.standard_normal((grid.ndofs, dim))
    N, G = reference_matrices(grid, p_.x)
    L = np.stack([np.stack([G[d] @ gv[:, c] for d in range(dim)], axis=-1)
                  for c in range(dim)], axis=1)
    lame = (2.0, 0.0) if dim == 1 else (1.5, 0.7)
    D = 0.5 * (L + L.transpose(0, 2, 1))
    tr = np.trace(D, axis1=1, axis2=2)
    stress_rate_ref = lame[0] * tr[:, None, None] * np.eye(dim) + 2 * lame[1] * D
    out = [np.full((n, dim), np.nan), np.full((n, dim), np.nan),
           np.full((n, dim, dim), np.nan), np.full((n, dim, dim), np.nan), np.full(n, np.nan)]
    t.rates(p_, ga, gv, *out, lame=lame)
    x_rate, v_rate, L_out, stress_rate, V_rate = out
    assert close(N @ gv, x_rate) and close(N @ ga, v_rate)
    assert close(p_.V * tr, V_rate)
    assert close(stress_rate_ref, stress_rate)
    assert np.isnan(L_out).all()  # fused: L is not stored
    t.rates(p_, ga, gv, *out)
    assert close(L, L_out)


def test_stage_combination_is_the_weighted_sum_of_the_rates():
    """kernels.staging.combine_stages against NumPy: y_n + sum_s c_s k_s
    per field, u moved by the same dx as x, stages with c_s = 0 skipped,
    the stress and V fields only with ``small``, F only with ``finite``."""
    from skfem_mpm.kernels.staging import combine_stages

    combine_stages = serial(combine_stages)  # the copy Runge-Kutta runs below SERIAL_BELOW call
    rng = np.random.default_rng(11)
    n, dim, stages = 57, 2, 4
    y = [rng.standard_normal(s) for s in ((n, dim), (n, dim), (n, dim), (n, dim, dim), (n,),
                                          (n, dim, dim))]
    k = [rng.standard_normal((stages,) + a.shape) for a in (y[0], y[2], y[3], y[4], y[5])]
    k[0][2] = np.nan  # a stage with weight 0 is never read
    c = np.array([0.1, 0.2, 0.0, 0.4])
    for small, finite in ((True, False), (False, True)):
        out = [np.full_like(a, 7.0) for a in y]
        combine_stages(c, *y, *k, small, finite, *out, 3)
        used = [0, 1, 3]

        def summed(start, rate):
            return start + sum(c[s] * rate[s] for s in used)

        dx = summed(np.zeros_like(y[0]), k[0])
        assert close(y[0] + dx, out[0]) and close(y[1] + dx, out[1])
        assert close(summed(y[2], k[1]), out[2])
        if small:
            assert close(summed(y[3], k[2]), out[3]) and close(summed(y[4], k[3]), out[4])
            assert (out[5] == 7.0).all()
        else:
            assert close(summed(y[5], k[4]), out[5])
            assert (out[3] == 7.0).all() and (out[4] == 7.0).all()


# ------------------------------------------------- consistent mass, any dimension
@pytest.mark.parametrize("p", [2, 3])
def test_the_1d_consistent_stencil_is_n_transpose_m_n(p):
    """The 1D stencil of Kernels (consistent_1d: the closed-form weights on
    the interior cells of a uniform axis, extraction elsewhere; then
    reduce_stencil) as a matrix is N^T diag(m) N of the transfer-matrix
    reference, and its stiffness weights sum m (dN_k/dx)^2, on a uniform
    and a graded axis with particles in every cell."""
    rng = np.random.default_rng(p)
    for breaks in (np.linspace(0.0, 2.0, 11), np.array([0.0, 0.3, 0.5, 1.1, 1.2, 1.6, 2.0])):
        x = np.sort(rng.uniform(0.0, 2.0, 200))[:, None]
        particles = SimpleNamespace(x=x, m=0.5 + rng.random(200))
        kernels = mpm.Kernels(SplineGrid(breaks, p), False)
        stencil, K = kernels.consistent_stencil(particles)
        N, G = reference_matrices(tensor_grid((breaks,), p), x)
        M = (N.T @ sp.diags(particles.m) @ N).toarray()
        assert np.abs(kernels.stencil_csr(stencil).toarray() - M).max() <= TOL * np.abs(M).max()
        stiff = G[0].multiply(G[0]).T @ particles.m
        assert np.abs(K - stiff).max() <= TOL * np.abs(stiff).max()


# the serial copies (what runs below SERIAL_BELOW call; the same blocks, the
# same bits): the parallel consistent_axes compiles for about 15 s of CPU and
# only the slow tier's case compiles it
@pytest.mark.parametrize("p, parallel", [
    (1, False), (2, False), (3, False),
    pytest.param(2, True, marks=pytest.mark.slow(reason="the parallel 3D consistent-mass "
                                                 "assembly compiles for about 15 s"))])
def test_consistent_stencil_of_any_dimension_is_n_transpose_m_n(p, parallel):
    """The 3D stencil of Kernels (consistent_axes, reduce_stencil, the 3D
    slot numbering) as a matrix is N^T diag(m) N of the transfer-matrix
    reference, and its stiffness weights sum m |grad N_k|^2; on a 2D grid
    consistent_axes gives what consistent_2d gives (1e-15)."""
    grid = SplineGrid((np.array([0.0, 0.5, 1.0, 1.2, 2.0]), np.linspace(0.0, 0.75, 4),
                       np.array([0.0, 0.4, 0.8, 1.2])), p)
    rng = np.random.default_rng(p)
    n = 300
    lo = np.array([0.0, 0.0, 0.0])
    hi = np.array([1.4, 0.6, 0.85])  # partly filled: empty rows and cut supports
    x = lo + (hi - lo) * rng.random((n, 3))
    x = x[np.lexsort(x.T[::-1])]
    particles = SimpleNamespace(x=x, m=0.5 + rng.random(n))
    kernels = mpm.Kernels(grid, parallel)
    stencil, K = kernels.consistent_stencil(particles)
    ref = tensor_grid(grid.breakpoints, p)
    N, G = reference_matrices(ref, x)
    M = (N.T @ sp.diags(particles.m) @ N).toarray()
    assert np.abs(kernels.stencil_csr(stencil).toarray() - M).max() <= TOL * np.abs(M).max()
    stiff = sum(G[d].multiply(G[d]).T @ particles.m for d in range(3))
    assert np.abs(K - stiff).max() <= TOL * np.abs(stiff).max()

    plane = SplineGrid((np.array([0.0, 0.5, 1.0, 1.2, 2.0]), np.linspace(0.0, 0.75, 4)), p)
    k2 = mpm.Kernels(plane, parallel)
    flat = SimpleNamespace(x=np.ascontiguousarray(x[:, :2]), m=particles.m)
    S2, K2 = [a.copy() for a in k2.consistent_stencil(flat)]
    touched = k2._stencil_touched
    consistent_axes = for_threads(mpm.consistent_axes, parallel)
    consistent_axes(flat.x, flat.m, *k2.args[0], *k2.args[1], *k2.args[0], p, k2.nbx,
                    plane.basis_per_axis[1], k2._stencil_copies, k2._stiff_copies, touched)
    S, K = np.zeros_like(S2), np.zeros_like(K2)
    for_threads(mpm.reduce_stencil, parallel)(
        k2._stencil_copies, k2._stiff_copies, touched, int(touched[:, 0].min()),
        int(touched[:, 1].max()), *k2.stencil_geometry, S, K)
    assert np.abs(S - S2).max() <= 1e-15 * np.abs(S2).max() * 10
    assert np.abs(K - K2).max() <= 1e-15 * np.abs(K2).max() * 10


@pytest.mark.parametrize("p", [pytest.param(1, marks=pytest.mark.slow), 2])  # p = 1 compiles its own kernels
def test_consistent_stencil_rows_emptied_since_the_last_assembly_are_zero(p):
    """reduce_stencil writes a row whose diagonal M_kk is 0 as zero without
    summing or mirroring it: assembled once over a filled block and then
    over two clumps apart (their touched ranges span the rows between
    them, filled before and empty now), the stencil is N^T diag(m) N of the
    second particles and K their sum m |grad N_k|^2; for p = 1 a particle
    on a grid line has N_k = 0 but grad N_k != 0 on the row across it."""
    grid = SplineGrid.rectangle((0, 1), (0, 2), (12, 10), p)
    ref = tensor_grid(grid.breakpoints, p)
    rng = np.random.default_rng(5)
    kernels = mpm.Kernels(grid, True)
    filled = rng.random((400, 2)) * [1.0, 2.0]
    kernels.consistent_stencil(SimpleNamespace(x=filled, m=0.5 + rng.random(400)))
    left = rng.random((60, 2)) * [0.2, 2.0]
    right = [0.8, 0.0] + rng.random((60, 2)) * [0.2, 2.0]
    on_line = np.array([[0.25, 1.0], [0.75, 0.5]])  # x on the grid lines 3 / 12 and 9 / 12
    x = np.concatenate([left, on_line, right])
    x = x[np.lexsort(x.T[::-1])]
    clumps = SimpleNamespace(x=x, m=0.5 + rng.random(x.shape[0]))
    stencil, K = kernels.consistent_stencil(clumps)
    N, G = reference_matrices(ref, x)
    M = (N.T @ sp.diags(clumps.m) @ N).toarray()
    between = np.zeros((grid.basis_per_axis[1], grid.basis_per_axis[0]), dtype=bool)
    between[:, p + 3:grid.basis_per_axis[0] - p - 3] = True
    assert np.all(M[between.ravel()] == 0.0)  # the clumps leave rows empty between them
    assert np.abs(kernels.stencil_csr(stencil).toarray() - M).max() <= TOL * np.abs(M).max()
    stiff = sum(G[d].multiply(G[d]).T @ clumps.m for d in range(2))
    assert np.abs(K - stiff).max() <= TOL * np.abs(stiff).max()


@pytest.mark.parametrize("dim", [1, 2])
def test_serial_consistent_mass_gives_the_parallel_bits_in_boundary_cells(dim):
    """The serial copies of consistent_1d and consistent_2d (their boundary
    cells' weights from a copy of _axis compiled without numba's runtime,
    serial._NO_RUNTIME) give the parallel kernels' stencil and stiffness
    weights to a few units of round-off (the compilers contract a * b + c
    into one rounding in different places), on uniform and non-uniform
    axes (the latter in every cell), particles in every cell."""
    for kind in ("uniform", "nonuniform"):
        rng = np.random.default_rng(dim)
        axes = breakpoints(kind, dim, 8, rng)
        grid = SplineGrid(np.asarray(axes[0], dtype=float) if dim == 1 else
                          tuple(np.asarray(b, dtype=float) for b in axes), 2)
        lo = np.array([b[0] for b in axes])
        hi = np.array([b[-1] for b in axes])
        x = lo + (hi - lo) * rng.random((500, dim))
        x = x[np.lexsort(x.T[::-1])]
        particles = SimpleNamespace(x=x, m=0.5 + rng.random(500))
        got = [[a.copy() for a in mpm.Kernels(grid, parallel).consistent_stencil(particles)]
               for parallel in (True, False)]
        for a, b in zip(*got):
            assert np.abs(a - b).max() <= 4e-16 * np.abs(a).max(), kind


def test_three_factor_kronecker_on_one_layer_is_the_two_factor_one():
    """apply_kronecker_axes with nz = 1 repeats apply_kronecker bit for bit
    (same passes, same order), and with three factors it is the inverse of
    S^-1 (M_z (x) M_y (x) M_x) S^-1 on a full box (dense check)."""
    from skfem_mpm.kernels.kronecker import apply_kronecker, apply_kronecker_axes

    # the serial copies (the same blocks, the same bits), which the small
    # runs call: the parallel apply_kronecker_axes compiles for about 10 s
    apply_kronecker, apply_kronecker_axes = serial(apply_kronecker), serial(apply_kronecker_axes)
    rng = np.random.default_rng(7)

    def factor(n):  # a banded Cholesky factor (p = 2) with 1 / L_ii in column 0
        return np.c_[1.0 / (1.0 + rng.random(n)), 0.3 * rng.random((n, 2))]

    for ny, nx, nc in ((5, 7, 2), (1, 9, 3)):
        Lx, Ly = factor(nx), factor(ny)
        nr = ny * nx - 3
        local = rng.permutation(ny * nx)[:nr].astype(np.int64)
        local[0] = -1  # a lumped row
        inv = 0.5 + rng.random(nr)
        r = rng.standard_normal((nr, nc))
        z2, z3 = np.empty_like(r), np.empty_like(r)
        apply_kronecker(Lx, Ly, local, inv, np.empty((ny, nx, nc)), 2, r, z2)
        one = np.array([[0, 1, ny, nx, 0, 0, 0]], dtype=np.int64)  # one box, one layer
        apply_kronecker_axes(Lx, Ly, np.ones((1, 3)), local, inv, np.empty(ny * nx * nc), 2,
                             one, r, z3)
        assert np.array_equal(z2, z3)

    def dense(L):  # (L L^T) from the stored factor
        n = L.shape[0]
        full = np.zeros((n, n))
        for i in range(n):
            full[i, i] = 1.0 / L[i, 0]
            for d in range(1, 3):
                if i - d >= 0:
                    full[i, i - d] = L[i, d]
        return full @ full.T

    nz, ny, nx = 3, 4, 5
    Lx, Ly, Lz = factor(nx), factor(ny), factor(nz)
    nr = nx * ny * nz
    local = np.arange(nr, dtype=np.int64)
    inv = 0.5 + rng.random(nr)
    r = rng.standard_normal((nr, 2))
    z = np.empty_like(r)
    box = np.array([[0, nz, ny, nx, 0, 0, 0]], dtype=np.int64)
    apply_kronecker_axes(Lx, Ly, Lz, local, inv, np.empty(nr * 2), 2, box, r, z)
    M = np.kron(dense(Lz), np.kron(dense(Ly), dense(Lx)))
    S = np.diag(1.0 / inv)
    assert np.abs(S @ M @ S @ z - r).max() < 1e-10 * np.abs(r).max()


def test_sorted_distinct_is_np_unique():
    """kernels.scatter._sorted_distinct (insertion sort for the few cut
    points of the per-thread reduction) gives np.unique's result."""
    from skfem_mpm.kernels.scatter import _sorted_distinct

    rng = np.random.default_rng(1)
    for n in (0, 1, 2, 5, 9, 40):
        for _ in range(10):
            values = rng.integers(-3, 9, size=n + 1).astype(np.int64)
            np.testing.assert_array_equal(_sorted_distinct(values), np.unique(values))


@pytest.mark.parametrize("dim", [2, 3])
def test_p2g_writes_the_grid_near_the_particles_only(dim):
    """reduce_fields rewrites only the nodes of the particles' hull and of
    the last call's (Transfers.occupied), on arrays that start as zeros:
    with particles in one corner, then in the opposite one, then in the
    first again, p2g's arrays equal the sum of the per-thread copies over
    every node (zero outside the hull: nothing stale), and the one-pass USL grid
    step on those ranges gives the a and v of a pass over every node. The
    serial copies (those compiled for small runs), three thread blocks."""
    grid, rng = make(dim, 2, "uniform")
    t = Transfers(grid, nthreads=3, parallel=False)
    nd = grid.ndofs
    lo = np.array([b[0] for b in grid.bounds])
    hi = np.array([b[1] for b in grid.bounds])
    full = np.array([0, nd, 0, nd])
    usl = for_threads(mpm.usl_grid, False)
    mask = np.zeros((nd, dim), dtype=bool)
    mask[:3] = True  # constrained dofs far from the second corner
    a, v = np.zeros((nd, dim)), np.zeros((nd, dim))
    for corner in (0.25, 0.6, 0.25):
        p_ = particles(grid, 60, rng, "cells")
        p_.x = lo + (hi - lo) * (corner + 0.15 * rng.random((60, dim)))
        mass, momentum, force = (x.copy() for x in t.p2g(p_))
        copies, touched = t.copies(1 + 2 * dim)
        first, last = int(touched[:, 0].min()), int(touched[:, 1].max())
        assert tuple(t.occupied[:2]) == (first, last) and 0 < first and last < nd
        summed = copies.sum(axis=0)  # the copies are zero outside their ranges
        everywhere = (summed[:, 0], summed[:, 1:1 + dim], summed[:, 1 + dim:])
        for got, want in zip((mass, momentum, force), everywhere):
            assert np.array_equal(got, want)
            assert not np.any(got[:first]) and not np.any(got[last:])
        gravity = np.full(dim, -2.0)
        a_all, v_all = np.full((nd, dim), np.nan), np.full((nd, dim), np.nan)
        usl(mass, momentum, force, gravity, mask, force, force, False, 0.1, a_all, v_all,
            full.copy())
        usl(mass, momentum, force, gravity, mask, force, force, False, 0.1, a, v, t.occupied)
        assert np.array_equal(a, a_all) and np.array_equal(v, v_all)
        assert tuple(t.occupied[2:]) == (first, last)


@pytest.mark.parametrize("dim", [2, 3])
def test_kronecker_boxes_follow_the_coupled_components(dim):
    """2D and 3D: the Kronecker preconditioner of KroneckerData.of_system
    takes one box per coupled component of the matrix
    (kernels.kronecker.kronecker_boxes): two blocks of free dofs, each a
    Kronecker product of its own banded factors, within the stencil's
    reach of each other but not coupled (zero entries between them), and
    dofs coupled to nothing: the preconditioner is the exact inverse (P = A
    wherever A is a Kronecker product, kernels.kronecker's docstring); one
    box over both blocks is not. In 2D the boxes are one layer each (the z
    factor of length 1, not applied), and without ``by_component`` (a
    single body, or the fringe correction's one box) the free dofs take one
    box."""
    from skfem_mpm.kernels.kronecker import KroneckerData, apply_kronecker, apply_kronecker_axes

    apply = serial(apply_kronecker_axes)
    rng = np.random.default_rng(3)
    p, nb = 2, 12
    width = 2 * p + 1
    ns = width ** dim
    nbz = nb if dim == 3 else 1

    def banded(n):  # SPD, positive entries, bandwidth p
        K = np.diag(2.0 + rng.random(n))
        for d, size in ((1, 0.5), (2, 0.1)):
            if n > d:  # (2D: the z factor is 1 x 1)
                off = size * rng.random(n - d)
                K += np.diag(off, d) + np.diag(off, -d)
        return K

    # block 0: a in 1..4; block 1: a in 6..9 (2 = p apart: stencil slots
    # between them exist, their entries are 0); both b, c in 2..5 and 3..7
    z_axis = (3, 8) if dim == 3 else (0, 1)
    blocks = [((1, 5), (2, 6), z_axis), ((6, 10), (2, 6), z_axis)]
    factors = [[banded(hi - lo) for lo, hi in axes] for axes in blocks]
    lonely = [(11, 0, 0), (0, 11, 11 if dim == 3 else 0)]  # coupled to nothing
    owner, local = {}, {}
    for i, axes in enumerate(blocks):
        for c in range(*axes[2]):
            for b in range(*axes[1]):
                for a in range(*axes[0]):
                    k = (c * nb + b) * nb + a
                    owner[k] = i
                    local[k] = (a - axes[0][0], b - axes[1][0], c - axes[2][0])
    rows = np.array(sorted(list(owner) + [(c * nb + b) * nb + a for a, b, c in lonely]))
    index = np.full(nb * nb * nbz, -1, dtype=np.int64)
    index[rows] = np.arange(rows.size)

    def offsets(s):
        dc = s // (width * width) - p if dim == 3 else 0
        return s % width - p, (s // width) % width - p, dc

    A = np.zeros((rows.size, ns))
    for r, k in enumerate(rows):
        a, b, c = k % nb, (k // nb) % nb, k // (nb * nb)
        if k not in owner:
            A[r, (ns - 1) // 2] = 1.5 + r
            continue
        Kx, Ky, Kz = factors[owner[k]]
        la, lb, lc = local[k]
        for s in range(ns):
            da, db, dc = offsets(s)
            j = ((c + dc) * nb + b + db) * nb + a + da
            if owner.get(j, -1) == owner[k]:
                ja, jb, jc = local[j]
                A[r, s] = Kx[la, ja] * Ky[lb, jb] * Kz[lc, jc]
    dense = np.zeros((rows.size, rows.size))
    for r, k in enumerate(rows):
        a, b, c = k % nb, (k // nb) % nb, k // (nb * nb)
        for s in np.flatnonzero(A[r]):
            da, db, dc = offsets(s)
            dense[r, index[((c + dc) * nb + b + db) * nb + a + da]] = A[r, s]
    x = rng.standard_normal((rows.size, 2))
    b = dense @ x
    kron = KroneckerData.of_system(A, rows, (p, nb, nb, dim), index=index, by_component=True)
    assert kron.boxes.shape[0] == 2
    if dim == 2:
        assert kron.factor_shape[0] == 1 and not kron.boxes[:, 6].any()
    assert np.array_equal(np.flatnonzero(kron.local < 0), index[[(c * nb + b_) * nb + a
                                                                 for a, b_, c in lonely]])
    z = np.empty_like(b)
    apply(*kron.args(2, 2), b, z)
    assert np.abs(z - x).max() < 1e-12 * np.abs(x).max()
    # one box over both blocks (the rows of both as one component): not exact
    joined = A.copy()
    first = [r for r, k in enumerate(rows) if owner.get(k) == 0 and local[k][0] == 3]
    joined[first, (ns - 1) // 2 + 2] = 1e-300  # a coupling to block 1 (a + 2)
    one = KroneckerData.of_system(joined, rows, (p, nb, nb, dim), index=index,
                                  by_component=True)
    if dim == 3:
        assert one.boxes.shape[0] == 1
        apply(*one.args(2, 2), b, z)
    else:  # one component: the one box of the free dofs (apply_kronecker's arguments)
        assert one.boxes is None and len(one.args(2, 1)) == 6
        serial(apply_kronecker)(*one.args(2, 1), b, z)
    assert np.abs(z - x).max() > 1e-3 * np.abs(x).max()
    if dim == 2:  # without by_component (a single body): the one box, also for two components
        boxed = KroneckerData.of_system(A, rows, (p, nb, nb, dim), index=index)
        assert boxed.boxes is None
        serial(apply_kronecker)(*boxed.args(2, 1), b, z)
        assert np.abs(z - x).max() > 1e-3 * np.abs(x).max()


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="reads VmRSS (Linux)")
def test_lazy_zeros_take_memory_only_where_written():
    """kernels.pages.lazy_zeros: C-contiguous writable zeros whose pages are
    mapped on first write: reading all of 64 MiB maps (nearly) nothing,
    writing a quarter maps about that quarter."""
    from skfem_mpm.kernels.pages import lazy_zeros

    def rss_mib():
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
        raise AssertionError("no VmRSS")

    size = 64 << 20
    before = rss_mib()
    a = lazy_zeros((size // 8 // 4, 4))
    assert a.flags.c_contiguous and a.flags.writeable and a.dtype == np.float64
    assert a.sum() == 0.0
    read = rss_mib() - before
    a[: a.shape[0] // 4] = 1.0
    written = rss_mib() - before
    assert read < 4 and 12 < written - read < 24, (read, written)


def test_small_lazy_zeros_are_numpy_zeros_and_large_ones_are_mapped():
    """kernels.pages.lazy_zeros maps its own memory from LAZY_FROM bytes
    only: below, a fresh mapping's page faults at the first write would be
    paid by every run of a small scene (a D2 16 x 16 run took 38 of them
    per call of simulate), for a few pages of memory saved."""
    import mmap

    from skfem_mpm.kernels.pages import LAZY_FROM, lazy_zeros
    from skfem_mpm.kernels.transfer import Transfers
    from skfem_mpm.spline import SplineGrid

    def mapped(a):
        base = a
        while isinstance(base, np.ndarray) and base.base is not None:
            base = base.base
        return isinstance(getattr(base, "obj", base), mmap.mmap)  # (frombuffer's memoryview)

    small = lazy_zeros((LAZY_FROM // 8 - 1,))
    large = lazy_zeros((LAZY_FROM // 8, 1))
    assert not mapped(small) and small.sum() == 0.0 and small.flags.c_contiguous
    assert mapped(large) and large.sum() == 0.0
    t = Transfers(SplineGrid.rectangle((0, 1), (0, 1), cells=(16, 16), degree=2), nthreads=2)
    copies, _ = t.copies(5)
    assert not any(mapped(a) for a in (t.mass, t._momentum, t._force, copies))


def test_serial_conjugate_gradients_let_converged_columns_leave():
    """The serial ell_pcg (its passes compiled without numba's runtime,
    serial._NO_RUNTIME_COPIES; its iterations in a loop that assigns no
    array, the columns packed between such loops) on three columns: one
    converged by its warm start, two converging at different iterations.
    Each solves A x = b to its tolerance and the iterations are the
    slowest column's in a NumPy Jacobi PCG with the same stopping rule."""
    for name in ("_ell_product_dot", "_cg_update", "_cg_direction", "_dots"):
        assert serial(getattr(mpm, name)).targetoptions.get("_nrt") is False, name
    rng = np.random.default_rng(17)
    n, ns = 80, 5
    offsets = np.arange(ns) - ns // 2
    cols = np.clip(np.arange(n)[:, None] + offsets, 0, n - 1)
    inside = (np.arange(n)[:, None] + offsets >= 0) & (np.arange(n)[:, None] + offsets < n)
    dense = np.zeros((n, n))
    for k in range(1, 3):  # symmetric off-diagonals, a dominant diagonal
        band = rng.uniform(0.1, 1.0, n - k)
        dense[np.arange(n - k), np.arange(k, n)] = band
        dense[np.arange(k, n), np.arange(n - k)] = band
    dense[np.arange(n), np.arange(n)] = 4.5 + rng.uniform(0.0, 20.0, n)
    A = np.where(inside, dense[np.arange(n)[:, None], cols], 0.0)
    cols = np.where(inside, cols, np.arange(n)[:, None]).astype(np.int32)
    exact = rng.standard_normal((n, 3))
    inv_diag = 1.0 / np.diag(dense)
    # an eigenvector of the Jacobi-scaled matrix: one iteration
    scaled = np.sqrt(inv_diag)[:, None] * dense * np.sqrt(inv_diag)
    exact[:, 1] = np.sqrt(inv_diag) * np.linalg.eigh(scaled)[1][:, 7]
    b = dense @ exact
    x = np.zeros((n, 3))
    x[:, 0] = exact[:, 0]  # converged by the warm start
    rtol = 1e-10
    its = serial(mpm.ell_pcg)(A, cols, inv_diag, None, None, b, x, np.arange(3), rtol, 500, 1,
                              np.zeros((6, n, 3)))

    def reference(bc):
        xc = np.zeros(n)
        r = bc.copy()
        z = inv_diag * r
        d = z.copy()
        it = 0
        while r @ r > rtol ** 2 * (bc @ bc):
            q = dense @ d
            alpha = (r @ z) / (d @ q)
            xc += alpha * d
            r_new = r - alpha * q
            z_new = inv_diag * r_new
            d = z_new + (r_new @ z_new) / (r @ z) * d
            r, z = r_new, z_new
            it += 1
        return it

    counts = [reference(b[:, c]) for c in (1, 2)]
    assert 0 < counts[0] < counts[1] and its == counts[1]
    for c in range(3):
        assert np.linalg.norm(dense @ x[:, c] - b[:, c]) <= 2 * rtol * np.linalg.norm(b[:, c])
