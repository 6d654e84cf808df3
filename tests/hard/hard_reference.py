"""Same-model references for the large-deformation hard cases.

The project's ``LinearElastic`` is hypoelastic and updated Lagrangian: in 1D
the Cauchy stress grows by E dx/x, so sigma = E ln F (Hencky), and the volume
follows the motion. At a 10% strain this model differs from the linear wave
equation of BENCHMARKS.md S2 by a few percent of the displacement, more than
any discretisation error of the methods under test. The grid-crossing tests
therefore measure the discretisation error against a fine Gauss-quadrature
FEM solution (total Lagrangian, cubic B-splines, consistent mass, central
differences) of the same model, P = E ln F (``Hencky1D``, shared with the
studies' same-model reference, ``skfem_mpm.model_reference``), and report
the linear-exact error beside it.
"""
import numpy as np
from scipy.interpolate import CubicSpline

from skfem_mpm import Body, Method, Scene, fem
from skfem_mpm.model_reference import Hencky1D


class ModelReference:
    """u(X, t) of the same model from a fine FEM run, saved ``saves`` times;
    evaluate only at those times (cubic interpolation in X)."""

    def __init__(self, benchmark, cells=160, degree=3, saves=40, steps_per_save=400):
        scene = benchmark.scene(cells, degree, 4, fem=True)
        body = Body(scene.bodies[0].particles, Hencky1D(benchmark.E))
        scene = Scene(scene.grid, body, benchmark.t_end, scene.effects)
        steps = saves * steps_per_save
        self.result = fem(scene, Method(mass="consistent", scheme="cd",
                                        dt=benchmark.t_end / steps), save_every=steps_per_save)
        self.times = self.result.times
        self.amplitude = benchmark.amplitude

    def displacement(self, X, t):
        k = int(np.argmin(np.abs(self.times - t)))
        if abs(self.times[k] - t) > 1e-9 * max(1.0, abs(t)):
            raise ValueError(f"no reference save at t = {t}")
        h = self.result.history
        X_ref, u_ref = h["X"][k][:, 0], h["u"][k][:, 0]
        order = np.argsort(X_ref)
        X_ref, keep = np.unique(X_ref[order], return_index=True)
        return CubicSpline(X_ref, u_ref[order][keep])(np.asarray(X)[:, 0])

    def error_max(self, result):
        """max over saves of the RMS displacement error, relative to the
        largest exact displacement (the project's error measure)."""
        h = result.history
        errs = [np.sqrt(np.mean((h["u"][k][:, 0] - self.displacement(h["X"][k], t)) ** 2))
                for k, t in enumerate(result.times)]
        return float(max(errs)) / self.amplitude


def run_saved_like(benchmark, scene, method, saves=40):
    """simulate with a step that puts ``saves`` saves exactly on the
    reference's times (dt <= the method's own choice)."""
    from skfem_mpm import simulate
    from skfem_mpm.solve import prepare

    need = prepare(scene, method).n_steps
    steps = saves * int(np.ceil(need / saves))
    kw = {k: getattr(method, k) for k in ("scheme", "mass", "reconstruction")}
    return simulate(scene, Method(dt=benchmark.t_end / steps, **kw), save_every=steps // saves)


def largest_stress_jump(result):
    """max |sigma_{p+1} - sigma_p| over neighbouring particles sorted by x (1D)."""
    x = result.particles.x[:, 0]
    s = result.particles.stress[np.argsort(x), 0, 0]
    return float(np.abs(np.diff(s)).max())
