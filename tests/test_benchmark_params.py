"""A benchmark parameter that would be replaced or would make its errors
meaningless is refused naming it: t_end = 0 (it silently meant the
benchmark's own end time, as --t-end 0 did), an amplitude of 0 (the errors
are relative to it), a series with no or a fractional number of terms. A
negative amplitude is a phase flip: its relative errors are positive."""
import numpy as np
import pytest

from skfem_mpm.benchmarks import BENCHMARKS, get_benchmark

EXACT = [name for name, cls in BENCHMARKS.items() if cls.has_exact]


@pytest.mark.parametrize("name", list(BENCHMARKS))
def test_an_end_time_of_zero_is_refused_not_replaced(name):
    with pytest.raises(ValueError, match=r"parameter t_end must be > 0 .*got 0"):
        get_benchmark(name, t_end=0.0)
    assert get_benchmark(name, t_end=0.25).t_end == 0.25


@pytest.mark.parametrize("name", EXACT)
def test_a_vanishing_amplitude_is_refused_naming_its_parameters(name):
    cls = BENCHMARKS[name]
    assert cls.amplitude_params, f"{name}: which parameters set the amplitude?"
    zero = dict.fromkeys(cls.amplitude_params, 0.0)
    with pytest.raises(ValueError, match="give a nonzero " + " or ".join(cls.amplitude_params)):
        get_benchmark(name, **zero)


def test_the_soil_columns_series_and_periods_are_checked():
    for terms in (0.0, -1.0, 2.5):
        with pytest.raises(ValueError, match=f"parameter terms .* got {terms}"):
            get_benchmark("soil-column", terms=terms)
    with pytest.raises(ValueError, match="parameter periods .* got 0"):
        get_benchmark("soil-column", periods=0.0)
    assert get_benchmark("soil-column", terms=50.0).terms == 50.0


class _Saved:
    """The part of a Result that Benchmark.errors reads."""

    def __init__(self, bench, X, times, offset):
        self.times = list(times)
        self.history = {"X": [X] * len(times),
                        "u": [bench.displacement(X, t) + offset for t in times],
                        "v": [bench.velocity(X, t) for t in times],
                        "stress": [bench.stress(X, t) for t in times]}


@pytest.mark.parametrize("name, param", [("traction-bar", "A"), ("vibrating-string", "v0")])
def test_a_negative_amplitude_gives_the_same_positive_relative_errors(name, param):
    errors = {}
    for sign in (1.0, -1.0):
        b = get_benchmark(name, **{param: sign * 0.01})
        X = np.linspace(0.1, 0.9, 9)[:, None] * b.params.get("L", 1.0)
        errors[sign] = b.errors(_Saved(b, X, [0.25 * b.t_end, b.t_end], 1e-5))
    for key, value in errors[1.0].items():
        assert value >= 0 and errors[-1.0][key] == pytest.approx(value, rel=1e-12), key
    assert errors[1.0]["error_rms"] == pytest.approx(1e-5 / 0.01 if param == "A" else
                                                     1e-5 / abs(get_benchmark(name, v0=0.01)
                                                                .amplitude), rel=1e-12)
