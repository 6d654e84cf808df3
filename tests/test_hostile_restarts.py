"""Restarts and determinism: a run interrupted after a checkpoint and
continued from it ends bit for bit equal to the uninterrupted run, on every
configuration listed; identical runs are identical bit for bit.

What a thread count changes (README, "Reliability"): the compiled scatter
gives each thread its own copy of the grid arrays and sums the copies, so
grid sums are added in another order with another thread count; results
then differ by rounding (1e-16 relative per step, grown by the run). At a
fixed thread count every run is bit-for-bit reproducible, and a restart
must use the thread count of the run that wrote the checkpoint to continue
it bit for bit.
"""
import numpy as np
import pytest

from skfem_mpm import (Body, Damping, Fixed, Gravity, LinearElastic, Method, NeoHookean,
                       Particles, Prescribed, Scene, SplineGrid, Traction, simulate)
from skfem_mpm.benchmarks import get_benchmark

# each case is bounded (tests/conftest.py): one that hangs fails by its name
# instead of hanging the suite; the bound leaves room for a cold numba
# compile under load
pytestmark = pytest.mark.timeout(300)


def s1(cells=8, p=2):
    return get_benchmark("vibrating-string", "small", L=1.0).scene(cells, p, 2)


def column():
    return get_benchmark("soil-column", "small").scene(8, 2, 2)


def bar_1d(material=None, effects=None, t_end=0.05):
    grid = SplineGrid.line(0.0, 1.0, 8, 2)
    p = Particles.seed(grid, 2, 1.0, region=((0.0, 0.75),),
                       velocity=lambda X: 0.2 * np.sin(np.pi * X))
    effects = [Fixed("left"), Traction("right", 0.1)] if effects is None else effects
    return Scene(grid, Body(p, material or LinearElastic(100.0, 0.3)), t_end, effects=effects)


def block_2d(material=None, effects=None):
    grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (4, 4), 2)
    p = Particles.seed(grid, 2, 1.0, region=((0.0, 0.75), (0.0, 0.75)),
                       velocity=lambda X: np.column_stack((0.1 * X[:, 1], -0.1 * X[:, 0])))
    effects = [Gravity((0.0, -1.0)), Fixed("bottom")] if effects is None else effects
    return Scene(grid, Body(p, material or LinearElastic(100.0, 0.3)), 0.05, effects=effects)


def flying():  # particles leave the grid and are removed
    grid = SplineGrid.line(0.0, 1.0, 8, 2)
    p = Particles.seed(grid, 2, 1.0, region=((0.5, 0.95),), velocity=lambda X: 3.0 + 0 * X)
    return Scene(grid, Body(p, LinearElastic(10.0)), 0.1)


def two_bodies():
    grid = SplineGrid.line(0.0, 1.0, 8, 2)
    a = Particles.seed(grid, 2, 1.0, region=((0.0, 0.4),), velocity=lambda X: 0.1 + 0 * X)
    b = Particles.seed(grid, 2, 2.0, region=((0.5, 0.9),))
    return Scene(grid, [Body(a, LinearElastic(50.0)), Body(b, LinearElastic(80.0))], 0.05,
                 effects=[Gravity(-1.0), Damping(0.05)])


def plastic(dim):
    from test_state import CappedPlasticCompiled, bar_scene

    return bar_scene(CappedPlasticCompiled(10.0, 0.3), dim, steps=14)


SCENES = {"s1": s1, "s1-p3": lambda: s1(8, 3), "column": column, "bar": bar_1d,
          "bar-neo": lambda: bar_1d(NeoHookean(100.0, 0.3)), "2d": block_2d,
          "2d-neo": lambda: block_2d(NeoHookean(100.0, 0.3)),
          "2d-prescribed": lambda: block_2d(effects=[Fixed("bottom"),
                                                     Prescribed("top", 1, lambda t: -0.1 * t)]),
          "flying": flying, "two-bodies": two_bodies, "plastic-1d": lambda: plastic(1),
          "plastic-2d": lambda: plastic(2)}

# (scene, method options, save_every, checkpoint every): the default tier
# runs the first of each group on the reference executor and the compiled
# one; the rest are slow
CONFIGS = [
    ("s1", dict(), 3, 4), ("s1", dict(scheme="usl"), 2, 3), ("s1", dict(scheme="usf"), 5, 2),
    ("s1", dict(scheme="cd"), None, 3), ("s1", dict(scheme="rk4"), 2, 2),
    ("s1", dict(mass="consistent"), 3, 4), ("s1", dict(mass="consistent", scheme="cd"), 1, 5),
    ("s1", dict(mass="consistent", mass_solver="cg"), 3, 4),
    ("s1", dict(mass="hybrid"), 3, 3), ("s1", dict(mass="consistent", scheme="rk4"), 2, 2),
    ("s1", dict(reconstruction="spline", mass="consistent"), 2, 3),
    ("s1", dict(reconstruction="tls", mass="consistent"), 2, 3),
    ("s1-p3", dict(mass="consistent", scheme="cd"), 4, 3),
    ("column", dict(mass="consistent"), 7, 10), ("column", dict(scheme="cd"), 7, 10),
    ("bar", dict(), 2, 3), ("bar", dict(scheme="cd"), None, 4),
    ("bar-neo", dict(), 3, 3), ("bar-neo", dict(scheme="rk4"), 2, 2),
    ("2d", dict(), 2, 3), ("2d", dict(mass="consistent"), 2, 3), ("2d", dict(scheme="cd"), 3, 2),
    ("2d-neo", dict(), 2, 3), ("2d-prescribed", dict(), 2, 3),
    ("flying", dict(on_exit="remove"), 2, 3), ("two-bodies", dict(), 2, 3),
    ("plastic-1d", dict(), 3, 4), ("plastic-2d", dict(scheme="usl"), 3, 4),
]
DEFAULT = {0, 3, 5, 15, 19, 24}


def _params():
    out = []
    for backend in ("numpy", "numba"):
        for i, (scene, options, save_every, every) in enumerate(CONFIGS):
            marks = () if i in DEFAULT else (pytest.mark.slow,)
            name = f"{backend}-{scene}-{'-'.join(map(str, options.values())) or 'musl'}-{i}"
            out.append(pytest.param(backend, scene, options, save_every, every, marks=marks,
                                    id=name))
    return out


def assert_identical(a, b):
    for k in ("x", "v", "u", "stress", "V", "m"):
        assert np.array_equal(getattr(a.particles, k), getattr(b.particles, k)), k
    for k, values in a.particles.state.items():
        assert np.array_equal(values, b.particles.state[k]), k
    assert np.array_equal(a.times, b.times)
    for k in ("x", "v", "stress"):
        ha, hb = a.history[k], b.history[k]
        assert len(ha) == len(hb) and all(np.array_equal(p, q) for p, q in zip(ha, hb)), k
    for k, values in a.energies.items():
        assert np.array_equal(values, b.energies[k]), k
    # how many steps the compiled loop took says how the steps ran (a run
    # with a callback steps in Python), not what they computed
    ignore = {"compiled_loop_steps"}
    assert {k: v for k, v in a.counts.items() if k not in ignore} == \
        {k: v for k, v in b.counts.items() if k not in ignore}


@pytest.mark.parametrize("backend, scene, options, save_every, every", _params())
def test_a_restart_continues_bit_for_bit(tmp_path, backend, scene, options, save_every, every):
    make = SCENES[scene]
    method = Method(backend=backend, **options)
    full = simulate(make(), method, save_every=save_every)
    assert scene != "flying" or full.counts["removed"] > 0
    steps = full.counts["steps"]
    stop = max(every, (steps // (2 * every)) * every + 1)  # past a checkpoint, not on one
    path = tmp_path / "run.npz"
    simulate(make(), method, save_every=save_every, checkpoint=(path, every),
             callback=lambda step, state: step < stop)
    resumed = simulate(make(), method, save_every=save_every, restart=path)
    assert_identical(resumed, full)


@pytest.mark.parametrize("backend", ["numpy", "numba"])
@pytest.mark.parametrize("options", [dict(mass="consistent"), dict(mass="consistent", scheme="cd"),
                                     dict(mass="hybrid"), dict()])
def test_identical_runs_are_identical_bit_for_bit(backend, options):
    """mass_solver="auto" chooses by size, never by timing: two runs of one
    scene and method agree to the last bit (at one thread count)."""
    a = simulate(s1(16), Method(backend=backend, **options), save_every=5)
    b = simulate(s1(16), Method(backend=backend, **options), save_every=5)
    assert_identical(a, b)


def test_the_restart_list_is_at_least_the_issues():
    assert len(_params()) >= 41
