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

Timing a run (:func:`run_one`): first an untimed warm-up run of the same
scene and method, cut to :data:`WARM_UP_STEPS` steps, compiles or
loads every kernel the run calls (the consistent-mass assembly and CG and
the reconstruction included, whatever ``warm_up_kernels`` covers); then
``repeat`` timed runs, whose median is ``wall_time_s`` (the range in
``wall_time_min_s``/``wall_time_max_s``). ``timed_compiles`` counts the
numba kernels compiled or loaded during the timed runs: 0 means no
compilation leaked into the figures. ``cpu_time_s`` (MPM runs) is the median
CPU time of the same interval (``Result.cpu_time``): on one thread, little
touched by the load of a shared machine; ``time_to_reach(records, e,
key="cpu_time_s")`` reads it.
"""
import contextlib
import csv
import inspect
import json
import math
import multiprocessing
import os
import statistics
import time
from concurrent.futures import FIRST_COMPLETED, Executor, ProcessPoolExecutor, wait
from itertools import zip_longest

from .benchmarks import get_benchmark
from .model_reference import model_reference
from .solve.method import HYBRID_SCHEMES, MASSES, RECONSTRUCTIONS, SCHEMES, Method
from .solve.timing import PHASES
from .testing import observed_orders

__all__ = [
    "DEFAULTS",
    "FULL_METHODS",
    "QUICK",
    "QUICK_METHODS",
    "REACH_TARGETS",
    "STUDY_CELLS",
    "WARM_UP_STEPS",
    "convergence",
    "job_errors",
    "job_method",
    "job_scene",
    "keyword_options",
    "markdown_table",
    "parse_method",
    "run_one",
    "time_to_reach",
    "time_to_reach_table",
    "verdict",
    "verdict_lines",
    "warm_up_run",
    "work_precision",
    "write_report",
]

# the error levels of the "time to reach e" table and the verdict
REACH_TARGETS = (1e-3, 1e-4, 1e-5, 1e-6, 1e-7)
# what a study's errors are measured against (see convergence)
COMPARE_WITH = ("auto", "exact")
# steps of the untimed run that compiles a job's kernels before it is timed
WARM_UP_STEPS = 3

# A study's defaults, the one source of them: convergence() and parse_method()
# take them as keyword defaults and the command line (`skfem-mpm study`) reads
# them. scheme and cfl are Method()'s; ppc is particles per cell and axis;
# repeat, the timed runs per job.
_METHOD = inspect.signature(Method).parameters
DEFAULTS = {"ppc": 2, "scheme": _METHOD["scheme"].default, "cfl": _METHOD["cfl"].default,
            "repeat": 1}
# cells per axis by dimension: (quick, full)
STUDY_CELLS = {1: ([8, 16, 32, 64], [8, 16, 32, 64, 128]), 2: ([4, 8, 16], [4, 8, 16, 32]),
               3: ([2, 4], [2, 4, 8])}
# a quick study's timed runs per job; repeat_budget: a job stops repeating
# after two timed runs that took that many seconds (the long ones)
QUICK = {"repeat": 3, "repeat_budget": 2.0}
# the quick study's methods: low order at the default scheme (linear and
# quadratic lumped MPM, the cheapest per run), high order (consistent mass,
# the spline reconstruction and rk4, whose time error does not cap the
# order at 2 as a second-order scheme's does at a cfl of 0.5: quadratic and
# cubic) and quadratic FEM (default scheme; fem has no rk4). The two rk4
# methods share their compiled loop, so the high-order family compiles once.
QUICK_METHODS = ("mpm-p1-lumped", "mpm-p2-lumped", "mpm-p2-consistent-spline-rk4",
                 "mpm-p3-consistent-spline-rk4", "fem-p2-consistent")
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
          "compared_with", "error_exact", "error_rms", "error_max",
          "error_rms_abs", "velocity_error_rms", "stress_error_rms", "order", "wall_time_s",
          "wall_time_min_s", "wall_time_max_s", "cpu_time_s", "repeats", "jit_time_s", "timed_compiles") \
    + tuple(f"phase_{p}_s" for p in PHASES) + ("status",)


def parse_method(name, scheme=DEFAULTS["scheme"], cfl=DEFAULTS["cfl"]):
    """``"mpm-p2-consistent-spline-cd"`` -> dict(kind, degree, mass,
    reconstruction, scheme, cfl). Omitted parts: reconstruction ``none``,
    the given default scheme (:data:`DEFAULTS`)."""
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


def keyword_options(items, argument="--option"):
    """{name: value} of ``NAME=VALUE`` strings (a command line's repeated
    ``argument``): the value read as JSON where it parses (numbers,
    true/false, lists), else kept as the string."""
    out = {}
    for item in items:
        name, sep, value = str(item).partition("=")
        if not sep or not name:
            raise ValueError(f"{argument} must be NAME=VALUE, got {item!r}")
        try:
            out[name] = json.loads(value)
        except json.JSONDecodeError:
            out[name] = value
    return out


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


def _compiled_kernels():
    """{id: number of compiled signatures} of every live numba dispatcher
    (found among the objects the garbage collector tracks)."""
    import gc

    from numba.core.dispatcher import Dispatcher

    # the classes themselves, not isinstance: an ABC's instance check over
    # every tracked object costs ~10x more (a timed run scans twice)
    kinds, todo = set(), [Dispatcher]
    while todo:
        kind = todo.pop()
        kinds.add(kind)
        todo += [k for k in kind.__subclasses__() if k not in kinds]
    return {id(d): len(d.overloads) for d in gc.get_objects() if type(d) in kinds}


def _kernels_added(before):
    """How many signatures were compiled or loaded since ``before``."""
    now = _compiled_kernels()
    return sum(max(0, n - before.get(k, 0)) for k, n in now.items())


def run_one(job):
    """Run one (benchmark, method, cells) job; returns a record (dict).

    An untimed warm-up run (``WARM_UP_STEPS`` steps of the same scene and
    method; for fem, the scene at a thousandth of its end time) compiles
    everything the job calls, then ``job["repeat"]`` (default 1) timed runs
    give the median ``wall_time_s`` and its range; with
    ``job["repeat_budget"]`` (seconds) the repeats stop early, after at least
    two, once the timed runs have taken that long (``repeats`` says how
    many ran). ``jit_time_s`` is the
    warm-up run's whole time (compilation, cache loads, first-use set-up),
    ``timed_compiles`` the kernels compiled or loaded during the timed runs."""
    from .errors import SimulationError
    from .solve import fem, simulate

    bench = get_benchmark(job["benchmark"], job.get("variant"), **job.get("params", {}))
    spec = job["method"]
    repeat = int(job.get("repeat", 1))
    if repeat < 1:
        raise ValueError(f"repeat must be a positive integer, got {repeat}")
    method = job_method(job)
    fem_run = spec["kind"] == "fem"
    scene, save_every = job_scene(bench, job, method)
    record = {"benchmark": bench.name, "variant": bench.variant, "method": spec["name"],
              "kind": spec["kind"], "degree": spec["degree"], "mass": spec["mass"],
              "reconstruction": spec["reconstruction"], "scheme": spec["scheme"],
              "cells": job["cells"], "h": float(min(scene.grid.h)), "ppc": job["ppc"],
              "dofs": scene.grid.ndofs, "status": "ok"}
    try:
        first_use = warm_up_run(bench, job["cells"], spec["degree"], job["ppc"], method,
                                fem_run, scene.t_end)
        times, cpus, compiles = [], [], 0
        budget = job.get("repeat_budget")
        while len(times) < repeat and not (
                budget is not None and len(times) >= 2 and sum(times) >= budget):
            before = _compiled_kernels()
            result = (fem(scene, method, save_every=save_every) if fem_run
                      else simulate(scene, method, save_every=save_every))
            compiles += _kernels_added(before)
            times.append(result.wall_time)
            if getattr(result, "cpu_time", None) is not None:  # MPM runs
                cpus.append(result.cpu_time)
    except (SimulationError, ValueError) as exc:
        record["status"] = f"failed: {str(exc).splitlines()[0][:200]}"
        return record
    record.update(particles=result.counts["particles"], steps=result.counts["steps"],
                  dt=result.dt, wall_time_s=statistics.median(times),
                  wall_time_min_s=min(times), wall_time_max_s=max(times), repeats=len(times),
                  jit_time_s=first_use, timed_compiles=compiles,
                  cpu_time_s=statistics.median(cpus) if cpus else None)
    for p, s in result.timings.items():
        record[f"phase_{p}_s"] = s
    record.update(job_errors(bench, result, job))
    return record


def job_scene(bench, job, method):
    """(scene, save_every) of a job: the benchmark's scene at the job's
    cells, degree and particles per cell (fem: its FEM scene), saved often
    enough for the benchmark's primary error (``bench.saves`` saves when it
    is a maximum over time, else only the end)."""
    spec = job["method"]
    scene = bench.scene(job["cells"], spec["degree"], job["ppc"], fem=spec["kind"] == "fem",
                        t_end=job.get("t_end"))
    save_every = None
    if bench.saves > 1:
        from .solve import prepare

        steps = prepare(bench.scene(job["cells"], spec["degree"], job["ppc"],
                                    t_end=job.get("t_end")), method).n_steps or bench.saves
        save_every = max(1, steps // bench.saves)
    return scene, save_every


def job_errors(bench, result, job):
    """The error columns of a job's record ({} without an exact solution):
    the benchmark's error measures against its exact solution, or, with
    ``job["compare_with"]`` ``"auto"`` (the default) for an MPM run of a
    variant whose exact solution is not MPM's model, against the same-model
    reference (:func:`skfem_mpm.model_reference.model_reference`;
    ``error_exact`` keeps the error against the exact solution);
    ``error`` is the primary measure, ``compared_with`` says which."""
    if not bench.has_exact:
        return {}
    # fem's LinearElastic is small strain: the linear model, whose solution
    # is the exact one; MPM's is hypoelastic (see model_reference)
    reference = (model_reference(bench) if job.get("compare_with", "auto") == "auto"
                 and job["method"]["kind"] != "fem" else None)
    if reference is None:
        out = dict(bench.errors(result), compared_with="exact")
    else:
        out = dict(reference.errors(result), compared_with="same-model reference",
                   error_exact=bench.errors(result)[bench.primary_error])
    out["error_measure"] = bench.primary_error
    out["error"] = out[bench.primary_error]
    return out


def job_method(job):
    """The Method of a job (``job["method_options"]``: further Method
    keyword arguments, e.g. ``frequency_guard``)."""
    spec = job["method"]
    return Method(scheme=spec["scheme"], mass=spec["mass"],
                  reconstruction=spec["reconstruction"], cfl=spec["cfl"], dt=job.get("dt"),
                  **job.get("method_options", {}))


def precompile(job):
    """Compile (or load) the consistent-mass share of the compiled loop
    ``job`` runs (:func:`skfem_mpm.solve.compiled_loop.precompile_mass`),
    untimed; returns no records. A second worker runs it while the first
    runs the job's family (:func:`run_chain`), which then loads that
    share instead of compiling it: the longest first use is split over
    two cores."""
    spec = job["method"]
    if spec["kind"] != "mpm" or spec["mass"] == "lumped":
        return []
    from .solve.compiled import CompiledExecutor, compiled_executor_applies
    from .solve.compiled_loop import precompile_mass
    from .solve.state import prepare

    bench = get_benchmark(job["benchmark"], job.get("variant"), **job.get("params", {}))
    state = prepare(bench.scene(job["cells"], spec["degree"], job["ppc"], t_end=job.get("t_end")),
                    job_method(job))
    if compiled_executor_applies(state)[0]:
        precompile_mass(state, CompiledExecutor(state))
    return []


def run_chain(jobs):
    """Run ``jobs`` one after the other in this process (:func:`run_one`
    each); returns their records in order. One worker runs a family of
    first jobs (:func:`compile_first`), so the kernels the family shares
    compile once, not in two workers at the same time."""
    return [run_one(job) for job in jobs]


def warm_up_run(bench, cells, degree, ppc, method, fem_run=False, t_end=None):
    """Run the scene of ``bench`` briefly, untimed, so that every kernel the
    full run calls is compiled (or loaded from numba's cache) first: MPM,
    the same scene cut to :data:`WARM_UP_STEPS` steps (the same kernels and
    the same compiled loop; a callback would keep every step in Python, so
    the loop would compile in the first timed run); FEM, the scene at a
    thousandth of its end time. Returns its wall time [s]."""
    from .solve import fem, prepare, simulate

    t0 = time.perf_counter()
    scene = bench.scene(cells, degree, ppc, fem=fem_run, t_end=t_end)
    if fem_run:
        fem(bench.scene(cells, degree, ppc, fem=True, t_end=1e-3 * scene.t_end), method)
    else:
        short = min(scene.t_end, WARM_UP_STEPS * prepare(scene, method).dt)
        simulate(bench.scene(cells, degree, ppc, t_end=short), method)
    return time.perf_counter() - t0


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


def convergence(benchmark, methods, cells, ppc=DEFAULTS["ppc"], variant=None, params=None,
                executor=None, progress=False, scheme=DEFAULTS["scheme"], cfl=DEFAULTS["cfl"],
                t_end=None, repeat=DEFAULTS["repeat"], compile_notice=None, compare_with="auto",
                repeat_budget=None):
    """Run every method at every resolution (defaults: :data:`DEFAULTS`, the
    command line's too); returns a list of records with
    errors, observed orders (between successive resolutions of a method),
    wall time (the median of ``repeat`` timed runs, compilation excluded,
    see :func:`run_one`; ``repeat_budget``: fewer repeats, at least two, for
    a job whose timed runs have already taken that many seconds) and
    per-phase times. ``executor`` as in the module
    docstring; ``"serial"`` runs in this process, one run at a time.
    ``compile_notice``: a context manager factory entered around the jobs
    that run first (the coarsest of each kernel set, in families that one
    worker runs in turn, :func:`compile_first`: where compilation happens);
    the command line passes one that says
    "compiling kernels" when they take long. None: silent.
    ``compare_with``: ``"auto"`` measures errors against the benchmark's
    exact solution, or, for a variant whose exact solution is not MPM's
    model (S2 ``large``), MPM runs against a same-model reference
    (:func:`skfem_mpm.model_reference.model_reference`: computed once here,
    cached on disk; each record's ``compared_with`` says which, and
    ``error_exact`` keeps the error against the exact solution);
    ``"exact"``: always the exact solution."""
    if compare_with not in COMPARE_WITH:
        raise ValueError(f"compare_with must be one of {COMPARE_WITH}, got {compare_with!r}")
    if isinstance(repeat, bool) or not isinstance(repeat, int) or repeat < 1:
        raise ValueError(f"repeat must be a positive integer, got {repeat!r}")
    if repeat_budget is not None and not (isinstance(repeat_budget, (int, float))
                                          and repeat_budget > 0):
        raise ValueError(f"repeat_budget must be a positive number of seconds or None, got "
                         f"{repeat_budget!r}")
    specs = [m if isinstance(m, dict) else parse_method(m, scheme, cfl) for m in methods]
    cells = [int(c) for c in cells]
    if not cells or any(c < 1 for c in cells):
        raise ValueError(f"cells must be positive integers, got {cells}")
    bench = get_benchmark(benchmark, variant, **(params or {}))  # validate early
    if compare_with == "auto" and any(spec["kind"] == "mpm" for spec in specs):
        model_reference(bench)  # computed and cached once, before the runs read it
    jobs = [{"benchmark": benchmark, "variant": variant, "params": dict(params or {}),
             "method": spec, "cells": n, "ppc": ppc, "t_end": t_end, "repeat": repeat,
             "repeat_budget": repeat_budget,
             "compare_with": compare_with}
            for spec in specs for n in cells]
    chains, rest = compile_first(jobs)
    notice = compile_notice or contextlib.nullcontext
    done = {}
    if executor == "serial":
        with notice():
            for chain in chains:
                for i in chain:
                    done[i] = run_one(jobs[i])
        for i in _progress(rest, progress):
            done[i] = run_one(jobs[i])
    else:
        pool, owned = _executor(executor)
        # with a notice, the bar starts after the compiling jobs (both write
        # to stderr)
        bar = None if compile_notice else _bar(len(jobs), progress)
        # each family's other jobs as soon as its first jobs are done (they
        # load what those compiled), beside the families still compiling
        later = {}
        for i in rest:
            later.setdefault(_family(jobs[i]["method"]), []).append(i)
        singles = {}
        try:
            with notice():
                chained = {(pool.submit(precompile, chain.job) if isinstance(chain, _Precompile)
                            else pool.submit(run_chain, [jobs[i] for i in chain])): chain
                           for chain in _with_precompile(chains, jobs, owned)}
                waiting = set(chained)
                while waiting:
                    finished, waiting = wait(waiting, return_when=FIRST_COMPLETED)
                    for f in finished:
                        chain = chained[f]
                        if isinstance(chain, _Precompile):
                            f.result()
                            continue
                        for i, record in zip(chain, f.result()):
                            done[i] = record
                        if bar is not None:
                            bar.update(len(chain))
                        for i in later.pop(_family(jobs[chain[0]]["method"]), []):
                            singles[i] = pool.submit(run_one, jobs[i])
            if bar is None:
                bar = _bar(len(jobs), progress, initial=len(done))
            for i in [i for group in later.values() for i in group]:  # (none: every family chains)
                singles[i] = pool.submit(run_one, jobs[i])
            for i, f in singles.items():
                done[i] = f.result()
                if bar is not None:
                    bar.update()
        finally:
            if bar is not None:
                bar.close()
            if owned:
                pool.shutdown()
    records = [done[i] for i in range(len(jobs))]
    _add_orders(records)
    return records


class _Precompile(list):
    """A chain of no jobs whose task is :func:`precompile` of its ``job``."""

    def __init__(self, job):
        super().__init__()
        self.job = job


def _with_precompile(chains, jobs, owned):
    """The chains to submit, in order: on a pool of our own with two workers
    or more, the first family needing consistent mass on the compiled
    loop (the longest first use) is followed by a :func:`precompile` of its
    first job, which the next free worker takes while the family's own
    worker compiles the rest of the loop."""
    out = list(chains)
    if not owned or (os.cpu_count() or 1) < 2:
        return out
    for k, chain in enumerate(chains):
        spec = jobs[chain[0]]["method"]
        if spec["kind"] == "mpm" and spec["mass"] != "lumped":
            out.insert(k + 1, _Precompile(jobs[chain[0]]))
            break
    return out


def _kernel_set(spec):
    """What decides which kernels a run compiles."""
    return (spec["kind"], spec["degree"], spec["mass"], spec["scheme"], spec["reconstruction"])


def _family(spec):
    """What the kernel sets of one family share: the compiled loop of one
    kind of run (lumped or not, reconstruction, scheme) and its kernels; the
    degree only picks the transfer kernels."""
    return (spec["kind"], spec["mass"] == "lumped", spec["reconstruction"], spec["scheme"])


def compile_first(jobs):
    """(chains, rest): the coarsest job of each kernel set, grouped into
    families (:func:`_family`) that one worker runs in turn, so that what a
    family shares compiles once; the families needing the consistent-mass
    machinery (the longest compile) alternate with lumped ones. ``rest``:
    the other jobs' indices."""
    first = {}
    for i, job in enumerate(jobs):
        key = _kernel_set(job["method"])
        if key not in first or job["cells"] < jobs[first[key]]["cells"]:
            first[key] = i
    families = {}
    for i in sorted(first.values()):
        families.setdefault(_family(jobs[i]["method"]), []).append(i)
    chains = list(families.values())
    heavy = [c for c in chains if jobs[c[0]]["method"]["mass"] != "lumped"]
    light = [c for c in chains if jobs[c[0]]["method"]["mass"] == "lumped"]
    # alternate, so that two workers starting together share few kernels
    order = [c for pair in zip_longest(heavy, light) for c in pair if c is not None]
    chosen = {i for c in order for i in c}
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


def _bar(total, enabled, initial=0):
    """A progress bar over ``total`` runs (None when not shown)."""
    if not enabled:
        return None
    import sys

    from tqdm import tqdm

    return tqdm(total=total, initial=initial, unit="run", disable=not sys.stderr.isatty(),
                leave=False)


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


def _reach(rows, target, key):
    """(time, bounded) for one method's ok runs ``rows`` in order of
    resolution, or None: see :func:`time_to_reach`."""
    for k, r in enumerate(rows):
        if r["error"] > target:
            continue
        if k == 0:
            return r[key], True
        a, b = rows[k - 1], r
        s = (math.log(target) - math.log(a["error"])) / \
            (math.log(b["error"]) - math.log(a["error"]))
        return math.exp(math.log(a[key]) + s * (math.log(b[key]) - math.log(a[key]))), False
    return None


def _by_method(records, key="wall_time_s"):
    """{method: its ok runs with a positive error and time, by resolution}."""
    by_method = {}
    for r in records:
        by_method.setdefault(r["method"], [])
        if r["status"] == "ok" and r.get("error", 0) > 0 and (r.get(key) or 0) > 0:
            by_method[r["method"]].append(r)
    for rows in by_method.values():
        rows.sort(key=lambda r: r["cells"])
    return by_method


def time_to_reach(records, target, key="wall_time_s", bounds=False):
    """{method: the wall time at which it reaches the relative error
    ``target``, or None when no run of it does}. Along a method's runs in
    order of resolution, the first run with error <= target and the one
    before it bracket the target; log(time) is interpolated linearly in
    log(error) between them (a straight segment of the log-log
    work-precision curve; never extrapolated beyond the measured runs).
    When the coarsest run already reaches it, its own time is reported: an
    upper bound, flagged with ``bounds=True``, which returns
    {method: (time, is_upper_bound) or None}. ``key`` picks the time
    column (``wall_time_min_s``, ``wall_time_max_s`` for the range)."""
    out = {}
    for method, rows in _by_method(records, key).items():
        reach = _reach(rows, target, key)
        out[method] = reach if bounds or reach is None else reach[0]
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


def time_to_reach_table(records, targets=REACH_TARGETS):
    """A Markdown table: per method, the time [s] to reach each target error
    (interpolated, see :func:`time_to_reach`; ``<=`` marks the coarsest
    run's time when it already reaches e, an upper bound; blank: not
    reached). ``targets=None``: the decades the study spans."""
    targets = reach_targets(records) if targets is None else list(targets)
    methods = list(dict.fromkeys(r["method"] for r in records))
    times = [time_to_reach(records, e, bounds=True) for e in targets]

    def cell(reach):
        if reach is None:
            return ""
        return ("<= " if reach[1] else "") + _fmt(reach[0])

    lines = ["| method | " + " | ".join(f"e = {e:.0e}" for e in targets) + " |",
             "|" + "---|" * (len(targets) + 1)]
    for m in methods:
        lines.append(f"| {m} | " + " | ".join(cell(t.get(m)) for t in times) + " |")
    return "\n".join(lines)


def verdict(records, targets=REACH_TARGETS):
    """Per target error e, the cheapest method (the smallest time to reach
    e, :func:`time_to_reach`) and how robust that is: its ratio to the
    runner-up, and whether it holds at the ends of the repeats' ranges (the
    winner at its slowest repeat, ``wall_time_max_s``, against the
    runner-up at its fastest, ``wall_time_min_s``; not judged, None, when
    either was timed once, ``repeats`` 1). Returns a list of dicts
    (target, best, time, upper_bound, runner_up, runner_up_time, ratio,
    worst_ratio, holds); ``best`` is None where no method reaches e."""
    out = []
    for e in targets:
        reach = {m: t for m, t in time_to_reach(records, e, bounds=True).items()
                 if t is not None}
        row = {"target": e, "best": None}
        if reach:
            ranked = sorted(reach, key=lambda m: reach[m][0])
            best = ranked[0]
            row.update(best=best, time=reach[best][0], upper_bound=reach[best][1],
                       runner_up=None, ratio=None, worst_ratio=None, holds=None)
            if len(ranked) > 1:
                second = ranked[1]
                slow = time_to_reach(records, e, "wall_time_max_s").get(best)
                fast = time_to_reach(records, e, "wall_time_min_s").get(second)
                row.update(runner_up=second, runner_up_time=reach[second][0],
                           ratio=reach[second][0] / reach[best][0])
                single = any((r.get("repeats") or 2) < 2 for r in records
                             if r["method"] in (best, second))
                if slow and fast and not single:  # one timed run has no range
                    row.update(worst_ratio=fast / slow, holds=fast > slow)
        out.append(row)
    return out


def verdict_lines(records, targets=REACH_TARGETS):
    """The verdict (:func:`verdict`) as sentences, one per target error."""
    lines = []
    for v in verdict(records, targets):
        e = f"{v['target']:.0e}"
        if v["best"] is None:
            lines.append(f"e = {e}: no method reaches it in this study")
            continue
        bound = "<= " if v["upper_bound"] else ""
        text = f"e = {e}: cheapest {v['best']} ({bound}{v['time']:.3g} s)"
        if v["runner_up"] is None:
            lines.append(text + ", the only method that reaches it")
            continue
        text += (f", {v['ratio']:.2f}x faster than the runner-up {v['runner_up']} "
                 f"({v['runner_up_time']:.3g} s)")
        if v["holds"] is None:
            text += "; one timed run each, no range to judge it by"
        elif v["holds"]:
            text += f"; holds over the repeats' range (worst case {v['worst_ratio']:.2f}x)"
        else:
            text += (f"; NOT robust: within the repeats' range (worst case "
                     f"{v['worst_ratio']:.2f}x)")
        lines.append(text)
    return lines


# ------------------------------------------------------------------ reports
def _fmt(value):
    if value is None:
        return ""
    if isinstance(value, float):
        if value == 0 or not math.isfinite(value):
            return f"{value:g}"
        return f"{value:.3e}" if abs(value) < 1e-2 or abs(value) >= 1e4 else f"{value:.4g}"
    return str(value)


def markdown_table(records, columns=None):
    """A Markdown table of the chosen columns (default: the study's main
    ones, with ``error_exact`` beside ``error`` when the errors were
    measured against a same-model reference)."""
    if columns is None:
        columns = ("method", "cells", "particles", "steps", "error") + (
            ("error_exact",) if any(r.get("error_exact") is not None for r in records)
            else ()) + ("order", "wall_time_s", "wall_time_min_s", "wall_time_max_s",
                        "jit_time_s")
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
        f.write("Wall time (median of the repeats) interpolated in log-log between the two "
                "runs that bracket e; `<=`: the coarsest run already reaches e (its time, an "
                "upper bound); blank: not reached. Never extrapolated.\n\n")
        f.write(time_to_reach_table(records) + "\n\n## Verdict\n\n")
        f.write("".join(f"- {line}\n" for line in verdict_lines(records)))
        f.write("\n## Time per phase [s]\n\n")
        f.write(markdown_table(records, phase_cols) + "\n")
    plot_convergence(records, paths["convergence"], title)
    plot_work_precision(records, paths["work_precision"], title)
    return paths
