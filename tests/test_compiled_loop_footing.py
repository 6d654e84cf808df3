"""The rigid footing and B-bar on the compiled paths.

The footing's compiled rule (kernels.grid_modifiers FOOTING) is the
effect's NumPy ``modify_force`` / ``modify_velocity`` to round-off; B-bar's
cell average (kernels.bbar) is ``BBar.averaged`` to the last bit; a footing
scene with a B-bar plastic material runs in the compiled step loop and gives
the compiled executor's bits (particles, material state, the footing's
reaction and load-settlement history), also when the executor takes steps
between calls of the loop.
"""
import numpy as np
import pytest

from skfem_mpm import (BBar, Body, Fixed, Footing, LinearElastic, Method, Particles, Scene,
                       SplineGrid, VonMises, simulate)
from skfem_mpm.kernels import grid_modifiers
from skfem_mpm.kernels.bbar import average_dilatation
from skfem_mpm.kernels.records import grid_record
from skfem_mpm.solve import compiled_loop, schemes
from skfem_mpm.solve.compiled import CompiledExecutor
from skfem_mpm.solve.state import prepare

from test_compiled_loop import assert_same, without_loop

E, NU, RHO = 100.0, 0.3, 1.0


def _random_grid_state(grid, rng):
    nd, dim = grid.ndofs, grid.dim
    force = rng.normal(size=(nd, dim))
    velocity = rng.normal(size=(nd, dim))
    mass = rng.random(nd) + 0.1
    mass[rng.random(nd) < 0.2] = 0.0  # empty nodes
    return force, velocity, mass


GRIDS = {2: lambda: SplineGrid.rectangle((0.0, 1.0), (0.0, 1.25), (4, 5), 2),
         3: lambda: SplineGrid.box((0.0, 1.0), (0.0, 1.0), (0.0, 1.0), (2, 3, 3), 1)}


@pytest.mark.parametrize("dim", (2, 3))
@pytest.mark.parametrize("rough", (True, False))
def test_the_footing_rule_is_the_effects_numpy_method(dim, rough):
    """kernels.grid_modifiers FOOTING against Footing.modify_force and
    modify_velocity on random grid states (empty nodes among them) at
    times in the ramp, after it, with the base in a lower cell and below
    the grid (clamped): forces and velocities to round-off (1e-13), the
    reaction to 1e-13, the recorded end time and base exactly (one rule
    among a wall and a damping, in order)."""
    rng = np.random.default_rng(dim + 2 * rough)
    grid = GRIDS[dim]()
    span = (0.0, 0.5) if dim == 2 else ((0.0, 0.5), (0.25, 1.0))
    top = grid.bounds[-1][1] - (0.25 if dim == 2 else 0.0)
    footing = Footing(span, top, 0.8, rough=rough, ramp=0.3)
    from skfem_mpm import Damping, Wall

    modifiers = [Wall("xmax", friction=0.3), footing, Damping(0.2)]
    for m in modifiers:
        m.check(grid)
    footing.bind(None, grid)
    packed = grid_modifiers.pack_rules([m.grid_rule(grid) for m in modifiers], dim)
    codes, parameters, offsets, dofs, reactions, data_offsets, data, states = packed
    moved = False
    for clock in (0.0, 0.1, 0.45, 0.6, 5.0):
        force, velocity, mass = _random_grid_state(grid, rng)
        dt = 0.05
        states[1] = footing.rule_state()
        expected = force
        for m in modifiers:
            expected = m.modify_force(expected, velocity, mass, dt, clock, 0.0)
        got = force.copy()
        grid_modifiers.modify_forces(codes, parameters, offsets, dofs, got, velocity, mass, dt,
                                     clock, 0.0, reactions, data_offsets, data, states)
        scale = np.abs(force).max()
        assert np.allclose(got, expected, rtol=1e-13, atol=1e-13 * scale), clock
        assert np.allclose(reactions[1], footing.reaction, rtol=1e-13, atol=1e-13 * scale)
        assert states[1].tolist() == footing.rule_state().tolist()  # (clock + dt, y_b)
        if not rough:
            assert np.all(reactions[1][:-1] == 0.0)
        moved |= np.abs(reactions[1]).max() > 0
        expected_v = velocity
        for m in modifiers[:2]:
            expected_v = m.modify_velocity(expected_v, mass)
        got_v = velocity.copy()
        grid_modifiers.modify_velocities(codes, parameters, offsets, dofs, got_v, mass,
                                         data_offsets, data, states)
        assert np.allclose(got_v, expected_v, rtol=1e-13, atol=1e-13 * np.abs(velocity).max())
    assert moved
    assert footing.history[-1][0] == 5.0 + 0.05  # (the NumPy method's own record)


def test_the_footing_rule_does_nothing_to_a_velocity_before_its_first_force_step():
    grid = GRIDS[2]()
    footing = Footing((0.0, 0.5), 1.0, 0.8)
    footing.check(grid)
    footing.bind(None, grid)
    packed = grid_modifiers.pack_rules([footing.grid_rule(grid)], 2)
    packed[7][0] = footing.rule_state()  # (0, NaN)
    _, velocity, mass = _random_grid_state(grid, np.random.default_rng(0))
    got = velocity.copy()
    grid_modifiers.modify_velocities(*packed[:4], got, mass, *packed[5:])
    assert np.array_equal(got, velocity)


@pytest.mark.parametrize("stage", (0.5, 1.0))
def test_a_stage_sees_its_own_time_and_records_nothing(stage):
    """An rk4 stage at t + c dt (c = ``stage``): the footing's force is the
    one of a step's first force evaluation at that time (its base line and
    target velocity), on the NumPy method and the compiled rule (1e-13);
    the stage leaves the footing's record, rule state and reaction as the
    step's first stage left them."""
    grid = GRIDS[2]()
    force, velocity, mass = _random_grid_state(grid, np.random.default_rng(7))
    t, dt = 0.2, 0.05  # inside the ramp: the target changes with the time

    def footing():
        f = Footing((0.0, 0.5), 1.0, 0.8, ramp=0.3)
        f.check(grid)
        f.bind(None, grid)
        return f

    first = footing()
    step_force = first.modify_force(force, velocity, mass, dt, t, 0.0)
    record = (list(first.history), first.rule_state().tolist(), first.reaction.copy())
    staged = first.modify_force(force, velocity, mass, dt, t, stage)
    assert (first.history, first.rule_state().tolist()) == record[:2]
    assert np.array_equal(first.reaction, record[2])
    alone = footing()
    expected = alone.modify_force(force, velocity, mass, dt, t + stage * dt, 0.0)
    scale = np.abs(force).max()
    assert np.allclose(staged, expected, rtol=1e-13, atol=1e-13 * scale)
    assert np.abs(staged - step_force).max() > 1e-3 * scale  # (the stage's own base and goal)
    packed = grid_modifiers.pack_rules([first.grid_rule(grid)], 2)
    codes, parameters, offsets, dofs, reactions, data_offsets, data, states = packed
    states[0] = first.rule_state()
    got = force.copy()
    grid_modifiers.modify_forces(codes, parameters, offsets, dofs, got, velocity, mass, dt, t,
                                 stage, reactions, data_offsets, data, states)
    assert np.allclose(got, staged, rtol=1e-13, atol=1e-13 * scale)
    assert states[0].tolist() == record[1] and np.all(reactions == 0.0)


def rk4_footing_scene():
    from test_geo_footing import layer_under_footing

    return layer_under_footing((0.0, 0.5), speed=0.05, ramp=0.0, t_end=0.05)


def test_rk4_with_a_footing_on_every_path(monkeypatch):
    """rk4 (an elastic layer, the footing over half of it, 20 steps): the
    loop ran every step with the executor's bits (particles, reactions,
    the footing's history: one record per step, at the step's end), the
    reference executor agrees to 1e-12, and the footing settled v t_end
    (it once advanced per stage: 4 v t_end)."""
    method = Method(scheme="rk4", dt=0.0025)
    runs = {}
    for path in ("loop", "executor", "reference"):
        scene, footing = rk4_footing_scene()
        if path == "loop":
            result = simulate(scene, method, save_every=7)
        elif path == "executor":
            result = without_loop(monkeypatch, scene, method, save_every=7)
        else:
            result = simulate(scene, Method(scheme="rk4", dt=0.0025, backend="numpy"),
                              save_every=7)
        history = history_array(footing)
        assert history.shape[0] == result.counts["steps"] == 20, path
        assert np.allclose(history[:, 0], 0.0025 * np.arange(1, 21), rtol=1e-12)
        assert footing.settlement == pytest.approx(0.05 * 0.05, rel=1e-12)
        runs[path] = result, history
    (looped, h_loop), (stepped, h_step), (ref, h_ref) = (runs[k] for k in
                                                          ("loop", "executor", "reference"))
    assert looped.counts["compiled_loop_steps"] == 20 and stepped.path == "fast"
    assert_same(looped, stepped)
    assert np.array_equal(h_loop, h_step)
    for a, b in zip(looped.reactions, stepped.reactions):
        assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)
    for a, b in ((ref.particles.x, looped.particles.x),
                 (ref.particles.stress, looped.particles.stress), (h_ref, h_loop)):
        assert np.abs(a - b).max() <= 1e-12 * np.abs(a).max()


# ------------------------------------------------------------------ B-bar
@pytest.mark.parametrize("average", ("cell", "vertex"))
@pytest.mark.parametrize("layout", ("random", "uniform"))
def test_the_compiled_cell_average_is_bbar_averaged(layout, average):
    """kernels.bbar.average_dilatation against BBar.averaged: the same bits,
    over every particle and over a body of some of them (uniform layout:
    particles on cell boundaries too, in the cell on their right), the
    cells' and the vertices' dilatation functions."""
    grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (3, 4), 2)
    p = Particles.seed(grid, 3, RHO, layout=layout, seed=1)
    if layout == "uniform":  # a column of particles on the knot x = 1/3
        p.x[::7, 0] = 1.0 / 3.0
    material = BBar(LinearElastic(E, NU), grid, average=average)
    L = np.random.default_rng(0).normal(size=(p.n, 2, 2))
    axes = grid_record(grid)[0]
    per = 4 if material.vertices else 1
    work = (np.empty(material.functions), np.empty(material.functions),
            np.empty((p.n, per), dtype=np.int64), np.empty((p.n, per)))
    got = L.copy()
    average_dilatation(axes, np.zeros(0, dtype=np.int64), True, material.vertices, p.x, p.V,
                       got, *work)
    assert np.array_equal(got, material.averaged(p, L))
    index = np.flatnonzero(np.arange(p.n) % 3 != 1)
    got = L.copy()
    average_dilatation(axes, index, False, material.vertices, p.x, p.V, got, *work)
    assert np.array_equal(got[index], material.averaged(p.subset(index), L[index]))
    rest = np.setdiff1d(np.arange(p.n), index)
    assert np.array_equal(got[rest], L[rest])


def test_bbar_gives_the_wrapped_point_law():
    grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (2, 2), 2)
    clay = VonMises(E, NU, 2.0)
    material = BBar(clay, grid)
    assert material.cell_average and material.point_update is clay.point_update
    assert np.array_equal(material.point_parameters(2), clay.point_parameters(2))
    assert not clay.cell_average


# ------------------------------------------------------- the compiled loop
def footing_scene(rough=True, t_end=0.15):
    """A 1 x 1 von Mises layer with B-bar (sliding sides, fixed base) under
    a footing over half its width, pushed fast enough to yield it."""
    nx, ny = 4, 4
    h = 1.0 / ny
    grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0 + h), (nx, ny + 1), 2)
    particles = Particles.seed(grid, 2, RHO, region=((0.0, 1.0), (0.0, 1.0)))
    footing = Footing((0.0, 0.5), 1.0, 0.5, rough=rough, ramp=0.01)
    scene = Scene(grid, Body(particles, BBar(VonMises(E, NU, 2.0), grid)), t_end,
                  effects=[Fixed("left", 0), Fixed("right", 0), Fixed("bottom"), footing])
    return scene, footing


def history_array(footing):
    return np.array([[t, s, *r] for t, s, r in footing.history])


@pytest.mark.parametrize("rough", (True, False))
def test_a_footing_on_bbar_clay_runs_in_the_loop_with_the_executors_bits(monkeypatch, rough):
    """MUSL (the G1 scene's scheme), saved every 7 steps: the loop ran every
    step and gave the executor's bits (positions, velocities, stresses,
    plastic strain, external work, the footing's reaction and its history
    of every step); the clay yielded."""
    scene, footing = footing_scene(rough)
    method = Method(scheme="musl")
    looped = simulate(scene, method, save_every=7)
    loop_history = history_array(footing)
    stepped = without_loop(monkeypatch, scene, method, save_every=7)
    assert looped.path == "fast (compiled loop)" and stepped.path == "fast"
    assert looped.counts["compiled_loop_steps"] == looped.counts["steps"] >= 20
    assert_same(looped, stepped)
    for a, b in ((looped.particles.state, stepped.particles.state),):
        assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)
    assert looped.particles.state["plastic_strain"].max() > 0
    for a, b in zip(looped.reactions, stepped.reactions):
        assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)
    assert np.array_equal(loop_history, history_array(footing))
    assert loop_history.shape[0] == looped.counts["steps"]


def test_the_loop_and_the_executor_take_turns(monkeypatch):
    """Steps 1-3 in the loop, 4 through the executor, 5-9 in the loop, 10
    through the executor: the same bits and footing history as ten
    executor steps (the footing's clock lives in the effect between calls)."""
    def run(turns):
        scene, footing = footing_scene(True)
        state = prepare(scene, Method(scheme="musl"))
        ops = CompiledExecutor(state)
        loop = compiled_loop.StepLoop(state, ops)
        for kind, n in turns:
            if kind == "loop":
                assert loop.run(state, n) == n
            else:
                for _ in range(n):
                    state.next_step_size()
                    schemes.step_musl(ops, state)
        return state, history_array(footing)

    state_a, history_a = run([("loop", 3), ("executor", 1), ("loop", 5), ("executor", 1)])
    state_b, history_b = run([("executor", 10)])
    assert state_a.step == state_b.step == 10
    for key in ("x", "v", "stress", "V"):
        assert np.array_equal(getattr(state_a.particles, key), getattr(state_b.particles, key))
    assert np.array_equal(history_a, history_b) and history_a.shape[0] == 10


def test_the_loop_agrees_with_the_reference_executor():
    """The NumPy reference (the effects' NumPy methods, BBar.update): the
    loop's particles and footing history to 1e-12 of their scale."""
    runs = []
    for backend in ("numpy", "numba"):
        scene, footing = footing_scene(True, t_end=0.06)
        r = simulate(scene, Method(scheme="musl", backend=backend))
        runs.append((r, history_array(footing)))
    (ref, h_ref), (fast, h_fast) = runs
    assert fast.path == "fast (compiled loop)"
    for a, b in ((ref.particles.x, fast.particles.x), (ref.particles.stress, fast.particles.stress),
                 (h_ref, h_fast)):
        assert np.abs(a - b).max() <= 1e-12 * np.abs(a).max()


@pytest.mark.slow(reason="one more compiled loop variant per scheme (USL, CD with B-bar)")
@pytest.mark.parametrize("scheme", ("usl", "cd"))
def test_other_schemes_with_a_footing_give_the_executors_bits(monkeypatch, scheme):
    scene, footing = footing_scene(False)
    looped = simulate(scene, Method(scheme=scheme), save_every=7)
    history = history_array(footing)
    stepped = without_loop(monkeypatch, scene, Method(scheme=scheme), save_every=7)
    assert looped.counts["compiled_loop_steps"] == looped.counts["steps"]
    assert_same(looped, stepped)
    assert np.array_equal(history, history_array(footing))


# ------------------------------------------------------------ G1 itself
def g1_run(cells, bbar, **params):
    from skfem_mpm.benchmarks import get_benchmark

    bench = get_benchmark("strip-footing", bbar=float(bbar), **params)
    result = simulate(bench.scene(cells), Method())
    return bench, result


def test_the_strip_footing_runs_in_the_loop_with_the_executors_bits(monkeypatch):
    """G1's own scene (1 cell under the half footing, B-bar von Mises clay,
    the rough footing) to a settlement of 0.02 B: every step in the loop,
    the executor's bits on the particles, the clay's state and the
    footing's load-settlement record."""
    bench, looped = g1_run(10, True, settlement=0.02)
    loop_history = history_array(bench.footing)
    with monkeypatch.context() as m:
        m.setattr(compiled_loop, "ENABLED", False)
        bench_b, stepped = g1_run(10, True, settlement=0.02)
    assert looped.path == "fast (compiled loop)" and stepped.path == "fast"
    assert looped.counts["compiled_loop_steps"] == looped.counts["steps"] > 200
    for key in ("x", "v", "stress", "V"):
        assert np.array_equal(getattr(looped.particles, key), getattr(stepped.particles, key))
    assert np.array_equal(looped.particles.state["plastic_strain"],
                          stepped.particles.state["plastic_strain"])
    assert np.array_equal(loop_history, history_array(bench_b.footing))
    assert looped.particles.state["plastic_strain"].max() > 0


@pytest.mark.slow(reason="the G1 study: five strip-footing runs to 0.15 B (about two minutes "
                  "in the compiled loop)")
def test_g1_bearing_capacity_in_the_loop():
    """N_c = q / c_u at a settlement of 0.1 B against Prandtl's 2 + pi at 2,
    4 and 8 cells under the half footing (20, 40 and 80 cells over 5 B),
    quadratic, 2 x 2 particles per cell, with B-bar (its vertex
    projection) and, at 2 and 4 cells, without, all in the compiled loop:
    within 10% of 5.14 (measured with B-bar 4.65, 5.08 and 5.21, without
    5.06 and 5.23); with B-bar the load curve (0.005 B bins) never falls by
    more than 1% of its largest value from one bin to the next (measured
    at most 0.1%; with cell averages it fell from 4.6 to 3.0 at 8 cells,
    N_c 3.31)."""
    prandtl = 2 + np.pi
    for cells, kinds in ((20, (True, False)), (40, (True, False)), (80, (True,))):
        for bbar in kinds:
            bench, result = g1_run(cells, bbar)
            assert result.counts["compiled_loop_steps"] == result.counts["steps"]
            figures = bench.checks(result)
            assert abs(figures["bearing_capacity_factor"] / prandtl - 1) <= 0.10, (cells, bbar)
            if bbar:
                q = np.array([point[1] for point in figures["curve"]])
                assert np.diff(q).min() >= -0.01 * q.max(), cells
