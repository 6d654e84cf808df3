"""What the study pictures mark: the cheapest method per error level (the
lower-left envelope) and reference slopes beside the runs they describe."""
import math

import pytest

from skfem_mpm.plot import (
    _reference_slopes,
    cheapest_envelope,
    plot_convergence,
    plot_work_precision,
)


def _run(method, cells, error, wall):
    return {"method": method, "cells": cells, "h": 1.0 / cells, "error": error,
            "wall_time_s": wall, "status": "ok"}


RECORDS = [_run("cheap-low-order", 8, 1e-2, 0.1), _run("cheap-low-order", 16, 2.5e-3, 0.4),
           _run("cheap-low-order", 32, 6.25e-4, 1.6),
           _run("high-order", 8, 1e-3, 1.0), _run("high-order", 16, 6.25e-5, 2.0),
           _run("high-order", 32, 3.9e-6, 4.0)]


def test_envelope_names_the_cheapest_method_at_each_error_level():
    envelope = cheapest_envelope(RECORDS, levels=50)
    winner = {round(math.log10(e), 1): m for e, _, m in envelope}
    # coarse errors: the low-order method is cheapest; below its reach, high order
    assert winner[-2.0] == "cheap-low-order" and winner[-5.0] == "high-order"
    for e, t, m in envelope:  # each point is the smallest time to reach e
        others = [r["wall_time_s"] for r in RECORDS if r["error"] <= e]
        assert t <= min(others) * (1 + 1e-12)


def test_reference_slopes_follow_the_finest_runs_of_each_observed_order():
    series = {"p1": [(1 / 32, 6.25e-4), (1 / 16, 2.5e-3), (1 / 8, 1e-2)],
              "p4": [(1 / 32, 3.9e-6), (1 / 16, 6.25e-5), (1 / 8, 1e-3)],
              "flat": [(1 / 32, 0.15), (1 / 16, 0.15)]}
    lines = _reference_slopes(series)
    assert [(order, m) for order, _, _, m in lines] == [(2, "p1"), (4, "p4")]  # none: flat
    for order, hs, es, _ in lines:
        finest = {2: 6.25e-4, 4: 3.9e-6}[order]
        assert hs == (1 / 32, 1 / 16) and es[0] == pytest.approx(0.5 * finest)
        assert math.log(es[1] / es[0]) / math.log(hs[1] / hs[0]) == pytest.approx(order)


def test_study_pictures_are_written(tmp_path):
    assert plot_convergence(RECORDS, tmp_path / "c.png", "t").exists()
    assert plot_work_precision(RECORDS, tmp_path / "w.png", "t").exists()
