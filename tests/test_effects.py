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
