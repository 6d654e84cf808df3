"""The compiled executor in 3D agrees with the reference executor.

The transfer kernels are generated for dim = 3 from the same templates as
1D and 2D (kernels/scatter.py, kernels/gather.py); the grid kernels (lumped
solve, tiny-mass count and merge) are written once for 1-3 axes. Lumped
mass: 1e-12 relative on positions, velocities and stresses (and the
external work), as tests/test_executors.py in 1D and 2D.
"""
import numpy as np
import pytest

from skfem_mpm import (Body, BodyForce, Damping, Fixed, Gravity, LinearElastic, Method,
                       NeoHookean, Particles, Scene, SplineGrid, Traction, simulate)
from skfem_mpm.kernels.mpm import small_mass_1d, small_mass_2d, small_mass_axes
from skfem_mpm.solve.compiled import compiled_executor_applies
from skfem_mpm.solve.state import prepare


def scene_3d(degree, material="linear", effect="gravity", steps=6, region=None):
    """A block in a 4 x 3 x 3 cell box (non-cubic cells), partly filled so
    that cut cells and empty dofs occur, rotating and shearing."""
    grid = SplineGrid.box((0.0, 1.0), (0.0, 0.75), (0.0, 1.2), (4, 3, 3), degree)
    region = region or ((0.0, 0.7), (0.0, 0.6), (0.0, 0.85))
    particles = Particles.seed(
        grid, 2, 1.0, region=region,
        velocity=lambda X: np.column_stack((0.05 * X[:, 2], -0.03 * X[:, 0],
                                            0.02 * X[:, 1] - 0.01 * X[:, 0])))
    material = {"linear": LinearElastic(10.0, 0.3), "neo-hookean": NeoHookean(10.0, 0.3)}[
        material]
    effects = [Fixed("zmin")] + {
        "none": [],
        "gravity": [Gravity((0.0, 0.0, -2.0))],
        "body-force": [BodyForce(lambda X, t: 0.5 * np.cos(3 * X + t))],
        "traction": [Traction("xmax", lambda t: (0.01 * t, 0.0, -0.005))],
        "damping": [Damping(0.05)]}[effect]
    return grid, particles, material, effects


def check_agreement(degree, scheme, material="linear", effect="gravity", steps=6, tol=1e-12,
                    mass="lumped", reconstruction="none", **kw):
    grid, particles, material, effects = scene_3d(degree, material, effect, **kw)
    method = dict(scheme=scheme, mass=mass, reconstruction=reconstruction)
    scene = Scene(grid, Body(particles, material), 1.0, effects=effects)
    dt = prepare(scene, Method(**method)).dt
    scene = Scene(grid, Body(particles, material), steps * dt, effects=effects)
    ref = simulate(scene, Method(backend="numpy", **method), save_every=2)
    fast = simulate(scene, Method(backend="numba", **method), save_every=2)
    # the compiled loop runs the lumped linear elastic cases (its own tests
    # compare it with the executor bit for bit), the executor the others
    assert fast.path in ("fast", "fast (compiled loop)") and ref.path.startswith("reference"), \
        (fast.path, ref.path)
    for key in ("x", "v", "stress"):
        a, b = ref.history[key], fast.history[key]
        scale = max(np.abs(a).max(), 1e-300)
        assert np.abs(a - b).max() <= tol * scale, (key, np.abs(a - b).max() / scale)
    w_ref, w_fast = ref.energies["external_work"], fast.energies["external_work"]
    assert np.abs(w_ref - w_fast).max() <= tol * max(np.abs(w_ref).max(), 1e-300) + 1e-300
    return ref, fast


LUMPED = [(1, "musl", "linear", "gravity"), (2, "usl", "linear", "gravity"),
          (3, "cd", "linear", "none"), (2, "musl", "neo-hookean", "traction"),
          (3, "usl", "neo-hookean", "body-force"), (1, "cd", "linear", "damping"),
          (3, "musl", "linear", "gravity"), (2, "cd", "linear", "gravity"),
          (1, "usl", "neo-hookean", "none"), (2, "rk4", "linear", "gravity"),
          (1, "rk4", "neo-hookean", "traction")]
# The 3D cubic transfer kernels take minutes to compile on a fresh install:
# the degree-3 cases run in the slow tier, and the default tier runs each of
# them at degree 2 (same scheme, material and effect; 3D p = 2 is compiled
# anyway), so every scheme, material and effect stays covered in 3D.
SLOW_3D_CUBIC = pytest.mark.slow(reason="3D p = 3 kernels compile for minutes; the "
                                 "default tier runs this case at p = 2")


def tiered(cases):
    """Each case; a degree-3 case in the slow tier plus its degree-2 copy
    in the default tier."""
    out = []
    for case in cases:
        if case[0] == 3:
            out.append(pytest.param(*case, marks=SLOW_3D_CUBIC,
                                    id="-".join(map(str, case))))
            case = (2,) + tuple(case[1:])
        out.append(pytest.param(*case, id="-".join(map(str, case))))
    return out


@pytest.mark.parametrize("degree,scheme,material,effect", tiered(LUMPED))
def test_lumped_3d_agrees_with_the_reference(degree, scheme, material, effect):
    ref, _ = check_agreement(degree, scheme, material, effect)
    assert np.abs(ref.history["x"][-1] - ref.history["x"][0]).max() > 0.0


# consistent (and hybrid) mass: the compiled executor solves by CG to rtol
# 1e-13 on the 3D stencil (three-factor Kronecker preconditioner), the
# reference by sparse LU: 1e-9 relative, as in tests/test_executors.py
CONSISTENT = [(2, "musl", "consistent", "linear", "gravity"),
              (3, "usl", "consistent", "neo-hookean", "traction"),
              (1, "cd", "consistent", "linear", "body-force"),
              (2, "musl", "hybrid", "linear", "damping"),
              (2, "rk4", "consistent", "linear", "gravity")]
FILLED = ((0.0, 1.0), (0.0, 0.75), (0.0, 1.2))  # the whole grid: no tiny masses


@pytest.mark.parametrize("degree,scheme,mass,material,effect", tiered(CONSISTENT))
def test_consistent_3d_agrees_with_the_reference(degree, scheme, mass, material, effect):
    check_agreement(degree, scheme, material, effect, mass=mass, tol=1e-9)


@pytest.mark.parametrize("degree,scheme", tiered(((2, "usl"), (3, "musl"))))
def test_consistent_3d_stencil_cg_agrees_with_the_reference(degree, scheme):
    """The grid filled (no tiny masses), so that every step solves
    with the stencil CG and the three-factor Kronecker preconditioner (the
    cut blocks above may take the sparse LU of a tiny-mass step)."""
    from skfem_mpm.solve.stencil_system import StencilSystem

    StencilSystem.iteration_log = log = []
    try:
        _, fast = check_agreement(degree, scheme, "linear", "gravity", mass="consistent",
                                  tol=1e-9, region=FILLED)
    finally:
        StencilSystem.iteration_log = None
    assert fast.counts["small_dofs_max"] == 0
    assert len(log) >= 6 and max(log) > 0


def test_three_factor_kronecker_is_exact_for_gauss_filled_cells():
    """Particles at the Gauss points of every cell (p + 1 per axis) give
    M = rho M_z (x) M_y (x) M_x, which the Kronecker preconditioner inverts:
    CG meets 1e-13 in one iteration on a non-cubic 3D grid (all dofs free)
    and the solution is the sparse solve's."""
    import scipy.sparse.linalg as sla

    from skfem_mpm.kernels.mpm import Kernels
    from skfem_mpm.solve.stencil_system import StencilSystem, preconditioned_with

    grid = SplineGrid((np.array([0.0, 0.3, 0.5, 1.0]), np.linspace(0.0, 0.8, 5),
                       np.array([-1.0, 0.0, 0.5])), 2)
    particles = Particles.seed(grid, 3, 2.0, layout="gauss")
    # the serial kernels (what a run below SERIAL_BELOW particles calls, the
    # same bits): the parallel 3D assembly and CG compile for about 40 s and
    # only the slow tier needs them
    kernels = Kernels(grid, parallel=False)
    stencil, _ = kernels.consistent_stencil(particles)
    lumped, _, _ = kernels.p2g(particles, None)

    class Free:
        mask = np.zeros((grid.ndofs, 3), dtype=bool)

    rhs = np.random.default_rng(5).standard_normal((grid.ndofs, 3))
    with preconditioned_with("kronecker") as iterations:
        system = StencilSystem(kernels, stencil, lumped.copy(), Free(), np.zeros(grid.ndofs),
                               {})
        x = system.solve(rhs, np.zeros_like(rhs), "a")
    assert iterations == [1]
    expected = sla.spsolve(kernels.stencil_csr(stencil).tocsc(), rhs)
    assert np.abs(x - expected).max() < 1e-11 * np.abs(expected).max()


def test_3d_tiny_masses_are_merged_as_the_reference_does():
    """A sliver of particles in the last cell layer gives tiny-mass dofs:
    the compiled merge (written once for 1-3 axes) agrees with the
    reference merge."""
    ref, fast = check_agreement(2, "usl", region=((0.0, 0.7), (0.0, 0.6), (0.0, 0.81)),
                                steps=4)
    # (the executors count differently: the compiled one also counts
    # constrained dofs; measured 27 and 26)
    assert fast.counts["small_dofs_max"] > 0 and ref.counts["small_dofs_max"] > 0


def test_small_mass_axes_is_the_1d_and_2d_rule():
    """The one tiny-mass count for 1-3 axes gives the 1D and 2D kernels'
    masks on random masses with zeros, and a brute-force 3D mask."""
    from skfem_mpm.kernels.serial import serial

    # the serial copies (the same thread blocks in a loop, the same bits),
    # which the runs below SERIAL_BELOW particles compile
    small_1d, small_2d, small_axes = (serial(small_mass_1d), serial(small_mass_2d),
                                      serial(small_mass_axes))
    rng = np.random.default_rng(3)
    for p in (1, 2, 3):
        m = rng.random(40) ** 8 * (rng.random(40) > 0.2)
        a, b = np.empty(40, bool), np.empty(40, bool)
        assert small_1d(m, p, 1e-3, a) == small_axes(m, 40, 1, 1, p, 1e-3, b)
        assert np.array_equal(a, b)
        m2 = rng.random(7 * 6) ** 8 * (rng.random(42) > 0.2)
        a, b = np.empty(42, bool), np.empty(42, bool)
        assert small_2d(m2, 7, 6, p, 1e-3, a) == small_axes(m2, 7, 6, 1, p, 1e-3, b)
        assert np.array_equal(a, b)
        shape = (5, 4, 6)
        m3 = rng.random(120) ** 8 * (rng.random(120) > 0.2)
        b = np.empty(120, bool)
        count = small_axes(m3, *shape, p, 1e-3, b)
        cube = m3.reshape(shape[::-1])  # (z, y, x)
        expected = np.zeros(120, bool)
        for k in range(120):
            c, bb, a = np.unravel_index(k, shape[::-1])
            near = cube[max(0, c - p):c + p + 1, max(0, bb - p):bb + p + 1,
                        max(0, a - p):a + p + 1]
            expected[k] = 0 < m3[k] < 1e-3 * near.max()
        assert np.array_equal(b, expected) and count == expected.sum() > 0


def test_3d_refusals_name_their_reason():
    grid, particles, material, effects = scene_3d(2)
    scene = Scene(grid, Body(particles, material), 0.01, effects=effects)
    for method in (Method(scheme="usl"), Method(mass="consistent"), Method(mass="hybrid")):
        assert compiled_executor_applies(prepare(scene, method)) == (True, "")
    ok, why = compiled_executor_applies(prepare(scene, Method(mass="consistent",
                                                              reconstruction="spline")))
    assert not ok and "reconstruction spline in 3D" in why
    for name in ("tls", "mls"):
        assert compiled_executor_applies(prepare(scene, Method(reconstruction=name))) == \
            (True, "")
    assert compiled_executor_applies(prepare(scene, Method(scheme="rk4"))) == (True, "")


# reconstruction in 3D (tls, mls) on the compiled executor and in the loop,
# from the 1D/2D kernels (kernels.gauss_rule, kernels.tls, kernels.mls): the
# block's free surfaces cut cells (their particles are points of the rule);
# 1e-12 lumped, 1e-9 consistent, as above. Each compiles a 3D reconstructed
# loop of its own: the slow tier.
RECONSTRUCTED = [("tls", "musl", "consistent"), ("mls", "musl", "consistent"),
                 ("tls", "usl", "lumped"), ("mls", "rk4", "lumped"),
                 ("tls", "rk4", "consistent")]


@pytest.mark.slow(reason="each case compiles a 3D reconstructed loop")
@pytest.mark.parametrize("reconstruction,scheme,mass", RECONSTRUCTED,
                         ids=["-".join(c) for c in RECONSTRUCTED])
def test_reconstructed_3d_agrees_with_the_reference_and_the_loop_with_the_executor(
        monkeypatch, reconstruction, scheme, mass):
    from skfem_mpm.solve import compiled_loop

    tol = 1e-12 if mass == "lumped" else 1e-9
    _, fast = check_agreement(2, scheme, "linear", "gravity", mass=mass, tol=tol,
                              reconstruction=reconstruction)
    assert fast.path == "fast (compiled loop)", fast.path
    monkeypatch.setattr(compiled_loop, "ENABLED", False)
    grid, particles, material, effects = scene_3d(2)
    method = Method(scheme=scheme, mass=mass, reconstruction=reconstruction)
    scene = Scene(grid, Body(particles, material), 6 * prepare(
        Scene(grid, Body(particles, material), 1.0, effects=effects), method).dt,
        effects=effects)
    stepped = simulate(scene, method, save_every=2)
    assert stepped.path == f"fast (reconstruction {reconstruction})", stepped.path
    for key in ("x", "v", "stress"):
        assert np.array_equal(stepped.history[key], fast.history[key]), key


@pytest.fixture(scope="module")
def c_reference(tmp_path_factory):
    from skfem_mpm.reference_c import ReferenceUnavailable, compile_reference, find_compiler

    try:
        find_compiler()
    except ReferenceUnavailable as exc:
        pytest.skip(f"no C compiler to build the C reference: {exc}")
    return compile_reference(tmp_path_factory.mktemp("c"))


@pytest.mark.parametrize("filled", (False, True), ids=("middle-half", "filled"))
def test_c_reference_3d_ends_in_the_state_simulate_computes(c_reference, tmp_path, filled):
    """usl_step.c in 3D on the bench's problem (8^3 cells: the middle half
    starts on a breakpoint, so no tiny-mass merge, which the C loop does not
    do; or every cell, so that the clamped boundary B-splines are used), the
    block expanding and shearing so that every stress component changes:
    the final state of simulate (USL, lumped, compiled) to round-off on 2
    threads and on 1; a state 1e-7 off is not accepted."""
    from skfem_mpm.bench import scene_3d
    from skfem_mpm.reference_c import compare, run_reference, write_problem

    scene, dt = scene_3d(cells=8, steps=8, dt=2e-4)
    body = scene.bodies[0]
    if filled:
        body.particles = Particles.seed(scene.grid, 2, 1.0)
    x = body.particles.x
    body.particles.v = 0.1 * (x - 0.5) + 0.05 * np.roll(x - 0.5, 1, axis=1)
    method = Method(scheme="usl", dt=dt * (1 - 1e-9))
    result = simulate(scene, method)
    assert result.path.startswith("fast")
    problem = write_problem(tmp_path / "in.bin", scene, method)
    assert problem["steps"] == result.counts["steps"] >= 8
    for threads in (2, 1):
        out = run_reference(c_reference, tmp_path / "in.bin", tmp_path / "out.bin", threads)
        assert out["threads"] == threads and out["invalid"] == 0
        agrees, differences = compare(result.particles, out["final"], problem)
        assert agrees and max(differences.values()) < 1e-12, differences
    shear = np.abs(result.particles.stress[:, [0, 0, 1], [1, 2, 2]]).max(axis=0)
    assert shear.min() / problem["modulus"] > 1e-6  # every shear component is compared
    wrong = dict(out["final"], stress=out["final"]["stress"] * (1 + 1e-7))
    assert not compare(result.particles, wrong, problem)[0]
