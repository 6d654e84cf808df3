"""G2 granular column collapse (issue 20): the runout table against the
experiments of Lube, Huppert, Sparks and Freundt (2005, Phys. Rev. E 72,
041301): (L_inf - L0) / L0 = 1.2 a for a below about 1.8 and 1.9 a^(2/3)
above about 2.8 (a = H0 / L0).

Each aspect ratio runs the benchmark ``column-collapse`` (Mohr-Coulomb,
friction angle 30 deg, dilation 0, a frictional floor with mu = tan 30 deg,
a smooth wall on the left; quadratic B-splines, lumped MUSL) and prints
one row: runout (rightmost particle), the experiments' scalings and the
ratio to the regime's law, the front of 97% of the mass, the final height
over H0, the kinetic energy left over the potential energy released, how
far the front moved over the last quarter of the run (in cells: 0 means
the flow has stopped), the particles thrown out of the
grid (removed, counted) and the wall time.

    python benchmarks/column_collapse.py                 # a = 0.5, 16 cells (~1 min)
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
    steps = scene.t_end / prepare(scene, method).dt  # about: the step follows the wave speed
    start = time.perf_counter()
    result = simulate(scene, method, save_every=max(1, int(steps / 16)))
    wall = time.perf_counter() - start
    fronts = [(t, float(x[:, 0].max())) for t, x in zip(result.times, result.history["x"])]
    record = {"a": a, "cells": cells, "ppc": ppc, "particles": result.counts["particles"],
              "removed": result.counts["removed"], "steps": result.counts["steps"],
              **bench.checks(result)}
    t_late = 0.75 * scene.t_end
    late = [x for t, x in fronts if t >= t_late - 1e-12]
    h = bench.L0 / cells
    record["front_drift_last_quarter_cells"] = (max(late) - min(late)) / h if late else None
    record["wall_time_s"] = wall
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
        print(f"{'a':>4} {'runout':>7} {'1.2a':>6} {'1.9a^2/3':>8} {'ratio':>6} "
              f"{'97% mass':>8} {'H_inf/H0':>8} {'KE/PE':>8} {'drift':>6} {'lost':>4} "
              f"{'wall s':>7}")
    rows = []
    for a in args.a:
        r = run(a, args.cells, args.ppc, **params)
        rows.append(r)
        if args.json:
            print(json.dumps(r, default=float), flush=True)
        else:
            print(f"{a:4g} {r['runout']:7.3f} {r['runout_lube_low_1.2a']:6.2f} "
                  f"{r['runout_lube_high_1.9a^(2/3)']:8.2f} {r['runout_ratio']:6.2f} "
                  f"{r['runout_97pct_mass']:8.3f} {r['final_height_ratio']:8.3f} "
                  f"{r['kinetic_over_released']:8.1e} "
                  f"{r['front_drift_last_quarter_cells']:6.2f} {r['removed']:4d} "
                  f"{r['wall_time_s']:7.0f}",
                  flush=True)
    return rows


if __name__ == "__main__":
    np.set_printoptions(precision=4)
    main()
