"""Adaptive steps in the compiled loop: a finite-strain material without a
wave speed bound and no ``Method(dt=...)`` takes each step at cfl times the
critical step of the current wave speed, the last one ending exactly at
t_end (``State.next_step_size``; the rule is compiled once,
skfem_mpm.kernels.step_size, and the wave speed is the material's compiled
point wave speed). The loop computes both before each step; it must give
the executor's bits, step for step, with the same number of steps and the
same final time; the rule itself is checked against an independent NumPy
computation of the wave speed.
"""
import numpy as np
import pytest

from skfem_mpm import (Body, Fixed, Gravity, Method, NeoHookean, Particles, Scene, SimulationError, SplineGrid,
                       simulate)
from skfem_mpm.benchmarks import get_benchmark
from skfem_mpm.materials import point_wave_speed
from skfem_mpm.materials.base import det
from skfem_mpm.materials.laws import neo_hookean_wave_speed_law
from skfem_mpm.solve import compiled_loop
from skfem_mpm.solve.compiled import CompiledExecutor
from skfem_mpm.solve.state import prepare
from skfem_mpm.solve.timestep import critical_time_step

from test_compiled_loop import (LAW_CASES, assert_same, law_scene, looped_and_stepped,
                                without_loop)
from test_executors import scene_for


def benchmark_scene(name, steps=17.5):
    """The benchmark's default scene of ``skfem-mpm run`` (16 cells per
    axis, quadratic, 2 particles per cell and axis) ending after about
    ``steps`` initial steps (a fraction: the last step is cut to t_end)."""
    bench = get_benchmark(name)
    dt = prepare(bench.scene(16, 2), Method()).dt
    return bench.scene(16, 2, t_end=steps * dt)


def assert_adaptive_agreement(monkeypatch, scene, method, every_step=True):
    """The loop took every step of the run (or, not ``every_step``, some:
    the executor takes those the loop cannot), as many as the executor,
    to the same final time t_end and the same last dt (every save bit for
    bit: looped_and_stepped); returns the looped result."""
    looped, stepped = looped_and_stepped(monkeypatch, scene, method)
    assert prepare(scene, method).adaptive
    assert looped.counts["steps"] == stepped.counts["steps"]
    taken = looped.counts["compiled_loop_steps"]
    assert taken == looped.counts["steps"] if every_step else 0 < taken
    assert looped.times[-1] == stepped.times[-1] == scene.t_end
    assert (looped.dt, looped.dt_crit) == (stepped.dt, stepped.dt_crit)
    assert np.array_equal(looped.particles.F, stepped.particles.F)
    return looped


@pytest.mark.parametrize("name", ["neo-hookean-bar", "axis-aligned-2d"])
def test_an_adaptive_benchmark_scene_runs_in_the_loop(monkeypatch, name):
    """The default method (MUSL, lumped mass, cfl 0.5, no dt) on the two
    neo-Hookean benchmark scenes: the loop runs their adaptive steps (and
    stops at each save, every 5 steps, and at t_end) with the executor's
    bits; the last step is shorter than cfl dt_crit."""
    scene = benchmark_scene(name)
    calls = []
    run = compiled_loop.StepLoop.run
    monkeypatch.setattr(compiled_loop.StepLoop, "run",
                        lambda self, state, n: calls.append(run(self, state, n)) or calls[-1])
    looped = assert_adaptive_agreement(monkeypatch, scene, Method())
    assert 17 <= looped.counts["steps"] <= 20
    assert looped.dt < 0.5 * looped.dt_crit
    # the body force's rows are evaluated one step at a time, within one
    # call from simulate to the next save (StepLoop._row_by_row)
    assert calls == [5] * (looped.counts["steps"] // 5) + [looped.counts["steps"] % 5]


def neo_hookean_wave_speed(particles, material):
    """c = sqrt(max_p max_k tangent_k / rho0_p) with the principal stretches
    from LAPACK (NeoHookean's NumPy formula before the compiled one)."""
    lam, mu = material.parameters(particles.dim)
    F = particles.F
    J = det(F)
    stretch2 = np.linalg.eigvalsh(np.swapaxes(F, 1, 2) @ F)
    tangent = mu * (1 + 1 / stretch2) + (lam * (1 - np.log(J)))[:, None] / stretch2
    return float(np.sqrt((tangent.max(axis=1) / (particles.m / particles.V0)).max()))


def test_each_step_follows_the_current_wave_speed_to_the_end():
    """The rule on the executor (a callback keeps every step in Python):
    t_k+1 = t_k + dt_k; dt_k = cfl dt_crit(c(F_k)), c the NumPy wave speed
    of the particles at the step's start, to 1e-12; the last step exactly
    t_end - t_k, shorter than cfl dt_crit; the run ends at t_end."""
    scene = benchmark_scene("neo-hookean-bar", steps=12.5)
    material = scene.bodies[0].material
    seen = []

    def record(step, state):
        seen.append((state.t, state.dt, state.particles))

    start = prepare(scene, Method())
    result = simulate(scene, Method(), callback=record)
    assert result.path == "fast"
    times = [0.0] + [t for t, _, _ in seen]
    befores = [start.particles] + [p for _, _, p in seen[:-1]]
    for k, ((t, dt, _), before) in enumerate(zip(seen, befores)):
        assert t == (scene.t_end if k == len(seen) - 1 else times[k] + dt)
        full = 0.5 * critical_time_step(scene.grid, neo_hookean_wave_speed(before, material))
        if k < len(seen) - 1:
            assert abs(dt - full) <= 1e-12 * full, k
    last_t, last_dt, _ = seen[-1]
    assert last_t == scene.t_end and last_dt == scene.t_end - times[-2] < full
    assert len(seen) > 12


def test_neo_hookean_wave_speed_is_the_lapack_one():
    """The compiled point wave speed (closed-form 2D, Jacobi 3D eigenvalues
    of C) against LAPACK's, stretched and sheared, nearly repeated
    stretches included, in 1D, 2D and 3D."""
    rng = np.random.default_rng(3)
    for dim in (1, 2, 3):
        grid = [SplineGrid.line(0.0, 1.0, 4, 2),
                SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (4, 4), 2),
                SplineGrid.box((0.0, 1.0), (0.0, 1.0), (0.0, 1.0), (3, 3, 3), 2)][dim - 1]
        p = Particles.seed(grid, 2, 1.5)
        material = NeoHookean(100.0, 0.3)
        for scale in (0.4, 1e-3, 1e-9):
            F = np.eye(dim) + scale * rng.standard_normal((p.n, dim, dim))
            F[det(F) < 0, 0] *= -1
            q = p.replaced(F=F)
            expected = neo_hookean_wave_speed(q, material)
            assert abs(material.wave_speed(q) - expected) <= 1e-13 * expected, (dim, scale)


@pytest.mark.parametrize("case", [c for c in LAW_CASES if c["material"] == "neo-hookean"],
                         ids=lambda c: f"{c['dim']}d-{c['scheme']}-{c['mass']}-p{c['degree']}")
def test_adaptive_point_law_cases(monkeypatch, case):
    """The neo-Hookean cases of test_compiled_loop's point laws (usl and
    musl lumped, cd consistent: its fast-dof guard's limit follows dt and
    the wave speed) with the adaptive step instead of their fixed dt."""
    scene, _ = law_scene(case)
    assert_adaptive_agreement(monkeypatch, scene,
                              Method(scheme=case["scheme"], mass=case["mass"]))


def test_the_fast_dof_guard_follows_the_adaptive_step(monkeypatch):
    """Consistent mass (cd): the fast-dof guard's limit q / (dt c)^2 moves
    with each step's dt and wave speed; here the body ends inside a cell
    (x < 0.66 of 8 cells), whose end dofs the guard partly lumps (and
    whose tiny masses stop the loop for a few steps: the executor's)."""
    grid = SplineGrid.line(0.0, 1.0, 8, 2)
    particles = Particles.seed(grid, 2, 1.0, region=((0.0, 0.66),),
                               velocity=lambda X: 0.05 * np.sin(np.pi * X))
    scene = Scene(grid, Body(particles, NeoHookean(10.0, 0.3)), 0.4,
                  effects=[Fixed("left"), Gravity(-2.0)])
    looped = assert_adaptive_agreement(monkeypatch, scene, Method(scheme="cd", mass="consistent"),
                                       every_step=False)
    assert looped.counts["compiled_loop_steps"] > looped.counts["steps"] // 2


@pytest.mark.parametrize("scheme", ["cd", "musl"])
def test_the_reconstructed_guard_follows_the_adaptive_step(monkeypatch, scheme):
    """Consistent mass with the spline reconstruction: the guard's stiffness
    of the particles' coverage sums is kept while those sums are (their pass
    skipped) at the same limit; the limit moves with each step's dt and wave
    speed, and the sums are made anew as the particles move, so the loop
    recomputes it after either (the body ends inside a cell, whose end dofs
    the guard partly lumps: the executor's bits, step for step)."""
    grid = SplineGrid.line(0.0, 1.0, 8, 2)
    particles = Particles.seed(grid, 2, 1.0, region=((0.0, 0.66),),
                               velocity=lambda X: 0.05 * np.sin(np.pi * X))
    scene = Scene(grid, Body(particles, NeoHookean(10.0, 0.3)), 0.4,
                  effects=[Fixed("left"), Gravity(-2.0)])
    method = Method(scheme=scheme, mass="consistent", reconstruction="spline")
    looped = assert_adaptive_agreement(monkeypatch, scene, method, every_step=False)
    assert looped.counts["compiled_loop_steps"] > looped.counts["steps"] // 2


@point_wave_speed
def stiffer_wave_speed(params, F, m, V0, state):
    """A user's compiled point wave speed: 1.25 times NeoHookean's (a
    user's law may call the library's compiled laws)."""
    return 1.25 * neo_hookean_wave_speed_law(params, F, m, V0, state)


class StifferNeoHookean(NeoHookean):
    """NeoHookean with a user's point wave speed (and its NumPy twin)."""

    point_wave_speed = stiffer_wave_speed

    def wave_speed(self, particles):
        return 1.25 * super().wave_speed(particles)


class NumPyWaveSpeedNeoHookean(NeoHookean):
    """NeoHookean whose wave speed has no compiled twin."""

    point_wave_speed = None

    def wave_speed(self, particles):
        return neo_hookean_wave_speed(particles, self)


def test_a_users_point_wave_speed_runs_in_the_loop(monkeypatch):
    """A user's material declaring ``point_wave_speed`` has its adaptive
    steps run by the loop (its wave speed sets dt: smaller steps than
    NeoHookean's); without one the run steps in Python, and says why."""
    case = dict(material="neo-hookean", dim=1, scheme="usl", mass="lumped", degree=3)
    scene, _ = law_scene(case)
    body = scene.bodies[0]
    for material, why in [(StifferNeoHookean(10.0, 0.3), ""),
                          (NumPyWaveSpeedNeoHookean(10.0, 0.3),
                           "an adaptive time step with a material without a compiled wave "
                           "speed (point_wave_speed None)")]:
        own = Scene(scene.grid, Body(body.particles, material), scene.t_end,
                    effects=scene.effects)
        state = prepare(own, Method(scheme="usl"))
        assert compiled_loop.loop_applies(state, CompiledExecutor(state)) == (not why, why)
        if not why:
            looped = assert_adaptive_agreement(monkeypatch, own, Method(scheme="usl"))
            plain = simulate(scene, Method(scheme="usl"))
            assert looped.counts["steps"] > plain.counts["steps"]
    assert simulate(own, Method(scheme="usl")).path == "fast"


def test_a_2d_reconstruction_reestimates_its_factor_between_calls(monkeypatch):
    """tls in 2D multiplies dt_crit by a factor re-estimated (power
    iterations, Python) at step 0 and every RECONSTRUCTION_EVERY steps:
    the loop stops before each re-estimate and takes the factor State
    estimates, once a step, as the executor does (30 steps: one
    re-estimate after step 0's)."""
    case = dict(material="neo-hookean", dim=2, scheme="usl", mass="lumped", degree=2, ppc=3)
    scene, _ = law_scene(case, steps=30)
    calls = []
    run = compiled_loop.StepLoop.run
    monkeypatch.setattr(compiled_loop.StepLoop, "run",
                        lambda self, state, n: calls.append((state.step, run(self, state, n)))
                        or calls[-1][1])
    method = Method(scheme="usl", reconstruction="tls")
    looped = simulate(scene, method, save_every=7)  # saves not at the re-estimates
    stepped = without_loop(monkeypatch, scene, method, save_every=7)
    assert_same(looped, stepped)
    assert looped.counts["compiled_loop_steps"] == looped.counts["steps"] > 25
    assert (looped.dt, looped.dt_crit) == (stepped.dt, stepped.dt_crit)
    assert (25, 3) in calls  # steps 21-24, then 25-27 from the new estimate
    assert all(step // 25 == (step + taken - 1) // 25 for step, taken in calls if taken)


def test_the_reconstruction_factor_is_estimated_once_a_step():
    """A step whose size is asked twice (the loop's call, then the
    executor's step when the loop could not take it) keeps one estimate of
    the factor: the same dt, from the same power-iteration vectors."""
    case = dict(material="neo-hookean", dim=2, scheme="usl", mass="lumped", degree=2, ppc=3)
    state = prepare(law_scene(case)[0], Method(scheme="usl", reconstruction="tls"))
    first = state.next_step_size(), state.dt_crit
    vectors = state._reconstruction_vectors
    assert (state.next_step_size(), state.dt_crit) == first
    assert state._reconstruction_vectors is vectors


@pytest.mark.slow(reason="another compiled loop variant (prescribed velocities with a point law)")
def test_prescribed_velocities_read_the_adaptive_dt(monkeypatch):
    """The prescribed velocities' table reads the step's dt (v(t + dt)):
    with an adaptive step it is set first, from the same particles by the
    same rule as the loop's."""
    case = dict(material="neo-hookean", dim=1, scheme="musl", mass="lumped", degree=2,
                effect="prescribed")
    scene = scene_for(case, steps=21)
    assert_adaptive_agreement(monkeypatch, scene, Method())


def test_a_step_the_loop_cannot_take_goes_to_the_executor(monkeypatch):
    """A particle leaving the grid on an adaptive run: the loop stops before
    that step, the executor takes it and raises, with the last good state
    as without the loop."""
    grid = SplineGrid.line(0.0, 1.0, 8, 2)
    particles = Particles.seed(grid, 2, 1.0, region=((0.3, 0.7),),
                               velocity=lambda X: 3.0 + 0.5 * X)
    scene = Scene(grid, Body(particles, NeoHookean(10.0)), 1.0)
    errors = []
    for run in (lambda: simulate(scene, Method(), save_every=3),
                lambda: without_loop(monkeypatch, scene, Method(), save_every=3)):
        with pytest.raises(SimulationError) as info:
            run()
        errors.append(info.value)
    looped, stepped = (e.result for e in errors)
    assert str(errors[0]) == str(errors[1]) and "left the grid" in str(errors[0])
    assert 0 < looped.counts["compiled_loop_steps"] == looped.counts["steps"]
    assert np.array_equal(looped.times, stepped.times)
    assert np.array_equal(looped.particles.x, stepped.particles.x)
