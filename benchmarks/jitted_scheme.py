"""Design probe: the scheme of ``solve/schemes.py`` compiled against
compiled operations, looping over steps without Python.

Issue "One method, written once" leaves open how the compiled executor gets
close to the arithmetic on small problems. This probe measures one answer:
``numba.njit(schemes.step_musl)`` - the very function the reference and
compiled executors run - typed against a ``structref`` whose methods
(``particles_to_grid``, ``solve_grid``, ...) are ``overload_method``\\ s that
call the package's kernels (the transfers generated per dimension and degree,
:mod:`skfem_mpm.kernels.scatter` / ``gather``). A compiled loop then runs the
steps.

It covers only the S1 vibrating string (1D, quadratic, 32 cells, 128
particles), lumped mass, MUSL, linear elasticity fused into g2p, fixed
ends, no gravity; it is a probe, not a path of the product. It prints the
microseconds per step of ``simulate`` and of the compiled loop (with the
parallel kernels, and with serial copies of them: ``--serial``) and how far
the two runs' particles are apart.

    python benchmarks/jitted_scheme.py [--serial] [--repeat 7]
"""
import argparse
import sys
import time
import types as pytypes

import numpy as np
from numba import njit, types
from numba.core.extending import overload_method
from numba.experimental import structref

from skfem_mpm import Method, simulate
from skfem_mpm.benchmarks import get_benchmark
from skfem_mpm.kernels import mpm, scatter
from skfem_mpm.kernels.gather import g2p_kernel
from skfem_mpm.kernels.records import grid_record
from skfem_mpm.solve import schemes
from skfem_mpm.solve.compiled import CompiledExecutor
from skfem_mpm.solve.state import prepare


def _serial_copy(dispatcher):
    """The kernel's Python source compiled without ``parallel``."""
    f = dispatcher.py_func
    copy = pytypes.FunctionType(f.__code__, dict(f.__globals__), f.__name__ + "_serial",
                                f.__defaults__, f.__closure__)
    return njit(error_model="numpy", fastmath=True)(copy)


K = pytypes.ModuleType("kernels")  # the kernels the operations call (set in main)


@structref.register
class RunType(types.StructRef):
    def preprocess_fields(self, fields):
        return tuple((name, types.unliteral(t)) for name, t in fields)


FIELDS = ("x", "v", "u", "stress", "V", "m", "x2", "v2", "u2", "stress2", "V2", "L", "acc",
          "grid", "E", "mass", "momentum", "force",
          "copies", "touched", "copies1", "touched1", "mass_range", "a", "v_grid", "p_new",
          "mask", "gravity", "flags", "dt", "t", "step", "vfactor", "stopped")


class Run(structref.StructRefProxy):
    def __new__(cls, *args):
        return structref.StructRefProxy.__new__(cls, *args)


structref.define_proxy(Run, RunType, list(FIELDS))


# The operations of solve/schemes.py on one run (the run is also its grid).
@overload_method(RunType, "particles_to_grid")
def _particles_to_grid(run, state):
    def impl(run, state):
        particles = (run.x, run.v, run.u, run.m, run.V, run.stress)
        K.p2g(particles, run.grid, run.force, False, run.copies, run.touched)
        K.reduce_fields(run.copies, run.touched, run.mass, run.momentum, run.force,
                        run.mass_range)
        return run
    return impl


@overload_method(RunType, "solve_grid")
def _solve_grid(run, state, grid, end_velocity=None):
    def impl(run, state, grid, end_velocity=None):
        K.lumped_solve(run.mass, run.force, run.gravity, run.mask, run.force, False, run.a)
    return impl


@overload_method(RunType, "update_particle_velocities")
def _update_particle_velocities(run, state, grid, velocity_factor=1.0, keep_acceleration=False):
    def impl(run, state, grid, velocity_factor=1.0, keep_acceleration=False):
        run.vfactor = velocity_factor  # fused into the next kernel
    return impl


@overload_method(RunType, "project_velocity")
def _project_velocity(run, state, grid):
    def impl(run, state, grid):
        particles = (run.x, run.v, run.u, run.m, run.V, run.stress)
        K.g2p2g(particles, run.grid, run.a, run.vfactor * run.dt, run.v2, run.copies1,
                run.touched1)
        K.reduce_copies(run.copies1, run.touched1, run.p_new)
        K.lumped_solve(run.mass, run.p_new, run.gravity, run.mask, run.p_new, False,
                       run.v_grid)
    return impl


@overload_method(RunType, "move_particles")
def _move_particles(run, state, grid):
    def impl(run, state, grid):
        particles = (run.x, run.v, run.u, run.m, run.V, run.stress)
        new = (run.x2, run.v2, run.u2, run.m, run.V2, run.stress2)
        update = (run.dt, run.vfactor, False, True, run.E, 0.0, False)  # records.Update
        K.g2p(particles, run.grid, run.a, run.v_grid, update, new, run.L, run.acc, run.flags)
        for t in range(run.flags.shape[0]):
            for j in range(3):
                if run.flags[t, j] >= 0:
                    run.stopped = True  # the Python step takes over
    return impl


@overload_method(RunType, "update_stress")
def _update_stress(run, state, grid, velocity=None):
    def impl(run, state, grid, velocity=None):
        pass  # fused into g2p
    return impl


@overload_method(RunType, "commit")
def _commit(run, state, grid):
    def impl(run, state, grid):
        if run.stopped:
            return
        run.x, run.x2 = run.x2, run.x
        run.v, run.v2 = run.v2, run.v
        run.u, run.u2 = run.u2, run.u
        run.stress, run.stress2 = run.stress2, run.stress
        run.V, run.V2 = run.V2, run.V
        run.step += 1
        run.t = run.step * run.dt
    return impl


step_musl = njit(schemes.step_musl)  # the one written scheme, compiled


@njit
def run_steps(run, n):
    for _ in range(n):
        step_musl(run, run)
        if run.stopped:
            break
    return run.step


@njit
def _result(run):
    return run.x, run.stress


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--serial", action="store_true", help="serial copies of the kernels")
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args(argv)
    parallel = not args.serial
    K.p2g = scatter.p2g_kernel(1, 2, None, parallel)
    K.g2p2g = scatter.g2p2g_kernel(1, 2, None, parallel)
    K.g2p = g2p_kernel(1, 2, parallel)
    for name, kernel in (("reduce_fields", scatter.reduce_fields),
                         ("reduce_copies", scatter.reduce_copies),
                         ("lumped_solve", mpm.lumped_solve)):
        setattr(K, name, _serial_copy(kernel) if args.serial else kernel)

    b = get_benchmark("vibrating-string", "small")
    scene = b.scene(32, 2, 4)
    scene = type(scene)(scene.grid, scene.bodies, 10 * scene.t_end, effects=scene.effects)
    method = Method(scheme="musl", mass="lumped")
    reference = simulate(scene, method)
    state = prepare(scene, method)
    k = CompiledExecutor(state).kernels
    p, nd = state.particles, scene.grid.ndofs
    copies, touched = k.transfers.copies(3)
    copies1, touched1 = k.transfers.copies(1)

    def new_run():
        return Run(p.x.copy(), p.v.copy(), p.u.copy(), p.stress.copy(), p.V.copy(), p.m.copy(),
                   np.empty_like(p.x), np.empty_like(p.v), np.empty_like(p.u),
                   np.empty_like(p.stress), np.empty_like(p.V), np.empty((1, 1, 1)),
                   np.zeros((1, 1)), grid_record(scene.grid), state.bodies[0][0].E,
                   np.empty(nd), np.empty((nd, 1)), np.empty((nd, 1)), copies, touched,
                   copies1, touched1, np.zeros((k.nthreads, 2)), np.empty((nd, 1)),
                   np.empty((nd, 1)), np.empty((nd, 1)), state.constraints.mask, np.zeros(1),
                   np.full((k.nthreads, 3), -1, dtype=np.int64), state.dt, 0.0, 0, 1.0, False)

    t0 = time.perf_counter()
    run_steps(new_run(), 1)
    print(f"compile: {time.perf_counter() - t0:.1f} s")
    n = reference.counts["steps"]
    times = []
    for _ in range(args.repeat):
        run = new_run()
        t0 = time.perf_counter()
        done = run_steps(run, n)
        times.append((time.perf_counter() - t0) / n * 1e6)
    x, stress = _result(run)
    print(f"steps {done} of {n}; |x - x_simulate| max {np.abs(x - reference.particles.x).max():.1e}, "
          f"stress relative {np.abs(stress - reference.particles.stress).max() / np.abs(reference.particles.stress).max():.1e}")
    print(f"simulate: {reference.wall_time / n * 1e6:.1f} us/step")
    print(f"compiled loop ({'serial' if args.serial else 'parallel'} kernels): "
          f"median {np.median(times):.1f} us/step, runs {[round(t, 1) for t in times]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
