"""The band factor of a narrow consistent-mass system (kernels.band_factor):
it solves its ELL system to round-off, refuses a matrix that is not
positive definite, and a 2D run switches to it where the Kronecker
preconditioner needs many iterations, on the compiled loop and the
executor alike."""
import numpy as np
import pytest

import skfem_mpm.solve.compiled_loop as compiled_loop
from skfem_mpm.benchmarks import get_benchmark
from skfem_mpm.kernels.band_factor import (apply_band_factor, ell_band_width, factor_columns,
                                           factor_layout_ok, fit_band_factor)
from skfem_mpm.solve import Method, simulate
from skfem_mpm.solve.stencil_system import StencilSystem, preconditioned_with


def _ell(dense):
    """ELL rows (entries, columns) of a dense matrix, unused slots pointing
    at their own row with a zero entry (compact_system's form)."""
    n = dense.shape[0]
    width = max(np.count_nonzero(row) for row in dense)
    A, cols = np.zeros((n, width)), np.tile(np.arange(n, dtype=np.int32)[:, None], width)
    for r in range(n):
        nz = np.flatnonzero(dense[r])
        A[r, :nz.size], cols[r, :nz.size] = dense[r, nz], nz
    return A, cols


def test_band_factor_solves_its_system_to_round_off():
    rng = np.random.default_rng(3)
    n, w = 40, 6
    dense = np.zeros((n, n))
    for d in range(1, w + 1):
        off = rng.uniform(-1, 1, n - d)
        dense += np.diag(off, d) + np.diag(off, -d)
    dense += np.diag(np.abs(dense).sum(axis=1) + 1.0)  # diagonally dominant: SPD
    A, cols = _ell(dense)
    assert ell_band_width(cols) == w
    C = np.empty((n, factor_columns(w)))
    assert fit_band_factor(A, cols, C)
    r = rng.standard_normal((n, 3))
    z = np.empty_like(r)
    apply_band_factor(C, r, z)
    assert np.abs(z - np.linalg.solve(dense, r)).max() <= 1e-13 * np.abs(z).max()
    assert factor_layout_ok(C)
    # kept warm data of the earlier layout (the columns of L only, w + 1
    # wide; a checkpoint may hold it) is refused, of odd and of even width
    assert not factor_layout_ok(np.ascontiguousarray(C[:, :w + 1]))
    assert not factor_layout_ok(np.ascontiguousarray(C[:, :w]))
    dense[n // 2, n // 2] = -1.0  # not positive definite
    A, cols = _ell(dense)
    assert not fit_band_factor(A, cols, C)


def test_band_solve_two_rows_at_a_time_of_any_size_and_band():
    """The solves take two rows of L at a time: an odd count of rows, a
    band of 0, 1 or the whole matrix, and bands wider than the rows left
    at either end all solve to round-off."""
    rng = np.random.default_rng(5)
    for n in (1, 2, 3, 4, 7, 10):
        for w in sorted({w for w in (0, 1, 2, n - 2, n - 1) if 0 <= w < n}):
            dense = np.zeros((n, n))
            for d in range(1, w + 1):
                off = rng.uniform(-1, 1, n - d)
                dense += np.diag(off, d) + np.diag(off, -d)
            dense += np.diag(np.abs(dense).sum(axis=1) + rng.uniform(1.0, 2.0, n))
            A, cols = _ell(dense)
            C = np.empty((n, factor_columns(w)))
            assert fit_band_factor(A, cols, C)
            r = rng.standard_normal((n, 2))
            z = np.empty_like(r)
            apply_band_factor(C, r, z)
            exact = np.linalg.solve(dense, r)
            assert np.abs(z - exact).max() <= 1e-13 * np.abs(exact).max(), (n, w)


@pytest.fixture(scope="module")
def plate():
    """D2 small at 16 x 16 cells, 2 x 2 particles per cell: the fast-row
    lumping breaks the Kronecker preconditioner's tensor structure (8-10
    iterations per solve), each group's box is 16 dofs wide (band 34)."""
    return get_benchmark("vibrating-plate-2d", "small").scene(16, 2, 2)


def _run(scene):
    return simulate(scene, Method(scheme="musl", mass="consistent"))


def test_plate_switches_to_the_band_factor_and_agrees(plate):
    """After the first Kronecker runs, each CG run takes at most 2
    iterations; the run agrees with the Kronecker-only run to the CG
    tolerance."""
    with preconditioned_with("kronecker+fringe") as banded:
        ours = _run(plate)
    with preconditioned_with("kronecker") as kronecker:
        theirs = _run(plate)
    print("CG iterations", sum(banded), sum(kronecker))
    assert np.median(kronecker) >= StencilSystem.BAND_FROM
    assert max(banded[8:]) <= 2 and sum(banded) < 0.5 * sum(kronecker)
    for name in ("u", "v", "stress"):
        a, b = getattr(ours.particles, name), getattr(theirs.particles, name)
        assert np.abs(a - b).max() <= 1e-10 * np.abs(b).max(), name


def test_loop_and_executor_take_the_band_factor_alike(plate, monkeypatch):
    """The compiled loop switches and factors as the executor does: the
    same bits."""
    loop = _run(plate)
    assert loop.path == "fast (compiled loop)"
    monkeypatch.setattr(compiled_loop, "ENABLED", False)
    executor = _run(plate)
    for name in ("x", "v", "stress"):
        assert np.array_equal(getattr(loop.particles, name), getattr(executor.particles, name))


def test_kept_band_factor_crosses_calls_checkpoints_and_the_executor(plate, tmp_path):
    """The band factor kept over steps (StencilSystem.BAND_KEEP) is warm
    data: the loop in one call, the loop saving every 3 steps (the factor
    handed out and back at each save), and a run whose first 10 steps the
    executor took (a callback) and which was restarted from their
    checkpoint on the loop give the same bits; on the executor's steps a
    factor serves several steps."""
    method = Method(scheme="musl", mass="consistent")
    whole = simulate(plate, method)
    saved = simulate(plate, method, save_every=3)
    path = tmp_path / "run.npz"
    factors = []  # the kept factor after each step (the arrays themselves: ids stay unique)
    simulate(plate, method, checkpoint=(path, 10),
             callback=lambda step, state: factors.append(state.warm.get("band0_factor")) or
             step < 10)
    resumed = simulate(plate, method, restart=path)
    assert whole.path == resumed.path == "fast (compiled loop)"
    kept = [f for f in factors if f is not None]
    assert len(kept) >= 6 and len({id(f) for f in kept}) <= 2, len({id(f) for f in kept})
    for other in (saved, resumed):
        for name in ("x", "v", "stress"):
            assert np.array_equal(getattr(whole.particles, name), getattr(other.particles, name)), \
                name


def test_band_factor_refitted_after_a_slow_run_alike(plate, monkeypatch):
    """With BAND_KEEP = 0 every CG run with a kept factor counts as slow:
    the next step factorises anew, on the loop as on the executor (the
    same bits), and each solve takes one iteration again."""
    monkeypatch.setattr(StencilSystem, "BAND_KEEP", 0)
    loop = _run(plate)
    assert loop.path == "fast (compiled loop)"
    with preconditioned_with("kronecker+fringe") as iterations:
        executor = _run(plate)  # (an iteration log: the executor takes every step)
    assert max(iterations[8:]) <= 1, iterations
    for name in ("x", "v", "stress"):
        assert np.array_equal(getattr(loop.particles, name), getattr(executor.particles, name))
