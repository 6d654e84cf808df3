"""The logic of issue 18's evidence scripts (benchmarks/work_precision.py,
benchmarks/orders.py) and what they read from the product: the steps' CPU
time of a run (Result.cpu_time, the study's cpu_time_s) and --option
parsing. Tiny runs (S1 at L = 1, 4 linear cells: what the study's timing
tests compile) or none."""
import importlib.util
import math
import pathlib

import pytest

from skfem_mpm import Method, simulate
from skfem_mpm.benchmarks import get_benchmark
from skfem_mpm.study import keyword_options, parse_method, run_one

BENCHMARKS = pathlib.Path(__file__).resolve().parent.parent / "benchmarks"


def script(name):
    spec = importlib.util.spec_from_file_location(f"bench_{name}", BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_cpu_time_is_the_steps_cpu_time():
    """One thread's CPU time over the steps: positive, and no more than the
    wall time of the same interval times the threads (plus the clocks'
    resolution); a second run of the same scene takes about as long."""
    import numba

    scene = get_benchmark("vibrating-string", "small", L=1.0).scene(4, 1, 2)
    method = Method(scheme="musl")
    simulate(scene, method)  # compiled
    r = simulate(scene, method)
    assert 0.0 < r.cpu_time <= r.wall_time * numba.get_num_threads() + 2e-3
    # the interval is the steps: far less than the process's CPU time so far
    import time

    assert r.cpu_time < 0.5 * time.process_time()


def test_cpu_time_leaves_out_what_the_loop_compiles_in_cpu_seconds(monkeypatch):
    """S2 large at 10 cells: tiny masses at the free top make the loop point
    at its merge kernels mid-run (StepLoop._compile_merge, counted as compile
    time). Under load that part's wall time far exceeds its CPU time; the
    steps' CPU time leaves out the part's CPU seconds, not its wall seconds
    (here 100 s of wall time: the CPU time stays the steps')."""
    from skfem_mpm.solve import compiled_loop

    real = compiled_loop.StepLoop._compile_merge
    calls = []

    def slow_wall(self):
        real(self)
        calls.append(1)
        self.compile_seconds += 100.0

    scene = get_benchmark("soil-column", "large").scene(10, 2, 2)
    simulate(scene, Method(scheme="musl"))  # compiled
    monkeypatch.setattr(compiled_loop.StepLoop, "_compile_merge", slow_wall)
    r = simulate(scene, Method(scheme="musl"))
    assert calls and r.jit_time >= 100.0
    assert 0.0 < r.cpu_time < 1.0


def test_the_study_records_the_median_cpu_time(monkeypatch):
    from skfem_mpm import solve

    real = solve.simulate
    cpus = iter([0.5, 0.1, 0.3])
    calls = []

    def timed(scene, method, **kwargs):
        result = real(scene, method, **kwargs)
        calls.append(scene.t_end)
        if len(calls) > 1:  # a timed run, not the warm-up
            result.cpu_time = next(cpus)
        return result

    monkeypatch.setattr(solve, "simulate", timed)
    job = {"benchmark": "vibrating-string", "variant": "small", "params": {"L": 1.0},
           "method": parse_method("mpm-p1-lumped"), "cells": 4, "ppc": 2, "repeat": 3}
    assert run_one(job)["cpu_time_s"] == 0.3


def test_keyword_options():
    assert keyword_options(["frequency_guard=0", "knots=grid", "cfl=0.25", "x=[1, 2]",
                            "flag=true"]) == {
        "frequency_guard": 0, "knots": "grid", "cfl": 0.25, "x": [1, 2], "flag": True}
    with pytest.raises(ValueError, match=r"--option must be NAME=VALUE, got 'frequency_guard'"):
        keyword_options(["frequency_guard"])
    with pytest.raises(ValueError, match=r"--option must be NAME=VALUE, got '=1'"):
        keyword_options(["=1"])


def _rec(method, degree, cells, error, cpu, case="s1"):
    return {"case": case, "method": method, "degree": degree, "cells": cells, "h": 1.0 / cells,
            "error": error, "cpu_time_s": cpu, "wall_time_s": 10 * cpu, "status": "ok",
            "steps": cells, "ppc": 2, "cpu_time_min_s": cpu, "cpu_time_max_s": cpu,
            "call_cpu_time_s": cpu, "repeats": 3, "timed_compiles": 0, "compared_with": "exact"}


def test_cheapest_of_each_class_and_their_ratio():
    """Time to reach e interpolated in log-log between the bracketing runs
    (the study's), the cheapest per class (degree 1 / 2-3), their ratio;
    a method that never reaches e is never extrapolated to it."""
    wp = script("work_precision")
    records = [
        _rec("lin-a", 1, 8, 1e-5, 0.01), _rec("lin-a", 1, 16, 1e-7, 0.1),   # reaches 1e-6 at 0.0316
        _rec("lin-b", 1, 8, 1e-5, 0.02), _rec("lin-b", 1, 16, 1e-7, 0.04),  # at 0.0283: cheapest
        _rec("high-a", 3, 8, 1e-5, 0.001), _rec("high-a", 3, 16, 1e-7, 0.004),  # at 0.002
        _rec("high-b", 2, 8, 1e-4, 1e-4), _rec("high-b", 2, 16, 2e-6, 2e-4),  # never: 2e-6
    ]
    got = wp.cheapest(records, 1e-6)
    assert got["linear"][0] == "lin-b" and got["linear"][1] == pytest.approx(0.02 * math.sqrt(2))
    assert got["high"] == ("high-a", pytest.approx(0.002))
    assert got["reach"]["high-b"] is None
    line = wp.verdict(records, 1e-6, 10.0)
    assert "cheapest linear lin-b" in line and "high-a" in line
    assert f"{0.02 * math.sqrt(2) / 0.002:.2f}x" in line and "MET" in line and "NOT" not in line
    assert "NOT met" in wp.verdict(records, 1e-6, 20.0)
    only_linear = [r for r in records if r["degree"] == 1 or r["method"] == "high-b"]
    assert "NOT judged" in wp.verdict(only_linear, 1e-6, 10.0)
    # no linear run reaches e (S3: linear MPM floors): the ratio is bounded
    # below by the cheapest linear method's finest run over the high-order time
    stalled = [_rec("lin-c", 1, 8, 1e-4, 0.01), _rec("lin-c", 1, 16, 5e-5, 0.05),
               _rec("lin-d", 1, 8, 1e-4, 0.02), _rec("lin-d", 1, 16, 2e-5, 0.03),
               _rec("high-a", 3, 8, 1e-5, 0.001), _rec("high-a", 3, 16, 1e-7, 0.004)]
    line = wp.verdict(stalled, 1e-6, 10.0)
    assert "no linear run reaches e (smallest error 2e-05, lin-d at 16 cells)" in line
    assert ">= 0.03 s (lin-d at 16 cells)" in line and "> 15.00x (a lower bound)" in line
    assert line.endswith("MET") and "NOT" not in line
    assert wp.verdict(stalled, 1e-6, 20.0).endswith("NOT met")
    table = wp.reach_table(records, 1e-6)
    assert "| high-b | not reached |  | 2e-06 |" in table
    assert "| high-a | 0.002 | 8-16 | 1e-07 |" in table
    matrix = wp.matrix_table(records)
    assert "| method | 8 | 16 |" in matrix and "| high-a | 1e-05 (1) | 1e-07 (4) |" in matrix
    # each run's CPU a step [us]: its steps' CPU over its steps (0.1 s over 40
    # steps at 16 cells), after the steps' CPU and its range
    run = dict(_rec("lin-a", 1, 16, 1e-7, 0.1), steps=40)
    assert "| lin-a | 16 | 2 | 40 | 1e-07 |  | 0.1 (0.1-0.1) | 2.5e+03 |" in wp.curve_table([run])
    # the wall time instead of the CPU time: 10x each, the same ratio
    assert wp.cheapest(records, 1e-6, key="wall_time_s")["high"][1] == pytest.approx(0.02)


def test_work_precision_runs_jobs_in_alternation(monkeypatch):
    """Warm-up twice per job before any timed run, then rounds that run
    every job once each; a job past its budget stops after two timed runs;
    the records carry the medians of the steps' CPU and wall time."""
    from skfem_mpm import solve, study

    wp = script("work_precision")
    real = solve.simulate
    order = []
    warm = []

    def timed(scene, method, **kwargs):
        result = real(scene, method, **kwargs)
        cells = scene.grid.ncells
        order.append(cells)
        result.cpu_time = {4: 2.0, 8: 0.1}[cells] * len([c for c in order if c == cells])
        result.wall_time = 2 * result.cpu_time
        return result

    def warm_up(bench, cells, *args, **kwargs):
        assert not order, "a warm-up after a timed run"
        warm.append(cells)
        return 0.0

    monkeypatch.setattr(solve, "simulate", timed)
    monkeypatch.setattr(study, "warm_up_run", warm_up)
    jobs = wp.make_jobs("s1", ["mpm-p1-lumped-musl"], (4, 8), (), 2)
    for job in jobs:
        job["params"] = {"L": 1.0}
    records = wp.time_alternating(jobs, rounds=4, budget=3.0, log=None)
    assert warm == [4, 8, 4, 8]
    # cells 4 takes 2 s, then 4 s: past the 3 s budget after two runs
    assert order == [4, 8, 4, 8, 8, 8]
    a, b = records
    assert (a["repeats"], a["cpu_time_s"], a["cpu_time_min_s"], a["cpu_time_max_s"]) == (
        2, 3.0, 2.0, 4.0)
    assert (b["repeats"], b["cpu_time_s"], b["wall_time_s"]) == (4, pytest.approx(0.25),
                                                                pytest.approx(0.5))
    assert a["error"] > b["error"] > 0 and a["compared_with"] == "exact"


def test_orders_passes_method_options_to_every_run(monkeypatch):
    orders = script("orders")
    seen = []

    def error(case, cells, degree, ppc, recon, scheme, **options):
        seen.append((case, cells, recon, scheme, options))
        return 2.0 ** (-4 * (cells // 8)), 10, 0.0

    monkeypatch.setattr(orders, "error", error)
    spec = dict(cases=("s1",), degree=3, ppc=2, cells=(8, 16), recons=("spline",),
                schemes=("rk4",))
    text = orders.table("cubic", spec, options={"frequency_guard": 0})
    assert "default cfl, frequency_guard=0" in text
    assert seen == [("s1", 8, "spline", "rk4", {"frequency_guard": 0}),
                    ("s1", 16, "spline", "rk4", {"frequency_guard": 0})]
    assert "| S1 small | spline | rk4 | 0.0625 | 0.00391 | 4.00 | 4.00 |" in text
    assert orders.overall_order([1.0, 2.0 ** -3, 2.0 ** -5]) == 2.5


def test_robustness_table_says_ran_or_fails_per_case_and_reconstruction():
    robustness = script("robustness")
    lines = [
        '{"case": "block", "reconstruction": "none", "status": "ran", "steps": 4628, "t": 1.2}',
        '{"case": "block", "reconstruction": "tls", "status": "failed", "t": 0.5097, "why": '
        '"step 1967 (t = 0.509767 -> 0.510026) failed: J = det(I + dt L) <= 0 at particle 80"}',
        '{"case": "s2", "reconstruction": "none", "status": "ran", "steps": 2973, "t": 0.8, '
        '"error": 0.0123, "compared_with": "same-model reference"}',
        '{"case": "s2", "reconstruction": "tls", "status": "timeout", "timeout": 600}',
        "not a run",
    ]
    assert robustness.table(lines).splitlines() == [
        "| case | none | tls |", "|---|---|---|",
        "| block | ran (4628 steps) | fails, step 1967, t = 0.51: J = det(I + dt L) <= 0 |",
        "| s2 | ran, 0.0123 (2973 steps) | timeout |"]
