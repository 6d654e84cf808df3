"""G2's measures of a deposit (ColumnCollapse.checks) on a made-up final
state whose answers are known."""
from types import SimpleNamespace

import numpy as np
import pytest

from skfem_mpm.benchmarks import get_benchmark


def deposit(x, m):
    """A Result-like object with particles at x (n, 2) of masses m, at rest,
    having fallen 0.1 from their reference positions."""
    X = x + np.array([0.0, 0.1])
    p = SimpleNamespace(x=x, X=X, m=m, v=np.zeros_like(x), n=len(m),
                        state={"plastic_strain": np.zeros(len(m))})
    return SimpleNamespace(particles=p)


def test_the_fronts_of_a_made_up_deposit():
    """100 particles in a row at x = 1.005 ... 1.995 (y = 0.05, one of them
    thrown up to y = 0.45) and one heavy particle at x = 0.5, y = 0.4
    holding half the mass, listed last: the runout is the rightmost
    particle plus half a spacing; 97% of the mass lies behind the particle
    whose cumulative share from the wall first reaches 0.97 (the row holds
    0.5, each of its particles 0.005: the 94th, x = 1.935); the final
    height is the highest particle within L0 of the wall, not the thrown
    grain."""
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
    assert checks["runout_ratio"] == pytest.approx((0.995 + 1 / 16) / 0.6)
