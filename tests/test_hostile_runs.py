"""Hostile runs: nothing lost, nothing handed out changes afterwards.

A failed run always ends in SimulationError carrying a finite last good
state and its time; what a callback or a Result hands out is never written
again by later steps.
"""
import numpy as np
import pytest

from skfem_mpm import (Body, Fixed, Gravity, LinearElastic, Method, NeoHookean, Particles,
                       Scene, SimulationError, SplineGrid, simulate)
from skfem_mpm.benchmarks import get_benchmark

# each case is bounded (tests/conftest.py): one that hangs fails by its name
# instead of hanging the suite; the bound leaves room for a cold numba
# compile under load
pytestmark = pytest.mark.timeout(300)

BACKENDS = ["numpy", "numba"]


def s1_scene(cells=8):
    return get_benchmark("vibrating-string", "small", L=1.0).scene(cells, 2, 2)


def block_2d(material=None):
    grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (4, 4), 2)
    p = Particles.seed(grid, 2, 1.0, region=((0.0, 0.75), (0.0, 0.75)))
    return Scene(grid, Body(p, material or LinearElastic(100.0, 0.3)), 0.05,
                 effects=[Gravity((0.0, -1.0)), Fixed("bottom")])


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_callback_writing_nan_in_place_stops_with_a_finite_last_good_state(backend):
    def poison(step, state):
        if step == 5:
            state.particles.v[1] = np.nan

    with pytest.raises(SimulationError, match=r"callback left a non-finite value in "
                                              r"particles.v \(particle 1\) after step 5") as info:
        simulate(s1_scene(), Method(backend=backend), callback=poison)
    exc = info.value
    r = exc.result
    assert exc.step == 5 and r.counts["steps"] == 5
    for k in ("x", "v", "stress", "V"):
        assert np.isfinite(getattr(r.particles, k)).all(), k
    assert r.final_time == pytest.approx(5 * r.dt)


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_blow_up_reports_the_time_of_its_last_good_state_without_saves(backend):
    s = s1_scene()
    scene = Scene(s.grid, s.bodies, 20.0, s.effects)  # long enough to blow up
    dt_crit = simulate(s, Method(backend=backend)).dt_crit
    with pytest.raises(SimulationError) as info:
        simulate(scene, Method(backend=backend, dt=3 * dt_crit, allow_unstable=True),
                 save_every=None)
    exc = info.value
    r = exc.result
    assert r.counts["steps"] == exc.step - 1 > 0
    assert r.final_time == pytest.approx((exc.step - 1) * r.dt) == exc.time
    assert np.isfinite(r.particles.x).all() and np.isfinite(r.particles.v).all()


@pytest.mark.parametrize("error", [ArithmeticError("CG did not converge"),
                                   ZeroDivisionError("float division by zero"),
                                   np.linalg.LinAlgError("Singular matrix")])
def test_an_arithmetic_failure_inside_a_step_is_a_simulation_error(monkeypatch, error):
    import importlib

    module = importlib.import_module("skfem_mpm.solve.simulate")

    steps = dict(module.SCHEME_STEPS)
    original = steps["musl"]

    def failing(ops, state):
        if state.step == 3:
            raise error
        return original(ops, state)

    monkeypatch.setattr(module, "SCHEME_STEPS", {**steps, "musl": failing})
    with pytest.raises(SimulationError, match=f"step 4 .* failed: {error}") as info:
        simulate(s1_scene(), Method(backend="numpy"))
    r = info.value.result
    assert r.counts["steps"] == 3 and np.isfinite(r.particles.x).all()


def test_a_checkpoint_path_that_is_a_folder_is_refused_before_the_first_step(tmp_path):
    with pytest.raises(ValueError, match="checkpoint path .* is a folder"):
        simulate(s1_scene(), Method(backend="numpy"), checkpoint=(tmp_path, 3))


# ----------------------------------------------------------- handed out
def _arrays(p):
    arrays = {k: getattr(p, k) for k in ("x", "v", "u", "stress", "V", "F")
              if getattr(p, k) is not None}
    arrays.update({f"state.{k}": a for k, a in p.state.items()})
    return arrays


def _kept_states(scene, method):
    """What each callback was handed: the Particles object, its arrays and
    copies of them."""
    kept = []

    def keep(step, state):
        p = state.particles
        kept.append((p, {k: (a, a.copy()) for k, a in _arrays(p).items()}))

    r = simulate(scene, method, callback=keep)
    return r, kept


HANDED = [
    ("s1", {}), ("s1", dict(scheme="cd")), ("s1", dict(scheme="usl")),
    ("s1", dict(mass="consistent")), ("s1", dict(scheme="rk4")),
    ("s1", dict(reconstruction="spline")), ("2d", {}), ("2d-neo", {}),
    ("plastic-1d", {}), ("plastic-2d", {}),  # a material state: double-buffered too
]


def plastic(dim):
    from test_state import CappedPlasticCompiled, bar_scene

    return bar_scene(CappedPlasticCompiled(10.0, 0.3), dim, steps=12)


@pytest.mark.parametrize("which, options", [
    pytest.param(w, o, id=f"{w}-{'-'.join(map(str, o.values())) or 'musl'}",
                 marks=() if (w, o) in (("s1", {}), ("plastic-1d", {})) else pytest.mark.slow)
    for w, o in HANDED])
def test_particles_handed_to_a_callback_are_never_written_again(which, options):
    scene = {"s1": s1_scene, "2d": block_2d,
             "2d-neo": lambda: block_2d(NeoHookean(100.0, 0.3)),
             "plastic-1d": lambda: plastic(1), "plastic-2d": lambda: plastic(2)}[which]()
    r, kept = _kept_states(scene, Method(backend="numba", **options))
    changed = [(i, k) for i, (_, arrays) in enumerate(kept) for k, (a, copy) in arrays.items()
               if not np.array_equal(a, copy)]
    assert not changed, f"{len(changed)} handed-out arrays changed, first {changed[:3]}"
    # nor is the Particles object handed out given other arrays
    rebound = [(i, k) for i, (p, arrays) in enumerate(kept) for k, a in _arrays(p).items()
               if k not in arrays or a is not arrays[k][0]]
    assert not rebound, f"{len(rebound)} handed-out attributes re-bound, first {rebound[:3]}"
    final = {k: getattr(r.particles, k).copy() for k in ("x", "v", "stress")}
    simulate(scene, Method(backend="numba", **options))  # another run on the same kernels
    for k, a in final.items():
        assert np.array_equal(getattr(r.particles, k), a)
