"""The compiled step loop: the scheme of :mod:`skfem_mpm.solve.schemes`,
compiled against compiled operations, run over the steps between two saves
without returning to Python.

On a small problem the arithmetic of a step costs a few microseconds and
the Python around it (the executor's operations, their kernel calls, the
phase timers) ten times that. Here the very scheme functions the executors
run are compiled by numba against a run (:mod:`skfem_mpm.solve.compiled_loop_ops`)
whose methods call the same kernels as the compiled executor
(:mod:`skfem_mpm.solve.compiled`), in the same order and on the same
blocks, so a run gives the same bits on either path.

:func:`loop_applies` names what the loop covers; a run outside it steps
through the executor in Python. A step the loop cannot finish (a
non-finite value, J <= 0, a particle outside the grid, a tiny-mass merge
whose rows outgrow the compiled merge's lists) stops it before the current
state is written; the executor then takes that step and raises, removes or
merges as its docstrings say.

Materials: one body, linear elastic (fused into the transfer kernels) or,
with MUSL, USL and CD, a material with a compiled point law, updated by the
executor's constitutive kernel inside the loop (with rk4 a finite-strain
one, its law called at each stage's F); the loop hands the new F
(finite strain) and the material state (views of its packed buffer) back
to ``state.particles`` as the executor does, and loads them again after
the executor has taken a step.

Time step: fixed, or adaptive (finite strain without a bound and no
``Method(dt=...)``) for a material with a compiled point wave speed: the
loop sets each step's dt from the current F as ``State.next_step_size``
does, by the same compiled rule (:mod:`skfem_mpm.kernels.step_size`), and
hands the last step's dt, dt_crit and wave speed back to the state. The
loop stops at the end time, and with a 2D reconstruction before each
re-estimate of its factor on dt_crit (``State.step_reconstruction_factor``,
Python); an effect tabulated in time (a body force, a side traction,
prescribed velocities) is evaluated at a step's time only once the loop
has reached it: a call of ``StepLoop.run`` then evaluates the next row and
calls the loop again for each step (prescribed velocities, which read dt,
return to the time loop of ``simulate`` every step).

Threads: the loop calls the kernels the executor calls: below
:data:`skfem_mpm.kernels.serial.SERIAL_BELOW` particles their serial copies
(the same source compiled without ``parallel``; the same blocks, so the
same bits), where starting the threads of a parallel region costs more
than the region's work.

Compiling: one generated module per dimension, threading and transfer
layout serves every degree, scheme, mass and reconstruction (each scheme's loop and each
mass kind compile on first use). The kernels are called by symbol and the
transfer kernels through the addresses the run holds
(:mod:`skfem_mpm.kernels.by_symbol`): each kernel compiles once, on its
own, and the loop's functions only their own code. What only some runs
reach is called through addresses that Python sets when a run first
needs it: the transfer kernels of the run's degree, and the tiny-mass merge
(compiled at the first step with tiny-mass dofs, see ``StepLoop.run``).
:func:`precompile_mass` compiles a consistent-mass loop's heaviest
functions without the loop, in another process (a study's second worker).
"""
import functools
import hashlib
import inspect
import os
import time

import numba
import numpy as np
from numba.core.typing.typeof import Purpose

from ..kernels import (band_factor, bbar, by_symbol, cell_integrals, cholesky, constitutive,
                       coverage_skip, fringe, gauss_rule, grid_modifiers, kronecker, merged_mass,
                       mls, mpm, scatter, spline_1d, spline_2d, staging, step_size, tiny_mass, tls,
                       traction, weights)
from ..kernels.by_symbol import ARGUMENT_TYPES, native_address
from ..kernels.gather import g2p_kernel, rates_kernel
from ..kernels.generated import load
from ..kernels.records import grid_record
from ..kernels.step_size import guard_limit
from ..kernels.scatter import g2p2g_kernel, p2g_kernel
from ..materials.state import state_layout
from ..kernels.serial import for_threads
from . import schemes
from .compiled import side_traction
from .compiled_loop_tables import ForceTable, PrescribedTable, TractionTable, reference_forces
from ..kernels.fringe import NO_FACTOR, FringePattern
from .stencil_system import StencilSystem, stencil_residual
from .timestep import (RECONSTRUCTION_EVERY, STABILITY_LIMIT, coverage_bound,
                       covered_parameters, fast_dof_limit, stiffness_root)

__all__ = ["ENABLED", "StepLoop", "loop_applies", "precompile_mass"]

ENABLED = True
"""False: every step goes through the executor in Python (for comparisons:
the tests check that both give the same bits)."""

_HERE = os.path.dirname(os.path.abspath(__file__))
_TEMPLATES = [os.path.join(_HERE, name)
              for name in ("compiled_loop_ops.py", "compiled_loop_mass.py",
                           "compiled_loop_reconstruct.py", "compiled_loop_traction.py",
                           "compiled_loop_body_force.py", "compiled_loop_prescribed.py",
                           "compiled_loop_modifiers.py")]

# the grid kernels the operations call, under the names the operations use
_GRID_KERNELS = {
    "REDUCE_FIELDS": scatter.reduce_fields,
    "REDUCE_COPIES": scatter.reduce_copies,
    "LUMPED_SOLVE": mpm.lumped_solve,
    "USL_GRID": mpm.usl_grid,
    "MASS_WEIGHTED_SUM": mpm.mass_weighted_sum,
    "SMALL_MASS_1D": mpm.small_mass_1d,
    "SMALL_MASS_2D": mpm.small_mass_2d,
    "SMALL_MASS_AXES": mpm.small_mass_axes,
    "COMBINE_STAGES": staging.combine_stages,
    "DEFORMATION_RATE": staging.deformation_rate,
    # a material's compiled point law (not fused linear elasticity)
    "MATERIAL_UPDATE": constitutive.material_update,
    "AVERAGE_DILATATION": bbar.average_dilatation,  # B-bar
    # its compiled point wave speed (an adaptive step)
    "MAX_WAVE_SPEED": constitutive.max_wave_speed,
    # reconstruction (compiled_loop_reconstruct)
    "GAUSS_RULE_1D": gauss_rule.gauss_rule_1d,
    "GAUSS_RULE_1D_INTO": gauss_rule.gauss_rule_1d_into,
    "NOT_A_KNOT_SPLINE_INTO": spline_1d.not_a_knot_spline_into,
    "LOCATE_CELLS": gauss_rule.locate_cells,
    "BODY_BOXES": gauss_rule.body_boxes,
    "GAUSS_RULE_CELLS": gauss_rule.gauss_rule_cells,
    "CUT_CELL_PARTICLES": gauss_rule.cut_cell_particles,
    "TLS_FACTOR": tls.tls_factor,
    "TLS_APPLY": tls.tls_apply,
    "TLS_COEFFICIENTS": tls.tls_coefficients,
    "SLOT_CELLS": tls.slot_cells,
    "CELL_P2G": cell_integrals.cell_p2g,
    "CELL_MOMENTUM": cell_integrals.cell_momentum,
    "CELL_MASS": cell_integrals.cell_mass,
    "MLS_FIT": mls.mls_fit,
    "SPLINE_LS_SYSTEM": spline_2d.spline_ls_system,
    "APPLY_BAND_FACTOR": band_factor.apply_band_factor,
    "SPLINE_EVALUATE": spline_2d.spline_evaluate,
    # a side traction (compiled_loop_traction)
    "SIDE_FACES": traction.side_faces,
    "LOADS_POWER": traction.loads_power,
    # damping, walls (compiled_loop_modifiers)
    "MODIFY_FORCES": grid_modifiers.modify_forces,
    "MODIFY_VELOCITIES": grid_modifiers.modify_velocities,
    # consistent mass (compiled_loop_mass)
    "CONSISTENT_1D": mpm.consistent_1d,
    "CONSISTENT_2D": mpm.consistent_2d,
    "CONSISTENT_CELLS_2D": mpm.consistent_cells_2d,
    "CONSISTENT_AXES": mpm.consistent_axes,
    "REDUCE_STENCIL": mpm.reduce_stencil,
    "COMPACT_SYSTEM": mpm.compact_system,
    "LUMPED_REACH": mpm.lumped_reach,
    "FAST_ROW_FRACTIONS": mpm.fast_row_fractions,
    "COVERED_STIFFNESS": mpm.covered_stiffness,
    "PARTICLE_COVERAGE": mpm.particle_coverage,
    "COVERAGE_REACH": coverage_skip.coverage_reach,
    "REDUCE_COVERAGE": mpm.reduce_coverage,
    "COVERAGE_HOLDS": coverage_skip.coverage_holds,
    "COMPACT_PROBLEM": mpm.compact_problem,
    "EXPAND_PROBLEM": mpm.expand_problem,
    "ELL_PCG": mpm.ell_pcg,
    "APPLY_KRONECKER": kronecker.apply_kronecker,
    "FIT_KRONECKER": kronecker.fit_kronecker,
    "ELL_BAND_WIDTH": band_factor.ell_band_width,
    "FIT_BAND_FACTOR": band_factor.fit_band_factor,
    "KRONECKER_BOXES": kronecker.kronecker_boxes,
}

# the tiny-mass merge (lumped: MERGED_SOLVE; consistent: the others, in the
# order of MassSystem.merge_at), called through addresses: a run compiles
# them only at its first step with tiny-mass dofs (StepLoop.run), and the
# return type each call site declares
MERGE_KERNELS = {
    "MERGED_SOLVE": (tiny_mass.merged_lumped_solve_axes, "int64"),
    "NEIGHBOUR_MAXIMA": (tiny_mass.neighbour_maxima, "none"),
    "MERGING_ROWS": (tiny_mass.merging_rows, "int64"),
    "MERGED_SYSTEM": (merged_mass.merged_system, "int64"),
    "MERGED_PROBLEM": (merged_mass.merged_problem, "none"),
    "MERGED_EXPAND": (merged_mass.merged_expand, "none"),
    # 1D: CG on a merged group (unmerged, P = A gives the solution at once)
    "MERGED_PCG": (mpm.ell_pcg, "int64"),
}
STOP_MERGE_KERNELS = 6
"""run.stop when a step met tiny-mass dofs before the merge kernels were
compiled: StepLoop.run compiles them and calls the loop again."""
STOP_FRINGE_FACTOR = 7
"""run.stop when a step with the fringe correction on found no factor
loaded for its free rows: the executor takes that step (and makes the
factor), the loop the ones after it."""
FRESH_KINDS = ("acceleration", "velocity", "acceleration+acceleration",
               "acceleration+velocity", "velocity+acceleration", "velocity+velocity")
"""The kinds of right-hand sides of one CG run (StencilSystem._keep_fringe's
names) in the order of the mass system's ``fringe_fresh``."""


def loop_applies(state, executor):
    """(True, '') when the compiled loop can run the steps of ``state`` on
    ``executor`` (a :class:`~skfem_mpm.solve.compiled.CompiledExecutor`),
    else (False, the first reason it cannot)."""
    m = state.method
    recon = getattr(executor, "recon", None)
    fused = bool(getattr(executor, "fused", False))  # one linear elastic body
    reasons = (
        (not ENABLED, "the compiled loop is switched off (compiled_loop.ENABLED)"),
        (executor is None or not executor.path.startswith("fast"), "not the compiled executor"),
        (recon is not None and recon.name == "spline" and recon.dim == 3,
         f"reconstruction {m.reconstruction} in {state.grid.dim}D"),
        (recon is not None and recon.name == "spline" and recon.dim == 2
         and recon.spline_ls.iterative,
         "reconstruction spline in 2D with its Kronecker-preconditioned CG (DIRECT_DOFS "
         "cubic dofs or more)"),
        (m.scheme not in ("musl", "usl", "cd", "rk4"), f"scheme {m.scheme}"),
        (len(state.bodies) != 1 and not fused, "several bodies of different materials"),
        (not fused and not getattr(executor, "point_laws", False),
         "a material without a compiled point law (point_update None)"),
        (not fused and m.scheme == "rk4" and not executor.finite,
         "rk4 with a small-strain material other than linear elasticity (its NumPy "
         "stress_rate)"),
        (not fused and len(state.bodies) == 1 and not isinstance(state.bodies[0][1], slice),
         "a body of some of the particles"),
        (not _side_tractions_only(executor), "particle forces other than gravity, one "
         "traction on a side of the body with tau(t) and forces of the reference "
         "configuration (reference_only: a BodyForce)"),
        (_without_rule(executor) is not None,
         f"a grid modifier without a compiled rule ({_without_rule(executor)!r})"),
        (state.adaptive and state.bodies[0][0].point_wave_speed is None,
         "an adaptive time step with a material without a compiled wave speed "
         "(point_wave_speed None)"),
        (state.grid.dim not in (1, 2, 3), f"{state.grid.dim}D"),
    )
    for failed, why in reasons:
        if failed:
            return False, why
    if m.mass != "lumped":
        why = _mass_unsupported(state)
        if why is not None:
            return False, why
    return True, ""


def _without_rule(executor):
    """The first grid modifier of the executor's run without a compiled
    rule (``grid_rule(grid)`` None: a Footing), or None."""
    if executor is None:
        return None
    return executor.force_modifiers.without_rule() or executor.velocity_modifiers.without_rule()


def _side_tractions_only(executor):
    """Whether the executor's particle forces other than gravity are at most
    one side traction with tau(t) (the loop's SideTraction) and forces of
    the reference configuration (the loop's BodyForce)."""
    if executor is None:
        return False
    forces = [f for f in executor.other_forces if not f.reference_only]
    return not forces or (len(forces) == 1 and side_traction(forces[0]))


def _mass_unsupported(state):
    """Why the loop cannot solve this run's consistent (or hybrid) mass, or
    None: it runs StencilSystem's Kronecker-preconditioned CG, not the
    sparse LU or the Jacobi preconditioner (the fringe correction it runs
    with the executor's factors, and it logs each CG run's iterations as
    StencilSystem.iteration_log asks)."""
    m, cls = state.method, StencilSystem
    if m.mass_solver == "direct":
        return "mass_solver 'direct' (sparse LU)"
    if cls.preconditioner != "kronecker":
        return f"the {cls.preconditioner!r} preconditioner"
    return None


# ------------------------------------------------------ the generated module
def _by_symbol(label, func):
    """Lines binding ``label`` to a call of ``func`` by symbol
    (:mod:`skfem_mpm.kernels.by_symbol`: the kernel is compiled once, on
    its own, not linked into every function above it)."""
    params = inspect.signature(func).parameters.values()
    if any(q.kind is not q.POSITIONAL_OR_KEYWORD or q.default is not q.empty for q in params):
        raise ValueError(f"{func.__name__}: a kernel called by symbol takes plain "
                         f"positional parameters")
    names = ", ".join(q.name for q in params)
    return [f"from {func.__module__} import {func.__name__} as _{label}",
            "",
            "",
            '@njit(inline="always")',
            f"def {label}({names}):",
            f"    return call(_{label}, {names})",
            "",
            ""]


def _transfer_kernels(dim, p, parallel, window):
    """The run's transfer kernels under the names the operations use."""
    return {"P2G": p2g_kernel(dim, p, window, parallel),
            "G2P2G": g2p2g_kernel(dim, p, window, parallel),
            "G2P": g2p_kernel(dim, p, parallel),
            "RATES": rates_kernel(dim, p, parallel)}


def _at_address(label, func, site, restype="none"):
    """Lines binding ``label(address, ...)`` to a call of the kernel at
    ``address`` with ``func``'s parameters, returning ``restype`` (a name in
    numba.types; :func:`by_symbol.call_at`, call site ``site``): one
    compiled loop serves every degree, and a kernel compiles only when a
    run points the loop at it."""
    names = ", ".join(inspect.signature(func).parameters)
    return ["",
            f"_{label}_AT = call_at({site!r}, types.{restype})",
            "",
            "",
            '@njit(inline="always")',
            f"def {label}(address, {names}):",
            f"    return _{label}_AT(address, {names})",
            "",
            ""]


def _prelude(dim, parallel, window, variant):
    """The lines binding the operations' kernel names for one variant."""
    lines = ['"""Generated by skfem_mpm.solve.compiled_loop; do not edit."""',
             "import numpy as np",
             "from numba import njit, prange, types",
             "",
             "from skfem_mpm.kernels.by_symbol import call, call_at",
             "from skfem_mpm.kernels.clock import monotonic_ns",
             "from skfem_mpm.kernels.band_factor import factor_band, factor_columns",
             "from skfem_mpm.kernels.mpm import work_increment as WORK_INCREMENT",
             "from skfem_mpm.kernels.step_size import (adaptive_step, critical_step, "
             "guard_limit, reached_end,",
             "                                         time_after_step)"]
    # the names only: the degree-1 kernels' parameters, the same at every degree
    for label, kernel in _transfer_kernels(dim, 1, parallel, window).items():
        lines += _at_address(label, kernel.py_func, f"{variant}:{label}")
    for label, (kernel, restype) in MERGE_KERNELS.items():
        lines += _at_address(label, kernel.py_func, f"{variant}:{label}", restype)
    for label, kernel in _GRID_KERNELS.items():
        lines += _by_symbol(label, for_threads(kernel, parallel).py_func)
    small = {1: "SMALL_MASS_1D(mass, p, tol, small)",
             2: "SMALL_MASS_2D(mass, nbx, nby, p, tol, small)",
             3: "SMALL_MASS_AXES(mass, nbx, nby, mass.shape[0] // (nbx * nby), p, tol, small)"}[dim]
    assemble = {1: "(bx, ux, ihx, Cx), = axes\n"
                   "    CONSISTENT_1D(x, m, bx, ux, ihx, Cx, p, copies, stiff, touched)",
                2: "(bx, ux, ihx, Cx), (by, uy, ihy, Cy) = axes\n"
                   "    CONSISTENT_2D(x, m, bx, by, ux, uy, ihx, ihy, Cx, Cy, p, nbx, copies, "
                   "stiff, touched)",
                3: "(b0, u0, ih0, C0), (b1, u1, ih1, C1), (b2, u2, ih2, C2) = axes\n"
                   "    CONSISTENT_AXES(x, m, b0, u0, ih0, C0, b1, u1, ih1, C1, b2, u2, ih2, C2, "
                   "p, nbx, nby, copies, stiff, touched)"}[dim]
    coverage = {1: "(b0, u0, ih0, C0), = axes\n"
                   "    PARTICLE_COVERAGE(x, m, b0, u0, ih0, C0, b0, u0, ih0, C0, b0, u0, ih0, C0, "
                   "p, nbx, nby, copies, touched)",
                2: "(b0, u0, ih0, C0), (b1, u1, ih1, C1) = axes\n"
                   "    PARTICLE_COVERAGE(x, m, b0, u0, ih0, C0, b1, u1, ih1, C1, b0, u0, ih0, C0, "
                   "p, nbx, nby, copies, touched)",
                3: "(b0, u0, ih0, C0), (b1, u1, ih1, C1), (b2, u2, ih2, C2) = axes\n"
                   "    PARTICLE_COVERAGE(x, m, b0, u0, ih0, C0, b1, u1, ih1, C1, b2, u2, ih2, C2, "
                   "p, nbx, nby, copies, touched)"}[dim]
    reach = coverage.replace("PARTICLE_COVERAGE", "COVERAGE_REACH").replace(
        "copies, touched)", "delta, out)")
    assemble_cells = ("(bx, ux, ihx, Cx), (by, uy, ihy, Cy) = axes\n"
                      "    CONSISTENT_CELLS_2D(x, m, cells, k, bx, by, ux, uy, ihx, ihy, Cx, Cy, p, "
                      "nbx, copies, stiff, touched)" if dim == 2 else
                      "raise ValueError('the cells rule is 2D')")
    by_boxes = ("return (cm.Lx[g, :nx], cm.Ly[g, :ny], cm.Lz[g, :nz], cm.box_index[g, :n], "
                "cm.inv_scale[g, :n], cm.box, nt, cm.boxes[g, :cm.n_boxes[g]])")
    kronecker = (by_boxes
                 if dim == 3 else
                 "return (cm.Lx[g], cm.Ly[g], cm.box_index[g, :n], cm.inv_scale[g, :n], "
                 "cm.box[:ny * nx * nc].reshape((ny, nx, nc)), max(1, min(nt, nx)))"
                 if dim == 1 else  # (the band factor is 2D's)
                 "w = cm.band_width[g]\n"
                 "    m = n if w >= 0 else 0  # the band factor's rows (none: Kronecker)\n"
                 "    wf = factor_columns(max(w, 0))\n"
                 "    band = cm.band[g, :m * wf].reshape((m, wf))\n"
                 "    return (cm.Lx[g], cm.Ly[g], cm.box_index[g, :n], cm.inv_scale[g, :n], "
                 "cm.box[:ny * nx * nc].reshape((ny, nx, nc)), max(1, min(nt, nx)), band, w >= 0)")
    pcg = ("return ELL_PCG(A, cols, inv_diag, KRONECKER_ARGS(cm, g, n, nc, nt), None, b, x, "
           "problem, cm.rtol, limit, nt, work)")
    direct = ("raise ValueError('the direct Kronecker solve is 1D')" if dim != 1 else
              "k = KRONECKER_ARGS(cm, g, n, nc, nt)\n"
              "    APPLY_KRONECKER(k[0], k[1], k[2], k[3], k[4], k[5], b, x)\n"
              "    return 1")
    if dim == 1:  # P = A: the solution at once (StencilSystem.solve_many); CG only on
        # a merged group, through the address the merge sets (cm.merge_at[5])
        pcg = ("if not cm.merged[g]:\n"
               "        return KRONECKER_DIRECT(cm, g, n, nc, nt, b, x)\n    "
               + pcg.replace("ELL_PCG(", "MERGED_PCG(cm.merge_at[5], "))
    if dim == 2:  # (the fringe correction is 2D's)
        pcg = ("if cm.fringe_used[g]:\n"
               "        return ELL_PCG(A, cols, inv_diag, KRONECKER_ARGS(cm, g, n, nc, nt), "
               "fringe_args(cm, g, nc), b, x, problem, cm.rtol, limit, nt, work)\n    "
               "if cm.n_boxes[g] > 1 and cm.band_width[g] < 0:\n"
               "        return ELL_PCG(A, cols, inv_diag, BOX_ARGS(cm, g, n, nc, nt), None, b, x, "
               "problem, cm.rtol, limit, nt, work)\n    " + pcg)
    body = f'''
DIM = {dim}


@njit(cache=True)
def BOX_ARGS(cm, g, n, nc, nt):
    """Group g's boxes of coupled components as apply_kronecker_axes takes them."""
    nz, ny, nx = cm.box_shape[g, 0], cm.box_shape[g, 1], cm.box_shape[g, 2]
    {by_boxes}


@njit(cache=True)
def SMALL_MASS(mass, tol, small, nbx, nby, p):
    """Count of the tiny-mass dofs (see kernels.mpm.small_mass_{dim}d)."""
    return {small}


@njit(cache=True)
def ASSEMBLE(x, m, axes, p, nbx, nby, copies, stiff, touched):
    """Per-thread copies of the consistent mass stencil (kernels.mpm.consistent_{dim}d)."""
    {assemble}


@njit(cache=True)
def COVERAGE(x, m, axes, p, nbx, nby, copies, touched):
    """Per-thread copies of the particles' guard sums (kernels.mpm.particle_coverage;
    the axes as Kernels.particle_coverage passes them)."""
    {coverage}


@njit(cache=True)
def REACH(x, m, axes, p, nbx, nby, delta, out):
    """The reach W_k of the guard's skip (kernels.coverage_skip.coverage_reach;
    the axes as COVERAGE passes them)."""
    {reach}


@njit(cache=True)
def ASSEMBLE_CELLS(x, m, axes, cells, k, p, nbx, copies, stiff, touched):
    """2D: per-thread copies of the consistent mass stencil of points whose
    first cells k x k blocks are cells' tensor rules (kernels.mpm.consistent_cells_2d)."""
    {assemble_cells}


@njit(cache=True)
def KRONECKER_ARGS(cm, g, n, nc, nt):
    """Group g's Kronecker preconditioner for n rows and nc columns as
    ell_pcg takes it (KroneckerData.args: apply_kronecker's arguments,
    3D apply_kronecker_axes', its boxes' factors concatenated)."""
    nz, ny, nx = cm.box_shape[g, 0], cm.box_shape[g, 1], cm.box_shape[g, 2]
    {kronecker}


@njit(cache=True)
def KRONECKER_DIRECT(cm, g, n, nc, nt, b, x):
    """1D, group g not merged: x = P^-1 b with its Kronecker factor, at once
    (P = A there: see StencilSystem.solve_many); returns 1 (the iterations
    the records count)."""
    {direct}


@njit(cache=True)
def KRONECKER_PCG(cm, g, n, nc, nt, A, cols, inv_diag, b, x, problem, limit, work):
    """Group g's CG run (ell_pcg) with its Kronecker preconditioner; in 2D
    with the boxes of its coupled components when it has two or more
    (apply_kronecker_axes' arguments, as KroneckerData.args gives them);
    in 1D, unless merged, x = P^-1 b at once (P = A there: see
    StencilSystem.solve_many)."""
    {pcg}
'''
    return "\n".join(lines) + "\n\n" + body


@functools.cache
def loop_module(dim, parallel, window):
    """The generated loop module of one variant (every degree: the run holds
    the addresses of its degree's transfer kernels)."""
    templates = []
    for path in _TEMPLATES:
        with open(path, encoding="utf-8") as f:
            templates.append(f.read())
    threads = "par" if parallel else "ser"
    name = f"{dim}d_{threads}_{'window' if window else 'cells'}"
    source = _prelude(dim, parallel, window, name) + "\n" + f"VARIANT = {name!r}\n" + \
        "\n\n" + "\n\n".join(templates)
    # the operations' callees are not tracked by numba's cache: their
    # sources go into the file's name (kernels.generated.load hashes it)
    depends = "".join(inspect.getsource(m) for m in (
        schemes, mpm, scatter, kronecker, fringe, band_factor, tiny_mass, merged_mass, staging,
        gauss_rule, spline_1d, spline_2d, tls, mls, cholesky, weights, traction, constitutive,
        grid_modifiers, bbar, by_symbol, step_size))
    tag = hashlib.sha1(depends.encode()).hexdigest()[:8]
    return load(f"loop_{name}_{tag}", source)


def precompile_mass(state, executor):
    """Compile (or load from numba's cache) the consistent-mass functions the
    compiled loop of ``state`` calls by symbol (the generated module's
    ``mass_units``: prepare_mass, then mass_solve and its CG), without
    compiling the loop nor building the run (only its type:
    :meth:`StepLoop._record`): a second process (a study's second worker)
    so takes that share of a first use while the first compiles the rest
    of the loop, which reaches them after its particles-to-grid pass;
    :class:`~skfem_mpm.kernels.by_symbol.compile_lock` makes
    each function compile in one of them. Returns whether the run has
    such functions (consistent or hybrid mass on the loop)."""
    if state.method.mass == "lumped" or not loop_applies(state, executor)[0]:
        return False
    loop = StepLoop(state, executor, compile_loop=False)
    loop.module.mass_units.compile((loop.run_state,))
    return True


# ----------------------------------------------------------------- the loop
class StepLoop:
    """The compiled loop of one simulation (see the module): ``run(state,
    n)`` takes up to n steps and returns how many it took."""

    def __init__(self, state, executor, compile_loop=True):
        """``compile_loop`` False (precompile_mass): the run is only typed,
        ``run_state`` its numba type (:meth:`_record`), never stepped."""
        ok, why = loop_applies(state, executor)
        if not ok:
            raise ValueError(f"the compiled loop does not apply: {why}")
        grid, k = state.grid, executor.kernels
        p = state.particles
        dim, nd, n = grid.dim, grid.ndofs, p.n
        self.parallel = k.parallel  # the executor's kernels: serial or parallel
        window = k.transfers.window
        self.module = loop_module(dim, self.parallel, window)
        self._typed_only = not compile_loop
        nbx, nby = (nd, 1) if dim == 1 else tuple(grid.basis_per_axis[:2])
        self.scheme = state.method.scheme
        self.executor = executor
        material = state.bodies[0][0]
        self.fused = executor.fused
        lam, mu = (0.0, 0.0) if not self.fused else \
            (material.E, 0.0) if dim == 1 else (material.lam, material.mu)
        copies_p2g, touched_p2g = k.transfers.copies(1 + 2 * dim)
        copies_g2p2g, touched_g2p2g = k.transfers.copies(dim)
        gravity_work = bool(executor.gravity_work)
        cd = self.scheme == "cd"
        empty = np.empty
        self._arrays = [empty((n, dim)) for _ in range(3)] + [empty(n)] + [empty((n, dim, dim))]
        x, v, u, V, stress = self._arrays
        vec = (lambda: empty((n, dim)))
        fields = dict(
            x=x, v=v, u=u, m=np.ascontiguousarray(p.m, dtype=np.float64), V=V, stress=stress,
            x_new=vec(), v_new=vec(), u_new=vec(), V_new=empty(n),
            stress_new=empty((n, dim, dim)),
            acc=vec() if cd else np.zeros((1, dim)),
            L=np.empty((1, 1, 1)) if self.fused else empty((n, dim, dim)),
            grid=grid_record(grid), mass_range=np.zeros((k.nthreads, 2)),
            occupied=k.transfers.occupied,  # shared with the executor, as the grid arrays
            copies_p2g=copies_p2g, touched_p2g=touched_p2g, copies_g2p2g=copies_g2p2g,
            touched_g2p2g=touched_g2p2g,
            mask=np.ascontiguousarray(state.constraints.mask),
            gravity=np.array(executor.gravity, dtype=np.float64), no_gravity=np.zeros(dim),
            no_force=np.zeros((1, dim)), small=np.zeros(nd, dtype=np.bool_),
            small_tol=float(state.method.small_mass), small_count=0, small_max=0,
            nbx=int(nbx), nby=int(nby), degree=int(grid.degree),
            flags=np.full((k.nthreads, 3), -1, dtype=np.int64), lam=float(lam), mu=float(mu),
            dt=float(state.dt), t=float(state.t), step=int(state.step),
            n_steps=-1 if state.adaptive else int(state.n_steps),
            t_end=float(state.scene.t_end), vfactor=1.0,
            store_acc=cd, velocities_done=False, gravity_work=gravity_work, work=0.0,
            work_sum=np.zeros(dim), stop=0, handover=False,
            phase_ns=np.zeros(len(self.PHASES), dtype=np.int64), nthreads=int(k.nthreads),
            p2g_at=0, g2p2g_at=0, g2p_at=0, rates_at=0, merged_solve_at=0)
        fields.update(executor.grid_arrays())  # mass, momentum, force, ..., v_old
        fields.update(self._step_size_fields(state, material, k.nthreads))
        fields.update(self._law_arrays(material, executor, n, dim, k.nthreads))
        fields.update(self._stage_arrays(n if self.scheme == "rk4" else 1, dim, fields))
        recon = executor.recon
        forces = reference_forces(executor.other_forces)
        side = next((f for f in executor.other_forces if not f.reference_only), None)
        # tabulated effects (compiled_loop_tables): a body force, prescribed velocities
        self.forces = ForceTable(self.module, forces, state) if forces else None
        self.prescribed = PrescribedTable(self.module, state) \
            if state.constraints.prescribed else None
        fields.update(rc=None if recon is None else self._reconstruction(recon, p, bool(forces)),
                      no_acceleration=np.zeros((nd if recon is not None else 1, dim)),
                      displacement=empty((n if recon is not None or side or forces else 1,
                                          dim)),
                      traction=None if side is None else self._side_traction(side, state, k),
                      body_force=None if not forces else self.forces.record,
                      prescribed=None if self.prescribed is None else self.prescribed.record)
        if side is not None and fields["V0"].shape[0] != n:  # (a point law loads its own)
            fields["V0"] = np.ascontiguousarray(p.V0, dtype=np.float64)
        self.side, self.traction = side, fields["traction"]
        tau = None if side is None else TractionTable(self.module, side, self.traction, state)
        self.tables = [t for t in (self.forces, self.prescribed, tau) if t is not None]
        # adaptive steps under tables of t alone: one call of run() goes on row by row
        self.row_by_row = bool(self.adaptive and self.tables and not self.refactored and
                               not any(table.reads_dt for table in self.tables))
        self._rule_arrays = {}  # "force" / "velocity": the packed rules' arrays
        self.force_rules = fields["force_rules"] = self._rules(
            "force", executor.force_modifiers, 1)
        self.velocity_rules = fields["velocity_rules"] = self._rules(
            "velocity", executor.velocity_modifiers, 0, executor.force_modifiers)
        # consistent or hybrid mass: the run's mass system (None: lumped)
        self.cm = fields["cm"] = None if state.method.mass == "lumped" else \
            self._mass_system(state, k)
        self.run_state = self._record("new_run", "RunType", self.module.FIELDS, fields)
        self.retired = False  # the executor takes every further step
        self._executor_next = False  # it takes the next step (a fringe factor to make)
        self._fringe_loaded = {}  # group -> the FringeFactor (or pattern) loaded
        self._loop = self.module.LOOPS[self.scheme]
        if compile_loop:  # (False: precompile_mass's run, never stepped)
            self._point_at_transfers(dim, grid.degree, window)
        self._loaded = None  # the particles whose arrays the run holds
        self._steps_per_call = 1  # parallel: grows to CALL_SECONDS of steps

    def _step_size_fields(self, state, material, nthreads):
        """The fields of an adaptive step (compiled_loop_ops.FIELDS: the
        material's point wave speed and the constants of
        kernels.step_size's rule, State.next_step_size's); placeholders
        for a fixed dt."""
        m, grid = state.method, state.grid
        self.adaptive = bool(state.adaptive)
        # a 2D reconstruction's factor on dt_crit, re-estimated in Python
        self.refactored = self.adaptive and m.reconstruction != "none" and grid.dim >= 2
        guard = 0.0 if m.mass in ("lumped", "hybrid") else m.frequency_guard
        return dict(
            adaptive=self.adaptive,
            wave_at=int(material.point_wave_speed.address()) if self.adaptive else 0,
            cfl=float(m.cfl), stability_limit=float(STABILITY_LIMIT.get(m.scheme, 2.0)),
            stiffness_root=stiffness_root(grid, m.mass), wave_speed=float(state.wave_speed_now),
            dt_crit=float(state.dt_crit), block_max=np.empty(nthreads),
            guard_q=float(guard * fast_dof_limit(grid.degree, m.scheme)) if guard > 0 else 0.0,
            taken_step=np.zeros(3), recon_factor=1.0)

    def _law_arrays(self, material, executor, n, dim, nthreads):
        """The point law's data of the run (compiled_loop_ops.FIELDS; fused
        linear elasticity: ``law_at`` None and placeholders of one row)."""
        empty = np.empty
        self.layout = None  # the packed material state's layout (None: no state)
        self.finite = False
        arrays = dict(law_at=None, law_params=np.zeros(0), finite=False,
                      F=empty((1, 1, 1)), F_new=empty((1, 1, 1)), V0=empty(1),
                      mstate=empty((1, 0)), mstate_new=empty((1, 0)),
                      law_flags=np.full(nthreads, -1, dtype=np.int64),
                      no_index=np.zeros(0, dtype=np.int64), cell_average=None)
        if self.fused:
            return arrays
        if material.cell_average:  # B-bar (kernels.bbar)
            functions, per = material.functions, (1 << dim) if material.vertices else 1
            arrays["cell_average"] = (grid_record(material.grid)[0], material.vertices,
                                      np.zeros(functions), np.zeros(functions),
                                      np.zeros((n, per), dtype=np.int64), np.zeros((n, per)))
        self.finite = bool(executor.finite)
        layout = state_layout(material, dim)
        self.layout = layout if layout else None
        width = layout.size if layout else 0
        F = (lambda: empty((n, dim, dim))) if self.finite else (lambda: empty((1, 1, 1)))
        arrays.update(
            law_at=int(material.point_update.address()),
            law_params=np.ascontiguousarray(material.point_parameters(dim), dtype=np.float64),
            finite=self.finite, F=F(), F_new=F(), V0=empty(n), mstate=empty((n, width)),
            mstate_new=empty((n, width)))
        return arrays

    def _load_law_state(self, p):
        """Copy the particles' F (finite strain), V0 and packed state into the run."""
        F = np.ascontiguousarray(p.F) if self.finite else np.empty((1, 1, 1))
        n = p.n
        packed = self.layout.pack(p.state) if self.layout is not None else np.empty((n, 0))
        self.module.load_law_state(self.run_state, F, np.ascontiguousarray(p.V0), packed)

    def _law_results(self, p):
        """The arrays of the new F and state (``Particles.replaced``
        keywords) as the executor hands them on: the run's current F, and
        the state dict with views of its current packed state (the
        executor's PackedState.written)."""
        if self.fused:
            return {}
        F, packed = self.module.law_state(self.run_state)
        out = {}
        if self.finite:
            out["F"] = F
        if self.layout is not None:
            state = dict(p.state)
            state.update(self.layout.views(packed))
            out["state"] = state
        return out

    def _stage_arrays(self, n, dim, fields):
        """The rk4 arrays of n particles (see compiled_loop_ops.FIELDS; other
        schemes: n = 1, and the reactions read the step's own grid arrays;
        F's only for a finite-strain point law, after :meth:`_law_arrays`)."""
        empty, zeros = np.empty, np.zeros
        stages = 4
        staged_F = self.scheme == "rk4" and self.finite
        arrays = dict(
            x_stage=empty((n, dim)), v_stage=empty((n, dim)), u_stage=empty((n, dim)),
            V_stage=empty(n), stress_stage=empty((n, dim, dim)), rate_x=zeros((stages, n, dim)),
            rate_v=zeros((stages, n, dim)), rate_stress=zeros((stages, n, dim, dim)),
            rate_V=zeros((stages, n)),
            rate_F=zeros((stages, n, dim, dim) if staged_F else (1, 1, 1, 1)),
            F_stage=empty((n, dim, dim) if staged_F else (1, 1, 1)), power=zeros(stages),
            stage_weights=zeros(stages), next_stage=0)
        for name in ("mass", "a", "force"):
            own = fields[name]
            arrays[f"reaction_{name}"] = empty(own.shape) if self.scheme == "rk4" else own
        return arrays

    # With grid rules a call of the loop takes at most this many steps (their
    # log holds a row per step: rk4's first stage's)
    RULE_LOG_STEPS = 512

    def _rules(self, kind, modifiers, calls_per_step, forces=None):
        """The run's packed grid rules (compiled_loop_modifiers) of
        ``modifiers`` (a CompiledModifiers), or None without any: a log of
        ``calls_per_step`` rows a step (the force rules); ``forces``: the
        force modifiers whose rules' states the velocity rules read."""
        if not modifiers:
            return None
        codes, parameters, offsets, dofs, reactions, data_offsets, data, states = \
            modifiers.packed()
        rows = self.RULE_LOG_STEPS * calls_per_step
        log_states = np.zeros((rows, *states.shape))
        log_reactions = np.zeros((rows, *reactions.shape))
        owners = [] if forces is None else forces.modifiers
        shared = np.array([next((r for r, f in enumerate(owners) if f is m), -1)
                           for m in modifiers.modifiers], dtype=np.int64)
        fields = dict(codes=codes, parameters=parameters, offsets=offsets, dofs=dofs,
                      reactions=reactions, data_offsets=data_offsets, data=data,
                      states=states, log_states=log_states, log_reactions=log_reactions,
                      logged=0, shared=shared)
        self._rule_arrays[kind] = (modifiers, fields)
        return self.module.new_grid_rules(*(fields[n] for n in self.module.RULE_FIELDS))

    def _load_rule_states(self):
        """The rules start from their modifiers' states (a step the loop
        stopped, or the executor's steps, moved them), the log from its
        first row."""
        for modifiers, fields in self._rule_arrays.values():
            modifiers.load_states(fields["states"])
        if self.force_rules is not None:
            self.module.reset_rule_log(self.force_rules)

    def _rule_results(self, taken):
        """The states and reactions of the ``taken`` steps to the force
        rules' modifiers (a footing's clock and history, the walls' reactions)."""
        modifiers, _ = self._rule_arrays["force"]
        logged, states, reactions = self.module.rule_log(self.force_rules)
        rows = min(int(logged), taken)
        modifiers.take_steps(states[:rows], reactions[:rows])

    def _side_traction(self, f, state, k):
        """The run's side traction (compiled_loop_traction) of the effect
        ``f`` (a SurfaceTraction of tau(t)); its table is filled before each
        call of the loop (:class:`~skfem_mpm.solve.compiled_loop_tables.TractionTable`)."""
        dim, nd, count = state.grid.dim, state.grid.ndofs, f.index.size
        zeros = np.zeros
        fields = dict(
            index=np.ascontiguousarray(f.index, dtype=np.int64),
            share=np.ascontiguousarray(f.share, dtype=np.float64),
            size=np.ascontiguousarray(f.size, dtype=np.float64), axis=int(f.axis),
            sign=float(f.sign), bounds=np.array(state.grid.bounds, dtype=np.float64),
            tau=zeros((1, 3, dim)), first_step=0, faces=zeros((count, dim)),
            loads=zeros((count, dim)), zero_v=zeros((count, dim)), zero_m=zeros(count),
            zero_stress=zeros((count, dim, dim)), mass=zeros(nd), momentum=zeros((nd, dim)),
            force=zeros((nd, dim)), mass_range=zeros((k.nthreads, 2)),
            occupied=zeros(4, dtype=np.int64))
        return self._record("new_side_traction", "SideTractionType",
                            self.module.TRACTION_FIELDS, fields)

    def _reconstruction(self, recon, p, forces):
        """The reconstruction data of the run (compiled_loop_reconstruct), with
        the rule's constants of the executor's CompiledReconstruction;
        ``forces``: whether a body force's density is fitted too."""
        n, dim = p.n, p.dim
        empty = np.empty
        k = 1 + dim + dim * dim + (dim if forces else 0)  # the fitted fields
        if recon.name != "spline" or dim == 2:  # on CompiledReconstruction.rule's rule
            fields = dict(
                ref=recon.ref, wref=recon.wref, gap=float(recon.gap), breaks=recon.breaks,
                axes=recon.axes, uniform=recon.uniform, ncells=recon.ncells,
                values=empty((n, k)),
                rho=empty(n), pcell=empty(0, dtype=np.int64), xg=empty((0, dim)), wg=empty(0),
                gcell=empty(0, dtype=np.int64), own=empty(0, dtype=np.int64),
                factor=None, radius=0.0, alpha=None, spline=None, tables=None,
                spline_cells=empty((0, 2), dtype=np.int64), spline_basis=empty((0, 8)),
                cell_shape=(0, 0, 0), coef=empty((0, 6, k)), slot_cell=empty(0, dtype=np.int64),
                momentum_coef=empty((0, 6, dim)),
                xq=empty((0, dim)), vq=empty((0, dim)), mq=empty(0), Vq=empty(0),
                sq=empty((0, dim, dim)), fq=empty((0, dim)), momentum_values=empty((n, dim)),
                momentum_fit=empty((0, dim)), no_stress=empty((0, dim, dim)),
                point_velocities=empty((0, dim)))
            if recon.name == "tls":
                fields["factor"] = tls.empty_factor(dim)
                if recon.cell_tables is not None:  # the cells' closed-form integrals
                    fields.update(tables=recon.cell_tables,
                                  cell_shape=(recon.ncx, recon.nbx, recon.degree))
            elif recon.name == "mls":
                fields.update(radius=float(recon.radius), alpha=empty((0, dim + 1)))
                if recon.cell_tables is not None:  # the cells' Gauss sums per axis
                    kg = len(recon.ref)
                    fields.update(tables=recon.cell_tables,
                                  cell_shape=(recon.ncx, recon.nbx, recon.degree),
                                  coef=empty((0, kg, kg, k)), momentum_coef=empty((0, kg, kg, dim)))
            else:  # SplineLeastSquares' data, BandedCholesky's arrays
                ls = recon.spline_ls
                factor = np.zeros((ls.ndofs, band_factor.factor_columns(3 * ls.nbx + 3)))
                fields["spline"] = (ls.axes, int(ls.nbx), int(ls.nby), float(ls.penalty),
                                    np.zeros_like(ls.A), ls.ell_cols, factor)
                if recon.cell_tables is not None:  # closed-form integrals of its cubic fit
                    fields.update(tables=recon.cell_tables,
                                  cell_shape=(recon.ncx, recon.nbx, recon.degree),
                                  coef=empty((0, k)), momentum_coef=empty((0, dim)))
            return self._record("new_rule_reconstruction", "RuleReconstructionType",
                                self.module.RULED_FIELDS, fields)
        fields = dict(
            ref=recon.ref, wref=recon.wref, gap=float(recon.gap), breaks=recon.breaks,
            values=empty((n, k)), rho=empty(n),
            order=empty(n, dtype=np.int64), piece_particles=empty(0, dtype=np.int64),
            piece_points=empty(0, dtype=np.int64), xg=empty(0), fit=empty((0, k)),
            spline_work=empty(spline_1d.spline_work_size(n, k)),
            **self._rule_arrays(n, len(recon.breaks) - 1, len(recon.ref)), xq=empty((0, dim)), vq=empty((0, dim)), mq=empty(0), Vq=empty(0),
            sq=empty((0, dim, dim)), fq=empty((0, dim)), momentum_values=empty((n, dim)),
            momentum_fit=empty((0, dim)), no_stress=empty((0, dim, dim)),
            point_velocities=empty((0, dim)))
        return self._record("new_reconstruction", "ReconstructionType",
                            self.module.RECONSTRUCTION_FIELDS, fields)

    @staticmethod
    def _rule_arrays(n, ncells, k):
        """The 1D spline's rule arrays (compiled_loop_reconstruct's rule_*
        fields) for n particles on ncells cells, k Gauss points a cell."""
        most = gauss_rule.gauss_points_most(n, ncells, k)
        ints, empty = np.int64, np.empty
        return dict(rule_starts=empty(n + 1, dtype=ints), rule_lows=empty(n),
                    rule_highs=empty(n), rule_first=empty(n, dtype=ints),
                    rule_points=empty(n + 1, dtype=ints), rule_xg=empty(most),
                    rule_wg=empty(most), rule_cell=empty(most, dtype=ints))

    def _point_at_transfers(self, dim, degree, window):
        """Compile (or load) the loop, which records the argument types of
        its transfer calls, then compile (or load) this degree's transfer
        kernels for them and set their addresses in the run (0: a transfer
        this scheme's loop does not call)."""
        self._loop.compile((numba.typeof(self.run_state), numba.types.int64))
        kernels = _transfer_kernels(dim, degree, self.parallel, window)
        addresses = []
        for label in ("P2G", "G2P2G", "G2P", "RATES"):
            site = f"{self.module.VARIANT}:{label}"
            if site not in ARGUMENT_TYPES:
                addresses.append(0)
                continue
            if ARGUMENT_TYPES[site] is None:  # (by_symbol.record_argument_types)
                raise RuntimeError(f"the compiled loop's call site {site} was compiled for "
                                   f"two lists of argument types")
            addresses.append(native_address(kernels[label], ARGUMENT_TYPES[site]))
        self.module.set_transfers(self.run_state, *addresses)

    def _mass_system(self, state, k):
        """The consistent-mass data of the run (compiled_loop_mass), sized
        for every dof; the constraint groups as StencilSystem forms them."""
        grid, method, cls = state.grid, state.method, StencilSystem
        dim, nd, p = grid.dim, grid.ndofs, grid.degree
        k._stencil_pattern()  # the stencil's shape
        ns = k._stencil_shape[1]
        nt = k.nthreads
        nbx, nby = (nd, 1) if dim == 1 else tuple(grid.basis_per_axis[:2])
        nbz = nd // (nbx * nby)
        hybrid = method.mass == "hybrid"
        guard = 0.0 if hybrid else method.frequency_guard
        reconstructed = method.reconstruction != "none"
        limit = 0.0
        weights, ratios, moving = np.ones(nd), np.ones(nd), np.ones(nd)
        if guard > 0:
            limit = guard_limit(guard * fast_dof_limit(grid.degree, method.scheme), state.dt,
                                state.wave_speed_now)
            weights, ratios, moving = state.fast_dof_guard_arrays()
        mask = state.constraints.mask
        groups = {}
        for c in range(dim):
            groups.setdefault(mask[:, c].tobytes(), []).append(c)
        G = len(groups)
        group_comps = np.zeros((G, dim), dtype=np.int64)
        for g, comps in enumerate(groups.values()):
            group_comps[g, :len(comps)] = comps
        nc = 2 * dim  # the most columns of a CG run: two problems
        band_max = int(cls.BAND_MAX) if dim == 2 else 0
        boxes = kronecker.MAX_BOXES if dim >= 2 else 1  # (the concatenated factors' rows)
        merged_size = int(cls.MERGE_BUFFER * nd * ns)  # as StencilSystem's
        zeros, empty = np.zeros, np.empty
        fields = dict(
            stencil=zeros((nd, ns)), stiffness=zeros(nd),
            copies=zeros((nt, nd, (ns + 1) // 2)), stiff_copies=zeros((nt, nd)),
            touched=zeros((nt, 2), dtype=np.int64), row_range=np.array([0, nd]),
            axes=tuple(k.args),
            guard=bool(guard > 0), limit=float(limit),
            weights=np.ascontiguousarray(weights, dtype=np.float64),
            mass_ratios=np.ascontiguousarray(ratios, dtype=np.float64),
            moving=np.asarray(moving, dtype=np.float64), covered=np.array(covered_parameters(grid, method.reconstruction), dtype=float),
            guarded=zeros(nd), fast=zeros(nd), near=zeros((2, nd)), diagonal=zeros(nd),
            by_particles=reconstructed and guard > 0,
            coverage_copies=zeros((nt if reconstructed and guard > 0 else 1, 3, nd)),
            coverage_touched=zeros((nt, 2), dtype=np.int64), coverage=zeros((3, nd)),
            coverage_bound=coverage_bound(grid), coverage_x=zeros((1, dim)),
            coverage_m=zeros(1), coverage_reach=zeros(nd), coverage_kept=False,
            guarded_limit=np.nan,
            reach=zeros(nd, dtype=np.bool_),
            group_comps=group_comps,
            group_size=np.array([len(c) for c in groups.values()], dtype=np.int64),
            rows=zeros((G, nd), dtype=np.int64), n_rows=zeros(G, dtype=np.int64),
            index=zeros((G, nd), dtype=np.int64), A=zeros((G, nd, ns)),
            cols=zeros((G, nd, ns), dtype=np.int32),
            # the fixed-column part is read only for nonzero constraint
            # values (prescribed velocities): else never written (np.zeros
            # leaves its pages unmapped)
            F=zeros((G, nd, ns)), fcols=zeros((G, nd, ns), dtype=np.int32),
            inv_diag=zeros((G, nd)),
            Lx=zeros((G, boxes * nbx, p + 1)), Ly=np.ones((G, boxes * nby, p + 1)),
            Lz=np.ones((G, boxes * nbz, p + 1)),
            boxed_rows=zeros((G, nd), dtype=np.int64),
            n_boxed=np.full(G, -1, dtype=np.int64), box_shape=zeros((G, 3), dtype=np.int64),
            box_index=zeros((G, nd), dtype=np.int64),
            box_coords=zeros((G, nd, 3), dtype=np.int64), inv_scale=zeros((G, nd)),
            fit_bands=zeros((3, boxes * max(nbx, nby, nbz), p + 1)),
            fit_sums=zeros((3, boxes * max(nbx, nby, nbz))),
            boxes=zeros((G, kronecker.MAX_BOXES, kronecker.BOX_FIELDS), dtype=np.int64),
            n_boxes=zeros(G, dtype=np.int64), by_component=len(state.bodies) > 1,
            b=empty(nd * nc), x=empty(nd * nc), work=empty(6 * nd * nc),
            box=empty(nbx * nby * nbz * nc), rtol=1e-13,
            max_iterations=int(cls.max_iterations or 0),
            fringe_from=int(cls.FRINGE_FROM), fringe_min_rows=int(cls.FRINGE_MIN_ROWS),
            fringe_layers=int(cls.FRINGE_LAYERS) if dim == 2 else 0,
            fringe_on=zeros(G, dtype=np.bool_), iterations=0,
            # (the factors' room grows as load_fringe needs it)
            fringe_kept=np.full(G, -1, dtype=np.int64),
            fringe_rows=zeros((G, nd if dim == 2 else 1), dtype=np.int64),
            fringe_used=zeros(G, dtype=np.bool_), fringe_sizes=zeros((G, 4), dtype=np.int64),
            fringe_ints=zeros((G, 1), dtype=np.int64), fringe_floats=zeros((G, 1)),
            # (fringe_args: rf, zf, yf, tn with the fringe and near rows <= nd)
            fringe_work=zeros(4 * (nd + 1) * nc if dim == 2 else 1),
            fringe_fresh=np.full((G, len(FRESH_KINDS)), -1, dtype=np.int64),
            fringe_fresh_good=np.full((G, len(FRESH_KINDS)), -1, dtype=np.int64),
            fringe_switch=zeros(G, dtype=np.bool_), fringe_dropped=zeros(G, dtype=np.bool_),
            fringe_slack=int(cls.FRINGE_SLACK),
            cg_log=zeros(self.CG_LOG, dtype=np.int64), cg_logged=-1, cg_logged_good=-1,
            banded_on=zeros(G, dtype=np.bool_), band_max=band_max,
            band_from=int(cls.BAND_FROM), band_width=np.full(G, -1, dtype=np.int64),
            # (np.zeros: only the rows of a group whose factor is on are written)
            band=zeros((G, nd * band_factor.factor_columns(band_max) if band_max > 0 else 1)),
            band_keep=int(cls.BAND_KEEP), band_kept=np.full((G, 2), -1, dtype=np.int64),
            band_rows=zeros((G, nd if band_max > 0 else 1), dtype=np.int64),
            warm=zeros((2, nd, dim)), has_warm=zeros(2, dtype=np.bool_),
            warm_good=zeros((2, nd, dim)), has_good=zeros(2, dtype=np.bool_),
            hybrid=hybrid,
            # the tiny-mass merge: only the rows of small dofs and the
            # merged rows are written (np.zeros leaves the rest unmapped)
            merged=zeros(G, dtype=np.bool_), merge_small=zeros((G, nd), dtype=np.bool_),
            entries=zeros((G, nd), dtype=np.int64),
            row_dof=zeros((G, nd, tiny_mass.MAX_ENTRIES), dtype=np.int64),
            row_weight=zeros((G, nd, tiny_mass.MAX_ENTRIES)), neighbour_max=zeros(nd),
            kept_rows=zeros((G, nd), dtype=np.int64), kept_index=zeros((G, nd), dtype=np.int64),
            merged_A=zeros((G, merged_size)), merged_cols=zeros((G, merged_size), dtype=np.int32),
            merged_F=zeros((G, merged_size)), merged_fcols=zeros((G, merged_size), dtype=np.int32),
            merged_inv_diag=zeros((G, nd)), merged_fit=zeros(nd * ns),
            merged_sizes=zeros((G, 3), dtype=np.int64), merge_at=zeros(len(StepLoop.MERGE_CONSISTENT), dtype=np.int64))
        rk4 = method.scheme == "rk4"
        for name in ("stencil", "fast"):
            own = fields[name]
            fields[f"reaction_{name}"] = np.zeros(own.shape) if rk4 else own
        self._groups = G
        return self._record("new_mass_system", "MassSystemType", self.module.MASS_FIELDS, fields)

    def _record(self, new, type_class, names, fields):
        """The record the module's constructor ``new`` builds of ``fields``
        (in the order ``names``); on a run that is only typed, its numba
        type instead: ``type_class`` of the fields' argument types (a
        field that is such a type stands for its record), the type ``new``
        would return, without compiling ``new`` (nor the structref's
        constructor, whose code unboxes every field)."""
        values = [fields[name] for name in names]
        if not self._typed_only:
            return getattr(self.module, new)(*values)
        return getattr(self.module, type_class)([
            (name, value if isinstance(value, numba.types.Type) else
             numba.typeof(value, Purpose.argument)) for name, value in zip(names, values)])

    def _row_by_row(self, state, n):
        """Up to n more adaptive steps under tables of t alone (a body
        force, a side traction; not prescribed velocities, which read dt):
        each next row evaluated at the time the loop reached, without
        handing the particles back between (the forces read only the
        reference configuration); returns the steps taken."""
        mod, run = self.module, self.run_state
        taken = 0
        while taken < n:
            t, step, stop, handover = mod.clock(run)
            state.t, state.step = t, step  # the tables' time (run() sets both after)
            if stop or handover or state.done:
                break
            rows = n - taken
            for table in self.tables:
                rows = table.cover(state, rows)
            if rows == 0:  # an effect's function raised: the executor takes the step
                break
            done = self._loop(run, rows)
            taken += done
            if done < rows:
                break
        return taken

    WARM_KINDS = ("acceleration", "velocity")
    # StencilSystem.iteration_log: the mass system logs up to CG_LOG CG runs
    # a call, each step at most RUNS_PER_STEP per group (rk4: four stages of
    # two solves)
    CG_LOG = 4096
    RUNS_PER_STEP = 8
    # the phases of run.phase_ns (compiled_loop_ops)
    PHASES = ("p2g", "solve", "g2p", "mass_matrix", "reconstruct", "constitutive", "effects")

    def _load_warm(self, state):
        """The run starts its CG runs from the state's warm starts, with its
        band factors and fringe corrections."""
        cm = self.cm
        nd, dim = self.executor.kernels.ndofs, state.grid.dim
        warm = np.zeros((2, nd, dim))
        has = np.zeros(2, dtype=np.bool_)
        for i, kind in enumerate(self.WARM_KINDS):
            prev = state.warm.get(kind)
            if prev is not None and prev.shape == (nd, dim):
                warm[i], has[i] = prev, True
        G = self._groups
        banded = np.array([f"banded{g}_on" in state.warm for g in range(G)], dtype=np.bool_)
        fringe_on = np.array([StencilSystem.FRINGE_FROM <= 0 or f"fringe{g}_on" in state.warm
                              for g in range(G)], dtype=np.bool_)
        fresh = np.full((G, len(FRESH_KINDS)), -1, dtype=np.int64)
        for g in range(G):
            for i, kinds in enumerate(FRESH_KINDS):
                first = state.warm.get(f"fringe{g}_fresh_{kinds}")
                if first is not None:
                    fresh[g, i] = int(first[0])
        factors = [self._fringe_factor(state, g) if fringe_on[g] else None for g in range(G)]
        keep = np.array([f is not None and self._fringe_loaded.get(g) is f
                         for g, f in enumerate(factors)], dtype=np.bool_)
        self.module.load_warm(cm, warm, has, banded, fringe_on, fresh, keep,
                              StencilSystem.iteration_log is not None)
        for g, factor in enumerate(factors):
            if factor is None:
                self._fringe_loaded.pop(g, None)
            elif not keep[g]:
                self._load_fringe(g, factor)
        for g in range(G):  # the kept band factors (StencilSystem._band)
            rows, factor = state.warm.get(f"band{g}_rows"), state.warm.get(f"band{g}_factor")
            if rows is not None and factor is not None and factor.ndim == 2 \
                    and band_factor.factor_layout_ok(factor):
                self.module.load_band(cm, g, np.ascontiguousarray(rows, dtype=np.int64),
                                      np.ascontiguousarray(factor, dtype=np.float64))

    def _fringe_factor(self, state, g):
        """The executor's fringe factor of group g that its next step would
        use (StencilSystem._fringe: the pattern of the free rows, the factor
        of the warm data's block, kept on the kernels), its pattern when
        the free rows have no fringe, or None (the loop's first step with
        the correction on then stops: the executor makes it)."""
        pattern = self.executor.kernels.__dict__.get("fringe_patterns", {}).get(g)
        if pattern is None or pattern.layers != StencilSystem.FRINGE_LAYERS:
            return None
        if not pattern.fringe.size:
            return pattern
        rows, block = state.warm.get(f"fringe{g}_rows"), state.warm.get(f"fringe{g}_block")
        factor = pattern.factor
        if rows is None or factor is None or factor.data is not block \
                or pattern.key != np.ascontiguousarray(rows, dtype=np.int64).tobytes():
            return None
        return factor

    def _load_fringe(self, g, factor):
        """Load group g's fringe factor (a FringeFactor, or a pattern
        without fringe rows) into the run."""
        if isinstance(factor, FringePattern):
            pattern, arrays = factor, factor.arrays() + NO_FACTOR
        else:
            pattern, arrays = factor.pattern, factor.arrays()
        rows = np.frombuffer(pattern.key, dtype=np.int64)
        load = self.module.load_fringe
        first = not load.signatures  # (compiled at a first need: compile time)
        start, cpu_start = time.perf_counter(), time.process_time()
        load(self.cm, g, rows, *(np.ascontiguousarray(a) for a in arrays))
        if first:
            self.compile_seconds += time.perf_counter() - start
            self.compile_cpu_seconds += time.process_time() - cpu_start
        self._fringe_loaded[g] = factor

    def _mass_results(self, state, handover):
        """The warm starts of the last step taken into the state (new
        arrays: warm data may be shared with a checkpoint), the fringe
        switch, and the reactions of consistent mass (M a - f on the
        constrained rows)."""
        run = self.run_state
        warm, has, fringe_on, stencil, fast, banded, kept, band_rows, band, fresh, dropped, \
            log, logged = self.module.mass_records(self.cm)
        if StencilSystem.iteration_log is not None:  # (the runs of the steps taken)
            StencilSystem.iteration_log.extend(log[:logged].tolist())
        for i, kind in enumerate(self.WARM_KINDS):
            if has[i]:
                state.warm[kind] = warm[i].copy()
        for g in np.flatnonzero(banded):
            state.warm[f"banded{g}_on"] = np.array([1])
        for g in range(self._groups):  # the kept band factors (StencilSystem._band)
            n, w = (int(v) for v in kept[g])
            if n >= 0:
                state.warm[f"band{g}_rows"] = band_rows[g, :n].copy()
                wf = band_factor.factor_columns(w)
                state.warm[f"band{g}_factor"] = band[g, :n * wf].reshape(n, wf).copy()
            else:
                state.warm.pop(f"band{g}_rows", None)
                state.warm.pop(f"band{g}_factor", None)
        for g in range(self._groups):  # the fringe factors' first iterations
            for i, kinds in enumerate(FRESH_KINDS):
                key = f"fringe{g}_fresh_{kinds}"
                if fresh[g, i] >= 0 and (key not in state.warm or
                                         state.warm[key][0] != fresh[g, i]):
                    state.warm[key] = np.array([fresh[g, i]])
        if handover:  # the fringe correction turned on, or a factor dropped
            for g in np.flatnonzero(fringe_on):
                state.warm[f"fringe{g}_on"] = np.array([1])
            for g in np.flatnonzero(dropped):  # (StencilSystem._keep_fringe)
                state.warm.pop(f"fringe{g}_rows", None)
            self._executor_next = True
        c = state.constraints
        if c.any:
            mass, a, force = self.module.grid_arrays(run)
            if state.method.mass == "hybrid":
                state.defer_reactions(c, mass, a, force, None)  # gravity is in the force
            else:  # evaluated at the next save (copies: the next call writes the run's)
                k = self.executor.kernels
                stencil, fast, mass, a, force = (v.copy() for v in (stencil, fast, mass, a, force))
                state.defer_reaction_rule(lambda: c.reactions(stencil_residual(
                    stencil, k.stencil_geometry, c.mask, mass <= 0, fast, a, force,
                    parallel=k.parallel)))

    def compile(self):
        """Compile (or load from numba's cache) everything ``run`` calls."""
        if self.cm is not None:
            nd, dim = self.executor.kernels.ndofs, self._arrays[0].shape[1]
            self.module.load_band(self.cm, 0, np.zeros(0, dtype=np.int64), np.zeros((0, 1)))
            G = self._groups
            self.module.load_warm(self.cm, np.zeros((2, nd, dim)), np.zeros(2, dtype=np.bool_),
                                  np.zeros(G, dtype=np.bool_), np.zeros(G, dtype=np.bool_),
                                  np.full((G, len(FRESH_KINDS)), -1, dtype=np.int64),
                                  np.zeros(G, dtype=np.bool_), False)
            self.module.mass_records(self.cm)
        for table in self.tables:
            table.compile()
        self.module.load_state(self.run_state, *self._arrays, 0.0, 0, 0.0)
        if not self.fused:
            F, packed = self.module.law_state(self.run_state)
            self.module.load_law_state(self.run_state, F.copy(), np.ones(self._arrays[3].shape),
                                       packed.copy())
        self.module.set_work(self.run_state, 0.0)
        self.module.taken_step(self.run_state)
        self.module.clock(self.run_state)
        self.module.set_reconstruction_factor(self.run_state, 1.0)
        self.module.reset_step_records(self.run_state)
        self._loop(self.run_state, 0)
        self.module.current(self.run_state)
        self.module.grid_arrays(self.run_state)
        self.module.records(self.run_state)
        if self.force_rules is not None:
            self.module.rule_log(self.force_rules)
            self.module.reset_rule_log(self.force_rules)

    # With parallel kernels a call of the loop lasts about this long, so
    # that the thread policy (solve/threads.py), which acts between calls,
    # still follows the machine's load (a serial loop runs to the next save).
    CALL_SECONDS = 0.05

    def run(self, state, n):
        """Up to ``n`` steps from ``state`` (its particles, t and step);
        the state is updated with those taken, which are returned. A step
        that met tiny-mass dofs before the merge kernels were compiled
        (STOP_MERGE_KERNELS) compiles them (their time goes to
        ``compile_seconds``) and the loop goes on from that step."""
        taken = self._run(state, n)
        if taken < n and self._stop == STOP_MERGE_KERNELS:
            self._compile_merge()
            taken += self._run(state, n - taken)
        return taken

    compile_seconds = 0.0
    """Seconds spent compiling during ``run`` (the merge kernels at their
    first need): simulate counts them as compile time, not run time."""
    compile_cpu_seconds = 0.0
    """The CPU seconds of the same (``Result.cpu_time`` leaves them out)."""

    MERGE_CONSISTENT = ("NEIGHBOUR_MAXIMA", "MERGING_ROWS", "MERGED_SYSTEM", "MERGED_PROBLEM",
                        "MERGED_EXPAND", "MERGED_PCG")  # MassSystem.merge_at's order

    def _merge_address(self, label):
        """The merge kernel ``label`` compiled (or loaded) for the argument
        types its call site was compiled with (0: a site this run's
        functions do not hold)."""
        kernel, restype = MERGE_KERNELS[label]
        if label != "MERGED_SOLVE":  # (as the executor calls them)
            kernel = for_threads(kernel, self.parallel)
        site = f"{self.module.VARIANT}:{label}"
        if site not in ARGUMENT_TYPES:
            return 0
        if ARGUMENT_TYPES[site] is None:
            raise RuntimeError(f"the compiled loop's call site {site} was compiled for two "
                               f"lists of argument types")
        return native_address(kernel, ARGUMENT_TYPES[site], getattr(numba.types, restype))

    def _compile_merge(self):
        """Compile the tiny-mass merge kernels and point the run at them."""
        start, cpu_start = time.perf_counter(), time.process_time()
        mod = self.module
        mod.set_merged_solve(self.run_state, self._merge_address("MERGED_SOLVE"))
        if self.cm is not None:
            mod.set_merge_at(self.cm, np.array([self._merge_address(label)
                                                for label in self.MERGE_CONSISTENT],
                                               dtype=np.int64))
        self.compile_seconds += time.perf_counter() - start
        self.compile_cpu_seconds += time.process_time() - cpu_start

    _stop = 0

    def _run(self, state, n):
        """``run`` without the compile at the first tiny-mass step."""
        self._stop = 0
        if self.retired:
            return 0
        if self._executor_next:  # it makes a fringe factor the loop then uses
            self._executor_next = False
            return 0
        if self.parallel:
            n = min(n, self._steps_per_call)
        if self.cm is not None and StencilSystem.iteration_log is not None:
            n = min(n, self.CG_LOG // (self.RUNS_PER_STEP * self._groups))  # room in the log
        p = state.particles
        if p.n != self._arrays[0].shape[0]:  # particles were removed
            return 0
        mod, run = self.module, self.run_state
        wanted = n
        for table in self.tables:  # the steps their tables hold (a body force: a chunk)
            n = table.cover(state, n)
        if self.refactored:  # up to the next re-estimate, which Python makes
            n = min(n, RECONSTRUCTION_EVERY - state.step % RECONSTRUCTION_EVERY)
            mod.set_reconstruction_factor(run, float(state.step_reconstruction_factor()))
        if n == 0:  # an effect's function raised: the executor takes the step
            return 0
        if self.force_rules is not None:  # (their log's rows)
            n = min(n, self.RULE_LOG_STEPS)
            self._load_rule_states()
        consistent = self.cm is not None
        if consistent:
            self._load_warm(state)
        if self._loaded is not p:
            c = np.ascontiguousarray  # (load_state copies flat: no copy when already so)
            mod.load_state(run, c(p.x), c(p.v), c(p.u), c(p.V), c(p.stress), float(state.t),
                           int(state.step), float(state.external_work))
            if not self.fused:
                self._load_law_state(p)
        else:
            mod.set_work(run, float(state.external_work))
        mod.reset_step_records(run)
        start = time.perf_counter()
        taken = self._loop(run, n)
        if taken == n and self.row_by_row:
            taken += self._row_by_row(state, wanted - taken)
        self._stop = int(mod.clock(run)[2])
        if self._stop == STOP_FRINGE_FACTOR and taken:  # (not the partial step again first)
            self._executor_next = True
        if taken:
            per_step = (time.perf_counter() - start) / taken
            self._steps_per_call = max(1, int(self.CALL_SECONDS / max(per_step, 1e-9)))
        if taken == 0:
            self._loaded = p
            return 0
        x, v, u, V, stress, t, step, work, acc = mod.current(run)
        state.particles = p.replaced(x=x, v=v, u=u, V=V, stress=stress, **self._law_results(p))
        self._loaded = state.particles
        state.t, state.step = t, step
        state.external_work = work
        if self.adaptive:  # the step size of the last step taken (State.next_step_size's)
            state.dt, state.dt_crit, state.wave_speed_now = mod.taken_step(run).tolist()
        if self.scheme == "cd":
            state.particle_acceleration = acc.copy()
        phase_ns, small_max, handover = mod.records(run)
        if consistent:
            self._mass_results(state, handover)
        elif state.constraints.any:
            mass, a, force = mod.grid_arrays(run)
            gravity = self.executor.gravity if self.executor.gravity_work else None
            if self.force_rules is not None:  # modify_force put it into the force
                gravity = None
            state.defer_reactions(state.constraints, mass, a, force, gravity)
        if self.force_rules is not None:  # the walls' reactions, the footings' records
            self._rule_results(taken)
        for phase, ns in zip(self.PHASES, phase_ns.tolist()):
            if ns:
                state.timer.add(phase, ns * 1e-9)
        state.small_dofs_max = max(state.small_dofs_max, int(small_max))
        state.loop_steps = getattr(state, "loop_steps", 0) + taken
        return taken
