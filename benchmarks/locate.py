"""SplineGrid.locate against scikit-fem's mesh.element_finder (issue: B-spline
spaces). Median of 5 timed calls after a warm-up, 1e5 random points, uniform
and non-uniform breakpoints, 1D (1000 cells) and 2D (128 x 128 cells); the
cells found are checked to agree. In 2D element_finder builds (points x
candidate cells x 2) arrays (48.8 GiB at 1e5 points here), so it is called
on batches of at most 256 MB and timed once over all batches.

    python benchmarks/locate.py [--points 100000] [--repeat 5]
"""
import argparse
import time

import numpy as np

from skfem_mpm import SplineGrid
from transfer import median_time  # benchmarks/ is on sys.path when run as a script


def batched(finder, candidates, budget=256e6):
    """finder over batches whose (points x candidates x 2) float arrays fit
    the memory budget."""
    size = max(1, int(budget / (16 * candidates)))

    def find(x):
        return np.concatenate([finder(*x[i:i + size].T) for i in range(0, len(x), size)])
    return find


def grids():
    b = np.linspace(0.0, 1.0, 1001)
    yield "1D uniform, 1000 cells", SplineGrid.line(0.0, 1.0, 1000, 2)
    yield "1D non-uniform, 1000 cells", SplineGrid(b ** 2, 2)
    yield "2D uniform, 128x128 cells", SplineGrid.rectangle((0, 1), (0, 1), 128, 2)
    c = np.linspace(0.0, 1.0, 129)
    yield "2D non-uniform, 128x128", SplineGrid((c ** 2, np.sqrt(c)), 2)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=100000)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(0)
    print(f"{'grid':28s} {'points':>8s} {'locate [s]':>11s} {'element_finder [s]':>19s} {'speed-up':>9s}")
    for name, grid in grids():
        x = rng.random((args.points, grid.dim))
        finder = batched(grid.mesh.element_finder(), grid.ncells if grid.dim == 2 else 1)
        ours = median_time(lambda: grid.locate(x), args.repeat)
        if grid.dim == 1:
            theirs = median_time(lambda: finder(x), args.repeat)
        else:  # minutes per call: timed once
            t0 = time.perf_counter()
            finder(x)
            theirs = time.perf_counter() - t0
        cells, _ = grid.locate(x)
        agree = np.mean(cells == finder(x))
        print(f"{name:28s} {args.points:8d} {ours:11.4f} {theirs:19.4f} {theirs / ours:9.1f}"
              f"   (same cell for {100 * agree:.2f}% of points)")


if __name__ == "__main__":
    main()
