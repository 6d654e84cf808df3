"""Observed orders of convergence of reconstructed MPM with each scheme (issue 18).

Accuracy only (no timing), so the tables do not depend on the machine's load.
Each table row is one method; its columns the error at each grid and the
observed order between consecutive grids, log2(e_h / e_(h/2)) (the grids
double). Errors are each benchmark's primary error relative to the exact
displacement amplitude (S1 small: RMS at t_end; S3 small and D2 small: as
the study measures them). Mass is consistent throughout; cfl each
scheme's default fraction of its own stable limit (0.6 for rk4, whose limit
is sqrt(2) times the central-difference one, 0.5 for the others; see
skfem_mpm.solve.method.DEFAULT_CFL).

    python benchmarks/orders.py                      # every table
    python benchmarks/orders.py --tables cubic       # one table: cubic, quadratic, d2
    python benchmarks/orders.py --json runs.jsonl    # also the runs as JSON lines
    python benchmarks/orders.py --ppc 3              # another particle count per cell
    python benchmarks/orders.py --cases s3 --recons tls --schemes rk4   # a part of a table
    python benchmarks/orders.py --option frequency_guard=0   # a Method keyword for every run

Tables:
  cubic      S1 small and S3 small, p = 3, 2 particles per cell, spline
             (particle knots, and ``knots="grid"``) / tls x rk4 / cd, 8-16-32
             cells (target: rk4 order >= 3.5 from 8 to 16)
  quadratic  S1 small and S3 small, p = 2, 8 particles per cell, the same
             methods, 16-32-64 cells (target: rk4 >= 2.7 over 16-32-64)

A reconstruction written ``name:option=value`` runs with that option
(``spline:knots=grid``; such runs stay on the reference executor).
  d2         D2 small, p = 2, 3 x 3 particles per cell, none / spline / tls /
             mls x musl / rk4, 8-16-32 cells per axis
"""
import argparse
import json
import math
import sys
import time

TABLES = {
    "cubic": dict(cases=("s1", "s3"), degree=3, ppc=2, cells=(8, 16, 32),
                  recons=("spline", "spline:knots=grid", "tls"), schemes=("rk4", "cd")),
    "quadratic": dict(cases=("s1", "s3"), degree=2, ppc=8, cells=(16, 32, 64),
                      recons=("spline", "spline:knots=grid", "tls"), schemes=("rk4", "cd")),
    "d2": dict(cases=("d2",), degree=2, ppc=3, cells=(8, 16, 32),
               recons=("none", "spline", "tls", "mls"), schemes=("musl", "rk4")),
}
BENCHMARKS = {"s1": ("vibrating-string", "small"), "s3": ("traction-bar", "small"),
              "d2": ("vibrating-plate-2d", "small")}


def error(case, cells, degree, ppc, recon, scheme, cfl=None, **options):
    """The benchmark's primary error of one run (relative), its steps and wall
    time; ``options``: further Method keyword arguments (e.g. frequency_guard)."""
    from skfem_mpm import Method, simulate
    from skfem_mpm.benchmarks import get_benchmark
    from skfem_mpm.solve import prepare

    b = get_benchmark(*BENCHMARKS[case])
    name, _, option = recon.partition(":")  # "spline:knots=grid": with that option
    recon_options = dict([option.split("=", 1)]) if option else None
    method = Method(scheme=scheme, mass="consistent", reconstruction=name, cfl=cfl,
                    reconstruction_options=recon_options, **options)
    scene = b.scene(cells, degree, ppc)
    save_every = None
    if b.saves > 1:  # as the study does for an error over the saves
        save_every = max(1, (prepare(scene, method).n_steps or b.saves) // b.saves)
    t0 = time.perf_counter()
    r = simulate(scene, method, save_every=save_every)
    return b.errors(r)[b.primary_error], r.counts["steps"], time.perf_counter() - t0


def orders(errors):
    """log2(e_k / e_(k+1)) between consecutive grids that each halve h."""
    return [math.log2(a / b) if a > 0 and b > 0 else float("nan")
            for a, b in zip(errors[:-1], errors[1:])]


def overall_order(errors):
    """The order over all the grids, log2(e_first / e_last) / (grids - 1):
    the mean of the consecutive orders (what "order over 16-32-64" reads
    as; each consecutive order is in the table beside it)."""
    a, b = errors[0], errors[-1]
    return math.log2(a / b) / (len(errors) - 1) if a > 0 and b > 0 else float("nan")


def table(name, spec, out=None, options=None):
    """The markdown table of one entry of TABLES (runs it); ``options``:
    further Method keyword arguments of every run (named in the title)."""
    options = options or {}
    cells = spec["cells"]
    head = ("| case | reconstruction | scheme | " + " | ".join(f"{c}" for c in cells) + " | "
            + " | ".join(f"order {a}-{b}" for a, b in zip(cells[:-1], cells[1:]))
            + f" | order {cells[0]}-{cells[-1]} |")
    rows = [f"{name}: degree {spec['degree']}, {spec['ppc']} particles per cell"
            f"{' per axis' if spec['cases'] == ('d2',) else ''}, consistent mass, default cfl"
            + "".join(f", {k}={v}" for k, v in options.items()),
            "", head, "|---" * (3 + 2 * len(cells)) + "|"]
    for case in spec["cases"]:
        for recon in spec["recons"]:
            for scheme in spec["schemes"]:
                errs = []
                for c in cells:
                    try:
                        e, steps, wall = error(case, c, spec["degree"], spec["ppc"], recon, scheme,
                                               **options)
                    except Exception as exc:  # a failed run is a result of the table
                        e, steps, wall = float("nan"), None, None
                        print(f"# {case} {recon} {scheme} {c}: {exc}"[:200], file=sys.stderr)
                    errs.append(e)
                    if out is not None:
                        out.write(json.dumps({"table": name, "case": case, "cells": c,
                                              "degree": spec["degree"], "ppc": spec["ppc"],
                                              "reconstruction": recon, "scheme": scheme,
                                              "options": options,
                                              "error": e, "steps": steps, "wall": wall}) + "\n")
                        out.flush()
                rows.append(f"| {case.upper()} small | {recon} | {scheme} | "
                            + " | ".join(f"{e:.3g}" for e in errs) + " | "
                            + " | ".join(f"{o:.2f}" for o in orders(errs))
                            + f" | {overall_order(errs):.2f} |")
                print(rows[-1], file=sys.stderr, flush=True)
    return "\n".join(rows)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tables", default=",".join(TABLES),
                    help=f"comma-separated, of {', '.join(TABLES)}")
    ap.add_argument("--cells", default=None,
                    help="override the grids, e.g. 8,16 (comma-separated, each twice the last)")
    ap.add_argument("--ppc", type=int, default=None,
                    help="override the particles per cell (per axis in 2D)")
    for key in ("cases", "recons", "schemes"):
        ap.add_argument(f"--{key}", default=None,
                        help=f"override the table's {key} (comma-separated, e.g. "
                             f"{','.join(TABLES['cubic'][key])})")
    ap.add_argument("--json", default=None, help="also write every run as a JSON line here")
    ap.add_argument("--option", action="append", default=[], metavar="NAME=VALUE",
                    help="a further Method keyword of every run, e.g. frequency_guard=0 "
                         "(the value read as JSON where it parses, else a string)")
    a = ap.parse_args()
    names = a.tables.split(",")
    for n in names:
        if n not in TABLES:
            raise SystemExit(f"--tables: {n!r} is not one of {', '.join(TABLES)}")
    from skfem_mpm.study import keyword_options

    try:
        options = keyword_options(a.option)
    except ValueError as exc:
        raise SystemExit(str(exc)) from None
    out = open(a.json, "a") if a.json else None
    try:
        for n in names:
            spec = dict(TABLES[n])
            if a.cells:
                spec["cells"] = tuple(int(c) for c in a.cells.split(","))
            if a.ppc:
                spec["ppc"] = a.ppc
            for key in ("cases", "recons", "schemes"):
                if getattr(a, key):
                    spec[key] = tuple(getattr(a, key).split(","))
            print(table(n, spec, out, options) + "\n", flush=True)
    finally:
        if out is not None:
            out.close()


if __name__ == "__main__":
    main()
