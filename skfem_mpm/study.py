"""Convergence and work-precision studies: what accuracy costs in time.

Each record's ``error`` is the benchmark's primary measure (relative RMS
displacement error at t_end, or its maximum over the saves where t_end is a
zero of the exact displacement, see ``Benchmark.primary_error``); ``order``
is observed on it.

    records = convergence("vibrating-string", ["mpm-p1-lumped", "mpm-p2-consistent",
                                               "fem-p2-consistent"], cells=[8, 16, 32])
    write_report(records, "skfem-mpm-report")

A method is named ``kind-pN-mass[-reconstruction][-scheme]``, e.g.
``mpm-p2-consistent-spline`` or ``fem-p3-consistent``; see :func:`parse_method`.

Runs are independent, so a sweep takes any ``concurrent.futures.Executor``:
by default a local process pool with one worker per core, each worker held to
one thread (numba and BLAS), so timed runs never share a core. A
``dask.distributed.Client`` is accepted too (its workers should also run one
thread each). Every run compiles (or loads) its kernels before the clock
starts; the compile time is reported separately as ``jit_time_s``. On a
pool the coarsest run of each kernel set (kind, degree, mass, scheme) goes
first, alone in its worker, the other runs once those are done: each set
compiles once and different sets compile side by side, instead of every
worker compiling the same kernels at the same time (the later runs load
them from numba's cache).
"""
import csv
import math
import multiprocessing
import os
from concurrent.futures import Executor, ProcessPoolExecutor
from itertools import zip_longest

import numpy as np

from .benchmarks import get_benchmark
from .solve.method import HYBRID_SCHEMES, MASSES, RECONSTRUCTIONS, SCHEMES, Method
from .solve.timing import PHASES
from .testing import observed_orders

__all__ = ["parse_method", "run_one", "convergence", "work_precision", "write_report",
           "QUICK_METHODS", "FULL_METHODS", "markdown_table", "time_to_reach",
           "time_to_reach_table"]

QUICK_METHODS = ("mpm-p1-lumped", "mpm-p2-lumped", "mpm-p2-consistent", "mpm-p3-consistent",
                 "mpm-p2-consistent-spline", "mpm-p3-consistent-spline", "fem-p2-consistent")
FEM_MASSES = tuple(m for m in MASSES if m != "hybrid")  # fem has no re-projection
# hybrid mass is MUSL only: its names carry the scheme, whatever the study's default
_SUFFIX = {"hybrid": "-musl"}
FULL_METHODS = tuple(
    [f"mpm-p1-{m}{_SUFFIX.get(m, '')}" for m in MASSES]
    + [f"mpm-p{p}-{m}-{r}{_SUFFIX.get(m, '')}" for p in (2, 3) for m in MASSES
       for r in RECONSTRUCTIONS]
    + [f"fem-p{p}-{m}" for p in (1, 2, 3) for m in FEM_MASSES])

FIELDS = ("benchmark", "variant", "method", "kind", "degree", "mass", "reconstruction", "scheme",
          "cells", "h", "ppc", "dofs", "particles", "steps", "dt", "error", "error_measure",
          "error_rms", "error_max",
          "error_rms_abs", "velocity_error_rms", "stress_error_rms", "order", "wall_time_s",
          "jit_time_s") + tuple(f"phase_{p}_s" for p in PHASES) + ("status",)


def parse_method(name, scheme="musl", cfl=0.5):
    """``"mpm-p2-consistent-spline-cd"`` -> dict(kind, degree, mass,
    reconstruction, scheme, cfl). Omitted parts: reconstruction ``none``,
    the given default scheme."""
    parts = str(name).split("-")
    if len(parts) < 3 or parts[0] not in ("mpm", "fem") or not parts[1].startswith("p"):
        raise ValueError(f"method must look like mpm-p2-consistent[-spline][-cd], got {name!r}")
    try:
        degree = int(parts[1][1:])
    except ValueError:
        raise ValueError(f"degree in {name!r} must be p1, p2 or p3") from None
    if degree not in (1, 2, 3):
        raise ValueError(f"degree in {name!r} must be p1, p2 or p3, got p{degree}")
    if parts[2] not in MASSES:
        raise ValueError(f"mass in {name!r} must be one of {MASSES}")
    spec = {"name": name, "kind": parts[0], "degree": degree, "mass": parts[2],
            "reconstruction": "none", "scheme": scheme, "cfl": cfl}
    for token in parts[3:]:
        if token in RECONSTRUCTIONS:
            spec["reconstruction"] = token
        elif token in SCHEMES:
            spec["scheme"] = token
        else:
            raise ValueError(f"unknown part {token!r} in method {name!r}; reconstructions "
                             f"{RECONSTRUCTIONS}, schemes {SCHEMES}")
    if spec["kind"] == "fem" and spec["reconstruction"] != "none":
        raise ValueError(f"fem methods take no reconstruction, got {name!r}")
    if spec["kind"] == "fem" and spec["scheme"] == "rk4":
        raise ValueError(f"fem methods have no scheme 'rk4' yet (method {name!r}; the study's "
                         f"default scheme is {scheme!r}): name the fem method's scheme, "
                         f"e.g. {'-'.join(parts[:3])}-cd")
    if spec["mass"] == "hybrid" and (spec["kind"] == "fem"
                                     or spec["scheme"] not in HYBRID_SCHEMES):
        raise ValueError(f"hybrid mass is an MPM method with scheme one of {HYBRID_SCHEMES} "
                         f"(e.g. mpm-p2-hybrid-spline-musl), got {name!r} with scheme "
                         f"{spec['scheme']!r}")
    return spec


def _limit_threads():
    """Worker initializer: one thread per timed run."""
    os.environ["OMP_NUM_THREADS"] = "1"
    os.environ["OPENBLAS_NUM_THREADS"] = "1"
    os.environ["MKL_NUM_THREADS"] = "1"
    try:
        import numba

        numba.set_num_threads(1)
    except (ImportError, ValueError):
        pass


def run_one(job):
    """Run one (benchmark, method, cells) job; returns a record (dict)."""
    from .errors import SimulationError
    from .solve import fem, simulate

    bench = get_benchmark(job["benchmark"], job.get("variant"), **job.get("params", {}))
    spec = job["method"]
    method = Method(scheme=spec["scheme"], mass=spec["mass"],
                    reconstruction=spec["reconstruction"], cfl=spec["cfl"], dt=job.get("dt"))
    fem_run = spec["kind"] == "fem"
    scene = bench.scene(job["cells"], spec["degree"], job["ppc"], fem=fem_run,
                        t_end=job.get("t_end"))
    save_every = None
    if bench.saves > 1:
        from .solve import prepare

        steps = prepare(bench.scene(job["cells"], spec["degree"], job["ppc"],
                                    t_end=job.get("t_end")), method).n_steps or bench.saves
        save_every = max(1, steps // bench.saves)
    record = {"benchmark": bench.name, "variant": bench.variant, "method": spec["name"],
              "kind": spec["kind"], "degree": spec["degree"], "mass": spec["mass"],
              "reconstruction": spec["reconstruction"], "scheme": spec["scheme"],
              "cells": job["cells"], "h": float(min(scene.grid.h)), "ppc": job["ppc"],
              "dofs": scene.grid.ndofs, "status": "ok"}
    try:
        result = (fem(scene, method, save_every=save_every) if fem_run
                  else simulate(scene, method, save_every=save_every))
    except (SimulationError, ValueError) as exc:
        record["status"] = f"failed: {str(exc).splitlines()[0][:200]}"
        return record
    record.update(particles=result.counts["particles"], steps=result.counts["steps"],
                  dt=result.dt, wall_time_s=result.wall_time, jit_time_s=result.jit_time)
    for p, s in result.timings.items():
        record[f"phase_{p}_s"] = s
    if bench.has_exact:
        record.update(bench.errors(result))
        record["error_measure"] = bench.primary_error
        record["error"] = record[bench.primary_error]
    return record


def _executor(executor):
    if executor is None:
        # spawn, not fork: numba's OpenMP threads make fork() unsafe
        return ProcessPoolExecutor(max_workers=os.cpu_count() or 1,
                                   mp_context=multiprocessing.get_context("spawn"),
                                   initializer=_limit_threads), True
    if hasattr(executor, "get_executor") and not isinstance(executor, Executor):
        return executor.get_executor(), False  # dask.distributed.Client
    if not isinstance(executor, Executor):
        raise ValueError(f"executor must be a concurrent.futures.Executor or a "
                         f"dask.distributed.Client, got {executor!r}")
    return executor, False


def convergence(benchmark, methods, cells, ppc=2, variant=None, params=None, executor=None,
                progress=False, scheme="musl", cfl=0.5, t_end=None):
    """Run every method at every resolution; returns a list of records with
    errors, observed orders (between successive resolutions of a method),
    wall time and per-phase times. ``executor`` as in the module docstring;
    ``"serial"`` runs in this process, one run at a time."""
    specs = [m if isinstance(m, dict) else parse_method(m, scheme, cfl) for m in methods]
    cells = [int(c) for c in cells]
    if not cells or any(c < 1 for c in cells):
        raise ValueError(f"cells must be positive integers, got {cells}")
    get_benchmark(benchmark, variant, **(params or {}))  # validate early
    jobs = [{"benchmark": benchmark, "variant": variant, "params": dict(params or {}),
             "method": spec, "cells": n, "ppc": ppc, "t_end": t_end}
            for spec in specs for n in cells]
    if executor == "serial":
        records = [run_one(job) for job in _progress(jobs, progress)]
    else:
        first, rest = compile_first(jobs)
        pool, owned = _executor(executor)
        bar = _bar(len(jobs), progress)
        try:
            done = {}
            for batch in (first, rest):
                futures = [(i, pool.submit(run_one, jobs[i])) for i in batch]
                for i, f in futures:
                    done[i] = f.result()
                    if bar is not None:
                        bar.update()
            records = [done[i] for i in range(len(jobs))]
        finally:
            if bar is not None:
                bar.close()
            if owned:
                pool.shutdown()
    _add_orders(records)
    return records


def _kernel_set(spec):
    """What decides which kernels a run compiles."""
    return (spec["kind"], spec["degree"], spec["mass"], spec["scheme"], spec["reconstruction"])


def compile_first(jobs):
    """(first, rest): indices of the coarsest job of each kernel set, those
    needing the consistent-mass machinery (the longest compile) alternating
    with lumped ones, and of the other jobs."""
    first = {}
    for i, job in enumerate(jobs):
        key = _kernel_set(job["method"])
        if key not in first or job["cells"] < jobs[first[key]]["cells"]:
            first[key] = i
    heavy = [i for i in sorted(first.values()) if jobs[i]["method"]["mass"] != "lumped"]
    light = [i for i in sorted(first.values()) if jobs[i]["method"]["mass"] == "lumped"]
    # alternate, so that two workers starting together share few kernels
    order = [i for pair in zip_longest(heavy, light) for i in pair if i is not None]
    chosen = set(order)
    return order, [i for i in range(len(jobs)) if i not in chosen]


def work_precision(benchmark, methods, cells, **kwargs):
    """The same sweep as :func:`convergence`, sorted by wall time per method:
    the data of the error-against-time picture."""
    records = convergence(benchmark, methods, cells, **kwargs)
    return sorted(records, key=lambda r: (r["method"], r.get("wall_time_s", math.inf)))


def _progress(items, enabled):
    if not enabled:
        return items
    import sys

    from tqdm import tqdm

    return tqdm(items, unit="run", disable=not sys.stderr.isatty(), leave=False)


def _bar(total, enabled):
    """A progress bar over ``total`` runs (None when not shown)."""
    if not enabled:
        return None
    import sys

    from tqdm import tqdm

    return tqdm(total=total, unit="run", disable=not sys.stderr.isatty(), leave=False)


def _add_orders(records):
    by_method = {}
    for r in records:
        by_method.setdefault(r["method"], []).append(r)
    for rows in by_method.values():
        rows.sort(key=lambda r: r["cells"])
        prev = None
        for r in rows:
            r["order"] = None
            ok = r["status"] == "ok" and r.get("error", 0) > 0
            if prev is not None and ok:
                r["order"] = float(observed_orders([prev["error"], r["error"]],
                                                   [prev["h"], r["h"]])[0])
            prev = r if ok else None


def fastest_to(records, target):
    """{method: the smallest wall time of a run whose error <= target}."""
    out = {}
    for r in records:
        if r["status"] == "ok" and r.get("error", math.inf) <= target:
            out[r["method"]] = min(out.get(r["method"], math.inf), r["wall_time_s"])
    return out


def time_to_reach(records, target):
    """{method: the wall time at which it reaches the relative error
    ``target``, or None when no run of it does}. Along a method's runs in
    order of resolution, the first run with error <= target and the one
    before it bracket the target; log(time) is interpolated linearly in
    log(error) between them. When the coarsest run already reaches it, its
    own time is reported (an upper bound)."""
    by_method = {}
    for r in records:
        by_method.setdefault(r["method"], [])
        if r["status"] == "ok" and r.get("error", 0) > 0 and r.get("wall_time_s", 0) > 0:
            by_method[r["method"]].append(r)
    out = {}
    for method, rows in by_method.items():
        rows.sort(key=lambda r: r["cells"])
        out[method] = None
        for k, r in enumerate(rows):
            if r["error"] > target:
                continue
            if k == 0:
                out[method] = r["wall_time_s"]
            else:
                a, b = rows[k - 1], r
                s = (math.log(target) - math.log(a["error"])) / \
                    (math.log(b["error"]) - math.log(a["error"]))
                out[method] = math.exp(math.log(a["wall_time_s"]) + s * (
                    math.log(b["wall_time_s"]) - math.log(a["wall_time_s"])))
            break
    return out


def reach_targets(records):
    """The decades 10^-k between the largest and the smallest error of the
    study (at most six, the smallest ones), as targets for
    :func:`time_to_reach`."""
    errors = [r["error"] for r in records if r["status"] == "ok" and r.get("error", 0) > 0]
    if not errors:
        return []
    high = math.floor(math.log10(max(errors)))
    low = math.ceil(math.log10(min(errors)))
    return [10.0 ** k for k in range(low, high + 1)][:6][::-1]


def time_to_reach_table(records, targets=None):
    """A Markdown table: per method, the time to reach each target error
    (interpolated, see :func:`time_to_reach`; blank: not reached)."""
    targets = reach_targets(records) if targets is None else list(targets)
    methods = list(dict.fromkeys(r["method"] for r in records))
    times = [time_to_reach(records, e) for e in targets]
    lines = ["| method | " + " | ".join(f"e = {e:.0e}" for e in targets) + " |",
             "|" + "---|" * (len(targets) + 1)]
    for m in methods:
        lines.append(f"| {m} | " + " | ".join(_fmt(t[m]) if t.get(m) is not None else ""
                                                for t in times) + " |")
    return "\n".join(lines)


# ------------------------------------------------------------------ reports
def _fmt(value):
    if value is None:
        return ""
    if isinstance(value, float):
        if value == 0 or not math.isfinite(value):
            return f"{value:g}"
        return f"{value:.3e}" if abs(value) < 1e-2 or abs(value) >= 1e4 else f"{value:.4g}"
    return str(value)


def markdown_table(records, columns=("method", "cells", "particles", "steps", "error",
                                     "order", "wall_time_s", "jit_time_s")):
    """A Markdown table of the chosen columns."""
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for r in records:
        lines.append("| " + " | ".join(_fmt(r.get(c)) for c in columns) + " |")
    return "\n".join(lines)


def write_csv(records, path):
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=FIELDS, extrasaction="ignore")
        writer.writeheader()
        for r in records:
            writer.writerow({k: r.get(k) for k in FIELDS})


def write_report(records, out, title=None, timing_note=None):
    """Write ``study.csv``, ``study.md``, ``convergence.png`` and
    ``work_precision.png`` into the directory ``out``; returns their paths."""
    from .plot import plot_convergence, plot_work_precision

    os.makedirs(out, exist_ok=True)
    title = title or f"{records[0]['benchmark']} ({records[0]['variant']})"
    paths = {"csv": os.path.join(out, "study.csv"), "md": os.path.join(out, "study.md"),
             "convergence": os.path.join(out, "convergence.png"),
             "work_precision": os.path.join(out, "work_precision.png")}
    write_csv(records, paths["csv"])
    phase_cols = ("method", "cells") + tuple(f"phase_{p}_s" for p in PHASES)
    with open(paths["md"], "w") as f:
        f.write(f"# Study: {title}\n\n")
        if timing_note:
            f.write(timing_note + "\n\n")
        f.write(markdown_table(records) + "\n\n## Time to reach a relative error e [s]\n\n")
        f.write("Wall time interpolated in log-log between the two runs that bracket e "
                "(blank: not reached).\n\n")
        f.write(time_to_reach_table(records) + "\n\n## Time per phase [s]\n\n")
        f.write(markdown_table(records, phase_cols) + "\n")
    plot_convergence(records, paths["convergence"], title)
    plot_work_precision(records, paths["work_precision"], title)
    return paths
