"""Wall(side, friction=mu): a rigid frictional wall on the grid side's
dofs. A block sliding on a frictional floor loses tangential momentum at
exactly mu times the normal impulse (so decelerates at mu g on average), a
block on an incline sticks below the friction angle and slides above it,
and both executors agree."""
import numpy as np
import pytest

from skfem_mpm import Body, Gravity, LinearElastic, Method, Particles, Scene, SplineGrid, Wall
from skfem_mpm import simulate

G, RHO, H, NU = 9.81, 1.0, 0.5, 0.3


def block_on_floor(theta=0.0, v0=1.0, mu=0.3, t_end=0.2):
    """A 1 x 0.5 elastic block on a Wall("bottom") floor, gravity tilted by
    theta degrees (an incline), started in its elastic K0 state."""
    grid = SplineGrid.rectangle((0.0, 4.0), (0.0, 1.0), (16, 4), 2)
    gx, gy = G * np.sin(np.radians(theta)), -G * np.cos(np.radians(theta))

    def stress(X):
        s = np.zeros((len(X), 2, 2))
        s[:, 1, 1] = RHO * gy * (H - X[:, 1])
        s[:, 0, 0] = NU / (1 - NU) * s[:, 1, 1]
        return s

    particles = Particles.seed(grid, 2, RHO, region=((0.5, 1.5), (0.0, H)), stress=stress,
                               velocity=lambda X: np.column_stack((v0 + 0 * X[:, 0],
                                                                  0 * X[:, 0])))
    return Scene(grid, Body(particles, LinearElastic(1e4, NU)), t_end,
                 effects=[Gravity((gx, gy)), Wall("bottom", friction=mu)])


def momentum(result):
    m = result.particles.m
    return np.array([m @ v for v in result.history["v"]]) / m.sum()  # per unit mass


@pytest.mark.parametrize("backend", ["numpy", "numba"])
def test_a_sliding_block_decelerates_at_mu_g(backend):
    """While every contact node slides, each step's tangential impulse is mu
    times the normal one: P_x(t) - P_x(0) = -mu (P_y(t) - P_y(0) + M g t)
    (per unit mass) to 1e-12 over the first 10 saves (later the light nodes
    at the block's ends stick now and then: 1e-3); the mean deceleration is
    mu g within 5% (the normal force oscillates about the weight)."""
    mu = 0.3
    result = simulate(block_on_floor(mu=mu), Method(backend=backend), save_every=5)
    P, t = momentum(result), result.times
    balance = np.abs(P[:, 0] - 1.0 + mu * (P[:, 1] + G * t))
    assert balance[:10].max() <= 1e-12 and balance.max() <= 1e-3
    decel = (P[0, 0] - P[-1, 0]) / (t[-1] - t[0])
    assert abs(decel / (mu * G) - 1) <= 0.05
    assert P[-1, 0] > 0.3  # still sliding


@pytest.mark.parametrize("theta, sticks", [(10.0, True), (25.0, False)])
def test_a_block_on_an_incline_sticks_below_the_friction_angle(theta, sticks):
    """mu = tan 17.7 deg: at 10 deg the block stays at rest (its velocity
    below 3% of the frictionless g sin(theta) t: the elastic block
    oscillates about rest); at
    25 deg it slides with the acceleration g (sin theta - mu cos theta)
    (within 5%; measured 2%)."""
    mu = np.tan(np.radians(17.7))
    result = simulate(block_on_floor(theta, v0=0.0, mu=mu, t_end=0.3), Method(backend="numba"),
                      save_every=5)
    P, t = momentum(result), result.times
    if sticks:
        assert np.abs(P[:, 0]).max() <= 0.03 * G * np.sin(np.radians(theta)) * t[-1]
    else:
        exact = G * (np.sin(np.radians(theta)) - mu * np.cos(np.radians(theta)))
        assert abs(P[-1, 0] / (exact * t[-1]) - 1) <= 0.05


def test_both_executors_agree_and_a_smooth_wall_keeps_the_momentum():
    """Reference and compiled paths (the compiled loop) to 1e-12; friction
    0: P_x constant; Result.reactions carries the wall's force (normal
    about the weight)."""
    scene = block_on_floor(t_end=0.05)
    ref = simulate(scene, Method(backend="numpy"), save_every=5)
    fast = simulate(scene, Method(backend="numba"), save_every=5)
    assert fast.path == "fast (compiled loop)"
    for key in ("x", "v", "stress"):
        a, b = ref.history[key], fast.history[key]
        assert np.abs(a - b).max() <= 1e-12 * np.abs(a).max(), key
    smooth = simulate(block_on_floor(mu=0.0, t_end=0.05), Method(backend="numba"), save_every=5)
    assert np.abs(momentum(smooth)[:, 0] - 1.0).max() <= 1e-12
    reaction = fast.reactions[-1]["Wall('bottom', friction=0.3)"]
    weight = fast.particles.m.sum() * G
    assert abs(reaction[1] / weight - 1) < 0.5
    assert abs(reaction[0] + 0.3 * reaction[1]) < 1e-9 * weight


def test_bad_walls_raise():
    with pytest.raises(ValueError, match="friction must be a finite number >= 0"):
        Wall("bottom", friction=-0.1)
    with pytest.raises(ValueError, match="side must be one of"):
        Wall("floor")


def test_the_contact_rule_on_single_nodes():
    """Both forms of the rule on a floor (n = (0, -1)), mu = 0.3, m = 2,
    dt = 0.1: sliding (v* = (1, -0.5): the normal part removed, the
    tangential reduced by mu d_n = 0.15), sticking (v* = (0.1, -0.5):
    stops), separating (v* = (1, 0.5): unchanged), an empty node
    (unchanged)."""
    grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (1, 1), 1)  # dofs 0, 1 on the floor
    wall = Wall("bottom", friction=0.3)
    wall.check(grid)
    cases = [((1.0, -0.5), 2.0, (0.85, 0.0)), ((0.1, -0.5), 2.0, (0.0, 0.0)),
             ((1.0, 0.5), 2.0, (1.0, 0.5)), ((1.0, -0.5), 0.0, (1.0, -0.5))]
    for v_star, m, expected in cases:
        v = np.zeros((4, 2))
        v[[0, 1]] = v_star
        mass = np.array([m, m, 1.0, 1.0])
        assert np.allclose(wall.modify_velocity(v, mass)[[0, 1]], expected, atol=1e-15)
        if m > 0:  # the force form: v* = v + dt f / m from v = 0
            force = v * m / 0.1
            new = wall.modify_force(force, np.zeros((4, 2)), mass, 0.1)
            assert np.allclose(0.1 * new[[0, 1]] / m, expected, atol=1e-14)
            assert np.allclose(wall.reaction, 2 * m / 0.1 * (np.array(expected) - v_star))


def thin_layer(rows, spacing, mu=0.5, g=10.0, v0=1.0, cells=16):
    """``rows`` rows of particles (half a cell apart, the lowest a quarter
    of a cell above the floor), one every ``spacing`` cells along x, each
    half a cell wide, sliding at v0 on a Wall("bottom", friction=mu) of
    quadratic B-splines with open knot vectors: only the first row of
    functions is non-zero at the floor, while a particle in the first cell
    also moves with the next two rows."""
    h = 1.0 / cells
    grid = SplineGrid.rectangle((0.0, 3.0), (0.0, 6 * h), (3 * cells, 6), 2)
    x = np.array([[0.5 + (k + 0.5) * spacing * h, (0.25 + 0.5 * j) * h]
                  for k in range(int(8 / spacing)) for j in range(rows)])
    V = np.full(len(x), 0.25 * h * h)
    particles = Particles(x, RHO * V, V, v=np.tile([v0, 0.0], (len(x), 1)))
    return Scene(grid, Body(particles, LinearElastic(1e5, NU)), 0.8 * v0 / (mu * g),
                 effects=[Gravity((0.0, -g)), Wall("bottom", friction=mu)])


@pytest.mark.parametrize("rows, spacing, cfl", [(1, 0.5, 0.25), (2, 0.5, 0.5), (1, 4.0, 0.5)],
                         ids=["one-row-layer", "one-cell-layer", "isolated-grains"])
def test_a_thin_layer_and_isolated_grains_decelerate_at_mu_g(rows, spacing, cfl):
    """A layer of one particle row (half a cell thick), of two rows (one
    cell) and grains four cells apart (no two share a function): the mean
    velocity falls linearly at mu g (slope within 1%; measured 0.0-0.2%),
    although the wall acts on the first row of functions only. The one-row
    layer at cfl 0.25: at the default 0.5 it decelerates at 1.052 mu g
    (both executors) while it lifts off the floor by 0.05 h, which it does
    not on a smooth wall nor at cfl 0.25 (the step is too long for the
    shear of a layer whose second and third rows of functions hold 41% and
    3% of its mass)."""
    mu, g = 0.5, 10.0
    result = simulate(thin_layer(rows, spacing, mu, g), Method(cfl=cfl), save_every=50)
    t = result.times
    v = momentum(result)[:, 0]
    keep = (t > 0.1 * t[-1]) & (t < 0.9 * t[-1])
    slope = np.polyfit(t[keep], v[keep], 1)[0]
    assert abs(-slope / (mu * g) - 1) <= 0.01
