"""The plain C reference of the bench step, shipped as package data.

``usl_step.c`` (beside this file) is a hand-written C99/OpenMP loop of the
step that ``skfem-mpm bench`` times for its USL rows: quadratic B-splines
on a uniform grid, lumped mass, gravity, fixed dofs, small-strain linear
elasticity and the volume update, 1D to 3D (its header states the equations and
the file formats). The bench compiles it here with the system's C
compiler, runs it on the very problem it gives ``simulate`` (the initial
particle state, time step and step count are written to a file), checks
that both computed the same final particle state, and only then prints
the ratio of the throughputs. Nothing is quoted from elsewhere.

    executable = compile_reference(directory)          # or ReferenceUnavailable
    problem = write_problem(path, scene, method)       # ValueError if not covered
    run = run_reference(executable, path, output, threads)
    agrees, differences = compare(result.particles, run["final"], problem)
"""
import os
import shlex
import shutil
import subprocess
from pathlib import Path

import numpy as np

from ..materials import LinearElastic
from ..solve.state import prepare
from ..spline import SplineGrid

__all__ = ["FLAGS", "SOURCE", "CompiledReference", "ReferenceUnavailable", "compare",
           "compile_reference", "find_compiler", "run_reference", "write_problem"]

SOURCE = Path(__file__).with_name("usl_step.c")
FLAGS = ("-O3", "-march=native", "-fopenmp")
MAGIC = b"USLSTEP2"

# Two correct runs differ by round-off only (the summation order differs
# between the C loop and the compiled kernels); a wrong step differs in the
# leading digits.
RTOL = 1e-8


class ReferenceUnavailable(RuntimeError):
    """The C reference cannot run here; the message says why."""


class CompiledReference:
    """The compiled C reference: ``path`` of the executable and the
    ``command`` that built it."""

    def __init__(self, path, command):
        self.path = Path(path)
        self.command = list(command)

    @property
    def description(self):
        flags = [a for a in self.command[1:]
                 if a.startswith("-") and a != "-o" and not a.startswith("-l")]
        return " ".join([Path(self.command[0]).name, *flags])


def find_compiler(environ=None):
    """The C compiler command (a list): ``$CC`` when set (it must exist),
    else ``cc`` or ``gcc`` on the PATH; raises ReferenceUnavailable."""
    environ = os.environ if environ is None else environ
    path = environ.get("PATH", os.defpath)
    if environ.get("CC"):
        command = shlex.split(environ["CC"])
        if shutil.which(command[0], path=path) is None:
            raise ReferenceUnavailable(f"the compiler CC={environ['CC']!r} was not found")
        return command
    for name in ("cc", "gcc"):
        if shutil.which(name, path=path):
            return [name]
    raise ReferenceUnavailable("no C compiler found (set CC, or put cc or gcc on the PATH)")


def compile_reference(directory, environ=None):
    """Compile ``usl_step.c`` into ``directory`` with the flags ``FLAGS``
    (again without ``-march=native`` if the compiler refuses it); returns a
    CompiledReference or raises ReferenceUnavailable with the compiler's
    last message."""
    compiler = find_compiler(environ)
    executable = Path(directory) / "usl_step"
    message = ""
    for flags in (FLAGS, tuple(f for f in FLAGS if f != "-march=native")):
        command = compiler + list(flags) + [str(SOURCE), "-o", str(executable), "-lm"]
        try:
            done = subprocess.run(command, capture_output=True, text=True, timeout=300,
                                  check=False)
        except (OSError, subprocess.TimeoutExpired) as exc:
            raise ReferenceUnavailable(f"{' '.join(compiler)} could not run: {exc}") from None
        if done.returncode == 0:
            return CompiledReference(executable, command)
        lines = [line for line in done.stderr.splitlines() if line.strip()]
        message = lines[-1] if lines else f"exit status {done.returncode}"
    raise ReferenceUnavailable(f"compilation with {' '.join(compiler)} failed: {message}")


def _covered(state):
    """Raise ValueError unless usl_step.c computes exactly this run's step."""
    m, grid = state.method, state.grid
    problems = []
    if (m.scheme, m.mass, m.reconstruction_name) != ("usl", "lumped", "none"):
        problems.append(f"the method (scheme {m.scheme}, mass {m.mass}, "
                        f"reconstruction {m.reconstruction_name}; it needs usl, lumped, none)")
    if not isinstance(grid, SplineGrid) or grid.degree != 2 or grid.dim not in (1, 2, 3) \
            or not all(grid._uniform) or min(grid.cells_per_axis) < 4:
        problems.append("the grid (it needs a uniform quadratic SplineGrid in 1D, 2D or 3D "
                        "with at least 4 cells per axis)")
    if len(state.bodies) != 1 or type(state.bodies[0][0]) is not LinearElastic \
            or state.scene.finite_strain:
        problems.append("the material (it needs one LinearElastic body, small strain)")
    if any(f.acceleration is None for f in state.forces) or state.force_modifiers \
            or state.constraints.prescribed:
        problems.append("the effects (it needs gravity and fixed dofs only)")
    if problems:
        raise ValueError("the C reference does not compute this run: " + "; ".join(problems))


def write_problem(path, scene, method):
    """Write the input of ``usl_step`` for ``simulate(scene, method)``: the
    initial particles, the time step and the step count that simulate
    chooses. Returns a dict (dim, particles, steps, dt, modulus: the scale
    of the stresses). Raises ValueError for a run the C loop does not do."""
    state = prepare(scene, method)
    _covered(state)
    p, grid, dim = state.particles, state.grid, state.grid.dim
    material = state.bodies[0][0]
    gravity = np.zeros(3)
    for f in state.forces:
        gravity[:dim] += f.acceleration
    cells = list(grid.cells_per_axis) + [1] * (3 - dim)
    bounds = [b for axis in grid.bounds for b in axis] + [0.0, 1.0] * (3 - dim)
    header = np.array([dim, *cells, p.n, state.n_steps], dtype=np.int64)
    lam, mu = (material.lam, material.mu) if dim >= 2 else (0.0, 0.0)
    E = material.E if dim == 1 else 0.0
    parameters = np.array(bounds + [state.dt, *gravity, lam, mu, E])
    with open(path, "wb") as f:
        f.write(MAGIC)
        f.write(header.tobytes())
        f.write(parameters.tobytes())
        f.write(state.constraints.mask.astype(np.uint8).tobytes())
        for a in (p.x, p.v, p.u, p.m, p.V, p.stress):
            f.write(np.ascontiguousarray(a, dtype=np.float64).tobytes())
    return {"dim": dim, "particles": int(p.n), "steps": int(state.n_steps),
            "dt": float(state.dt), "modulus": float(material.modulus(dim))}


def run_reference(executable, problem_path, output_path, threads, repeat=1):
    """Run the compiled reference on a problem file with ``threads`` OpenMP
    threads; returns {"seconds": [per run], "threads", "invalid": particles
    found invalid (outside, non-finite, J <= 0), "final": {x, v, u, V,
    stress} after the steps}. Raises RuntimeError when it fails."""
    env = dict(os.environ, OMP_NUM_THREADS=str(int(threads)))
    path = executable.path if isinstance(executable, CompiledReference) else executable
    done = subprocess.run([str(path), str(problem_path), str(output_path), str(int(repeat))],
                          capture_output=True, text=True, env=env, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"the C reference failed ({done.returncode}): {done.stderr.strip()}")
    seconds, values = [], {}
    for line in done.stdout.splitlines():
        key, _, value = line.partition(" ")
        if key == "seconds":
            seconds.append(float(value))
        else:
            values[key] = int(value)
    with open(problem_path, "rb") as f:
        f.seek(len(MAGIC))
        dim, _, _, _, n, _ = np.frombuffer(f.read(48), dtype=np.int64)
    data = np.fromfile(output_path, dtype=np.float64)
    shapes = {"x": (n, dim), "v": (n, dim), "u": (n, dim), "V": (n,), "stress": (n, dim, dim)}
    final, start = {}, 0
    for name, shape in shapes.items():
        size = int(np.prod(shape))
        final[name] = data[start:start + size].reshape(shape)
        start += size
    if start != data.size:
        raise RuntimeError(f"the C reference wrote {data.size} values, expected {start}")
    return {"seconds": seconds, "threads": values.get("threads"),
            "invalid": values.get("invalid"), "final": final}


def compare(particles, final, problem, rtol=RTOL):
    """Whether the C run's final state ``final`` is ``particles`` (the final
    state of simulate) up to round-off: per field (u, v, V, stress) the
    largest difference divided by its scale (the field's largest value;
    for the stresses at least the modulus times 1e-6, so that the round-off
    of a stress-free block is not compared with itself) must be <= rtol.
    Returns (agrees, {field: scaled difference})."""
    differences = {}
    for name in ("u", "v", "V", "stress"):
        ours = getattr(particles, name)
        theirs = final[name]
        if ours.shape != theirs.shape:
            differences[name] = float("inf")
            continue
        scale = float(np.max(np.abs(ours))) if ours.size else 0.0
        if name == "stress":
            scale = max(scale, 1e-6 * problem["modulus"])
        diff = float(np.max(np.abs(theirs - ours))) if ours.size else 0.0
        differences[name] = diff / scale if scale > 0 else diff
    agrees = all(np.isfinite(d) and d <= rtol for d in differences.values())
    return agrees, differences
