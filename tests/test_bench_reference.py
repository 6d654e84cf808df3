"""The C reference of ``skfem-mpm bench``: it computes the step that
``simulate`` computes, and the bench prints a ratio to it only when it was
compiled and run in the same run."""
import json

import numpy as np
import pytest

from skfem_mpm import Body, Fixed, Gravity, LinearElastic, Particles, Scene, SplineGrid
from skfem_mpm.bench import _print_c_reference, scene_1d, scene_2d
from skfem_mpm.cli import main
from skfem_mpm.reference_c import (ReferenceUnavailable, compare, compile_reference,
                                   find_compiler, run_reference, write_problem)
from skfem_mpm.solve import Method, simulate
from skfem_mpm.solve.timestep import critical_time_step


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    try:
        find_compiler()
    except ReferenceUnavailable as exc:
        pytest.skip(f"no C compiler to build the C reference: {exc}")
    return compile_reference(tmp_path_factory.mktemp("c"))


def _expanding_block(scene):
    body = scene.bodies[0]
    body.particles.v = 0.4 * (body.particles.x - 0.5)
    return scene


def _filled_square(cells=6, steps=8):
    """Particles in every cell (the clamped boundary B-splines too), moving
    apart, walls fixed, gravity."""
    grid = SplineGrid.rectangle((0, 1), (0, 1), cells, 2)
    particles = Particles.seed(grid, 2, 1.0)
    particles.v = 0.1 * (particles.x - 0.5)
    material = LinearElastic(1e4, 0.3)
    effects = [Gravity((0.0, -9.81))] + [Fixed(s) for s in ("left", "right", "bottom", "top")]
    dt = 0.5 * critical_time_step(grid, np.sqrt(material.modulus(2)), "lumped")
    return Scene(grid, Body(particles, material), steps * dt, effects=effects), dt


CASES = {
    "2d expanding block": lambda: (_expanding_block(scene_2d(cells=8, steps=10)[0]),
                                   scene_2d(cells=8, steps=10)[1]),
    "2d filled square": _filled_square,
    "1d bar": lambda: scene_1d(cells=12, steps=15),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_c_reference_ends_in_the_state_simulate_computes(reference, tmp_path, case):
    """usl_step.c run on the problem file of a run ends in the final
    particle state of simulate (USL, lumped) to round-off, on 2 threads
    and on 1; a state that differs in the 7th digit is not accepted."""
    scene, dt = CASES[case]()
    method = Method(scheme="usl", dt=dt * (1 - 1e-9))
    result = simulate(scene, method)
    problem = write_problem(tmp_path / "in.bin", scene, method)
    assert problem["steps"] == result.counts["steps"] and problem["dt"] == result.dt
    for threads in (2, 1):
        out = run_reference(reference, tmp_path / "in.bin", tmp_path / "out.bin", threads)
        assert out["threads"] == threads and out["invalid"] == 0
        agrees, differences = compare(result.particles, out["final"], problem)
        print(case, threads, differences)
        assert agrees and max(differences.values()) < 1e-12, differences
    strain = np.abs(result.particles.stress).max() / problem["modulus"]
    print(case, "largest stress / modulus", strain)
    assert strain > 1e-6  # the comparison sees the stress update, not round-off
    wrong = dict(out["final"], u=out["final"]["u"] * (1 + 1e-7))
    assert not compare(result.particles, wrong, problem)[0]


def test_c_reference_refuses_runs_it_does_not_compute(tmp_path):
    scene, dt = scene_2d(cells=8, steps=2)
    with pytest.raises(ValueError, match="scheme musl"):
        write_problem(tmp_path / "in.bin", scene, Method(scheme="musl", dt=dt))


def test_compiler_from_cc_must_exist():
    with pytest.raises(ReferenceUnavailable, match="CC='/nonexistent' was not found"):
        find_compiler({"CC": "/nonexistent", "PATH": "/usr/bin:/bin"})
    with pytest.raises(ReferenceUnavailable, match="no C compiler found"):
        find_compiler({"PATH": ""})


def small_problems(monkeypatch):
    """What the bench tests check is the report, not the speed: the bench's
    problems at sizes below SERIAL_BELOW particles (1,024 in 2D, 4,000 in 1D,
    512 in 3D), whose runs call the serial kernels that other tests compile
    (the quick problems, 64^2 and 25,000 cells, took 204 s here; above
    SERIAL_BELOW they compile parallel kernels and loops of their own; the
    slow tier runs the quick bench as it is)."""
    from skfem_mpm import bench

    scene_2d, scene_1d, scene_3d = bench.scene_2d, bench.scene_1d, bench.scene_3d
    monkeypatch.setattr(bench, "scene_2d", lambda cells, steps: scene_2d(cells=16, steps=steps))
    monkeypatch.setattr(bench, "scene_1d", lambda cells, steps: scene_1d(cells=1000, steps=steps))
    monkeypatch.setattr(bench, "scene_3d", lambda cells, steps: scene_3d(cells=8, steps=steps))


def test_the_small_problems_run_serial_kernels(monkeypatch):
    from skfem_mpm import bench
    from skfem_mpm.kernels.serial import SERIAL_BELOW

    small_problems(monkeypatch)
    for scene in (bench.scene_2d(64, 2), bench.scene_1d(25_000, 2), bench.scene_3d(16, 2)):
        n = scene[0].bodies[0].particles.n
        assert 100 < n < SERIAL_BELOW, n


def test_bench_without_a_compiler_prints_no_ratio(monkeypatch, capsys):
    """With CC pointing nowhere the bench says why the C reference is
    unavailable and prints no ratio (text and JSON)."""
    monkeypatch.setenv("CC", "/nonexistent")
    small_problems(monkeypatch)
    assert main(["bench", "--quick"]) == 0
    out = capsys.readouterr().out
    assert "C reference unavailable: the compiler CC='/nonexistent' was not found" in out
    assert "x C" not in out and "ratio" not in out
    assert main(["bench", "--quick", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["c_reference"] == {"available": False, "reason":
                                     "the compiler CC='/nonexistent' was not found"}
    assert "ratio" not in json.dumps(report)
    assert report["2d_usl"]["particle_steps_per_s"] > 0


def test_a_c_run_that_computed_something_else_gets_no_ratio(capsys):
    row = {"threads": 2, "agrees": False, "invalid_particles": 0,
           "differences": {"u": 1e-3, "v": 2e-3, "V": 0.0, "stress": 5e-2},
           "threaded": {"threads": 2, "particle_steps_per_s": 3e7, "runs": [3e7]},
           "single_thread": {"threads": 1, "particle_steps_per_s": 2e7, "runs": [2e7]},
           "ratio_threaded": None, "ratio_single_thread": None}
    _print_c_reference({"c_reference": {"available": True, "compiler": "cc -O3",
                                        "2d_usl": row}})
    out = capsys.readouterr().out
    assert "WARNING: the C reference did not end in our final state" in out
    assert "no ratio" in out and "x C" not in out


@pytest.mark.parametrize("size", ["small", pytest.param("quick", marks=pytest.mark.slow(
    reason="the quick bench's own sizes compile parallel kernels and loops that only it "
           "calls"))])
def test_the_numpy_path_ratio_is_computed_from_this_runs_figures(monkeypatch, capsys, size):
    """--reference: the compiled/NumPy ratio divides the two throughputs of
    the same report, and the machine line names CPU, cores and threads."""
    from skfem_mpm.bench import _print_report

    monkeypatch.setenv("CC", "/nonexistent")
    if size == "small":
        small_problems(monkeypatch)
    assert main(["bench", "--quick", "--reference", "--json"]) == 0
    measured = json.loads(capsys.readouterr().out)
    ours, numpy_path = measured["2d_usl"], measured["2d_usl_reference"]
    assert numpy_path["ratio_compiled_to_reference"] == pytest.approx(
        ours["particle_steps_per_s"] / numpy_path["particle_steps_per_s"], rel=1e-12)

    phases = {"p2g": 0.5}
    row = lambda rate: {"particle_steps_per_s": rate, "particles": 10, "steps": 2,
                        "jit_time_s": 0.0, "path": "p", "phases": phases, "wall_time_s": 1.0}
    report = {"machine": {"cpu": "Test CPU 9000", "cores": 2, "system": "Linux",
                          "python": "3.x"}, "threads": 2,
              "2d_usl": row(8e6), "2d_usl_reference": dict(row(2e6)),
              "c_reference": {"available": False, "reason": "none here"}}
    report["2d_usl_reference"]["ratio_compiled_to_reference"] = 4.0
    _print_report(report, 1)
    out = capsys.readouterr().out
    assert "machine: Test CPU 9000, 2 cores" in out and "threads: 2 (numba)" in out
    assert "4.0x this NumPy reference path (both measured in this run)" in out
    assert "x C" not in out
