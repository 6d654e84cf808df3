"""G1 strip footing: linear against quadratic B-spline MPM (issue 20).

Runs the benchmark ``strip-footing`` (rough footing, von Mises clay, B-bar)
with degree 1 and 2 on the same grid and prints, per degree, N_c at 0.1 B
and the scatter of the vertical stress under the footing at the end (mean
and standard deviation of -sigma_yy / c_u over the particles of a band one
cell high, its middle ``depth`` B below the base, x < 0.45 B); writes
``footing_stress.png``: -sigma_yy / c_u of those particles against x.

    python benchmarks/strip_footing_degrees.py              # 20 cells over 5 B
    python benchmarks/strip_footing_degrees.py --cells 40   # 4 under B/2
"""
import argparse
import json

import numpy as np


def run(degree, cells, depths):
    from skfem_mpm.benchmarks import get_benchmark
    from skfem_mpm.solve import Method, simulate

    bench = get_benchmark("strip-footing")
    scene = bench.scene(cells, degree)
    result = simulate(scene, Method())
    figures = bench.checks(result)
    p = result.particles
    h = bench.width * bench.B / figures["cells_across_width"]
    base = bench.depth * bench.B - bench.footing.settlement
    sigma = -p.stress[:, 1, 1] / bench.c_u
    out = {"degree": degree, "cells_across_width": figures["cells_across_width"],
           "bearing_capacity_factor": figures["bearing_capacity_factor"],
           "wall_time_s": result.wall_time, "bands": {}}
    points = {}
    for depth in depths:
        y = base - depth * bench.B
        band = (np.abs(p.x[:, 1] - y) <= 0.5 * h) & (p.x[:, 0] < 1.5 * bench.B)
        under = band & (p.x[:, 0] < 0.45 * bench.B)
        out["bands"][depth] = {"mean": float(sigma[under].mean()),
                               "std": float(sigma[under].std()), "particles": int(under.sum())}
        points[depth] = (p.x[band, 0] / bench.B, sigma[band])
    return out, points


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, default=20, help="cells over 5 B (default 20)")
    parser.add_argument("--out", default="footing_stress.png")
    args = parser.parse_args(argv)
    depths = (0.1, 0.3)
    rows, points = [], {}
    for degree in (1, 2):
        row, pts = run(degree, args.cells, depths)
        rows.append(row)
        points[degree] = pts
        print(json.dumps(row), flush=True)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(depths), figsize=(11, 4))
    for ax, depth in zip(axes, depths):
        for degree, colour in ((1, "tab:orange"), (2, "tab:blue")):
            x, s = points[degree][depth]
            ax.plot(x, s, ".", color=colour, ms=5,
                    label=f"{'linear' if degree == 1 else 'quadratic'} B-splines")
        ax.axvline(0.5, color="k", lw=0.8)
        ax.set_title(f"vertical stress {depth} B below the footing's base", fontsize=10)
        ax.set_xlabel("x / B (footing edge at 0.5)")
        ax.set_ylabel("-sigma_yy / c_u")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out, dpi=100)
    return rows


if __name__ == "__main__":
    main()
