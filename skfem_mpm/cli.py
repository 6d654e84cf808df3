"""The ``skfem-mpm`` command line.

    skfem-mpm list
    skfem-mpm run BENCHMARK [--variant V] [--set NAME=VALUE ...] [--degree P] [--cells N]
                            [--ppc K] [--mass M] [--reconstruction R] [--scheme S] [--cfl C]
                            [--dt DT] [--t-end T] [--out DIR [--field F]] [--json]
    skfem-mpm fem BENCHMARK ...            (the same options, Gauss-quadrature FEM)
    skfem-mpm study BENCHMARK [--quick] [--methods M ...] [--cells N ...] [--repeat R]
                              [--out DIR] [--dask ADDRESS] [--serial]
    skfem-mpm bench [--quick] [--json] [--repeat R] [--reference] [--consistent]

Every option's help names its choices and default (``--help``).

Bad arguments print one line ``skfem-mpm: error: ...`` and exit with code 2.
"""
import argparse
import functools
import json
import os
import sys
import time

from .errors import SimulationError

__all__ = ["main"]


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        raise _UsageError(message)


class _UsageError(Exception):
    pass


# seconds of warm-up after which the command line says it is compiling: a
# warm cache loads a run's kernels in well under this, an empty one takes
# tens of seconds
COMPILE_NOTICE_AFTER = 2.0


def _kernel_cache_is_cold():
    """True when numba's cache holds no machine code for the basis-function
    kernels that every compiled run calls first (``kernels.weights``): an
    empty cache (first use, a new NUMBA_CACHE_DIR) or a stale one (numba
    keys its index on the source file's time stamp). Reads the cache index
    files only. None when numba's cache internals are not as expected."""
    try:
        from numba.core.dispatcher import Dispatcher

        from .kernels import weights

        caches = [obj._cache for obj in vars(weights).values()
                  if isinstance(obj, Dispatcher) and hasattr(obj._cache, "_cache_file")]
        if not caches:
            return None
        return not any(c._cache_file._load_index() for c in caches)
    except Exception:  # numba's private cache API moved: fall back on the time alone
        return None


class _CompileNotice:
    """Around a block that compiles or loads kernels (a warm-up run, a
    study's first jobs): once it has lasted ``after`` seconds, the line
    ``compiling kernels (first use only)...`` goes to stderr, completed by
    the block's time when it ends; a shorter block prints nothing, and so
    does any block when ``cold`` is False (:func:`_kernel_cache_is_cold`:
    the kernels load from the cache; a study's first jobs under load last
    longer than ``after`` without compiling anything)."""

    MESSAGE = "compiling kernels (first use only)..."

    def __init__(self, after=None, stream=None, message=None, cold=None):
        self.after = COMPILE_NOTICE_AFTER if after is None else after
        self.cold = cold
        self.message = self.MESSAGE if message is None else message
        self.stream = stream if stream is not None else sys.stderr
        self.shown = False

    def _show(self):
        with self._lock:
            if not self._closed:
                print(self.message, end="", file=self.stream, flush=True)
                self.shown = True

    def __enter__(self):
        import threading

        self._lock = threading.Lock()
        self._closed = False
        self._t0 = time.perf_counter()
        self._timer = threading.Timer(self.after, self._show)
        self._timer.daemon = True
        if self.cold is not False:
            self._timer.start()
        return self

    def __exit__(self, *exc):
        self._timer.cancel()
        with self._lock:
            self._closed = True
            if self.shown:
                print(f" {time.perf_counter() - self._t0:.1f} s", file=self.stream, flush=True)
        return False


def _parse_set(items):
    params = {}
    for item in items or ():
        if "=" not in item:
            raise _UsageError(f"--set expects NAME=VALUE, got {item!r}")
        name, value = item.split("=", 1)
        try:
            params[name.strip()] = float(value)
        except ValueError:
            raise _UsageError(f"--set {name}: value must be a number, got {value!r}") from None
    return params


def _method_default(name):
    """The default of ``Method(name=...)``: the command line and the API agree."""
    import inspect

    from .solve.method import Method

    return inspect.signature(Method).parameters[name].default


def _cfl_default_text():
    """How --cfl's help names its default (Method's DEFAULT_CFL)."""
    from .solve.method import default_cfl

    return f"the scheme's, {default_cfl('rk4')} for rk4 and {default_cfl('musl')} for the others"


def _run_options(p):
    from .solve.method import MASSES, RECONSTRUCTIONS, SCHEMES

    p.add_argument("benchmark", help="a benchmark name (see 'skfem-mpm list')")
    p.add_argument("--variant", default=None, help="the benchmark's variant (default: its first)")
    p.add_argument("--set", action="append", metavar="NAME=VALUE", dest="params",
                   help="override a benchmark parameter (repeatable; default: none)")
    p.add_argument("--degree", type=int, default=2, choices=(1, 2, 3),
                   help="B-spline degree (default: %(default)s)")
    p.add_argument("--cells", type=int, default=None,
                   help=f"cells per axis (default: {RUN_CELLS[1]}; {RUN_CELLS[3]} in 3D)")
    p.add_argument("--ppc", type=int, default=2,
                   help="particles per cell and axis (default: %(default)s)")
    p.add_argument("--mass", default=_method_default("mass"), choices=MASSES,
                   help="mass matrix (default: %(default)s, as Method())")
    p.add_argument("--reconstruction", default=_method_default("reconstruction"),
                   choices=RECONSTRUCTIONS, help="particle data reconstruction before Gauss "
                   "integration (default: %(default)s)")
    p.add_argument("--scheme", default=_method_default("scheme"), choices=SCHEMES,
                   help="time-stepping scheme (default: %(default)s)")
    p.add_argument("--cfl", type=float, default=_method_default("cfl"),
                   help=f"time step as a fraction of the critical one (default: "
                   f"{_cfl_default_text()}, as Method())")
    p.add_argument("--dt", type=float, default=None,
                   help="a fixed time step instead of --cfl (default: cfl * dt_crit)")
    p.add_argument("--t-end", type=float, default=None, dest="t_end",
                   help="end time (default: the benchmark's)")
    p.add_argument("--out", default=None, help="write a ParaView series and PNG pictures "
                   "into this folder (default: none)")
    p.add_argument("--field", default="stress", choices=RUN_FIELDS,
                   help="with --out: the field drawn at a few times in particles_FIELD.png "
                   "(1D: a line over position; default: %(default)s)")
    p.add_argument("--json", action="store_true", help="print one JSON object (default: a "
                   "table)")


def build_parser():
    from .solve.method import MASSES, RECONSTRUCTIONS, SCHEMES
    from .study import COMPARE_WITH, DEFAULTS, QUICK, QUICK_METHODS, STUDY_CELLS

    parser = _Parser(prog="skfem-mpm", description="B-spline MPM and FEM benchmarks "
                     "(scikit-fem plugin): errors and what they cost in time.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    sub.add_parser("list", help="benchmarks, variants and their defaults")
    _run_options(sub.add_parser("run", help="run one MPM simulation of a benchmark"))
    _run_options(sub.add_parser("fem", help="run the FEM reference of a benchmark"))
    s = sub.add_parser("study", help="convergence and work-precision study")
    s.add_argument("benchmark", help="a benchmark with an exact solution (see 'skfem-mpm list')")
    s.add_argument("--variant", default=None, help="the benchmark's variant (default: its first)")
    s.add_argument("--set", action="append", metavar="NAME=VALUE", dest="params",
                   help="override a benchmark parameter (repeatable; default: none)")
    s.add_argument("--quick", action="store_true",
                   help=f"a small study: methods {' '.join(QUICK_METHODS)}; cells "
                   f"{' '.join(map(str, STUDY_CELLS[1][0]))} in 1D, "
                   f"{' '.join(map(str, STUDY_CELLS[2][0]))} in 2D, "
                   f"{' '.join(map(str, STUDY_CELLS[3][0]))} in 3D; {QUICK['repeat']} timed "
                   f"repeats, 2 once two have taken {QUICK['repeat_budget']:g} s (default: off, "
                   f"the full study)")
    s.add_argument("--methods", nargs="+", default=None, metavar="METHOD",
                   help="methods named kind-pN-mass[-reconstruction][-scheme]: kind mpm or fem, "
                   f"N 1-3, mass {{{','.join(MASSES)}}}, reconstruction "
                   f"{{{','.join(RECONSTRUCTIONS)}}}, scheme {{{','.join(SCHEMES)}}} "
                   "(default: the quick or the full list)")
    s.add_argument("--cells", nargs="+", type=int, default=None, metavar="N",
                   help="cells per axis, one run each (default: "
                   f"{' '.join(map(str, STUDY_CELLS[1][1]))} in 1D, "
                   f"{' '.join(map(str, STUDY_CELLS[2][1]))} in 2D, "
                   f"{' '.join(map(str, STUDY_CELLS[3][1]))} in 3D; --quick: see there)")
    # the defaults are the API's (skfem_mpm.study.DEFAULTS, convergence()'s)
    s.add_argument("--ppc", type=int, default=DEFAULTS["ppc"],
                   help="particles per cell and axis (default: %(default)s, as "
                   "study.convergence())")
    s.add_argument("--scheme", default=DEFAULTS["scheme"], choices=SCHEMES,
                   help="scheme of methods that name none (default: %(default)s, as "
                   "study.convergence() and Method())")
    s.add_argument("--cfl", type=float, default=DEFAULTS["cfl"],
                   help=f"time step as a fraction of the critical one (default: "
                   f"{_cfl_default_text()}, as study.convergence() and Method())")
    s.add_argument("--repeat", type=int, default=None,
                   help="timed runs per job, the median is reported (default: "
                   f"{QUICK['repeat']} with --quick, else {DEFAULTS['repeat']} as "
                   "study.convergence())")
    s.add_argument("--compare-with", default="auto", choices=COMPARE_WITH, dest="compare_with",
                   help="what errors are measured against: auto, the benchmark's exact "
                   "solution, or for a variant beyond its exact solution's model (soil-column "
                   "large) MPM runs against a fine FEM of the same model, computed once and "
                   "cached; exact: always the exact solution (default: %(default)s)")
    s.add_argument("--out", default="skfem-mpm-report",
                   help="folder for study.csv, study.md and the PNGs (default: %(default)s)")
    s.add_argument("--dask", default=None, metavar="ADDRESS",
                   help="run on a Dask cluster (scheduler address; default: a local process "
                   "pool, one worker per core)")
    s.add_argument("--serial", action="store_true",
                   help="run in this process, one at a time (default: off)")
    b = sub.add_parser("bench", help="particle-steps per second of the fast path")
    b.add_argument("--quick", action="store_true",
                   help="smaller problems (64^2 cells in 2D, 25,000 in 1D), 20 steps, one run "
                   "(default: off: 128^2 and 250,000 cells, 200 steps)")
    b.add_argument("--json", action="store_true", help="print one JSON object (default: text)")
    b.add_argument("--repeat", type=int, default=None,
                   help="timed runs per problem, the median is reported (default: 5; 1 with "
                   "--quick)")
    b.add_argument("--reference", action="store_true",
                   help="also time the NumPy reference path, with our ratio to it (default: off)")
    b.add_argument("--consistent", action="store_true",
                   help="also compare consistent with lumped mass per step (default: off)")
    return parser


def _cmd_list(args):
    from .benchmarks import BENCHMARKS

    for name, cls in BENCHMARKS.items():
        print(f"{name}: {cls.title} ({cls.dim}D{'' if cls.has_exact else ', no exact solution'})")
        print(f"    defaults: {', '.join(f'{k}={v}' for k, v in cls.defaults.items())}")
        for i, (variant, over) in enumerate(cls.variants.items()):
            extra = ", ".join(f"{k}={v}" for k, v in over.items()) or "the defaults"
            note = " (default)" if i == 0 else ""
            if cls.name == "vibrating-string" and variant == "small":
                extra = "v0 = 1e-6 c (peak strain 1e-6)"
            print(f"    variant {variant}{note}: {extra}")
    return 0


def _check_run_args(args):
    if args.field == "error" and args.out is not None:
        from .benchmarks import get_benchmark

        if not get_benchmark(args.benchmark, args.variant, **_parse_set(args.params)).has_exact:
            raise _UsageError(f"--field error: {args.benchmark} has no exact solution; choose "
                              f"one of {', '.join(RUN_FIELDS[:3])}")
    if args.degree not in (1, 2, 3):
        raise _UsageError(f"--degree must be 1, 2 or 3, got {args.degree}")
    for flag, value in (("--t-end", args.t_end), ("--dt", args.dt), ("--cfl", args.cfl)):
        if value is not None and not value > 0:
            raise _UsageError(f"{flag} must be a positive number, got {value}")
    if args.cells is not None and args.cells < 1:
        raise _UsageError(f"--cells must be a positive integer, got {args.cells}")
    if args.ppc < 1:
        raise _UsageError(f"--ppc must be a positive integer, got {args.ppc}")


def _cmd_run(args, kind):
    from .benchmarks import get_benchmark
    from .solve import Method, fem, prepare, simulate
    from .study import warm_up_run

    _check_run_args(args)
    _check_out(args.out)
    bench = get_benchmark(args.benchmark, args.variant, **_parse_set(args.params))
    if args.cells is None:
        args.cells = RUN_CELLS[bench.dim]
    method = Method(scheme=args.scheme, mass=args.mass, reconstruction=args.reconstruction,
                    cfl=args.cfl, dt=args.dt)
    with _CompileNotice(cold=_kernel_cache_is_cold()):
        first_use = warm_up_run(bench, args.cells, args.degree, args.ppc, method,
                                kind == "fem", args.t_end)
    # the run's scene after the warm-up's: a benchmark's checks read the
    # effects of the scene it built last (e.g. the strip footing's record)
    scene = bench.scene(args.cells, args.degree, args.ppc, fem=kind == "fem", t_end=args.t_end)
    save_every = None
    if args.out:
        steps = prepare(scene, method).n_steps or 100
        save_every = max(1, steps // 50)
    if kind == "fem":
        result = fem(scene, method, save_every=save_every, progress=not args.json)
    else:
        result = simulate(scene, method, save_every=save_every, progress=not args.json)
    record = {"benchmark": bench.name, "variant": bench.variant, "kind": kind,
              "degree": args.degree, **method.as_dict(), "cells": args.cells, "ppc": args.ppc,
              "dofs": scene.grid.ndofs, "particles": result.counts["particles"],
              "steps": result.counts["steps"], "dt": result.dt, "t_end": result.final_time}
    if bench.has_exact:
        record.update(bench.errors(result))
    else:
        record.update(bench.checks(result))
    record.update(wall_time_s=result.wall_time, jit_time_s=first_use + result.jit_time,
                  phase_times=result.phase_table())
    if args.out:
        _write_run_pictures(result, bench, args.out, args.field)
        record["out"] = os.path.abspath(args.out)
    if args.json:
        print(json.dumps(record, default=float))
        return 0
    width = max(len(k) for k in record)
    for k, v in record.items():
        if k == "phase_times":
            print(f"{'phase times [s]':<{width}}  " + ", ".join(f"{p} {s:.3g}" for p, s in v.items()))
        else:
            print(f"{k:<{width}}  {v:.6g}" if isinstance(v, float) else f"{k:<{width}}  {v}")
    return 0


def _write_run_pictures(result, bench, out, field="stress"):
    from .plot import (
        plot_displacement_history,
        plot_energy,
        plot_field_snapshots,
        plot_particles,
    )

    result.save(out)
    exact = bench.displacement if bench.has_exact else None
    plot_field_snapshots(result, os.path.join(out, f"particles_{field}.png"), field=field,
                         exact=exact)
    if exact is not None and field != "error":
        plot_particles(result, os.path.join(out, "particles_error.png"), field="error",
                       exact=exact)
    plot_energy(result, os.path.join(out, "energy.png"))
    plot_displacement_history(result, os.path.join(out, "displacement.png"), exact=exact)


RUN_FIELDS = ("stress", "velocity", "displacement", "error")
# default cells per axis of `run` and `fem`; 3D runs on the reference executor
RUN_CELLS = {1: 16, 2: 16, 3: 4}


def _cmd_study(args):
    from .benchmarks import get_benchmark
    from .model_reference import model_reference
    from .study import (
        DEFAULTS,
        FULL_METHODS,
        QUICK,
        QUICK_METHODS,
        STUDY_CELLS,
        convergence,
        markdown_table,
        parse_method,
        time_to_reach_table,
        verdict_lines,
        write_report,
    )

    params = _parse_set(args.params)
    bench = get_benchmark(args.benchmark, args.variant, **params)
    if not bench.has_exact:
        raise _UsageError(f"{bench.name} has no exact solution to study; use 'run' for its checks")
    methods = args.methods or (QUICK_METHODS if args.quick else FULL_METHODS)
    cells = args.cells or STUDY_CELLS[bench.dim][0 if args.quick else 1]
    if any(c < 1 for c in cells):
        raise _UsageError(f"--cells must be positive integers, got {cells}")
    if args.ppc < 1:
        raise _UsageError(f"--ppc must be a positive integer, got {args.ppc}")
    if args.cfl is not None and not args.cfl > 0:
        raise _UsageError(f"--cfl must be a positive number, got {args.cfl}")
    if args.cfl is not None and args.cfl > 1:  # every job would fail on it
        raise _UsageError(f"--cfl must be at most 1 (above it the time step exceeds the "
                          f"critical one), got {args.cfl}")
    if args.repeat is not None and args.repeat < 1:
        raise _UsageError(f"--repeat must be a positive integer, got {args.repeat}")
    for name in methods:  # before the same-model reference is computed
        parse_method(name)
    repeat = args.repeat or (QUICK["repeat"] if args.quick else DEFAULTS["repeat"])
    budget = QUICK["repeat_budget"] if args.quick and args.repeat is None else None
    _check_out(args.out)
    ppc, scheme, cfl = args.ppc, args.scheme, args.cfl
    executor = None
    where = (f"a local process pool with {os.cpu_count()} workers, one thread each, so runs "
             f"never share a core")
    if args.serial:
        executor = "serial"
        where = "one at a time in one process"
    if args.dask:
        from dask.distributed import Client

        executor = Client(args.dask)
        where = (f"Dask cluster at {args.dask} "
                 f"({len(executor.scheduler_info()['workers'])} workers)")
    runs = f"{repeat} timed run(s)" if budget is None else (
        f"up to {repeat} timed runs (2 once two have taken {budget:g} s; column repeats)")
    note = (f"Timed runs: {where}. Wall time: the median of {runs} after an "
            f"untimed warm-up run that compiles every kernel (its time: jit_time_s).")
    reference = None
    if args.compare_with == "auto" and any(m.startswith("mpm") for m in methods):
        with _CompileNotice(message="computing the same-model reference (first use only)..."):
            reference = model_reference(bench)
    records = convergence(bench.name, methods, cells, ppc=ppc, variant=bench.variant,
                          params=params, executor=executor, progress=True, scheme=scheme, cfl=cfl,
                          repeat=repeat, repeat_budget=budget,
                          compile_notice=functools.partial(_CompileNotice,
                                                           cold=_kernel_cache_is_cold()),
                          compare_with=args.compare_with)
    leaked = sum(r.get("timed_compiles") or 0 for r in records)
    if leaked:
        note += f" WARNING: {leaked} kernel(s) compiled during timed runs."
    setup = (f"{bench.title}, variant {bench.variant}: ppc {ppc} per axis, scheme {scheme}, "
             f"cfl {cfl}. Errors: " + ("max over the saves of the RMS displacement error"
                                       if bench.primary_error == "error_max" else
                                       "RMS displacement error at t_end")
             + " relative to the amplitude.")
    gap = bench.model_gaps.get(bench.variant)
    if reference is not None:
        setup += (f" MPM runs compared with: {reference.describe()}, which MPM's model "
                  f"leaves at variant {bench.variant} by more than the methods' errors (the "
                  f"column error_exact is the error against it); FEM runs (small strain: the "
                  f"linear model) with the exact solution.")
    else:
        setup += " Compared with: the benchmark's exact solution."
        if gap and any(name.startswith("mpm") for name in methods):
            setup += f" WARNING, variant {bench.variant}: {gap}."
        elif gap:  # the gap is MPM's model's: fem's small-strain law is the linear one
            setup += (f" At variant {bench.variant} MPM's model leaves that solution; FEM's "
                      f"small-strain LinearElastic is its linear model, so FEM errors measure "
                      f"the method.")
    paths = write_report(records, args.out, title=f"{bench.name} ({bench.variant})",
                         timing_note=setup + "\n\n" + note)
    print(setup)
    print(note)
    print(markdown_table(records))
    print("time to reach a relative error e [s] (interpolated in log-log between the runs "
          "that bracket e; <= the coarsest run already reaches e; blank: not reached):")
    print(time_to_reach_table(records))
    print("verdict:")
    for line in verdict_lines(records):
        print("  " + line)
    for key in ("csv", "md", "convergence", "work_precision"):
        print(f"wrote {paths[key]}")
    return 0


def _check_out(out):
    """--out must be a folder that exists or can be made (checked before a
    run, so that a run is not lost when its output cannot be written)."""
    if out is None:
        return
    if os.path.exists(out) and not os.path.isdir(out):
        raise _UsageError(f"--out {out!r} is a file, not a folder")
    parent = os.path.dirname(os.path.abspath(out))
    while not os.path.exists(parent):
        parent = os.path.dirname(parent)
    if not os.path.isdir(parent):
        raise _UsageError(f"--out {out!r}: {parent!r} is a file, not a folder")
    from .validation import can_write_in

    target = out if os.path.isdir(out) else parent
    if not can_write_in(target):
        raise _UsageError(f"--out {out!r}: {target!r} is not writable")


def _cmd_bench(args):
    from .bench import main as bench_main

    if args.repeat is not None and args.repeat < 1:
        raise _UsageError(f"--repeat must be a positive integer, got {args.repeat}")

    argv = [f"--{flag}" for flag in ("quick", "json", "reference", "consistent")
            if getattr(args, flag)]
    if args.repeat is not None:
        argv += ["--repeat", str(args.repeat)]
    return bench_main(argv)


def main(argv=None):
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
        if args.command == "list":
            return _cmd_list(args)
        if args.command in ("run", "fem"):
            return _cmd_run(args, args.command)
        if args.command == "study":
            return _cmd_study(args)
        if args.command == "bench":
            return _cmd_bench(args)
    except (_UsageError, ValueError) as exc:
        message = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        print(f"skfem-mpm: error: {message}", file=sys.stderr)
        return 2
    except SimulationError as exc:
        print(f"skfem-mpm: run failed: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
