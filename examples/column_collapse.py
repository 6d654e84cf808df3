"""Collapse of a granular column (benchmark G2): a column of dry sand, L0
wide and H0 = a L0 high, held by a smooth wall on its left, is released
onto a rough floor and spreads under its own weight. The picture shows the
final deposit (particles coloured by accumulated plastic shear strain)
over the initial column, with the runout the experiments give for the
same aspect ratio (Lube, Huppert, Sparks, Freundt 2005: (L_inf - L0) / L0
= 1.2 a below a = 1.8, 1.9 a^(2/3) above 2.8) and the computed fronts:
where the deposit is still 0.05 L0 thick (the one compared with the
experiments), the last grain, and the place behind which 97% of the mass
lies. A strip below shows the deposit's thickness along the floor.

Soil: Mohr-Coulomb, friction angle 30 deg, no cohesion, no dilation,
stiff enough that elastic strains stay below 1e-3, grains out of contact
(no stress) once loosened 1% beyond their initial packing; floor friction
tan 30 deg; started from the at-rest stress K0 = 1 - sin(30 deg); run
until the motion has died out (10 sqrt(H0 / g)).

    python examples/column_collapse.py            # a = 1, 16 cells across L0 (~20 s)
    python examples/column_collapse.py 0.5 8      # a = 0.5, 8 cells (~2 s)
"""
import sys

import numpy as np

from skfem_mpm import Method, simulate
from skfem_mpm.benchmarks import get_benchmark


def main(a=1.0, cells=16, out="column_collapse.png"):
    bench = get_benchmark("column-collapse", a=a)
    scene = bench.scene(cells)
    result = simulate(scene, Method())
    figures = bench.checks(result)
    draw(result, bench, figures, cells, out)
    print(f"a = {a:g}: runout (L_inf - L0) / L0 = {figures['runout_thickness_front']:.2f} "
          f"(last grain {figures['runout']:.2f}, 97% of the mass "
          f"{figures['runout_97pct_mass']:.2f}) "
          f"(experiments {1.2 * a:.2f} for a < 1.8, {1.9 * a ** (2 / 3):.2f} for a > 2.8); "
          f"final height H_inf / H0 = {figures['final_height_ratio']:.2f}; picture {out}")
    return figures


def draw(result, bench, figures, cells, out):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from skfem_mpm.benchmarks import deposit_thickness

    p = result.particles
    L0, H0, a = bench.L0, bench.H0, bench.a
    low, high = 1.2 * a, 1.9 * a ** (2 / 3)
    laws = [(low, "-", "1.2 a")] if a < 1.8 else [(high, "-", "1.9 a^(2/3)")] if a > 2.8 \
        else [(low, "-", "1.2 a"), (high, ":", "1.9 a^(2/3)")]
    right = max([1 + v for v, _, _ in laws] + [1 + figures["runout"]]) * 1.08
    height = H0 * 1.1
    fig, (ax, strip) = plt.subplots(
        2, 1, sharex=True, figsize=(9, 2.6 + 6.5 * height / (right * L0)),
        gridspec_kw={"height_ratios": [max(height / (right * L0) * 6.5, 1.0), 1.0]})
    ax.plot([0, L0, L0], [H0, H0, 0], "k--", lw=1, label="initial column")
    size = 3000 * (L0 / right) ** 2 / p.n ** 0.5  # dots about the particle spacing
    dots = ax.scatter(p.x[:, 0] / L0, p.x[:, 1] / L0, c=p.state["plastic_strain"], s=size,
                      cmap="viridis", vmin=0, vmax=1)
    fig.colorbar(dots, ax=[ax, strip], label="plastic shear strain", shrink=0.8)
    fronts = [(figures["runout_thickness_front"], "-", 2.0,
               f"computed front, deposit 0.05 L0 thick: {figures['runout_thickness_front']:.2f}"),
              (figures["runout"], ":", 1.2, f"computed, last grain: {figures['runout']:.2f}"),
              (figures["runout_97pct_mass"], "--", 1.2,
               f"computed, 97% of the mass behind: {figures['runout_97pct_mass']:.2f}")]
    for axis in (ax, strip):
        for value, style, name in laws:
            axis.axvline(1 + value, color="tab:red", ls=style, lw=1.5,
                         label=f"experiments' front: (L - L0)/L0 = {name} = {value:.2f}"
                         if axis is ax else None)
        for value, style, width, name in fronts:
            axis.axvline(1 + value, color="tab:blue", ls=style, lw=width,
                         label=name if axis is ax else None)
    # the deposit's thickness along the floor: solid volume per length in
    # windows L0 / 8 wide (the measure of the 0.05 L0 front)
    window = L0 / 8
    centres = np.arange(0.0, right * L0, window / 8)
    strip.plot(centres / L0, deposit_thickness(p.x[:, 0], p.V0, centres, window) / L0, "k-",
               lw=1.2)
    strip.axhline(bench.front_thickness, color="tab:blue", lw=0.8)
    strip.set_ylabel("thickness / L0")
    strip.set_ylim(0, max(0.2, 0.3 * a))
    strip.set_xlabel("distance from the wall x / L0")
    ax.set_xlim(0, right)
    ax.set_ylim(0, height)
    ax.set_aspect("equal")
    ax.set_ylabel("height y / L0")
    ax.set_title(f"Granular column collapse, a = H0/L0 = {a:g}: the final deposit\n"
                 f"Mohr-Coulomb 30 deg, floor friction tan 30 deg, {cells} cells "
                 f"across L0", fontsize=10)
    ax.legend(loc="upper right", ncol=1, fontsize=7, framealpha=0.9)
    fig.savefig(out, dpi=110, bbox_inches="tight")
    plt.close(fig)


if __name__ == "__main__":
    args = [float(v) for v in sys.argv[1:3]]
    main(*(args[:1] + [int(v) for v in args[1:2]]))
