"""Cost of one MPM step on small problems, against a minimal compiled step.

The product's promise is that accuracy pays; on small problems that holds
only when a step costs close to its arithmetic. This script times, through
the public API (``simulate``, JIT compilation excluded), the microseconds
per step of:

* S1, the vibrating string: 32 quadratic cells, 4 particles per cell
  (128 particles), one period, MUSL, lumped and consistent mass, and
  both with the spline reconstruction (particle knots);
* D2 small, the vibrating plate: 16 x 16 quadratic cells, 2 x 2 particles
  per cell, MUSL, lumped and consistent mass;
* D2 small at 16 x 16 and 128 x 128 quadratic cells with 3 x 3 particles
  per cell (``d2-<cells>-ppc3-...``: 40 and 5 steps of the lumped step size),
  MUSL: lumped, consistent, and consistent with each of spline, tls and
  mls; each also as the ratio to the lumped step of the same scene (issue
  18's target: <= 4), pair by pair (the cases' runs alternate);

and, in the same run, a minimal compiled lumped MUSL step of the S1 problem
(one numba function, four passes over the particles: particles to grid,
particle velocities, momentum re-projection, positions and stress). Each
figure is printed also as a ratio to that minimal step, so the targets hold
as ratios on another machine.

    python benchmarks/step_cost.py [--repeat 5] [--json] [--only NAME ...]

(``--only d2-16-ppc3-lumped-musl d2-16-ppc3-consistent-tls-musl`` gives
that case's same-scene ratio; ``--list`` prints the case names.)
"""
import argparse
import json
import statistics
import sys
import time

import numpy as np
from numba import njit


# --------------------------------------------------------- the minimal step
@njit(cache=True, inline="always", error_model="numpy")
def _basis(j, e, s, ncells):
    """Value and d/ds of the quadratic B-spline j on the open uniform knot
    vector (knots clamped to [0, ncells]) at s in cell e (Cox-de Boor)."""
    u0 = min(max(j - 2, 0), ncells)
    u1 = min(max(j - 1, 0), ncells)
    u2 = min(max(j, 0), ncells)
    u3 = min(max(j + 1, 0), ncells)
    n01 = 1.0 if u0 <= e < u1 else 0.0
    n11 = 1.0 if u1 <= e < u2 else 0.0
    n21 = 1.0 if u2 <= e < u3 else 0.0
    n02 = ((s - u0) / (u1 - u0) * n01 if u1 > u0 else 0.0) + \
        ((u2 - s) / (u2 - u1) * n11 if u2 > u1 else 0.0)
    n12 = ((s - u1) / (u2 - u1) * n11 if u2 > u1 else 0.0) + \
        ((u3 - s) / (u3 - u2) * n21 if u3 > u2 else 0.0)
    w = ((s - u0) / (u2 - u0) * n02 if u2 > u0 else 0.0) + \
        ((u3 - s) / (u3 - u1) * n12 if u3 > u1 else 0.0)
    dw = (2.0 / (u2 - u0) * n02 if u2 > u0 else 0.0) - \
        (2.0 / (u3 - u1) * n12 if u3 > u1 else 0.0)
    return w, dw


@njit(cache=True, inline="always", error_model="numpy")
def _weights(x, x0, inv_h, ncells):
    """Cell e and the three quadratic B-spline values and x-derivatives:
    closed form in interior cells, Cox-de Boor in the two boundary cells at
    each end."""
    t = (x - x0) * inv_h
    e = min(max(int(np.floor(t)), 0), ncells - 1)
    xi = t - e
    if 2 <= e < ncells - 2:
        r = 1.0 - xi
        return (e, 0.5 * r * r, 0.5 + xi * r, 0.5 * xi * xi,
                -r * inv_h, (1.0 - 2.0 * xi) * inv_h, xi * inv_h)
    w0, d0 = _basis(e, e, t, ncells)
    w1, d1 = _basis(e + 1, e, t, ncells)
    w2, d2 = _basis(e + 2, e, t, ncells)
    return e, w0, w1, w2, d0 * inv_h, d1 * inv_h, d2 * inv_h


@njit(cache=True, error_model="numpy")
def minimal_musl(x, v, m, V, s, E, x0, inv_h, ncells, dt, steps):
    """``steps`` lumped MUSL steps of a 1D quadratic B-spline MPM with both
    ends fixed, small-strain linear elasticity; arrays updated in place."""
    nd = ncells + 2
    n = x.shape[0]
    mass = np.empty(nd)
    mom = np.empty(nd)
    force = np.empty(nd)
    for _ in range(steps):
        mass[:] = 0.0
        mom[:] = 0.0
        force[:] = 0.0
        for i in range(n):  # 1: particles to grid
            e, w0, w1, w2, d0, d1, d2 = _weights(x[i], x0, inv_h, ncells)
            mi, pi, si = m[i], m[i] * v[i], V[i] * s[i]
            mass[e] += w0 * mi
            mass[e + 1] += w1 * mi
            mass[e + 2] += w2 * mi
            mom[e] += w0 * pi
            mom[e + 1] += w1 * pi
            mom[e + 2] += w2 * pi
            force[e] -= d0 * si
            force[e + 1] -= d1 * si
            force[e + 2] -= d2 * si
        for k in range(nd):  # acceleration (fixed ends)
            force[k] = force[k] / mass[k] if mass[k] > 0 and 0 < k < nd - 1 else 0.0
        mom[:] = 0.0
        for i in range(n):  # 2, 3: particle velocities and their momentum
            e, w0, w1, w2, d0, d1, d2 = _weights(x[i], x0, inv_h, ncells)
            v[i] += dt * (w0 * force[e] + w1 * force[e + 1] + w2 * force[e + 2])
            pi = m[i] * v[i]
            mom[e] += w0 * pi
            mom[e + 1] += w1 * pi
            mom[e + 2] += w2 * pi
        for k in range(nd):  # grid velocity
            mom[k] = mom[k] / mass[k] if mass[k] > 0 and 0 < k < nd - 1 else 0.0
        for i in range(n):  # 4: positions, strain rate, stress
            e, w0, w1, w2, d0, d1, d2 = _weights(x[i], x0, inv_h, ncells)
            vp = w0 * mom[e] + w1 * mom[e + 1] + w2 * mom[e + 2]
            L = d0 * mom[e] + d1 * mom[e + 1] + d2 * mom[e + 2]
            x[i] += dt * vp
            s[i] += dt * E * L
            V[i] *= 1.0 + dt * L


def minimal_step_us(repeat):
    """Microseconds per step of the minimal loop on the S1 problem."""
    from skfem_mpm.benchmarks import get_benchmark

    b = get_benchmark("vibrating-string", "small")
    scene = b.scene(32, 2, 4)
    p = scene.particles()
    method_dt = _api_dt(scene)
    steps = int(round(2 * np.pi / b.omega / method_dt))
    args = (0.0, 32 / b.L, 32, method_dt)

    def once(k):
        x, v = p.x[:, 0].copy(), p.v[:, 0].copy()
        m, V, s = p.m.copy(), p.V.copy(), p.stress[:, 0, 0].copy()
        t0 = time.perf_counter()
        minimal_musl(x, v, m, V, s, b.E, *args, k)
        return time.perf_counter() - t0

    once(2)  # compile
    runs = [once(steps) / steps * 1e6 for _ in range(repeat)]
    return statistics.median(runs), runs


def minimal_step_agreement(steps=30):
    """Largest relative difference in position and stress between the
    minimal loop and ``simulate`` (lumped MUSL) after ``steps`` steps: the
    two are the same step."""
    from skfem_mpm import Method, simulate
    from skfem_mpm.benchmarks import get_benchmark

    b = get_benchmark("vibrating-string", "small")
    scene = b.scene(32, 2, 4)
    r = simulate(scene, Method(scheme="musl", dt=_api_dt(scene)), save_every=1)
    p = scene.particles()
    x, v = p.x[:, 0].copy(), p.v[:, 0].copy()
    m, V, s = p.m.copy(), p.V.copy(), p.stress[:, 0, 0].copy()
    minimal_musl(x, v, m, V, s, b.E, 0.0, 32 / b.L, 32, r.dt, steps)
    u = r.history["u"][steps][:, 0]
    stress = r.history["stress"][steps][:, 0, 0]
    return max(np.abs(x - r.history["x"][steps][:, 0]).max() / np.abs(u).max(),
               np.abs(s - stress).max() / np.abs(stress).max())


def _api_dt(scene):
    from skfem_mpm import Method
    from skfem_mpm.solve.state import prepare

    return prepare(scene, Method()).dt


# ------------------------------------------------------- the product's steps
D2_PPC3_STEPS = {16: 40, 128: 5}
D2_PPC3_VARIANTS = {"lumped": dict(mass="lumped"), "consistent": dict(mass="consistent"),
                    **{f"consistent-{r}": dict(mass="consistent", reconstruction=r)
                       for r in ("spline", "tls", "mls")}}


def _d2_ppc3(cells):
    """D2 small, quadratic, 3 x 3 particles per cell, lasting
    D2_PPC3_STEPS[cells] lumped steps."""
    from skfem_mpm.benchmarks import get_benchmark

    d2 = get_benchmark("vibrating-plate-2d", "small")
    return d2.scene(cells, 2, 3, t_end=D2_PPC3_STEPS[cells] * _api_dt(d2.scene(cells, 2, 3)))


def same_scene_lumped(name):
    """The lumped case of the same scene as case ``name`` (a D2 ppc3 case),
    or None."""
    for variant in D2_PPC3_VARIANTS:
        if name.endswith(f"-{variant}-musl") and name.startswith("d2-") and "-ppc3-" in name:
            return name[:-len(f"{variant}-musl")] + "lumped-musl"
    return None


def cases():
    from skfem_mpm.benchmarks import get_benchmark

    s1 = get_benchmark("vibrating-string", "small")
    d2 = get_benchmark("vibrating-plate-2d", "small")
    period = 2 * np.pi / s1.omega
    ppc3 = {f"d2-{cells}-ppc3-{variant}-musl": ((lambda cells=cells: _d2_ppc3(cells)), margs)
            for cells in D2_PPC3_STEPS for variant, margs in D2_PPC3_VARIANTS.items()}
    return {
        "s1-lumped-musl": (lambda: s1.scene(32, 2, 4, t_end=period), dict(mass="lumped")),
        "s1-consistent-musl": (lambda: s1.scene(32, 2, 4, t_end=period),
                               dict(mass="consistent")),
        "s1-consistent-spline-musl": (lambda: s1.scene(32, 2, 4, t_end=period),
                                      dict(mass="consistent", reconstruction="spline")),
        "s1-lumped-spline-musl": (lambda: s1.scene(32, 2, 4, t_end=period),
                                  dict(mass="lumped", reconstruction="spline")),
        "d2-16-lumped-musl": (lambda: d2.scene(16, 2, 2), dict(mass="lumped")),
        "d2-16-consistent-musl": (lambda: d2.scene(16, 2, 2), dict(mass="consistent")),
        **ppc3,
    }


def step_runs(selected, repeat):
    """{name: (runs, path)}: microseconds per step through ``simulate`` (JIT
    and the run's preparation excluded) of each selected case (name ->
    (make_scene, method_args)), ``repeat`` runs each, the cases in turn
    (A B C A B C ...) so that same-scene ratios are taken pair by pair."""
    from skfem_mpm import Method, simulate

    prepared = {}
    for name, (make_scene, method_args) in selected.items():
        scene = make_scene()
        method = Method(scheme="musl", **method_args)
        simulate(scene, method)  # compile or load every kernel the run uses
        prepared[name] = (scene, method)
    out = {name: ([], None) for name in selected}
    for _ in range(repeat):
        for name, (scene, method) in prepared.items():
            r = simulate(scene, method)
            out[name][0].append(r.wall_time / r.counts["steps"] * 1e6)
            out[name] = (out[name][0], r.path)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5, help="runs per figure (default 5)")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    ap.add_argument("--only", nargs="*", default=None, help="case names to run (default all)")
    ap.add_argument("--list", action="store_true", help="print the case names and stop")
    args = ap.parse_args(argv)
    if args.list:
        print("\n".join(cases()))
        return 0
    unknown = sorted(set(args.only or ()) - set(cases()))
    if unknown:
        ap.error(f"--only: unknown case names {unknown}; valid: {sorted(cases())}")
    if args.repeat < 1:
        ap.error(f"--repeat must be >= 1, got {args.repeat}")
    base, base_runs = minimal_step_us(args.repeat)
    out = {"minimal-step-us": base, "minimal-step-runs": base_runs,
           "minimal-step-agreement": minimal_step_agreement(), "cases": {}}
    selected = {name: case for name, case in cases().items()
                if not args.only or name in args.only}
    measured = step_runs(selected, args.repeat)
    for name, (runs, path) in measured.items():
        us = statistics.median(runs)
        out["cases"][name] = {"us_per_step": us, "ratio_to_minimal": us / base, "runs": runs,
                              "path": path}
        lumped = same_scene_lumped(name)
        if lumped in measured and lumped != name:
            ratios = [a / b for a, b in zip(runs, measured[lumped][0])]
            out["cases"][name]["ratio_to_lumped"] = statistics.median(ratios)
            out["cases"][name]["ratios_to_lumped"] = ratios
    if args.json:
        print(json.dumps(out, indent=1))
        return 0
    print(f"minimal compiled lumped MUSL step (S1, 128 particles): {base:8.2f} us "
          f"(agrees with simulate to {out['minimal-step-agreement']:.1e})")
    for name, c in out["cases"].items():
        same = ""
        if "ratio_to_lumped" in c:
            same = (f"  {c['ratio_to_lumped']:5.2f}x lumped ({min(c['ratios_to_lumped']):.2f}-"
                    f"{max(c['ratios_to_lumped']):.2f})")
        print(f"{name:30s} {c['us_per_step']:9.1f} us/step  {c['ratio_to_minimal']:7.1f}x minimal"
              f"{same}   [{c['path']}]")
    return 0


if __name__ == "__main__":
    sys.exit(main())
