"""Collapse of a granular column (benchmark G2): a column of dry sand, L0
wide and H0 = a L0 high, held by a smooth wall on its left, is released
onto a rough floor and spreads under its own weight. The picture shows the
final deposit (particles coloured by accumulated plastic shear strain)
over the initial column, the computed front (the last grain, and the
place behind which 97% of the mass lies), with the runout the
experiments give for the same aspect ratio (Lube, Huppert, Sparks,
Freundt 2005: (L_inf - L0) / L0 = 1.2 a below a = 1.8, 1.9 a^(2/3) above
2.8).

Soil: Mohr-Coulomb, friction angle 30 deg, no cohesion, no dilation,
stiff enough that elastic strains stay below 1e-3; floor friction
tan 30 deg; started from the at-rest stress K0 = 1 - sin(30 deg).

    python examples/column_collapse.py            # a = 1, 16 cells across L0 (~2 min)
    python examples/column_collapse.py 0.5 8      # a = 0.5, 8 cells (~30 s)
"""
import sys

from skfem_mpm import Method, simulate
from skfem_mpm.benchmarks import get_benchmark


def main(a=1.0, cells=16, out="column_collapse.png"):
    bench = get_benchmark("column-collapse", a=a)
    scene = bench.scene(cells)
    result = simulate(scene, Method())
    figures = bench.checks(result)
    draw(result, bench, figures, cells, out)
    print(f"a = {a:g}: runout (L_inf - L0) / L0 = {figures['runout']:.2f} "
          f"(97% of the mass: {figures['runout_97pct_mass']:.2f}) "
          f"(experiments {1.2 * a:.2f} for a < 1.8, {1.9 * a ** (2 / 3):.2f} for a > 2.8); "
          f"final height H_inf / H0 = {figures['final_height_ratio']:.2f}; picture {out}")
    return figures


def draw(result, bench, figures, cells, out):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p = result.particles
    L0, H0, a = bench.L0, bench.H0, bench.a
    low, high = 1.2 * a, 1.9 * a ** (2 / 3)
    laws = [(low, "-", "1.2 a")] if a < 1.8 else [(high, "-", "1.9 a^(2/3)")] if a > 2.8 \
        else [(low, "-", "1.2 a"), (high, ":", "1.9 a^(2/3)")]
    right = max([1 + v for v, _, _ in laws] + [1 + figures["runout"]]) * 1.08
    fig, ax = plt.subplots(figsize=(9, 1.6 + 6.5 * H0 * 1.1 / (right * L0)))
    ax.plot([0, L0, L0], [H0, H0, 0], "k--", lw=1, label="initial column")
    size = 3000 * (L0 / right) ** 2 / p.n ** 0.5  # dots about the particle spacing
    dots = ax.scatter(p.x[:, 0] / L0, p.x[:, 1] / L0, c=p.state["plastic_strain"], s=size,
                      cmap="viridis", vmin=0, vmax=1)
    fig.colorbar(dots, ax=ax, label="plastic shear strain", shrink=0.8)
    for value, style, name in laws:
        ax.axvline(1 + value, color="tab:red", ls=style, lw=1.5,
                   label=f"experiments' front: (L - L0)/L0 = {name} = {value:.2f}")
    ax.axvline(1 + figures["runout"], color="tab:blue", lw=1.5,
               label=f"computed front (last grain): {figures['runout']:.2f}")
    ax.axvline(1 + figures["runout_97pct_mass"], color="tab:blue", ls="--", lw=1.2,
               label=f"computed, 97% of the mass behind: {figures['runout_97pct_mass']:.2f}")
    ax.set_xlim(0, right)
    ax.set_ylim(0, H0 * 1.1)
    ax.set_aspect("equal")
    ax.set_xlabel("distance from the wall x / L0")
    ax.set_ylabel("height y / L0")
    ax.set_title(f"Granular column collapse, a = H0/L0 = {a:g}: the final deposit\n"
                 f"Mohr-Coulomb 30 deg, floor friction tan 30 deg, {cells} cells "
                 f"across L0", fontsize=10)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.25), ncol=2, fontsize=8,
              frameon=False)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    args = [float(v) for v in sys.argv[1:3]]
    main(*(args[:1] + [int(v) for v in args[1:2]]))
