"""Random particle layouts (hypothesis): ppc per axis 1-4, degree 1-3, 1D
and 2D, random positions and velocities; over a few steps of a run, the
mass and momentum that reach the grid equal the particle totals to 1e-12
(partition of unity of the B-splines), on the NumPy reference and on the
compiled kernels."""
import numpy as np
from hypothesis import given, settings, strategies as st

from skfem_mpm import Body, LinearElastic, Method, Particles, Scene, SplineGrid, simulate
from skfem_mpm.kernels.mpm import Kernels
from skfem_mpm.kernels.serial import SERIAL_BELOW
from skfem_mpm.solve import particles_to_grid


@st.composite
def scenes(draw):
    dim = draw(st.sampled_from([1, 2]))
    degree = draw(st.integers(1, 3))
    cells = draw(st.integers(2, 9))
    ppc = tuple(draw(st.integers(1, 4)) for _ in range(dim))
    seed = draw(st.integers(0, 2 ** 31 - 1))
    grid = (SplineGrid.line(0.0, 1.0, cells, degree) if dim == 1 else
            SplineGrid.rectangle((0.0, 1.0), (0.0, 2.0), (cells, cells + 1), degree))
    rng = np.random.default_rng(seed)
    parts = Particles.seed(grid, ppc if dim == 2 else ppc[0], 1.0 + rng.random(),
                           layout=draw(st.sampled_from(["random", "uniform"])), seed=seed,
                           velocity=lambda X: 1e-3 * rng.standard_normal(X.shape))
    parts = parts.replaced(m=parts.m * (0.5 + rng.random(parts.n)))   # unequal masses
    return Scene(grid, Body(parts, LinearElastic(1.0, 0.2)), 1.0)


def check_totals(state):
    p = state.particles
    mass, momentum = p.m.sum(), p.m @ p.v
    scale = np.abs(p.m[:, None] * p.v).sum(axis=0) + 1e-300
    data = particles_to_grid(state)
    assert abs(data.lumped.sum() - mass) <= 1e-12 * mass
    assert np.all(np.abs(data.momentum.sum(axis=0) - momentum) <= 1e-12 * scale)
    # the kernels such a run calls (below SERIAL_BELOW particles: the serial
    # copies); the parallel ones are checked against the transfer matrices
    # in tests/test_kernels_generic.py
    m_fast, mv_fast, _ = Kernels(state.grid, parallel=p.n >= SERIAL_BELOW).p2g(p, None)
    assert abs(m_fast.sum() - mass) <= 1e-12 * mass
    assert np.all(np.abs(mv_fast.sum(axis=0) - momentum) <= 1e-12 * scale)


@settings(max_examples=40, deadline=None)
@given(scenes())
def test_mass_and_momentum_reach_the_grid(scene):
    checked = []

    def callback(step, state):
        check_totals(state)
        checked.append(step)
        return step < 3

    # a random particle may sit within one step of the edge: exits are removed
    simulate(scene, Method(scheme="usl", cfl=0.2, on_exit="remove"), callback=callback)
    assert checked == [1, 2, 3]
