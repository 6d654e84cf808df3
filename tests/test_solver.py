"""The MPM solver and the FEM reference on exact solutions (S1, S2, D1, D2)."""
import numpy as np
import pytest
from skfem import MeshTri1

from skfem_mpm import (Body, Damping, Fixed, Gravity, LagrangeGrid, LinearElastic, Method,
                       Particles, Scene, SimulationError, SplineGrid, fem, simulate)
from skfem_mpm.benchmarks import get_benchmark
from skfem_mpm.solve import (commit, grid_to_particles, particles_to_grid, prepare, solve_grid,
                             update_stress)
from skfem_mpm.testing import assert_order, observed_orders


def s1(**params):
    return get_benchmark("vibrating-string", "small", L=1.0, **params)


def s1_error(cells, degree, ppc=4, **method):
    b = s1()
    return b.errors(simulate(b.scene(cells, degree, ppc), Method(**method)))["error_rms"]


def test_s1_linear_mpm_is_second_order():
    cells = [8, 16, 32, 64]
    errors = [s1_error(n, 1) for n in cells]
    assert_order(errors, 1.0 / np.array(cells), expected=2.0, tol=0.15)


def test_s1_quadratic_consistent_mass_beats_lumped_tenfold_at_32_cells():
    # measured: 1.97e-5 (consistent) vs 3.65e-4 (lumped) at cfl = 0.1
    consistent = s1_error(32, 2, mass="consistent", cfl=0.1)
    lumped = s1_error(32, 2, mass="lumped", cfl=0.1)
    assert lumped / consistent >= 10.0, (consistent, lumped)


@pytest.mark.parametrize("p", (1, 2, 3))
def test_s1_fem_converges_at_order_p_plus_one(p):
    b = s1()
    cells = [4, 8, 16, 32]
    errors = [b.errors(fem(b.scene(n, p, 4, fem=True),
                           Method(mass="consistent", scheme="cd", cfl=0.02)))["error_rms"]
              for n in cells]
    assert_order(errors, 1.0 / np.array(cells), expected=p + 1, tol=0.2)


def test_s2_small_deformation_converges():
    # gravity switched on at t = 0 makes u only ~H^2.5 in space: the order is
    # limited (about 1.7), every method shows it; assert a steady decrease
    b = get_benchmark("soil-column", "small")
    cells = [8, 16, 32]
    errors = [b.errors(simulate(b.scene(n, 2, 2), Method(mass="consistent", scheme="cd")))
              ["error_rms"] for n in cells]
    assert_order(errors, 1.0 / np.array(cells), expected=1.6, tol=0.1)


@pytest.mark.parametrize("mass", ("lumped", "consistent"))
def test_s2_large_deformation_runs_to_the_end(mass):
    b = get_benchmark("soil-column", "large")
    result = simulate(b.scene(20, 2, 2), Method(mass=mass), save_every=20)
    assert np.isclose(result.final_time, b.t_end)
    assert np.all(np.isfinite(result.particles.x))
    # the top has moved down by more than a cell: particles crossed cells
    assert result.history["u"][:, :, 0].min() < -0.05


def test_d1_manufactured_neo_hookean_converges_for_quadratic():
    # measured: small 1.08e-2, 2.23e-3 (order 2.28); large 8.0e-3, 2.4e-3
    small = get_benchmark("axis-aligned-2d", "small")
    errors = [small.errors(simulate(small.scene(n, 2, 2), Method(mass="consistent")))
              ["error_rms"] for n in (8, 16)]
    assert observed_orders(errors, [1 / 8, 1 / 16])[0] > 2.0, errors
    large = get_benchmark("axis-aligned-2d", "large")
    errors = [large.errors(simulate(large.scene(n, 2, 2), Method(mass="consistent")))
              ["error_rms"] for n in (8, 16)]
    assert errors[1] < errors[0] / 2.5 and errors[1] < 5e-3, errors


@pytest.mark.parametrize("scheme", ("cd", "musl"))
def test_s1_energy_over_ten_periods(scheme):
    b = s1()
    T = 2 * np.pi / b.omega
    r = simulate(b.scene(16, 2, 2, t_end=10 * T), Method(mass="consistent", scheme=scheme),
                 save_every=10)
    e = r.energies["total"]
    assert abs(e[-1] - e[0]) / e[0] < 0.01  # measured: cd +0.18 %, musl -0.09 %
    assert np.all(np.abs(r.energies["external_work"]) == 0.0)


def test_general_path_p1_triangles_converges():
    b = get_benchmark("vibrating-plate-2d", "small")
    errors = []
    for k in (2, 3, 4):
        mesh = MeshTri1.init_sqsymmetric().refined(k)
        particles = Particles.from_mesh(mesh, b.rho, intorder=2,
                                        velocity=lambda X: b.velocity(X, 0.0))
        scene = Scene(LagrangeGrid(mesh), Body(particles, LinearElastic(b.E, b.nu)), b.t_end,
                      effects=[Fixed("left", 0), Fixed("right", 0), Fixed("bottom", 1),
                               Fixed("top", 1)])
        errors.append(b.errors(simulate(scene, Method()))["error_rms"])
    assert_order(errors, [1, 0.5, 0.25], expected=1.6, tol=0.1)


def test_scene_is_not_modified():
    b = s1()
    scene = b.scene(8, 2, 2)
    before = {k: getattr(scene.bodies[0].particles, k).copy() for k in ("x", "v", "stress", "V")}
    simulate(scene, Method())
    fem(scene, Method())
    for k, a in before.items():
        assert np.array_equal(getattr(scene.bodies[0].particles, k), a)


def test_named_step_functions_reproduce_simulate():
    b = s1()
    scene = b.scene(8, 2, 2)
    method = Method(scheme="musl", mass="consistent")
    reference = simulate(scene, method)
    state = prepare(scene, method)
    while not state.done:
        state.next_step_size()
        grid = particles_to_grid(state)
        solve_grid(state, grid)
        L = grid_to_particles(state, grid)
        update_stress(state, L, grid)
        commit(state, grid)
    assert np.array_equal(state.particles.x, reference.particles.x)


@pytest.mark.parametrize("backend", ("numpy", "numba"))
def test_undeclared_effects_cost_nothing(backend):
    b = s1()
    plain = simulate(b.scene(8, 2, 2), Method(backend=backend))
    assert not plain.phase_counts.get("effects")
    assert not plain.phase_counts.get("reconstruct")
    assert plain.particles.F is None  # small strain never builds F
    body = get_benchmark("neo-hookean-bar", "small")
    loaded = simulate(body.scene(8, 2, 2), Method(backend=backend))
    # the body force is timed: every step in Python, at every call of the
    # compiled loop (which evaluates its rows step by step within a call)
    steps = loaded.counts["steps"]
    assert loaded.phase_counts["effects"] >= (steps if backend == "numpy" else 1)
    assert loaded.timings["effects"] > 0.0
    grav = get_benchmark("soil-column", "small")
    falling = simulate(grav.scene(8, 2, 2), Method(backend=backend))
    assert falling.energies["external_work"][-1] != 0.0
    if backend == "numba":  # gravity is g times the nodal mass: no per-particle pass,
        assert falling.phase_counts.get("effects", 0) <= 1  # only the binding at the start


def test_fem_rejects_a_body_that_does_not_fill_the_grid():
    b = get_benchmark("traction-bar", "small")
    with pytest.raises(ValueError, match="fills the grid"):
        fem(b.scene(8, 2, 2), Method())
    fem(b.scene(8, 2, 2, fem=True), Method())


def test_damped_column_settles_and_reaction_carries_the_weight():
    b = get_benchmark("soil-column", "small")
    scene = b.scene(8, 2, 2, t_end=40 * 4 * b.H / b.c)
    scene = Scene(scene.grid, scene.bodies, scene.t_end, effects=scene.effects + (Damping(0.2),))
    r = simulate(scene, Method(mass="lumped"))
    weight = r.particles.m.sum() * b.g
    reaction = r.reactions[-1]["Fixed('left', component=None)"][0]
    assert abs(reaction - weight) < 1e-3 * weight  # the base pushes up with the weight
    static = b._static(r.history["X"][-1][:, 0])
    assert np.abs(r.history["u"][-1][:, 0] - static).max() < 0.02 * np.abs(static).max()


def test_momentum_is_exact_with_tiny_mass_merging():
    # free flight, no forces: total momentum stays exactly the initial one
    grid = SplineGrid.rectangle((0, 1), (0, 1), 8, 2)
    parts = Particles.seed(grid, 2, 1.0, region=((0.3, 0.5001), (0.3, 0.6)),
                           velocity=lambda X: np.column_stack((0.1 + X[:, 1], -0.2 * X[:, 0])))
    scene = Scene(grid, Body(parts, LinearElastic(1e3, 0.3)), 0.05)
    for mass in ("lumped", "consistent"):
        r = simulate(scene, Method(mass=mass), save_every=5)
        assert r.counts["small_dofs_max"] > 0
        p0 = parts.m @ parts.v
        for v in r.history["v"]:
            assert np.abs(parts.m @ v - p0).max() < 1e-13 * np.abs(p0).max()


def test_gravity_free_fall_matches_ballistics():
    grid = SplineGrid.rectangle((0, 1), (0, 1), 4, 2)
    parts = Particles.seed(grid, 2, 1.0, region=((0.25, 0.75), (0.5, 0.75)))
    scene = Scene(grid, Body(parts, LinearElastic(1e3, 0.3)), 0.1,
                  effects=[Gravity((0.0, -9.81))])
    r = simulate(scene, Method(scheme="cd"))
    drop = -r.history["u"][-1][:, 1].mean()
    assert abs(drop - 0.5 * 9.81 * 0.1 ** 2) < 1e-12
    # external work equals the loss of potential energy m g drop
    assert np.isclose(r.energies["external_work"][-1], parts.m.sum() * 9.81 * drop, rtol=1e-12)


def test_fem_follows_a_users_small_strain_material():
    """fem integrates the material's own update (here the 1D elastic-perfectly
    plastic material of examples/custom_material.py). Under monotonic loading
    (before any point unloads) that law gives sigma = clip(E eps, +-sigma_y)
    at every particle; linear elasticity would exceed the yield stress."""
    import sys
    from pathlib import Path

    from skfem_mpm.quadrature import transfer_matrices

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
    try:
        from custom_material import ElasticPlastic1D
    finally:
        sys.path.pop(0)
    E, yield_stress = 100.0, 0.09
    grid = SplineGrid.line(0.0, 1.0, 16, 2)
    particles = Particles.seed(grid, 2, 1.0, velocity=lambda X: 1e-2 * np.sin(np.pi * X))
    scene = Scene(grid, Body(particles, ElasticPlastic1D(E, yield_stress)), 0.044,
                  effects=[Fixed("left"), Fixed("right")])
    result = fem(scene, Method(mass="consistent"))
    _, G = transfer_matrices(grid, particles.X)
    elastic = E * (G[0] @ result.grid_displacement[:, 0])
    stress = result.particles.stress[:, 0, 0]
    assert np.abs(elastic).max() > 1.05 * yield_stress  # the plastic branch is reached
    assert np.abs(stress - np.clip(elastic, -yield_stress, yield_stress)).max() \
        <= 1e-12 * yield_stress


@pytest.mark.parametrize("backend", ["numba", "numpy"])
@pytest.mark.parametrize("finite", [False, True])
def test_particles_a_callback_keeps_are_never_written_again(backend, finite):
    """A callback may keep the state's particles; later steps must not
    write into their arrays (the compiled executor double-buffers its
    particle arrays and used to reuse the ones handed out)."""
    from skfem_mpm.benchmarks import get_benchmark

    b = get_benchmark("neo-hookean-bar" if finite else "vibrating-string",
                      None if finite else "small")
    scene = b.scene(8, 2, 2)
    kept = []

    def keep(step, state):
        p = state.particles
        kept.append((p, {k: getattr(p, k).copy() for k in ("x", "v", "u", "stress", "V", "F")
                         if getattr(p, k) is not None}))
        return step < 8

    simulate(scene, Method(scheme="musl", backend=backend), callback=keep)
    assert len(kept) == 8
    changed = [i for i, (p, values) in enumerate(kept)
               if any(not np.array_equal(getattr(p, k), v) for k, v in values.items())]
    assert changed == []
