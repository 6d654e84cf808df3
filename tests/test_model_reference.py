"""The same-model reference of S2 large (skfem_mpm.model_reference): its
interpolation, its cache, the study header that names it, and no flat line
in the studies the README shows."""
import csv
import re
from pathlib import Path

import numpy as np
import pytest

from skfem_mpm import model_reference as mr
from skfem_mpm.benchmarks import get_benchmark
from skfem_mpm.cli import main

# a coarse reference, so that the default tier computes it in seconds
COARSE = {"cells": 16, "degree": 3, "ppc": 4, "steps_per_period": 2000, "save_every": 20,
          "format": 1}


@pytest.fixture
def coarse_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setattr(mr, "REFERENCE_SETTINGS", COARSE)
    return tmp_path / "cache"


def test_interpolation_is_exact_for_cubics_in_x_and_t():
    """u = X (1 + X) (1 + t - 2 t^2 + t^3) is cubic in X and t, zero at the
    base: the cubic spline in X and the Hermite interpolant in t (module
    docstring) reproduce it, its velocity and its stress E ln(1 + du/dX)
    between the saves."""
    b = get_benchmark("soil-column", "large")
    times = np.linspace(0.0, 0.8, 5)
    X = np.linspace(0.05, 1.0, 12)

    def p(t):
        return 1 + t - 2 * t ** 2 + t ** 3

    def dp(t):
        return 1 - 4 * t + 3 * t ** 2

    u = np.array([X * (1 + X) * p(t) for t in times])
    v = np.array([X * (1 + X) * dp(t) for t in times])
    ref = mr.ModelReference(b, times, X[::-1], u[:, ::-1], v[:, ::-1])  # any order
    x = np.linspace(0.0, 1.0, 7)
    for t in (0.0, 0.13, 0.41, 0.8):
        uh, vh, sh = ref._fields(x, t)
        assert np.allclose(uh, x * (1 + x) * p(t), atol=1e-12)
        assert np.allclose(vh, x * (1 + x) * dp(t), atol=1e-12)
        assert np.allclose(sh, b.E * np.log1p((1 + 2 * x) * p(t)), rtol=1e-11)
    with pytest.raises(ValueError, match="the reference covers t in"):
        ref._fields(x, 0.9)


def test_only_a_variant_beyond_its_model_has_one(coarse_cache):
    assert mr.model_reference(get_benchmark("soil-column", "small")) is None
    assert mr.model_reference(get_benchmark("traction-bar", "small")) is None
    assert mr.model_reference(get_benchmark("vibrating-string")) is None


def test_s3_large_is_beyond_its_model_and_gets_a_reference(coarse_cache, tmp_path, capsys):
    """S3 large (2.4% strain): the same model leaves the linear exact
    solution by 0.88% of the amplitude (measured with the fine reference:
    MPM p2 consistent sat at 8.8e-3 to 1.3e-2 against the exact solution at
    8-64 cells, 1.7e-3 -> 1.4e-4 against the reference), so a study of it
    compares MPM with the reference and its header says so."""
    b = get_benchmark("traction-bar", "large")
    ref = mr.model_reference(b)
    assert ref is not None and np.isclose(ref.times[-1], b.t_end)
    X = np.linspace(0.05, 1.0, 20) * b.L
    gap = max(np.sqrt(np.mean((ref.displacement(X, t) - b.displacement(X, t)) ** 2))
              for t in ref.times) / b.amplitude
    assert 8.0e-3 < gap < 9.5e-3, gap
    out = tmp_path / "s3"
    assert main(["study", "traction-bar", "--variant", "large", "--methods", "mpm-p1-lumped",
                 "--cells", "4", "--serial", "--repeat", "1", "--out", str(out)]) == 0
    header = capsys.readouterr().out.splitlines()[0]
    assert "MPM runs compared with: a fine FEM of the same model" in header, header
    assert _rows(out / "study.csv")[0]["compared_with"] == "same-model reference"


def test_computed_once_then_read_from_the_cache(coarse_cache, monkeypatch):
    b = get_benchmark("soil-column", "large")
    first = mr.model_reference(b)
    path = Path(mr.reference_path(b))
    assert path.is_file() and str(path).startswith(str(coarse_cache))
    # the reference starts at rest with the static u = 0 and follows gravity
    assert first.times[0] == 0.0 and np.allclose(first.times[-1], b.t_end)
    assert np.all(first.u[0] == 0.0) and first.u[len(first.times) // 4, -1] < 0.0

    def no_compute(*args):
        raise AssertionError("recomputed although cached")

    monkeypatch.setattr(mr, "_compute", no_compute)
    again = mr.model_reference(b)
    assert np.array_equal(again.u, first.u) and np.array_equal(again.times, first.times)
    # another parameter is another reference; a damaged file is recomputed
    assert mr.reference_path(get_benchmark("soil-column", "large", E=2e5)) != str(path)
    assert mr.model_reference(get_benchmark("soil-column", "large", E=2e5),
                              compute=False) is None
    path.write_bytes(b"not a zip file")
    with pytest.raises(AssertionError, match="recomputed"):
        mr.model_reference(b)


@pytest.mark.slow(
    reason="a README study (S2 large with its fine FEM reference); the default tier checks "
           "the reference on S3 large")
def test_the_study_header_names_the_reference(coarse_cache, tmp_path, capsys):
    """S2 large with an MPM method: the header printed and written says MPM
    runs are compared with the fine FEM of the same model, the rows say so
    (compared_with), and error_exact keeps the error against the linear
    exact solution. FEM rows stay
    compared with the exact solution, their model's."""
    out = tmp_path / "study"
    assert main(["study", "soil-column", "--variant", "large", "--methods", "mpm-p1-lumped",
                 "fem-p1-lumped", "--cells", "4", "8", "--serial", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    header = (out / "study.md").read_text()
    for text in (printed.splitlines()[0], header):
        assert "MPM runs compared with: a fine FEM of the same model (sigma = E ln F" in text
        assert "WARNING" not in text
    assert "| error_exact |" in printed
    rows = _rows(out / "study.csv")
    for r in rows:
        mpm = r["kind"] == "mpm"
        assert r["compared_with"] == ("same-model reference" if mpm else "exact"), r
        if mpm:
            assert 0.0 < float(r["error_exact"]) != float(r["error"]), r
        else:
            assert r["error_exact"] == "", r
    # --compare-with exact: the linear exact solution and the warning
    assert main(["study", "soil-column", "--variant", "large", "--methods", "mpm-p1-lumped",
                 "--cells", "4", "--serial", "--compare-with", "exact", "--out",
                 str(tmp_path / "exact")]) == 0
    assert "WARNING, variant large" in capsys.readouterr().out.splitlines()[0]


def _rows(path):
    with open(path) as f:
        return list(csv.DictReader(f))


def _readme_studies():
    """The `skfem-mpm study ...` commands the README shows, as argv lists."""
    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    found = re.findall(r"^\s*(?:.*&& )?skfem-mpm (study [^\n#]*)", text, flags=re.MULTILINE)
    return [line.split() for line in found if "..." not in line]


def test_the_readme_shows_studies():
    studies = _readme_studies()
    assert ["study", "vibrating-string", "--quick"] in studies, studies
    assert any("soil-column" in s for s in studies), studies


def _no_flat_line(rows):
    """Every method's error falls at least 2x from its coarsest to its finest
    run (a flat line: the error measures something else, e.g. the model)."""
    by_method = {}
    for r in rows:
        assert r["status"] == "ok", r
        by_method.setdefault(r["method"], []).append((int(r["cells"]), float(r["error"])))
    for method, runs in by_method.items():
        runs.sort()
        assert runs[0][1] >= 2 * runs[-1][1], (method, runs)


@pytest.mark.slow
@pytest.mark.parametrize("argv", _readme_studies(), ids=lambda a: " ".join(a[1:]))
def test_no_study_shown_in_the_readme_has_a_flat_line(argv, tmp_path, capsys):
    """Each study the README shows, as written (one timed run each)."""
    out = tmp_path / "study"
    assert main(argv + ["--repeat", "1", "--out", str(out)]) == 0
    capsys.readouterr()
    _no_flat_line(_rows(out / "study.csv"))


@pytest.mark.slow
def test_s2_large_against_the_same_model_is_not_flat(tmp_path, monkeypatch, capsys):
    """S2 large, the issue's flat line (MPM at 0.153 at every size against the
    exact solution): against the real same-model reference the error of
    mpm-p2-consistent-spline falls with h (measured 1.2e-3, 5.2e-4,
    2.7e-4 at 8, 16, 32 cells) while error_exact stays near 0.15."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    out = tmp_path / "study"
    assert main(["study", "soil-column", "--variant", "large", "--methods",
                 "mpm-p2-consistent-spline", "--cells", "8", "16", "32", "--serial",
                 "--out", str(out)]) == 0
    capsys.readouterr()
    rows = _rows(out / "study.csv")
    _no_flat_line(rows)
    assert all(0.1 < float(r["error_exact"]) < 0.25 for r in rows), rows
