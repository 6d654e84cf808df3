"""The ParaView series carries what a person inspects: per particle mass,
volume, density and body id; on the grid, the nodal mass and velocity of
every save."""
import numpy as np

from skfem_mpm import (
    Body,
    Fixed,
    LinearElastic,
    Method,
    Particles,
    Scene,
    SplineGrid,
    simulate,
)
from skfem_mpm.solve import prepare


def _two_bodies():
    grid = SplineGrid.rectangle((0, 1), (0, 1), 4, degree=2)
    left = Particles.seed(grid, 2, density=2.0, region=lambda x: x[:, 0] < 0.5,
                          velocity=lambda X: np.column_stack((0.1 * X[:, 1], 0 * X[:, 0])))
    right = Particles.seed(grid, 2, density=3.0, region=lambda x: x[:, 0] > 0.5,
                           velocity=lambda X: np.column_stack((0 * X[:, 0], -0.1 * X[:, 0])))
    bodies = [Body(left, LinearElastic(100.0, 0.3)), Body(right, LinearElastic(50.0, 0.2))]
    return Scene(grid, bodies, 0.01, effects=[Fixed("bottom")])


def test_particles_and_grid_series_carry_mass_volume_density_body_and_nodal_fields(tmp_path):
    import meshio

    scene = _two_bodies()
    result = simulate(scene, Method(), save_every=max(1, prepare(scene, Method()).n_steps // 3))
    pvd = result.save(tmp_path / "out")
    saves = len(result.times)
    assert saves >= 3 and pvd.read_text().count("<DataSet") == saves
    grid_pvd = (tmp_path / "out" / "grid.pvd").read_text()
    assert grid_pvd.count("<DataSet") == saves
    for k in (0, saves - 1):
        particles = meshio.read(tmp_path / "out" / f"particles_{k:04d}.vtu")
        data = particles.point_data
        m, V = data["mass"], data["volume"]
        left = particles.points[:, 0] < 0.5
        np.testing.assert_allclose(data["density"], m / V)
        rtol = 1e-12 if k == 0 else 2e-2  # the bodies deform a little
        np.testing.assert_allclose(data["density"][left], 2.0, rtol=rtol)
        np.testing.assert_allclose(data["density"][~left], 3.0, rtol=rtol)
        assert set(data["body"][left]) == {0.0} and set(data["body"][~left]) == {1.0}
        np.testing.assert_allclose(V, result.history["V"][k])
        grid = meshio.read(tmp_path / "out" / f"grid_{k:04d}.vtu")
        nodal_m, nodal_v = grid.point_data["nodal_mass"], grid.point_data["nodal_velocity"]
        assert grid.points.shape[0] == result.grid.ndofs
        # partition of unity: the grid holds the particles' mass and momentum
        np.testing.assert_allclose(nodal_m.sum(), m.sum(), rtol=1e-12)
        momentum = (m[:, None] * data["velocity"]).sum(axis=0)
        np.testing.assert_allclose((nodal_m[:, None] * nodal_v).sum(axis=0), momentum,
                                   rtol=1e-10, atol=1e-15)
    # the velocity moves: the series are per save, not one state repeated
    first = meshio.read(tmp_path / "out" / "grid_0000.vtu").point_data["nodal_velocity"]
    last = meshio.read(tmp_path / "out" / f"grid_{saves - 1:04d}.vtu")
    assert np.abs(first - last.point_data["nodal_velocity"]).max() > 1e-4
