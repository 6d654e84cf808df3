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

Past the limit load the pressure keeps rising: the footing sinks and the
clay beside it heaves, so the footing becomes embedded, its base a depth
D = settlement + heave below the ground beside it, and an embedded footing
carries more (Brinch Hansen's depth factor d_c = 1 + 0.4 D/B). The dotted
curve divides that out, q / d_c: once the clay has yielded it is flat (the
plateau), near 5.14.

Half model by symmetry (5 B wide, 5 B deep), quadratic B-splines, 2 x 2
particles per cell, E = 300 c_u, nu = 0.3, footing speed 0.05 B/s reached
over 0.4 s (the kinetic energy stays far below the plastic work), pushed
to a settlement of 0.25 B.

    python examples/strip_footing.py          # 40 cells over 5 B (4 under B/2), about a minute
    python examples/strip_footing.py 20       # 2 under B/2 (coarse: no plateau yet), ~10 s
"""
import sys

import numpy as np

from skfem_mpm import Method, simulate
from skfem_mpm.benchmarks import get_benchmark
from skfem_mpm.solve import prepare


def run(cells, bbar, settlement):
    bench = get_benchmark("strip-footing", bbar=float(bbar), settlement=settlement)
    scene = bench.scene(cells)
    steps = prepare(scene, Method()).n_steps or 100
    result = simulate(scene, Method(), save_every=max(1, steps // 60))  # for the heave
    return bench.checks(result), result.wall_time


def main(cells=40, out="strip_footing.png", without_bbar=True, settlement=0.25):
    figures, wall = run(cells, True, settlement)
    others = run(cells, False, settlement)[0] if without_bbar else None
    draw(figures, others, out)
    print(f"N_c = q / c_u at a settlement of 0.1 B: {figures['bearing_capacity_factor']:.3f} "
          f"(Prandtl 2 + pi = 5.142, {100 * figures['bearing_capacity_error']:+.1f}%), "
          f"{figures['cells_under_half_footing']} cells under the half footing, {wall:.0f} s"
          + (f"; without B-bar {others['bearing_capacity_factor']:.3f}" if others else "")
          + f"; with the embedment divided out {figures['bearing_capacity_depth_corrected']:.3f}"
          f" (base {figures['embedment'][-1][1]:.3f} B below the ground beside it at the end)"
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
    corrected = np.array(figures["curve_depth_corrected"])
    ax.plot(corrected[:, 0], corrected[:, 1], ":", color="tab:blue", lw=2,
            label="the same with the footing's embedment divided out: q / d_c,\n"
                  "d_c = 1 + 0.4 D/B, D = settlement + heave beside the footing")
    ax.axhline(2 + np.pi, color="k", lw=1, label="Prandtl: q_ult = (2 + pi) c_u = 5.14 c_u")
    s_read, n_c = figures["read_at_settlement_over_B"], figures["bearing_capacity_factor"]
    ax.plot([s_read], [n_c], "o", color="tab:red", ms=7,
            label=f"N_c read at settlement 0.1 B: {n_c:.2f}")
    ax.set_xlabel("footing settlement / B")
    ax.set_ylabel("footing pressure q / c_u")
    ax.set_xlim(0, curve[-1, 0] * 1.02)
    ax.set_ylim(0, 7.0)
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
