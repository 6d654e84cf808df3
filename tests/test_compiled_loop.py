"""The compiled step loop (skfem_mpm.solve.compiled_loop) gives the same bits
as the compiled executor stepping in Python.

The loop runs the schemes of skfem_mpm.solve.schemes compiled against a
run whose operations call the executor's kernels in the same order on the
same blocks, so every recorded quantity must agree exactly: positions,
velocities, stresses, external work, reactions and the time of each save.
A step the loop cannot finish (a particle leaving the grid, J <= 0, tiny
masses) is handed to the executor, which must then do what it does
without the loop.
"""
import itertools
import json
import os
import subprocess
import sys

import numba
import numpy as np
import pytest
from tiers import tiered

from skfem_mpm import (Body, DruckerPrager, Fixed, Gravity, LinearElastic, Method, MohrCoulomb,
                       NeoHookean, Particles, Scene, SimulationError, SplineGrid, Traction,
                       VonMises, simulate)
from skfem_mpm.kernels import serial
from skfem_mpm.kernels.fringe import NO_FACTOR
from skfem_mpm.solve import compiled_loop, compiled_reconstruct
from skfem_mpm.solve.compiled import CompiledExecutor
from skfem_mpm.solve.state import prepare
from skfem_mpm.solve.stencil_system import StencilSystem, preconditioned_with

from test_executors import CappedStress, CappedStressCompiled, scene_for


def _case_id(case):
    return "-".join(map(str, case.values()))


KEYS = ("x", "v", "u", "stress")


def without_loop(monkeypatch, scene, method, **kwargs):
    with monkeypatch.context() as m:
        m.setattr(compiled_loop, "ENABLED", False)
        return simulate(scene, method, **kwargs)


def assert_same(a, b):
    assert np.array_equal(a.times, b.times)
    for key in KEYS:
        assert np.array_equal(a.history[key], b.history[key]), key
    assert np.array_equal(a.energies["external_work"], b.energies["external_work"])


def looped_and_stepped(monkeypatch, scene, method):
    """The run with the compiled loop and without it (the executor stepping
    in Python), saved every 5 steps: the loop ran it, and both give the same
    bits (every recorded quantity, the reactions)."""
    looped = simulate(scene, method, save_every=5)
    stepped = without_loop(monkeypatch, scene, method, save_every=5)
    assert looped.path == "fast (compiled loop)"
    assert_same(looped, stepped)
    assert len(looped.reactions) == len(stepped.reactions)
    for a, b in zip(looped.reactions, stepped.reactions):
        assert a.keys() == b.keys()
        for key in a:
            assert np.array_equal(a[key], b[key]), key
    return looped, stepped


LOOP_FACTORS = {"scheme": ("musl", "usl", "cd"), "degree": (1, 2, 3), "dim": (1, 2),
                "effect": ("none", "gravity")}
# Each (scheme, degree, dim) compiles a loop function of its own (30-280 s
# on a fresh install): the default tier runs a set covering every pair of
# factor values (checked below), picked among the variants other tests
# compile anyway (usl 2D p2: the falling block; cd 1D p2: the unwritten
# scene; musl 2D p2: reactions); the rest of the product runs in the slow
# tier.
DEFAULT_LOOP_CASES = [("musl", 1, 1, "none"), ("musl", 2, 2, "gravity"),
                      ("musl", 3, 2, "none"), ("usl", 1, 2, "gravity"),
                      ("usl", 2, 2, "none"), ("usl", 3, 1, "gravity"),
                      ("cd", 1, 2, "none"), ("cd", 2, 1, "gravity"), ("cd", 3, 1, "none")]
SLOW_LOOP = pytest.mark.slow(reason="one more compiled loop variant; the default tier "
                             "covers every pair of scheme, degree, dim and effect")


def loop_case(scheme, degree, dim, effect):
    return dict(scheme=scheme, mass="lumped", degree=degree, dim=dim, material="linear",
                effect=effect)


CASES = [loop_case(s, p, d, e) if (s, p, d, e) in DEFAULT_LOOP_CASES else
         pytest.param(loop_case(s, p, d, e), marks=SLOW_LOOP)
         for s in ("musl", "usl", "cd") for p in (1, 2, 3) for d in (1, 2)
         for e in ("none", "gravity")]


def test_the_default_loop_cases_cover_every_pair():
    """Every pair of values of any two factors occurs in a default case."""
    names = list(LOOP_FACTORS)
    for i, j in itertools.combinations(range(len(names)), 2):
        seen = {(c[i], c[j]) for c in DEFAULT_LOOP_CASES}
        assert seen == set(itertools.product(LOOP_FACTORS[names[i]],
                                             LOOP_FACTORS[names[j]])), (names[i], names[j])


@pytest.mark.parametrize("case", CASES, ids=lambda c: "-".join(str(v) for v in c.values()))
def test_loop_gives_the_executors_bits(monkeypatch, case):
    scene = scene_for(case, steps=23)
    method = Method(scheme=case["scheme"], mass="lumped")
    looped = simulate(scene, method, save_every=5)  # chunks of 5 and a last one of 3
    stepped = without_loop(monkeypatch, scene, method, save_every=5)
    assert looped.path == "fast (compiled loop)"
    assert stepped.path == "fast"
    assert_same(looped, stepped)
    assert looped.counts["steps"] == looped.counts["compiled_loop_steps"] == 23
    assert stepped.counts["compiled_loop_steps"] == 0


def test_reactions_and_phases(monkeypatch):
    case = dict(scheme="musl", mass="lumped", degree=2, dim=2, material="linear",
                effect="gravity")
    scene = scene_for(case, steps=12)
    method = Method(scheme="musl")
    looped = simulate(scene, method, save_every=4)
    stepped = without_loop(monkeypatch, scene, method, save_every=4)
    assert_same(looped, stepped)
    assert looped.counts["compiled_loop_steps"] == 12
    for a, b in zip(looped.reactions, stepped.reactions):
        assert a.keys() == b.keys()
        for key in a:
            assert np.array_equal(a[key], b[key]), key
    phases = looped.phase_table()
    for phase in ("p2g", "solve", "g2p"):
        assert phases[phase] > 0.0, phase
    assert sum(phases.values()) <= looped.wall_time


def falling_block(on_exit, cells=8):
    """A block falling freely out of the bottom of the grid."""
    grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (cells, cells), 2)
    particles = Particles.seed(grid, 2, 1.0, region=((0.3, 0.7), (0.05, 0.4)))
    scene = Scene(grid, Body(particles, LinearElastic(50.0, 0.3)), 0.2,
                  effects=[Gravity((0.0, -9.81))])
    return scene, Method(scheme="usl", on_exit=on_exit)


def test_particles_leaving_are_removed_as_without_the_loop(monkeypatch):
    scene, method = falling_block("remove")
    looped = simulate(scene, method, save_every=10)
    stepped = without_loop(monkeypatch, scene, method, save_every=10)
    assert looped.counts["removed"] == stepped.counts["removed"] > 0
    assert 0 < looped.counts["compiled_loop_steps"] < looped.counts["steps"]
    assert np.array_equal(looped.times, stepped.times)
    for a, b in zip(looped.history["x"], stepped.history["x"]):
        assert np.array_equal(a, b)


def test_a_failing_step_raises_as_without_the_loop(monkeypatch):
    scene, method = falling_block("raise")
    with pytest.raises(SimulationError) as looped:
        simulate(scene, method, save_every=10)
    with pytest.raises(SimulationError) as stepped:
        without_loop(monkeypatch, scene, method, save_every=10)
    assert str(looped.value) == str(stepped.value)
    assert looped.value.step == stepped.value.step
    a, b = looped.value.result, stepped.value.result
    assert np.array_equal(a.particles.x, b.particles.x)
    assert np.isfinite(a.particles.x).all()


def test_the_scene_is_never_written(monkeypatch):
    case = dict(scheme="cd", mass="lumped", degree=2, dim=1, material="linear", effect="none")
    scene = scene_for(case, steps=10)
    before = {k: getattr(scene.bodies[0].particles, k).copy() for k in ("x", "v", "stress")}
    r = simulate(scene, Method(scheme="cd"))
    assert r.path == "fast (compiled loop)"
    for k, a in before.items():
        assert np.array_equal(getattr(scene.bodies[0].particles, k), a), k


@pytest.mark.parametrize("case", [
    dict(scheme="musl", mass="lumped", degree=2, dim=2, material="linear", effect="gravity"),
    pytest.param(dict(scheme="cd", mass="lumped", degree=2, dim=1, material="linear",
                      effect="none"),
                 marks=pytest.mark.slow(reason="one more parallel loop variant (1D, cd); the "
                                        "default tier runs the parallel loop in 2D (musl)")),
], ids=lambda c: f"{c['scheme']}-{c['dim']}d")
def test_parallel_kernels_give_the_same_bits(monkeypatch, case):
    """Above SERIAL_BELOW particles the loop calls the parallel kernels, a
    few steps per call so that the thread policy can act between calls; the
    executor stepping alone below it calls their serial copies: the same
    bits."""
    scene = scene_for(case, steps=23)
    method = Method(scheme=case["scheme"], mass="lumped")
    with monkeypatch.context() as m:
        m.setattr(serial, "SERIAL_BELOW", 0)
        m.setattr(compiled_loop.StepLoop, "CALL_SECONDS", 1e-9)  # one step per call
        looped = simulate(scene, method, save_every=5)
    stepped = without_loop(monkeypatch, scene, method, save_every=5)
    assert looped.counts["compiled_loop_steps"] == 23
    assert_same(looped, stepped)


# ------------------------------------------------------------ consistent mass
# A run with consistent (or hybrid) mass solves its grid equations in the
# loop with the Kronecker-preconditioned CG of StencilSystem; the same bits
# as the executor, warm starts carried across calls of the loop and handed
# back to the executor. The scenes fill whole cells (tiny-mass dofs send a
# consistent step to the executor's general grid system). In 2D the fringe
# correction turns on once a CG run needs StencilSystem.FRINGE_FROM
# iterations: the loop takes that step and hands the rest to the executor.
MASS_CASES = [  # every scheme x mass x degree x dimension pair at least once
    dict(scheme="musl", mass="consistent", degree=2, dim=1),
    dict(scheme="usl", mass="consistent", degree=1, dim=1),
    dict(scheme="cd", mass="consistent", degree=3, dim=1),
    dict(scheme="musl", mass="hybrid", degree=3, dim=1),
    dict(scheme="musl", mass="consistent", degree=1, dim=2),
    dict(scheme="usl", mass="consistent", degree=2, dim=2),
    dict(scheme="cd", mass="consistent", degree=2, dim=2),
    dict(scheme="musl", mass="hybrid", degree=2, dim=2),
]
ALL_MASS_CASES = [dict(scheme=s, mass=m, degree=p, dim=d)
                   for s in ("musl", "usl", "cd") for m in ("consistent", "hybrid")
                   for p in (1, 2, 3) for d in (1, 2) if m == "consistent" or s == "musl"]
ALL_MASS_CASES = [c for c in ALL_MASS_CASES if c not in MASS_CASES]


def mass_case(case, effect="gravity"):
    return dict(case, material="linear", effect=effect, aligned=True)


def check_mass_case(monkeypatch, case, fringe=True):
    scene = scene_for(mass_case(case), steps=23)
    method = Method(scheme=case["scheme"], mass=case["mass"])
    with monkeypatch.context() as m:
        if not fringe:
            m.setattr(StencilSystem, "FRINGE_LAYERS", 0)
        try:
            looped = simulate(scene, method, save_every=5)
        except SimulationError as error:  # (hybrid mass, linear: J <= 0 on this scene)
            with pytest.raises(SimulationError) as stepped:
                without_loop(monkeypatch, scene, method, save_every=5)
            assert str(error) == str(stepped.value)
            assert_same(error.result, stepped.value.result)
            return error.result
        stepped = without_loop(monkeypatch, scene, method, save_every=5)
    assert looped.path == "fast (compiled loop)"
    assert_same(looped, stepped)
    for a, b in zip(looped.reactions, stepped.reactions):
        assert a.keys() == b.keys()
        for key in a:
            assert np.array_equal(a[key], b[key]), key
    return looped


DEFAULT_MASS_CASES = {  # the default tier's cases (tests/tiers.py)
    "cd-consistent-2-2",
    "cd-consistent-3-1",
    "musl-consistent-2-1",
    "musl-hybrid-2-2",
    "musl-hybrid-3-1",
    "usl-consistent-1-1",
    "usl-consistent-2-2",
}


@pytest.mark.parametrize("case", tiered(
    "consistent mass in the loop", MASS_CASES, _case_id, DEFAULT_MASS_CASES),
                         ids=_case_id)
def test_consistent_mass_gives_the_executors_bits(monkeypatch, case):
    looped = check_mass_case(monkeypatch, case)
    steps = looped.counts["compiled_loop_steps"]
    if case["dim"] == 1:  # tiny masses at most now and then
        assert steps >= 20, steps
    else:  # the fringe correction turns on after the first CG runs
        assert steps >= 1


@pytest.mark.parametrize("case", [MASS_CASES[5], MASS_CASES[7]],
                         ids=lambda c: "-".join(map(str, c.values())))
def test_consistent_mass_in_2d_without_the_fringe_correction(monkeypatch, case):
    looped = check_mass_case(monkeypatch, case, fringe=False)
    assert looped.counts["compiled_loop_steps"] >= 20


def test_consistent_mass_as_the_free_rows_change_with_their_count_kept(monkeypatch):
    """A block spinning about its centre: as its corners sweep across the
    cells the rows with mass change shape while their count stays (a
    translation would not do: it keeps every row's columns), so the loop's
    ELL columns (rewritten only when the free rows change) must follow the
    rows, not their count; the loop gives the executor's bits."""
    grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (16, 16), 2)
    particles = Particles.seed(grid, 2, 1.0, region=((0.25, 0.75), (0.25, 0.75)),
                               velocity=lambda X: 6.0 * np.column_stack((0.5 - X[:, 1],
                                                                         X[:, 0] - 0.5)))
    effects = [Fixed("bottom"), Gravity((0.0, -2.0))]  # (the loop variant of usl-consistent-2-2)
    body = Body(particles, LinearElastic(10.0, 0.3))
    method = Method(scheme="usl", mass="consistent")
    dt = prepare(Scene(grid, body, 1.0, effects=effects), method).dt
    scene = Scene(grid, body, 60 * dt, effects=effects)
    with monkeypatch.context() as m:
        m.setattr(StencilSystem, "FRINGE_LAYERS", 0)
        looped, _ = looped_and_stepped(monkeypatch, scene, method)
    assert looped.counts["compiled_loop_steps"] >= 50
    travel = np.linalg.norm(looped.history["x"][-1] - looped.history["x"][0], axis=1)
    assert travel.max() > 1.0 / 16  # (the corners crossed faces)


# The fringe correction (2D, kernels.fringe) in the loop: the executor makes
# its SuperLU factor (StencilSystem._fringe), the loop applies it while the
# free rows stay. A block expanding on a 16 x 16 grid with the correction on
# from the first solve (FRINGE_FROM 0, every group): the free rows change
# now and then (a step stops, the executor takes it and factorises) and a
# stale factor needs FRINGE_SLACK iterations more than a fresh one now and
# then (the loop drops it and hands the next step over); every other step
# runs in the loop with the executor's factor, to the executor's bits.
def fringe_scene(steps=23):
    grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (16, 16), 2)
    particles = Particles.seed(grid, 2, 1.0, region=((0.25, 0.75), (0.25, 0.75)),
                               velocity=lambda X: np.column_stack((0.4 * (X[:, 0] - 0.5),
                                                                   0.4 * (X[:, 1] - 0.5) - 1.0)))
    effects = [Fixed("bottom"), Gravity((0.0, -2.0))]  # (the loop variant of usl-consistent-2-2)
    body = Body(particles, LinearElastic(10.0, 0.3))
    dt = prepare(Scene(grid, body, 1.0, effects=effects), Method(mass="consistent")).dt
    return Scene(grid, body, steps * dt, effects=effects)


def fringe_events(monkeypatch):
    """Spy on the loop: the stop codes of its calls, the groups each handover
    dropped a fringe factor of."""
    events = {"stops": [], "dropped": []}
    run, results = compiled_loop.StepLoop._run, compiled_loop.StepLoop._mass_results

    def spy_run(self, state, n):
        taken = run(self, state, n)
        events["stops"].append((self._stop, taken))
        return taken

    def spy_results(self, state, handover):
        if handover:
            events["dropped"].append(self.module.mass_records(self.cm)[10].copy())
        return results(self, state, handover)

    monkeypatch.setattr(compiled_loop.StepLoop, "_run", spy_run)
    monkeypatch.setattr(compiled_loop.StepLoop, "_mass_results", spy_results)
    return events


@pytest.mark.parametrize("scheme", [
    "usl", pytest.param("musl", marks=SLOW_LOOP), pytest.param("cd", marks=SLOW_LOOP)])
def test_fringe_correction_runs_in_the_loop_with_the_executors_factors(monkeypatch, scheme):
    """With FRINGE_SLACK as it is, stale factors are dropped; with a slack
    no run exceeds, the factor is kept until the free rows change."""
    monkeypatch.setattr(StencilSystem, "FRINGE_FROM", 0)
    monkeypatch.setattr(StencilSystem, "FRINGE_MIN_ROWS", 0)
    method = Method(scheme=scheme, mass="consistent")
    for slack in (StencilSystem.FRINGE_SLACK, 1000):
        with monkeypatch.context() as m:
            m.setattr(StencilSystem, "FRINGE_SLACK", slack)
            events = fringe_events(m)
            looped, _ = looped_and_stepped(m, fringe_scene(), method)
        steps = looped.counts["compiled_loop_steps"]
        assert (10 if slack < 1000 else 15) <= steps < looped.counts["steps"], (slack, steps)
        stops = [stop for stop, _ in events["stops"]]
        dropped = any(d.any() for d in events["dropped"])
        assert dropped is (slack < 1000), events  # a stale factor dropped
        if slack == 1000:  # the first step, then new free rows
            assert stops.count(compiled_loop.STOP_FRINGE_FACTOR) >= 2, events


def test_the_loop_logs_each_cg_run_as_the_executor_does(monkeypatch):
    """StencilSystem.iteration_log (`bench --consistent` counts the CG
    iterations so) does not send a run to the executor: the loop logs the
    same runs with the same iterations."""
    monkeypatch.setattr(StencilSystem, "FRINGE_FROM", 0)
    monkeypatch.setattr(StencilSystem, "FRINGE_MIN_ROWS", 0)
    logs, results = [], []
    for enabled in (True, False):
        with monkeypatch.context() as m, preconditioned_with("kronecker+fringe") as log:
            m.setattr(compiled_loop, "ENABLED", enabled)
            results.append(simulate(fringe_scene(), Method(scheme="usl", mass="consistent"),
                                    save_every=5))
        logs.append(log)
    assert results[0].path == "fast (compiled loop)"
    assert results[0].counts["compiled_loop_steps"] >= 10
    assert logs[0] == logs[1] and len(logs[0]) >= 23, logs
    assert_same(*results)


def test_fringe_factors_cross_checkpoints_and_the_executor(monkeypatch, tmp_path):
    """The fringe block and its first iterations are warm data: a run whose
    first 10 steps the executor took (a callback) and which was restarted
    from their checkpoint on the loop (no factor on the kernels: the
    executor makes it from the checkpoint's block) gives the loop's bits."""
    monkeypatch.setattr(StencilSystem, "FRINGE_FROM", 0)
    monkeypatch.setattr(StencilSystem, "FRINGE_MIN_ROWS", 0)
    scene, method = fringe_scene(), Method(scheme="usl", mass="consistent")
    whole = simulate(scene, method)
    path = tmp_path / "run.npz"
    simulate(scene, method, checkpoint=(path, 10), callback=lambda step, state: step < 10)
    resumed = simulate(scene, method, restart=path)
    assert whole.path == resumed.path == "fast (compiled loop)"
    assert resumed.counts["compiled_loop_steps"] >= 5
    for name in ("x", "v", "stress"):
        assert np.array_equal(getattr(whole.particles, name), getattr(resumed.particles, name))


def test_a_fringe_factor_serves_only_the_free_rows_it_was_made_for():
    """The loop applies a loaded fringe factor to a step whose free rows
    are the factor's, not merely as many (a block moved by a cell has as
    many free rows as before, shifted)."""
    state = prepare(fringe_scene(), Method(mass="consistent"))
    loop = compiled_loop.StepLoop(state, CompiledExecutor(state))
    rows = np.arange(10, 40, dtype=np.int64)
    none, one = np.zeros(0, dtype=np.int64), np.zeros(1, dtype=np.int64)
    no_entries = np.zeros((0, 2), dtype=np.int64)
    loop.module.load_fringe(loop.cm, 0, rows, none, one, no_entries, none, one, no_entries,
                            *NO_FACTOR)
    kept = loop.module._kept_fringe
    assert kept(loop.cm, 0, rows.copy())
    assert not kept(loop.cm, 0, rows + 1)
    assert not kept(loop.cm, 0, rows[:-1])


@pytest.mark.exhaustive  # each case compiles a loop of its own (tens of seconds)
@pytest.mark.parametrize("case", ALL_MASS_CASES, ids=lambda c: "-".join(map(str, c.values())))
def test_consistent_mass_gives_the_executors_bits_everywhere(monkeypatch, case):
    check_mass_case(monkeypatch, case, fringe=case["degree"] != 3)


# Tiny masses with consistent (and hybrid) mass: the loop solves the merged
# system of kernels.merged_mass, as the executor's StencilSystem does, on
# every step. Free surfaces cut cells (scene_for's unaligned bodies, the
# colliding disks), so tiny-mass dofs occur from the first step; the cases
# reuse loop variants the cases above compile (prescribed velocities: the
# constraint values' fixed columns of the merged rows).
TINY_CASES = [
    dict(scheme="usl", mass="consistent", degree=2, dim=2, effect="gravity"),
    dict(scheme="musl", mass="hybrid", degree=2, dim=2, effect="gravity"),
    dict(scheme="cd", mass="consistent", degree=2, dim=2, effect="prescribed"),
]


@pytest.mark.parametrize("case", TINY_CASES, ids=lambda c: "-".join(map(str, c.values())))
def test_tiny_masses_with_consistent_mass_stay_in_the_loop(monkeypatch, case):
    scene = scene_for(dict(case, material="linear", aligned=False), steps=23)
    method = Method(scheme=case["scheme"], mass=case["mass"])
    looped, _ = looped_and_stepped(monkeypatch, scene, method)
    assert looped.counts["small_dofs_max"] > 0
    assert looped.counts["compiled_loop_steps"] == looped.counts["steps"] == 23
    if case["effect"] == "prescribed":
        assert looped.reactions[-1]["Prescribed('bottom', component=0)"][0] != 0.0


def test_the_merge_kernels_compile_at_the_first_step_with_tiny_masses(monkeypatch):
    """The tiny-mass merge is called through addresses set at the first
    step that needs it (compile_seconds > 0; the loop then goes on from
    that step), never in a run without tiny-mass dofs (the cases' bodies
    fill whole cells, or cut them)."""
    monkeypatch.setattr(StencilSystem, "FRINGE_LAYERS", 0)  # every step in the loop
    for aligned in (True, False):
        case = dict(TINY_CASES[0], material="linear", aligned=aligned)
        state = prepare(scene_for(case, steps=23), Method(scheme="usl", mass="consistent"))
        loop = compiled_loop.StepLoop(state, CompiledExecutor(state))
        assert loop.run(state, 23) == 23
        assert (state.small_dofs_max > 0) is (not aligned)
        assert (loop.compile_seconds > 0.0) is (not aligned)


_ONE_D_CG = r"""
import json, sys
import numpy as np
from skfem_mpm import Body, Fixed, Gravity, LinearElastic, Method, Particles, Scene, simulate
from skfem_mpm.kernels import mpm, serial
from skfem_mpm.spline import SplineGrid


def bar(end, steps=23):
    # a 1D quadratic bar on 8 cells ending at end: 0.63 leaves a tiny-mass
    # dof past it, 0.75 (a knot) none
    grid = SplineGrid.line(0.0, 1.0, 8, 2)
    p = Particles.seed(grid, 2, 1.0, region=((0.0, end),),
                       velocity=lambda X: 0.05 * np.sin(np.pi * X))
    scene = Scene(grid, [Body(p, LinearElastic(10.0, 0.3))], 1.0,
                  effects=[Fixed("left"), Gravity(-2.0)])
    from skfem_mpm.solve.state import prepare
    dt = prepare(scene, Method(scheme="usl", mass="consistent")).dt
    return Scene(grid, [Body(p, LinearElastic(10.0, 0.3))], steps * dt,
                 effects=[Fixed("left"), Gravity(-2.0)])


if __name__ == "__main__":
    r = simulate(bar(float(sys.argv[1])), Method(scheme="usl", mass="consistent"))
    print(json.dumps({"path": r.path, "small": r.counts["small_dofs_max"],
                      "cg": len(serial.serial(mpm.ell_pcg).overloads)}))
"""


def test_a_1d_loop_merges_tiny_masses_with_the_executors_bits(monkeypatch):
    """1D consistent mass with a tiny-mass dof: the loop merges it and runs
    CG on the merged group (ell_pcg through the address the merge sets),
    with the bits of the executor stepping in Python."""
    namespace = {}
    exec(_ONE_D_CG.split('if __name__')[0], namespace)
    scene = namespace["bar"](0.63)
    looped, _ = looped_and_stepped(monkeypatch, scene, Method(scheme="usl", mass="consistent"))
    assert looped.counts["small_dofs_max"] > 0
    assert looped.counts["compiled_loop_steps"] == looped.counts["steps"] == 23


@pytest.mark.parametrize("end", [0.75, 0.63])
def test_a_1d_loop_compiles_cg_only_for_a_merged_group(end):
    """1D consistent mass in the loop: the Kronecker step is the solution
    (P = A) unless a group is merged, so ell_pcg is compiled (or loaded)
    with the merge kernels at the first step with tiny-mass dofs, never in
    a run without them (a fresh process: nothing else compiled it)."""
    out = subprocess.run([sys.executable, "-c", _ONE_D_CG, str(end)],
                         capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report["path"] == "fast (compiled loop)"
    tiny = end != 0.75
    assert (report["small"] > 0) is tiny
    assert report["cg"] == (1 if tiny else 0)


def test_precompile_mass_compiles_what_the_loop_calls():
    """A study's second worker compiles a consistent-mass loop's CG solve
    (precompile_mass) for the very argument types the loop then calls it
    with: one signature of it and of the system's preparation; lumped
    mass has none to compile."""
    scene = scene_for(mass_case(MASS_CASES[0]), steps=23)
    state = prepare(scene, Method(scheme="musl", mass="consistent"))
    assert compiled_loop.precompile_mass(state, CompiledExecutor(state))
    loop = compiled_loop.StepLoop(state, CompiledExecutor(state))
    for name in ("mass_solve", "prepare_mass"):
        assert len(getattr(loop.module, name).overloads) == 1, name
    lumped = prepare(scene, Method(scheme="musl", mass="lumped"))
    assert not compiled_loop.precompile_mass(lumped, CompiledExecutor(lumped))


def test_a_serial_run_fits_the_kronecker_factors_with_the_serial_copy(monkeypatch):
    """Below SERIAL_BELOW particles the executor's consistent solve (its
    warm-up included) fits the Kronecker preconditioner with the serial
    copy of fit_kronecker, the one the compiled loop calls: a first use
    compiles that copy only, not also the parallel kernel (whose compile
    costs a few times more; the same blocks, so the same bits)."""
    from skfem_mpm.kernels.kronecker import KroneckerData, fit_kronecker

    built = KroneckerData.of_system.__func__
    fits = []

    def spy(cls, *args, **kwargs):
        fits.append(kwargs.get("fit"))
        return built(cls, *args, **kwargs)

    monkeypatch.setattr(KroneckerData, "of_system", classmethod(spy))
    scene = scene_for(mass_case(MASS_CASES[0]), steps=23)
    result = without_loop(monkeypatch, scene, Method(scheme="musl", mass="consistent"))
    assert result.counts["particles"] < serial.SERIAL_BELOW
    assert fits and all(fit is serial.serial(fit_kronecker) for fit in fits), set(fits)


_PRECOMPILE = r"""
import json, sys
sys.path.insert(0, "tests")
from skfem_mpm import Method
from skfem_mpm.solve import compiled_loop
from skfem_mpm.solve.compiled import CompiledExecutor
from skfem_mpm.solve.state import prepare
from test_executors import scene_for
scene = scene_for(dict(scheme="musl", mass="consistent", degree=2, dim=1, material="linear",
                       effect="gravity", aligned=True), steps=23)
state = prepare(scene, Method(scheme="musl", mass="consistent"))
compiled_loop.precompile_mass(state, CompiledExecutor(state))
module = compiled_loop.StepLoop(state, CompiledExecutor(state), compile_loop=False).module
print(json.dumps({name: len(getattr(module, name).overloads)
                  for name in ("prepare_mass", "mass_solve", "run_musl")}))
"""


def test_precompile_mass_takes_the_preparation_and_the_solve():
    """A study's second worker compiles (or loads) the system's
    preparation and its solve, not the loop (a fresh process: nothing
    else compiled them)."""
    out = subprocess.run([sys.executable, "-c", _PRECOMPILE], capture_output=True, text=True,
                         timeout=900,
                         cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    assert out.returncode == 0, out.stderr[-3000:]
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report == {"prepare_mass": 1, "mass_solve": 1, "run_musl": 0}


@pytest.mark.parametrize("case", ["musl-consistent", "rk4-spline"])
def test_a_typed_only_run_has_the_type_of_the_built_run(case):
    """precompile_mass types the run without building it (the fields'
    types, no constructor compiled): that type is the built run's, mass
    system and reconstruction records included, so the loop finds what
    the second worker compiled."""
    from skfem_mpm.benchmarks import get_benchmark

    if case == "musl-consistent":  # (the variants the tests above compile)
        scene = scene_for(mass_case(MASS_CASES[0]), steps=23)
        method = Method(scheme="musl", mass="consistent")
    else:
        scene = get_benchmark("traction-bar", "small").scene(8, 3, 2, t_end=0.03)
        method = Method(scheme="rk4", mass="consistent", reconstruction="spline")
    state = prepare(scene, method)
    typed = compiled_loop.StepLoop(state, CompiledExecutor(state), compile_loop=False)
    built = compiled_loop.StepLoop(state, CompiledExecutor(state))
    assert isinstance(typed.run_state, numba.types.StructRef)
    assert typed.run_state == numba.typeof(built.run_state)
    assert typed.run_state.field_dict["cm"] == numba.typeof(built.cm)


def test_tiny_masses_of_the_traction_bar_stay_in_the_loop(monkeypatch):
    """S3 (1D, cubic, spline reconstruction, consistent mass, rk4: the
    variant test_rk4 compiles): the free end's last function is seen only
    at the tail of its support, a tiny-mass dof at every step."""
    from skfem_mpm.benchmarks import get_benchmark

    scene = get_benchmark("traction-bar", "small").scene(8, 3, 2, t_end=0.04)  # 12 steps
    method = Method(scheme="rk4", mass="consistent", reconstruction="spline")
    looped, _ = looped_and_stepped(monkeypatch, scene, method)
    assert looped.counts["small_dofs_max"] > 0
    assert looped.counts["compiled_loop_steps"] == looped.counts["steps"] >= 10


def test_colliding_disks_with_consistent_mass_run_in_the_loop(monkeypatch):
    """D3 with consistent mass: the disks' edges cut cells, so every step
    has tiny-mass dofs; every step runs in the loop, with the executor's
    bits."""
    from skfem_mpm.benchmarks import get_benchmark

    scene = get_benchmark("colliding-disks").scene(t_end=0.15)
    looped, _ = looped_and_stepped(monkeypatch, scene, Method(mass="consistent"))
    assert looped.counts["small_dofs_max"] > 0
    assert looped.counts["compiled_loop_steps"] == looped.counts["steps"] >= 20


@pytest.mark.slow(
    reason="parallel kernels in the loop run in the default tier with lumped linear "
           "elasticity (test_parallel_kernels_give_the_same_bits); this one compiles the 1D "
           "parallel transfer kernels, the parallel consistent-mass kernels and another "
           "parallel run type")
def test_consistent_mass_with_parallel_kernels(monkeypatch):
    case = MASS_CASES[0]
    with monkeypatch.context() as m:
        m.setattr(serial, "SERIAL_BELOW", 0)
        m.setattr(compiled_loop.StepLoop, "CALL_SECONDS", 1e-9)  # one step per call
        looped = check_mass_case(monkeypatch, case)
    assert looped.counts["compiled_loop_steps"] >= 20


# ----------------------------------------------------------------------- rk4
# Classical Runge-Kutta in the loop: four stages of particles to grid, grid
# solves and the rates gather, the stage combinations of kernels.staging;
# the reactions of the first stage. Lumped and consistent mass, 1D and 2D.
RK4_CASES = [dict(scheme="rk4", mass="lumped", degree=2, dim=1),
             dict(scheme="rk4", mass="lumped", degree=1, dim=2),
             dict(scheme="rk4", mass="consistent", degree=3, dim=1),
             dict(scheme="rk4", mass="consistent", degree=2, dim=2)]


DEFAULT_RK4_CASES = {  # the default tier's cases (tests/tiers.py)
    "rk4-consistent-2-2",
    "rk4-consistent-3-1",
    "rk4-lumped-1-2",
    "rk4-lumped-2-1",
}


@pytest.mark.parametrize("case", tiered(
    "rk4 in the loop", RK4_CASES, _case_id, DEFAULT_RK4_CASES),
                         ids=_case_id)
def test_rk4_gives_the_executors_bits(monkeypatch, case):
    looped = check_mass_case(monkeypatch, case)
    assert looped.counts["compiled_loop_steps"] >= 20
    assert any(np.any(r != 0) for r in looped.reactions[-1].values())  # compared above


def test_rk4_particles_leaving_are_removed_as_without_the_loop(monkeypatch):
    scene, _ = falling_block("remove")
    method = Method(scheme="rk4", on_exit="remove")
    looped = simulate(scene, method, save_every=10)
    stepped = without_loop(monkeypatch, scene, method, save_every=10)
    assert looped.counts["removed"] == stepped.counts["removed"] > 0
    assert 0 < looped.counts["compiled_loop_steps"] < looped.counts["steps"]
    for a, b in zip(looped.history["x"], stepped.history["x"]):
        assert np.array_equal(a, b)


# ------------------------------------------------------------ reconstruction
# The particle-knot spline in 1D: the Gauss rule over the body, the fit of
# the particles' fields at its points and their integration by the p2g
# kernel and the consistent-mass assembly; MUSL re-projects the fitted
# momentum; rk4 reconstructs at every stage. Every scheme and mass kind.
RECONSTRUCTED_CASES = [
    dict(scheme="musl", mass="consistent", degree=3, effect="gravity"),
    dict(scheme="musl", mass="lumped", degree=2, effect="gravity"),
    dict(scheme="musl", mass="hybrid", degree=2, effect="gravity"),
    dict(scheme="usl", mass="lumped", degree=3, effect="none"),
    dict(scheme="cd", mass="consistent", degree=2, effect="gravity"),
    dict(scheme="rk4", mass="consistent", degree=3, effect="gravity"),
    dict(scheme="rk4", mass="lumped", degree=2, effect="gravity"),
]


DEFAULT_RECONSTRUCTED_CASES = {  # the default tier's cases (tests/tiers.py)
    "cd-consistent-2-gravity",
    "musl-consistent-3-gravity",
    "musl-hybrid-2-gravity",
    "musl-lumped-2-gravity",
    "rk4-consistent-3-gravity",
    "rk4-lumped-2-gravity",
    "usl-lumped-3-none",
}


@pytest.mark.parametrize("case", tiered(
    "spline reconstruction in the loop", RECONSTRUCTED_CASES, _case_id,
    DEFAULT_RECONSTRUCTED_CASES, paired=("scheme", "mass")),
                         ids=_case_id)
def test_spline_reconstruction_gives_the_executors_bits(monkeypatch, case):
    full = dict(case, dim=1, material="linear", reconstruction="spline", aligned=True)
    scene = scene_for(full, steps=23)
    method = Method(scheme=case["scheme"], mass=case["mass"], reconstruction="spline")
    looped, stepped = looped_and_stepped(monkeypatch, scene, method)
    assert stepped.path == "fast (reconstruction spline)"
    assert looped.counts["compiled_loop_steps"] >= 18
    assert looped.phase_table()["reconstruct"] > 0.0


# The published TLS (default options) in 1D and 2D: the cells' Taylor least
# squares fits at the Gauss points (2D: the particles of the cells a free
# surface cuts are points of the rule themselves), integrated as above.
# Every pair of dimension, scheme and mass kind; in 2D both the aligned
# body (whole cells) and the unaligned one (cut cells: particle points).
# Consistent and hybrid mass in 2D run on the aligned body; the unaligned
# one with consistent MUSL (the particle points' consistent mass next to
# the fitted cells' closed-form integrals) in the slow tier.
TLS_CASES = [
    dict(dim=1, scheme="musl", mass="hybrid", degree=2, effect="gravity", aligned=False),
    dict(dim=1, scheme="musl", mass="lumped", degree=3, effect="gravity", aligned=False),
    dict(dim=1, scheme="usl", mass="lumped", degree=3, effect="none", aligned=False),
    dict(dim=1, scheme="cd", mass="consistent", degree=2, effect="gravity", aligned=False),
    dict(dim=1, scheme="rk4", mass="consistent", degree=3, effect="gravity", aligned=False),
    dict(dim=2, scheme="musl", mass="lumped", degree=2, effect="gravity", aligned=False),
    dict(dim=2, scheme="musl", mass="consistent", degree=2, effect="gravity", aligned=True),
    dict(dim=2, scheme="musl", mass="hybrid", degree=3, effect="gravity", aligned=True),
    dict(dim=2, scheme="usl", mass="consistent", degree=3, effect="none", aligned=True),
    dict(dim=2, scheme="cd", mass="lumped", degree=2, effect="gravity", aligned=True),
    dict(dim=2, scheme="rk4", mass="lumped", degree=2, effect="gravity", aligned=False),
    dict(dim=2, scheme="rk4", mass="consistent", degree=2, effect="gravity", aligned=True),
    dict(dim=2, scheme="musl", mass="consistent", degree=2, effect="gravity", aligned=False),
]


def test_the_tls_cases_cover_every_pair():
    """Every scheme with every mass kind it has, and each in both dimensions."""
    pairs = {(c["scheme"], c["mass"]) for c in TLS_CASES}
    assert pairs == {(s, m) for s in ("musl", "usl", "cd", "rk4") for m in ("lumped", "consistent")
                     } | {("musl", "hybrid")}
    for name in ("scheme", "mass"):
        assert {(c["dim"], c[name]) for c in TLS_CASES} == \
            {(d, c[name]) for d in (1, 2) for c in TLS_CASES}, name
    assert {c["aligned"] for c in TLS_CASES if c["dim"] == 2} == {True, False}


DEFAULT_TLS_CASES = {  # the default tier's cases (tests/tiers.py)
    "1-cd-consistent-2-gravity-False",
    "1-musl-hybrid-2-gravity-False",
    "1-musl-lumped-3-gravity-False",
    "1-rk4-consistent-3-gravity-False",
    "1-usl-lumped-3-none-False",
    "2-cd-lumped-2-gravity-True",
    "2-musl-consistent-2-gravity-True",
    "2-musl-hybrid-3-gravity-True",
    "2-rk4-consistent-2-gravity-True",
    "2-rk4-lumped-2-gravity-False",
    "2-usl-consistent-3-none-True",
}


@pytest.mark.parametrize("case", tiered(
    "tls in the loop", TLS_CASES, _case_id, DEFAULT_TLS_CASES),
                         ids=_case_id)
def test_tls_reconstruction_gives_the_executors_bits(monkeypatch, case):
    full = dict(case, material="linear", reconstruction="tls", ppc=3)
    scene = scene_for(full, steps=23)
    method = Method(scheme=case["scheme"], mass=case["mass"], reconstruction="tls")
    looped, stepped = looped_and_stepped(monkeypatch, scene, method)
    assert stepped.path == "fast (reconstruction tls)"
    assert len(looped.reactions) > 0
    assert looped.counts["compiled_loop_steps"] >= 18
    assert looped.phase_table()["reconstruct"] > 0.0


# The 2D spline (its direct solve: the banded Cholesky, kept for the step's
# MUSL projection) and mls (M_g^-1 e_0 and each point's weighted particles
# kept likewise) on the rule TLS uses, in the loop: the same bits as the
# executor. Coverage rule (tests/tiers.py, checked by tests/test_tiers.py):
# the default tier runs every reconstruction, every dimension and both mass
# kinds (lumped; a mass system: consistent or hybrid), which the 2D spline
# with consistent MUSL on the aligned body (issue 18's configuration) and
# 1D mls with lumped MUSL give; the slow tier every other scheme, mass
# kind, degree, 2D mls (particle points) and the spline's cut cells. (The
# schemes and the effects are the other loop families' coverage: here each
# would compile one more loop variant per reconstruction.)
RULED_CASES = [
    dict(reconstruction="spline", dim=2, scheme="musl", mass="consistent", degree=2,
         effect="gravity", aligned=True),
    dict(reconstruction="mls", dim=1, scheme="musl", mass="lumped", degree=2, effect="gravity",
         aligned=False),
    dict(reconstruction="mls", dim=2, scheme="musl", mass="lumped", degree=2, effect="gravity",
         aligned=False),
    dict(reconstruction="spline", dim=2, scheme="musl", mass="lumped", degree=2,
         effect="gravity", aligned=False),
    dict(reconstruction="spline", dim=2, scheme="musl", mass="hybrid", degree=3,
         effect="gravity", aligned=True),
    dict(reconstruction="spline", dim=2, scheme="usl", mass="consistent", degree=3,
         effect="none", aligned=True),
    dict(reconstruction="spline", dim=2, scheme="cd", mass="lumped", degree=2, effect="gravity",
         aligned=True),
    dict(reconstruction="spline", dim=2, scheme="rk4", mass="consistent", degree=2,
         effect="gravity", aligned=True),
    dict(reconstruction="mls", dim=2, scheme="musl", mass="consistent", degree=2,
         effect="gravity", aligned=True),
    dict(reconstruction="mls", dim=2, scheme="usl", mass="lumped", degree=3, effect="none",
         aligned=True),
    dict(reconstruction="mls", dim=2, scheme="cd", mass="consistent", degree=2,
         effect="gravity", aligned=True),
    dict(reconstruction="mls", dim=2, scheme="rk4", mass="lumped", degree=2, effect="gravity",
         aligned=False),
    dict(reconstruction="mls", dim=1, scheme="musl", mass="hybrid", degree=2, effect="gravity",
         aligned=False),
    dict(reconstruction="mls", dim=1, scheme="rk4", mass="consistent", degree=3,
         effect="gravity", aligned=False),
]
DEFAULT_RULED_CASES = {  # the default tier's cases (tests/tiers.py)
    "spline-2-musl-consistent-2-gravity-True",
    "mls-1-musl-lumped-2-gravity-False",
}


def _ruled_coverage(case):
    """What the default tier of the ruled family covers: every value of
    the reconstruction, the dimension and the mass kind (lumped, or a mass
    system: consistent and hybrid share the loop's MassSystem)."""
    return dict(reconstruction=case["reconstruction"], dim=case["dim"],
                mass="lumped" if case["mass"] == "lumped" else "system")


@pytest.mark.parametrize("case", tiered(
    "spline and mls on the rule in the loop", RULED_CASES, _case_id, DEFAULT_RULED_CASES,
    paired=(), options=_ruled_coverage), ids=_case_id)
def test_spline_and_mls_on_the_rule_give_the_executors_bits(monkeypatch, case):
    full = dict(case, material="linear", ppc=3)
    scene = scene_for(full, steps=23)
    method = Method(scheme=case["scheme"], mass=case["mass"],
                    reconstruction=case["reconstruction"])
    looped, stepped = looped_and_stepped(monkeypatch, scene, method)
    assert stepped.path == f"fast (reconstruction {case['reconstruction']})"
    assert looped.counts["compiled_loop_steps"] >= 18
    assert looped.phase_table()["reconstruct"] > 0.0


def test_the_unaligned_2d_tls_rule_has_particle_points():
    """The unaligned 2D cases integrate cut cells with their particles
    (CompiledReconstruction.rule's particle_points), the aligned ones not."""
    for aligned in (False, True):
        case = dict(TLS_CASES[5], aligned=aligned, material="linear", reconstruction="tls", ppc=3)
        state = prepare(scene_for(case, steps=5), Method(reconstruction="tls"))
        rule = CompiledExecutor(state).recon.rule(state.particles)
        assert (getattr(rule, "particle_points", None) is not None) == (not aligned)


# ---------------------------------------------------------------- point laws
# A body whose material has a compiled point law (not the fused linear
# elasticity): g2p stores L, the constitutive kernel (material_update, the
# executor's call) updates stress, V, F (finite strain) and the packed
# material state into the run's second set of arrays, swapped at commit; a
# J <= 0 or a non-finite state stops the loop (the executor raises). The
# loop hands the new F and state back to the particles as the executor
# does. A user's small-strain law, NeoHookean (finite strain; a fixed dt:
# its adaptive steps are tests/test_compiled_loop_adaptive.py's) and the
# plastic materials with per-particle state (2D); musl, usl, cd; lumped,
# consistent and hybrid mass; once with TLS reconstruction.
SHEAR, COHESION = 0.3, 0.4  # the block yields near its walls, tiny masses do not occur


def plastic_material(name, c=COHESION):
    return {"mohr-coulomb": MohrCoulomb(10.0, 0.3, 30.0, c),
            "mohr-coulomb-large": MohrCoulomb(10.0, 0.3, 30.0, c, large_deformation=True),
            "drucker-prager": DruckerPrager(10.0, 0.3, 30.0, c),
            "von-mises": VonMises(10.0, 0.3, 2 * c, hardening=1.0)}[name]


def law_scene(case, steps=23):
    """(scene, fixed dt) of a point-law case: scene_for's, or for a plastic
    material a 2D block sheared against the bottom and left walls, which
    yields within a few steps."""
    method = Method(scheme=case["scheme"], mass=case["mass"])
    if case["material"] in ("custom-compiled", "neo-hookean"):
        scene = scene_for(dict(case, effect="gravity"), steps=steps)
        grid, body, effects = scene.grid, scene.bodies[0], scene.effects
    else:
        grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (6, 5), case["degree"])
        region = ((0.0, 4 / 6), (0.0, 0.6)) if case.get("aligned") else \
            ((0.0, 0.7), (0.0, 0.62))
        shear = case.get("shear", SHEAR)
        particles = Particles.seed(grid, case.get("ppc", 2), 1.0, region=region,
                                   velocity=lambda X: np.column_stack((shear * X[:, 1],
                                                                       -0.3 * X[:, 0])))
        body = Body(particles, plastic_material(case["material"],
                                                case.get("cohesion", COHESION)))
        effects = [Fixed("bottom"), Fixed("left", 0), Gravity((0.0, -2.0))]
    dt = prepare(Scene(grid, body, 1.0, effects=effects), method).dt
    return Scene(grid, body, steps * dt, effects=effects), dt


LAW_CASES = [  # every scheme x mass pair, each material in both dimensions it models
    dict(material="custom-compiled", dim=1, scheme="musl", mass="lumped", degree=2),
    dict(material="custom-compiled", dim=2, scheme="cd", mass="consistent", degree=2,
         aligned=True),
    dict(material="neo-hookean", dim=1, scheme="usl", mass="lumped", degree=3),
    dict(material="neo-hookean", dim=1, scheme="cd", mass="consistent", degree=2),
    dict(material="neo-hookean", dim=2, scheme="musl", mass="lumped", degree=2),
    dict(material="mohr-coulomb", dim=2, scheme="musl", mass="hybrid", degree=2, aligned=True),
    dict(material="mohr-coulomb-large", dim=2, scheme="cd", mass="lumped", degree=2),
    dict(material="drucker-prager", dim=2, scheme="usl", mass="consistent", degree=2,
         aligned=True),
    dict(material="von-mises", dim=2, scheme="musl", mass="consistent", degree=1, aligned=True),
    dict(material="mohr-coulomb", dim=2, scheme="usl", mass="lumped", degree=2,
         reconstruction="tls", ppc=3),
    # rk4 stages a finite-strain law at each stage's F (dF/dt = L F, the law with dt = 0)
    dict(material="neo-hookean", dim=1, scheme="rk4", mass="consistent", degree=3),
    dict(material="neo-hookean", dim=2, scheme="rk4", mass="lumped", degree=2),
]


def check_law_case(monkeypatch, case, steps=23):
    scene, dt = law_scene(case, steps)
    recon = case.get("reconstruction", "none")
    method = Method(scheme=case["scheme"], mass=case["mass"], dt=dt, reconstruction=recon)
    with monkeypatch.context() as m:
        m.setattr(StencilSystem, "FRINGE_LAYERS", 0)  # 2D consistent: the loop keeps going
        looped = simulate(scene, method, save_every=5)
        stepped = without_loop(monkeypatch, scene, method, save_every=5)
    assert looped.path == "fast (compiled loop)"
    assert stepped.path == ("fast" if recon == "none" else f"fast (reconstruction {recon})")
    assert_same(looped, stepped)
    assert np.array_equal(looped.history["V"], stepped.history["V"])
    names = tuple(scene.bodies[0].material.state_fields(case["dim"]))
    for name in names:  # the material state at every save and at the end
        assert np.array_equal(looped.history[name], stepped.history[name]), name
        assert np.array_equal(looped.particles.state[name], stepped.particles.state[name]), name
    assert looped.particles.state.keys() == stepped.particles.state.keys()
    F = looped.particles.F
    assert (F is None) == (stepped.particles.F is None) == (not scene.finite_strain)
    if F is not None:
        assert np.array_equal(F, stepped.particles.F)
        assert not np.array_equal(F, scene.bodies[0].particles.F)  # it moved
    assert len(looped.reactions) == len(stepped.reactions) > 0
    for a, b in zip(looped.reactions, stepped.reactions):
        assert a.keys() == b.keys()
        for key in a:
            assert np.array_equal(a[key], b[key]), key
    assert looped.phase_table()["constitutive"] > 0.0
    if "plastic_strain" in names:  # the law yielded: the state matters
        assert looped.particles.state["plastic_strain"].max() > 0.01
    return looped, stepped


DEFAULT_LAW_CASES = {  # the default tier's cases (tests/tiers.py)
    "custom-compiled-1-musl-lumped-2",
    "drucker-prager-2-usl-consistent-2-True",
    "mohr-coulomb-2-musl-hybrid-2-True",
    "mohr-coulomb-2-usl-lumped-2-tls-3",
    "mohr-coulomb-large-2-cd-lumped-2",
    "neo-hookean-1-cd-consistent-2",
    "neo-hookean-1-usl-lumped-3",
    "neo-hookean-1-rk4-consistent-3",
    "neo-hookean-2-rk4-lumped-2",
    "von-mises-2-musl-consistent-1-True",
}


@pytest.mark.parametrize("case", tiered(
    "point laws in the loop", LAW_CASES, _case_id, DEFAULT_LAW_CASES),
                         ids=_case_id)
def test_point_laws_give_the_executors_bits(monkeypatch, case):
    looped, _ = check_law_case(monkeypatch, case)
    assert looped.counts["compiled_loop_steps"] >= 20, looped.counts


def test_the_point_law_cases_cover_every_pair():
    pairs = {(c["scheme"], c["mass"]) for c in LAW_CASES}
    assert pairs == {(s, m) for s in ("musl", "usl", "cd", "rk4")
                     for m in ("lumped", "consistent")} | {("musl", "hybrid")}
    for material in ("custom-compiled", "neo-hookean"):
        assert {c["dim"] for c in LAW_CASES if c["material"] == material} == {1, 2}


@pytest.mark.slow(
    reason="parallel kernels in the loop run in the default tier with lumped linear "
           "elasticity (test_parallel_kernels_give_the_same_bits); this one compiles another "
           "parallel run type")
def test_point_laws_with_parallel_kernels(monkeypatch):
    """Above SERIAL_BELOW the loop calls the parallel constitutive kernel
    (each thread's block flags its own J <= 0): the executor's bits."""
    case = dict(material="mohr-coulomb", dim=2, scheme="musl", mass="lumped", degree=2)
    with monkeypatch.context() as m:
        m.setattr(serial, "SERIAL_BELOW", 0)
        m.setattr(compiled_loop.StepLoop, "CALL_SECONDS", 1e-9)  # one step per call
        looped, _ = check_law_case(monkeypatch, case)
    assert looped.counts["compiled_loop_steps"] == 23


def test_point_laws_with_the_executor_between_loop_calls(monkeypatch):
    """A 2D body with hybrid mass that collapses gets tiny-mass dofs after
    a dozen steps; with no room for the merged system
    (StencilSystem.MERGE_BUFFER 0) those steps stop the loop and the
    executor takes them with its general grid system, from the F and state
    the loop handed back; the loop then goes on from the executor's. The
    same bits as the executor alone."""
    case = dict(material="mohr-coulomb-large", dim=2, scheme="musl", mass="hybrid", degree=2,
                aligned=True, shear=0.5, cohesion=0.02)
    monkeypatch.setattr(StencilSystem, "MERGE_BUFFER", 0)
    looped, _ = check_law_case(monkeypatch, case)
    assert 0 < looped.counts["compiled_loop_steps"] < looped.counts["steps"]


def test_point_law_handed_back_arrays_are_the_loops_own(monkeypatch):
    """The particles the loop starts from (the scene's, the executor's) are
    never written; what the loop hands back (x, stress, V, F, the state's
    views) are new arrays of its own, and the executor's next step writes
    new arrays, not the loop's."""
    case = dict(material="mohr-coulomb-large", dim=2, scheme="musl", mass="lumped", degree=2)
    scene, dt = law_scene(case, steps=12)
    given = scene.bodies[0].particles
    before = given.copy()
    state = prepare(scene, Method(scheme="musl", dt=dt))
    ops = CompiledExecutor(state)
    loop = compiled_loop.StepLoop(state, ops)
    loop.compile()
    start = state.particles
    assert loop.run(state, 4) == 4
    first = state.particles
    kept = first.copy()
    arrays = [first.x, first.stress, first.V, first.F, *first.state.values()]
    for a in arrays:
        assert not any(np.shares_memory(a, b) for b in
                       [start.x, start.stress, start.V, start.F, *start.state.values()])
    schemes_step = compiled_loop.schemes.step_musl
    schemes_step(ops, state)  # the executor takes a step from the loop's particles
    second = state.particles
    for a, b in zip(arrays, [second.x, second.stress, second.V, second.F,
                             *second.state.values()]):
        assert not np.shares_memory(a, b)
    for name in ("x", "stress", "V", "F"):  # the executor did not write the loop's arrays
        assert np.array_equal(getattr(first, name), getattr(kept, name)), name
    for name in first.state:
        assert np.array_equal(first.state[name], kept.state[name]), name
    snapshot = second.copy()
    assert loop.run(state, 4) == 4  # from the executor's particles, which stay as they were
    for name in ("x", "stress", "V", "F"):
        assert np.array_equal(getattr(second, name), getattr(snapshot, name)), name
    for name in second.state:
        assert np.array_equal(second.state[name], snapshot.state[name]), name
    assert state.step == 9
    for name in ("x", "v", "stress", "V", "F", "V0"):  # the scene's particles
        assert np.array_equal(getattr(given, name), getattr(before, name)), name
    for name in before.state:
        assert np.array_equal(given.state[name], before.state[name]), name


def test_a_point_law_failing_step_raises_as_without_the_loop(monkeypatch):
    """J <= 0 in the constitutive kernel (a NeoHookean bar compressed
    through itself): the loop stops before writing the state, the executor
    takes that step and raises."""
    grid = SplineGrid.line(0.0, 1.0, 8, 2)
    particles = Particles.seed(grid, 2, 1.0, region=((0.0, 0.75),),
                               velocity=lambda X: -40.0 * X)
    scene = Scene(grid, Body(particles, NeoHookean(10.0)), 1.0, effects=[Fixed("left")])
    dt = prepare(scene, Method(scheme="usl")).dt
    scene = Scene(grid, Body(particles, NeoHookean(10.0)), 40 * dt, effects=[Fixed("left")])
    method = Method(scheme="usl", dt=dt)
    with pytest.raises(SimulationError) as looped:
        simulate(scene, method, save_every=5)
    with pytest.raises(SimulationError) as stepped:
        without_loop(monkeypatch, scene, method, save_every=5)
    assert str(looped.value) == str(stepped.value)
    assert "J = det" in str(looped.value)
    assert looped.value.step == stepped.value.step > 1
    assert looped.value.result.counts["compiled_loop_steps"] > 0
    assert_same(looped.value.result, stepped.value.result)
    assert np.array_equal(looped.value.result.particles.F, stepped.value.result.particles.F)


# ------------------------------------------------------------ side traction
# A traction on a side of the body with tau(t): its loaded faces, loads and
# grid force (the p2g kernel at the faces) in the run, tau tabulated by
# Python at the steps' times before each call; the work of the loads.
TRACTION_CASES = [
    dict(scheme="musl", mass="lumped", degree=2, dim=1),
    dict(scheme="musl", mass="consistent", degree=3, dim=1),
    dict(scheme="usl", mass="consistent", degree=2, dim=2),
    dict(scheme="cd", mass="lumped", degree=1, dim=2),
    dict(scheme="rk4", mass="consistent", degree=3, dim=1),
    dict(scheme="rk4", mass="lumped", degree=2, dim=2),
    dict(scheme="musl", mass="lumped", degree=2, dim=2, reconstruction="tls"),
]


DEFAULT_TRACTION_CASES = {  # the default tier's cases (tests/tiers.py)
    "cd-lumped-1-2",
    "musl-consistent-3-1",
    "musl-lumped-2-1",
    "musl-lumped-2-2-tls",
    "rk4-consistent-3-1",
    "rk4-lumped-2-2",
    "usl-consistent-2-2",
}


@pytest.mark.parametrize("case", tiered(
    "side traction in the loop", TRACTION_CASES, _case_id, DEFAULT_TRACTION_CASES),
                         ids=_case_id)
def test_a_side_traction_gives_the_executors_bits(monkeypatch, case):
    full = dict(case, material="linear", effect="traction", aligned=True)
    scene = scene_for(full, steps=23)
    method = Method(scheme=case["scheme"], mass=case["mass"],
                    reconstruction=case.get("reconstruction", "none"))
    looped, _ = looped_and_stepped(monkeypatch, scene, method)
    assert looped.counts["compiled_loop_steps"] >= 20
    assert looped.energies["external_work"][-1] != 0.0  # the loads' work is counted


def test_a_traction_of_x_and_t_stays_with_the_executor():
    full = dict(scheme="musl", mass="lumped", degree=2, dim=1, material="linear",
                effect="none", aligned=True)
    scene = scene_for(full, steps=5)
    loaded = Scene(scene.grid, scene.bodies, scene.t_end,
                   effects=list(scene.effects) + [Traction("right", lambda x, t: 0.01 * t)])
    state = prepare(loaded, Method(scheme="musl"))
    ok, why = compiled_loop.loop_applies(state, CompiledExecutor(state))
    assert not ok and "traction on a side of the body with tau(t)" in why


def test_what_the_loop_leaves_to_the_executor(monkeypatch):
    case = mass_case(MASS_CASES[0])
    scene = scene_for(case, steps=5)
    state = prepare(scene, Method(scheme="musl", mass="consistent", mass_solver="direct"))
    assert compiled_loop.loop_applies(state, CompiledExecutor(state)) == \
        (False, "mass_solver 'direct' (sparse LU)")
    state = prepare(scene, Method(scheme="musl", mass="consistent"))
    with preconditioned_with("lumped"):
        assert not compiled_loop.loop_applies(state, CompiledExecutor(state))[0]
    assert compiled_loop.loop_applies(state, CompiledExecutor(state)) == (True, "")
    dim = scene.grid.dim
    state = prepare(scene, Method(scheme="musl", reconstruction="mls"))
    assert compiled_loop.loop_applies(state, CompiledExecutor(state)) == (True, "")
    plate = scene_for(mass_case(MASS_CASES[4]), steps=5)
    state = prepare(plate, Method(scheme="musl", reconstruction="spline"))
    assert compiled_loop.loop_applies(state, CompiledExecutor(state)) == (True, "")
    monkeypatch.setattr(compiled_reconstruct, "DIRECT_DOFS", 0)
    state = prepare(plate, Method(scheme="musl", reconstruction="spline"))
    assert compiled_loop.loop_applies(state, CompiledExecutor(state)) == \
        (False, "reconstruction spline in 2D with its Kronecker-preconditioned CG "
         "(DIRECT_DOFS cubic dofs or more)")
    state = prepare(scene, Method(scheme="musl", reconstruction="tls"))
    assert compiled_loop.loop_applies(state, CompiledExecutor(state)) == (True, "")
    grid, effects = scene.grid, scene.effects
    particles = scene.bodies[0].particles
    for material, scheme, why in [
            (CappedStress(10.0, 0.3, 0.05), "musl",
             "a material without a compiled point law (point_update None)"),
            (UnfusedLinearElastic(10.0, 0.3), "rk4",
             "rk4 with a small-strain material other than linear elasticity (its NumPy "
             "stress_rate)"),
            (CappedStressCompiled(10.0, 0.3, 0.05), "cd", "")]:
        state = prepare(Scene(grid, Body(particles, material), scene.t_end, effects=effects),
                        Method(scheme=scheme))
        assert compiled_loop.loop_applies(state, CompiledExecutor(state)) == (not why, why)
    two = Scene(grid, [Body(particles, CappedStressCompiled(10.0, 0.3, 0.05)),
                       Body(particles, NeoHookean(10.0))], scene.t_end, effects=effects)
    state = prepare(two, Method(scheme="musl", dt=1e-3))
    assert compiled_loop.loop_applies(state, CompiledExecutor(state)) == \
        (False, "several bodies of different materials")
    neo = Scene(grid, Body(particles, NeoHookean(10.0)), scene.t_end, effects=effects)
    state = prepare(neo, Method(scheme="musl"))  # finite strain: dt adaptive by default
    assert state.adaptive
    assert compiled_loop.loop_applies(state, CompiledExecutor(state)) == (True, "")


class UnfusedLinearElastic(LinearElastic):
    """Linear elasticity not fused into the transfer kernels (its type is not
    LinearElastic): a small-strain point law with a NumPy stress rate."""


def box_scene(scheme, degree, effect, steps=13):
    """A 3D block (4 x 3 x 3 cells of a 5 x 4 x 4 grid, not aligned with the
    knots) with a shear velocity, fixed at zmin, with or without gravity."""
    grid = SplineGrid.box((0.0, 1.0), (0.0, 1.0), (0.0, 1.0), (5, 4, 4), degree)
    velocity = lambda X: np.column_stack((0.05 * X[:, 2], -0.03 * X[:, 0],  # noqa: E731
                                          0.02 * X[:, 1]))
    particles = Particles.seed(grid, 2, 1.0, region=((0.0, 0.75), (0.0, 0.7), (0.0, 0.72)),
                               velocity=velocity)
    effects = [Fixed("zmin")] + ([Gravity((0.0, 0.0, -2.0))] if effect == "gravity" else [])
    body = Body(particles, LinearElastic(10.0, 0.3))
    dt = prepare(Scene(grid, body, 1.0, effects=effects), Method(scheme=scheme)).dt
    return Scene(grid, body, steps * dt, effects=effects)


SLOW_3D = pytest.mark.slow(reason="one more compiled 3D loop variant; the default tier runs "
                           "one per scheme at p = 1 or 2")


@pytest.mark.parametrize("scheme,degree,effect", [
    ("musl", 2, "gravity"), ("usl", 1, "none"), ("cd", 2, "none"), ("rk4", 2, "gravity"),
    # cubic 3D kernels compile for tens of seconds: the slow tier
    pytest.param("cd", 3, "gravity", marks=SLOW_3D), pytest.param("usl", 3, "none", marks=SLOW_3D),
    pytest.param("musl", 1, "none", marks=SLOW_3D), pytest.param("usl", 2, "gravity",
                                                                  marks=SLOW_3D)])
def test_a_3d_run_in_the_loop_gives_the_executors_bits(monkeypatch, scheme, degree, effect):
    """The loop's operations are the same source in 3D (lumped mass, one
    linear elastic body): the run is the executor's, bit for bit, reactions
    included."""
    looped, _ = looped_and_stepped(monkeypatch, box_scene(scheme, degree, effect),
                                   Method(scheme=scheme))
    assert looped.counts["compiled_loop_steps"] == looped.counts["steps"] == 13
    assert np.abs(looped.history["v"][-1]).max() > 0


@pytest.mark.parametrize("scheme,mass,degree,effect", [
    ("musl", "consistent", 2, "gravity"), ("rk4", "consistent", 2, "gravity"),
    # the variants test_three_d_compiled compiles run in the default tier
    pytest.param("usl", "consistent", 1, "none", marks=SLOW_3D),
    pytest.param("musl", "hybrid", 2, "gravity", marks=SLOW_3D)])
def test_consistent_mass_in_3d_in_the_loop_gives_the_executors_bits(monkeypatch, scheme, mass,
                                                                    degree, effect):
    """Consistent and hybrid mass in the 3D loop: the stencil of
    consistent_axes and the three-factor Kronecker preconditioner
    (apply_kronecker_axes), as the executor's StencilSystem; the block's
    free surface cuts cells, so some steps merge tiny-mass dofs."""
    looped, _ = looped_and_stepped(monkeypatch, box_scene(scheme, degree, effect),
                                   Method(scheme=scheme, mass=mass))
    assert looped.counts["compiled_loop_steps"] == looped.counts["steps"] >= 13
    assert np.abs(looped.history["v"][-1]).max() > 0


def test_colliding_spheres_with_consistent_mass_run_in_the_loop(monkeypatch):
    """T3 at 8^3 cells with consistent mass: tiny-mass dofs on the spheres'
    surfaces at every step, merged in the 3D loop as in the executor."""
    from skfem_mpm.benchmarks import get_benchmark

    scene = get_benchmark("colliding-spheres").scene(cells=8, t_end=0.3)
    looped, _ = looped_and_stepped(monkeypatch, scene, Method(mass="consistent"))
    assert looped.counts["small_dofs_max"] > 0
    assert looped.counts["compiled_loop_steps"] == looped.counts["steps"] >= 20


def test_colliding_spheres_get_a_kronecker_box_each():
    """T3 at 8^3 cells, consistent mass (MUSL, t_end 0.3: the spheres
    approach): the Kronecker preconditioner takes a box per coupled
    component of the free dofs (kernels.kronecker.kronecker_boxes), one per
    sphere, the fast-lumped rows their own diagonal. Measured: 23.7 CG
    iterations per solve (one box over both spheres: 54.6)."""
    from skfem_mpm.benchmarks import get_benchmark
    from skfem_mpm.solve.stencil_system import preconditioned_with

    scene = get_benchmark("colliding-spheres").scene(cells=8, t_end=0.3)
    with preconditioned_with("kronecker") as iterations:  # (the executor: the log)
        result = simulate(scene, Method(mass="consistent"))
    assert result.counts["steps"] == 23 and len(iterations) == 47
    assert np.mean(iterations) < 30


def test_colliding_disks_get_a_kronecker_box_each():
    """D3 (20 x 20 quadratic cells, consistent MUSL, t_end 0.15: the scene
    of test_colliding_disks_with_consistent_mass_run_in_the_loop, which
    checks the loop's bits on it): in 2D too the Kronecker preconditioner
    of a scene of several bodies takes a box per coupled component of the
    free dofs when there are two or more (kernels.kronecker.kronecker_boxes),
    one per disk. Measured:
    11.9 CG iterations per solve (570 in 48 runs; one box over both disks:
    18.5, 889)."""
    from skfem_mpm.benchmarks import get_benchmark
    from skfem_mpm.solve.stencil_system import preconditioned_with

    scene = get_benchmark("colliding-disks").scene(t_end=0.15)
    with preconditioned_with("kronecker") as iterations:  # (the executor: the log)
        result = simulate(scene, Method(mass="consistent"))
    assert result.counts["steps"] == 23 and len(iterations) == 48
    assert np.mean(iterations) < 14


def separate_blocks(bodies, steps=12):
    """Two blocks of one material, two cells apart on a 16 x 8 quadratic grid
    (their free dofs share no mass-matrix entry), with cell-aligned edges (no
    tiny masses), moving towards each other, fixed at the bottom; as two
    Bodies or as one."""
    grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (16, 8), 2)

    def velocity(sign):
        return lambda X: np.column_stack((0.1 * sign + 0 * X[:, 0], 0.05 * np.sin(3 * X[:, 0])))

    left = Particles.seed(grid, 2, 1.0, region=((0.125, 0.375), (0.125, 0.625)),
                          velocity=velocity(1))
    right = Particles.seed(grid, 2, 1.0, region=((0.625, 0.875), (0.25, 0.75)),
                           velocity=velocity(-1))
    material = LinearElastic(10.0, 0.3)
    parts = [Body(left, material), Body(right, material)] if bodies == 2 else \
        [Body(Particles.concatenate([left, right]), material)]
    effects = [Fixed("bottom")]
    dt = prepare(Scene(grid, parts, 1.0, effects=effects), Method()).dt
    return Scene(grid, parts, steps * dt, effects=effects)


def test_separate_bodies_without_tiny_masses_get_a_kronecker_box_each(monkeypatch):
    """The 2D box per coupled component where no dof is merged (the disks
    merge tiny masses every step): two separate blocks as two bodies take a
    box each, in the loop as on the executor (same bits), and their CG
    needs fewer iterations than the same blocks as one body (one box over
    both). Measured: 23.8 against 35.5 iterations per solve (50 runs)."""
    from skfem_mpm.solve.stencil_system import preconditioned_with

    method = Method(mass="consistent")
    looped, _ = looped_and_stepped(monkeypatch, separate_blocks(2), method)
    assert looped.counts["compiled_loop_steps"] == looped.counts["steps"] == 24
    assert looped.counts["small_dofs_max"] == 0
    mean = {}
    for bodies in (1, 2):
        with preconditioned_with("kronecker") as iterations:  # (the executor: the log)
            simulate(separate_blocks(bodies), method)
        mean[bodies] = np.mean(iterations)
    assert mean[2] < 0.8 * mean[1], mean


def test_fringe_correction_takes_the_one_box_of_several_bodies(monkeypatch):
    """The exception to a box per body: the fringe correction
    (kernels.fringe) works on the one box of the free dofs, so with it on
    (here from the first solve, the band factor off) the two separate
    blocks of the test above take one Kronecker box as if they were one
    body, and move as the one-body run moves (the same physics: no mass
    entry joins them) to CG's tolerance. A box per body with the fringe on
    does not compile (the fringe step needs the one box's numbering)."""
    from skfem_mpm.kernels.kronecker import KroneckerData

    built = KroneckerData.of_system.__func__
    boxes = []

    def spy(cls, *args, **kwargs):
        data = built(cls, *args, **kwargs)
        boxes.append("one" if data.boxes is None else "per component")
        return data

    monkeypatch.setattr(KroneckerData, "of_system", classmethod(spy))
    x = {}
    for bodies in (1, 2):
        with preconditioned_with("kronecker+fringe") as iterations:
            monkeypatch.setattr(StencilSystem, "BAND_MAX", 0)
            monkeypatch.setattr(StencilSystem, "FRINGE_FROM", 0)
            monkeypatch.setattr(StencilSystem, "FRINGE_MIN_ROWS", 0)
            result = simulate(separate_blocks(bodies), Method(mass="consistent"))
        assert result.counts["steps"] == 24 and len(iterations) == 50
        assert set(boxes) == {"one"}, (bodies, set(boxes))
        boxes.clear()
        x[bodies] = result.particles.x
    assert np.abs(x[2] - x[1]).max() < 1e-9 * np.abs(x[1]).max()


def two_blocks(E_right=10.0, steps=23):
    """Two blocks moving towards each other on a 2D grid (quadratic), each
    its own Body, fixed at the bottom, under gravity."""
    grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (8, 6), 2)
    left = Particles.seed(grid, 2, 1.0, region=((0.1, 0.45), (0.0, 0.5)),
                          velocity=lambda X: np.column_stack((0.2 + 0 * X[:, 0], 0 * X[:, 1])))
    right = Particles.seed(grid, 2, 1.0, region=((0.55, 0.9), (0.0, 0.4)),
                           velocity=lambda X: np.column_stack((-0.2 + 0 * X[:, 0], 0 * X[:, 1])))
    bodies = [Body(left, LinearElastic(10.0, 0.3)), Body(right, LinearElastic(E_right, 0.3))]
    effects = [Fixed("bottom"), Gravity((0.0, -2.0))]
    dt = prepare(Scene(grid, bodies, 1.0, effects=effects), Method()).dt
    return Scene(grid, bodies, steps * dt, effects=effects)


@pytest.mark.parametrize("scheme", ["musl", "usl"])
def test_bodies_of_one_linear_elastic_material_run_in_the_loop(monkeypatch, scheme):
    """Several bodies of one linear elastic material (equal E and nu) are one
    material to the compiled paths: its stress update fused for every
    particle, in the loop and in the executor (bit for bit), and the
    reference (per body) agrees to round-off."""
    scene = two_blocks()
    looped, _ = looped_and_stepped(monkeypatch, scene, Method(scheme=scheme))
    assert looped.counts["compiled_loop_steps"] == looped.counts["steps"] == 23
    reference = simulate(scene, Method(scheme=scheme, backend="numpy"), save_every=5)
    for key in KEYS:
        a, b = reference.history[key], looped.history[key]
        assert np.abs(a - b).max() <= 1e-12 * np.abs(a).max(), key
    assert np.abs(looped.history["stress"][-1]).max() > 0


@pytest.mark.parametrize("save_every", [None, 23])
def test_the_last_save_keeps_the_last_steps_arrays(save_every):
    """The save of the last step (after the loop, or its own save_every
    save) keeps the arrays the result's particles hold (nothing writes them
    again) instead of a copy: a state less per particle at the peak."""
    result = simulate(two_blocks(), Method(scheme="usl"), save_every=save_every)
    assert result.counts["steps"] == 23
    saved = dict.__getitem__(result.history, "x")  # the list, before History stacks it
    assert saved[-1] is result.particles.x
    assert dict.__getitem__(result.history, "stress")[-1] is result.particles.stress
    assert not np.array_equal(saved[-1], saved[0])


def test_bodies_of_different_materials_stay_with_the_executor():
    state = prepare(two_blocks(E_right=20.0), Method())
    executor = CompiledExecutor(state)
    assert not executor.fused
    assert compiled_loop.loop_applies(state, executor) == \
        (False, "several bodies of different materials")
