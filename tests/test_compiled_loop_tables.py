"""The compiled loop's tabulated effects (skfem_mpm.solve.compiled_loop_tables):
a body force f_p = m_p b(X_p, t) and prescribed grid velocities, whose Python
functions StepLoop evaluates ahead at the steps' times, give the same bits
as the compiled executor stepping in Python: positions, velocities,
stresses, the external work (the body force's), the reactions (the
prescribed dofs'), every scheme, lumped and consistent mass, 1D and 2D;
also when the table ends before the steps do (a body force's chunk), when
the executor takes steps between calls, after removals and after a
restart from a checkpoint.
"""
import numpy as np
import pytest
from tiers import tiered

from skfem_mpm import BodyForce, Fixed, Method, Prescribed, Scene, Traction, simulate
from skfem_mpm.solve import compiled_loop
from skfem_mpm.solve.compiled import CompiledExecutor
from skfem_mpm.solve.compiled_loop_tables import ForceTable
from skfem_mpm.solve.state import prepare
from skfem_mpm.solve.stencil_system import StencilSystem

from test_compiled_loop import (_case_id, _ruled_coverage, assert_same, box_scene, check_law_case,
                                falling_block, law_scene, looped_and_stepped, without_loop)
from test_executors import scene_for


def with_effects(scene, *effects):
    return Scene(scene.grid, scene.bodies, scene.t_end, effects=list(scene.effects) + list(effects))


def looped_case(monkeypatch, case, steps=23):
    """looped_and_stepped of scene_for's scene of ``case`` (2D consistent
    mass without the fringe correction, which hands over to the executor)."""
    full = dict(case, material=case.get("material", "linear"))
    scene = scene_for(full, steps=steps)
    method = Method(scheme=case["scheme"], mass=case["mass"])
    with monkeypatch.context() as m:
        m.setattr(StencilSystem, "FRINGE_LAYERS", 0)
        looped, stepped = looped_and_stepped(monkeypatch, scene, method)
    assert looped.counts["compiled_loop_steps"] == looped.counts["steps"] == steps
    return looped, stepped


BODY_FORCE_CASES = [
    dict(scheme="musl", mass="lumped", degree=2, dim=1),
    dict(scheme="musl", mass="consistent", degree=3, dim=1),
    dict(scheme="usl", mass="lumped", degree=1, dim=1),
    dict(scheme="usl", mass="consistent", degree=2, dim=2, aligned=True),
    dict(scheme="cd", mass="lumped", degree=1, dim=2),
    dict(scheme="musl", mass="hybrid", degree=2, dim=2, aligned=True),
    dict(scheme="rk4", mass="lumped", degree=2, dim=1),
    dict(scheme="rk4", mass="consistent", degree=2, dim=2, aligned=True),
]


DEFAULT_BODY_FORCE_CASES = {  # the default tier's cases (tests/tiers.py)
    "cd-lumped-1-2",
    "musl-consistent-3-1",
    "musl-hybrid-2-2-True",
    "musl-lumped-2-1",
    "rk4-consistent-2-2-True",
    "rk4-lumped-2-1",
    "usl-consistent-2-2-True",
    "usl-lumped-1-1",
}


@pytest.mark.parametrize("case", tiered(
    "body force in the loop", BODY_FORCE_CASES, _case_id, DEFAULT_BODY_FORCE_CASES),
                         ids=_case_id)
def test_a_body_force_gives_the_executors_bits(monkeypatch, case):
    looped, _ = looped_case(monkeypatch, dict(case, effect="body-force"))
    assert looped.energies["external_work"][-1] != 0.0  # the body force's work is counted


# A body force with a reconstruction: its density rho b = f_p / V_p is
# fitted with the other fields and integrated at the rule's points (the
# executor's volume forces: CompiledExecutor._reconstructed_to_grid). Every
# reconstruction, both dimensions, lumped and a mass system; the default
# tier's spline and tls cases are test_executors' default body-force cases
# with reconstruction (the same loop variants), 1D mls with consistent MUSL
# is its one new variant.
RECONSTRUCTED_BODY_FORCE_CASES = [
    dict(reconstruction="spline", scheme="usl", mass="lumped", degree=2, dim=2,
         material="custom-compiled", ppc=2, aligned=False),
    dict(reconstruction="tls", scheme="usl", mass="lumped", degree=3, dim=2,
         material="custom-compiled", ppc=2, aligned=True),
    dict(reconstruction="mls", scheme="musl", mass="consistent", degree=2, dim=1,
         material="linear", ppc=3, aligned=False),
    dict(reconstruction="tls", scheme="musl", mass="consistent", degree=2, dim=2,
         material="linear", ppc=3, aligned=True),
    dict(reconstruction="spline", scheme="musl", mass="hybrid", degree=2, dim=1,
         material="linear", ppc=3, aligned=False),
    dict(reconstruction="mls", scheme="cd", mass="lumped", degree=2, dim=2,
         material="linear", ppc=2, aligned=False),
    dict(reconstruction="spline", scheme="rk4", mass="consistent", degree=2, dim=2,
         material="linear", ppc=3, aligned=True),
    dict(reconstruction="tls", scheme="rk4", mass="lumped", degree=3, dim=1,
         material="linear", ppc=3, aligned=False),
]
DEFAULT_RECONSTRUCTED_BODY_FORCE_CASES = {  # the default tier's cases (tests/tiers.py)
    "spline-usl-lumped-2-2-custom-compiled-2-False",
    "tls-usl-lumped-3-2-custom-compiled-2-True",
    "mls-musl-consistent-2-1-linear-3-False",
}


@pytest.mark.parametrize("case", tiered(
    "body force with reconstruction in the loop", RECONSTRUCTED_BODY_FORCE_CASES, _case_id,
    DEFAULT_RECONSTRUCTED_BODY_FORCE_CASES, paired=(), options=_ruled_coverage), ids=_case_id)
def test_a_body_force_with_reconstruction_gives_the_executors_bits(monkeypatch, case):
    scene = scene_for(dict(case, effect="body-force"), steps=23)
    method = Method(scheme=case["scheme"], mass=case["mass"],
                    reconstruction=case["reconstruction"])
    ok, why = compiled_loop.loop_applies(prepare(scene, method),
                                         CompiledExecutor(prepare(scene, method)))
    assert ok, why
    looped, stepped = looped_and_stepped(monkeypatch, scene, method)
    assert stepped.path == f"fast (reconstruction {case['reconstruction']})"
    assert looped.counts["compiled_loop_steps"] >= 18
    assert looped.energies["external_work"][-1] != 0.0  # the body force's work is counted


PRESCRIBED_CASES = [
    dict(scheme="musl", mass="lumped", degree=2, dim=1),
    dict(scheme="musl", mass="lumped", degree=2, dim=2),
    dict(scheme="usl", mass="lumped", degree=3, dim=2),
    dict(scheme="usl", mass="lumped", degree=1, dim=1),
    dict(scheme="cd", mass="lumped", degree=1, dim=1),
    dict(scheme="cd", mass="lumped", degree=2, dim=2),
    dict(scheme="rk4", mass="lumped", degree=2, dim=1),
    dict(scheme="rk4", mass="lumped", degree=1, dim=2),
    # consistent mass: the fixed columns' values on the right-hand side of the CG
    dict(scheme="musl", mass="consistent", degree=2, dim=1),
    dict(scheme="musl", mass="hybrid", degree=2, dim=2, aligned=True),
    dict(scheme="usl", mass="consistent", degree=3, dim=1),
    dict(scheme="cd", mass="consistent", degree=2, dim=2, aligned=True),
    dict(scheme="rk4", mass="consistent", degree=2, dim=1),
    dict(scheme="rk4", mass="consistent", degree=1, dim=2, aligned=True),
]


DEFAULT_PRESCRIBED_CASES = {  # the default tier's cases (tests/tiers.py)
    "cd-consistent-2-2-True",
    "cd-lumped-1-1",
    "musl-consistent-2-1",
    "musl-hybrid-2-2-True",
    "musl-lumped-2-1",
    "rk4-consistent-1-2-True",
    "rk4-lumped-2-1",
    "usl-consistent-3-1",
    "usl-lumped-1-1",
    "usl-lumped-3-2",
}


@pytest.mark.parametrize("case", tiered(
    "prescribed velocities in the loop", PRESCRIBED_CASES, _case_id, DEFAULT_PRESCRIBED_CASES),
                         ids=_case_id)
def test_prescribed_velocities_give_the_executors_bits(monkeypatch, case):
    looped, _ = looped_case(monkeypatch, dict(case, effect="prescribed"))
    key = "Prescribed('left', component=0)" if case["dim"] == 1 else \
        "Prescribed('bottom', component=0)"
    assert looped.reactions[-1][key][0] != 0.0  # the prescribed dofs push the body


@pytest.mark.parametrize("scheme", ["musl", pytest.param("rk4", marks=pytest.mark.slow(
    reason="one more run type's rk4 loop; the default tier runs musl"))])
def test_a_body_force_prescribed_velocities_and_a_traction_together(monkeypatch, scheme):
    case = dict(scheme=scheme, mass="lumped", degree=2, dim=2, material="linear",
                effect="prescribed", aligned=True)
    scene = with_effects(scene_for(case, steps=23),
                         BodyForce(lambda X, t: np.column_stack((0.1 + 0 * X[:, 0], -t * X[:, 1]))),
                         Traction("right", lambda t: (0.01 * t, -0.005)),
                         BodyForce(lambda X, t: 0.2 * X * (1 + t)))
    looped, _ = looped_and_stepped(monkeypatch, scene, Method(scheme=scheme))
    assert looped.counts["compiled_loop_steps"] == 23


@pytest.mark.parametrize("scheme,degree", [
    ("musl", 2), pytest.param("rk4", 1, marks=pytest.mark.slow(
        reason="one more 3D run type's rk4 loop; the default tier runs musl (3D rk4: "
               "test_compiled_loop)"))])
def test_a_body_force_and_prescribed_velocities_in_3d(monkeypatch, scheme, degree):
    """The same templates in 3D (lumped mass): a body force and a
    prescribed component of a side beside its fixed others."""
    scene = box_scene(scheme, degree, "none")
    grid, body = scene.grid, scene.bodies[0]
    effects = [Fixed("zmin", 0), Fixed("zmin", 1), Prescribed("zmin", 2, lambda t: 0.03 * t),
               BodyForce(lambda X, t: np.column_stack((np.cos(X[:, 2] + t), 0 * X[:, 0],
                                                       -X[:, 0] * (1 + t))))]
    scene = Scene(grid, body, scene.t_end, effects=effects)
    looped, _ = looped_and_stepped(monkeypatch, scene, Method(scheme=scheme))
    assert looped.counts["compiled_loop_steps"] == looped.counts["steps"] == 13
    assert looped.energies["external_work"][-1] != 0.0
    assert looped.reactions[-1]["Prescribed('zmin', component=2)"][2] != 0.0


def test_a_point_law_under_a_body_force(monkeypatch):
    """A neo-Hookean bar under a manufactured body force (the neo-hookean-bar
    benchmark's kind of scene), with a fixed dt."""
    case = dict(material="neo-hookean", dim=1, scheme="musl", mass="lumped", degree=2)
    scene, dt = law_scene(case)
    scene = with_effects(scene, BodyForce(lambda X, t: 0.3 * np.sin(np.pi * X) * np.cos(t)))
    looped, _ = looped_and_stepped(monkeypatch, scene, Method(scheme="musl", dt=dt))
    assert looped.counts["compiled_loop_steps"] == 23


@pytest.mark.parametrize("scheme", ["usl", "rk4"])
def test_body_force_tables_of_a_few_steps(monkeypatch, scheme):
    """A memory budget of 3 steps' forces: the loop returns at each
    table's end, and StepLoop evaluates the next (from the step reached,
    not from 0)."""
    case = dict(scheme=scheme, mass="lumped", degree=2, dim=1, material="linear",
                effect="body-force")
    scene = scene_for(case, steps=23)
    n, dim = scene.bodies[0].particles.n, 1
    columns = 3 if scheme == "rk4" else 1
    monkeypatch.setattr(ForceTable, "BYTES", 3 * columns * n * dim * 8)
    calls = []
    run = compiled_loop.StepLoop.run
    monkeypatch.setattr(compiled_loop.StepLoop, "run",
                        lambda self, state, n: calls.append(run(self, state, n)) or calls[-1])
    looped, _ = looped_and_stepped(monkeypatch, scene, Method(scheme=scheme))
    assert looped.counts["compiled_loop_steps"] == 23
    assert max(calls) == 3 and len(calls) >= 23 // 3


def test_tables_kept_while_the_executor_takes_steps_between_calls(monkeypatch):
    """A collapsing block (hybrid mass) gets tiny-mass dofs: with no room
    for the merged system (StencilSystem.MERGE_BUFFER 0) those steps stop
    the loop and the executor takes them; the loop goes on with the body
    force's table it holds (and the same bits as the executor alone)."""
    case = dict(material="mohr-coulomb-large", dim=2, scheme="musl", mass="hybrid", degree=2,
                aligned=True, shear=0.5, cohesion=0.02)
    monkeypatch.setattr(StencilSystem, "MERGE_BUFFER", 0)
    scene, dt = law_scene(case)
    loaded = with_effects(scene, BodyForce(lambda X, t: np.column_stack(
        (0.3 * X[:, 1] * np.cos(5 * t), -0.2 * X[:, 0]))))
    monkeypatch.setattr("test_compiled_loop.law_scene", lambda case, steps=23: (loaded, dt))
    looped, _ = check_law_case(monkeypatch, case)
    assert 0 < looped.counts["compiled_loop_steps"] < looped.counts["steps"]


def test_particles_leaving_under_a_body_force(monkeypatch):
    """Removed particles: the loop's arrays and tables are the old ones, so
    the executor takes the rest of the run, with the survivors' forces."""
    scene, method = falling_block("remove")
    scene = Scene(scene.grid, scene.bodies, scene.t_end,
                  effects=[BodyForce(lambda X, t: np.column_stack(
                      (0.5 * X[:, 0] * t, -9.81 + 0 * X[:, 1])))])
    looped = simulate(scene, method, save_every=10)
    stepped = without_loop(monkeypatch, scene, method, save_every=10)
    assert looped.counts["removed"] == stepped.counts["removed"] > 0
    assert 0 < looped.counts["compiled_loop_steps"] < looped.counts["steps"]
    assert np.array_equal(looped.times, stepped.times)
    for key in ("x", "v", "stress"):
        for a, b in zip(looped.history[key], stepped.history[key]):
            assert np.array_equal(a, b), key
    assert np.array_equal(looped.energies["external_work"], stepped.energies["external_work"])


@pytest.mark.parametrize("scheme", ["musl", pytest.param("rk4", marks=pytest.mark.slow(
    reason="one more run type's rk4 loop; the default tier runs musl"))])
def test_a_restart_evaluates_its_own_tables(monkeypatch, tmp_path, scheme):
    """A run stopped at step 10 (a callback: the executor steps) and
    restarted from its checkpoint: the restart's loop evaluates the body
    force and the prescribed velocities from step 10 on, and the result is
    the uninterrupted run's, with the loop and without it."""
    case = dict(scheme=scheme, mass="lumped", degree=2, dim=2, material="linear",
                effect="prescribed")
    scene = with_effects(scene_for(case, steps=23),
                         BodyForce(lambda X, t: np.column_stack((np.sin(X[:, 1] + 9 * t),
                                                                 -X[:, 0] * t))))
    method = Method(scheme=scheme)
    full = simulate(scene, method, save_every=5)
    assert full.counts["compiled_loop_steps"] == 23
    path = tmp_path / "run.npz"
    simulate(scene, method, save_every=5, checkpoint=(path, 10),
             callback=lambda step, state: step < 10)
    resumed = simulate(scene, method, save_every=5, restart=path)
    assert resumed.counts["compiled_loop_steps"] == 13
    stepped = without_loop(monkeypatch, scene, method, save_every=5, restart=path)
    for other in (resumed, stepped):
        assert_same(full, other)
        for a, b in zip(full.reactions, other.reactions):
            for key in a:
                assert np.array_equal(a[key], b[key]), key


def test_what_the_tables_leave_to_the_executor():
    case = dict(scheme="musl", mass="lumped", degree=2, dim=1, material="linear",
                effect="body-force")
    scene = scene_for(case, steps=5)
    # a body force with a reconstruction runs in the loop too (its density
    # fitted with the other fields: test_compiled_loop's body-force cases)
    state = prepare(scene, Method(scheme="musl", reconstruction="tls"))
    assert compiled_loop.loop_applies(state, CompiledExecutor(state)) == (True, "")
    state = prepare(scene, Method(scheme="musl"))
    assert compiled_loop.loop_applies(state, CompiledExecutor(state)) == (True, "")
    # a traction of (x, t) is not of the reference configuration
    scene = with_effects(scene, Traction("right", lambda x, t: 0.01 * t))
    state = prepare(scene, Method(scheme="musl"))
    ok, why = compiled_loop.loop_applies(state, CompiledExecutor(state))
    assert not ok and "reference_only" in why


def test_a_failing_body_force_raises_as_without_the_loop(monkeypatch):
    """b raises at t >= 10 dt: the loop's table ends before that step, and
    the executor takes it and raises the same error."""
    case = dict(scheme="musl", mass="lumped", degree=2, dim=1, material="linear",
                effect="none")
    scene = scene_for(case, steps=23)
    dt = prepare(scene, Method(scheme="musl")).dt

    def b(X, t):
        if t >= 9.5 * dt:
            raise ValueError("b: no force after t = 9.5 dt")
        return 0.1 * X

    scene = with_effects(scene, BodyForce(b))
    with pytest.raises(ValueError, match="no force after") as looped:
        simulate(scene, Method(scheme="musl"), save_every=5)
    with pytest.raises(ValueError, match="no force after") as stepped:
        without_loop(monkeypatch, scene, Method(scheme="musl"), save_every=5)
    assert str(looped.value) == str(stepped.value)
