"""Throughput of the MPM step: particle-steps per second (``skfem-mpm bench``).

The problems (as in the project's performance issue):

* 2D: unit square, 128 x 128 cells, quadratic B-splines, 4 x 4 particles per
  cell in the middle half (65,536 particles), small-strain linear elasticity,
  gravity, fixed edges, 200 explicit steps, float64, lumped mass.
* 1D: 250,000 cells, quadratic, 4 particles per cell (1e6 particles), the
  same physics, 200 steps.

Each figure is the median of ``repeat`` runs of the project's own
``simulate`` (USL, and MUSL beside it), with JIT compilation excluded and
reported separately. Peak memory per particle is measured in a child
process: its peak resident memory during ``simulate`` minus its resident
memory just before, with the scene (the user's particles) already built
(tracemalloc does not see numba's arrays).
The scaling series keeps 4 x 4 particles per cell and grows the grid with
the particles.

    python -m skfem_mpm.bench [--quick] [--repeat 5] [--json] [--reference] [--consistent]
"""
import argparse
import json
import os
import statistics
import subprocess
import sys
import time

import numpy as np

__all__ = ["scene_2d", "scene_1d", "run", "main"]


def scene_2d(cells=128, ppc=4, degree=2, steps=200):
    """The 2D problem; returns (scene, dt)."""
    from . import Body, Fixed, Gravity, LinearElastic, Particles, Scene, SplineGrid
    from .solve.timestep import critical_time_step

    grid = SplineGrid.rectangle((0, 1), (0, 1), cells, degree)
    particles = Particles.seed(grid, ppc, 1.0, region=((0.25, 0.75), (0.25, 0.75)))
    material = LinearElastic(1e4, 0.3)
    dt = 0.5 * critical_time_step(grid, np.sqrt(material.modulus(2)), "lumped")
    effects = [Gravity((0.0, -9.81))] + [Fixed(s) for s in ("left", "right", "bottom", "top")]
    return Scene(grid, Body(particles, material), steps * dt, effects=effects), dt


def scene_1d(cells=250_000, ppc=4, degree=2, steps=200):
    """The 1D problem; returns (scene, dt)."""
    from . import Body, Fixed, Gravity, LinearElastic, Particles, Scene, SplineGrid
    from .solve.timestep import critical_time_step

    grid = SplineGrid.line(0.0, 1.0, cells, degree)
    particles = Particles.seed(grid, ppc, 1.0)
    material = LinearElastic(1e4)
    dt = 0.5 * critical_time_step(grid, np.sqrt(material.E), "lumped")
    return (Scene(grid, Body(particles, material), steps * dt,
                  effects=[Gravity(-9.81), Fixed("left"), Fixed("right")]), dt)


def run(scene, dt, scheme="usl", mass="lumped", backend=None, repeat=3):
    """Median particle-steps per second, JIT seconds, and the phase split of
    the median run (a dict)."""
    from .solve import Method, simulate

    method = Method(scheme=scheme, mass=mass, dt=dt * (1 - 1e-9), backend=backend)
    results = [simulate(scene, method) for _ in range(repeat)]
    rates = [r.counts["particles"] * r.counts["steps"] / r.wall_time for r in results]
    median = sorted(range(repeat), key=lambda i: rates[i])[repeat // 2]
    r = results[median]
    return {"particle_steps_per_s": float(statistics.median(rates)),
            "runs": [float(x) for x in rates], "jit_time_s": float(results[0].jit_time),
            "wall_time_s": float(r.wall_time), "steps": int(r.counts["steps"]),
            "particles": int(r.counts["particles"]), "path": r.path,
            "phases": {k: float(v) for k, v in r.timings.items() if v > 0},
            "fused": {k: list(v) for k, v in r.fused.items()}}


def _rss_kb(field):
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    raise RuntimeError(f"{field} not in /proc/self/status")


def memory_child(dim, cells, steps):
    """In a child process: bytes per particle of peak RSS above the baseline."""
    code = f"""
import json
from skfem_mpm.bench import scene_{dim}d, _rss_kb
from skfem_mpm.solve import Method, simulate
small, dt = scene_{dim}d(cells=8, steps=2)
simulate(small, Method(scheme="usl", dt=dt * (1 - 1e-9)))   # imports and JIT
scene, dt = scene_{dim}d(cells={cells}, steps={steps})   # the user's particles
method = Method(scheme="usl", dt=dt * (1 - 1e-9))
with open("/proc/self/clear_refs", "w") as f:
    f.write("5")   # reset the peak
base = _rss_kb("VmRSS")
r = simulate(scene, method)
peak = _rss_kb("VmHWM")
print(json.dumps({{"bytes_per_particle": (peak - base) * 1024 / r.counts["particles"]}}))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])["bytes_per_particle"]


def consistent_comparison(cells=(64, 128), steps=20, repeat=3):
    """Step time of consistent against lumped mass on the 2D problem (USL),
    all at the consistent mass's default time step (cfl 0.5 of its critical
    step): lumped; consistent with the stencil CG and its Kronecker
    preconditioner with the fringe correction (the default), without it,
    and with the lumped-mass (Jacobi) preconditioner; a fresh sparse LU
    factorisation each step. The 2D problem's block falls freely (it is
    stress free: its grid acceleration is g, which the CG warm start
    already meets), so lumped and the default consistent solver are also
    run on the same block expanding (initial v = 0.4 (x - 0.5)), which
    sends stress waves through it. Returns rows with ms per step, the phase
    split of the median run and the mean CG iterations per solve."""
    from .solve import Method, simulate
    from .solve import stencil_system as fast_module
    from .solve.timestep import critical_time_step

    cg = dict(mass="consistent", mass_solver="cg")
    layers = fast_module.StencilSystem.FRINGE_LAYERS
    variants = (("lumped", dict(mass="lumped"), None, layers),
                ("consistent, CG + Kronecker + fringe", cg, "kronecker", layers),
                ("consistent, CG + Kronecker", cg, "kronecker", 0),
                ("consistent, CG + lumped", cg, "lumped", layers),
                ("consistent, sparse LU", dict(mass="consistent", mass_solver="direct"), None,
                 layers))
    rows = []
    for n in cells:
        for problem in ("falling block", "expanding block"):
            scene, _ = scene_2d(cells=n, steps=steps)
            body = scene.bodies[0]
            if problem == "expanding block":
                body.particles.v = 0.4 * (body.particles.x - 0.5)
            dt = 0.5 * critical_time_step(scene.grid, np.sqrt(body.material.modulus(2)),
                                          "consistent")
            scene = type(scene)(scene.grid, scene.bodies, steps * dt, effects=scene.effects)
            chosen = variants if problem == "falling block" else variants[:2]
            for label, options, preconditioner, fringe_layers in chosen:
                saved = fast_module.StencilSystem.preconditioner
                if preconditioner:
                    fast_module.StencilSystem.preconditioner = preconditioner
                fast_module.StencilSystem.FRINGE_LAYERS = fringe_layers
                counted = fast_module.StencilSystem.iteration_log = []
                try:
                    results = [simulate(scene, Method(scheme="usl", dt=dt, **options))
                               for _ in range(repeat)]
                finally:
                    fast_module.StencilSystem.iteration_log = None
                    fast_module.StencilSystem.preconditioner = saved
                    fast_module.StencilSystem.FRINGE_LAYERS = layers
                results.sort(key=lambda r: r.wall_time / r.counts["steps"])
                r = results[repeat // 2]  # the median run, its phases too
                rows.append({"cells": n, "problem": problem, "variant": label,
                             "ms_per_step": r.wall_time / r.counts["steps"] * 1e3,
                             "phases_ms_per_step": {k: v / r.counts["steps"] * 1e3
                                                    for k, v in r.timings.items() if v > 0},
                             "cg_iterations_per_solve": (float(np.mean(counted))
                                                         if preconditioner else None)})
            base = rows[-len(chosen)]["ms_per_step"]
            for row in rows[-len(chosen):]:
                row["ratio_to_lumped"] = row["ms_per_step"] / base
    return rows


TARGETS = {"2d_usl": 25e6, "1d_usl": 100e6}
REFERENCE = {"2d": {"C -O3 OpenMP 2 threads": 28e6, "C single thread": 15e6,
                    "numba parallel 2 threads": 23e6, "NVIDIA Warp CPU": 12e6,
                    "Taichi CPU 2 threads": 8.5e6, "best pure NumPy": 3.0e6,
                    "SciPy CSR transfers": 2.3e6},
             "1d": {"numba 2 threads": 125e6, "C OpenMP": 113e6, "C single thread": 64e6,
                    "Taichi": 57e6, "Warp": 47e6, "NumPy": 14e6}}


def main(argv=None):
    parser = argparse.ArgumentParser(description="MPM throughput (particle-steps per second)")
    parser.add_argument("--quick", action="store_true", help="smaller problems, fewer runs")
    parser.add_argument("--repeat", type=int, default=None)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--reference", action="store_true",
                        help="also time the NumPy reference path")
    parser.add_argument("--consistent", action="store_true",
                        help="also compare consistent with lumped mass (2D, 64^2 to 256^2)")
    args = parser.parse_args(argv)
    repeat = args.repeat or (1 if args.quick else 5)
    steps = 20 if args.quick else 200
    report = {"threads": int(__import__("numba").get_num_threads()), "repeat": repeat}
    s2, dt2 = scene_2d(cells=64 if args.quick else 128, steps=steps)
    report["2d_usl"] = run(s2, dt2, "usl", repeat=repeat)
    report["2d_musl"] = run(s2, dt2, "musl", repeat=repeat)
    if args.reference:
        report["2d_usl_reference"] = run(s2, dt2, "usl", backend="numpy", repeat=1)
    s1, dt1 = scene_1d(cells=25_000 if args.quick else 250_000, steps=steps)
    report["1d_usl"] = run(s1, dt1, "usl", repeat=repeat)
    report["1d_musl"] = run(s1, dt1, "musl", repeat=repeat)
    if not args.quick:
        report["memory_2d_bytes_per_particle"] = memory_child(2, 128, 20)
        series = []
        for cells in (64, 128, 256, 512):
            s, dt = scene_2d(cells=cells, steps=50)
            r = run(s, dt, "usl", repeat=3)
            series.append({"cells": cells, "particles": r["particles"],
                           "wall_time_s": r["wall_time_s"],
                           "particle_steps_per_s": r["particle_steps_per_s"]})
        for a, b in zip(series, series[1:]):
            b["time_ratio_for_4x_particles"] = b["wall_time_s"] / a["wall_time_s"]
        report["scaling_2d"] = series
    if args.consistent:
        report["consistent_2d"] = consistent_comparison(
            cells=(32, 64) if args.quick else (64, 128, 256), steps=10 if args.quick else 20,
            repeat=1 if args.quick else 3)
    if args.json:
        print(json.dumps(report, indent=2))
        return 0
    print(f"threads: {report['threads']}, median of {repeat} run(s), JIT excluded")
    for key in ("2d_usl", "2d_musl", "2d_usl_reference", "1d_usl", "1d_musl"):
        if key not in report:
            continue
        r = report[key]
        target = TARGETS.get(key)
        note = f" (target {target / 1e6:.0f} M)" if target else ""
        print(f"{key:18s} {r['particle_steps_per_s'] / 1e6:8.2f} M particle-steps/s{note}, "
              f"{r['particles']} particles x {r['steps']} steps, JIT {r['jit_time_s']:.2f} s, "
              f"path {r['path']}")
        split = ", ".join(f"{k} {v / r['wall_time_s'] * 100:.0f}%" for k, v in r["phases"].items())
        print(f"{'':18s} phases: {split}")
    for dim in ("2d", "1d"):
        ours = report[f"{dim}_usl"]["particle_steps_per_s"]
        ratios = ", ".join(f"{name} {ours / rate:.2f}x" for name, rate in REFERENCE[dim].items())
        print(f"{dim} USL against the reference implementations: {ratios}")
    if "memory_2d_bytes_per_particle" in report:
        print(f"2D peak memory: {report['memory_2d_bytes_per_particle']:.0f} bytes per particle "
              f"(target <= 300)")
    for row in report.get("consistent_2d", []):
        split = ", ".join(f"{k} {v:.2f}" for k, v in row["phases_ms_per_step"].items())
        its = row["cg_iterations_per_solve"]
        extra = f", CG iterations per solve {its:.1f}" if its is not None else ""
        print(f"consistent {row['cells']:>4d}^2 {row['problem']:15s} {row['variant']:28s} "
              f"{row['ms_per_step']:8.2f} ms/step (x{row['ratio_to_lumped']:.1f} lumped){extra}; "
              f"ms/step: {split}")
    for row in report.get("scaling_2d", []):
        ratio = row.get("time_ratio_for_4x_particles")
        extra = f", time x{ratio:.2f} for 4x particles" if ratio else ""
        print(f"scaling: {row['particles']:>8d} particles "
              f"{row['particle_steps_per_s'] / 1e6:7.2f} M/s{extra}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
