"""The effect protocol: what a bound particle force keeps about particles
follows removals and restarts."""
import numpy as np
import pytest

from skfem_mpm import (Body, Gravity, Method, NeoHookean, Particles, Scene, SplineGrid, Traction,
                       simulate)
from skfem_mpm.effects import Damping, Fixed


def test_side_traction_follows_particle_removal_and_checkpoints():
    grid = SplineGrid.rectangle((0, 1), (0, 1), 4, 2)
    particles = Particles.seed(grid, 2, 1.0, region=((0.0, 0.5), (0.0, 1.0)))
    force, = Traction("right", (1.0, 0.0)).bind(particles, grid)
    loaded = force.index.copy()
    assert loaded.size == 8
    size, share = force.size.copy(), force.share.copy()
    keep = np.ones(particles.n, dtype=bool)
    keep[loaded[[1, 5]]] = False  # two loaded particles leave
    force.rebind(keep)
    survivors = np.flatnonzero(keep[loaded])
    new_position = np.cumsum(keep) - 1
    assert np.array_equal(force.index, new_position[loaded[survivors]])
    assert np.array_equal(force.size, size[survivors])
    assert np.array_equal(force.share, share[survivors])
    fresh, = Traction("right", (1.0, 0.0)).bind(particles, grid)
    fresh.restore(force.checkpoint_arrays())
    for name in ("index", "size", "share"):
        assert np.array_equal(getattr(fresh, name), getattr(force, name))


def test_effects_contribute_only_their_own_part():
    grid = SplineGrid.line(0.0, 1.0, 4, 2)
    particles = Particles.seed(grid, 2, 1.0)
    gravity = Gravity(-9.81)
    gravity.check(grid)
    assert gravity.bind(particles, grid) == [gravity] and gravity.acceleration[0] == -9.81
    assert gravity.constraints(grid) == [] and gravity.force_modifiers() == []
    fixed = Fixed("left")
    assert fixed.bind(particles, grid) == [] and len(fixed.constraints(grid)) == 1
    damping = Damping(0.1)
    assert damping.force_modifiers() == [damping] and damping.bind(particles, grid) == []
    f = damping.modify_force(np.array([[2.0]]), np.array([[1.0]]))
    assert f[0, 0] == 2.0 - 0.1 * 2.0


def test_a_1d_side_traction_loads_the_body_end_once_when_it_ends_inside_a_cell():
    """The body [0, 1] ends inside a cell of the grid (13 cells on [0, 1.6]):
    the particles of the cut cell are smaller than their neighbours, and
    the last full-size particle's face lies within half its size of the
    end. Only the end particle carries the load (total force tau, at the
    body's end); the rule 'within half its own size of the edge' loaded
    both, doubling the force."""
    grid = SplineGrid.line(0.0, 1.6, 13, 2)
    particles = Particles.seed(grid, 2, 1.0, region=((0.0, 1.0),))
    force, = Traction("right", 1.0).bind(particles, grid)
    assert force.index.tolist() == [int(np.argmax(particles.X[:, 0]))]
    assert force.share.sum() == 1.0
    assert force.points(particles)[0, 0] == 1.0


@pytest.mark.xfail(strict=True, reason=(
    "SurfaceTraction takes V0^(1/dim) as a particle's extent along the normal: with "
    "particles that are not squares (cells of aspect 2, a body ending inside a column of "
    "cells) the face area V0 / V0^(1/2) and the face position are wrong (measured: total "
    "force 1.41 and 0.77 of tau x side length); particles carry no per-axis extent to "
    "fix it with"))
@pytest.mark.parametrize("cells, right", [((4, 4), 1.5), ((8, 4), 1.4)])
def test_a_2d_side_traction_gives_tau_times_the_side_length(cells, right):
    grid = SplineGrid.rectangle((0.0, 2.0), (0.0, 1.0), cells, 2)
    particles = Particles.seed(grid, 2, 1.0, region=((0.0, right), (0.0, 1.0)))
    force, = Traction("right", (1.0, 0.0)).bind(particles, grid)
    assert abs(force.share.sum() - 1.0) < 1e-12
    assert np.allclose(force.points(particles)[:, 0], right, rtol=0, atol=1e-12)


def static_stretch_neo_hookean_1d(tau, E):
    """The stretch of a 1D neo-Hookean bar (lambda = 0, mu = E / 2) under a
    dead load tau per unit reference cross-section: P(s) = mu (s - 1/s) =
    tau, i.e. s^2 - (tau / mu) s - 1 = 0, s = (t + sqrt(t^2 + 4)) / 2 with
    t = tau / mu (the positive root)."""
    t = tau / (E / 2)
    return 0.5 * (t + np.sqrt(t * t + 4.0))


def pulled_bar(cells, tau, E=1.0, ramp=10.0, t_end=25.0):
    """A neo-Hookean bar on [0, 1] (rho = 1, c = 1) fixed at x = 0, pulled
    at x = 1 by a traction ramped to tau over ``ramp``, damped to rest
    (local damping 0.3), on a grid reaching to 1.6 (the body ends inside a
    cell)."""
    grid = SplineGrid.line(0.0, 1.6, int(round(1.6 * cells)), 2)
    particles = Particles.seed(grid, 2, 1.0, region=((0.0, 1.0),))
    effects = [Fixed("left"), Traction("right", lambda t: tau * min(t / ramp, 1.0)),
               Damping(0.3)]
    scene = Scene(grid, Body(particles, NeoHookean(E)), t_end, effects=effects)
    return simulate(scene, Method(reconstruction="spline"), save_every=100)


def test_large_strain_side_traction_reaches_the_static_stretch():
    """A bar pulled to 25% strain by a dead load comes to rest at the
    closed-form stretch s with P(s) = tau (:func:`static_stretch_neo_hookean_1d`):
    homogeneous, every particle at V / V0 = s, the end at x = s L.

    Face stretch: the traction acts on the body's moving end, the outer
    face of the end particle, at x_p + (s_p / 2) (V_p / V0_p)^(1/dim) (in
    1D x_p + V_p / 2): its reference half size s_p / 2 stretched with the
    particle. A face taken at x_p + s_p / 2 (the reference size, the face
    stretch ignored) lies (s - 1) s_p / 2 inside the body: the load acts
    on a point the end particle's own stress does not reach, the grid
    forces tau N_i(face) no longer balance the internal forces of the
    homogeneous state, and the bar settles with the end particles' strain
    off by 2-10% whatever the grid (measured: 2.3% in V / V0 and 10% in
    the end stress at 8 and at 16 cells). With the face where it is, the
    error converges (measured: V / V0 to 1.4e-3 at 8 cells, 4.4e-4 at 16;
    end stress 0.6%, 0.06%).

    The spline reconstruction integrates the internal force over the
    body exactly for a homogeneous stress; with particle quadrature the
    static state of a stretched bar carries a 20-30% stress ripple of
    its own (cell crossing) that would hide the face."""
    E, tau = 1.0, 0.225  # mu = 0.5: s = 1.25
    s = static_stretch_neo_hookean_1d(tau, E)
    assert abs(0.5 * E * (s - 1 / s) - tau) < 1e-15 and abs(s - 1.25) < 1e-14
    errors = []
    for cells in (8, 16):
        r = pulled_bar(cells, tau, E)
        p = r.particles
        end = int(np.argmax(p.x[:, 0]))
        assert r.energies["kinetic"][-1] < 1e-5 * r.energies["strain"][-1]  # at rest
        assert abs(p.x[end, 0] + 0.5 * p.V[end] - s) < 1e-3 * (s - 1)  # the end at s L
        errors.append(np.abs(p.V / p.V0 / s - 1).max())
        assert errors[-1] < 5e-3, (cells, errors[-1])
        assert abs(p.stress[end, 0, 0] / tau - 1) < 0.03, (cells, p.stress[end, 0, 0] / tau)
    assert errors[1] < errors[0] / 2, errors


def test_a_constant_traction_is_that_constant_at_every_time():
    """A number or vector given as tau is the traction at every time (the
    constant's own default argument once made it read as tau(x, t), so the
    traction was the time t)."""
    assert Traction("right", 5.0).traction(None, 0.25) == 5.0
    assert np.array_equal(Traction("zmax", (0.0, 0.0, -1.0)).traction(np.zeros((4, 3)), 0.7),
                          [0.0, 0.0, -1.0])
