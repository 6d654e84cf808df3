"""Work-precision on S1 small (issue 18): error and wall time of the cheapest
linear run and of high-order runs near a relative error of 1e-6.

Each run is simulated once to warm up (compiles, caches), then the runs are
timed in alternation, ``--repeat`` rounds, so that the load of a shared
machine falls on all of them alike: compare the medians' ratios, not the
absolute times. Errors are S1's primary error (RMS at t_end, relative).

    python benchmarks/work_precision.py [--repeat 5]
"""
import argparse
import statistics
import time

RUNS = (  # label, cells, degree, ppc, Method keyword arguments
    ("p1 lumped usl, cfl 0.5", 512, 1, 4, dict(scheme="usl", mass="lumped", cfl=0.5)),
    ("p1 lumped usl, cfl 0.1", 512, 1, 4, dict(scheme="usl", mass="lumped", cfl=0.1)),
    ("p3 consistent spline rk4", 16, 3, 2,
     dict(scheme="rk4", mass="consistent", reconstruction="spline")),
    ("p3 consistent spline rk4", 12, 3, 2,
     dict(scheme="rk4", mass="consistent", reconstruction="spline")),
)


def main():
    from skfem_mpm import Method, simulate
    from skfem_mpm.benchmarks import get_benchmark

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5, help="timed rounds (default 5)")
    a = ap.parse_args()
    b = get_benchmark("vibrating-string", "small")
    jobs = [(label, cells, b.scene(cells, p, ppc), Method(**kw))
            for label, cells, p, ppc, kw in RUNS]
    errors, steps, times = {}, {}, {i: [] for i in range(len(jobs))}
    for i, (_, _, scene, method) in enumerate(jobs):
        r = simulate(scene, method)
        errors[i], steps[i] = b.errors(r)["error_rms"], r.counts["steps"]
    for _ in range(a.repeat):
        for i, (_, _, scene, method) in enumerate(jobs):
            t0 = time.perf_counter()
            simulate(scene, method)
            times[i].append(time.perf_counter() - t0)
    base = statistics.median(times[0])
    print("| run | cells | error | steps | wall median [ms] (range) | / first |")
    print("|---|---|---|---|---|---|")
    for i, (label, cells, _, _) in enumerate(jobs):
        t = times[i]
        print(f"| {label} | {cells} | {errors[i]:.3g} | {steps[i]} | "
              f"{1e3 * statistics.median(t):.1f} ({1e3 * min(t):.1f}-{1e3 * max(t):.1f}) | "
              f"{statistics.median(t) / base:.2f} |")


if __name__ == "__main__":
    main()
