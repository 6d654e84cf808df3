"""``simulate``: the MPM time loop over the named step functions."""
import numbers
import os
import sys
import time

import numpy as np
from numpy.linalg import LinAlgError

from ..errors import InvalidState, SimulationError
from ..kernels import serial
from ..scene import Scene
from ..validation import can_write_in
from .method import Method
from .result import Recorder
from .compiled import CompiledExecutor, compiled_executor_applies
from .compiled_loop import StepLoop, loop_applies
from .reference import ReferenceExecutor
from .schemes import SCHEME_STEPS
from .state import MAX_STEPS, prepare
from .threads import ThreadPolicy

__all__ = ["simulate"]


def _check_every(name, value):
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
        raise ValueError(f"{name} must be a positive integer number of steps, got {value!r}")
    return int(value)


def _check_checkpoint(checkpoint):
    if checkpoint is None:
        return None
    try:
        path, every = checkpoint
    except (TypeError, ValueError):
        raise ValueError(f"checkpoint must be a pair (path, every_steps), got {checkpoint!r}") \
            from None
    if not isinstance(path, (str, os.PathLike)):
        raise ValueError(f"checkpoint path must be a str or os.PathLike, got {path!r}")
    if os.path.isdir(os.fspath(path)):
        raise ValueError(f"checkpoint path {os.fspath(path)!r} is a folder; give a file "
                         f"name such as {os.path.join(os.fspath(path), 'run.npz')!r}")
    folder = os.path.dirname(os.path.abspath(os.fspath(path)))
    if not os.path.isdir(folder) or not can_write_in(folder):
        raise ValueError(f"checkpoint path {os.fspath(path)!r}: folder {folder!r} does not "
                         f"exist or is not writable (it is checked before the first step)")
    return path, _check_every("checkpoint every_steps", every)


def non_finite(particles):
    """None, or a description of the first particle array holding NaN or
    Inf (checked after a callback, which may edit the state in place)."""
    arrays = {k: getattr(particles, k) for k in ("x", "v", "u", "stress", "m", "V", "F")}
    arrays.update({f"state[{k!r}]": a for k, a in particles.state.items()})
    for name, a in arrays.items():
        if a is not None and a.size and not np.isfinite(a).all():
            row = int(np.flatnonzero(~np.isfinite(a.reshape(a.shape[0], -1)).all(axis=1))[0])
            return f"a non-finite value in particles.{name} (particle {row})"
    return None


def _progress_bar(enabled, total):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, unit="step", disable=not sys.stderr.isatty(), leave=False)


def warm_up(state, fast, loop=None):
    """Compile the kernels the run will use on a tiny input (and the
    compiled loop); returns seconds."""
    if state.backend != "numba":
        return 0.0
    from .warmup import warm_up_kernels

    t0 = time.perf_counter()
    warm_up_kernels(state.grid, fast=fast, materials=state.materials, method=state.method,
                    parallel=state.particles.n >= serial.SERIAL_BELOW,
                    grid_rules=bool(state.force_modifiers or state.velocity_modifiers),
                    merge=loop is None)
    if loop is not None:
        loop.compile()
    return time.perf_counter() - t0


def _steps_to_next_event(state, save_every, checkpoint):
    """Steps until the next save, checkpoint or the end of the run (an
    adaptive run: its end is a time, where the compiled loop stops)."""
    n = MAX_STEPS if state.adaptive else state.n_steps - state.step
    for every in (save_every, checkpoint[1] if checkpoint is not None else None):
        if every is not None:
            n = min(n, every - state.step % every)
    return n


def simulate(scene, method=None, save_every=None, progress=False, callback=None,
             checkpoint=None, restart=None):
    """Run the MPM simulation of ``scene`` with ``method`` (default ``Method()``).

    Parameters
    ----------
    save_every
        Save the state every so many steps; None saves the initial and the
        final state. Energies are recorded at every save.
    progress
        Show a progress bar (tqdm; hidden when stderr is not a terminal).
    callback
        ``callback(step, state)`` after every step; returning ``False``
        stops the run there (the Result ends at that step). The particles
        it receives are never written by later steps (keep them if you
        like); it may edit ``state.particles`` in place, but an edit that
        leaves NaN or Inf stops the run with ``SimulationError`` whose
        result holds the state as the callback received it (a copy is
        taken before each call, so a callback costs O(particles) a step).
    checkpoint
        ``(path, every_steps)``: write a restart file every so many steps.
    restart
        Path of a checkpoint to continue from (same scene and method).

    Returns a :class:`~skfem_mpm.solve.result.Result`. Raises
    :class:`~skfem_mpm.SimulationError` when the run cannot continue (NaN or
    Inf, J <= 0, a particle leaving the grid with ``on_exit='raise'``, a
    singular or unconverged mass solve, any other arithmetic failure of a
    step, a checkpoint that cannot be written); its ``result`` holds the
    last good state and its time (``result.final_time``). The scene is
    never modified.
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"simulate needs a Scene (grid, bodies, t_end, effects), got "
                        f"{type(scene).__name__} {scene!r}"[:200])
    method = Method() if method is None else method
    if not isinstance(method, Method):
        raise ValueError(f"method must be a Method, got {method!r}")
    save_every = _check_every("save_every", save_every)
    checkpoint = _check_checkpoint(checkpoint)
    if callback is not None and not callable(callback):
        raise ValueError(f"callback must be callable, got {callback!r}")
    if restart is not None and not isinstance(restart, (str, os.PathLike)):
        raise TypeError(f"restart must be the path of a checkpoint (str or os.PathLike), "
                        f"got {restart!r}")
    state = prepare(scene, method)
    if restart is not None:
        from ..io import checkpoint_size_bound, read_checkpoint, restore_state

        recorder = restore_state(state, read_checkpoint(
            restart, max_bytes=checkpoint_size_bound(state, save_every)))
    else:
        recorder = Recorder()
        recorder.save(state, share=True)
    fast, why_not = compiled_executor_applies(state)
    ops = CompiledExecutor(state) if fast else ReferenceExecutor(state, why_not)
    scheme = SCHEME_STEPS[method.scheme]
    path = ops.path
    loop = None
    if fast and callback is None and loop_applies(state, ops)[0]:
        loop = StepLoop(state, ops)
        path = "fast (compiled loop)"
    jit_time = warm_up(state, fast, loop)
    bar = _progress_bar(progress, state.n_steps)
    threads = ThreadPolicy(ops.kernels.nthreads) if fast else None
    t0, c0 = time.perf_counter(), time.process_time()

    def result_now():
        """The recorded result so far: the compiled loop's compiles at a
        first need (StepLoop.compile_seconds) count as compile time."""
        late = loop.compile_seconds if loop is not None else 0.0
        late_cpu = loop.compile_cpu_seconds if loop is not None else 0.0
        return recorder.result(state, time.perf_counter() - t0 - late, jit_time + late,
                               extra={"path": path,
                                      "cpu_time": time.process_time() - c0 - late_cpu})

    def failed(exc, last_good):
        state.particles = last_good
        result = result_now()
        return SimulationError(
            f"step {state.step + 1} (t = {state.t:.6g} -> {state.t + state.dt:.6g}) "
            f"failed: {exc}", result=result, step=state.step + 1, time=state.t,
            particle=getattr(exc, "particle", None))

    try:
        while not state.done:
            if threads is not None:
                threads.update()
            taken = 0
            if loop is not None:  # compiled steps up to the next save, checkpoint or end
                taken = loop.run(state, _steps_to_next_event(state, save_every, checkpoint))
            if taken == 0:  # one step through the executor
                state.next_step_size()
                last_good = state.particles
                try:
                    data = scheme(ops, state)
                except (InvalidState, ArithmeticError, LinAlgError) as exc:
                    # InvalidState (NaN, J <= 0, a particle leaving, a singular or
                    # unconverged mass solve) and any other arithmetic failure of
                    # the step: the run stops with its last good state
                    raise failed(exc, last_good) from exc
                if data is not None and data.system is not None:
                    state.small_dofs_max = max(state.small_dofs_max, data.system.small_dofs)
                taken = 1
            if bar is not None:
                bar.update(taken)
            if save_every is not None and state.step % save_every == 0:
                # the last step's arrays are written no more: shared unless a
                # callback may still edit them in place
                recorder.save(state, share=state.done and callback is None)
            if checkpoint is not None and state.step % checkpoint[1] == 0:
                from ..io import write_checkpoint

                try:
                    write_checkpoint(checkpoint[0], state, recorder)
                except OSError as exc:  # e.g. a full disk: the run itself is good
                    result = result_now()
                    raise SimulationError(
                        f"writing the checkpoint after step {state.step} failed: {exc}",
                        result=result, step=state.step, time=state.t) from exc
            if callback is not None:
                ops.hand_out(state.particles)
                before = state.particles.copy()  # what the callback may edit in place
                go_on = callback(state.step, state)
                bad = non_finite(state.particles)
                if bad is not None:
                    state.particles = before
                    result = result_now()
                    raise SimulationError(
                        f"the callback left {bad} after step {state.step} (t = {state.t:.6g}); "
                        f"the result holds the state the callback was given",
                        result=result, step=state.step, time=state.t)
                if go_on is False:
                    break
    finally:
        if threads is not None:
            threads.restore()
        if bar is not None:
            bar.close()
    end, cpu_end = time.perf_counter(), time.process_time()
    late = loop.compile_seconds if loop is not None else 0.0
    late_cpu = loop.compile_cpu_seconds if loop is not None else 0.0
    loop = None  # its spare particle arrays and grid copies go before the last save
    if recorder.last_step_saved != state.step:
        recorder.save(state, share=True)  # no step writes the final arrays again
    return recorder.result(state, end - t0 - late, jit_time + late,
                           extra={"path": path, "cpu_time": cpu_end - c0 - late_cpu})
