"""Per-particle material state (``particles.state[name]``), end to end.

A stateful test material (linear elasticity with every stress component
capped, in 1D and 2D) declares fields of several shapes: a plastic strain
tensor (dim, dim), its accumulated magnitude (scalar), a step counter
(scalar), a marker (2,) its law never touches (a user may seed it), and in
2D the plane-strain sigma_zz. Its NumPy update and its compiled point law
must give the same state on both executors; the state must follow particle
removal, the joining of bodies, checkpoints and restarts, and appear in the
history and the ParaView output; bad shapes raise.
"""
import numpy as np
import pytest

from skfem_mpm import (Body, Fixed, LinearElastic, Method, NeoHookean, Particles, Scene,
                       SplineGrid, fem, simulate)
from skfem_mpm.materials import Material, point_update, state_layout
from skfem_mpm.materials.laws import linear_elastic_law
from skfem_mpm.solve.state import prepare

CAP = 0.02


class CappedPlastic(Material):
    """Linear elasticity (hypoelastic) with every stress component clamped
    to +-cap; the clamped part over E accumulates as a plastic strain."""

    def __init__(self, E, nu, cap=CAP):
        self.inner = LinearElastic(E, nu)
        self.E, self.cap = float(E), float(cap)

    def state_fields(self, dim):
        fields = {"plastic": ((dim, dim), 0.0), "eq_plastic": ((), 0.0), "steps": ((), 0.0),
                  "marker": ((2,), (1.0, -1.0))}
        if dim == 2:
            fields["sigma_zz"] = ((), 0.0)
        return fields

    def update(self, particles, L, dt):
        trial, V, F = self.inner.update(particles, L, dt)
        stress = np.clip(trial, -self.cap, self.cap)
        excess = (trial - stress) / self.E
        s = particles.state
        new = {"plastic": s["plastic"] + excess,
               "eq_plastic": s["eq_plastic"] + np.abs(excess).sum(axis=(1, 2)),
               "steps": s["steps"] + 1.0}  # the marker is left out: it keeps its values
        if particles.dim == 2:
            new["sigma_zz"] = s["sigma_zz"] + self.inner.lam * dt * (L[:, 0, 0] + L[:, 1, 1])
        return stress, V, F, new

    def wave_speed(self, particles):
        return self.inner.wave_speed(particles)

    def strain_energy(self, particles):
        return self.inner.strain_energy(particles)


@point_update
def capped_plastic_law(params, L, F, dt, stress, state, stress_out, state_out):
    """CappedPlastic for one particle; params: the linear law's, then E,
    cap; state: plastic (dim*dim), eq_plastic, steps, marker (2),
    sigma_zz (2D)."""
    dim = L.shape[0]
    n = len(params)
    linear_elastic_law(params[:n - 2], L, F, dt, stress, state, stress_out, state_out)
    E, cap = params[n - 2], params[n - 1]
    total = 0.0
    for i in range(dim):
        for j in range(dim):
            trial = stress_out[i, j]
            s = min(max(trial, -cap), cap)
            stress_out[i, j] = s
            excess = (trial - s) / E
            state_out[i * dim + j] = state[i * dim + j] + excess
            total += abs(excess)
    k = dim * dim
    state_out[k] = state[k] + total
    state_out[k + 1] = state[k + 1] + 1.0
    if dim == 2:
        state_out[k + 4] = state[k + 4] + params[0] * dt * (L[0, 0] + L[1, 1])


class CappedPlasticCompiled(CappedPlastic):
    point_update = capped_plastic_law

    def point_parameters(self, dim):
        return np.append(self.inner.point_parameters(dim), (self.E, self.cap))


def bar_scene(material, dim, steps=25, region=None, velocity=None, effects=None, marker=False,
              **method):
    if dim == 1:
        grid = SplineGrid.line(0.0, 1.0, 8, 2)
        region = ((0.0, 0.75),) if region is None else region
        velocity = (lambda X: 0.3 * np.sin(np.pi * X)) if velocity is None else velocity
    else:
        grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (5, 4), 2)
        region = ((0.0, 0.7), (0.0, 0.6)) if region is None else region
        velocity = (lambda X: np.column_stack((0.3 * X[:, 1], -0.2 * X[:, 0]))) \
            if velocity is None else velocity
    particles = Particles.seed(grid, 2, 1.0, region=region, velocity=velocity)
    if marker:  # a user-supplied field: each particle's own number
        k = np.arange(particles.n, dtype=float)
        particles = particles.replaced(state={"marker": np.column_stack((k, -k))})
    if effects is None:
        effects = [Fixed("left" if dim == 1 else "bottom")]
    scene = Scene(grid, Body(particles, material), 1.0, effects=effects)
    dt = prepare(scene, Method(**method)).dt
    return Scene(grid, Body(particles, material), steps * dt, effects=effects)


def names(dim):
    return ["plastic", "eq_plastic", "steps", "marker"] + (["sigma_zz"] if dim == 2 else [])


# ---------------------------------------------------------------- executors
@pytest.mark.parametrize("dim", [1, 2])
@pytest.mark.parametrize("scheme, mass", [("musl", "lumped"), ("usl", "consistent"),
                                          ("cd", "lumped")])
def test_both_executors_give_the_same_state(dim, scheme, mass):
    scene = bar_scene(CappedPlasticCompiled(10.0, 0.3), dim, scheme=scheme, mass=mass)
    method = dict(scheme=scheme, mass=mass, mass_solver="direct")
    ref = simulate(scene, Method(backend="numpy", **method), save_every=5)
    fast = simulate(scene, Method(backend="numba", **method), save_every=5)
    numpy_law = simulate(scene.__class__(scene.grid, Body(scene.bodies[0].particles,
                                                          CappedPlastic(10.0, 0.3)),
                                         scene.t_end, effects=scene.effects),
                         Method(backend="numba", **method), save_every=5)
    assert fast.path.startswith("fast") and ref.path.startswith("reference")
    steps = ref.counts["steps"]
    assert sorted(ref.particles.state) == sorted(fast.particles.state) == sorted(names(dim))
    for name in names(dim):
        a = ref.history[name]
        assert a.shape == (len(ref.times), ref.particles.n) + ref.particles.state[name].shape[1:]
        scale = max(np.abs(a).max(), 1e-300)
        for other in (fast, numpy_law):
            b = other.history[name]
            assert np.abs(a - b).max() <= 1e-12 * scale, (name, np.abs(a - b).max() / scale)
    assert np.all(fast.particles.state["steps"] == steps)
    assert np.all(fast.particles.state["marker"] == (1.0, -1.0))
    assert fast.particles.state["eq_plastic"].max() > 1e-3  # the cap is reached
    assert np.abs(ref.history["stress"] - fast.history["stress"]).max() <= \
        1e-12 * np.abs(ref.history["stress"]).max()


def test_a_material_without_state_keeps_none():
    scene = bar_scene(LinearElastic(10.0, 0.3), 2)
    assert scene.particles().state == {}
    r = simulate(scene, Method(backend="numba"), save_every=5)
    assert r.particles.state == {} and set(r.history) == {"X", "x", "u", "v", "stress", "index",
                                                          "m", "V", "body"}


# ------------------------------------------------------------------ removal
@pytest.mark.parametrize("backend", ["numpy", "numba"])
def test_state_follows_particle_removal(backend):
    """Particles fly out of the right end and are removed: the survivors
    keep their own state (the user-seeded marker is each one's number)."""
    scene = bar_scene(CappedPlasticCompiled(10.0, 0.3), 1, steps=60, region=((0.3, 0.9),),
                      velocity=lambda X: 0.3 + 0.2 * X, effects=[], marker=True,
                      on_exit="remove")
    r = simulate(scene, Method(backend=backend, on_exit="remove"), save_every=10)
    assert r.counts["removed"] > 0
    for k in range(len(r.times)):
        index = r.history["index"][k]
        assert np.array_equal(r.history["marker"][k], np.column_stack((index, -index)))
        assert r.history["steps"][k].shape == index.shape
    final = r.particles
    assert final.state["marker"].shape == (final.n, 2)
    assert np.array_equal(final.state["marker"][:, 0], r.history["index"][-1])
    assert np.all(final.state["steps"] == r.counts["steps"])
    if backend == "numba":
        ref = simulate(scene, Method(backend="numpy", on_exit="remove"), save_every=10)
        for name in names(1):
            assert np.abs(ref.particles.state[name] - final.state[name]).max() <= \
                1e-12 * max(np.abs(ref.particles.state[name]).max(), 1e-300)


def test_subset_copy_replaced_keep_the_state_consistent():
    p = Particles(np.linspace(0.1, 0.9, 5), np.ones(5), np.ones(5),
                  state={"a": np.arange(5.0), "b": np.arange(10.0).reshape(5, 2)})
    q = p.subset(np.array([True, False, True, False, True]))
    assert np.array_equal(q.state["a"], [0.0, 2.0, 4.0])
    assert np.array_equal(q.state["b"], [[0, 1], [4, 5], [8, 9]])
    assert np.array_equal(p.subset(slice(1, 3)).state["b"], [[2, 3], [4, 5]])
    c = p.copy()
    c.state["a"][0] = 99.0
    assert p.state["a"][0] == 0.0
    r = p.replaced(x=p.x + 1)
    r.state["c"] = np.zeros(5)  # the replaced object has its own dict
    assert "c" not in p.state and r.state["a"] is p.state["a"]
    assert p.replaced(state={"z": np.ones(5)}).state.keys() == {"z"}


# ----------------------------------------------------------- concatenation
def test_concatenate_takes_the_union_of_the_fields():
    a = Particles([0.1, 0.2], np.ones(2), np.ones(2), state={"ep": [1.0, 2.0]})
    b = Particles([0.3], np.ones(1), np.ones(1), state={"back": [[5.0, 6.0]]})
    c = Particles.concatenate([a, b], fill={"back": (-1.0, -2.0)})
    assert np.array_equal(c.state["ep"], [1.0, 2.0, 0.0])  # 0 when fill does not name it
    assert np.array_equal(c.state["back"], [[-1, -2], [-1, -2], [5, 6]])
    bad = Particles([0.4], np.ones(1), np.ones(1), state={"ep": [[1.0, 2.0]]})
    with pytest.raises(ValueError, match=r"state\['ep'\] has per-particle shape \(\) in one "
                                         r"part and \(2,\) in part 1"):
        Particles.concatenate([a, bad])


@pytest.mark.parametrize("backend", ["numpy", "numba"])
def test_bodies_with_different_materials_join_their_state(backend):
    """Body 0 declares the fields (a user seeds its marker), body 1 is
    linear elastic (no state): it gets each field's declared initial value,
    its rows never change, and both executors agree."""
    grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (5, 4), 2)
    velocity = lambda X: np.column_stack((0.3 * X[:, 1], -0.2 * X[:, 0]))  # noqa: E731
    left = Particles.seed(grid, 2, 1.0, region=((0.0, 0.4), (0.0, 0.6)), velocity=velocity)
    right = Particles.seed(grid, 2, 2.0, region=((0.4, 0.7), (0.0, 0.6)), velocity=velocity)
    marker = np.column_stack((np.arange(left.n), -np.arange(left.n))).astype(float)
    left = left.replaced(state={"marker": marker})
    bodies = [Body(left, CappedPlasticCompiled(10.0, 0.3)), Body(right, LinearElastic(12.0, 0.2))]
    scene = Scene(grid, bodies, 1.0, effects=[Fixed("bottom")])
    dt = prepare(scene, Method()).dt
    scene = Scene(grid, bodies, 20 * dt, effects=[Fixed("bottom")])
    joined = scene.particles()
    assert sorted(joined.state) == sorted(names(2))
    assert np.array_equal(joined.state["marker"][:left.n], marker)  # the user's values kept
    assert np.all(joined.state["marker"][left.n:] == (1.0, -1.0))  # the declared initial value
    r = simulate(scene, Method(backend=backend), save_every=5)
    body = r.particles.body
    assert np.all(r.particles.state["steps"][body == 0] == r.counts["steps"])
    assert np.all(r.particles.state["steps"][body == 1] == 0.0)
    assert np.array_equal(r.particles.state["marker"][body == 0], marker)
    assert r.particles.state["eq_plastic"][body == 0].max() > 0
    if backend == "numba":
        assert r.path.startswith("fast")
        ref = simulate(scene, Method(backend="numpy"), save_every=5)
        for name in names(2):
            a, b = ref.history[name], r.history[name]
            assert np.abs(a - b).max() <= 1e-12 * max(np.abs(a).max(), 1e-300), name


def test_two_stateful_materials_sharing_a_field_on_the_compiled_executor():
    grid = SplineGrid.line(0.0, 1.0, 8, 2)
    velocity = lambda X: 0.3 * np.sin(np.pi * X)  # noqa: E731
    a = Particles.seed(grid, 2, 1.0, region=((0.0, 0.4),), velocity=velocity)
    b = Particles.seed(grid, 2, 1.0, region=((0.4, 0.8),), velocity=velocity)
    bodies = [Body(a, CappedPlasticCompiled(10.0, 0.0)),
              Body(b, CappedPlasticCompiled(20.0, 0.0, cap=0.01))]
    scene = Scene(grid, bodies, 1.0, effects=[Fixed("left")])
    scene = Scene(grid, bodies, 30 * prepare(scene, Method()).dt, effects=[Fixed("left")])
    ref = simulate(scene, Method(backend="numpy"), save_every=10)
    fast = simulate(scene, Method(backend="numba"), save_every=10)
    assert fast.path.startswith("fast")
    for name in names(1):
        x, y = ref.history[name], fast.history[name]
        assert np.abs(x - y).max() <= 1e-12 * max(np.abs(x).max(), 1e-300), name
    assert np.all(fast.particles.state["steps"] == fast.counts["steps"])


# ------------------------------------------------------- checkpoint/restart
@pytest.mark.parametrize("backend, dim", [("numba", 2), ("numpy", 1), ("numba", 1)])
def test_restart_continues_the_state_bit_for_bit(tmp_path, backend, dim):
    scene = bar_scene(CappedPlasticCompiled(10.0, 0.3), dim, steps=30, marker=True)
    method = Method(backend=backend)
    full = simulate(scene, method, save_every=7)
    path = tmp_path / "run.npz"

    def interrupt(step, state):
        if step == 20:
            raise KeyboardInterrupt("stop at 20")

    with pytest.raises(KeyboardInterrupt):
        simulate(scene, method, save_every=7, checkpoint=(path, 10), callback=interrupt)
    resumed = simulate(scene, method, save_every=7, restart=path)
    for name in names(dim):
        assert np.array_equal(resumed.particles.state[name], full.particles.state[name]), name
        assert np.array_equal(resumed.history[name], full.history[name]), name
    assert np.array_equal(resumed.particles.stress, full.particles.stress)
    assert np.array_equal(resumed.times, full.times)


def test_restart_rejects_a_checkpoint_without_the_declared_state(tmp_path):
    path = tmp_path / "run.npz"
    plain = bar_scene(LinearElastic(10.0, 0.3), 1, steps=12)
    simulate(plain, Method(), checkpoint=(path, 5))
    stateful = bar_scene(CappedPlasticCompiled(10.0, 0.3), 1, steps=12)
    with pytest.raises(ValueError, match=r"different scene or method: body 0 material"):
        simulate(stateful, Method(), restart=path)


# ------------------------------------------------------ history and output
def test_state_is_in_the_history_and_the_paraview_output(tmp_path):
    import meshio

    scene = bar_scene(CappedPlasticCompiled(10.0, 0.3), 2, steps=20)
    r = simulate(scene, Method(), save_every=10)
    assert r.history["steps"].shape == (3, r.particles.n)
    assert np.array_equal(r.history["steps"][:, 0], [0.0, 10.0, 20.0])
    assert r.history["plastic"].shape == (3, r.particles.n, 2, 2)
    assert np.array_equal(r.history["plastic"][-1], r.particles.state["plastic"])
    pvd = r.save(tmp_path / "out")
    assert pvd.exists()
    last = meshio.read(tmp_path / "out" / "particles_0002.vtu")
    data = last.point_data
    assert np.array_equal(data["steps"], r.particles.state["steps"])
    assert np.array_equal(data["sigma_zz"], r.particles.state["sigma_zz"])
    assert np.array_equal(data["plastic"], r.particles.state["plastic"].reshape(-1, 4))
    assert np.array_equal(data["marker"], r.particles.state["marker"])
    assert "stress" in data and "displacement" in data


# ---------------------------------------------------------------------- fem
def test_fem_carries_the_state_at_gauss_points_and_particles():
    grid = SplineGrid.line(0.0, 1.0, 8, 2)
    particles = Particles.seed(grid, 2, 1.0, velocity=lambda X: 0.03 * np.sin(np.pi * X))
    scene = Scene(grid, Body(particles, CappedPlastic(10.0, 0.0)), 1.0,
                  effects=[Fixed("left"), Fixed("right")])
    scene = Scene(grid, scene.bodies, 30 * prepare(scene, Method()).dt, effects=scene.effects)
    r = fem(scene, Method(), save_every=10)
    mpm = simulate(scene, Method(), save_every=10)
    steps = r.counts["steps"]
    assert np.all(r.particles.state["steps"] == steps)
    assert r.history["eq_plastic"].shape == (len(r.times), particles.n)
    assert np.abs(r.history["stress"]).max() <= CAP * (1 + 1e-14)
    ep, ep_mpm = r.particles.state["eq_plastic"], mpm.particles.state["eq_plastic"]
    assert ep.max() > 1e-2 and ep[7] == ep[8] == 0.0  # the ends yield, the middle does not
    assert np.abs(ep - ep[::-1]).max() <= 1e-12 * ep.max()  # the bar is symmetric
    assert abs(ep.max() - ep_mpm.max()) <= 0.2 * ep_mpm.max()  # the same flow, two methods


def test_fem_refuses_finite_strain_with_state():
    class StatefulNeoHookean(NeoHookean):
        def state_fields(self, dim):
            return {"damage": ((), 0.0)}

    grid = SplineGrid.line(0.0, 1.0, 4, 2)
    particles = Particles.seed(grid, 2, 1.0)
    scene = Scene(grid, Body(particles, StatefulNeoHookean(10.0)), 0.1)
    with pytest.raises(ValueError, match="StatefulNeoHookean declares"):
        fem(scene)


# -------------------------------------------------------------- bad input
def test_bad_state_shapes_raise():
    x = np.linspace(0.1, 0.9, 4)
    with pytest.raises(ValueError, match=r"state\['ep'\] must have shape \(n, \.\.\.\) with one "
                                         r"row per particle \(n = 4\), got \(3,\)"):
        Particles(x, np.ones(4), np.ones(4), state={"ep": np.zeros(3)})
    with pytest.raises(ValueError, match=r"state\['ep'\] must be finite"):
        Particles(x, np.ones(4), np.ones(4), state={"ep": [0.0, np.nan, 0.0, 0.0]})
    with pytest.raises(ValueError, match="'stress' cannot name a state field"):
        Particles(x, np.ones(4), np.ones(4), state={"stress": np.zeros(4)})
    with pytest.raises(ValueError, match="must be a Python identifier"):
        Particles(x, np.ones(4), np.ones(4), state={"plastic strain": np.zeros(4)})
    p = Particles(x, np.ones(4), np.ones(4), state={"ep": np.zeros(4)})
    p.state["ep"] = np.zeros((4, 2, 2))[:3]
    with pytest.raises(ValueError, match=r"state\['ep'\]"):
        p.validate()
    # declared shapes: a user's field must match what the material declares
    grid = SplineGrid.line(0.0, 1.0, 4, 2)
    seeded = Particles.seed(grid, 2, 1.0)
    wrong = seeded.replaced(state={"plastic": np.zeros(seeded.n)})
    with pytest.raises(ValueError, match=r"particles.state\['plastic'\] has shape \(8,\), but "
                                         r"CappedPlastic declares 'plastic' with shape \(1, 1\) "
                                         r"per particle: expected \(8, 1, 1\)"):
        Body(wrong, CappedPlastic(10.0, 0.0))
    body = Body(seeded, CappedPlastic(10.0, 0.0))
    seeded.state["steps"] = np.zeros((seeded.n, 3))  # edited after the Body was made
    with pytest.raises(ValueError, match=r"\['steps'\] has shape \(8, 3\)"):
        Scene(grid, body, 0.1).particles()


def test_bad_declarations_and_updates_raise():
    class Declares(LinearElastic):
        def __init__(self, fields, returned=None):
            super().__init__(10.0)
            self.fields, self.returned = fields, returned

        def state_fields(self, dim):
            return self.fields

        def update(self, particles, L, dt):
            return super().update(particles, L, dt) + (self.returned,)

    for fields, message in [({"a": ((-1,), 0.0)}, "must be a tuple of positive integers"),
                            ({"a": 3.0}, r"must map to \(shape, initial\)"),
                            ({"a": ((2,), (1.0, 2.0, 3.0))}, "number or an array of shape"),
                            ({"a": ((), np.inf)}, "must be finite"),
                            ({"x": ((), 0.0)}, "'x' cannot name a state field"),
                            (["a"], "must return a dict")]:
        with pytest.raises(ValueError, match=message):
            state_layout(Declares(fields), 1)
    grid = SplineGrid.line(0.0, 1.0, 4, 2)
    particles = Particles.seed(grid, 2, 1.0, velocity=lambda X: 0.1 * X)
    for returned, message in [({"b": np.zeros(8)}, "returned the state field 'b'"),
                              ({"a": np.zeros(3)}, r"returned state\['a'\] of shape \(3,\), "
                                                   r"expected \(8,\)")]:
        scene = Scene(grid, Body(particles, Declares({"a": ((), 0.0)}, returned)), 0.01)
        with pytest.raises(ValueError, match=message):
            simulate(scene, Method(backend="numpy"))
    two = [Body(particles.subset(slice(0, 4)), Declares({"a": ((), 0.0)})),
           Body(particles.subset(slice(4, 8)), Declares({"a": ((2,), 0.0)}))]
    with pytest.raises(ValueError, match="both declare the state field 'a', with per-particle "
                                         r"shapes \(\) and \(2,\)"):
        Scene(grid, two, 0.01)


@pytest.mark.parametrize("backend", ["numpy", "numba"])
def test_a_failed_step_keeps_the_last_good_state(backend):
    """A particle leaves the grid (on_exit='raise'): the error's result
    holds the state after the last good step, equal to a run stopped there."""
    from skfem_mpm import SimulationError

    scene = bar_scene(CappedPlasticCompiled(10.0, 0.3), 1, steps=60, region=((0.3, 0.9),),
                      velocity=lambda X: 0.3 + 0.2 * X, effects=[])
    with pytest.raises(SimulationError) as info:
        simulate(scene, Method(backend=backend))
    failed = info.value.step
    good = info.value.result.particles
    assert failed > 3 and np.all(good.state["steps"] == failed - 1)
    stopped = simulate(scene, Method(backend=backend),
                       callback=lambda step, state: step < failed - 1).particles
    for name in names(1):
        assert np.array_equal(good.state[name], stopped.state[name]), name
