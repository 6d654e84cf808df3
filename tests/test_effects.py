"""The effect protocol: what a bound particle force keeps about particles
follows removals and restarts."""
import numpy as np

from skfem_mpm import Gravity, Particles, SplineGrid, Traction
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
