"""Bearing capacity of a strip footing on undrained clay (benchmark G1).

A rough rigid footing of width B is pushed slowly into a layer of clay of
undrained shear strength c_u (Tresca: von Mises in plane strain with
yield stress sqrt(3) c_u; no weight). Prandtl's limit pressure is
q_ult = (2 + pi) c_u = 5.14 c_u. The picture is the load-settlement curve,
footing pressure q / c_u against settlement / B, beside 5.14, with the
bearing capacity factor N_c read at a settlement of 0.1 B; the curve
without the anti-locking treatment (B-bar: each particle's volumetric
strain rate replaced by a smooth average over its neighbourhood, one value
per grid vertex) is drawn too.

Half model by symmetry (5 B wide, 5 B deep), quadratic B-splines, 2 x 2
particles per cell, E = 300 c_u, nu = 0.3, footing speed 0.05 B/s reached
over 0.4 s (the kinetic energy stays far below the plastic work).

    python examples/strip_footing.py          # 20 cells over 5 B (2 under B/2), ~1 min
    python examples/strip_footing.py 40       # 4 under B/2, a few minutes
"""
import sys

import numpy as np

from skfem_mpm import Method, simulate
from skfem_mpm.benchmarks import get_benchmark


def run(cells, bbar):
    bench = get_benchmark("strip-footing", bbar=float(bbar))
    result = simulate(bench.scene(cells), Method())
    return bench.checks(result), result.wall_time


def main(cells=20, out="strip_footing.png", without_bbar=True):
    figures, wall = run(cells, True)
    others = run(cells, False)[0] if without_bbar else None
    draw(figures, others, out)
    print(f"N_c = q / c_u at a settlement of 0.1 B: {figures['bearing_capacity_factor']:.3f} "
          f"(Prandtl 2 + pi = 5.142, {100 * figures['bearing_capacity_error']:+.1f}%), "
          f"{figures['cells_under_half_footing']} cells under the half footing, {wall:.0f} s"
          + (f"; without B-bar {others['bearing_capacity_factor']:.3f}" if others else "")
          + f"; picture {out}")
    return figures, others


def draw(figures, others, out):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    curve = np.array(figures["curve"])
    ax.plot(curve[:, 0], curve[:, 1], "-", color="tab:blue", lw=2,
            label="MPM, quadratic, B-bar (volumetric strain rate on the grid's vertices)")
    if others is not None:
        other = np.array(others["curve"])
        ax.plot(other[:, 0], other[:, 1], "--", color="tab:orange", lw=1.5,
                label="MPM, quadratic, without B-bar")
    ax.axhline(2 + np.pi, color="k", lw=1, label="Prandtl: q_ult = (2 + pi) c_u = 5.14 c_u")
    s_read, n_c = figures["read_at_settlement_over_B"], figures["bearing_capacity_factor"]
    ax.plot([s_read], [n_c], "o", color="tab:red", ms=7,
            label=f"N_c read at settlement 0.1 B: {n_c:.2f}")
    ax.set_xlabel("footing settlement / B")
    ax.set_ylabel("footing pressure q / c_u")
    ax.set_xlim(0, curve[-1, 0] * 1.02)
    ax.set_ylim(0, 6.5)
    ax.grid(True, alpha=0.3)
    ax.set_title(f"Rough strip footing on undrained clay: load-settlement curve\n"
                 f"{figures['cells_under_half_footing']} cell(s) under the half footing "
                 f"({figures['cells_across_width']} across 5 B)", fontsize=10)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main(*[int(v) for v in sys.argv[1:2]])
