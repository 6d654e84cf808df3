"""Work-precision (issue 18): the time each method takes to reach a relative
error e, and the cheapest high-order method against the cheapest linear one.

Per case (S1 small and S3 small at e = 1e-6, target ratio 10; D2 small at
e = 1e-5, target 5) every method runs at every grid of its class: linear MPM
(degree 1: lumped / consistent mass x musl / usl / cd, and hybrid musl) up
to 1,024 cells, high order (degree 2 and 3, consistent mass, reconstruction
none / spline / tls x cd / rk4, and lumped mass x cd / rk4) up to 128 cells
(D2: 256 and 64 per axis); each scheme's default cfl (0.6 of rk4's own
limit, 0.5 of the others': skfem_mpm.solve.method.DEFAULT_CFL).
S2 large (grid crossing, ``--cases s2``): the consistent high-order methods
at 20-160 cells, errors against the same-model reference, no target.

Timing: every job is first run for a few steps, untimed, so that every
kernel it calls is compiled or loaded (:func:`skfem_mpm.study.warm_up_run`,
every job twice;
``timed_compiles`` counts any that still load in the timed runs: 0 means no
compilation in the figures); then ``--rounds`` rounds each run every job
once, in alternation, so that the load of a shared machine falls on all of
them alike; a job whose timed runs have already taken ``--budget`` seconds
stops after two. Each timed run records the study's time, the run's
``wall_time`` (its steps: set-up, compilation and the last save excluded),
the CPU time of the same interval (``Result.cpu_time``, one thread:
NUMBA_NUM_THREADS=1 is required) and the CPU time of the whole
``simulate`` call (``call_cpu_time_s``: what a user waits for, set-up
included); the medians go into the records. The time to reach e is the
study's (:func:`skfem_mpm.study.time_to_reach`: log-log interpolation between
the two runs that bracket e, never extrapolated) on the steps' CPU time
(``--time wall``: their wall time, ``--time call``: the whole call's CPU);
the cheapest of each class is the smallest time to reach e among its
methods, and the ratio linear / high order is the target's measure.

    NUMBA_NUM_THREADS=1 python benchmarks/work_precision.py --cases s1 --json s1.jsonl
    python benchmarks/work_precision.py --from s1.jsonl     # the tables again

Method names are the study's (:func:`skfem_mpm.study.parse_method`), with an
optional ``@N``: N particles per cell and axis instead of ``--ppc``.
"""
import argparse
import json
import math
import os
import statistics
import sys
import time

CASES = {  # benchmark, variant, target error, target ratio, dim
    "s1": ("vibrating-string", "small", 1e-6, 10.0, 1),
    "s3": ("traction-bar", "small", 1e-6, 10.0, 1),
    "d2": ("vibrating-plate-2d", "small", 1e-5, 5.0, 2),
    # grid crossing; errors against the same-model reference (the study's
    # compare_with="auto"); no target, the high-order table only
    "s2": ("soil-column", "large", None, None, 1),
}
LINEAR = tuple(f"mpm-p1-{m}-{s}" for m in ("lumped", "consistent") for s in ("musl", "usl", "cd")) \
    + ("mpm-p1-hybrid-musl",)
HIGH = tuple(f"mpm-p{p}-consistent-{r}-{s}" for p in (2, 3) for r in ("none", "spline", "tls")
             for s in ("cd", "rk4")) \
    + tuple(f"mpm-p{p}-lumped-{s}" for p in (2, 3) for s in ("cd", "rk4"))
# cells per axis: (linear, high order)
CELLS = {"s1": ((8, 16, 32, 64, 128, 256, 512, 1024), (8, 16, 32, 64, 128)),
         "s3": ((8, 16, 32, 64, 128, 256, 512, 1024), (8, 16, 32, 64, 128)),
         "d2": ((8, 16, 32, 64, 128, 256), (8, 16, 32, 64)),
         "s2": ((), (20, 40, 80, 160))}
# the study's 2 per cell in 1D; 3 x 3 in 2D, where the published tls is well posed
PPC = {"s1": 2, "s3": 2, "d2": 3, "s2": 2}
# S2 large: degree 2 and 3 x none / spline / tls x cd / rk4 (issue 18)
S2_METHODS = tuple(m for m in HIGH if "-consistent-" in m)


def method_spec(name, ppc):
    """(study method spec, particles per cell) of ``name[@ppc]``."""
    from skfem_mpm.study import parse_method

    base, _, n = name.partition("@")
    spec = parse_method(base)
    spec["name"] = name
    return spec, int(n) if n else ppc


def make_jobs(case, methods, linear_cells, high_cells, ppc, options=None):
    """The study's job dicts: every method at every grid of its class
    (``options``: further Method keyword arguments of every run)."""
    benchmark, variant = CASES[case][:2]
    jobs = []
    for name in methods:
        spec, n = method_spec(name, ppc)
        for cells in (linear_cells if spec["degree"] == 1 else high_cells):
            jobs.append({"benchmark": benchmark, "variant": variant, "params": {},
                         "method": spec, "cells": cells, "ppc": n, "case": case,
                         "method_options": dict(options or {})})
    return jobs


def time_alternating(jobs, rounds, budget, out=None, log=sys.stderr):
    """Run ``jobs`` (warm-up, then ``rounds`` alternating timed rounds, see
    the module docstring); returns one record per job, the study's columns
    plus ``cpu_time_s`` (median), ``cpu_time_min_s``, ``cpu_time_max_s``."""
    from skfem_mpm.benchmarks import get_benchmark
    from skfem_mpm.errors import SimulationError
    from skfem_mpm.solve import simulate
    from skfem_mpm.study import (
        _compiled_kernels,
        _kernels_added,
        job_errors,
        job_method,
        job_scene,
        warm_up_run,
    )

    state = []
    for job in jobs:
        spec = job["method"]
        bench = get_benchmark(job["benchmark"], job["variant"], **job.get("params", {}))
        record = {"case": job["case"], "benchmark": bench.name, "variant": bench.variant,
                  "method": spec["name"], "degree": spec["degree"], "mass": spec["mass"],
                  "reconstruction": spec["reconstruction"], "scheme": spec["scheme"],
                  "cfl": spec["cfl"], "cells": job["cells"], "ppc": job["ppc"], "status": "ok",
                  "options": job.get("method_options", {}),
                  "cpu": [], "wall": [], "call": [], "call_wall": [], "timed_compiles": 0}
        try:
            method = job_method(job)
            scene, save_every = job_scene(bench, job, method)
            record["h"] = float(min(scene.grid.h))
            record["jit_time_s"] = warm_up_run(bench, job["cells"], spec["degree"], job["ppc"],
                                               method, False, scene.t_end)
        except (SimulationError, ValueError) as exc:
            record["status"] = f"failed: {str(exc).splitlines()[0][:200]}"
            scene = method = save_every = None
        state.append((job, bench, scene, method, save_every, record))
    # a second pass: a later job's warm-up can leave an earlier job a kernel
    # to load (seen: S1 p1 usl after p3 rk4 loaded rates_1d_p1_serial)
    for job, bench, scene, method, _, record in state:
        if record["status"] == "ok":
            warm_up_run(bench, job["cells"], job["method"]["degree"], job["ppc"], method,
                        False, scene.t_end)
    for k in range(rounds):
        for job, bench, scene, method, save_every, record in state:
            if record["status"] != "ok" or (len(record["cpu"]) >= 2
                                            and sum(record["cpu"]) >= budget):
                continue
            before = _compiled_kernels()
            c0, w0 = time.process_time(), time.perf_counter()
            try:
                result = simulate(scene, method, save_every=save_every)
            except SimulationError as exc:
                record["status"] = f"failed: {str(exc).splitlines()[0][:200]}"
                continue
            record["call"].append(time.process_time() - c0)
            record["call_wall"].append(time.perf_counter() - w0)
            record["cpu"].append(result.cpu_time)
            record["wall"].append(result.wall_time)
            record["timed_compiles"] += _kernels_added(before)
            if k == 0:
                record.update(job_errors(bench, result, job), steps=result.counts["steps"],
                              dt=result.dt, particles=result.counts["particles"],
                              path=str(result.counts.get("path", "")))
                print(f"# {job['case']} {record['method']} {job['cells']}: error "
                      f"{record.get('error', float('nan')):.3g}, {record['steps']} steps, "
                      f"{record['cpu'][-1]:.3g} s cpu (steps)", file=log, flush=True)
            del result
    records = []
    for *_, record in state:
        cpu, wall = record.pop("cpu"), record.pop("wall")
        call, call_wall = record.pop("call"), record.pop("call_wall")
        if cpu:
            record.update(cpu_time_s=statistics.median(cpu), cpu_time_min_s=min(cpu),
                          cpu_time_max_s=max(cpu), wall_time_s=statistics.median(wall),
                          wall_time_min_s=min(wall), wall_time_max_s=max(wall),
                          call_cpu_time_s=statistics.median(call),
                          call_wall_time_s=statistics.median(call_wall), repeats=len(cpu))
        elif record["status"] == "ok":
            record["status"] = "failed: no timed run"
        records.append(record)
        if out is not None:
            out.write(json.dumps(record) + "\n")
            out.flush()
    return records


def cheapest(records, target, key="cpu_time_s"):
    """{"linear": (method, time) or None, "high": ...}: per class (degree 1,
    degree 2 or 3), the method with the smallest time to reach ``target``
    (:func:`skfem_mpm.study.time_to_reach` on ``key``), and
    ``"reach"``: {method: (time, is_upper_bound) or None} of every method."""
    from skfem_mpm.study import time_to_reach

    reach = time_to_reach(records, target, key=key, bounds=True)
    degree = {r["method"]: r["degree"] for r in records}
    out = {"reach": reach}
    for cls, pick in (("linear", lambda d: d == 1), ("high", lambda d: d > 1)):
        times = {m: t[0] for m, t in reach.items() if t is not None and pick(degree[m])}
        best = min(times, key=times.get) if times else None
        out[cls] = (best, times[best]) if best else None
    return out


def _g(x, fmt=".3g"):
    return "" if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, fmt)


def curve_table(records):
    """Markdown: every run, by method and cells (with its steps' CPU time
    divided by its steps: the cost a step, the run's fixed cost included)."""
    rows = ["| method | cells | ppc | steps | error | order | steps' CPU median [s] (range) | "
            "CPU a step [us] | steps' wall median [s] | whole call CPU [s] | repeats | "
            "timed compiles |",
            "|---" * 12 + "|"]
    prev = {}
    for r in records:
        order = None
        p = prev.get(r["method"])
        if p is not None and r.get("error") and p.get("error"):
            order = math.log(p["error"] / r["error"]) / math.log(p["h"] / r["h"])
        prev[r["method"]] = r if r["status"] == "ok" else None
        if r["status"] != "ok":
            rows.append(f"| {r['method']} | {r['cells']} | {r['ppc']} | | {r['status'][:80]} "
                        f"| | | | | | | |")
            continue
        rows.append(f"| {r['method']} | {r['cells']} | {r['ppc']} | {r['steps']} | "
                    f"{_g(r.get('error'))} | {_g(order, '.2f')} | {_g(r['cpu_time_s'], '.4g')} "
                    f"({_g(r['cpu_time_min_s'], '.3g')}-{_g(r['cpu_time_max_s'], '.3g')}) | "
                    f"{_g(1e6 * r['cpu_time_s'] / max(r['steps'], 1), '.3g')} | "
                    f"{_g(r['wall_time_s'], '.4g')} | {_g(r.get('call_cpu_time_s'), '.4g')} | "
                    f"{r['repeats']} | {r['timed_compiles']} |")
    return "\n".join(rows)


def matrix_table(records, key="cpu_time_s"):
    """Markdown, one row per method, one column per grid: "error (time
    [ms])" of each run (``key``'s median), blank where the method has no
    such grid, the status where the run failed."""
    cells = sorted({r["cells"] for r in records})
    by = {}
    for r in records:
        by.setdefault(r["method"], {})[r["cells"]] = r
    rows = ["| method | " + " | ".join(str(c) for c in cells) + " |", "|---" * (len(cells) + 1)
            + "|"]
    for m, runs in by.items():
        out = []
        for c in cells:
            r = runs.get(c)
            if r is None:
                out.append("")
            elif r["status"] != "ok":
                out.append(r["status"][:40])
            else:
                out.append(f"{_g(r.get('error'))} ({_g(1e3 * r[key], '.3g')})")
        rows.append(f"| {m} | " + " | ".join(out) + " |")
    return "\n".join(rows)


def reach_table(records, target, key="cpu_time_s"):
    """Markdown: every method's time to reach ``target`` ('<=': its coarsest
    run already does, an upper bound; 'not reached': no run does), the
    cells that bracket it and the smallest error it reaches."""
    got = cheapest(records, target, key)
    rows = [f"| method | time to reach {target:.0e} [s] | bracketing cells | smallest error |",
            "|---|---|---|---|"]
    by = {}
    for r in records:
        by.setdefault(r["method"], []).append(r)
    order = sorted(by, key=lambda m: (got["reach"].get(m) or (math.inf,))[0])
    for m in order:
        runs = [r for r in by[m] if r["status"] == "ok" and r.get("error")]
        t = got["reach"].get(m)
        first = next((r["cells"] for r in runs if r["error"] <= target), None)
        before = [r["cells"] for r in runs if first is not None and r["cells"] < first]
        bracket = "" if first is None else (f"{before[-1]}-{first}" if before else f"{first}")
        low = min((r["error"] for r in runs), default=None)
        text = "not reached" if t is None else ("<= " if t[1] else "") + _g(t[0], ".4g")
        rows.append(f"| {m} | {text} | {bracket} | {_g(low)} |")
    return "\n".join(rows)


def verdict(records, target, ratio, key="cpu_time_s"):
    """One line: the cheapest linear and high-order methods, their ratio and
    whether it meets ``ratio``."""
    got = cheapest(records, target, key)
    lin, high = got["linear"], got["high"]
    if lin is None and high is not None:
        return _unreached_linear(records, target, ratio, high, key)
    if lin is None or high is None:
        return (f"e = {target:.0e}: cheapest linear {lin and lin[0]}, cheapest high order "
                f"{high and high[0]}: no ratio (a class does not reach e); target {ratio:g}x "
                f"NOT judged")
    r = lin[1] / high[1]
    return (f"e = {target:.0e}: cheapest linear {lin[0]} {lin[1]:.4g} s, cheapest high order "
            f"{high[0]} {high[1]:.4g} s ({key}): {r:.2f}x, target {ratio:g}x: "
            f"{'MET' if r >= ratio else 'NOT met'}")


def _unreached_linear(records, target, ratio, high, key):
    """The verdict when high order reaches ``target`` and no linear run
    does: each linear method's time to reach e is at least the time of its
    finest run (a finer grid costs more), so t_lin / t_high is bounded below
    by min over the linear methods of that time over the high-order time;
    the smallest linear error says how far linear MPM stayed from e."""
    finest = {}
    for r in records:
        if r["degree"] == 1 and r["status"] == "ok":
            if r["method"] not in finest or r["cells"] > finest[r["method"]]["cells"]:
                finest[r["method"]] = r
    if not finest:
        return f"e = {target:.0e}: no linear run; target {ratio:g}x NOT judged"
    slow = min(finest.values(), key=lambda r: r[key])
    low = min((r for r in records if r["degree"] == 1 and r["status"] == "ok"
               and r.get("error")), key=lambda r: r["error"])
    bound = slow[key] / high[1]
    return (f"e = {target:.0e}: no linear run reaches e (smallest error {low['error']:.3g}, "
            f"{low['method']} at {low['cells']} cells); cheapest high order {high[0]} "
            f"{high[1]:.4g} s ({key}); every linear method's finest run took >= {slow[key]:.4g} s "
            f"({slow['method']} at {slow['cells']} cells), so the ratio is > {bound:.2f}x "
            f"(a lower bound), target {ratio:g}x: {'MET' if bound >= ratio else 'NOT met'}")


def report(records, case, key="cpu_time_s", compact=False):
    benchmark, variant, target, ratio, _ = CASES[case]
    rows = [r for r in records if r["case"] == case]
    against = sorted({r.get("compared_with", "") for r in rows if r["status"] == "ok"})
    options = {json.dumps(r.get("options", {}), sort_keys=True) for r in rows}
    parts = [f"### {case.upper()} {variant} ({benchmark}; errors against: "
             f"{', '.join(against)}; Method options {', '.join(sorted(options))})",
             matrix_table(rows, key) if compact else curve_table(rows)]
    if target is not None:
        parts += [reach_table(rows, target, key), verdict(rows, target, ratio, key)]
    return "\n\n".join(parts)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="s1,s3,d2", help=f"comma-separated, of {', '.join(CASES)}")
    ap.add_argument("--methods", default=None, help="comma-separated (default: every linear "
                    "and high-order method of the module docstring)")
    ap.add_argument("--linear-cells", default=None, help="e.g. 8,16,32 (default: by dimension)")
    ap.add_argument("--high-cells", default=None)
    ap.add_argument("--ppc", type=int, default=None, help="particles per cell and axis "
                    "(default: 2 in 1D, 3 in 2D)")
    ap.add_argument("--rounds", type=int, default=3, help="alternating timed rounds (default 3)")
    ap.add_argument("--budget", type=float, default=10.0,
                    help="a job stops repeating after two timed runs whose steps took this "
                         "many CPU seconds (default 10)")
    ap.add_argument("--time", choices=("cpu", "wall", "call"), default="cpu",
                    help="the time to reach e of: the steps' CPU time (default), their wall "
                         "time, the whole simulate call's CPU time")
    ap.add_argument("--json", default=None, help="append every record here as a JSON line")
    ap.add_argument("--option", action="append", default=[], metavar="NAME=VALUE",
                    help="a further Method keyword of every run, e.g. frequency_guard=0")
    ap.add_argument("--compact", action="store_true",
                    help="one row per method (error (time [ms]) per grid) instead of one per run")
    ap.add_argument("--from", dest="source", default=None,
                    help="no runs: the tables of the records in this JSON-lines file")
    a = ap.parse_args()
    key = {"cpu": "cpu_time_s", "wall": "wall_time_s", "call": "call_cpu_time_s"}[a.time]
    cases = a.cases.split(",")
    for c in cases:
        if c not in CASES:
            raise SystemExit(f"--cases: {c!r} is not one of {', '.join(CASES)}")
    if a.source:
        with open(a.source) as f:
            records = [json.loads(line) for line in f if line.strip()]
        for c in cases:
            if any(r["case"] == c for r in records):
                print(report(records, c, key, a.compact) + "\n")
        return
    if os.environ.get("NUMBA_NUM_THREADS") != "1":
        raise SystemExit("set NUMBA_NUM_THREADS=1: the times are one thread's")
    from skfem_mpm.study import keyword_options

    try:
        options = keyword_options(a.option)
    except ValueError as exc:
        raise SystemExit(str(exc)) from None
    out = open(a.json, "a") if a.json else None
    try:
        for c in cases:
            lin_cells, high_cells = CELLS[c]
            if a.linear_cells:
                lin_cells = tuple(int(x) for x in a.linear_cells.split(","))
            if a.high_cells:
                high_cells = tuple(int(x) for x in a.high_cells.split(","))
            methods = a.methods.split(",") if a.methods else (
                S2_METHODS if c == "s2" else LINEAR + HIGH)
            jobs = make_jobs(c, methods, lin_cells, high_cells, a.ppc or PPC[c],
                             options)
            print(f"# {c}: {len(jobs)} jobs, load {os.getloadavg()[0]:.2f}", file=sys.stderr,
                  flush=True)
            records = time_alternating(jobs, a.rounds, a.budget, out)
            print(f"# {c}: done, load {os.getloadavg()[0]:.2f}", file=sys.stderr, flush=True)
            print(report(records, c, key, a.compact) + "\n", flush=True)
    finally:
        if out is not None:
            out.close()


if __name__ == "__main__":
    main()
