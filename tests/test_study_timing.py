"""What a study's times mean: compilation kept out of the timed runs, the
median of repeats, the "time to reach e" table and the verdict."""
import pytest

from skfem_mpm.study import (
    QUICK_METHODS,
    REACH_TARGETS,
    convergence,
    parse_method,
    run_one,
    time_to_reach,
    time_to_reach_table,
    verdict,
    verdict_lines,
)


def test_no_kernel_compiles_or_loads_during_the_timed_runs():
    """In fresh worker processes (numba's disk cache may be warm: a cache
    load counts too), every quick method plus consistent mass with and
    without a reconstruction (spline, tls), hybrid and rk4 compiles all its
    kernels in the untimed warm-up run."""
    methods = list(dict.fromkeys(list(QUICK_METHODS) + [
        "mpm-p2-consistent", "mpm-p3-consistent", "mpm-p2-consistent-spline",
        "mpm-p3-consistent-spline", "mpm-p2-consistent-tls", "mpm-p2-hybrid-spline-musl",
        "mpm-p3-consistent-spline-rk4"]))
    records = convergence("vibrating-string", methods, [8], ppc=2, params={"L": 1.0},
                          scheme="cd", cfl=0.1, repeat=2)
    assert [r["status"] for r in records] == ["ok"] * len(methods)
    leaks = {r["method"]: r["timed_compiles"] for r in records if r["timed_compiles"]}
    assert not leaks, f"kernels compiled or loaded while timed: {leaks}"
    for r in records:
        assert r["repeats"] == 2 and r["jit_time_s"] > 0
        assert r["wall_time_min_s"] <= r["wall_time_s"] <= r["wall_time_max_s"]


def test_wall_time_is_the_median_of_the_repeats(monkeypatch):
    from skfem_mpm import solve

    real = solve.simulate
    walls = iter([5.0, 1.0, 3.0])

    calls = []

    def timed(scene, method, **kwargs):
        result = real(scene, method, **kwargs)
        calls.append(scene.t_end)
        if len(calls) > 1:  # a timed run, not the warm-up (the first, shorter)
            assert scene.t_end > calls[0]
            result.wall_time = next(walls)
        return result

    monkeypatch.setattr(solve, "simulate", timed)
    job = {"benchmark": "vibrating-string", "variant": "small", "params": {"L": 1.0},
           "method": parse_method("mpm-p1-lumped"), "cells": 4, "ppc": 2, "repeat": 3}
    r = run_one(job)
    assert (r["wall_time_s"], r["wall_time_min_s"], r["wall_time_max_s"]) == (3.0, 1.0, 5.0)
    with pytest.raises(ValueError, match="repeat must be a positive integer, got 0"):
        convergence("vibrating-string", ["mpm-p1-lumped"], [4], repeat=0, executor="serial")


def _run(method, cells, error, wall, spread=0.0):
    return {"method": method, "cells": cells, "error": error, "wall_time_s": wall,
            "wall_time_min_s": wall * (1 - spread), "wall_time_max_s": wall * (1 + spread),
            "status": "ok"}


def test_time_to_reach_table_spans_1e_3_to_1e_7_and_never_extrapolates():
    records = [_run("a", 8, 1e-2, 1.0), _run("a", 16, 1e-4, 4.0), _run("a", 32, 1e-6, 16.0),
               _run("b", 8, 5e-4, 0.5), _run("b", 16, 2e-5, 1.0)]
    table = time_to_reach_table(records)
    header = table.splitlines()[0]
    assert [f"e = {e:.0e}" in header for e in REACH_TARGETS] == [True] * 5
    # a: 1e-3 halfway (in log error) between 1 s and 4 s -> 2 s; 1e-7 beyond its last run
    assert "| a | 2 | 4 | 8 | 16 |  |" in table
    # b: its coarsest run already reaches 1e-3 (an upper bound, marked); 1e-6 not reached
    assert table.splitlines()[3].startswith("| b | <= 0.5 |")
    assert table.splitlines()[3].endswith("|  |  |")
    assert time_to_reach(records, 1e-7) == {"a": None, "b": None}


def test_verdict_names_the_cheapest_method_and_its_margin():
    records = [_run("a", 8, 1e-2, 1.0, 0.1), _run("a", 16, 1e-4, 4.0, 0.1),
               _run("b", 8, 1e-2, 0.2, 0.5), _run("b", 16, 1e-4, 3.0, 0.5),
               _run("c", 8, 1e-3, 5.0, 0.01), _run("c", 16, 1e-5, 10.0, 0.01)]
    rows = {v["target"]: v for v in verdict(records)}
    # 1e-4: b (3.0 s) beats a (4.0 s) by 1.33x, but b's slowest repeat (4.5 s)
    # is slower than a's fastest (3.6 s): not robust
    assert rows[1e-4]["best"] == "b" and rows[1e-4]["runner_up"] == "a"
    assert rows[1e-4]["ratio"] == pytest.approx(4.0 / 3.0)
    assert rows[1e-4]["worst_ratio"] == pytest.approx(3.6 / 4.5) and not rows[1e-4]["holds"]
    # 1e-3: b (0.2 s -> 3 s, halfway in log: 0.77 s) before a (2 s); 1e-5: only c
    assert rows[1e-3]["best"] == "b" and rows[1e-3]["runner_up"] == "a"
    assert rows[1e-5]["best"] == "c" and rows[1e-5]["runner_up"] is None
    assert rows[1e-6]["best"] is None
    lines = verdict_lines(records)
    assert lines[1].startswith("e = 1e-04: cheapest b (3 s), 1.33x faster than the runner-up a")
    assert "NOT robust" in lines[1] and "the only method" in lines[2]
    assert lines[3] == "e = 1e-06: no method reaches it in this study"
    c_wins = [_run("a", 8, 1e-2, 1.0, 0.1), _run("a", 16, 1e-4, 4.0, 0.1),
              _run("c", 8, 1e-3, 2.0, 0.01), _run("c", 16, 1e-5, 4.0, 0.01)]
    v = verdict(c_wins, [1e-4])[0]  # c: 1e-4 halfway between 2 s and 4 s in log
    assert v["best"] == "c" and v["holds"] and v["ratio"] == pytest.approx(4.0 / 2 ** 1.5)
    for r in c_wins:  # one timed run each: nothing to judge robustness by
        r["repeats"] = 1
    assert verdict(c_wins, [1e-4])[0]["holds"] is None
    assert "one timed run each" in verdict_lines(c_wins, [1e-4])[0]


def test_a_repeat_budget_stops_long_jobs_after_two_runs(monkeypatch):
    """repeat 3 with a 2 s budget: a job whose runs take 1.5 s stops after
    two (3 s >= 2 s), one whose runs take 0.5 s runs three times; the
    median and range come from the runs made."""
    from skfem_mpm import solve

    real = solve.simulate

    def timed_at(wall):
        calls = []

        def timed(scene, method, **kwargs):
            result = real(scene, method, **kwargs)
            calls.append(scene.t_end)
            if len(calls) > 1:  # a timed run, not the warm-up
                result.wall_time = wall + 0.01 * len(calls)
            return result
        return timed

    job = {"benchmark": "vibrating-string", "variant": "small", "params": {"L": 1.0},
           "method": parse_method("mpm-p1-lumped"), "cells": 4, "ppc": 2, "repeat": 3,
           "repeat_budget": 2.0}
    monkeypatch.setattr(solve, "simulate", timed_at(1.5))
    r = run_one(job)
    assert r["repeats"] == 2 and (r["wall_time_min_s"], r["wall_time_max_s"]) == (1.52, 1.53)
    monkeypatch.setattr(solve, "simulate", timed_at(0.5))
    r = run_one(job)
    assert r["repeats"] == 3 and r["wall_time_s"] == 0.53
    monkeypatch.setattr(solve, "simulate", timed_at(1.5))
    assert run_one(dict(job, repeat_budget=None))["repeats"] == 3
    with pytest.raises(ValueError, match="repeat_budget must be a positive number"):
        convergence("vibrating-string", ["mpm-p1-lumped"], [4], repeat_budget=0,
                    executor="serial")
