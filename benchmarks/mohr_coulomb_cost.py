"""Cost of a Mohr-Coulomb step against a LinearElastic step (issue 20).

The issue's target: on G2 (``column-collapse``) at a = 2 with 128 cells
across L0, while most particles yield, a Mohr-Coulomb step of the compiled
executor costs at most twice a LinearElastic step of the same scene.

Both runs take the benchmark's scene (quadratic B-splines, 2 x 2 particles
per cell, lumped MUSL, the compiled step loop) with the same fixed time
step (the Mohr-Coulomb run's: its wave-speed bound), ``--steps`` steps
from t = 0; only the material differs: the benchmark's ``MohrCoulomb``
(friction angle 30 deg, large deformation, disconnected grains above
J = 1.01) or ``LinearElastic(E, nu)``. So that most particles yield in the
timed steps, the column starts from the geostatic state with
K0 = ``--k0`` (default: 0.9 times Rankine's active ratio
K_a = (1 - sin phi) / (1 + sin phi), i.e. every particle just beyond the
yield surface; the benchmark itself starts from Jaky's K0 = 1 - sin phi,
inside it). Printed: microseconds per step (JIT excluded, median of
``--repeat`` runs that alternate MC, LE, MC, LE, ...), the ratio, the
fraction of particles whose accumulated plastic strain grew during the
timed steps, and ``uptime``'s load.

    python benchmarks/mohr_coulomb_cost.py                     # 128 cells, 20 steps
    python benchmarks/mohr_coulomb_cost.py --cells 32 --steps 50 --json
"""
import argparse
import json
import os
import statistics

import numpy as np


def scenes(cells, a, k0, steps):
    """(Mohr-Coulomb scene, LinearElastic scene, dt) of G2 at ``a``."""
    from skfem_mpm import Body, LinearElastic, Scene
    from skfem_mpm.benchmarks import get_benchmark
    from skfem_mpm.solve import Method, prepare

    bench = get_benchmark("column-collapse", a=a, K0=k0)
    mc = bench.scene(cells, 2, 2)
    dt = prepare(mc, Method()).dt
    t_end = steps * dt
    mc = bench.scene(cells, 2, 2, t_end=t_end)
    body = mc.bodies[0]
    elastic = LinearElastic(body.material.E, body.material.nu)
    le = Scene(mc.grid, Body(body.particles, elastic), t_end, effects=list(mc.effects))
    return mc, le, dt


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", type=int, default=128, help="cells across L0 (default 128)")
    ap.add_argument("--a", type=float, default=2.0, help="aspect ratio H0 / L0 (default 2)")
    ap.add_argument("--steps", type=int, default=20, help="timed steps a run (default 20)")
    ap.add_argument("--repeat", type=int, default=3, help="runs per material (default 3)")
    ap.add_argument("--k0", type=float, default=None,
                    help="K0 of the initial state (default 0.9 K_a: every particle yields)")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args(argv)
    if args.cells < 1 or args.steps < 1 or args.repeat < 1:
        ap.error("--cells, --steps and --repeat must be >= 1")
    from skfem_mpm.solve import Method, simulate

    phi = np.radians(30.0)
    k0 = 0.9 * (1 - np.sin(phi)) / (1 + np.sin(phi)) if args.k0 is None else args.k0
    mc, le, dt = scenes(args.cells, args.a, k0, args.steps)
    method = Method(dt=dt)
    simulate(mc, method)  # compile or load every kernel of both runs
    simulate(le, method)
    times = {"mohr_coulomb": [], "linear_elastic": []}
    yielded, paths = None, {}
    for _ in range(args.repeat):
        for name, scene in (("mohr_coulomb", mc), ("linear_elastic", le)):
            r = simulate(scene, method)
            times[name].append(r.wall_time / r.counts["steps"] * 1e6)
            paths[name] = (r.path, r.counts["compiled_loop_steps"], r.counts["steps"])
            if name == "mohr_coulomb":
                before = scene.bodies[0].particles.state.get("plastic_strain")
                after = r.particles.state["plastic_strain"]
                grew = after > (0.0 if before is None else before)
                yielded = float(grew.mean())
    med = {k: statistics.median(v) for k, v in times.items()}
    out = {"cells_across_L0": args.cells, "a": args.a, "particles": int(mc.bodies[0].particles.n),
           "steps": args.steps, "dt": dt, "k0": k0,
           "us_per_step_mohr_coulomb": med["mohr_coulomb"],
           "us_per_step_linear_elastic": med["linear_elastic"],
           "ratio": med["mohr_coulomb"] / med["linear_elastic"],
           "runs_us": times, "fraction_yielding": yielded,
           "paths": {k: {"path": p, "loop_steps": ls, "steps": s}
                     for k, (p, ls, s) in paths.items()},
           "load": os.getloadavg()[0]}
    if args.json:
        print(json.dumps(out))
    else:
        print(f"G2 a = {args.a:g}, {args.cells} cells across L0, {out['particles']} particles, "
              f"{args.steps} steps of dt = {dt:.3g}, K0 = {k0:.3f}: Mohr-Coulomb "
              f"{med['mohr_coulomb']:.0f} us, LinearElastic {med['linear_elastic']:.0f} us a "
              f"step (median of {args.repeat}), ratio {out['ratio']:.2f} (target <= 2); "
              f"{100 * yielded:.0f}% of the particles yielded; load {out['load']:.1f}")
    return out


if __name__ == "__main__":
    main()
