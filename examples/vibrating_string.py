"""S1 by hand, as a scikit-fem user writes it: a string fixed at both ends
with an initial velocity, solved with quadratic B-spline MPM and with FEM on
the same spline space, both compared with the exact solution.

    python examples/vibrating_string.py
"""
import numpy as np

from skfem_mpm import (Body, Fixed, LinearElastic, Method, Particles, Scene, SplineGrid, fem,
                       simulate)


def main(cells=32, degree=2):
    L, E, rho = 1.0, 100.0, 1.0
    c = np.sqrt(E / rho)
    w = np.pi * c / L
    v0 = 1e-6 * c  # peak strain 1e-6: the linear solution is exact enough
    grid = SplineGrid.line(0.0, L, cells, degree)
    particles = Particles.seed(grid, ppc=4, density=rho,
                               velocity=lambda X: v0 * np.sin(np.pi * X / L))
    scene = Scene(grid, Body(particles, LinearElastic(E)), t_end=np.pi / (2 * w),
                  effects=[Fixed("left"), Fixed("right")])
    errors = {}
    for name, run in (("mpm", simulate), ("fem", fem)):
        result = run(scene, Method(mass="consistent", scheme="cd", cfl=0.1))
        X, u = result.history["X"][-1], result.history["u"][-1]
        exact = v0 / w * np.sin(w * result.times[-1]) * np.sin(np.pi * X / L)
        errors[name] = float(np.sqrt(np.mean((u - exact) ** 2)) / (v0 / w))
        print(f"{name}: relative RMS error {errors[name]:.3e}, {result.counts['steps']} steps, "
              f"{result.wall_time:.3f} s")
    return errors


if __name__ == "__main__":
    main()
