"""The stencil CG's preconditioner variants (``preconditioned_with``): each
solves the consistent-mass run that the sparse LU solves, they differ in
iterations only, and leaving the block restores the default."""
import numpy as np
import pytest

from skfem_mpm.bench import consistent_scene
from skfem_mpm.solve import Method, simulate
from skfem_mpm.solve.stencil_system import (PRECONDITIONERS, StencilSystem,
                                            preconditioned_with)


@pytest.fixture(scope="module")
def expanding_block():
    """A 16 x 16 consistent MUSL run with stress waves, by sparse LU."""
    scene, dt = consistent_scene(16, 10, "expanding block")
    lu = simulate(scene, Method(scheme="musl", mass="consistent", mass_solver="direct", dt=dt))
    return scene, dt, lu


def _cg_run(scene, dt):
    return simulate(scene, Method(scheme="musl", mass="consistent", mass_solver="cg", dt=dt))


def test_invalid_preconditioner_is_refused():
    with pytest.raises(ValueError, match="preconditioner must be one of 'kronecker\\+fringe', "
                                         "'kronecker', 'lumped', got 'jacobi'"):
        with preconditioned_with("jacobi"):
            pass


@pytest.mark.parametrize("preconditioner", PRECONDITIONERS)
def test_each_preconditioner_solves_what_the_sparse_lu_solves(expanding_block, preconditioner):
    """Ten MUSL steps (two solves each) agree with the sparse LU run to the
    CG tolerance (relative residual 1e-13 per solve)."""
    scene, dt, lu = expanding_block
    with preconditioned_with(preconditioner) as iterations:
        result = _cg_run(scene, dt)
    assert len(iterations) >= 2 * result.counts["steps"]
    for name in ("u", "v", "stress"):
        ours, exact = getattr(result.particles, name), getattr(lu.particles, name)
        assert np.abs(ours - exact).max() <= 1e-10 * np.abs(exact).max(), name


def test_preconditioners_differ_in_iterations_and_the_default_comes_back(expanding_block,
                                                                         monkeypatch):
    """The lumped (Jacobi) preconditioner needs the most CG iterations, the
    Kronecker one fewer, the fringe correction fewer again (turned on for
    this grid's 324 dofs, below FRINGE_MIN_ROWS); after the blocks (one
    left by an exception) the default run is bit for bit the run before
    them."""
    scene, dt, _ = expanding_block
    before = _cg_run(scene, dt)
    totals = {}
    for preconditioner in PRECONDITIONERS:
        with preconditioned_with(preconditioner) as iterations, monkeypatch.context() as m:
            m.setattr(StencilSystem, "FRINGE_MIN_ROWS", 0)
            _cg_run(scene, dt)
        totals[preconditioner] = sum(iterations)
    print("CG iterations:", totals)
    assert totals["lumped"] > 1.5 * totals["kronecker"] > 1.5 * totals["kronecker+fringe"]
    with pytest.raises(RuntimeError), preconditioned_with("lumped"):
        raise RuntimeError("leaves the block")
    assert (StencilSystem.preconditioner, StencilSystem.FRINGE_LAYERS,
            StencilSystem.iteration_log) == ("kronecker", 3, None)
    after = _cg_run(scene, dt)
    for name in ("x", "v", "stress"):
        assert np.array_equal(getattr(before.particles, name), getattr(after.particles, name))
