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
