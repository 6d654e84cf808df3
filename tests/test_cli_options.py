"""Every command-line option says its choices and default, and a bad value
is refused before anything runs: exit 2, one line naming the option."""
import argparse

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


def test_a_study_beyond_the_exact_solutions_model_says_so(tmp_path, capsys):
    """S2 large (10% strain) is compared with the linear exact solution: the
    header printed and written to study.md warns; S2 small's does not."""
    for variant, warned in (("large", True), ("small", False)):
        out = tmp_path / variant
        assert main(["study", "soil-column", "--variant", variant, "--methods",
                     "fem-p1-lumped", "--cells", "4", "8", "--serial", "--out", str(out)]) == 0
        printed = capsys.readouterr().out.splitlines()[0]
        header = (out / "study.md").read_text()
        for text in (printed, header):
            assert ("WARNING, variant large: the exact solution is the linear wave equation's"
                    in text) == warned
