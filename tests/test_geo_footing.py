"""Footing (a rigid footing on the dofs under its current base) and BBar
(the cell-averaged volumetric strain rate against volumetric locking)."""
import json

import numpy as np
import pytest

from skfem_mpm import (
    BBar,
    Body,
    Fixed,
    Footing,
    LinearElastic,
    Method,
    Particles,
    Scene,
    SplineGrid,
    VonMises,
    simulate,
)
from skfem_mpm.cli import main
from skfem_mpm.materials import lame_parameters

E, NU, RHO = 100.0, 0.3, 1.0


def layer_under_footing(span, speed=0.05, ramp=0.2, t_end=0.5, cells=(4, 4), material=None):
    """A 1 x 1 elastic layer (sliding sides, fixed base) under a Footing
    with its base on the surface; the grid reaches a cell above it."""
    nx, ny = cells
    h = 1.0 / ny
    grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0 + h), (nx, ny + 1), 2)
    particles = Particles.seed(grid, 2, RHO, region=((0.0, 1.0), (0.0, 1.0)))
    footing = Footing(span, 1.0, speed, ramp=ramp)
    material = LinearElastic(E, NU) if material is None else material
    scene = Scene(grid, Body(particles, material), t_end,
                  effects=[Fixed("left", 0), Fixed("right", 0), Fixed("bottom"), footing])
    return scene, footing


@pytest.mark.parametrize("backend", ["numpy", "numba"])
def test_a_footing_over_the_whole_width_compresses_the_layer_oedometrically(backend):
    """A footing as wide as the layer pushes it down like an oedometer
    plate: the bearing pressure is the constrained modulus times the
    strain, q = (lambda + 2 mu) s / H, within 2% at a settlement of
    0.02 H reached slowly (the P wave crosses the layer in 0.085 s; the
    settlement takes 0.5 s; measured 0.3%); the particles along the
    surface move down with the footing (its speed to 1e-9) while the
    footing has moved more than a cell (the dofs are chosen anew)."""
    scene, footing = layer_under_footing((0.0, 1.0), speed=0.05, ramp=0.2, t_end=0.6)
    result = simulate(scene, Method(backend=backend), save_every=10)
    lam, mu = lame_parameters(E, NU)
    s = np.array([record[1] for record in footing.history])
    reaction = [record[2] for record in footing.history]
    q = -np.array([r[1] for r in reaction]) / footing.width
    late = s >= 0.8 * s.max()
    exact = (lam + 2 * mu) * s[late] / 1.0
    assert np.abs(q[late] / exact - 1).max() <= 0.02
    assert footing.settlement == pytest.approx(0.05 * (0.6 - 0.1), rel=1e-12)
    assert result.reactions[-1][repr(footing)][1] < 0


def test_the_footing_keeps_contact_after_settling_more_than_a_cell():
    """A narrow footing (a quarter of the width) settles 1.5 cells (h =
    0.1): the particles along its base stay with it, within a third of a
    cell (they start half a particle spacing, 0.025, below it; measured
    0.012), as they do after a third of a cell; a dof set chosen once
    would have left them behind after one cell."""
    for t_end, settled in ((0.1, 0.02), (0.55, 0.15)):
        scene, footing = layer_under_footing((0.0, 0.25), speed=0.3, ramp=0.05, t_end=t_end,
                                             cells=(8, 10))
        result = simulate(scene, Method())
        assert footing.settlement >= settled - 1e-12
        x = result.particles.x
        base = 1.0 - footing.settlement
        under = x[:, 0] < 0.2
        column = np.floor(x[:, 0] / 0.0625)  # the particles' columns (spacing 0.0625)
        for c in np.unique(column[under]):  # the top particle of each column under it
            k = under & (column == c)
            assert abs(x[k, 1].max() - base) <= 0.1 / 3, (t_end, c)


def test_rk4_moves_the_footing_at_its_speed():
    """rk4 and MUSL with the same dt (40 steps to t = 0.1, the reference
    executor): one record per step, at the step's end t_k = k dt, with
    the settlement s(t_k) of the ramp (0.02), so s(t_end) = v (t_end -
    ramp / 2) after the run (the footing once advanced its clock per rk4
    stage: 4 t_end); over the last quarter of the run, past the
    transient, rk4's bearing reaction is MUSL's within 5% of MUSL's last
    (measured 2.9%; USL's 1.6%)."""
    records = {}
    for scheme in ("musl", "rk4"):
        scene, footing = layer_under_footing((0.0, 0.5), speed=0.05, ramp=0.02, t_end=0.1)
        result = simulate(scene, Method(scheme=scheme, dt=0.0025, backend="numpy"))
        assert result.counts["steps"] == len(footing.history) == 40
        t = np.array([record[0] for record in footing.history])
        s = np.array([record[1] for record in footing.history])
        assert np.allclose(t, 0.0025 * np.arange(1, 41), rtol=1e-12)
        assert np.allclose(s, [footing.settlement_at(tk) for tk in 0.0025 * np.arange(1, 41)],
                           rtol=1e-12)
        assert footing.settlement == pytest.approx(0.05 * (0.1 - 0.01), rel=1e-12)
        records[scheme] = np.array([record[2][1] for record in footing.history])
    musl, rk4 = records["musl"][30:], records["rk4"][30:]
    assert np.abs(rk4 - musl).max() <= 0.05 * abs(musl[-1])


def test_a_restarted_footing_goes_on_from_its_settlement(tmp_path):
    """20 steps with a checkpoint, then a restart from it to t_end: the
    footing goes on from s(t) (its records those of the continuous run's
    last 20 steps, the particles the same bits; it once started again at
    s = 0, and the checkpoint's fingerprint took the footing's history
    for part of the scene, so the restart was refused)."""
    method = Method(dt=0.0025, backend="numpy")

    def run(**kwargs):
        scene, footing = layer_under_footing((0.0, 0.5), speed=0.05, ramp=0.02, t_end=0.1)
        result = simulate(scene, method, **kwargs)
        return result, np.array([[t, s, *r] for t, s, r in footing.history])

    full, whole = run()
    path = tmp_path / "footing.npz"
    run(checkpoint=(path, 20), callback=lambda step, state: step < 20)
    resumed, rest = run(restart=path)
    assert rest.shape[0] == 20 and np.array_equal(rest, whole[20:])
    assert np.array_equal(resumed.particles.x, full.particles.x)


def test_bad_footings_raise():
    with pytest.raises(ValueError, match="span must have x0 < x1"):
        Footing((1.0, 0.0), 1.0, 0.1)
    with pytest.raises(ValueError, match="speed must be"):
        Footing((0.0, 1.0), 1.0, 0.0)
    with pytest.raises(ValueError, match="rough must be True or False"):
        Footing((0.0, 1.0), 1.0, 0.1, rough="yes")
    grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (4, 4), 2)
    particles = Particles.seed(grid, 2, RHO)
    with pytest.raises(ValueError, match="base must lie in the grid's vertical range"):
        Scene(grid, Body(particles, LinearElastic(E, NU)), 0.1,
              effects=[Footing((0.0, 0.5), 2.0, 0.1)])
    with pytest.raises(ValueError, match="contains no Greville abscissa"):
        Scene(grid, Body(particles, LinearElastic(E, NU)), 0.1,
              effects=[Footing((0.3, 0.32), 1.0, 0.1)])


# ------------------------------------------------------------------ BBar
def random_gradients(n, seed=0):
    return np.random.default_rng(seed).normal(size=(n, 2, 2))


def test_bbar_averages_the_dilatation_over_each_cell_and_keeps_the_deviator():
    """average="cell": L_bar - L is isotropic; per cell the volume-weighted
    dilatation is unchanged and L_bar's is uniform (1e-14); a uniform L is
    left as it is up to round-off (1e-15), and the wrapped material's
    update with it (1e-13)."""
    grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (3, 3), 2)
    p = Particles.seed(grid, 3, RHO, layout="random", seed=1)
    material = BBar(LinearElastic(E, NU), grid, average="cell")
    L = random_gradients(p.n)
    Lb = material.averaged(p, L)
    d = Lb - L
    assert np.abs(d[:, 0, 1]).max() == 0 and np.abs(d[:, 0, 0] - d[:, 1, 1]).max() <= 1e-14
    cells, _ = grid.locate(p.x)
    theta, theta_b = np.trace(L, axis1=1, axis2=2), np.trace(Lb, axis1=1, axis2=2)
    for c in range(grid.ncells):
        k = cells == c
        assert abs(p.V[k] @ theta[k] - p.V[k] @ theta_b[k]) <= 1e-14
        assert np.ptp(theta_b[k]) <= 1e-14
    uniform = np.broadcast_to(L[0], L.shape).copy()
    assert np.abs(material.averaged(p, uniform) - uniform).max() <= 1e-15
    a, b = material.update(p, uniform, 1e-3), LinearElastic(E, NU).update(p, uniform, 1e-3)
    assert all(np.abs(x - y).max() <= 1e-13 * np.abs(y).max()
               for x, y in zip(a, b) if x is not None)


def test_bbar_projects_the_dilatation_onto_the_vertex_functions():
    """average="vertex" (the default on a quadratic grid; "cell" on a
    linear one): L_bar - L is isotropic; theta_bar is the interpolant of
    vertex means theta_A, each the hat-weighted mean of the particles'
    dilatations (1e-13, from the formula); the body's volume-weighted
    dilatation is kept (1e-13); theta_bar lies within the particles'
    range; a uniform L is left as it is (1e-15)."""
    grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.5), (3, 4), 2)
    p = Particles.seed(grid, 3, RHO, layout="random", seed=2)
    material = BBar(LinearElastic(E, NU), grid)
    assert material.average == "vertex" and material.functions == 4 * 5
    linear = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (3, 3), 1)
    assert BBar(LinearElastic(E, NU), linear).average == "cell"
    L = random_gradients(p.n, 3)
    Lb = material.averaged(p, L)
    d = Lb - L
    assert np.abs(d[:, 0, 1]).max() == 0 and np.abs(d[:, 0, 0] - d[:, 1, 1]).max() <= 1e-14
    theta, theta_b = np.trace(L, axis1=1, axis2=2), np.trace(Lb, axis1=1, axis2=2)

    def hat(values, knots, x):  # the vertex's piecewise-linear function
        return np.interp(x, knots, values)

    kx, ky = np.linspace(0.0, 1.0, 4), np.linspace(0.0, 1.5, 5)
    expected = np.zeros(p.n)
    for j in range(5):
        for i in range(4):
            H = hat(np.eye(4)[i], kx, p.x[:, 0]) * hat(np.eye(5)[j], ky, p.x[:, 1])
            if H.any():
                expected += H * (((H * p.V) @ theta) / (H * p.V).sum())
    assert np.abs(theta_b - expected).max() <= 1e-13 * np.abs(theta).max()
    assert abs(p.V @ theta_b - p.V @ theta) <= 1e-13 * (p.V @ np.abs(theta))
    assert theta.min() <= theta_b.min() and theta_b.max() <= theta.max()
    uniform = np.broadcast_to(L[0], L.shape).copy()
    assert np.abs(material.averaged(p, uniform) - uniform).max() <= 1e-15


def test_the_vertex_projection_keeps_the_footings_load_curve_rising():
    """A small strip footing (half width 0.5 over 4 cells, a domain of 1.5
    B, quadratic, 2 x 2 particles per cell, B-bar clay) pushed 0.25 B, two
    cells: the load-settlement curve (0.005 B bins) does not fall by more
    than 1% of its largest value from one bin to the next (measured: at
    most 0.1%). With cell averages it peaked at 5.19 c_u near 0.08 B and
    fell to 4.5 c_u by 0.16 B, the particles under the footing drifting
    into rows (the BBar docstring)."""
    from skfem_mpm.benchmarks import get_benchmark

    bench = get_benchmark("strip-footing", settlement=0.25, width=1.5, depth=1.5)
    scene = bench.scene(12)
    assert scene.bodies[0].material.average == "vertex"
    result = simulate(scene, Method(), save_every=100)
    checks = bench.checks(result)
    q = np.array([point[1] for point in checks["curve"]])
    assert result.particles.state["plastic_strain"].max() > 0.05
    assert np.diff(q).min() >= -0.01 * q.max()
    # the saved positions give the embedment and the pressure with it divided out
    settled, depth = np.array(checks["embedment"]).T
    assert settled[0] == 0.0 and depth[0] == 0.0 and depth[-1] > settled[-1]  # it heaved
    s, corrected = np.array(checks["curve_depth_corrected"]).T
    assert np.allclose(corrected * (1 + 0.4 * np.interp(s, settled, depth)), q, rtol=1e-12)


def test_the_embedment_is_the_settlement_plus_the_heave_beside_the_footing():
    """footing_embedment: D = s + (the highest particle within B/2 <= x <= B
    minus the highest initial one); particles under the footing or farther
    out do not count. hansen_depth_factor: 1 + 0.4 D/B up to D = B, then
    1 + 0.4 arctan(D/B)."""
    from skfem_mpm.benchmarks import footing_embedment, hansen_depth_factor

    X = np.array([[0.2, 0.9], [0.7, 0.9], [0.9, 0.95], [1.5, 0.95], [3.0, 0.5]])
    x = X + np.array([[0.0, -0.1], [0.05, 0.06], [0.02, 0.07], [0.0, 0.2], [0.0, 0.0]])
    assert footing_embedment(x, X, 1.0, 0.1) == pytest.approx(0.1 + 1.02 - 0.95)
    assert footing_embedment(x, X, 2.0, 0.1) == pytest.approx(0.1 + 1.15 - 0.95)  # up to x = B
    assert hansen_depth_factor(0.5) == pytest.approx(1.2)
    assert np.allclose(hansen_depth_factor([1.0, 2.0]), [1.4, 1 + 0.4 * np.arctan(2.0)])
    with pytest.raises(ValueError, match="depth_over_width must be >= 0"):
        hansen_depth_factor([0.5, -0.1])
    with pytest.raises(ValueError, match="no particle beside the footing"):
        footing_embedment(x, X, 0.1, 0.1)


def test_bbar_runs_the_same_on_both_executors():
    """A plastic layer under a footing with BBar: NumPy and compiled
    executors agree to 1e-12 (stress, positions, plastic strain)."""
    grid_scene, _ = layer_under_footing((0.0, 0.5), speed=0.5, ramp=0.01, t_end=0.05)
    grid = grid_scene.grid
    material = BBar(VonMises(E, NU, 2.0), grid)
    runs = []
    for backend in ("numpy", "numba"):
        scene, _ = layer_under_footing((0.0, 0.5), speed=0.5, ramp=0.01, t_end=0.05,
                                       material=material)
        runs.append(simulate(scene, Method(backend=backend)))
    ref, fast = runs
    for a, b in ((ref.particles.stress, fast.particles.stress), (ref.particles.x, fast.particles.x),
                 (ref.particles.state["plastic_strain"], fast.particles.state["plastic_strain"])):
        assert np.abs(a - b).max() <= 1e-12 * max(1.0, np.abs(a).max())
    assert ref.particles.state["plastic_strain"].max() > 0  # it yielded


def test_bad_bbar_raises():
    grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (2, 2), 2)
    with pytest.raises(ValueError, match="material must be a Material"):
        BBar("clay", grid)
    with pytest.raises(ValueError, match="grid must be the scene's SplineGrid"):
        BBar(LinearElastic(E, NU), None)
    with pytest.raises(ValueError, match=r"average must be one of \('cell', 'vertex'\).*'patch'"):
        BBar(LinearElastic(E, NU), grid, average="patch")


def test_cli_runs_the_strip_footing_and_reports_the_bearing_capacity(capsys):
    """G1 at 1 cell under the half footing, pushed to 0.11 B (the
    validation is a benchmark run, not a test): the JSON record has the
    bearing capacity factor under a key with "bearing" and the curve; the
    clay has yielded and the pressure is on its plateau below Prandtl's."""
    assert main(["run", "strip-footing", "--cells", "10", "--set", "settlement=0.11",
                 "--json"]) == 0
    record = json.loads(capsys.readouterr().out)
    assert record["cells_across_width"] == 10 and record["cells_under_half_footing"] == 1
    n_c = record["bearing_capacity_factor"]
    assert 3.5 < n_c < 2 + np.pi and record["bearing_capacity_prandtl"] == 2 + np.pi
    assert record["curve"][-1][0] == pytest.approx(0.1125)  # the last 0.005 B bin
