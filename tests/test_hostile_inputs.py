"""Hostile inputs through the API: every bad argument raises ValueError or
TypeError whose message names the argument (and, where the check makes it
possible, the value and what is valid), before any step runs.

The cases are generated: a list of bad values per argument of each public
constructor and function (wrong types, strings, None, NaN, Inf, complex,
zero, negative, non-integers, wrong shapes, out of range), plus the silent
or questionable inputs the hostile probe of issue 21 found (a 3-tuple
range, a fractional Gauss order, negative cell indices, complex positions,
runs of 1e148 steps, Fixed and Prescribed on one component, cfl above the
stable limit). Each case runs on the reference executor: nothing compiles.
"""
import re

import numpy as np
import pytest

from skfem_mpm import (Body, BodyForce, Damping, Fixed, Gravity, LinearElastic, Method,
                       NeoHookean, ParticleBasis, Particles, Prescribed, Scene, SplineGrid,
                       Traction, fem, simulate)

# each case is bounded (tests/conftest.py): one that hangs fails by its name
# instead of hanging the suite; the bound leaves room for a cold numba
# compile under load
pytestmark = pytest.mark.timeout(300)

NUMPY = Method(backend="numpy")
GENERIC_NUMBERS = [None, "a", "1", float("nan"), float("inf"), -float("inf"), 1j, [1.0, 2.0],
                   object()]


def g1():
    return SplineGrid.line(0.0, 1.0, 4, 2)


def g2():
    return SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (4, 4), 2)


def p1():
    return Particles.seed(g1(), 2, 1.0, region=((0.0, 0.75),))


def body1(material=None):
    return Body(p1(), material or LinearElastic(1.0))


def scene1(**kw):
    return Scene(g1(), body1(), 0.01, **kw)


def x2(n=2):
    return np.full((n, 1), 0.5)


CASES = []  # (id, callable, argument name in the message)


def case(name, arg, make):
    # no memory addresses in an id: every pytest process must collect the same ids
    name = re.sub(r" at 0x[0-9a-fA-F]+", "", name)
    CASES.append(pytest.param(make, arg, id=f"{name}-{len(CASES)}"))


def each(name, arg, values, make):
    for v in values:
        case(f"{name}={v!r}"[:60], arg, (lambda v=v: make(v)))


# ------------------------------------------------------------------ grids
each("line a", "a", GENERIC_NUMBERS, lambda v: SplineGrid.line(v, 1.0, 4, 2))
each("line b", "b|interval", GENERIC_NUMBERS + [0.0, -1.0], lambda v: SplineGrid.line(0.0, v, 4, 2))
each("line cells", "cells", [0, -1, 2.5, "4", None, True, float("nan"), [4]],
     lambda v: SplineGrid.line(0.0, 1.0, v, 2))
each("line degree", "degree", [0, -1, 2.5, "2", None, True, 99],
     lambda v: SplineGrid.line(0.0, 1.0, 4, v))
each("line tiny", "breakpoints", [1e-200, 1e-155, 1e-160], lambda v: SplineGrid.line(0.0, v, 4, 2))
each("line huge", "breakpoints", [1e200], lambda v: SplineGrid.line(0.0, v, 4, 2))
RANGES = [1.0, (0, 1, 5), (1, 0), (0, float("nan")), ("a", 1), None, "ab", (0,), (0, 1j)]
each("rectangle xlim", "xlim", RANGES, lambda v: SplineGrid.rectangle(v, (0, 1), (2, 2), 2))
each("rectangle ylim", "ylim", RANGES, lambda v: SplineGrid.rectangle((0, 1), v, (2, 2), 2))
CELLS2 = [2.0, (2,), (2, 2, 2), (0, 2), (2, -1), "2", None, (2.5, 2), True]
each("rectangle cells", "cells", CELLS2, lambda v: SplineGrid.rectangle((0, 1), (0, 1), v, 2))
each("rectangle degree", "degree", [0, 2.5, "2", None],
     lambda v: SplineGrid.rectangle((0, 1), (0, 1), 2, v))
each("box zlim", "zlim", RANGES[:5],
     lambda v: SplineGrid.box((0, 1), (0, 1), v, (2, 2, 2), 1))
each("box cells", "cells", [(2, 2), (0, 2, 2), 2.0, "2"],
     lambda v: SplineGrid.box((0, 1), (0, 1), (0, 1), v, 1))
each("SplineGrid breakpoints", "breakpoints",
     [[0.0], [1.0, 0.0], [0.0, float("nan"), 1.0], [[0.0, 1.0], [2.0]], [0.0, 0.5, 0.5, 1.0],
      "ab"], lambda v: SplineGrid(v, 2))
each("gauss_rule points", "points_per_axis", [0, -1, 2.7, "2", None, 1000, True],
     lambda v: g1().gauss_rule(v))
each("gauss_rule cells", "cells", [[99], [-1], [0.5], [[0]], ["a"], [4]],
     lambda v: g1().gauss_rule(2, cells=v))
each("locate x", "x", [np.array([[0.5, 0.5]]), np.array([[np.nan]]), np.array([[0.5j]]),
                       np.array([["a"]])], lambda v: g1().locate(v))

# -------------------------------------------------------------- particles
each("Particles x", "x", [np.full((2, 4), 0.5), np.array([[np.nan], [0.5]]),
                          np.array([[0.5 + 1j], [0.5]]), np.array([["a"], ["b"]]), None,
                          np.zeros((2, 1, 1)), "x"],
     lambda v: Particles(v, np.ones(2), np.ones(2)))
each("Particles m", "m", [-np.ones(2), np.zeros(2), np.full(2, np.nan), np.ones(3), "a",
                          None, np.ones(2) * 1j],
     lambda v: Particles(x2(), v, np.ones(2)))
each("Particles V", "V", [-np.ones(2), np.zeros(2), np.full(2, np.inf), np.ones(1), "a"],
     lambda v: Particles(x2(), np.ones(2), v))
each("Particles v", "v", [np.ones(3), np.ones((2, 2)), np.full((2, 1), np.nan), "a",
                          np.ones((2, 1)) * 1j],
     lambda v: Particles(x2(), np.ones(2), np.ones(2), v=v))
each("Particles X", "X", [np.ones(3), np.ones((2, 2)), np.full((2, 1), np.nan)],
     lambda v: Particles(x2(), np.ones(2), np.ones(2), X=v))
each("Particles stress", "stress", [np.ones((2, 2, 2)), np.ones(2), np.full((2, 1, 1), np.nan)],
     lambda v: Particles(x2(), np.ones(2), np.ones(2), stress=v))
each("Particles F", "F", [np.ones((2, 2, 2)), np.full((2, 1, 1), np.inf)],
     lambda v: Particles(x2(), np.ones(2), np.ones(2), F=v))
each("Particles body", "body", [np.ones(2) * 0.5, np.zeros(3, dtype=int), "a"],
     lambda v: Particles(x2(), np.ones(2), np.ones(2), body=v))
each("Particles state", "state", [5, {"x": np.ones(2)}, {"1bad": np.ones(2)},
                                  {"ok": np.ones(3)}, {"ok": np.full(2, np.nan)}, [1]],
     lambda v: Particles(x2(), np.ones(2), np.ones(2), state=v))
each("seed ppc", "ppc", [0, -1, 2.5, "2", None, (2, 2), True],
     lambda v: Particles.seed(g1(), v, 1.0))
each("seed density", "density", [0, -1, float("nan"), "a", None, 1j,
                                 lambda X: np.ones(3), lambda X: -np.ones(len(X)),
                                 lambda X: np.full(len(X), np.nan)],
     lambda v: Particles.seed(g1(), 2, v))
each("seed layout", "layout", ["hex", None, 1], lambda v: Particles.seed(g1(), 2, 1.0, layout=v))
each("seed region", "region", [(0.1, 0.1), ((2.0, 3.0),), "a", ((0.5, 0.1),),
                               lambda X: np.zeros(len(X), dtype=bool), ((0.0, 1.0), (0.0, 1.0))],
     lambda v: Particles.seed(g1(), 2, 1.0, region=v))
each("seed velocity", "velocity", [np.ones(3), lambda X: np.ones((len(X), 3)), "a",
                                   lambda X: np.full(len(X), np.nan)],
     lambda v: Particles.seed(g1(), 2, 1.0, velocity=v))
each("seed stress", "stress", [np.ones((2, 2)), lambda X: np.ones((len(X), 2, 2))],
     lambda v: Particles.seed(g1(), 2, 1.0, stress=v))
each("seed seed", "seed", [-1, 2.5, "a", True],
     lambda v: Particles.seed(g1(), 2, 1.0, layout="random", seed=v))
def _form_without_axis(values):
    from skfem import LinearForm, asm

    @LinearForm
    def load(v, w):
        return w["rho"] * v

    p = Particles.seed(g1(), 3, 1.0)  # 12 particles, 6 dofs (equal counts cannot be told apart)
    return asm(load, ParticleBasis(g1(), p), rho=values(p))


each("form data without the quadrature axis", r"trailing quadrature axis|dof vector",
     [lambda p: p.m / p.V, lambda p: np.ones(p.n + 1)], _form_without_axis)
each("ParticleBasis particles", "particles", [np.array([[0.5]]), None, "a", g1()],
     lambda v: ParticleBasis(g1(), v))

# -------------------------------------------------------------- materials
NUMBERS_POS = GENERIC_NUMBERS + [0.0, -1.0]
each("LinearElastic E", "E", NUMBERS_POS, lambda v: LinearElastic(v, 0.3))
each("LinearElastic nu", "nu", [0.5, -1.0, 0.7, float("nan"), "a", None, 1j],
     lambda v: LinearElastic(1.0, v))
each("NeoHookean E", "E", NUMBERS_POS[:6], lambda v: NeoHookean(v, 0.3))
each("NeoHookean nu", "nu", [0.5, -1.5, "a"], lambda v: NeoHookean(1.0, v))

# ---------------------------------------------------------------- effects
each("Gravity g", "g", [float("nan"), "a", None, (0.0, float("nan")), 1j, object()],
     lambda v: Gravity(v))
each("Gravity dim", "g", [(0.0, -1.0), (0.0, 0.0, -1.0)],
     lambda v: Scene(g1(), body1(), 0.01, effects=[Gravity(v)]))
each("BodyForce b", "BodyForce", [1.0, None, "a"], lambda v: BodyForce(v))
each("Fixed side", "side", ["north", 5, None, "top", "zmax"],
     lambda v: Scene(g1(), body1(), 0.01, effects=[Fixed(v)]))
each("Fixed component", "component", [5, -1, 1.5, "x", True],
     lambda v: Scene(g1(), body1(), 0.01, effects=[Fixed("left", v)]))
each("Prescribed velocity", "velocity", ["a", float("nan"), [1.0, 2.0], None,
                                         lambda t: np.ones(3), lambda t: "fast",
                                         lambda t: float("nan"), lambda t: 1j],
     lambda v: Scene(g1(), body1(), 0.01, effects=[Prescribed("left", 0, v)]))
each("Prescribed component", "component", [None, 3, -1, "0"],
     lambda v: Scene(g1(), body1(), 0.01, effects=[Prescribed("left", v, 1.0)]))
each("Traction where", "where.*(got|no particle)", ["north", 5, np.zeros(3, dtype=bool), np.ones(3),
                                      "top"],
     lambda v: Scene(g1(), body1(), 0.01, effects=[Traction(v, 1.0)]))
each("Traction tau", "tau", ["a", float("nan"), None, 1j],
     lambda v: Traction("right", v))
each("Traction depth", "depth", ["a", -1.0, 0.0, float("nan"), 1j],
     lambda v: Traction("right", 1.0, depth=v))
each("Damping alpha", "alpha", [-0.1, 1.5, "a", float("nan"), None],
     lambda v: Damping(v))

# ------------------------------------------------------------ body, scene
each("Body particles", "particles", [None, "a", np.ones((2, 1)), g1()],
     lambda v: Body(v, LinearElastic(1.0)))
each("Body material", "material", [None, "steel", 1.0, LinearElastic],
     lambda v: Body(p1(), v))
each("Scene grid", "grid", [None, "a", np.ones(3), 1.0], lambda v: Scene(v, body1(), 0.01))
each("Scene bodies", "bodies", [None, [], [1], "a", p1(), (p1(),)],
     lambda v: Scene(g1(), v, 0.01))
each("Scene t_end", "t_end", NUMBERS_POS, lambda v: Scene(g1(), body1(), v))
each("Scene effects", "effects", [Gravity(-1.0), "gravity", [1], [None], 5, [Gravity]],
     lambda v: Scene(g1(), body1(), 0.01, effects=v))
case("Scene dim", "2D|dim", lambda: Scene(g2(), body1(), 0.01))
EMPTY = Particles(np.zeros((0, 1)), np.zeros(0), np.zeros(0))  # e.g. a region that missed
case("Scene body without particles", r"bodies: body 0 has no particles \(n = 0\)",
     lambda: Scene(g1(), Body(EMPTY, LinearElastic(1.0)), 0.01))
case("Scene second body without particles", r"bodies: body 1 has no particles",
     lambda: Scene(g1(), [body1(), Body(EMPTY, LinearElastic(1.0))], 0.01))
case("Scene outside", "outside the grid",
     lambda: Scene(g1(), Body(Particles(np.array([[1.5]]), np.ones(1), np.ones(1)),
                              LinearElastic(1.0)), 0.01))

# ----------------------------------------------------------------- method
each("Method scheme", "scheme", ["leapfrog", None, 1, "MUSL"], lambda v: Method(scheme=v))
each("Method mass", "mass", ["diagonal", None, 0], lambda v: Method(mass=v))
each("Method reconstruction", "reconstruction", ["fft", None, 3], lambda v: Method(reconstruction=v))
each("Method dt", "dt", NUMBERS_POS[1:], lambda v: Method(dt=v))
each("Method cfl", "cfl", [v for v in NUMBERS_POS if v is not None],  # None: the scheme's default
     lambda v: Method(cfl=v))
each("Method allow_unstable", "allow_unstable", [1, "yes", None], lambda v: Method(allow_unstable=v))
each("Method on_exit", "on_exit", ["ignore", None], lambda v: Method(on_exit=v))
each("Method small_mass", "small_mass", [1.5, -0.1, "a", None, float("nan")],
     lambda v: Method(small_mass=v))
each("Method frequency_guard", "frequency_guard", [-1.0, float("inf"), "a", None],
     lambda v: Method(frequency_guard=v))
each("Method mass_solver", "mass_solver", ["gmres", None], lambda v: Method(mass_solver=v))
each("Method backend", "backend", ["cuda", 1], lambda v: Method(backend=v))
each("Method reconstruction_options", "reconstruction_options",
     [5, "penalty", [("penalty", 1.0)], {1: 2}, {"foo": 1}, {"radius": 2.0}],
     lambda v: Method(reconstruction="spline", reconstruction_options=v))
case("Method options without reconstruction", "reconstruction_options",
     lambda: Method(reconstruction_options={"penalty": 1.0}))
each("Method hybrid scheme", "hybrid", ["usl", "cd", "rk4"],
     lambda v: Method(scheme=v, mass="hybrid"))

# --------------------------------------------------------------- simulate
each("simulate scene", "Scene", [None, "a", 1.0], lambda v: simulate(v))
case("simulate grid", "Scene", lambda: simulate(g1()))
case("simulate body", "Scene", lambda: simulate(body1()))
each("simulate method", "method", ["musl", 1, {"scheme": "musl"}],
     lambda v: simulate(scene1(), v))
each("simulate save_every", "save_every", [0, -1, 2.5, "3", True],
     lambda v: simulate(scene1(), NUMPY, save_every=v))
each("simulate callback", "callback", [3, "f"], lambda v: simulate(scene1(), NUMPY, callback=v))
each("simulate checkpoint", "checkpoint", ["file.npz", (None, 1), ("f.npz",), 5,
                                           ("f.npz", 0), ("f.npz", 2.5), ("f.npz", "1"),
                                           ("/nonexistent-folder/run.npz", 1), ("/", 1),
                                           # os.access says yes to root there: tried
                                           ("/proc/run.npz", 1), ("/sys/run.npz", 1)],
     lambda v: simulate(scene1(), NUMPY, checkpoint=v))
each("simulate restart", "restart|checkpoint", [123, 1.5, ["a"], "/nonexistent.npz", "/"],
     lambda v: simulate(scene1(), NUMPY, restart=v))
each("fem scene", "Scene", [None, "a"], lambda v: fem(v))
each("fem method", "method", ["musl", 1], lambda v: fem(scene1(), v))

# --------------------------------------- questionable runs, refused at start
case("cfl above 1", r"cfl = 1\.5", lambda: simulate(scene1(), Method(backend="numpy", cfl=1.5)))
case("cfl 3", r"cfl = 3", lambda: simulate(scene1(), Method(backend="numpy", cfl=3.0)))
case("cfl above 1 rk4", r"cfl = 1\.2",
     lambda: simulate(scene1(), Method(backend="numpy", cfl=1.2, scheme="rk4")))
case("dt above dt_crit", "dt = ", lambda: simulate(scene1(), Method(backend="numpy", dt=1.0)))
case("V = 1e300", "steps", lambda: simulate(
    Scene(g1(), Body(Particles(x2(1), np.ones(1), np.full(1, 1e300)), LinearElastic(1.0)),
          1.0), NUMPY))
case("E = 1e300", "steps", lambda: simulate(Scene(g1(), body1(LinearElastic(1e300)), 1.0),
                                            NUMPY))
case("t_end 1e300", "steps", lambda: simulate(Scene(g1(), body1(), 1e300), NUMPY))
case("m = 1e308 in a small volume", "time step dt", lambda: simulate(
    Scene(g1(), Body(Particles(x2(1), np.full(1, 1e308), np.full(1, 1e-10)),
                     LinearElastic(1.0)), 1.0), NUMPY))
for effects in ([Fixed("left"), Prescribed("left", 0, 1.0)],
                [Prescribed("left", 0, 1.0), Fixed("left")],
                [Prescribed("left", 0, 1.0), Prescribed("left", 0, 2.0)],
                [Fixed("left", 0), Prescribed("left", 0, lambda t: t)]):
    case("fixed and prescribed", "component 0",
         lambda effects=effects: simulate(Scene(g1(), body1(), 0.01, effects=effects), NUMPY))


@pytest.mark.parametrize("make, argument", CASES)
def test_a_bad_input_raises_a_clear_error_naming_the_argument(make, argument):
    with pytest.raises((ValueError, TypeError), match=argument):
        make()


def test_the_probe_counts_at_least_as_many_cases_as_the_issue():
    assert len(CASES) >= 243, len(CASES)


def test_good_inputs_next_to_the_bad_ones_still_run():
    """The checks refuse nothing that is valid: integers for floats, numpy
    scalars, (n,) arrays in 1D, a Prescribed constant, options by name."""
    grid = SplineGrid.line(np.float64(0.0), 1, np.int64(4), 2)
    p = Particles(np.array([0.25, 0.5]), np.ones(2), np.ones(2) * 0.1, v=np.zeros(2))
    scene = Scene(grid, Body(p, LinearElastic(np.float32(1.0), 0)), 0.01,
                  effects=(Gravity(-1), Prescribed("left", 0, 0), Damping(0.1)))
    r = simulate(scene, Method(backend="numpy", reconstruction="spline",
                               reconstruction_options={"penalty": 1e-6}), save_every=1)
    assert np.isfinite(r.particles.x).all()
    assert grid.gauss_rule(np.int64(2), cells=np.array([0, 3]))[0].shape == (4, 1)
    SplineGrid.rectangle([0, 1], np.array([0.0, 2.0]), [2, 3], 1)
