"""The command line, studies and the Dask path."""
import csv
import json

import pytest

from skfem_mpm.cli import main
from skfem_mpm.study import compile_first, convergence, parse_method


def test_list(capsys):
    assert main(["list"]) == 0
    out = capsys.readouterr().out
    for name in ("vibrating-string", "soil-column", "traction-bar", "neo-hookean-bar",
                 "axis-aligned-2d", "vibrating-plate-2d", "colliding-disks", "vibrating-cube",
                 "axis-aligned-3d", "colliding-spheres"):
        assert name in out


def test_run_json_has_the_documented_fields(capsys):
    assert main(["run", "vibrating-string", "--cells", "8", "--set", "L=1", "--mass", "consistent",
                 "--json"]) == 0
    record = json.loads(capsys.readouterr().out)
    for key in ("benchmark", "variant", "scheme", "mass", "reconstruction", "cells", "ppc",
                "dofs", "particles", "steps", "dt", "error_rms", "error_max", "error_rms_abs",
                "velocity_error_rms", "stress_error_rms", "wall_time_s", "jit_time_s",
                "phase_times"):
        assert key in record, key
    assert record["error_rms"] < 1e-2 and record["degree"] == 2
    assert set(record["phase_times"]) >= {"locate", "basis", "p2g", "solve", "g2p"}


def test_fem_command(capsys):
    assert main(["fem", "soil-column", "--variant", "small", "--cells", "8", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["kind"] == "fem"


def test_run_writes_paraview_and_pictures(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", "vibrating-plate-2d", "--cells", "4", "--out", str(out)]) == 0
    for name in ("particles.pvd", "grid.vtu", "particles_stress.png", "energy.png",
                 "displacement.png", "particles_error.png"):
        assert (out / name).exists(), name


def test_run_help_lists_choices_and_defaults_as_the_api(capsys):
    from skfem_mpm import Method

    with pytest.raises(SystemExit):
        main(["run", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "{lumped,consistent,hybrid}" in text and "{musl,usl,usf,cd,rk4}" in text
    assert f"mass matrix (default: {Method().mass}, as Method())" in text
    assert f"time-stepping scheme (default: {Method().scheme})" in text


def test_an_explicit_end_time_is_used():
    from skfem_mpm.benchmarks import get_benchmark

    b = get_benchmark("vibrating-string", "small")
    assert b.scene(4, 2, 2, t_end=1e-3).t_end == 1e-3
    with pytest.raises(ValueError, match="t_end"):
        b.scene(4, 2, 2, t_end=0.0)


@pytest.mark.parametrize("argv, fragment", [
    (["run", "nope"], "unknown benchmark"),
    (["run", "vibrating-string", "--degree", "7"], "--degree: invalid choice"),
    (["run", "vibrating-string", "--t-end", "0"], "--t-end must be a positive number, got 0"),
    (["fem", "vibrating-string", "--dt", "-0.001"], "--dt must be a positive number"),
    (["run", "vibrating-string", "--scheme", "rk9"], "--scheme: invalid choice"),
    (["run", "vibrating-string", "--cfl", "3"], "cfl = 3 puts the time step above"),
    (["run", "vibrating-string", "--out", __file__], "is a file, not a folder"),
    (["study", "vibrating-string", "--cfl", "0"], "--cfl must be a positive number, got 0"),
    (["study", "vibrating-string", "--ppc", "0"], "--ppc must be a positive integer, got 0"),
    (["bench", "--repeat", "0"], "--repeat must be a positive integer, got 0"),
    (["bench", "--repeat", "-1"], "--repeat must be a positive integer, got -1"),
    (["run", "vibrating-string", "--cells", "0"], "--cells must be a positive integer"),
    (["run", "vibrating-string", "--mass", "heavy"], "--mass: invalid choice"),
    (["run", "vibrating-string", "--set", "E=abc"], "value must be a number"),
    (["study", "vibrating-string", "--methods", "mpm-p9-lumped"], "degree"),
    (["frobnicate"], "invalid choice"),
])
def test_bad_arguments_give_one_line_and_exit_2(argv, fragment, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("skfem-mpm: error:") and fragment in err


def test_quick_study_writes_table_and_plots(tmp_path, capsys):
    out = tmp_path / "report"
    assert main(["study", "vibrating-string", "--quick", "--cells", "8", "16", "--serial",
                 "--methods", "mpm-p1-lumped", "fem-p2-consistent", "--out", str(out)]) == 0
    for name in ("study.csv", "study.md", "convergence.png", "work_precision.png"):
        assert (out / name).exists()
    rows = list(csv.DictReader(open(out / "study.csv")))
    assert len(rows) == 4 and all(r["status"] == "ok" for r in rows)
    assert float(rows[1]["order"]) > 1.8  # linear MPM, 8 -> 16 cells
    assert "phase_p2g_s" in rows[0]


def test_parse_method():
    spec = parse_method("mpm-p3-consistent-tls-usl")
    assert (spec["degree"], spec["mass"], spec["reconstruction"], spec["scheme"]) == \
        (3, "consistent", "tls", "usl")
    with pytest.raises(ValueError, match="fem methods take no reconstruction"):
        parse_method("fem-p2-consistent-spline")
    with pytest.raises(ValueError, match="unknown part"):
        parse_method("mpm-p2-lumped-magic")


def test_default_process_pool_and_orders():
    records = convergence("vibrating-string", ["mpm-p1-lumped"], [8, 16], ppc=2,
                          params={"L": 1.0})
    assert records[1]["order"] > 1.8 and records[0]["jit_time_s"] >= 0


def test_each_kernel_set_compiles_first_once():
    """The coarsest run of every kernel set goes first, in families that one
    worker runs in turn (the degrees of one kind of run: they share its
    compiled loop and kernels), consistent-mass families alternating with
    lumped ones; every other run after: each job once."""
    names = ["mpm-p1-lumped", "mpm-p2-consistent", "mpm-p2-lumped", "mpm-p3-consistent",
             "mpm-p2-consistent-spline", "mpm-p3-consistent-spline", "fem-p2-consistent"]
    jobs = [{"method": parse_method(m), "cells": n} for m in names for n in (32, 8, 16)]
    chains, rest = compile_first(jobs)
    first = [i for chain in chains for i in chain]
    assert sorted(first + rest) == list(range(len(jobs)))
    assert [[jobs[i]["method"]["name"] for i in chain] for chain in chains] == [
        ["mpm-p2-consistent", "mpm-p3-consistent"], ["mpm-p1-lumped", "mpm-p2-lumped"],
        ["mpm-p2-consistent-spline", "mpm-p3-consistent-spline"], ["fem-p2-consistent"]]
    assert all(jobs[i]["cells"] == 8 for i in first)


def test_dask_local_cluster():
    distributed = pytest.importorskip("dask.distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client:
        records = convergence("vibrating-string", ["mpm-p2-consistent"], [8, 16], ppc=2,
                              params={"L": 1.0}, executor=client)
    assert [r["status"] for r in records] == ["ok", "ok"]
    assert records[1]["error"] < records[0]["error"]


def test_run_defaults_to_4_cells_in_3d(capsys):
    """`run` on a 3D benchmark (the reference executor) defaults to 4 cells
    per axis, 16 in 1D and 2D, as its help says."""
    assert main(["run", "vibrating-cube", "--json"]) == 0
    record = json.loads(capsys.readouterr().out)
    assert record["cells"] == 4 and record["particles"] == 8 * 4 ** 3
    with pytest.raises(SystemExit):
        main(["run", "--help"])
    assert "default: 16; 4 in 3D" in " ".join(capsys.readouterr().out.split())
