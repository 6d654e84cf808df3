"""The warm-up compiles what a run calls, so that no compilation falls into
the timed steps (a study's wall times exclude JIT), and nothing else."""
import json
import subprocess
import sys

import pytest

# In a fresh process: the number of compiled signatures of every numba
# function of the package after the warm-up (``after_warm_up``) and now
# (``compiled()``), then a benchmark's run.
WATCH_COMPILES = r"""
import json, sys
import numpy as np
from numba.core.registry import CPUDispatcher
import skfem_mpm
from skfem_mpm import Method, simulate
from skfem_mpm.benchmarks import get_benchmark
import importlib
sim_module = importlib.import_module("skfem_mpm.solve.simulate")
import skfem_mpm.kernels.mpm, skfem_mpm.kernels.fringe, skfem_mpm.kernels.kronecker
import skfem_mpm.kernels.constitutive, skfem_mpm.kernels.weights

def compiled():
    count = {}
    for name, module in list(sys.modules.items()):
        if not name.startswith(("skfem_mpm", "_skfem_mpm_generated")):
            continue  # the package and its generated kernels
        for attr, value in vars(module).items():
            if isinstance(value, CPUDispatcher):
                count[f"{name}.{attr}"] = len(value.overloads)
    return count

after_warm_up = {}
original = sim_module.warm_up

def warm_up(state, fast, loop=None):
    seconds = original(state, fast, loop)
    after_warm_up.update(compiled())
    return seconds

sim_module.warm_up = warm_up
"""
_CHILD = WATCH_COMPILES + r"""
bench, variant, mass, scheme = sys.argv[1:5]
b = get_benchmark(bench, variant)
scene = {1: lambda: b.scene(16, 2, 4), 2: lambda: b.scene(8, 2, 2),
         3: lambda: b.scene(4, 2, 2)}[b.dim]()
r = simulate(scene, Method(mass=mass, scheme=scheme))
after_run = compiled()
late = sorted(k for k, v in after_run.items() if v > after_warm_up.get(k, 0))
consistent = sorted(k for k, v in after_warm_up.items()
                    if v and k.rsplit(".", 1)[1] in ("ell_pcg", "consistent_1d", "consistent_2d"))
generated = sorted(k for k, v in after_warm_up.items() if v and k.startswith("_skfem_mpm_gen"))
print(json.dumps({"late": late, "path": r.path, "consistent_compiled": consistent,
                  "generated": generated}))
"""


@pytest.mark.parametrize("bench, variant, mass, scheme", [
    ("vibrating-string", "small", "consistent", "musl"),
    ("vibrating-string", "small", "hybrid", "musl"),
    ("vibrating-string", "small", "lumped", "cd"),
    ("vibrating-string", "small", "lumped", "rk4"),
    ("vibrating-plate-2d", "small", "consistent", "usl"),
    ("vibrating-cube", "small", "lumped", "usl"),  # the warm-up compiled 2D kernels
])
def test_nothing_compiles_inside_the_timed_steps(bench, variant, mass, scheme):
    out = subprocess.run([sys.executable, "-c", _CHILD, bench, variant, mass, scheme],
                         capture_output=True, text=True, timeout=1500)
    assert out.returncode == 0, out.stderr[-3000:]
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report["path"].startswith("fast")
    assert report["late"] == []
    # the generated transfers are among the kernels the warm-up compiled
    assert {name.rsplit(".", 1)[1].split("_")[0] for name in report["generated"]} \
        >= {"p2g"} | ({"rates"} if scheme == "rk4" else {"g2p"}) \
        | ({"g2p2g"} if scheme == "musl" else set())
    # a lumped run does not compile the consistent-mass machinery (hybrid
    # solves its velocities with it)
    assert bool(report["consistent_compiled"]) == (mass != "lumped")
