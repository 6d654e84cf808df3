"""Cost of building the transfer matrices N and grad_N (issue: particle quadrature).

Prints median wall times (5 runs, after a warm-up that pays the JIT) for
1D quadratic with 1e6 particles and 2D quadratic with 1e5 particles, uniform
and clustered (5% of the particles in one cell), and scikit-fem's
``basis.probes`` on a few thousand of the points (at the full count its dense
point-by-cell arrays do not fit in memory).

    python benchmarks/transfer.py [--repeat 5] [--json]
"""
import argparse
import json
import time

import numpy as np

from skfem_mpm import SplineGrid, transfer_matrices


def median_time(fn, repeat):
    fn()  # warm-up (JIT, page cache)
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def points(grid, n, clustered, seed=0):
    rng = np.random.default_rng(seed)
    lo = np.array([b[0] for b in grid.bounds])
    hi = np.array([b[1] for b in grid.bounds])
    x = lo + (hi - lo) * rng.random((n, grid.dim))
    if clustered:
        k = n // 20
        cell = np.array(grid.h)  # the first cell
        x[:k] = lo + cell * rng.random((k, grid.dim))
    return x


def probes_time(grid, x, repeat):
    basis = grid.basis()
    return median_time(lambda: basis.probes(x.T), repeat)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    cases = [
        ("1D quadratic", SplineGrid.line(0, 1, 250_000, 2), 1_000_000, 0.3),
        ("2D quadratic", SplineGrid.rectangle((0, 1), (0, 1), 256, 2), 100_000, 0.1),
    ]
    rows = []
    for name, grid, n, target in cases:
        uniform = median_time(lambda: transfer_matrices(grid, points(grid, n, False)), args.repeat)
        clustered = median_time(lambda: transfer_matrices(grid, points(grid, n, True)), args.repeat)
        # points() itself is part of both timings; measure it to subtract
        gen = median_time(lambda: points(grid, n, False), args.repeat)
        # probes builds dense (points x cells) arrays: 1e6 points on 2.5e5 cells
        # would need 233 GiB, so it is timed on a few thousand points
        probe_n = 1_000 if grid.dim == 1 else 2_000
        x_probe = points(grid, probe_n, False)
        ours_small = median_time(lambda: transfer_matrices(grid, x_probe), args.repeat)
        probes = probes_time(grid, x_probe, max(1, args.repeat // 2))
        rows.append(dict(case=name, particles=n, cells=grid.ncells, target_s=target,
                         build_s=uniform - gen, clustered_s=clustered - gen,
                         clustered_ratio=(clustered - gen) / (uniform - gen),
                         probes_points=probe_n, probes_s=probes, ours_same_points_s=ours_small,
                         speedup_vs_probes=probes / ours_small))
    if args.json:
        print(json.dumps(rows, indent=2))
        return
    print(f"{'case':14} {'particles':>10} {'N+grad_N [s]':>13} {'target':>7} "
          f"{'clustered/uniform':>18} {'probes pts':>10} {'probes [s]':>11} {'speed-up':>9}")
    for r in rows:
        print(f"{r['case']:14} {r['particles']:>10d} {r['build_s']:13.4f} {r['target_s']:7.2f} "
              f"{r['clustered_ratio']:18.2f} {r['probes_points']:>10d} {r['probes_s']:11.4f} "
              f"{r['speedup_vs_probes']:9.0f}")


if __name__ == "__main__":
    main()
