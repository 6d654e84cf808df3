"""Bad input: every public constructor and simulate raise ValueError whose
message names the argument, the bad value and what is valid (one case per
row). Faults (blow-up, interruption) are in tests/test_guards.py:
test_forced_instability_raises_with_last_good_state and
test_restart_from_checkpoint_is_bit_for_bit."""
import numpy as np
import pytest

from skfem_mpm import (Body, BodyForce, Damping, Fixed, Gravity, LinearElastic, Method, NeoHookean,
                       Particles, Prescribed, Scene, SplineGrid, Traction, fem, simulate)
from skfem_mpm.benchmarks import get_benchmark
from skfem_mpm.quadrature import ParticleBasis

GRID = SplineGrid.line(0.0, 1.0, 4, 2)
ONE = dict(x=np.array([[0.5]]), m=np.array([1.0]), V=np.array([1.0]))


def particles(**changes):
    return Particles(**{**ONE, **changes})


def s1_scene(fem_scene=False):
    return get_benchmark("vibrating-string", "small", L=1.0).scene(8, 2, 2, fem=fem_scene)


CASES = {
    # non-positive or non-finite material constants, density, volume, mass
    "E <= 0 (LinearElastic)": (lambda: LinearElastic(0.0), r"E must be finite and > 0, got 0.0"),
    "E <= 0 (NeoHookean)": (lambda: NeoHookean(-2.0), r"E must be finite and > 0, got -2.0"),
    "E NaN": (lambda: LinearElastic(np.nan), r"E must be finite and > 0, got nan"),
    "nu = 0.5": (lambda: LinearElastic(1.0, 0.5), r"nu must lie in \(-1, 0.5\), got 0.5"),
    "nu = -1": (lambda: NeoHookean(1.0, -1.0), r"nu must lie in \(-1, 0.5\), got -1.0"),
    "density <= 0": (lambda: Particles.seed(GRID, 2, 0.0), r"density must be finite and > 0, got 0.0"),
    "volume <= 0": (lambda: particles(V=np.array([0.0])), r"V must be > 0 for every particle, got 0.0"),
    "mass <= 0": (lambda: particles(m=np.array([-1.0])), r"m must be > 0 for every particle, got -1.0"),
    # ppc
    "ppc = 0": (lambda: Particles.seed(GRID, 0, 1.0), r"ppc must be a positive integer \(per axis\), got 0"),
    "ppc per axis": (lambda: Particles.seed(SplineGrid.rectangle((0, 1), (0, 1), 2, 2), (2, 0), 1.0),
                     r"ppc must be a positive integer \(per axis\), got 0"),
    # NaN / Inf in every input array
    "x NaN": (lambda: particles(x=np.array([[np.nan]])), r"x must be finite, got nan at index 0"),
    "m Inf": (lambda: particles(m=np.array([np.inf])), r"m must be finite, got inf at index 0"),
    "V NaN": (lambda: particles(V=np.array([np.nan])), r"V must be finite, got nan at index 0"),
    "v Inf": (lambda: particles(v=np.array([[np.inf]])), r"v must be finite, got inf at index 0"),
    "stress Inf": (lambda: particles(stress=np.full((1, 1, 1), np.inf)),
                   r"stress must be finite, got inf at index 0"),
    "F NaN": (lambda: particles(F=np.full((1, 1, 1), np.nan)), r"F must be finite, got nan at index 0"),
    "seed velocity NaN": (lambda: Particles.seed(GRID, 2, 1.0, velocity=lambda X: X * np.nan),
                          r"velocity\(X\) must be finite, got nan"),
    "gravity Inf": (lambda: Gravity(np.inf), r"g must be finite, got inf"),
    "traction Inf": (lambda: Traction("left", np.inf), r"tau must be finite, got inf"),
    "prescribed NaN": (lambda: Prescribed("left", 0, np.nan), r"velocity must be finite .* got nan"),
    # mismatched lengths
    "m length": (lambda: particles(m=np.ones(2)), r"m must have shape \(1,\), got \(2,\)"),
    "V length": (lambda: particles(V=np.ones(3)), r"V must have shape \(1,\), got \(3,\)"),
    "v length": (lambda: particles(v=np.zeros((2, 1))), r"v must have shape \(1, 1\), got \(2, 1\)"),
    "stress shape": (lambda: particles(stress=np.zeros((1, 1))), r"stress must have shape \(1, 1, 1\)"),
    "body length": (lambda: particles(body=np.array([0, 1])), r"body must be an integer array of shape \(1,\)"),
    # outside the grid
    "outside (Scene)": (lambda: Scene(GRID, Body(particles(x=np.array([[1.5]])), LinearElastic(1.0)), 1.0),
                        r"outside the grid"),
    "outside (ParticleBasis)": (lambda: ParticleBasis(GRID, particles(x=np.array([[-0.5]]))),
                                r"lie outside the grid \[0, 1\]; the first is index 0 at \[-0.5\]"),
    "seed region outside": (lambda: Particles.seed(GRID, 2, 1.0, region=((0.5, 2.0),)),
                            r"region box axis 0 \(0.5, 2.0\) must lie inside the grid \(0.0, 1.0\)"),
    # dt above the stable limit
    "dt (simulate)": (lambda: simulate(s1_scene(), Method(dt=1.0)),
                      r"dt = 1 exceeds the critical time step dt_crit = [0-9.]+"),
    "dt (fem)": (lambda: fem(s1_scene(True), Method(dt=1.0)),
                 r"dt = 1 exceeds the critical time step dt_crit = [0-9.]+"),
    # unknown option strings
    "scheme": (lambda: Method(scheme="rk3"), r"scheme must be one of 'musl', 'usl', 'usf', 'cd', 'rk4', got 'rk3'"),
    "mass": (lambda: Method(mass="row-sum"), r"mass must be one of .*got 'row-sum'"),
    "reconstruction": (lambda: Method(reconstruction="kriging"), r"reconstruction must be one of .*got 'kriging'"),
    "on_exit": (lambda: Method(on_exit="wrap"), r"on_exit must be one of .*got 'wrap'"),
    "mass_solver": (lambda: Method(mass_solver="gmres"), r"mass_solver must be one of .*got 'gmres'"),
    "backend": (lambda: Method(backend="cuda"), r"backend must be one of .*got 'cuda'"),
    "layout": (lambda: Particles.seed(GRID, 2, 1.0, layout="hex"), r"layout must be one of .*got 'hex'"),
    "side": (lambda: Scene(GRID, Body(particles(), LinearElastic(1.0)), 1.0, effects=[Fixed("top")]),
             r"side must be one of .*"),
    "traction where": (lambda: Traction("north", 1.0), r"where must be one of"),
    "knots": (lambda: simulate(s1_scene(), Method(reconstruction="spline",
                                                  reconstruction_options={"knots": "cells"})),
              r"knots must be 'grid' or 'particles', got 'cells'"),
    "benchmark": (lambda: get_benchmark("sloshing"), r"unknown benchmark 'sloshing'; valid: vibrating-string"),
    "variant": (lambda: get_benchmark("soil-column", "huge"), r"variant must be one of \['large', 'small'\]"),
    # other constructor arguments
    "degree": (lambda: SplineGrid.line(0, 1, 4, 4), r"degree must be one of \(1, 2, 3\), got 4"),
    "cells": (lambda: SplineGrid.line(0, 1, 0, 2), r"cells must be a positive integer, got 0"),
    "interval": (lambda: SplineGrid.line(1, 0, 4, 2), r"a < b .*got a=1.0, b=0.0"),
    "damping": (lambda: Damping(1.5), r"alpha must be a number in \[0, 1\), got 1.5"),
    "body force": (lambda: BodyForce(3.0), r"BodyForce needs a callable b\(X, t\), got 3.0"),
    "component": (lambda: Fixed("left", component=3), r"component must be None or an integer in \[0, 2\], got 3"),
    "gravity type": (lambda: Gravity("down"), r"g must be a number .* got 'down'"),
    "t_end": (lambda: Scene(GRID, Body(particles(), LinearElastic(1.0)), -1.0), r"t_end must be finite and > 0"),
    "save_every": (lambda: simulate(s1_scene(), save_every=0), r"save_every must be a positive integer number of steps, got 0"),
    "benchmark parameter": (lambda: get_benchmark("soil-column", "large", E=-1.0), r"parameter E must be > 0"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_bad_input_is_named(case):
    make, message = CASES[case]
    with pytest.raises(ValueError, match=message):
        make()
