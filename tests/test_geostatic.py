"""The geostatic (K0) stress helper and G4: a layer loaded by gravity
reaches sigma_h = K0 sigma_v, and a layer started from the K0 procedure
stays at rest."""
import json

import numpy as np
import pytest

from skfem_mpm import Method, Particles, SplineGrid, simulate
from skfem_mpm.benchmarks import get_benchmark
from skfem_mpm.cli import main
from skfem_mpm.geostatic import geostatic_stress


def test_geostatic_stress_formula():
    """sigma_v = -rho g depth, sigma_h = sigma_zz = K0 sigma_v, zero above
    the surface and off the diagonal; K0 from nu is nu / (1 - nu)."""
    grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 2.0), (2, 4), 2)
    p = Particles.seed(grid, 2, 3.0)
    out = geostatic_stress(p, 1.5, 10.0, nu=0.25)
    depth = np.maximum(1.5 - p.x[:, 1], 0.0)
    assert np.allclose(out.stress[:, 1, 1], -30.0 * depth, rtol=1e-14, atol=0)
    assert np.allclose(out.stress[:, 0, 0], -10.0 * depth, rtol=1e-14, atol=0)
    assert np.allclose(out.state["sigma_zz"], -10.0 * depth, rtol=1e-14, atol=0)
    assert np.all(out.stress[:, 0, 1] == 0) and np.all(out.stress[p.x[:, 1] > 1.5] == 0)
    assert p.stress is not out.stress and np.all(p.stress == 0)  # a new set
    sloped = geostatic_stress(p, lambda x: 1.0 + 0.5 * x[:, 0], 10.0, K0=0.5)
    d = np.maximum(1.0 + 0.5 * p.x[:, 0] - p.x[:, 1], 0.0)
    assert np.allclose(sloped.stress[:, 1, 1], -30.0 * d, rtol=1e-14, atol=0)
    box = SplineGrid.box((0, 1), (0, 1), (0, 1), (1, 1, 2), 1)
    q = geostatic_stress(Particles.seed(box, 2, 1.0), 1.0, 2.0, K0=0.7)
    assert np.allclose(q.stress[:, 0, 0], 0.7 * q.stress[:, 2, 2]) and \
        np.allclose(q.stress[:, 1, 1], 0.7 * q.stress[:, 2, 2]) and q.stress[:, 2, 2].min() < 0


def test_geostatic_stress_rejects_bad_input():
    grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (2, 2), 1)
    p = Particles.seed(grid, 2, 1.0)
    with pytest.raises(ValueError, match="exactly one of K0 and nu"):
        geostatic_stress(p, 1.0, 9.81)
    with pytest.raises(ValueError, match="K0 must be finite and >= 0"):
        geostatic_stress(p, 1.0, 9.81, K0=-0.5)
    with pytest.raises(ValueError, match="surface must be a finite number"):
        geostatic_stress(p, "top", 9.81, K0=0.5)
    with pytest.raises(ValueError, match="g must be"):
        geostatic_stress(p, 1.0, 0.0, K0=0.5)


def test_g4_gravity_loading_reaches_k0_within_one_percent():
    """Gravity loading with local damping, 20 cells deep, 20 transit times:
    sigma_h / sigma_v = K0 over the particles one cell below the surface
    (measured: 7e-12 off; the lateral strain is zero), sigma_v within 1%
    of rho g (H - Y) (measured 0.38%), at rest (speed 3e-5 sqrt(g H))."""
    bench = get_benchmark("geostatic-stress")
    result = simulate(bench.scene(20), Method())
    checks = bench.checks(result)
    assert checks["k0_error_max"] <= 0.01
    assert checks["sigma_v_error_max"] <= 0.01
    assert checks["speed_max_over_sqrt_gH"] <= 1e-3
    undamped = get_benchmark("geostatic-stress", damping=0.0)
    free = undamped.checks(simulate(undamped.scene(20), Method()))
    assert free["speed_max_over_sqrt_gH"] > 1e-2  # damping is what brings it to rest


@pytest.mark.parametrize("K0", [None, 0.8])
@pytest.mark.parametrize("backend", ["numpy", "numba"])
def test_g4_k0_procedure_stays_at_rest(backend, K0):
    """Started from geostatic_stress (elastic K0 or a user's 0.8), Gauss
    particles, no damping, 10 P-wave transit times: every save's speed below
    1e-6 sqrt(g H) (measured 1e-16)."""
    bench = get_benchmark("geostatic-stress", "k0-procedure", K0=K0)
    result = simulate(bench.scene(20), Method(backend=backend), save_every=50)
    scale = np.sqrt(bench.g * bench.H)
    speeds = [np.sqrt(np.einsum("ij,ij->i", v, v)).max() / scale for v in result.history["v"]]
    assert max(speeds) <= 1e-6
    assert bench.checks(result)["k0_error_max"] <= 1e-10


def test_cli_runs_g4(capsys):
    assert main(["run", "geostatic-stress", "--variant", "k0-procedure", "--cells", "10",
                 "--json"]) == 0
    record = json.loads(capsys.readouterr().out)
    assert record["k0_error_max"] <= 1e-10 and record["benchmark"] == "geostatic-stress"


def test_cli_runs_the_column_collapse_and_reports_the_runout(capsys):
    """G2 at a tiny size and a short time (the validation is a benchmark
    run, not a test): the JSON record has the runout and final height
    ratio, the column has started to spread and the grains yield."""
    assert main(["run", "column-collapse", "--cells", "4", "--set", "a=0.5", "--t-end", "0.15",
                 "--json"]) == 0
    record = json.loads(capsys.readouterr().out)
    assert {"runout", "final_height_ratio", "runout_lube_low_1.2a"} <= set(record)
    assert 0.0 < record["runout"] < 1.0 and record["final_height_ratio"] < 1.01
    assert record["plastic_strain_max"] > 1e-3
