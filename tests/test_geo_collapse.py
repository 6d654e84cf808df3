"""G2's measures of a deposit (ColumnCollapse.checks) on a made-up final
state whose answers are known."""
from types import SimpleNamespace

import numpy as np
import pytest

from skfem_mpm.benchmarks import get_benchmark, thickness_front


def deposit(x, m, v=None):
    """A Result-like object with particles at x (n, 2) of masses m (density
    1: V0 = m), at rest or moving at v, having fallen 0.1 from their
    reference positions."""
    X = x + np.array([0.0, 0.1])
    p = SimpleNamespace(x=x, X=X, m=m, V0=m.copy(), v=np.zeros_like(x) if v is None else v,
                        n=len(m), state={"plastic_strain": np.zeros(len(m))})
    return SimpleNamespace(particles=p)


def test_the_fronts_of_a_made_up_deposit():
    """100 particles in a row at x = 1.005 ... 1.995 (y = 0.05, one of them
    thrown up to y = 0.45) and one heavy particle at x = 0.5, y = 0.4
    holding half the mass, listed last: the runout is the rightmost
    particle plus half a spacing; 97% of the mass lies behind the particle
    whose cumulative share from the wall first reaches 0.97 (the row holds
    0.5, each of its particles 0.005: the 94th, x = 1.935); the final
    height is the highest particle within L0 of the wall, not the thrown
    grain. The row is 0.5 L0 thick by volume, so the thickness front is the
    last window centre (steps of 1/64) whose window (1/8 wide) holds two
    of its particles (0.01 >= 0.05 / 8): centre < 1.985 + 1/16, k / 64 with
    k = 131, runout 131 / 64 - 1."""
    bench = get_benchmark("column-collapse", a=0.5)
    bench.scene(cells=4)  # sets the particle spacing, 1/8
    x = np.column_stack((1.005 + 0.01 * np.arange(100), np.full(100, 0.05)))[::-1]
    x[10, 1] = 0.45
    x = np.vstack((x, [[0.5, 0.4]]))
    m = np.append(np.full(100, 0.005), 0.5)
    checks = bench.checks(deposit(x, m))
    assert checks["runout"] == pytest.approx(0.995 + 1 / 16)
    assert checks["runout_97pct_mass"] == pytest.approx(0.935)
    assert checks["runout_99pct_mass"] == pytest.approx(0.975)
    assert checks["final_height_ratio"] == pytest.approx((0.4 + 1 / 16) / 0.5)
    assert checks["runout_thickness_front"] == pytest.approx(131 / 64 - 1)
    assert checks["runout_ratio"] == pytest.approx((131 / 64 - 1) / 0.6)
    assert checks["runout_friction_model"] == pytest.approx(0.5 * np.sqrt(3))  # a / tan 30
    assert checks["kinetic_grid_over_released"] == 0.0


def test_the_grid_kinetic_energy_sees_motion_not_noise():
    """A block of 8 x 8 particles moving at (1, -0.5): the grid's kinetic
    energy is the particles' (the functions sum to one); the same block
    with a velocity alternating +-1 from one particle to the next (a
    pattern two particles per cell cannot show on a quadratic grid): the
    grid's is below 2% of the particles' (measured 0.1%)."""
    bench = get_benchmark("column-collapse", a=0.5)
    bench.scene(cells=4)
    g = (np.arange(8) + 0.5) / 16
    x = np.column_stack([a.ravel() for a in np.meshgrid(0.25 + g, 0.1 + g)])
    m = np.full(64, 1 / 64)
    moving = bench.checks(deposit(x, m, np.tile([1.0, -0.5], (64, 1))))
    assert moving["kinetic_grid_over_released"] == pytest.approx(
        moving["kinetic_over_released"], rel=1e-12)
    sign = (-1.0) ** (np.arange(64) + np.arange(64) // 8)
    noisy = bench.checks(deposit(x, m, np.column_stack((sign, 0 * sign))))
    assert noisy["kinetic_grid_over_released"] <= 0.02 * noisy["kinetic_over_released"]


def test_the_thickness_front_of_a_wedge():
    """thickness_front on a wedge of thickness 1 - x over 0 < x < 1 (volumes
    of points 1e-3 apart): the window average of a linear profile is the
    profile, so the front at thickness 0.2 is x = 0.8 (to the 1/64 step of
    the centres and the points' spacing)."""
    x = np.arange(0.0005, 1.0, 0.001)
    front = thickness_front(x, (1 - x) * 0.001, 0.2, 1 / 8)
    assert 0.8 - 1 / 64 <= front <= 0.8 + 0.002


@pytest.mark.slow
def test_the_cost_script_times_both_materials_while_every_particle_yields(capsys):
    """benchmarks/mohr_coulomb_cost.py at 4 cells across L0, 5 steps: both
    runs go through the compiled loop on the same step, the ratio is the
    medians', and from 0.9 K_a every particle yields in the timed steps."""
    import importlib.util
    import json
    import pathlib

    path = pathlib.Path(__file__).parent.parent / "benchmarks" / "mohr_coulomb_cost.py"
    spec = importlib.util.spec_from_file_location("mohr_coulomb_cost", path)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    out = script.main(["--cells", "4", "--steps", "5", "--repeat", "1", "--json"])
    assert json.loads(capsys.readouterr().out)["ratio"] == out["ratio"]
    assert out["k0"] == pytest.approx(0.9 / 3)
    assert out["fraction_yielding"] == 1.0
    assert out["ratio"] == pytest.approx(out["us_per_step_mohr_coulomb"]
                                         / out["us_per_step_linear_elastic"])
    for run in out["paths"].values():
        assert run["loop_steps"] == run["steps"] == 5
