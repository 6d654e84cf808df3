"""Step time beside busy processes, against the same run on an idle machine.

The performance issue's target: beside 3 busy processes on the 2 cores
(each a pure-Python spin loop), the 2D expanding block of ``skfem-mpm
bench --consistent`` at 64 x 64 cells, consistent MUSL, takes <= 4x its
idle time (a fair share of 2 cores among 4 busy processes is about 2.5x).

For each mass (consistent and lumped by default) the script runs
``simulate`` once untimed (compilation), then ``--repeat`` times on the
machine as it is ("idle"); then it starts ``--spinners`` processes running
``while True: pass``, runs each case ``--repeat`` times again ("loaded"),
and stops them. Each figure is the median of the step loop's wall time
(``Result.wall_time``, compilation excluded); the ratio is loaded / idle.
The load average before each phase is printed: other work on the machine
makes "idle" less idle and the ratio smaller.

    python benchmarks/under_load.py [--cells 64] [--steps 20] [--scheme musl]
        [--mass consistent lumped] [--spinners 3] [--repeat 5] [--threads N] [--json]
"""
import argparse
import json
import os
import statistics
import subprocess
import sys
import time

import numba

from skfem_mpm.bench import consistent_scene
from skfem_mpm.solve import Method, simulate

SPIN = "while True: pass"
TARGET = 4.0  # the target for consistent MUSL at 64 x 64


def start_spinners(count):
    """``count`` Python processes each spinning on one core."""
    return [subprocess.Popen([sys.executable, "-c", SPIN]) for _ in range(count)]


def stop_spinners(spinners):
    for p in spinners:
        p.kill()
    for p in spinners:
        p.wait()


def step_loop_seconds(scene, method, repeat):
    """Wall times (s) of the step loop of ``repeat`` runs."""
    return [simulate(scene, method).wall_time for _ in range(repeat)]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cells", type=int, default=64, help="cells per axis (default 64)")
    parser.add_argument("--steps", type=int, default=20, help="steps per run (default 20)")
    parser.add_argument("--scheme", default="musl", help="scheme (default musl)")
    parser.add_argument("--mass", nargs="+", default=["consistent", "lumped"],
                        help="masses to time (default: consistent lumped)")
    parser.add_argument("--spinners", type=int, default=3,
                        help="busy processes beside the run (default 3)")
    parser.add_argument("--repeat", type=int, default=5, help="runs per median (default 5)")
    parser.add_argument("--threads", type=int, default=None,
                        help="numba threads (default: numba's, NUMBA_NUM_THREADS)")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    for name, low in (("repeat", 1), ("steps", 1), ("cells", 4), ("spinners", 0)):
        if getattr(args, name) < low:
            parser.error(f"--{name} must be >= {low}, got {getattr(args, name)}")
    if args.threads is not None:
        numba.set_num_threads(args.threads)
    scene, dt = consistent_scene(args.cells, args.steps, "expanding block")
    methods = {mass: Method(scheme=args.scheme, mass=mass, dt=dt) for mass in args.mass}
    for method in methods.values():
        simulate(scene, method)  # compile (and load the kernels) untimed
    report = {"cells": args.cells, "steps": args.steps, "scheme": args.scheme,
              "spinners": args.spinners, "repeat": args.repeat,
              "threads": numba.get_num_threads(), "cores": os.cpu_count(),
              "load_average_idle": os.getloadavg()[0], "cases": {}}
    idle = {mass: step_loop_seconds(scene, m, args.repeat) for mass, m in methods.items()}
    spinners = start_spinners(args.spinners)
    try:
        time.sleep(1.0)  # let them take their cores
        report["load_average_loaded"] = os.getloadavg()[0]
        loaded = {mass: step_loop_seconds(scene, m, args.repeat) for mass, m in methods.items()}
    finally:
        stop_spinners(spinners)
    for mass in methods:
        a, b = statistics.median(idle[mass]), statistics.median(loaded[mass])
        report["cases"][mass] = {"idle_s": a, "loaded_s": b, "ratio": b / a,
                                 "idle_runs_s": idle[mass], "loaded_runs_s": loaded[mass]}
    if args.json:
        print(json.dumps(report, indent=2))
        return 0
    print(f"2D expanding block, {args.cells} x {args.cells} cells, {args.steps} steps, "
          f"{args.scheme.upper()}, {report['threads']} numba threads on {report['cores']} "
          f"cores; median of {args.repeat}; load average before: idle "
          f"{report['load_average_idle']:.2f}, loaded {report['load_average_loaded']:.2f}")
    for mass, case in report["cases"].items():
        target = f" (target <= {TARGET:g}x)" if mass == "consistent" else ""
        print(f"{mass:10s} idle {case['idle_s'] * 1e3:8.1f} ms, beside {args.spinners} "
              f"spinners {case['loaded_s'] * 1e3:8.1f} ms: {case['ratio']:.2f}x{target}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
