"""Every command-line option says its choices and default, and a bad value
is refused before anything runs: exit 2, one line naming the option."""
import argparse
import os

import pytest

from skfem_mpm.cli import build_parser, main


def _subcommands():
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices


@pytest.mark.parametrize("command", ["run", "fem", "study", "bench"])
def test_every_option_names_its_default_and_choices(command):
    parser = _subcommands()[command]
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction) or not action.option_strings:
            continue
        text = action.help or ""
        assert "default" in text, f"{command} {action.option_strings[0]}: no default in {text!r}"
        if action.choices is not None:
            help_text = " ".join(parser.format_help().split())
            listing = "{" + ",".join(map(str, action.choices)) + "}"
            assert listing in help_text, f"{command} {action.option_strings[0]}: no choices"


def test_study_help_gives_the_quick_settings(capsys):
    with pytest.raises(SystemExit):
        main(["study", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "3 timed repeats" in text and "fem-p2-consistent" in text
    assert "cells 8 16 32 64 in 1D" in text


@pytest.mark.parametrize("argv, fragment", [
    (["study", "vibrating-string", "--repeat", "0"], "--repeat must be a positive integer, got 0"),
    (["study", "vibrating-string", "--repeat", "-1"], "--repeat must be a positive integer, got -1"),
    (["study", "vibrating-string", "--cells", "0", "8"], "--cells must be positive integers"),
    (["study", "vibrating-string", "--scheme", "leapfrog"], "--scheme: invalid choice"),
    (["study", "vibrating-string", "--out", __file__], "is a file, not a folder"),
    (["study", "vibrating-string", "--out", __file__ + "/report"], "is a file, not a folder"),
    (["run", "vibrating-string", "--out", __file__ + "/deeper/run"], "is a file, not a folder"),
    (["run", "vibrating-string", "--ppc", "0"], "--ppc must be a positive integer, got 0"),
    (["run", "vibrating-string", "--cfl", "0"], "--cfl must be a positive number, got 0"),
    (["fem", "vibrating-string", "--t-end", "-1"], "--t-end must be a positive number, got -1"),
    (["run", "vibrating-string", "--field", "pressure"], "--field: invalid choice"),
    (["run", "colliding-disks", "--field", "error", "--out", "x"], "has no exact solution"),
])
def test_bad_values_are_refused_before_running(argv, fragment, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("skfem-mpm: error:") and fragment in err, err


def test_a_fem_study_beyond_mpms_model_says_why_fem_is_still_measured_right(tmp_path,
                                                                            capsys):
    """S2 large (10% strain) with FEM only: FEM's small-strain LinearElastic
    is the linear model of the exact solution, so the header says so and
    does not warn (the warning is for MPM against the exact solution:
    tests/test_model_reference.py); S2 small's says nothing of it."""
    for variant, noted in (("large", True), ("small", False)):
        out = tmp_path / variant
        assert main(["study", "soil-column", "--variant", variant, "--methods",
                     "fem-p1-lumped", "--cells", "4", "8", "--serial", "--out", str(out)]) == 0
        printed = capsys.readouterr().out.splitlines()[0]
        header = (out / "study.md").read_text()
        for text in (printed, header):
            assert "WARNING" not in text
            assert ("At variant large MPM's model leaves that solution; FEM's small-strain "
                    "LinearElastic is its linear model" in text) == noted


# ------------------------------------------------------ hostile command lines
# The command-line half of the hostile probe (issue 21 counted 36 bad command
# lines): each is refused with exit 2 and one line naming the option and the
# value, before any step, study job, reference or benchmark runs (the
# fixture turns each of those into a failure of the test).
VS = ["vibrating-string"]
HOSTILE_ARGV = [
    (["run", *VS, "--cfl", "nan"], "--cfl must be a positive number, got nan"),
    (["run", *VS, "--cfl", "inf"], "cfl must be finite and > 0, got inf"),
    (["run", *VS, "--cfl", "1.5"], "cfl = 1.5 puts the time step above"),
    (["run", *VS, "--dt", "nan"], "--dt must be a positive number, got nan"),
    (["run", *VS, "--dt", "inf"], "dt must be finite and > 0, got inf"),
    (["run", *VS, "--dt", "1"], "dt = 1 exceeds the critical time step"),
    (["run", *VS, "--t-end", "nan"], "--t-end must be a positive number, got nan"),
    (["run", *VS, "--t-end", "inf"], "t_end must be finite and > 0, got inf"),
    (["run", *VS, "--t-end", "1e300"], "t_end = 1e+300 with dt"),
    (["run", *VS, "--ppc", "-2"], "--ppc must be a positive integer, got -2"),
    (["run", *VS, "--ppc", "2.5"], "argument --ppc: invalid int value: '2.5'"),
    (["run", *VS, "--cells", "abc"], "argument --cells: invalid int value: 'abc'"),
    (["run", *VS, "--cells", "-3"], "--cells must be a positive integer, got -3"),
    (["run", *VS, "--variant", "nope"], "variant must be one of"),
    (["run", *VS, "--set", "nope=1"], "unknown parameter(s) ['nope']"),
    (["run", *VS, "--set", "E"], "--set expects NAME=VALUE, got 'E'"),
    (["run", *VS, "--set", "E=-1"], "parameter E must be > 0, got -1.0"),
    (["run", *VS, "--set", "L=0"], "parameter L must be > 0, got 0.0"),
    (["run", *VS, "--set", "E=nan"], "parameter E must be a finite number, got nan"),
    (["run", *VS, "--set", "t_end=0"], "parameter t_end must be > 0 (or omitted for"),
    (["fem", "soil-column", "--set", "g=0"], "parameters g=0.0, p0=0.0: the exact displacement"),
    (["study", *VS, "--variant", "seed", "--set", "v0=0"], "give a nonzero v0"),
    (["study", "soil-column", "--set", "terms=2.5"], "parameter terms (modes of the series"),
    (["run", *VS, "--reconstruction", "fft"], "--reconstruction: invalid choice: 'fft'"),
    (["run"], "the following arguments are required: benchmark"),
    (["run", *VS, "--out", "/proc/skfem-mpm-out"], "'/proc' is not writable"),
    (["run", *VS, "--out", "/sys/skfem-mpm-out/deeper"], "'/sys' is not writable"),
    (["fem", *VS, "--cfl", "0"], "--cfl must be a positive number, got 0"),
    (["fem", *VS, "--cfl", "3"], "cfl = 3 puts the time step above"),
    (["fem", *VS, "--t-end", "nan"], "--t-end must be a positive number, got nan"),
    (["fem", "nope"], "unknown benchmark 'nope'"),
    (["fem", *VS, "--out", __file__], "is a file, not a folder"),
    (["study", *VS, "--cfl", "3"], "--cfl must be at most 1"),
    (["study", *VS, "--cfl", "1.5"], "--cfl must be at most 1"),
    (["study", *VS, "--cfl", "nan"], "--cfl must be a positive number, got nan"),
    (["study", *VS, "--cfl", "-1"], "--cfl must be a positive number, got -1"),
    (["study", *VS, "--ppc", "-1"], "--ppc must be a positive integer, got -1"),
    (["study", *VS, "--cells"], "argument --cells: expected at least one argument"),
    (["study", *VS, "--cells", "x"], "argument --cells: invalid int value: 'x'"),
    (["study", *VS, "--methods", "foo"], "method must look like mpm-p2-consistent"),
    (["study", *VS, "--methods", "mpm-p2-heavy"], "mass in 'mpm-p2-heavy' must be one of"),
    (["study", *VS, "--methods", "fem-p1-lumped", "mpm-p2-lumped-fft"], "unknown part 'fft'"),
    (["study", *VS, "--compare-with", "x"], "--compare-with: invalid choice: 'x'"),
    (["study", *VS, "--repeat", "abc"], "argument --repeat: invalid int value: 'abc'"),
    (["study", "nope"], "unknown benchmark 'nope'"),
    (["study", "colliding-disks"], "colliding-disks has no exact solution to study"),
    (["study", *VS, "--out", "/proc/skfem-mpm-report"], "'/proc' is not writable"),
    (["study", *VS, "--variant", "nope"], "variant must be one of"),
    (["study", *VS, "--set", "E=x"], "--set E: value must be a number, got 'x'"),
    (["bench", "--repeat", "abc"], "argument --repeat: invalid int value: 'abc'"),
    (["bench", "--bogus"], "unrecognized arguments: --bogus"),
    (["list", "extra"], "unrecognized arguments: extra"),
    ([], "the following arguments are required: command"),
]


@pytest.fixture
def nothing_runs(monkeypatch):
    """Any step, study, same-model reference or benchmark fails the test."""
    import importlib

    import skfem_mpm.bench
    import skfem_mpm.model_reference
    import skfem_mpm.study

    def ran(*args, **kwargs):
        raise AssertionError("a bad command line started running")

    simulate_module = importlib.import_module("skfem_mpm.solve.simulate")
    monkeypatch.setenv("SKFEM_MPM_BACKEND", "numpy")  # every step through SCHEME_STEPS
    monkeypatch.setattr(simulate_module, "SCHEME_STEPS",
                        {k: ran for k in simulate_module.SCHEME_STEPS})
    for module, name in ((skfem_mpm.study, "convergence"),
                         (skfem_mpm.model_reference, "model_reference"),
                         (skfem_mpm.bench, "main")):
        monkeypatch.setattr(module, name, ran)


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="the /proc and /sys cases need Linux")
@pytest.mark.parametrize("argv, fragment", HOSTILE_ARGV, ids=[" ".join(a) or "(none)"
                                                             for a, _ in HOSTILE_ARGV])
def test_a_hostile_command_line_is_refused_before_anything_runs(argv, fragment, capsys,
                                                                 nothing_runs):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("skfem-mpm: error:") and fragment in err, err


def test_the_command_line_probe_counts_at_least_as_many_cases_as_the_issue():
    assert len(HOSTILE_ARGV) >= 36


# ------------------------------------------------- defaults and what is printed
def test_run_and_fem_defaults_are_the_apis():
    """Every option of run and fem that is a Method() argument defaults to
    Method()'s value (the API's stand)."""
    import inspect

    from skfem_mpm import Method

    api = {name: p.default for name, p in inspect.signature(Method).parameters.items()}
    for command in ("run", "fem"):
        parser = _subcommands()[command]
        shared = [a for a in parser._actions if a.dest in api and a.option_strings]
        assert {a.dest for a in shared} >= {"mass", "reconstruction", "scheme", "cfl", "dt"}
        for action in shared:
            assert action.default == api[action.dest], (command, action.dest)


def _synthetic_study(benchmark, methods, cells, **kwargs):
    """What convergence returns, without running: error h^2 for p1 and h^3
    for the rest, times growing with the cells; the keyword arguments kept."""
    _synthetic_study.kwargs = kwargs
    records = []
    for method in methods:
        order = 2 if "-p1-" in method else 3
        for n in cells:
            t = 1e-3 * n * order ** 3
            records.append({"benchmark": benchmark, "variant": kwargs.get("variant"),
                            "method": method, "kind": method.split("-")[0], "cells": n,
                            "h": 1.0 / n, "error": 0.5 * n ** -order, "wall_time_s": t,
                            "wall_time_min_s": 0.9 * t, "wall_time_max_s": 1.1 * t,
                            "repeats": kwargs["repeat"], "jit_time_s": 0.1,
                            "timed_compiles": 0, "status": "ok"})
    return records


def test_study_defaults_are_the_apis():
    """study's --ppc, --scheme and --cfl default to convergence()'s values,
    which are study.DEFAULTS, and scheme and cfl are Method()'s (the API's
    stand); their help names the value."""
    import inspect

    from skfem_mpm import Method
    from skfem_mpm.solve.method import default_cfl
    from skfem_mpm.study import DEFAULTS, convergence, parse_method

    api = {name: p.default for name, p in inspect.signature(convergence).parameters.items()}
    method = {name: p.default for name, p in inspect.signature(Method).parameters.items()}
    parsed = {name: p.default for name, p in inspect.signature(parse_method).parameters.items()}
    parser = _subcommands()["study"]
    options = {a.dest: a for a in parser._actions if a.option_strings}
    text = " ".join(parser.format_help().split())
    for name in ("ppc", "scheme", "cfl"):
        assert options[name].default == api[name] == DEFAULTS[name], name
        if name != "cfl":
            assert f"default: {api[name]}, as study.convergence()" in text, name
    # cfl None: each scheme's own (Method's DEFAULT_CFL)
    assert api["cfl"] is None
    assert (f"default: the scheme's, {default_cfl('rk4')} for rk4 and {default_cfl('musl')} "
            f"for the others, as study.convergence()") in text
    for name in ("scheme", "cfl"):
        assert api[name] == method[name] == parsed[name], name
    assert api["repeat"] == DEFAULTS["repeat"]


def test_the_quick_study_prints_its_settings_table_and_verdict(tmp_path, capsys, monkeypatch):
    """study --quick hands convergence the quick settings (3 repeats with
    the 2 s budget; ppc, scheme and cfl the API's, convergence()'s defaults)
    and prints, as study.md writes, the time-to-reach table and the verdict
    per e."""
    import skfem_mpm.study

    monkeypatch.setattr(skfem_mpm.study, "convergence", _synthetic_study)
    out = tmp_path / "quick"
    assert main(["study", "vibrating-string", "--quick", "--methods", "mpm-p1-lumped",
                 "mpm-p2-consistent", "--out", str(out)]) == 0
    kwargs = _synthetic_study.kwargs
    assert (kwargs["repeat"], kwargs["repeat_budget"], kwargs["scheme"], kwargs["cfl"],
            kwargs["ppc"]) == (3, 2.0, "musl", None, 2)
    printed = capsys.readouterr().out
    report = (out / "study.md").read_text()
    for text in (printed, report):
        assert "| method | e = 1e-03 | e = 1e-04 | e = 1e-05 | e = 1e-06 | e = 1e-07 |" in text
        assert "e = 1e-03: cheapest mpm-p1-lumped" in text
        assert "1.21x faster than the runner-up mpm-p2-consistent" in text
        assert "NOT robust: within the repeats' range" in text  # 0.9-1.1 of each time
        assert "e = 1e-04: cheapest mpm-p2-consistent (0.462 s), the only method" in text
        assert "the median of up to 3 timed runs" in text
    assert main(["study", "vibrating-string", "--methods", "mpm-p1-lumped", "--repeat", "5",
                 "--out", str(tmp_path / "five")]) == 0
    assert (_synthetic_study.kwargs["repeat"], _synthetic_study.kwargs["repeat_budget"]) == (5,
                                                                                          None)
