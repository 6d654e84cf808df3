"""Compile (or load from numba's cache) the kernels a grid will use, on a
tiny input, so that timed runs exclude JIT compilation."""
import numpy as np

__all__ = ["warm_up_kernels"]


def warm_up_kernels(grid, fast=False, materials=(), method=None, parallel=True,
                    grid_rules=False, merge=True):
    """Compile on a small grid of the same dimension and degree (the machine
    code does not depend on the grid's size, and no grid-sized buffer is
    allocated); with ``fast``, also the constitutive kernel and the point
    laws of ``materials`` that have one: the parallel kernels, or with
    ``parallel`` False their serial copies (what a run below
    :data:`~skfem_mpm.kernels.serial.SERIAL_BELOW` particles calls). With a
    ``method``, only what its run calls: the consistent-mass assembly and
    CG (the largest share of the compile time) only for consistent or
    hybrid mass, the MUSL re-projection only for MUSL, the one-pass USL grid
    step only for USL and CD, the g2p kernel for every scheme but RK4, whose
    stage rates and combination only it, the tiny-mass scan only when the
    merge is on (and its lumped merge unless ``merge`` is False: a run on
    the compiled loop, which compiles its merge at its first step with
    tiny-mass dofs), the grid modifiers' rules (damping, walls) only with
    ``grid_rules``."""
    if not hasattr(grid, "breakpoints"):
        return
    from ..spline import SplineGrid

    cells = 2 * grid.degree + 2  # interior and boundary cells both occur
    unit = ((0.0, 1.0),) * grid.dim  # the same dimension: 3D kernels for a 3D grid
    grid = (SplineGrid.line(0.0, 1.0, cells, grid.degree) if grid.dim == 1
            else SplineGrid.rectangle(*unit, cells, grid.degree) if grid.dim == 2
            else SplineGrid.box(*unit, cells, grid.degree))
    x = np.array([b[0] + 0.5 * (b[1] - b[0]) for b in grid.bounds])[None, :]
    from ..kernels.weights import SERIAL_BELOW

    for axis in range(grid.dim):  # the serial and (parallel) the threaded evaluation
        for n in (1, SERIAL_BELOW) if parallel else (1,):
            grid.axis_functions(axis, np.repeat(x[:, axis], n), backend="numba")
    if not fast:
        return
    from ..kernels.mpm import Kernels
    from ..materials import LinearElastic
    from ..particles import Particles

    k = Kernels(grid, parallel)
    p = Particles(x.copy(), np.ones(1), np.ones(1))
    new = p.copy()
    dim = grid.dim
    zeros = np.zeros((grid.ndofs, dim))
    material = LinearElastic(1.0, 0.0)
    def needs(what):
        if method is None:
            return True
        return {"consistent": method.needs_consistent_mass,  # hybrid: velocity solves
                "musl": method.scheme == "musl",
                "usl_grid": method.scheme in ("usl", "cd"),
                "g2p": method.scheme != "rk4",
                "rk4": method.scheme == "rk4",
                "small_mass": method.small_mass > 0}[what]

    for fext in (None, np.zeros((1, dim))):
        k.p2g(p, fext)
    if needs("musl"):
        k.g2p2g(p, zeros, 0.0, new.v)
    for fused in (True, False):
        L = np.empty((1, dim, dim)) if not fused else np.empty((1, 1, 1))
        if needs("g2p"):
            for flip in (True, False):
                for acc in (None, np.empty((1, dim))):
                    k.g2p(p, zeros, zeros, 0.0, 1.0, flip, fused, material, new, L, acc)
        if needs("rk4"):
            k.rates(p, zeros, zeros, fused, material, new.v, new.u, np.empty((1, dim, dim)),
                    np.empty((1, dim, dim)), np.empty(1))
    if needs("rk4"):
        from ..kernels.staging import combine_stages

        rates = [np.zeros((4,) + a.shape) for a in (p.x, p.v, p.stress, p.V, p.stress)]
        k.kernel(combine_stages)(np.zeros(4), p.x, p.u, p.v, p.stress, p.V, p.stress, *rates, True,
                       True, new.x, new.u, new.v, new.stress, new.V, new.stress.copy(),
                       k.nthreads)
    if needs("small_mass"):
        k.small_mass(np.ones(grid.ndofs), 1e-3)
    if needs("small_mass") and merge:
        for values in (None, zeros):
            k.merged_solve(np.ones(grid.ndofs), zeros, np.zeros(dim),
                           np.zeros((grid.ndofs, dim), dtype=bool), values, 1e-3,
                           np.empty((grid.ndofs, dim)))
    k.gravity_work(np.ones(grid.ndofs), zeros, 0.0, np.zeros(grid.dim))
    if needs("consistent"):
        _warm_up_consistent(k, p, grid)
    mask = np.zeros((grid.ndofs, dim), dtype=bool)
    out = np.empty((grid.ndofs, dim))
    for values in (None, zeros):
        k.solve(np.ones(grid.ndofs), zeros, np.zeros(dim), mask, values, out)
        if needs("usl_grid"):
            k.usl_grid(np.ones(grid.ndofs), zeros, zeros, np.zeros(dim), mask, values, values,
                       0.0, out, zeros.copy())
    _warm_up_point_laws(k, grid.dim, materials)
    if grid_rules:
        _warm_up_grid_rules(grid.ndofs, dim)
    if method is None or method.reconstruction != "none":
        _warm_up_reconstruction(grid, method)


def _warm_up_consistent(k, p, grid):
    """The consistent-mass assembly, the stencil CG and its residual."""
    from ..kernels.mpm import fast_row_fractions
    from .grid_system import Constraints
    from .stencil_system import StencilSystem

    dim = grid.dim
    k.stencil_csr(k.consistent_stencil(p)[0])
    st, K = k.consistent_stencil(p)
    for fringe_from in ((StencilSystem.FRINGE_FROM, 0) if dim == 2 else (StencilSystem.FRINGE_FROM,)):
        # the Kronecker CG, and in 2D the one with the fringe correction (a
        # run switches it on after FRINGE_FROM iterations)
        system = StencilSystem(k, st + np.eye(1, st.shape[1], (st.shape[1] - 1) // 2),
                               np.ones(grid.ndofs), Constraints(grid, []),
                               np.zeros(grid.ndofs), {})
        system.FRINGE_FROM = fringe_from
        system.solve(np.ones((grid.ndofs, dim)), np.zeros((grid.ndofs, dim)), "velocity")
    system.residual(np.ones((grid.ndofs, dim)), np.ones((grid.ndofs, dim)))
    k.kernel(fast_row_fractions)(K, np.ones(grid.ndofs), np.ones(grid.ndofs), 1.0,
                                 np.empty(grid.ndofs))


def _warm_up_grid_rules(ndofs, dim):
    """The grid modifiers' kernels (kernels.grid_modifiers), with no rule."""
    from ..kernels.grid_modifiers import modify_forces, modify_velocities, pack_rules

    codes, parameters, offsets, dofs, reactions, data_offsets, data, states = pack_rules([], dim)
    zeros = np.zeros((ndofs, dim))
    modify_forces(codes, parameters, offsets, dofs, zeros, zeros.copy(), np.ones(ndofs), 0.1,
                  0.0, 0.0, reactions, data_offsets, data, states)
    modify_velocities(codes, parameters, offsets, dofs, zeros, np.ones(ndofs), data_offsets,
                      data, states)


def _warm_up_reconstruction(grid, method):
    """The Gauss rule and the reconstruction the compiled executor runs."""
    from .compiled_reconstruct import unsupported

    if grid.dim != 1 or (method is not None and unsupported(method, grid.dim) is not None):
        return
    from ..kernels.gauss_rule import gauss_rule_1d
    from ..kernels.spline_1d import not_a_knot_spline

    x = np.linspace(0.1, 0.9, 5)
    rule = gauss_rule_1d(x, np.full(5, 0.1), 1.0, grid.breakpoints[0], x[:2], x[:2])
    not_a_knot_spline(x, np.ones((5, 2)), rule[0], rule[1], rule[2], rule[3],
                      np.empty((rule[3].size, 2)))


def _warm_up_point_laws(k, dim, materials):
    """Compile (or load) the constitutive kernel and each material's point
    law on one particle."""
    from numba import get_num_threads

    from ..kernels.constitutive import material_update
    from ..materials import LinearElastic
    from ..materials.state import state_layout

    if len(materials) == 1 and type(materials[0]) is LinearElastic:
        return  # fused into the transfer kernels: the constitutive kernel never runs
    one = np.zeros((1, dim, dim))
    for material in materials:
        if material.point_update is None:
            continue
        finite = bool(material.finite_strain)
        F = np.broadcast_to(np.eye(dim), (1, dim, dim)).copy()
        layout = state_layout(material, dim)
        state = layout.pack(layout.initial_arrays(1)) if layout else np.zeros((1, 0))
        k.kernel(material_update)(material.point_update.address(), material.point_parameters(dim),
                        np.zeros(0, dtype=np.int64), True, one, 0.0, finite, one.copy(), F,
                        np.ones(1), np.ones(1), state, one.copy(), F.copy(), np.ones(1),
                        state.copy(), np.full(get_num_threads(), -1, dtype=np.int64))
        if material.cell_average:  # B-bar's pass before the point law
            from ..kernels.bbar import average_dilatation
            from ..kernels.records import grid_record

            x = np.array([[b[0] for b in k.grid.bounds]])
            per = (1 << dim) if material.vertices else 1
            average_dilatation(grid_record(k.grid)[0], np.zeros(0, dtype=np.int64), True,
                               material.vertices, x, np.ones(1), one.copy(),
                               np.zeros(material.functions), np.zeros(material.functions),
                               np.zeros((1, per), dtype=np.int64), np.zeros((1, per)))
