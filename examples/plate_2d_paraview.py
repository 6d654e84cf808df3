"""A 2D vibrating plate (D2) with sliding walls, saved as a ParaView series.

    python examples/plate_2d_paraview.py   # then open plate-output/particles.pvd
"""
import numpy as np

from skfem_mpm import (Body, Fixed, LinearElastic, Method, Particles, Scene, SplineGrid,
                       simulate)


def main(cells=8, out="plate-output"):
    E, nu, rho, A = 100.0, 0.3, 1.0, 1e-3
    lam, mu = E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))
    w = np.pi * np.sqrt(2 * (lam + 2 * mu) / rho)
    grid = SplineGrid.rectangle((0, 1), (0, 1), cells, degree=2)
    shape = lambda X: np.column_stack((np.sin(np.pi * X[:, 0]) * np.cos(np.pi * X[:, 1]),
                                       np.cos(np.pi * X[:, 0]) * np.sin(np.pi * X[:, 1])))
    particles = Particles.seed(grid, ppc=2, density=rho, velocity=lambda X: A * w * shape(X))
    walls = [Fixed("left", 0), Fixed("right", 0), Fixed("bottom", 1), Fixed("top", 1)]
    scene = Scene(grid, Body(particles, LinearElastic(E, nu)), np.pi / (2 * w), effects=walls)
    result = simulate(scene, Method(mass="consistent"), save_every=4)
    pvd = result.save(out)
    u = result.history["u"][-1]
    exact = A * np.sin(w * result.times[-1]) * shape(result.history["X"][-1])
    error = float(np.sqrt(np.mean(np.sum((u - exact) ** 2, axis=1))) / A)
    print(f"relative RMS error {error:.3e}; ParaView series: {pvd}")
    return error, pvd


if __name__ == "__main__":
    main()
