"""Same-model references: what a study compares with when a benchmark's
exact solution is not its model's.

The project's ``LinearElastic`` is hypoelastic and updated Lagrangian. In
1D the Cauchy stress then grows by E dx/x, so

    sigma = E ln F        (Hencky; F = 1 + du/dX),

and at a large strain this model leaves the linear wave equation, whose
solution is the benchmark's exact one: S2 ``large`` (10% strain) by about
15% of the amplitude, S3 ``large`` (2.4%) by 0.88% (max over time). Against
that solution every method's error stops there however fine the grid: a
flat line that measures the model, not the method.

The reference here is a fine Gauss-quadrature FEM solution of the same
model (``fem`` with :class:`Hencky1D`: total Lagrangian, P = E ln F, cubic
B-splines on 160 cells, consistent mass, central differences at 8,000 steps
per period, ``Benchmark.period``), saved every 50 steps. It is computed once per
benchmark, variant and parameter set and kept in the user's cache
directory (``$XDG_CACHE_HOME/skfem_mpm/references`` or
``~/.cache/skfem_mpm/references``). Between its saves it is interpolated:

    in X: a cubic spline through the saved points and the fixed base u = 0;
    in t: cubic Hermite with the saved u and v at the two bracketing saves,
          u(t) = h00(s) u_k + h10(s) D v_k + h01(s) u_k+1 + h11(s) D v_k+1,
          s = (t - t_k) / D, h00 = 2s^3 - 3s^2 + 1, h10 = s^3 - 2s^2 + s,
          h01 = 3s^2 - 2s^3, h11 = s^3 - s^2 (error O(D^4));

its velocity is the time derivative of that interpolant and its stress
E ln(1 + du/dX). The same construction at 40 saves without time
interpolation is the reference of ``tests/hard/test_grid_crossing.py``.
"""
import hashlib
import json
import os

import numpy as np

from .materials import LinearElastic, Material

__all__ = ["REFERENCE_SETTINGS", "Hencky1D", "ModelReference", "model_reference",
           "reference_path"]

#: how the same-model reference is computed (part of its cache key)
REFERENCE_SETTINGS = {"cells": 160, "degree": 3, "ppc": 4, "steps_per_period": 8000,
                      "save_every": 50, "format": 1}


class Hencky1D(Material):
    """Uniaxial log-strain elasticity, P = sigma = E ln F (1D, finite
    strain): the model the hypoelastic ``LinearElastic`` integrates in 1D."""

    finite_strain = True

    def __init__(self, E):
        self.E = float(E)

    def check_dim(self, dim):
        if dim != 1:
            raise ValueError(f"Hencky1D is a 1D model, got dim={dim}")

    def first_piola(self, F):
        return self.E * np.log(F)

    def cauchy_stress(self, F):
        return self.E * np.log(F)

    def update(self, p, L, dt):
        F = (1.0 + dt * L) * p.F
        return self.E * np.log(F), p.V0 * F[:, 0, 0], F

    def wave_speed(self, p):
        F = p.F[:, 0, 0] if p.F is not None else np.ones(p.n)
        return float(np.sqrt(self.E / F.min() / (p.m / p.V0).min()))

    def strain_energy(self, p):
        F = p.F[:, 0, 0] if p.F is not None else np.ones(p.n)
        return float(np.sum(0.5 * self.E * np.log(F) ** 2 * p.V0))


def _applies(bench):
    """A 1D benchmark variant whose exact solution is not its model's (its
    ``model_gaps`` entry), with one linear elastic body fixed at x = 0."""
    return bench.dim == 1 and bench.has_exact and bench.variant in bench.model_gaps


def _cache_directory():
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "skfem_mpm", "references")


def reference_path(bench, settings=None):
    """Where the reference of ``bench`` (its name, variant and every
    parameter, the settings and the package version) is cached."""
    from . import __version__

    settings = REFERENCE_SETTINGS if settings is None else settings
    key = json.dumps({"benchmark": bench.name, "variant": bench.variant,
                      "params": {k: bench.params[k] for k in sorted(bench.params)},
                      "t_end": bench.t_end, "settings": settings, "version": __version__},
                     sort_keys=True, default=float)
    digest = hashlib.sha256(key.encode()).hexdigest()[:16]
    return os.path.join(_cache_directory(), f"{bench.name}-{bench.variant}-{digest}.npz")


def _compute(bench, settings):
    """Run the fine FEM of the same model; returns (times, X, u, v)."""
    from .scene import Body, Scene
    from .solve import Method, fem

    scene = bench.scene(settings["cells"], settings["degree"], settings["ppc"], fem=True)
    body = scene.bodies[0]
    if len(scene.bodies) != 1 or type(body.material) is not LinearElastic:
        raise ValueError(f"a same-model reference needs one LinearElastic body, got "
                         f"{[type(b.material).__name__ for b in scene.bodies]}")
    from .effects import Fixed

    if not any(isinstance(e, Fixed) and e.side in ("left", "xmin") for e in scene.effects):
        raise ValueError(f"a same-model reference needs the body fixed at x = 0 (its points "
                         f"start there with u = 0), got effects {scene.effects}")
    scene = Scene(scene.grid, Body(body.particles, Hencky1D(body.material.E)), bench.t_end,
                  scene.effects)
    period = bench.period  # S2: 4 H / c; S3: 2 pi / (c k)
    every = int(settings["save_every"])
    steps = every * int(np.ceil(bench.t_end / period * settings["steps_per_period"] / every))
    result = fem(scene, Method(mass="consistent", scheme="cd", dt=bench.t_end / steps),
                 save_every=every)
    h = result.history
    return (np.asarray(result.times, dtype=np.float64), np.asarray(h["X"][0][:, 0]),
            np.asarray(h["u"])[:, :, 0], np.asarray(h["v"])[:, :, 0])


def _load(path):
    try:
        with np.load(path, allow_pickle=False) as data:
            times, X, u, v = (np.array(data[k], dtype=np.float64) for k in ("t", "X", "u", "v"))
    except (OSError, KeyError, ValueError):
        return None
    n = (times.size, X.size)
    if times.ndim != 1 or u.shape != n or v.shape != n or n[0] < 2 or not (
            np.all(np.isfinite(u)) and np.all(np.isfinite(v)) and np.all(np.diff(times) > 0)):
        return None
    return times, X, u, v


class ModelReference:
    """u, v and sigma of the same model at any (X, t) with 0 <= t <= t_end,
    interpolated from the cached fine FEM run (module docstring); and the
    error measures of :meth:`Benchmark.errors` against it."""

    def __init__(self, bench, times, X, u, v):
        self.bench = bench
        order = np.argsort(X)
        # the fixed base, u = v = 0 at X = 0, is a point of every save
        self.X = np.concatenate([[0.0], X[order]])
        zero = np.zeros((len(times), 1))
        self.u = np.hstack([zero, u[:, order]])
        self.v = np.hstack([zero, v[:, order]])
        self.times = times

    def describe(self):
        s = REFERENCE_SETTINGS
        return (f"a fine FEM of the same model (sigma = E ln F: cubic B-splines on "
                f"{s['cells']} cells, consistent mass, central differences at "
                f"{s['steps_per_period']} steps a period; computed once and cached), not the "
                f"benchmark's exact solution")

    def _fields(self, X, t):
        from scipy.interpolate import CubicSpline

        times = self.times
        tol = 1e-9 * max(1.0, abs(times[-1]))
        if not times[0] - tol <= t <= times[-1] + tol:
            raise ValueError(f"the reference covers t in [{times[0]}, {times[-1]}], got t = {t}")
        k = int(np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2))
        D = times[k + 1] - times[k]
        s = float(np.clip((t - times[k]) / D, 0.0, 1.0))
        h = np.array([2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, 3 * s**2 - 2 * s**3,
                      s**3 - s**2])
        dh = np.array([6 * s**2 - 6 * s, 3 * s**2 - 4 * s + 1, 6 * s - 6 * s**2,
                       3 * s**2 - 2 * s])
        nodes = (self.u[k], D * self.v[k], self.u[k + 1], D * self.v[k + 1])
        u = sum(w * a for w, a in zip(h, nodes))
        v = sum(w * a for w, a in zip(dh, nodes)) / D
        X = np.asarray(X, dtype=np.float64).reshape(-1)
        spline = CubicSpline(self.X, u)
        return spline(X), CubicSpline(self.X, v)(X), self.bench.E * np.log1p(spline(X, 1))

    def displacement(self, X, t):
        return self._fields(X, t)[0][:, None]

    def errors(self, result):
        """The keys of ``Benchmark.errors`` (relative to the benchmark's
        amplitudes), measured against this reference."""
        b, hist = self.bench, result.history
        rms = []
        for k, t in enumerate(result.times):
            du = hist["u"][k][:, 0] - self._fields(hist["X"][k], t)[0]
            rms.append(float(np.sqrt(np.mean(du * du))))
        _, v, sigma = self._fields(hist["X"][-1], result.times[-1])
        dv = hist["v"][-1][:, 0] - v
        ds = hist["stress"][-1][:, 0, 0] - sigma
        return {"error_rms": rms[-1] / abs(b.amplitude), "error_max": max(rms) / abs(b.amplitude),
                "error_rms_abs": rms[-1],
                "velocity_error_rms": float(np.sqrt(np.mean(dv * dv)))
                / abs(b.velocity_amplitude()),
                "stress_error_rms": float(np.sqrt(np.mean(ds * ds))) / abs(b.stress_amplitude())}


def model_reference(bench, compute=True):
    """The same-model reference of ``bench`` (:class:`ModelReference`), or
    None when its exact solution is its model's (nothing in its
    ``model_gaps``). Read from the cache; computed and cached when absent
    (``compute=False``: None then). A damaged cache file is recomputed."""
    if not _applies(bench):
        return None
    path = reference_path(bench)
    data = _load(path) if os.path.exists(path) else None
    if data is None:
        if not compute:
            return None
        data = _compute(bench, REFERENCE_SETTINGS)
        os.makedirs(os.path.dirname(path), exist_ok=True)
        tmp = f"{path}.{os.getpid()}.tmp.npz"
        np.savez(tmp, t=data[0], X=data[1], u=data[2], v=data[3])
        os.replace(tmp, path)
    return ModelReference(bench, *data)
