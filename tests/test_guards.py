"""Guards, bad input, restart: a clear error and nothing lost."""
import numpy as np
import pytest

from skfem_mpm import (Body, BodyForce, Damping, Fixed, Gravity, LinearElastic, Method,
                       NeoHookean, Particles, Prescribed, Scene, SimulationError, SplineGrid,
                       Traction, simulate)
from skfem_mpm.benchmarks import get_benchmark


def s1_scene(cells=8, p=2, **kw):
    return get_benchmark("vibrating-string", "small", L=1.0).scene(cells, p, 2, **kw)


def test_dt_above_the_critical_step_is_rejected_with_dt_crit():
    scene = s1_scene()
    with pytest.raises(ValueError, match=r"dt = 1 exceeds the critical time step dt_crit = "):
        simulate(scene, Method(dt=1.0))


def test_forced_instability_raises_with_last_good_state():
    b = get_benchmark("vibrating-string", "small", L=1.0)
    scene = b.scene(8, 2, 2, t_end=100 * 2 * np.pi / b.omega)
    dt_crit = simulate(b.scene(8, 2, 2), Method()).dt_crit
    with pytest.raises(SimulationError) as info:
        simulate(scene, Method(dt=10 * dt_crit, allow_unstable=True, scheme="usl"))
    err = info.value
    assert err.step >= 1 and err.time >= 0.0
    p = err.result.particles
    assert all(np.all(np.isfinite(a)) for a in (p.x, p.v, p.stress, p.V))
    assert "step" in str(err)
    # the result's time is its particles' time (only t = 0 was saved)
    assert err.result.counts["steps"] == err.step - 1 > 0
    assert err.result.final_time == pytest.approx(err.time) and err.time > 0


def test_inverted_element_raises_naming_the_particle():
    grid = SplineGrid.line(0, 1, 8, 2)
    parts = Particles.seed(grid, 2, 1.0, region=((0.25, 0.75),),
                           velocity=lambda X: -2000.0 * (X - 0.5))
    scene = Scene(grid, Body(parts, NeoHookean(1.0)), 0.01)
    # the reference path finds det F <= 0, the fast path det(I + dt L) <= 0
    with pytest.raises(SimulationError, match=r"J = det.* <= 0 at particle \d+") as info:
        simulate(scene, Method(dt=1e-3))
    assert info.value.particle is not None
    assert np.all(info.value.result.particles.F[:, 0, 0] > 0)


def flying_scene():
    grid = SplineGrid.rectangle((0, 1), (0, 1), 4, 2)
    parts = Particles.seed(grid, 2, 1.0, region=((0.7, 0.95), (0.4, 0.6)),
                           velocity=np.array([5.0, 0.0]))
    return Scene(grid, Body(parts, LinearElastic(1e2, 0.3)), 0.05)


def test_particle_leaving_the_grid_raises_or_is_removed():
    with pytest.raises(SimulationError, match="left the grid"):
        simulate(flying_scene(), Method())
    r = simulate(flying_scene(), Method(on_exit="remove"), save_every=1)
    assert r.counts["removed"] > 0
    assert r.particles.n + r.counts["removed"] == flying_scene().bodies[0].particles.n
    assert isinstance(r.history["x"], list)  # particle counts differ between saves


@pytest.mark.parametrize("kwargs, match", [
    (dict(scheme="leapfrog"), "scheme must be one of"),
    (dict(mass="diagonal"), "mass must be one of"),
    (dict(reconstruction="fft"), "reconstruction must be one of"),
    (dict(on_exit="ignore"), "on_exit must be one of"),
    (dict(dt=-1.0), "dt must be finite and > 0"),
    (dict(cfl=0.0), "cfl must be finite and > 0"),
    (dict(small_mass=1.5), "small_mass must be a number in"),
    (dict(mass_solver="gmres"), "mass_solver must be one of"),
    (dict(backend="cuda"), "backend must be one of"),
])
def test_bad_method_options(kwargs, match):
    with pytest.raises(ValueError, match=match):
        Method(**kwargs)


@pytest.mark.parametrize("make, match", [
    (lambda: LinearElastic(-1.0), "E must be finite and > 0"),
    (lambda: LinearElastic(1.0, 0.5), r"nu must lie in \(-1, 0.5\)"),
    (lambda: NeoHookean(1.0, -1.0), r"nu must lie in \(-1, 0.5\)"),
    (lambda: Gravity((0.0, np.nan)), "g must be finite"),
    (lambda: Traction("north", 1.0), "where must be one of"),
    (lambda: Scene(SplineGrid.line(0, 1, 2, 2), [], 1.0), "bodies must be"),
])
def test_bad_constructor_arguments(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_bad_scene_arguments():
    grid = SplineGrid.line(0, 1, 4, 2)
    body = Body(Particles.seed(grid, 2, 1.0), LinearElastic(1.0))
    with pytest.raises(ValueError, match="t_end must be finite and > 0"):
        Scene(grid, body, 0.0)
    with pytest.raises(ValueError, match="g must have 1 component"):
        Scene(grid, body, 1.0, effects=[Gravity((0.0, -1.0))])
    with pytest.raises(ValueError, match="side must be one of"):
        Scene(grid, body, 1.0, effects=[Fixed("top")])
    with pytest.raises(ValueError, match="effects must be Effect objects"):
        Scene(grid, body, 1.0, effects=["gravity"])
    outside = Particles(np.array([[1.5]]), np.ones(1), np.ones(1))
    with pytest.raises(ValueError, match="outside the grid"):
        Scene(grid, Body(outside, LinearElastic(1.0)), 1.0)
    with pytest.raises(ValueError, match="Prescribed needs a component"):
        Scene(grid, body, 1.0, effects=[Prescribed("left", None, 1.0)])


def test_bad_simulate_arguments():
    scene = s1_scene()
    with pytest.raises(ValueError, match="save_every must be a positive integer"):
        simulate(scene, save_every=0)
    with pytest.raises(ValueError, match=r"checkpoint must be a pair"):
        simulate(scene, checkpoint="file.npz")
    with pytest.raises(ValueError, match="method must be a Method"):
        simulate(scene, method="musl")
    with pytest.raises(ValueError, match="callback must be callable"):
        simulate(scene, callback=3)


@pytest.mark.parametrize("scheme, mass", [("musl", "consistent"), ("cd", "lumped"),
                                          ("musl", "hybrid")])
def test_restart_from_checkpoint_is_bit_for_bit(tmp_path, scheme, mass):
    b = get_benchmark("soil-column", "small")
    scene = b.scene(8, 2, 2)
    method = Method(scheme=scheme, mass=mass)
    full = simulate(scene, method, save_every=7)
    path = tmp_path / "run.npz"

    def interrupt(step, state):
        if step == 30:
            raise KeyboardInterrupt("stop at 30")

    with pytest.raises(KeyboardInterrupt):
        simulate(scene, method, save_every=7, checkpoint=(path, 10), callback=interrupt)
    resumed = simulate(scene, method, save_every=7, restart=path)
    for k in ("x", "v", "stress", "V"):
        assert np.array_equal(getattr(resumed.particles, k), getattr(full.particles, k))
    assert np.array_equal(resumed.times, full.times)
    assert np.array_equal(resumed.history["u"], full.history["u"])
    assert np.array_equal(resumed.energies["total"], full.energies["total"])


def test_restart_rejects_a_foreign_checkpoint(tmp_path):
    path = tmp_path / "run.npz"
    simulate(s1_scene(), Method(), checkpoint=(path, 5))
    with pytest.raises(ValueError, match="different scene"):
        simulate(s1_scene(cells=16), Method(), restart=path)
    with pytest.raises(ValueError, match="written with"):
        simulate(s1_scene(), Method(mass="consistent"), restart=path)
    bad = tmp_path / "junk.npz"
    np.savez(bad, a=np.zeros(2))
    with pytest.raises(ValueError, match="not a skfem-mpm checkpoint"):
        simulate(s1_scene(), Method(), restart=bad)


def test_callback_can_stop_the_run():
    r = simulate(s1_scene(), Method(), callback=lambda step, state: step < 5)
    assert r.counts["steps"] == 5


@pytest.mark.parametrize("backend", ["numpy", "numba"])
def test_removal_with_two_bodies_rebinds_to_the_survivors(backend):
    """Body 1 flies out of the grid; body 0 keeps being updated with its own
    material (the bodies' index arrays refer to the surviving particles)."""
    grid = SplineGrid.rectangle((0, 1), (0, 1), 4, 2)
    stay = Particles.seed(grid, 2, 1.0, region=((0.1, 0.4), (0.1, 0.4)))
    leave = Particles.seed(grid, 2, 1.0, region=((0.7, 0.95), (0.6, 0.9)),
                           velocity=np.array([5.0, 0.0]))
    scene = Scene(grid, [Body(stay, LinearElastic(1e2, 0.3)), Body(leave, NeoHookean(1e2, 0.3))],
                  0.05)
    r = simulate(scene, Method(on_exit="remove", backend=backend), save_every=1)
    assert r.counts["removed"] > 0
    assert r.particles.n == stay.n + leave.n - r.counts["removed"]
    assert np.all(np.isfinite(r.particles.stress)) and np.all(r.particles.V > 0)


# --------------------------------------------------------------- restart, every field
MEASURED = {"wall_time", "jit_time", "cpu_time"}  # seconds: differ between any two runs
KEYS_ONLY = {"timings", "phase_counts"}  # seconds and timed intervals per phase (the
# compiled loop times a call of many steps at once): compare which phases ran


def assert_same(a, b, where):
    """a and b equal bit for bit, recursively; an unknown type fails (so a
    new recorded quantity cannot slip past the comparison unexamined)."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a), np.asarray(b)
        assert a.shape == b.shape and a.dtype == b.dtype, \
            f"{where}: {a.shape} {a.dtype} vs {b.shape} {b.dtype}"
        assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), \
            f"{where}: differs by up to {np.max(np.abs(a - b)) if a.dtype.kind in 'fiu' else '?'}"
    elif isinstance(a, dict):
        assert isinstance(b, dict) and set(a) == set(b), f"{where}: keys {sorted(a)} vs {sorted(b)}"
        for k in a:
            assert_same(a[k], b[k], f"{where}[{k!r}]")  # History stacks on __getitem__
    elif isinstance(a, (list, tuple)):
        assert type(a) is type(b) and len(a) == len(b), f"{where}: lengths {len(a)} vs {len(b)}"
        for i, (x, y) in enumerate(zip(a, b)):
            assert_same(x, y, f"{where}[{i}]")
    elif isinstance(a, Particles):
        assert isinstance(b, Particles)
        assert_same(vars(a), vars(b), f"{where}.")
    elif isinstance(a, SplineGrid):
        assert a is b, f"{where}: another grid"
    elif a is None or isinstance(a, (bool, int, float, str, np.number, np.bool_)):
        assert type(a) is type(b) and a == b, f"{where}: {a!r} vs {b!r}"
    else:
        raise AssertionError(f"{where}: no comparison for {type(a).__name__}; extend assert_same")


def assert_same_result(full, resumed):
    fields = set(vars(full))
    assert fields == set(vars(resumed)), fields ^ set(vars(resumed))
    for name in sorted(fields - MEASURED):
        a, b = getattr(full, name), getattr(resumed, name)
        if name in KEYS_ONLY:
            a, b = sorted(a), sorted(b)
        if name == "counts":  # the compiled loop's steps say how this call ran its steps
            a, b = ({k: v for k, v in c.items() if k != "compiled_loop_steps"} for c in (a, b))
        assert_same(a, b, name)


def loaded_plate():
    """A neo-Hookean plate (adaptive dt), clamped on the left, pulled on its
    right side by a traction, under a body force, with local damping: every
    kind of recorded quantity moves (external work of two forces,
    reactions, damping's sign of velocity)."""
    grid = SplineGrid.rectangle((0.0, 1.5), (0.0, 1.5), (6, 6), 2)
    parts = Particles.seed(grid, 2, 1.0, region=((0.0, 1.0), (0.25, 1.25)),
                           velocity=lambda X: np.column_stack((0.05 * X[:, 0], 0.02 * X[:, 0])))
    effects = [Fixed("left"), Traction("right", lambda t: (0.2 * min(t / 0.3, 1.0), 0.02)),
               BodyForce(lambda X, t: np.column_stack((0.0 * X[:, 0], -0.5 - 0.5 * X[:, 0]))),
               Damping(0.05)]
    return Scene(grid, Body(parts, NeoHookean(10.0, 0.3)), 0.6, effects=effects)


@pytest.mark.parametrize("backend", ["numba", "numpy"])
@pytest.mark.parametrize("scheme, mass", [("cd", "lumped"), ("cd", "consistent"),
                                          ("musl", "lumped"), ("musl", "consistent"),
                                          ("rk4", "lumped"), ("rk4", "consistent")])
def test_restart_reproduces_every_recorded_quantity(tmp_path, backend, scheme, mass):
    """A run stopped after its checkpoint at step 10 and restarted from it
    gives the Result of the uninterrupted run: every attribute of the
    Result (enumerated, so a new one is compared too), bit for bit, except
    measured seconds (wall and compile time; the phases timed must agree).

    So does a restart from the checkpoint of the last step, which runs no
    step: its final save (when the last step was not a save step) reports
    the velocities from the kept state (CD: v^(n+1/2) + dt/2 N a^n, so the
    kept acceleration must come back), and a save made before that
    checkpoint is not recorded twice."""
    scene = loaded_plate()
    # cfl 0.5 for every scheme (rk4's default 0.6 takes fewer than 20 steps with lumped mass)
    method = Method(scheme=scheme, mass=mass, backend=backend, cfl=0.5)
    full = simulate(scene, method, save_every=3)
    assert full.counts["steps"] > 20 and full.energies["external_work"][-1] != 0.0
    assert any(np.any(f != 0) for r in full.reactions for f in r.values())
    path = tmp_path / "run.npz"
    stopped = simulate(scene, method, save_every=3, checkpoint=(path, 10),
                       callback=lambda step, state: step < 10)
    assert stopped.counts["steps"] == 10
    resumed = simulate(scene, method, save_every=3, restart=path)
    assert_same_result(full, resumed)
    for save_every in (None, 1):  # the last step unsaved / saved before its checkpoint
        full = simulate(scene, method, save_every=save_every)
        last = tmp_path / f"last_{save_every}.npz"
        simulate(scene, method, save_every=save_every, checkpoint=(last, 1))
        assert_same_result(full, simulate(scene, method, save_every=save_every, restart=last))
@pytest.mark.parametrize("run", ["simulate", "fem"])
def test_cfl_above_one_is_refused_like_a_dt_above_dt_crit(run):
    from skfem_mpm import fem
    from skfem_mpm.benchmarks import get_benchmark

    b = get_benchmark("vibrating-string", "small")
    scene = b.scene(8, 2, 2, fem=run == "fem")
    go = simulate if run == "simulate" else fem
    with pytest.raises(ValueError, match=r"cfl = 1\.5 .*cfl <= 1.*allow_unstable=True"):
        go(scene, Method(cfl=1.5))
    r = go(scene, Method(cfl=1.5, allow_unstable=True))
    assert r.counts["steps"] > 0


def test_a_singular_consistent_mass_is_an_invalid_state_not_a_bare_error():
    import scipy.sparse as sp

    from skfem_mpm.errors import InvalidState
    from skfem_mpm.solve.grid_system import Constraints, GridSystem

    grid = SplineGrid.line(0.0, 1.0, 4, 2)
    n = grid.ndofs
    M = sp.csr_matrix(np.ones((n, n)))  # rank one: singular
    system = GridSystem(np.ones(n), Constraints(grid, []), M, None, 0.0, "direct")
    with pytest.raises(InvalidState, match="singular"):
        system.solve(np.ones((n, 1)), np.zeros((n, 1)), "velocity")


def test_a_consistent_mass_cg_that_does_not_converge_is_an_invalid_state():
    """The reference path's CG (mass_solver="cg") on a singular mass with a
    right-hand side outside its range: InvalidState (simulate turns it into
    SimulationError with the last good state), not NaN velocities."""
    import scipy.sparse as sp

    from skfem_mpm.errors import InvalidState
    from skfem_mpm.solve.grid_system import Constraints, GridSystem

    grid = SplineGrid.line(0.0, 1.0, 4, 2)
    n = grid.ndofs
    M = sp.csr_matrix(np.ones((n, n)))
    system = GridSystem(np.ones(n), Constraints(grid, []), M, None, 0.0, "cg")
    with np.errstate(all="ignore"), pytest.raises(InvalidState, match="did not converge"):
        system.solve(np.arange(n, dtype=float)[:, None], np.zeros((n, 1)), "velocity")


def test_a_checkpoint_folder_that_does_not_exist_is_refused_before_the_first_step(tmp_path):
    from skfem_mpm.benchmarks import get_benchmark

    scene = get_benchmark("vibrating-string", "small").scene(8, 2, 2)
    with pytest.raises(ValueError, match="checkpoint path .*does not exist or is not writable"):
        simulate(scene, Method(), checkpoint=(tmp_path / "missing" / "run.npz", 5))
    with pytest.raises(ValueError, match="checkpoint path must be a str or os.PathLike"):
        simulate(scene, Method(), checkpoint=(None, 1))


def test_a_failed_checkpoint_write_keeps_the_run_and_leaves_no_temporary_file(tmp_path,
                                                                              monkeypatch):
    from skfem_mpm import SimulationError
    from skfem_mpm.benchmarks import get_benchmark

    def full_disk(file, **arrays):
        with open(file, "wb") as f:
            f.write(b"half")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(np, "savez", full_disk)
    scene = get_benchmark("vibrating-string", "small").scene(8, 2, 2)
    with pytest.raises(SimulationError, match="checkpoint after step 3 failed") as info:
        simulate(scene, Method(), checkpoint=(tmp_path / "run.npz", 3))
    assert info.value.step == 3 and info.value.result.counts["steps"] == 3
    assert np.isfinite(info.value.result.particles.x).all()
    assert list(tmp_path.iterdir()) == []


def test_fixed_and_prescribed_on_the_same_dofs_are_refused():
    grid = SplineGrid.line(0.0, 1.0, 4, 2)
    p = Particles.seed(grid, 2, 1.0)
    body = Body(p, LinearElastic(1.0))
    for effects in ([Fixed("left"), Prescribed("left", 0, lambda t: 1.0)],
                    [Prescribed("left", 0, lambda t: 1.0), Fixed("left")],
                    [Prescribed("left", 0, lambda t: 1.0), Prescribed("left", 0, lambda t: 2.0)]):
        with pytest.raises(ValueError, match="constrains component 0 of dofs that another"):
            simulate(Scene(grid, body, 0.01, effects=effects), Method())
    # the same constraint twice is harmless
    simulate(Scene(grid, body, 0.01, effects=[Fixed("left"), Fixed("left")]), Method())


# ------------------------------------------------ fast-dof guard: effective mass
def _sliver_scene(end=1.0625):
    """A cubic bar (h = 1/8) fixed at x = 0 whose free end lies half-way
    into its last cell (2 particles per cell: 2 in that half cell)."""
    from skfem_mpm import Particles as P

    grid = SplineGrid(np.linspace(0.0, 1.5, 13), 3)
    parts = P.seed(grid, 2, 1.0, region=((0.0, end),),
                   velocity=lambda X: 1e-3 * np.sin(np.pi * X / 2 / end))
    return Scene(grid, Body(parts, LinearElastic(100.0)), 0.4, effects=[Fixed("left")])


@pytest.mark.parametrize("backend", ["numpy", "numba"])
def test_the_guard_still_lumps_a_body_ending_inside_a_cell(backend):
    """Half the last cell filled (cubic, consistent CD, cfl 0.5): the end
    dof is fast (a mode localised at the cut cell, ~ Lambda / l^2), and
    the guard must lump it: without the guard the run fails at step 16
    (J <= 0); with it, 220 steps and |v| stays below its initial 1e-3.
    ~5 s per backend. Without a reconstruction the end dof, a tail, takes
    the plain limit (timestep.covered_parameters)."""
    r = simulate(_sliver_scene(), Method(scheme="cd", mass="consistent", backend=backend))
    assert r.counts["steps"] == 220
    assert np.abs(r.particles.v).max() < 1e-3
    with pytest.raises(SimulationError):
        simulate(_sliver_scene(), Method(scheme="cd", mass="consistent", backend=backend,
                                         frequency_guard=0.0))
