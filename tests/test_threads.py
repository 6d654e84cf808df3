"""The thread policy (solve/threads.py): the thread count may change between
steps, the result may not."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from skfem_mpm.solve.threads import ThreadPolicy, other_runnable_threads

# Runs in a child process with two numba threads (also on a one-core
# machine: numba runs two threads there too), so that the block count T = 2
# whatever the machine, and alternates 1 and 2 threads step by step.
_CHILD = r"""
import json, sys
import numpy as np
import numba
from skfem_mpm import Method, simulate
from skfem_mpm.bench import scene_2d
from skfem_mpm.solve import compiled_loop, threads as policy_module

# every step through the executor, so that the policy acts between steps
# (the compiled loop runs the steps between saves in one call; it gives the
# executor's bits: tests/test_compiled_loop.py)
compiled_loop.ENABLED = False

mass, scheme = sys.argv[1], sys.argv[2]
scene, _ = scene_2d(cells=16, steps=12)
body = scene.bodies[0]
body.particles.v = 0.4 * (body.particles.x - 0.5)  # stress waves: the CG iterates


class Alternating(policy_module.ThreadPolicy):
    used = set()

    def __init__(self, blocks, **kw):
        super().__init__(blocks, enabled=False)
        self.count = 0

    def update(self):
        self.count += 1
        threads = 1 if self.count % 2 else 2
        numba.set_num_threads(threads)
        Alternating.used.add(numba.get_num_threads())
        return threads

    def restore(self):
        numba.set_num_threads(self.initial)


method = Method(scheme=scheme, mass=mass, mass_solver="cg" if mass == "consistent" else "auto")
fixed = simulate(scene, method)
policy_module_sim = __import__("skfem_mpm.solve.simulate", fromlist=["x"])
policy_module_sim.ThreadPolicy = Alternating
varied = simulate(scene, method)
a, b = fixed.particles, varied.particles
same = all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ("x", "v", "stress", "V"))
print(json.dumps({"same": same, "used": sorted(Alternating.used), "path": varied.path,
                  "blocks": numba.get_num_threads()}))
"""


@pytest.mark.parametrize("mass, scheme", [("consistent", "musl"), ("lumped", "usl")])
def test_thread_count_changing_between_steps_changes_no_bit(mass, scheme):
    env = dict(os.environ, NUMBA_NUM_THREADS="2")
    out = subprocess.run([sys.executable, "-c", _CHILD, mass, scheme], env=env,
                         capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report["path"].startswith("fast")
    assert report["used"] == [1, 2]
    assert report["same"]


def test_policy_gives_the_busy_cores_away():
    policy = ThreadPolicy(4, cpus=4, enabled=False)
    policy.initial = 4
    assert [policy.choose(others) for others in (0, 1, 2, 3, 4, 9)] == [4, 3, 2, 1, 1, 1]
    policy = ThreadPolicy(2, cpus=8, enabled=False)
    policy.initial = 2
    assert policy.choose(0) == 2 and policy.choose(6) == 2 and policy.choose(7) == 1


def test_policy_setting_is_checked(monkeypatch):
    monkeypatch.setenv("SKFEM_MPM_THREADS", "sometimes")
    with pytest.raises(ValueError, match="SKFEM_MPM_THREADS.*'adaptive' or 'fixed'"):
        ThreadPolicy(2)


@pytest.mark.skipif(not os.path.exists("/proc/loadavg"), reason="needs Linux /proc")
def test_a_busy_process_is_seen():
    import time

    spinner = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        time.sleep(0.3)
        samples = []
        for _ in range(10):
            samples.append(other_runnable_threads())
            time.sleep(0.02)
    finally:
        spinner.kill()
        spinner.wait()
    assert min(samples) >= 1, samples


def test_small_basis_evaluations_run_serially_with_the_same_values():
    """Below SERIAL_BELOW points the axis basis runs on one thread (a
    parallel region there cost a reconstructed rk4 step 2.4-2.8x on a busy
    machine); both give the same values."""
    from skfem_mpm import SplineGrid
    from skfem_mpm.kernels import weights

    grid = SplineGrid((np.array([0.0, 0.1, 0.35, 0.5, 1.0]),), 3)
    x = np.random.default_rng(1).uniform(0.0, 1.0, 500)
    breaks, C = grid.breakpoints[0], np.ascontiguousarray(grid.extraction[0])
    out = [(np.empty(x.size, np.int64), np.empty((x.size, 4)), np.empty((x.size, 4)))
           for _ in range(2)]
    inv_h = (breaks.size - 1) / (breaks[-1] - breaks[0])
    weights.axis_functions_kernel(x, breaks, False, inv_h, C, 3, *out[0])
    weights.axis_functions_serial(x, breaks, False, inv_h, C, 3, *out[1])
    for a, b in zip(*out):
        assert np.array_equal(a, b)
    assert x.size < weights.SERIAL_BELOW


_RUN_AT_T = r"""
import json, sys
import numba
from skfem_mpm import Method, simulate
from skfem_mpm.benchmarks import get_benchmark

out = {}
for mass in ("lumped", "consistent"):
    scene = get_benchmark("vibrating-string", "small", L=1.0).scene(16, 2, 2)
    r = simulate(scene, Method(mass=mass), save_every=5)
    out[mass] = {"x": r.particles.x.ravel().tolist(), "v": r.particles.v.ravel().tolist(),
                 "path": r.path}
print(json.dumps({"threads": numba.get_num_threads(), "runs": out}))
"""


def test_another_thread_count_changes_results_by_round_off_only():
    """What a thread count changes (README, "Reliability"): the compiled
    kernels split their loops into as many blocks as numba has threads when
    the run starts, so with another NUMBA_NUM_THREADS grid sums are added in
    another order. S1, 16 quadratic cells, compiled loop, 1 against 2
    threads: measured 4e-15 (lumped) and 3e-14 (consistent) of the largest
    velocity; at one count every run agrees bit for bit
    (tests/test_hostile_restarts.py)."""
    reports = []
    for threads in ("1", "2"):
        env = dict(os.environ, NUMBA_NUM_THREADS=threads)
        out = subprocess.run([sys.executable, "-c", _RUN_AT_T], env=env, capture_output=True,
                             text=True, timeout=900)
        assert out.returncode == 0, out.stderr[-3000:]
        reports.append(json.loads(out.stdout.strip().splitlines()[-1]))
    assert [r["threads"] for r in reports] == [1, 2]
    for mass in ("lumped", "consistent"):
        a, b = (r["runs"][mass] for r in reports)
        assert a["path"] == b["path"] == "fast (compiled loop)"
        for k in ("x", "v"):
            pa, pb = np.array(a[k]), np.array(b[k])
            assert np.abs(pa - pb).max() <= 1e-11 * np.abs(pa).max(), (mass, k)
