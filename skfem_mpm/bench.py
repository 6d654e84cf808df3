"""Throughput of the MPM step: particle-steps per second (``skfem-mpm bench``).

The problems (as in the project's performance issue):

* 2D: unit square, 128 x 128 cells, quadratic B-splines, 4 x 4 particles per
  cell in the middle half (65,536 particles), small-strain linear elasticity,
  gravity, fixed edges, 200 explicit steps, float64, lumped mass.
* 1D: 250,000 cells, quadratic, 4 particles per cell (1e6 particles), the
  same physics, 200 steps.
* 3D: unit cube, 64^3 cells, quadratic, 2 x 2 x 2 particles per cell in
  the middle half [0.25, 0.75]^3 (262,144 particles), the same physics, all
  faces fixed, dt 1e-5, 100 steps.

Each figure is the median of ``repeat`` runs of the project's own
``simulate`` (USL, and MUSL beside it), with JIT compilation excluded and
reported separately.

The USL rows are compared with a plain C loop of the same step
(:mod:`skfem_mpm.reference_c`), compiled now with the system's C compiler
(``$CC``, else ``cc``/``gcc``; ``-O3 -march=native -fopenmp``) and run on
the same problem in turn with ours, on as many OpenMP threads as numba uses
and on one. A ratio is printed only when the C run ended in the same final
particle state (to round-off); with no compiler the bench says why the
ratio is unavailable.

Peak memory per particle is measured in a child process: its peak resident
memory during ``simulate`` minus its resident memory just before, with the
scene (the user's particles) already built (tracemalloc does not see
numba's arrays). The scaling series keeps 4 x 4 particles per cell and
grows the grid with the particles.

    python -m skfem_mpm.bench [--quick] [--repeat 5] [--json] [--reference] [--consistent]
"""
import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

__all__ = ["consistent_scene", "main", "run", "run_with_c", "scene_1d", "scene_2d", "scene_3d"]

C_TARGET = 0.9  # the target: our USL throughput >= 0.9x the C loop's


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


def scene_3d(cells=64, ppc=2, degree=2, steps=100, dt=1e-5):
    """The 3D problem; returns (scene, dt)."""
    from . import Body, Fixed, Gravity, LinearElastic, Particles, Scene, SplineGrid

    grid = SplineGrid.box((0, 1), (0, 1), (0, 1), cells, degree)
    particles = Particles.seed(grid, ppc, 1.0, region=((0.25, 0.75),) * 3)
    effects = [Gravity((0.0, 0.0, -9.81))] + [Fixed(s) for s in (
        "xmin", "xmax", "ymin", "ymax", "zmin", "zmax")]
    return Scene(grid, Body(particles, LinearElastic(1e4, 0.3)), steps * dt,
                 effects=effects), dt


def consistent_scene(cells, steps, problem="falling block"):
    """The 2D problem at the consistent mass's time step (cfl 0.5 of its
    critical step): ``"falling block"`` (stress free: its grid acceleration
    is g, which the CG warm start already meets) or ``"expanding block"``
    (initial v = 0.4 (x - 0.5), which sends stress waves through it).
    Returns (scene, dt)."""
    from .solve.timestep import critical_time_step
    from .validation import check_choice

    check_choice("problem", problem, ("falling block", "expanding block"))
    scene, _ = scene_2d(cells=cells, steps=steps)
    body = scene.bodies[0]
    if problem == "expanding block":
        body.particles.v = 0.4 * (body.particles.x - 0.5)
    dt = 0.5 * critical_time_step(scene.grid, np.sqrt(body.material.modulus(2)), "consistent")
    return type(scene)(scene.grid, scene.bodies, steps * dt, effects=scene.effects), dt


def _rates(results):
    return [r.counts["particles"] * r.counts["steps"] / r.wall_time for r in results]


def run(scene, dt, scheme="usl", mass="lumped", backend=None, repeat=3, alongside=None):
    """Median particle-steps per second, JIT seconds, and the phase split of
    the median run (a dict). ``alongside(result)``, if given, is called
    after each run (what it times alternates with ours)."""
    from .solve import Method, simulate

    method = Method(scheme=scheme, mass=mass, dt=dt * (1 - 1e-9), backend=backend)
    results = []
    for _ in range(repeat):
        results.append(simulate(scene, method))
        if alongside is not None:
            alongside(results[-1])
    rates = _rates(results)
    median = sorted(range(repeat), key=lambda i: rates[i])[repeat // 2]
    r = results[median]
    return {"particle_steps_per_s": float(statistics.median(rates)),
            "runs": [float(x) for x in rates], "jit_time_s": float(results[0].jit_time),
            "wall_time_s": float(r.wall_time), "steps": int(r.counts["steps"]),
            "particles": int(r.counts["particles"]), "path": r.path,
            "phases": {k: float(v) for k, v in r.timings.items() if v > 0},
            "fused": {k: list(v) for k, v in r.fused.items()}}


def run_with_c(scene, dt, reference, directory, repeat=3, threads=None):
    """Our USL row (as :func:`run`) and the C reference's on the same
    problem, run in turn: after each of our runs, one C run on ``threads``
    OpenMP threads (numba's count by default) and one on a single thread.
    Returns (our row, the C figures: per thread count the median
    particle-steps per second and the runs, whether every C run ended in
    our final state, the largest scaled differences, and our ratios to
    the C figures, None when the states differ)."""
    from numba import get_num_threads

    from .reference_c import compare, run_reference, write_problem
    from .solve import Method

    threads = get_num_threads() if threads is None else int(threads)
    counts = sorted({threads, 1}, reverse=True)
    directory = Path(directory)
    problem_path, output_path = directory / "problem.bin", directory / "final.bin"
    problem = write_problem(problem_path, scene, Method(scheme="usl", dt=dt * (1 - 1e-9)))
    seconds = {t: [] for t in counts}
    checks = []

    def alongside(result):
        for t in counts:
            out = run_reference(reference, problem_path, output_path, t)
            seconds[t] += out["seconds"]
            agrees, differences = compare(result.particles, out["final"], problem)
            checks.append((agrees and out["invalid"] == 0, differences, out["invalid"]))

    ours = run(scene, dt, "usl", repeat=repeat, alongside=alongside)
    work = problem["particles"] * problem["steps"]
    agrees = all(ok for ok, _, _ in checks)
    c = {"threads": threads, "agrees": agrees,
         "differences": {k: max(d[k] for _, d, _ in checks) for k in checks[0][1]},
         "invalid_particles": max(i for _, _, i in checks)}
    for t in counts:
        rates = [work / s for s in seconds[t]]
        key = "single_thread" if t == 1 else "threaded"
        c[key] = {"threads": t, "particle_steps_per_s": float(statistics.median(rates)),
                  "runs": [float(x) for x in rates]}
        c[f"ratio_{key}"] = ours["particle_steps_per_s"] / c[key]["particle_steps_per_s"] \
            if agrees else None
    return ours, c


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
# imports and JIT: a scene large enough for the same kernels as the measured
# one (the compiled loop runs serial kernel copies below SERIAL_BELOW particles)
small, dt = scene_{dim}d(cells={cells} // 2, steps=2)
simulate(small, Method(scheme="usl", dt=dt * (1 - 1e-9)))
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


CONSISTENT_VARIANTS = (
    ("lumped", {"mass": "lumped"}, None),
    ("consistent, CG + Kronecker + fringe", {"mass": "consistent", "mass_solver": "cg"},
     "kronecker+fringe"),
    ("consistent, CG + Kronecker", {"mass": "consistent", "mass_solver": "cg"}, "kronecker"),
    ("consistent, CG + lumped (Jacobi)", {"mass": "consistent", "mass_solver": "cg"},
     "lumped"),
    ("consistent, sparse LU", {"mass": "consistent", "mass_solver": "direct"}, None),
)
"""(label, Method options, stencil CG preconditioner or None)."""


def consistent_comparison(cells=(64, 128), steps=20, repeat=3):
    """Step time of consistent against lumped mass on the 2D problem (USL),
    all at the consistent mass's time step, on both problems of
    :func:`consistent_scene`: lumped; consistent with the stencil CG and
    each of its preconditioners (Kronecker with the fringe correction, the
    default; Kronecker alone; the lumped mass, i.e. Jacobi); a fresh sparse
    LU factorisation each step. Returns rows with ms per step, the phase
    split of the median run and the mean CG iterations per solve."""
    from .solve import Method, simulate
    from .solve.stencil_system import preconditioned_with

    rows = []
    for n in cells:
        for problem in ("falling block", "expanding block"):
            scene, dt = consistent_scene(n, steps, problem)
            for label, options, preconditioner in CONSISTENT_VARIANTS:
                counted = None
                if preconditioner is None:
                    results = [simulate(scene, Method(scheme="usl", dt=dt, **options))
                               for _ in range(repeat)]
                else:
                    with preconditioned_with(preconditioner) as counted:
                        results = [simulate(scene, Method(scheme="usl", dt=dt, **options))
                                   for _ in range(repeat)]
                results.sort(key=lambda r: r.wall_time / r.counts["steps"])
                r = results[repeat // 2]  # the median run, its phases too
                rows.append({"cells": n, "problem": problem, "variant": label,
                             "ms_per_step": r.wall_time / r.counts["steps"] * 1e3,
                             "phases_ms_per_step": {k: v / r.counts["steps"] * 1e3
                                                    for k, v in r.timings.items() if v > 0},
                             "cg_iterations_per_solve": (float(np.mean(counted))
                                                         if counted else None)})
            chosen = rows[-len(CONSISTENT_VARIANTS):]
            for row in chosen:
                row["ratio_to_lumped"] = row["ms_per_step"] / chosen[0]["ms_per_step"]
    return rows


def machine():
    """What the figures were measured on: CPU model, cores, system."""
    model = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    model = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {"cpu": model, "cores": os.cpu_count(), "system": platform.platform(),
            "python": platform.python_version()}


def _usl_rows(report, rows, repeat):
    """Our USL rows ``rows`` = [(key, scene, dt)] into ``report``, each with
    the C reference beside it in report["c_reference"][key] (or, when it
    cannot run here, report["c_reference"]["reason"])."""
    from .reference_c import ReferenceUnavailable, compile_reference

    with tempfile.TemporaryDirectory(prefix="skfem-mpm-bench-") as directory:
        try:
            reference = compile_reference(directory)
            report["c_reference"] = {"available": True, "compiler": reference.description}
        except ReferenceUnavailable as exc:
            reference = None
            report["c_reference"] = {"available": False, "reason": str(exc)}
        for key, scene, dt in rows:
            if reference is None:
                report[key] = run(scene, dt, "usl", repeat=repeat)
                continue
            try:
                report[key], report["c_reference"][key] = run_with_c(
                    scene, dt, reference, directory, repeat=repeat)
            except RuntimeError as exc:  # the C program itself failed
                report["c_reference"] = {"available": False, "reason": str(exc)}
                reference = None
                report[key] = run(scene, dt, "usl", repeat=repeat)


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
    report = {"machine": machine(), "threads": int(__import__("numba").get_num_threads()),
              "repeat": repeat}
    s2, dt2 = scene_2d(cells=64 if args.quick else 128, steps=steps)
    s1, dt1 = scene_1d(cells=25_000 if args.quick else 250_000, steps=steps)
    s3, dt3 = scene_3d(cells=16 if args.quick else 64, steps=10 if args.quick else 100)
    _usl_rows(report, [("2d_usl", s2, dt2), ("1d_usl", s1, dt1), ("3d_usl", s3, dt3)], repeat)
    report["2d_musl"] = run(s2, dt2, "musl", repeat=repeat)
    if args.reference:
        report["2d_usl_reference"] = ref = run(s2, dt2, "usl", backend="numpy", repeat=1)
        ref["ratio_compiled_to_reference"] = (report["2d_usl"]["particle_steps_per_s"]
                                              / ref["particle_steps_per_s"])
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
        report["memory_3d_bytes_per_particle"] = memory_child(3, 64, 10)
        series = []
        for cells in (16, 32, 64):
            s, dt = scene_3d(cells=cells, steps=20)
            r = run(s, dt, "usl", repeat=3)
            series.append({"cells": cells, "particles": r["particles"],
                           "wall_time_s": r["wall_time_s"],
                           "particle_steps_per_s": r["particle_steps_per_s"]})
        for a, b in zip(series, series[1:]):
            b["time_ratio_for_8x_particles"] = b["wall_time_s"] / a["wall_time_s"]
        report["scaling_3d"] = series
    if args.consistent:
        report["consistent_2d"] = consistent_comparison(
            cells=(32, 64) if args.quick else (64, 128, 256), steps=10 if args.quick else 20,
            repeat=1 if args.quick else 3)
    if args.json:
        print(json.dumps(report, indent=2))
        return 0
    _print_report(report, repeat)
    return 0


def _print_c_reference(report):
    c = report["c_reference"]
    if not c["available"]:
        print(f"C reference unavailable: {c['reason']}")
        return
    print(f"C reference ({c['compiler']}, usl_step.c of skfem_mpm.reference_c), compiled and "
          f"run now on the same problems, in turn with ours:")
    for key in ("2d_usl", "1d_usl", "3d_usl"):
        row = c.get(key)
        if row is None:
            continue
        figures = "; ".join(
            f"C {row[k]['threads']} thread{'s' if row[k]['threads'] > 1 else ''} "
            f"{row[k]['particle_steps_per_s'] / 1e6:.2f} M"
            for k in ("threaded", "single_thread") if k in row)
        differences = ", ".join(f"{k} {v:.1e}" for k, v in row["differences"].items())
        if not row["agrees"]:
            print(f"{key:18s} {figures}")
            print(f"{'':18s} WARNING: the C reference did not end in our final state "
                  f"(largest differences, scaled: {differences}; invalid particles "
                  f"{row['invalid_particles']}): no ratio")
            continue
        ratios = "; ".join(
            f"{row[f'ratio_{k}']:.2f}x C on {row[k]['threads']} thread"
            f"{'s' if row[k]['threads'] > 1 else ''}"
            for k in ("threaded", "single_thread") if k in row)
        print(f"{key:18s} {figures} particle-steps/s; ours {ratios} "
              f"(target >= {C_TARGET}x the threaded C); same final state "
              f"(scaled differences {differences})")


def _print_report(report, repeat):
    m = report["machine"]
    print(f"machine: {m['cpu']}, {m['cores']} cores, {m['system']}, Python {m['python']}")
    print(f"threads: {report['threads']} (numba), median of {repeat} run(s), JIT excluded; "
          f"compared only with references run now, on this machine")
    for key in ("2d_usl", "2d_musl", "2d_usl_reference", "1d_usl", "1d_musl", "3d_usl"):
        if key not in report:
            continue
        r = report[key]
        print(f"{key:18s} {r['particle_steps_per_s'] / 1e6:8.2f} M particle-steps/s, "
              f"{r['particles']} particles x {r['steps']} steps, JIT {r['jit_time_s']:.2f} s, "
              f"path {r['path']}")
        split = ", ".join(f"{k} {v / r['wall_time_s'] * 100:.0f}%" for k, v in r["phases"].items())
        print(f"{'':18s} phases: {split}")
        if "ratio_compiled_to_reference" in r:
            print(f"{'':18s} the compiled 2d_usl above: {r['ratio_compiled_to_reference']:.1f}x "
                  f"this NumPy reference path (both measured in this run)")
    _print_c_reference(report)
    if "memory_2d_bytes_per_particle" in report:
        print(f"2D peak memory: {report['memory_2d_bytes_per_particle']:.0f} bytes per particle "
              f"(target <= 300)")
    if "memory_3d_bytes_per_particle" in report:
        print(f"3D peak memory: {report['memory_3d_bytes_per_particle']:.0f} bytes per particle "
              f"(target <= 400)")
    for row in report.get("consistent_2d", []):
        split = ", ".join(f"{k} {v:.2f}" for k, v in row["phases_ms_per_step"].items())
        its = row["cg_iterations_per_solve"]
        extra = f", CG iterations per solve {its:.1f}" if its is not None else ""
        print(f"consistent {row['cells']:>4d}^2 {row['problem']:15s} {row['variant']:36s} "
              f"{row['ms_per_step']:8.2f} ms/step (x{row['ratio_to_lumped']:.1f} lumped){extra}; "
              f"ms/step: {split}")
    for row in report.get("scaling_2d", []):
        ratio = row.get("time_ratio_for_4x_particles")
        extra = f", time x{ratio:.2f} for 4x particles" if ratio else ""
        print(f"scaling: {row['particles']:>8d} particles "
              f"{row['particle_steps_per_s'] / 1e6:7.2f} M/s{extra}")
    for row in report.get("scaling_3d", []):
        ratio = row.get("time_ratio_for_8x_particles")
        extra = f", time x{ratio:.2f} for 8x particles" if ratio else ""
        print(f"scaling 3D: {row['particles']:>8d} particles "
              f"{row['particle_steps_per_s'] / 1e6:7.2f} M/s{extra}")


if __name__ == "__main__":
    sys.exit(main())
