"""Grid modifiers (Damping, Wall) on the compiled paths.

The compiled step loop runs scenes with local damping and frictional walls
(skfem_mpm.solve.compiled_loop_modifiers) and gives the compiled executor's
bits (every recorded quantity and the reactions, the walls' included); the
executor applies the same compiled rules (skfem_mpm.kernels.grid_modifiers),
which agree with the effects' NumPy methods (the reference executor's).
"""
import json
import subprocess
import sys

import numpy as np
import pytest
from tiers import tiered

from skfem_mpm import (Body, Damping, Fixed, Footing, Gravity, LinearElastic, Method,
                       Particles, Prescribed, Scene, SplineGrid, Wall, simulate)
from skfem_mpm.effects import Effect, GridModifier
from skfem_mpm.kernels import grid_modifiers, serial
from skfem_mpm.solve import compiled_loop
from skfem_mpm.solve.compiled import CompiledExecutor
from skfem_mpm.solve.state import prepare

from test_compiled_loop import box_scene, looped_and_stepped, without_loop
from test_executors import scene_for
from test_warmup import WATCH_COMPILES

# effects of each case: walls on different sides, with and without
# friction, alone or with damping (and a Fixed side or prescribed velocities
# where noted)
EFFECTS = {
    "walls+damping": lambda dim: ([Wall("left"), Damping(0.1)] if dim == 1 else
                                  [Wall("bottom", friction=0.3), Wall("left"), Damping(0.1)]),
    "walls": lambda dim: ([Wall("left", friction=0.4)] if dim == 1 else
                          [Wall("left", friction=0.2), Wall("bottom", friction=0.5)]),
    "damping+fixed": lambda dim: [Fixed("left" if dim == 1 else "bottom"), Damping(0.2)],
    "prescribed+damping": lambda dim: (
        [Prescribed("left", 0, lambda t: 0.02 * t), Damping(0.1)] if dim == 1 else
        [Fixed("bottom", 1), Prescribed("bottom", 0, lambda t: 0.02 * t),
         Wall("left", friction=0.3), Damping(0.1)]),
    "fixed+wall": lambda dim: ([Fixed("left"), Wall("left", friction=0.2)] if dim == 1 else
                               [Fixed("left", 0), Wall("bottom", friction=0.3), Damping(0.05)]),
}

# (scheme, mass, degree, dim, effects): every scheme with each mass and
# dimension (rk4: lumped and consistent), each effect set in 1D and 2D
CASES = [("musl", "lumped", 2, 2, "walls+damping"), ("usl", "lumped", 1, 1, "walls+damping"),
         ("cd", "lumped", 3, 2, "walls"), ("musl", "lumped", 2, 1, "damping+fixed"),
         ("usl", "consistent", 2, 2, "fixed+wall"), ("musl", "consistent", 3, 1, "walls"),
         ("cd", "consistent", 2, 1, "fixed+wall"), ("musl", "consistent", 2, 2, "damping+fixed"),
         ("musl", "hybrid", 2, 2, "walls+damping"), ("usl", "lumped", 2, 2, "fixed+wall"),
         ("cd", "lumped", 1, 1, "damping+fixed"), ("rk4", "lumped", 2, 1, "walls+damping"),
         ("rk4", "consistent", 2, 2, "fixed+wall"), ("musl", "lumped", 2, 2, "prescribed+damping"),
         ("usl", "consistent", 2, 1, "prescribed+damping"),
         ("rk4", "lumped", 1, 2, "prescribed+damping")]


def modified_scene(scheme, mass, degree, dim, effects, steps=23):
    """The executors' test scene (a body resting on the grid's left / bottom
    side, moving) under gravity toward that side, with ``effects``."""
    case = dict(scheme=scheme, mass=mass, degree=degree, dim=dim, material="linear",
                effect="gravity", aligned=True)
    scene = scene_for(case, steps=steps)
    g = -2.0 if dim == 1 else (0.0, -2.0)
    return Scene(scene.grid, scene.bodies, scene.t_end,
                 effects=[Gravity(g)] + EFFECTS[effects](dim))


def _id(case):
    return "-".join(map(str, case))


DEFAULT_CASES = {  # the default tier's cases (tests/tiers.py)
    "cd-consistent-2-1-fixed+wall",
    "cd-lumped-1-1-damping+fixed",
    "cd-lumped-3-2-walls",
    "musl-consistent-3-1-walls",
    "musl-hybrid-2-2-walls+damping",
    "musl-lumped-2-1-damping+fixed",
    "musl-lumped-2-2-walls+damping",
    "rk4-consistent-2-2-fixed+wall",
    "rk4-lumped-2-1-walls+damping",
    "usl-consistent-2-1-prescribed+damping",
    "usl-lumped-2-2-fixed+wall",
}


@pytest.mark.parametrize("case", tiered(
    "grid modifiers in the loop", CASES, _id, DEFAULT_CASES,
    options=lambda c: dict(zip(("scheme", "mass", "degree", "dim", "effects"), c))), ids=_id)
def test_modifiers_give_the_executors_bits(monkeypatch, case):
    scheme, mass, degree, dim, effects = case
    scene = modified_scene(*case)
    looped, stepped = looped_and_stepped(monkeypatch, scene, Method(scheme=scheme, mass=mass))
    assert looped.counts["compiled_loop_steps"] >= 20
    walls = [repr(e) for e in scene.effects if isinstance(e, Wall)]
    for key in walls:  # every wall touched the body: its reaction is recorded
        assert np.abs(looped.reactions[-1][key]).max() > 0.0, key
    assert "effects" in looped.phase_table()


@pytest.mark.parametrize("scheme", ("musl", pytest.param("usl", marks=pytest.mark.slow(
    reason="one more 3D run type's loop; the default tier runs musl"))))
def test_modifiers_in_3d_give_the_executors_bits(monkeypatch, scheme):
    """3D lumped: walls on two sides (with and without friction) and a damping."""
    box = box_scene(scheme, 2, "gravity")
    scene = Scene(box.grid, box.bodies, box.t_end,
                  effects=[Gravity((0.0, 0.0, -2.0)), Wall("zmin", friction=0.3), Wall("xmin"),
                           Damping(0.1)])
    looped, _ = looped_and_stepped(monkeypatch, scene, Method(scheme=scheme))
    assert looped.counts["compiled_loop_steps"] == looped.counts["steps"] == 13
    for key in ("Wall('zmin', friction=0.3)", "Wall('xmin', friction=0)"):
        assert np.abs(looped.reactions[-1][key]).max() > 0.0, key


@pytest.mark.slow(
    reason="parallel kernels in the loop run in the default tier with lumped linear "
           "elasticity (test_parallel_kernels_give_the_same_bits); this one compiles another "
           "parallel run type")
def test_modifiers_with_parallel_kernels(monkeypatch):
    monkeypatch.setattr(serial, "SERIAL_BELOW", 1)
    scene = modified_scene("musl", "lumped", 2, 2, "walls+damping")
    looped, _ = looped_and_stepped(monkeypatch, scene, Method(scheme="musl"))
    assert looped.counts["compiled_loop_steps"] >= 20


def test_the_walls_reactions_at_every_step(monkeypatch):
    """Saved every step (one step per call of the loop): the walls'
    reactions the loop hands back after each call are the executor's."""
    scene = modified_scene("usl", "lumped", 2, 2, "walls")
    method = Method(scheme="usl")
    looped = simulate(scene, method, save_every=1)
    stepped = without_loop(monkeypatch, scene, method, save_every=1)
    assert looped.counts["compiled_loop_steps"] == 23
    assert len(looped.reactions) == len(stepped.reactions) == 24
    for a, b in zip(looped.reactions[1:], stepped.reactions[1:]):
        assert a.keys() == b.keys() and len(a) == 2
        for key in a:
            assert np.array_equal(a[key], b[key]), key


class ScaledForce(Effect, GridModifier):
    """A user's grid modifier in NumPy only (no compiled rule)."""

    def __repr__(self):
        return "ScaledForce()"

    def force_modifiers(self):
        return [self]

    def modify_force(self, force, velocity, mass, dt):
        return 0.5 * force


def test_what_the_loop_leaves_to_the_executor():
    scene = modified_scene("musl", "lumped", 2, 2, "walls+damping", steps=5)
    own = ScaledForce()
    with_own = Scene(scene.grid, scene.bodies, scene.t_end, effects=list(scene.effects) + [own])
    state = prepare(with_own, Method(scheme="musl"))
    assert compiled_loop.loop_applies(state, CompiledExecutor(state)) == \
        (False, "a grid modifier without a compiled rule (ScaledForce())")
    footing = Footing((0.0, 0.3), 0.6, 0.1)  # a footing has its rule
    for scheme, effects in (("musl", [footing]), ("rk4", [])):
        state = prepare(Scene(scene.grid, scene.bodies, scene.t_end,
                              effects=list(scene.effects) + effects), Method(scheme=scheme))
        assert compiled_loop.loop_applies(state, CompiledExecutor(state)) == (True, "")


def test_the_executor_agrees_with_the_reference(monkeypatch):
    """The compiled executor's rules (kernels) against the effects' NumPy
    methods (the reference executor), every scheme the loop runs."""
    for scheme in ("musl", "usl", "cd", "rk4"):
        scene = modified_scene(scheme, "lumped", 2, 2, "walls+damping", steps=20)
        ref = simulate(scene, Method(scheme=scheme, backend="numpy"), save_every=5)
        fast = without_loop(monkeypatch, scene, Method(scheme=scheme), save_every=5)
        assert fast.path == "fast"
        for key in ("x", "v", "stress"):
            a, b = ref.history[key], fast.history[key]
            assert np.abs(a - b).max() <= 1e-12 * np.abs(a).max(), (scheme, key)
        for a, b in zip(ref.reactions, fast.reactions):
            assert a.keys() == b.keys()
            for key in a:
                assert np.allclose(a[key], b[key], rtol=1e-10, atol=1e-12), (scheme, key)


def _random_grid_state(grid, rng):
    nd, dim = grid.ndofs, grid.dim
    force = rng.normal(size=(nd, dim))
    velocity = rng.normal(size=(nd, dim))
    velocity[rng.random((nd, dim)) < 0.1] = 0.0  # sign(0) = 0
    mass = rng.random(nd) + 0.1
    mass[rng.random(nd) < 0.2] = 0.0  # empty nodes
    return force, velocity, mass


@pytest.mark.parametrize("dim", (1, 2, 3))
def test_the_rules_are_the_effects_numpy_methods(dim):
    """kernels.grid_modifiers against Damping / Wall's modify_force and
    modify_velocity on random grid states (contact, separation, sliding,
    sticking and empty nodes all occur), several walls and a damping in
    order, each wall's reaction: equal to round-off."""
    rng = np.random.default_rng(dim)
    grid = {1: lambda: SplineGrid.line(0.0, 1.0, 5, 2),
            2: lambda: SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (4, 3), 2),
            3: lambda: SplineGrid.box((0.0, 1.0), (0.0, 1.0), (0.0, 1.0), (2, 3, 2), 1)}[dim]()
    sides = {1: ("left", "right"), 2: ("bottom", "left", "top"),
             3: ("zmin", "xmax", "ymin")}[dim]
    modifiers = [Wall(side, friction=mu) for side, mu in zip(sides, (0.3, 0.0, 2.0))]
    modifiers.insert(1, Damping(0.3))
    for m in modifiers:
        m.check(grid)
    packed = grid_modifiers.pack_rules([m.grid_rule(grid) for m in modifiers], dim)
    contact = False
    for trial in range(20):
        force, velocity, mass = _random_grid_state(grid, rng)
        dt = 0.05
        expected = force
        for m in modifiers:
            expected = m.modify_force(expected, velocity, mass, dt)
        got = force.copy()
        grid_modifiers.modify_forces(*packed[:4], got, velocity, mass, dt, 0.0, 0.0,
                                     *packed[4:])
        assert np.allclose(got, expected, rtol=1e-14, atol=1e-14 * np.abs(force).max())
        walls = [m for m in modifiers if isinstance(m, Wall)]
        rows = [r for r, m in enumerate(modifiers) if isinstance(m, Wall)]
        for wall, row in zip(walls, rows):
            assert np.allclose(packed[4][row], wall.reaction, rtol=1e-13, atol=1e-13)
        expected_v = velocity
        for m in walls:
            expected_v = m.modify_velocity(expected_v, mass)
        got_v = velocity.copy()
        grid_modifiers.modify_velocities(*packed[:4], got_v, mass, *packed[5:])
        assert np.allclose(got_v, expected_v, rtol=1e-14, atol=1e-15)
        contact |= not np.array_equal(got_v, velocity)
    assert contact


_PLAIN_RUN = r"""
import json, sys
sys.path.insert(0, "tests")
from skfem_mpm import Method, simulate
from skfem_mpm.kernels import grid_modifiers
from test_executors import scene_for
scene = scene_for(dict(scheme="musl", mass="lumped", degree=2, dim=2, material="linear",
                       effect="gravity", aligned=True), steps=5)
r = simulate(scene, Method(scheme="musl"))
print(json.dumps({"path": r.path,
                  "rules": len(grid_modifiers.modify_forces.overloads)
                  + len(grid_modifiers.modify_velocities.overloads)}))
"""


def test_a_run_without_modifiers_compiles_none_of_them():
    out = subprocess.run([sys.executable, "-c", _PLAIN_RUN], capture_output=True, text=True,
                         timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report == {"path": "fast (compiled loop)", "rules": 0}


_EXECUTOR_RUN = WATCH_COMPILES + r"""
sys.path.insert(0, "tests")
from skfem_mpm.solve import compiled_loop
from test_compiled_loop_modifiers import modified_scene
compiled_loop.ENABLED = False
scheme = sys.argv[1]
r = simulate(modified_scene(scheme, "lumped", 2, 2, "walls+damping"), Method(scheme=scheme))
late = sorted(k for k, v in compiled().items() if v > after_warm_up.get(k, 0))
print(json.dumps({"path": r.path, "late": late,
                  "rules": after_warm_up.get("skfem_mpm.kernels.grid_modifiers.modify_forces")}))
"""


def test_the_executors_rules_compile_in_the_warm_up():
    """Without the loop, the executor's rule kernels compile in the warm-up,
    not inside the timed steps (MUSL: the velocity rules too)."""
    out = subprocess.run([sys.executable, "-c", _EXECUTOR_RUN, "musl"], capture_output=True,
                         text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report == {"path": "fast", "late": [], "rules": 1}
