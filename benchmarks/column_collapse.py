"""G2 granular column collapse (issue 20): the runout table against the
experiments of Lube, Huppert, Sparks and Freundt (2005, Phys. Rev. E 72,
041301): (L_inf - L0) / L0 = 1.2 a for a below about 1.8 and 1.9 a^(2/3)
above about 2.8 (a = H0 / L0).

Each aspect ratio runs the benchmark ``column-collapse`` (Mohr-Coulomb,
friction angle 30 deg, dilation 0, grains disconnected above J = 1.01, a
frictional floor with mu = tan 30 deg, a smooth wall on the left; quadratic
B-splines, lumped MUSL, the compiled step loop) and prints one row: the
runout by the deposit's front at 0.05 L0 thickness, by the rightmost
particle and by the fronts of 97% and 99% of the mass, the experiments'
laws and the runout of a purely frictional flow with mu = tan(phi),
a / tan(phi) (Staron and Hinch 2005's energy balance; Lube's 1.2 a is
that of mu = 0.83), its ratio to the experiments' law of the regime, the
final height over H0, the kinetic
energy left (of the grid's velocity and of the particles') over the
potential energy released, how far the rightmost particle moved over the
last quarter of the run (in cells), the grains thrown out of the grid
(removed, counted), the steps (all in the compiled loop?) and the wall time.

    python benchmarks/column_collapse.py                 # a = 0.5, 16 cells
    python benchmarks/column_collapse.py --a 0.5 1 1.5 2 3 4 --cells 16   # the table
    python benchmarks/column_collapse.py --json          # one JSON line per run
"""
import argparse
import json
import time

import numpy as np


def run(a, cells, ppc=2, **params):
    """One collapse: the benchmark's checks plus the front's drift over the
    last quarter of the run and the wall time."""
    from skfem_mpm.benchmarks import get_benchmark
    from skfem_mpm.solve import Method, prepare, simulate

    bench = get_benchmark("column-collapse", a=a, **params)
    scene = bench.scene(cells, 2, ppc)
    method = Method(on_exit="remove")  # a grain thrown out of the grid is counted
    steps = prepare(scene, method).n_steps or int(scene.t_end / prepare(scene, method).dt)
    start = time.perf_counter()
    result = simulate(scene, method, save_every=max(1, steps // 16))
    wall = time.perf_counter() - start
    fronts = [(t, float(x[:, 0].max())) for t, x in zip(result.times, result.history["x"])]
    record = {"a": a, "cells": cells, "ppc": ppc, "particles": result.counts["particles"],
              "removed": result.counts["removed"], "steps": result.counts["steps"],
              "loop_steps": result.counts["compiled_loop_steps"], "path": result.path,
              **bench.checks(result)}
    t_late = 0.75 * scene.t_end
    late = [x for t, x in fronts if t >= t_late - 1e-12]
    h = bench.L0 / cells
    record["front_drift_last_quarter_cells"] = (max(late) - min(late)) / h if late else None
    record["wall_time_s"] = wall  # the call, compilation included
    record["jit_time_s"] = result.jit_time
    return record


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--a", type=float, nargs="+", default=[0.5],
                        help="aspect ratios H0 / L0 (default: 0.5)")
    parser.add_argument("--cells", type=int, default=16,
                        help="cells across L0 (default: 16)")
    parser.add_argument("--ppc", type=int, default=2, help="particles per cell and axis")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                        help="another benchmark parameter (e.g. floor_angle=45)")
    parser.add_argument("--json", action="store_true", help="one JSON line per run")
    args = parser.parse_args(argv)
    params = {k: float(v) for k, v in (s.split("=", 1) for s in args.set)}
    if not args.json:
        print(f"{'a':>4} {'front':>6} {'last':>6} {'97%':>6} {'99%':>6} {'1.2a':>5} "
              f"{'1.9a^2/3':>8} {'a/tanf':>6} {'ratio':>5} {'H/H0':>5} {'KEgrid':>7} {'KEpart':>7} "
              f"{'drift':>5} {'lost':>4} {'steps':>7} {'loop':>4} {'wall s':>6}")
    rows = []
    for a in args.a:
        r = run(a, args.cells, args.ppc, **params)
        rows.append(r)
        if args.json:
            print(json.dumps(r, default=float), flush=True)
        else:
            print(f"{a:4g} {r['runout_thickness_front']:6.2f} {r['runout']:6.2f} "
                  f"{r['runout_97pct_mass']:6.2f} {r['runout_99pct_mass']:6.2f} "
                  f"{r['runout_lube_low_1.2a']:5.2f} {r['runout_lube_high_1.9a^(2/3)']:8.2f} "
                  f"{r['runout_friction_model']:6.2f} "
                  f"{r['runout_ratio']:5.2f} {r['final_height_ratio']:5.2f} "
                  f"{r['kinetic_grid_over_released']:7.1e} {r['kinetic_over_released']:7.1e} "
                  f"{r['front_drift_last_quarter_cells']:5.2f} {r['removed']:4d} "
                  f"{r['steps']:7d} {'yes' if r['loop_steps'] == r['steps'] else 'no':>4} "
                  f"{r['wall_time_s']:6.0f}", flush=True)
    return rows


if __name__ == "__main__":
    np.set_printoptions(precision=4)
    main()
