"""Robustness of each reconstruction on the hard 2D scenes (issue 18).

Each case runs with reconstruction none, spline, tls, mls (quadratic,
consistent mass, MUSL, default cfl unless a case says otherwise), each in
its own process with a time limit; prints one JSON line per run: ran or
failed (the exception), steps, wall time, final time, and the case's error
where it has an exact solution (as a study measures it: S2 large against the
same-model reference, ``compared_with`` says which).

    python benchmarks/robustness.py [--cases d1,block,...] [--recon none,tls] > runs.jsonl
    python benchmarks/robustness.py --table runs.jsonl     # the note's markdown table

``--option name=value`` passes a reconstruction option (e.g.
``constraint=mean`` for tls), ``--backend numpy`` the reference executor.
"""
import argparse
import json
import subprocess
import sys
import time

CASES = ("d1", "d2small", "block", "expanding", "s2", "d2", "disks")
RECONS = ("none", "spline", "tls", "mls")


def scene(case, ppc):
    from skfem_mpm import (
        Body,
        Fixed,
        Gravity,
        LinearElastic,
        Particles,
        Scene,
        SplineGrid,
    )
    from skfem_mpm.benchmarks import get_benchmark

    if case == "d1":      # D1 large, 16 x 16
        b = get_benchmark("axis-aligned-2d", "large")
        return b.scene(16, 2, ppc), b
    if case == "d2small":  # D2 small, 16 x 16 (the accuracy case)
        b = get_benchmark("vibrating-plate-2d", "small")
        return b.scene(16, 2, ppc), b
    if case == "d2":      # D2 large, 16 x 16
        b = get_benchmark("vibrating-plate-2d", "large")
        return b.scene(16, 2, ppc), b
    if case == "s2":      # S2 large, 80 cells (grid crossing at the free top)
        b = get_benchmark("soil-column", "large")
        return b.scene(80, 2, ppc), b
    if case == "disks":   # D3, 20 x 20 to t = 3.5
        b = get_benchmark("colliding-disks")
        return b.scene(20, 2, ppc), None
    if case == "block":   # falls 0.45 in 0.3 s onto a fixed floor, rests there until t = 1.2
        grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), 16, 2)
        parts = Particles.seed(grid, ppc, 1000.0, region=((0.3, 0.7), (0.45, 0.65)))
        return Scene(grid, Body(parts, LinearElastic(1e6, 0.3)), 1.2,
                     effects=[Gravity((0.0, -9.81)), Fixed("bottom")]), None
    if case == "expanding":  # 32 x 32, initial v = 0.4 (x - 0.5), walls fixed, gravity
        from skfem_mpm.bench import consistent_scene
        s, _ = consistent_scene(32, 200, "expanding block")
        return s, None
    raise ValueError(f"case must be one of {CASES}, got {case!r}")


def one(case, recon, ppc, cfl, options=None, backend=None):
    from skfem_mpm import Method, simulate
    from skfem_mpm.errors import SimulationError
    from skfem_mpm.study import job_errors

    s, b = scene(case, ppc)
    m = Method(mass="consistent", scheme="musl", reconstruction=recon, cfl=cfl,
               reconstruction_options=options or None, backend=backend)
    t0 = time.perf_counter()
    out = {"case": case, "reconstruction": recon, "ppc": ppc, "cfl": cfl}
    if options:
        out["options"] = options
    if backend:
        out["backend"] = backend
    try:
        r = simulate(s, m, save_every=20)
        out.update(status="ran", steps=r.counts["steps"], t=r.final_time)
        if b is not None:  # as a study measures it (S2 large: the same-model reference)
            e = job_errors(b, r, {"method": {"kind": "mpm"}})
            out.update(error=e["error"], compared_with=e["compared_with"])
    except SimulationError as exc:
        out.update(status="failed", why=str(exc)[:200],
                   t=getattr(exc.result, "final_time", None))
    out["wall"] = time.perf_counter() - t0
    return out


def table(lines):
    """Markdown table, one row per case and one column per reconstruction:
    "ran, error e (steps)" or "fails: why" from the JSON lines of runs."""
    runs = [json.loads(line) for line in lines if line.strip().startswith("{")]
    cases = list(dict.fromkeys(r["case"] for r in runs))
    recons = list(dict.fromkeys(r["reconstruction"] + (
        "".join(f" {k}={v}" for k, v in r.get("options", {}).items())) for r in runs))
    cell = {}
    for r in runs:
        name = r["reconstruction"] + "".join(f" {k}={v}" for k, v in r.get("options", {}).items())
        if r["status"] == "ran":
            text = "ran" + (f", {r['error']:.3g}" if "error" in r else "") + f" ({r['steps']} steps)"
        elif r["status"] == "failed":
            step, _, why = r["why"].partition(" failed: ")
            text = f"fails, {step.split(' (')[0]}, t = {r['t']:.3g}: {why.split(' at ')[0][:40]}" \
                if r.get("t") is not None else f"fails: {r['why'][:60]}"
        else:
            text = r["status"]
        cell[r["case"], name] = text
    rows = ["| case | " + " | ".join(recons) + " |", "|---" * (len(recons) + 1) + "|"]
    for case in cases:
        rows.append(f"| {case} | " + " | ".join(cell.get((case, n), "") for n in recons) + " |")
    return "\n".join(rows)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--recon", default=",".join(RECONS))
    ap.add_argument("--ppc", type=int, default=3)
    ap.add_argument("--cfl", type=float, default=0.5)
    ap.add_argument("--timeout", type=float, default=1200.0)
    ap.add_argument("--one", nargs=2)
    ap.add_argument("--option", action="append", default=[])
    ap.add_argument("--backend", default=None)
    ap.add_argument("--table")
    a = ap.parse_args()
    if a.table:
        with open(a.table) as f:
            print(table(f.readlines()))
        return
    from skfem_mpm.study import keyword_options

    try:
        options = keyword_options(a.option)  # numbers as numbers
    except ValueError as exc:
        raise SystemExit(str(exc)) from None
    if a.one:
        print(json.dumps(one(a.one[0], a.one[1], a.ppc, a.cfl, options, a.backend)), flush=True)
        return
    for case in a.cases.split(","):
        for recon in a.recon.split(","):
            cmd = [sys.executable, __file__, "--one", case, recon, "--ppc", str(a.ppc),
                   "--cfl", str(a.cfl)] + [f"--option={o}" for o in a.option] + (
                       ["--backend", a.backend] if a.backend else [])
            try:
                p = subprocess.run(cmd, capture_output=True, text=True, timeout=a.timeout, check=False)
                line = p.stdout.strip().splitlines()[-1] if p.stdout.strip() else json.dumps(
                    {"case": case, "reconstruction": recon, "status": "error",
                     "why": p.stderr.strip().splitlines()[-1][:200]})
            except subprocess.TimeoutExpired:
                line = json.dumps({"case": case, "reconstruction": recon, "status": "timeout",
                                   "timeout": a.timeout})
            print(line, flush=True)


if __name__ == "__main__":
    main()
