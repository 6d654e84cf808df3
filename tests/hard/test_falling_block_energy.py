"""The falling block (tests/hard/test_free_surface.py) left on the floor for
about 100 periods of its own vibration: what each method does to the
energy. The figures are the README's ("Which method for which case");
a change of method that moves them fails here, so the table is updated.

Measure: Result.energy_balance = E_0 + W_ext - E (initial energy plus the
work of gravity minus the current energy), at the end, divided by the
largest |E_0 + W_ext| of the run: negative when the run gained energy.
The block (P-wave speed 36.7, height 0.2) has a period 4 H / c = 0.022 s;
it hits the floor at t = 0.30 and rests to t = 2.8 (about 115 periods).

Linear consistent MUSL gains energy on a path that becomes chaotic after
t ~ 1.5: changes of the mass solve at rounding level (CG tolerance 1e-12,
1e-13, 1e-14; the fringe correction on or off) give the same gain to three
digits up to t = 1 (+0.115) and +0.19 to +0.21 at t = 1.5, but +0.39 to
+0.98 at t = 2.8. Its case checks the gain at t = 1 and 1.5 in bands and
only the sign of the end figure; the other cases have no CG and are checked
at the end.
"""
import numpy as np
import pytest
from test_free_surface import falling_block

from skfem_mpm import Method, SimulationError, simulate

T_END = 2.8


def gained(r):
    """Energy gained by the end, relative to the energy budget."""
    budget = r.energies["total"][0] + r.energies["external_work"]
    return float(-r.energy_balance[-1] / np.abs(budget).max())


def gained_at(r, t):
    """The gain of `gained` at the saved time nearest t."""
    budget = r.energies["total"][0] + r.energies["external_work"]
    i = int(np.argmin(np.abs(np.asarray(r.times) - t)))
    return float(-r.energy_balance[i] / np.abs(budget).max())


@pytest.mark.slow
@pytest.mark.parametrize("degree, mass, scheme, low, high", [
    (1, "lumped", "musl", 0.30, 0.37),      # measured +0.336
    (2, "lumped", "musl", -0.07, -0.03),    # measured -0.049
    (2, "lumped", "cd", -0.70, -0.60),      # measured -0.657
])
def test_energy_after_a_hundred_periods_on_the_floor(degree, mass, scheme, low, high):
    r = simulate(falling_block(degree, T_END), Method(mass=mass, scheme=scheme), save_every=20)
    g = gained(r)
    print(f"\nfalling block p={degree} {mass} {scheme}, t = {T_END}: energy gained {g:+.3f} "
          f"of the budget")
    assert r.final_time == pytest.approx(T_END)
    assert low < g < high, g


@pytest.mark.slow
def test_linear_consistent_gains_energy_on_the_floor():
    """p = 1, consistent MUSL: +0.115 at t = 1 and +0.19 to +0.21 at 1.5
    whatever the rounding of the mass solve; by 2.8 the figure depends on
    it (+0.39 to +0.98), so only its sign is checked. A particle thrown out
    of the grid is dropped (with CG tolerance 1e-12 one leaves at t = 2.0)."""
    r = simulate(falling_block(1, T_END), Method(mass="consistent", scheme="musl",
                                                 on_exit="remove"), save_every=20)
    early, middle, end = gained_at(r, 1.0), gained_at(r, 1.5), gained(r)
    print(f"\nfalling block p=1 consistent musl: energy gained {early:+.3f} (t = 1), "
          f"{middle:+.3f} (t = 1.5), {end:+.3f} (t = {T_END})")
    assert r.final_time == pytest.approx(T_END)
    assert 0.10 < early < 0.13, early
    assert 0.16 < middle < 0.24, middle
    assert end > 0.25, end


@pytest.mark.slow
def test_linear_central_difference_fails_after_the_impact():
    """p = 1, lumped, CD: J <= 0 soon after the contact at t = 0.30
    (measured t = 0.369)."""
    with pytest.raises(SimulationError, match="J = det") as info:
        simulate(falling_block(1, T_END), Method(mass="lumped", scheme="cd"), save_every=20)
    assert 0.30 < info.value.result.final_time < 0.45
