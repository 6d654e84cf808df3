"""What the study pictures mark: the cheapest method per error level (the
lower-left envelope) and reference slopes beside the runs they describe."""
import math

import numpy as np
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


# ------------------------------------------------------ what the pictures show
class _Figures(list):
    """The figures the plot functions wrote (plot._save wrapped)."""


@pytest.fixture
def figures(monkeypatch):
    from skfem_mpm import plot

    saved = _Figures()
    real = plot._save

    def keep(plt, fig, path):
        saved.append(fig)
        real(plt, fig, path)

    monkeypatch.setattr(plot, "_save", keep)
    return saved


def test_each_decade_is_named_inside_the_work_precision_axes(tmp_path, figures):
    """A method cheapest near the left edge (0.01 s): its decade's label
    is drawn to the right of its point instead of over the tick labels."""
    records = [_run("mpm-p1-lumped-cheap", 8, 2.6e-3, 0.01),
               _run("mpm-p1-lumped-cheap", 16, 6.5e-4, 0.03),
               _run("mpm-p1-lumped-cheap", 32, 1.6e-4, 0.08),
               _run("mpm-p3-consistent-spline", 8, 9e-5, 0.7),
               _run("mpm-p3-consistent-spline", 16, 1.5e-6, 0.9),
               _run("mpm-p3-consistent-spline", 32, 1e-7, 5.0)]
    plot_work_precision(records, tmp_path / "w.png", "t")
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    fig = figures[-1]
    ax = fig.axes[0]
    renderer = FigureCanvasAgg(fig).get_renderer()  # closed figures lose their canvas
    box = ax.get_window_extent(renderer)
    labels = {t.get_text(): t for t in ax.texts}
    assert set(labels) == {"1e-03: mpm-p1-lumped-cheap", "1e-04: mpm-p3-consistent-spline",
                           "1e-05: mpm-p3-consistent-spline",
                           "1e-06: mpm-p3-consistent-spline",
                           "1e-07: mpm-p3-consistent-spline"}
    for text, label in labels.items():
        extent = label.get_window_extent(renderer)
        assert box.x0 <= extent.x0 and extent.x1 <= box.x1, (text, extent, box)
    # the band: wide, translucent segments in the colours of the cheapest methods
    colours = {line.get_label(): line.get_color() for line in ax.lines
               if not line.get_label().startswith("_")}
    band = [line for line in ax.lines if line.get_linewidth() == 9 and len(line.get_xdata())]
    assert {line.get_color() for line in band} == {colours["mpm-p1-lumped-cheap"],
                                                   colours["mpm-p3-consistent-spline"]}


def test_slope_labels_sit_on_their_own_reference_line(tmp_path, figures):
    plot_convergence(RECORDS, tmp_path / "c.png", "t")
    ax = figures[-1].axes[0]
    slopes = {line.get_color(): line for line in ax.lines if line.get_linestyle() == ":"}
    assert len(ax.texts) == len(slopes) == 2
    for text in ax.texts:
        line = slopes[text.get_color()]  # the label in its line's colour
        (h0, h1), (e0, e1) = line.get_xdata(), line.get_ydata()
        assert text.xy == pytest.approx((math.sqrt(h0 * h1), math.sqrt(e0 * e1)))
        assert text.xyann[1] < 0  # below its line, away from the data above it


class _Saved:
    """The parts of a Result the run pictures read (1D, particles at
    X = (i + 1/2) / n moving by u = a(t) sin(pi X))."""

    def __init__(self, n=12, saves=11, dim=1):
        self.times = list(np.linspace(0.0, 1.0, saves))
        X = ((np.arange(n) + 0.5) / n)[:, None]
        u = [0.01 * np.sin(t) * np.sin(np.pi * X) for t in self.times]
        self.history = {"X": [X] * saves, "u": u, "x": [X + ui for ui in u],
                        "v": [0.01 * np.cos(t) * np.sin(np.pi * X) for t in self.times],
                        "stress": [np.cos(np.pi * X)[:, :, None] * np.sin(t)
                                   for t in self.times]}


def _exact(X, t):
    return 0.0101 * np.sin(t) * np.sin(np.pi * X)


def test_displacement_curves_are_labelled_by_position_with_the_exact_ones_on_top(tmp_path,
                                                                                  figures):
    from skfem_mpm.plot import plot_displacement_history

    result = _Saved()
    plot_displacement_history(result, tmp_path / "d.png", exact=_exact)
    ax = figures[-1].axes[0]
    computed = [line for line in ax.lines if line.get_marker() == "o"]
    exact = [line for line in ax.lines if line.get_linestyle() == "--" and len(line.get_xdata())]
    X = result.history["X"][0][:, 0]
    assert [line.get_label() for line in computed] == [f"X = {X[i]:.3g}" for i in (3, 6, 9)]
    assert len(exact) == 3 and all(line.get_color() == "black" for line in exact)
    # drawn by z-order, then in order of addition: every exact curve over every computed one
    drawn = sorted(ax.lines, key=lambda line: line.get_zorder())
    assert min(drawn.index(line) for line in exact) > max(drawn.index(line) for line in computed)
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    assert legend[-1] == "exact"


def test_a_1d_field_is_drawn_over_position_at_four_times(tmp_path, figures):
    from skfem_mpm.plot import plot_field_snapshots

    result = _Saved()
    plot_field_snapshots(result, tmp_path / "u.png", field="displacement", exact=_exact)
    ax = figures[-1].axes[0]
    assert ax.get_xlabel() == "position x" and ax.get_ylabel() == "u_x"
    drawn = [line for line in ax.lines if line.get_linestyle() == "-"]
    assert [line.get_label() for line in drawn] == ["t = 0", "t = 0.3", "t = 0.7", "t = 1"]
    for line, k in zip(drawn, (0, 3, 7, 10)):
        x = result.history["x"][k][:, 0]
        assert np.array_equal(line.get_xdata(), np.sort(x))  # over the current position
        assert np.allclose(line.get_ydata(), result.history["u"][k][np.argsort(x), 0])
    exact = [line for line in ax.lines if line.get_linestyle() == "--" and len(line.get_xdata())]
    assert len(exact) == 4 and all(line.get_color() == "black" for line in exact)
    plot_field_snapshots(result, tmp_path / "s.png", field="stress")
    ax = figures[-1].axes[0]
    assert ax.get_ylabel() == "sigma_xx" and len(ax.lines) == 4
