"""A scheme's time order shows where the body starts accelerated (S2).

MUSL and USL update the velocity and then the position with it (symplectic
Euler). From rest under a constant load b that gives x_n = b t^2 / 2 +
b t dt / 2: an error of order dt, so of order h at a fixed CFL, whatever
the space discretisation. S1 starts with zero acceleration and hides it
(MUSL shows order 2 there); the soil column, gravity switched on at t = 0,
shows it, in FEM as in MPM. Central difference starts its velocity at the
half step and keeps order 2. The README's soil-column study runs ``cd`` for
this reason.
"""
import numpy as np
import pytest

from skfem_mpm.study import convergence


@pytest.mark.parametrize("scheme, lo, hi", [("musl", 0.9, 1.1), ("cd", 1.7, 2.3)])
def test_soil_column_converges_at_the_schemes_time_order(scheme, lo, hi):
    """FEM p2 on S2 small at 8-16-32 cells, cfl 0.5: MUSL order 1.0 (0.9-1.1),
    central difference 1.8-2.0 (1.7-2.3)."""
    records = convergence("soil-column", ["fem-p2-consistent"], [8, 16, 32], variant="small",
                          executor="serial", scheme=scheme)
    errors = np.array([r["error"] for r in records])
    orders = np.log2(errors[:-1] / errors[1:])
    assert np.all((orders > lo) & (orders < hi)), (scheme, errors, orders)
