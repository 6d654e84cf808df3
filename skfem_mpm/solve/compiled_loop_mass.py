"""Consistent (and hybrid) mass on a compiled run: part of the source of the
generated loop modules (not imported as a module; see
:mod:`skfem_mpm.solve.compiled_loop_ops`).

The same equations, kernels and order of operations as the compiled
executor's :class:`~skfem_mpm.solve.stencil_system.StencilSystem` with the
Kronecker preconditioner, so that a run gives the same bits on either path:

    assemble        M (stencil rows) and the fast-dof guard's stiffness
                    weights K_k = sum_p m_p |grad N_k(x_p)|^2 (kernel pair
                    consistent_1d, consistent_2d or, 3D, consistent_axes;
                    + reduce_stencil)
    cover           with a reconstruction (and the guard on) the particles'
                    own sums K_k, M_kk, m_k of the fast-dof guard
                    (Kernels.particle_coverage: kernels.mpm.particle_coverage
                    and reduce_coverage), kept from the last pass while
                    kernels.coverage_skip.coverage_holds shows that they
                    give the lumping of new ones; without one the
                    assembly's K, the stencil's diagonal and the lumped
                    mass are those sums
    prepare         the fast-row lumping fractions theta_k of
                    :func:`skfem_mpm.solve.timestep.lumping_fraction` of the
                    guard's stiffness
                    :func:`skfem_mpm.solve.timestep.covered_stiffness`
                    (hybrid mass: no guard, theta = 0); for each constraint
                    pattern ("group") its free dofs (not constrained, with
                    mass), their rows in ELL form (compact_system), and the
                    Kronecker preconditioner fitted to those rows
                    (:func:`skfem_mpm.kernels.kronecker.fit_kronecker`, as
                    KroneckerData.of_system: banded Cholesky factors of the
                    rows' axis marginals on the free dofs' index box, whose
                    numbering is kept while the free-dof set stays; three
                    factors in 3D, KRONECKER_ARGS of the generated prelude
                    giving ell_pcg apply_kronecker_axes' arguments);
                    with tiny-mass dofs (``small_tol`` > 0) a group with
                    small dofs is merged (StencilSystem's merge: the rows
                    of T, :func:`skfem_mpm.kernels.tiny_mass.merging_rows`,
                    and the system T^T M' T on its kept free dofs,
                    :mod:`skfem_mpm.kernels.merged_mass`), the
                    preconditioner fitted to that system's stencil part;
                    a group whose band factor is on (StencilSystem.BAND_FROM)
                    and whose system is narrow enough gets the band
                    factor of its rows instead (kernels.band_factor),
                    kept over the steps while its free rows stay and CG
                    needs at most StencilSystem.BAND_KEEP iterations with it
                    in 3D one Kronecker box per coupled component of the
                    fitted rows (kernels.kronecker.kronecker_boxes), in 2D
                    the same when there are two or more (else the one box
                    of the free rows), as KroneckerData.of_system builds
                    them
    mass_solve      M x = rhs on the free dofs (constrained dofs their
                    prescribed values, or 0; massless dofs 0: the fixed
                    columns' known values moved to the right-hand side
                    when any is nonzero), one or two right-hand sides in
                    one CG run (ell_pcg), warm started from the last
                    solution of the same kind (0 acceleration, 1 velocity);
                    a merged group restricts the right-hand sides and
                    prolongs the solution to its small dofs (x = T x_r)

The fringe correction of the preconditioner (kernels.fringe): a group of
at least ``fringe_min_rows`` free dofs whose Kronecker-preconditioned CG
needed ``fringe_from`` iterations turns it on for the rest of the run (as
StencilSystem does). Its SuperLU factors are made by the executor
(StencilSystem._fringe, SciPy) and loaded into the run (``load_fringe``:
the factor of the warm data's block, made for the free rows
``fringe_rows``); a step applies them in its CG (ell_pcg's fringe branch,
the executor's kernel) while its free rows are those rows. A step whose
free rows differ, or that finds no factor loaded, stops before it writes
anything (stop 7: the executor takes it and factorises anew); a step that
turns the correction on, or whose CG needed more than FRINGE_SLACK
iterations beyond the first run with the factor on the same right-hand
sides (``fringe_fresh``, StencilSystem._keep_fringe: the factor is
dropped), ends the call after it is taken (``handover``): the executor
takes the next step and makes the factor.
"""


@structref.register
class MassSystemType(types.StructRef):
    def preprocess_fields(self, fields):
        return tuple((name, types.unliteral(t)) for name, t in fields)


MassSystemType.__name__ = MassSystemType.__qualname__ = f"MassSystemType_{VARIANT}"
globals()[MassSystemType.__name__] = MassSystemType


MASS_FIELDS = (
    # assembly: the stencil (dofs, (2p + 1)^dim), K, per-thread copies, the
    # rows the last assembly touched, the axes' (breakpoints, uniform, 1/h,
    # extraction)
    "stencil", "stiffness", "copies", "stiff_copies", "touched", "row_range", "axes",
    # fast-dof guard: on?, its limit, covered_stiffness' w, mu, the moving
    # dofs (1.0 / 0.0), timestep.covered_parameters (lo, hi, tail, floor),
    # the guard's stiffness, the lumping fractions, the stencil's diagonal
    # (its M_kk without a reconstruction); with a reconstruction (by_particles)
    # the particles' sums (K, M_kk, m: Kernels.particle_coverage), their
    # per-thread copies and touched ranges; covered_stiffness' work (2, dofs);
    # the rows the lumping changes (kernels.mpm.lumped_reach); the skip of
    # the particles' pass (kernels.coverage_skip): timestep.coverage_bound,
    # the last pass's positions, masses and reach W_k, whether they are set;
    # the limit the guard's stiffness of those sums was computed at (NaN:
    # not computed since the last pass)
    "guard", "limit", "weights", "mass_ratios", "moving", "covered", "guarded", "fast", "near",
    "diagonal", "by_particles", "coverage", "coverage_copies", "coverage_touched", "reach",
    "coverage_bound", "coverage_x", "coverage_m", "coverage_reach", "coverage_kept",
    "guarded_limit",
    # groups: their components, the free rows and dof -> row, the ELL rows
    "group_comps", "group_size", "rows", "n_rows", "index", "A", "cols", "F", "fcols",
    "inv_diag",
    # Kronecker preconditioner per group: factors (1 / L_ii in column 0;
    # an axis the box spans with one index is not applied), the rows the
    # box was built for, box shape (nz, ny, nx), box index and box-local
    # (a, b, c) per row, scaling; fit_kronecker's work space
    "Lx", "Ly", "Lz", "boxed_rows", "n_boxed", "box_shape", "box_index", "box_coords",
    "inv_scale", "fit_bands", "fit_sums",
    # the band factor per group (kernels.band_factor): switched on (for the
    # rest of the run), the largest band it takes (0: never), the
    # iterations that switch it on, this step's band (-1: the Kronecker
    # preconditioner), the factor (flat, rows x (band + 1)); the kept
    # factor (StencilSystem.BAND_KEEP): the most iterations it may need,
    # its rows' count and band (count -1: none kept) and its rows
    "banded_on", "band_max", "band_from", "band_width", "band", "band_keep", "band_kept",
    "band_rows",
    # 3D: one box per coupled component (kernels.kronecker.kronecker_boxes):
    # the boxes' rows of apply_kronecker_axes and their count; box_shape
    # the concatenated factors' lengths, box_coords the rows' coordinates
    # in them, box_index their entries in the work space (-1: diagonal)
    # 2D: whether to search the coupled components (several bodies:
    # StencilSystem's by_component)
    "boxes", "n_boxes", "by_component",
    # conjugate gradients: right-hand sides, solutions, work space (flat)
    "b", "x", "work", "box", "rtol", "max_iterations", "fringe_from", "fringe_min_rows",
    "fringe_layers", "fringe_on", "iterations",
    # the fringe correction per group (kernels.fringe, FringeFactor.args):
    # the rows its factor was made for (count, -1: none loaded) and their
    # list, this step uses it, the sizes (fringe, near rows, L's and U's
    # entries) and the factor packed (ints: fringe, its row pointers and
    # entries, near, theirs, Lp, Li, Up, Ui, perm_r, perm_c; floats: Lx,
    # Ux, 1 / U_jj), its work space
    # (flat); the iterations of the first CG run with the factor per kind
    # of right-hand sides (FRESH_KINDS' order, -1: none yet) and those of
    # the last step taken; the groups that switched this step (turned on
    # or dropped the factor) and those that dropped it
    "fringe_kept", "fringe_rows", "fringe_used", "fringe_sizes", "fringe_ints",
    "fringe_floats", "fringe_work", "fringe_fresh", "fringe_fresh_good", "fringe_switch",
    "fringe_dropped", "fringe_slack",
    # StencilSystem.iteration_log: each CG run's iterations, how many were
    # logged (-1: no log) and how many by the last step taken
    "cg_log", "cg_logged", "cg_logged_good",
    # warm starts: [0] acceleration, [1] velocity; those of the last step
    # taken (a step that stops hands its own start to the executor)
    "warm", "has_warm", "warm_good", "has_good",
    # hybrid mass: the acceleration is solved with the lumped mass
    "hybrid",
    # the tiny-mass merge per group (kernels.tiny_mass, kernels.merged_mass):
    # merged this step?, the rows of T (small dofs, entries, dofs,
    # weights), the neighbours' largest masses, the kept free dofs and dof
    # -> kept row, the merged rows (packed: entries, columns; constrained
    # columns: entries, dofs; flat, StencilSystem.MERGE_BUFFER dofs x
    # stencil), 1 / T^T m,
    # the stencil-slot rows the preconditioner is fitted to, (rows, W, WF)
    "merged", "merge_small", "entries", "row_dof", "row_weight", "neighbour_max", "kept_rows",
    "kept_index", "merged_A", "merged_cols", "merged_F", "merged_fcols", "merged_inv_diag",
    "merged_fit", "merged_sizes",
    # the native entry points of the merge kernels (neighbour_maxima,
    # merging_rows, merged_system, merged_problem, merged_expand and, in 1D,
    # ell_pcg: there only a merged group runs CG), 0 until a step needs them
    # (prepare_mass returns 6)
    "merge_at",
    # the stencil and lumping fractions of the last step's reactions: the
    # step's own, or with rk4 copies of its first stage's
    "reaction_stencil", "reaction_fast",
)


class MassSystem(structref.StructRefProxy):
    """The consistent-mass data of a compiled run."""

    def __new__(cls, *fields):
        return structref.StructRefProxy.__new__(cls, *fields)


structref.define_proxy(MassSystem, MassSystemType, list(MASS_FIELDS))


@njit(cache=True)
def new_mass_system(*fields):
    """A MassSystem with ``fields`` in the order of MASS_FIELDS."""
    return MassSystem(*fields)


@njit(cache=True)
def load_warm(cm, warm, has_warm, banded_on, fringe_on, fringe_fresh, fringe_keep, log):
    """Set the warm starts, the band factor's and the fringe correction's
    switches and the fringe factors' first iterations (the executor's,
    when it took steps between calls); no band factor kept (see
    load_band), the loaded fringe factors kept where ``fringe_keep`` (see
    load_fringe); an empty CG log when ``log``, else none."""
    copy_into(cm.banded_on, banded_on)
    cm.band_kept[:, 0] = -1
    copy_into(cm.warm, warm)
    copy_into(cm.has_warm, has_warm)
    copy_into(cm.warm_good, warm)
    copy_into(cm.has_good, has_warm)
    copy_into(cm.fringe_on, fringe_on)
    copy_into(cm.fringe_fresh, fringe_fresh)
    copy_into(cm.fringe_fresh_good, fringe_fresh)
    for g in range(fringe_keep.shape[0]):
        if not fringe_keep[g]:
            cm.fringe_kept[g] = -1
    cm.fringe_switch[:] = False
    cm.fringe_dropped[:] = False
    cm.cg_logged = 0 if log else -1
    cm.cg_logged_good = cm.cg_logged


@njit(cache=True)
def load_band(cm, g, rows, factor):
    """Group g's kept band factor (the executor's, when it took steps
    between calls): ``factor`` (rows x (band + 1)) made for the free
    ``rows``."""
    n, w1 = factor.shape
    cm.band_kept[g, 0] = n
    cm.band_kept[g, 1] = factor_band(w1)
    copy_into(cm.band_rows[g, :n], rows)
    copy_into(cm.band[g, :n * w1], factor.reshape(n * w1))


@njit(cache=True)
def load_fringe(cm, g, rows, fringe, fringe_ptr, fringe_entries, near, near_ptr, near_entries,
                Lp, Li, Lx, Up, Ui, Ux, inv_udiag, perm_r, perm_c):
    """Group g's fringe factor (the executor's FringeFactor.arrays: its
    pattern's fringe and near rows with their entries by rows, SuperLU's L
    and U by rows, 1 / U_jj, the permutations) made for the free ``rows``;
    no fringe (empty ``fringe``, fringe.NO_FACTOR): the Kronecker step
    alone on those rows."""
    n = rows.shape[0]
    nf, nn, nl, nu = fringe.shape[0], near.shape[0], Li.shape[0], Ui.shape[0]
    cm.fringe_kept[g] = n
    copy_into(cm.fringe_rows[g, :n], rows)
    cm.fringe_sizes[g, 0] = nf
    cm.fringe_sizes[g, 1] = nn
    cm.fringe_sizes[g, 2] = nl
    cm.fringe_sizes[g, 3] = nu
    ints_parts = (fringe, fringe_ptr, fringe_entries.reshape(fringe_entries.size), near,
                  near_ptr, near_entries.reshape(near_entries.size), Lp, Li, Up, Ui, perm_r,
                  perm_c)
    ni = 0
    for part in ints_parts:
        ni += part.size
    nx = nl + nu + nf
    G = cm.fringe_kept.shape[0]
    if ni > cm.fringe_ints.shape[1]:  # room for this factor (the others' kept)
        ints = np.zeros((G, ni), dtype=np.int64)
        for h in range(G):
            copy_into(ints[h, :cm.fringe_ints.shape[1]], cm.fringe_ints[h])
        cm.fringe_ints = ints
    if nx > cm.fringe_floats.shape[1]:
        floats = np.zeros((G, nx))
        for h in range(G):
            copy_into(floats[h, :cm.fringe_floats.shape[1]], cm.fringe_floats[h])
        cm.fringe_floats = floats
    ints = cm.fringe_ints[g]
    o = 0
    for part in ints_parts:
        copy_into(ints[o:o + part.size], part)
        o += part.size
    floats = cm.fringe_floats[g]
    o = 0
    for part in (Lx, Ux, inv_udiag):
        copy_into(floats[o:o + part.size], part)
        o += part.size


@njit(cache=True)
def fringe_args(cm, g, nc):
    """Group g's fringe factor for nc columns as ell_pcg takes it
    (FringeFactor.args: the factor's arrays and the work space); the
    entries' counts are the row pointers' last."""
    nf, nn, nl, nu = (cm.fringe_sizes[g, 0], cm.fringe_sizes[g, 1], cm.fringe_sizes[g, 2],
                      cm.fringe_sizes[g, 3])
    ints = cm.fringe_ints[g]
    fringe = ints[:nf]
    o = nf
    fringe_ptr = ints[o:o + nf + 1]
    o += nf + 1
    ef = fringe_ptr[nf]
    fringe_entries = ints[o:o + 2 * ef].reshape((ef, 2))
    o += 2 * ef
    near = ints[o:o + nn]
    o += nn
    near_ptr = ints[o:o + nn + 1]
    o += nn + 1
    en = near_ptr[nn]
    near_entries = ints[o:o + 2 * en].reshape((en, 2))
    o += 2 * en
    Lp = ints[o:o + nf + 1]
    o += nf + 1
    Li = ints[o:o + nl]
    o += nl
    Up = ints[o:o + nf + 1]
    o += nf + 1
    Ui = ints[o:o + nu]
    o += nu
    perm_r = ints[o:o + nf]
    o += nf
    perm_c = ints[o:o + nf]
    floats = cm.fringe_floats[g]
    Lx = floats[:nl]
    Ux = floats[nl:nl + nu]
    inv_udiag = floats[nl + nu:nl + nu + nf]
    work = cm.fringe_work
    h = (nc + 1) // 2
    rf = work[:nf * nc].reshape((nf, nc))
    o = nf * nc
    zf = work[o:o + nf * nc].reshape((nf, nc))
    o += nf * nc
    yf = work[o:o + 2 * nf * h].reshape((2, nf, h))
    o += 2 * nf * h
    tn = work[o:o + nn * nc].reshape((nn, nc))
    return (fringe, fringe_ptr, fringe_entries, near, near_ptr, near_entries, Lp, Li, Lx, Up,
            Ui, Ux, inv_udiag, perm_r, perm_c, rf, zf, yf, tn)


@njit(cache=True)
def commit_mass(cm):
    """The step is taken: its warm starts and the fringe factors' first
    iterations are the good ones; True when a group turned the fringe
    correction on or dropped its factor (the executor takes the next
    step)."""
    copy_into(cm.warm_good, cm.warm)
    copy_into(cm.has_good, cm.has_warm)
    copy_into(cm.fringe_fresh_good, cm.fringe_fresh)
    cm.cg_logged_good = cm.cg_logged
    switched = False
    for g in range(cm.fringe_switch.shape[0]):
        switched = switched or cm.fringe_switch[g]
    return switched


@njit(cache=True)
def mass_records(cm):
    """The warm starts of the last step taken, the groups whose fringe
    correction is on, the stencil and lumping fractions of the last
    step's reactions, the groups whose band factor is on, the kept band
    factors (their rows' count and band, rows and factors), the fringe
    factors' first iterations, the groups that dropped theirs (at a
    handover), the CG log and how many runs of the steps taken it holds."""
    return (cm.warm_good, cm.has_good, cm.fringe_on, cm.reaction_stencil, cm.reaction_fast,
            cm.banded_on, cm.band_kept, cm.band_rows, cm.band, cm.fringe_fresh_good,
            cm.fringe_dropped, cm.cg_log, cm.cg_logged_good)


@njit(cache=True)
def set_merge_at(cm, addresses):
    """Point the mass system at the compiled merge kernels."""
    copy_into(cm.merge_at, addresses)


@njit(cache=True)
def keep_stage_mass(cm):
    """rk4: the first stage's stencil and lumping fractions, for the reactions."""
    copy_into(cm.reaction_stencil, cm.stencil)
    copy_into(cm.reaction_fast, cm.fast)


@njit(cache=True)
def assemble_mass(cm, x, m, p, nbx, nby, dim):
    """The consistent mass stencil and K of the particles (Kernels.consistent_stencil)."""
    ASSEMBLE(x, m, cm.axes, p, nbx, nby, cm.copies, cm.stiff_copies, cm.touched)
    _reduce_mass(cm, p, nbx, nby, dim)


@njit(cache=True)
def cover_particles(cm, x, m, p, nbx, nby):
    """The particles' own sums of the fast-dof guard (Kernels.particle_coverage),
    kept from the last pass while kernels.coverage_skip.coverage_holds shows
    that they give the lumping of new ones."""
    if cm.coverage_kept and COVERAGE_HOLDS(x, m, cm.coverage_x, cm.coverage_m, cm.coverage,
                                           cm.coverage_reach, cm.coverage_bound, cm.weights,
                                           cm.mass_ratios, cm.moving, cm.covered[0],
                                           cm.covered[1], cm.covered[2], cm.covered[3],
                                           cm.limit):
        return
    COVERAGE(x, m, cm.axes, p, nbx, nby, cm.coverage_copies, cm.coverage_touched)
    REDUCE_COVERAGE(cm.coverage_copies, cm.coverage_touched, cm.coverage)
    cm.guarded_limit = np.nan  # prepare_mass computes the guard's stiffness of the new sums
    # worth keeping only if the new sums' own ratios stay below the threshold
    # (coverage_holds at zero displacement, reach = D: see Kernels.particle_coverage)
    if not COVERAGE_HOLDS(x, m, x, m, cm.coverage, cm.coverage[1], cm.coverage_bound, cm.weights,
                          cm.mass_ratios, cm.moving, cm.covered[0], cm.covered[1],
                          cm.covered[2], cm.covered[3], cm.limit):
        cm.coverage_kept = False
        return
    REACH(x, m, cm.axes, p, nbx, nby, cm.coverage_bound[0], cm.coverage_reach)
    if cm.coverage_x.shape[0] != x.shape[0]:
        cm.coverage_x = np.empty((x.shape[0], x.shape[1]))
        cm.coverage_m = np.empty(x.shape[0])
    copy_into(cm.coverage_x, x)
    copy_into(cm.coverage_m, m)
    cm.coverage_kept = True


@njit(cache=True)
def assemble_mass_cells(cm, x, m, cells, k, p, nbx, nby):
    """2D: the consistent mass stencil and K of points whose first ``cells``
    blocks of k x k are whole cells' tensor Gauss rules
    (Kernels.consistent_stencil with cells, k: kernels.mpm.consistent_cells_2d)."""
    ASSEMBLE_CELLS(x, m, cm.axes, cells, k, p, nbx, cm.copies, cm.stiff_copies, cm.touched)
    _reduce_mass(cm, p, nbx, nby, 2)


@njit(cache=True, inline="always")
def _reduce_mass(cm, p, nbx, nby, dim):
    """The stencil and K from the per-thread copies (Kernels.consistent_stencil)."""
    lo = cm.touched[0, 0]
    hi = cm.touched[0, 1]
    for t in range(1, cm.touched.shape[0]):
        lo = min(lo, cm.touched[t, 0])
        hi = max(hi, cm.touched[t, 1])
    if hi <= lo:  # no particles
        lo = 0
        hi = 0
    was_lo = cm.row_range[0]
    was_hi = cm.row_range[1]
    # rows outside the touched union are zero: clear those that held entries
    for a, b in ((was_lo, min(lo, was_hi)), (max(hi, was_lo), was_hi)):
        for k in range(a, b):
            cm.stencil[k, :] = 0.0
            cm.stiffness[k] = 0.0
    cm.row_range[0] = lo
    cm.row_range[1] = hi
    REDUCE_STENCIL(cm.copies, cm.stiff_copies, cm.touched, lo, hi, p, nbx, nby, dim,
                   cm.stencil, cm.stiffness)


@njit(cache=True)
def _kronecker_box(cm, g, rows, nbx, nby):
    """Group g's index box and box numbering (KroneckerData._box: dof k =
    (c nby + b) nbx + a; 1D and 2D have c = 0), unless they were built for
    the same rows."""
    n = rows.shape[0]
    boxed = cm.boxed_rows[g]
    if cm.n_boxed[g] == n:
        same = True
        for r in range(n):
            if boxed[r] != rows[r]:
                same = False
                break
        if same:
            return
    a0 = b0 = c0 = 1 << 62
    a1 = b1 = c1 = 0
    for r in range(n):
        a = rows[r] % nbx
        b = (rows[r] // nbx) % nby
        c = rows[r] // (nbx * nby)
        a0 = min(a0, a)
        a1 = max(a1, a + 1)
        b0 = min(b0, b)
        b1 = max(b1, b + 1)
        c0 = min(c0, c)
        c1 = max(c1, c + 1)
    box_index = cm.box_index[g]
    box_coords = cm.box_coords[g]
    for r in range(n):
        a = rows[r] % nbx - a0
        b = (rows[r] // nbx) % nby - b0
        c = rows[r] // (nbx * nby) - c0
        box_index[r] = (c * (b1 - b0) + b) * (a1 - a0) + a
        box_coords[r, 0] = a
        box_coords[r, 1] = b
        box_coords[r, 2] = c
        boxed[r] = rows[r]
    cm.n_boxed[g] = n
    cm.box_shape[g, 0] = c1 - c0
    cm.box_shape[g, 1] = b1 - b0
    cm.box_shape[g, 2] = a1 - a0


@njit(cache=True)
def prepare_mass(cm, mass, mask, p, nbx, nby, dim, fixed_columns, small_tol):
    """The step's fast-row fractions, free-dof groups, ELL rows and
    preconditioner (see the module); with ``fixed_columns`` (prescribed
    velocities) also the rows' fixed-column part; with ``small_tol`` > 0
    (tiny-mass dofs) the merge of each group. Returns 0, or 4 when a merged
    row outgrew the kernels' lists (the executor's general grid system
    takes the step), 6 when the merge kernels are not compiled yet
    (``cm.merge_at``: StepLoop.run compiles them and takes the step again),
    7 when a group with the fringe correction on has no factor loaded for
    its free rows (the executor takes the step and factorises)."""
    stencil = cm.stencil
    nd, ns = stencil.shape
    if cm.guard:  # the guard's stiffness (timestep.covered_stiffness), then theta
        if cm.by_particles:  # the particles' sums (cover_particles)
            # a function of those sums and the limit alone: kept while the
            # sums are (cover_particles' skip) at the same limit
            if not cm.guarded_limit == cm.limit:
                COVERED_STIFFNESS(cm.coverage[0], cm.coverage[1], cm.coverage[2], cm.weights,
                                  cm.mass_ratios, cm.moving, cm.covered[0], cm.covered[1],
                                  cm.covered[2], cm.covered[3], cm.limit, p, nbx, nby, cm.near,
                                  cm.guarded)
                cm.guarded_limit = cm.limit
            FAST_ROW_FRACTIONS(cm.guarded, cm.coverage[1], mass, cm.limit, cm.fast)
        else:  # K, the stencil's diagonal and the lumped mass are the particles' own
            centre = (ns - 1) // 2
            for k in range(nd):
                cm.diagonal[k] = stencil[k, centre]
            COVERED_STIFFNESS(cm.stiffness, cm.diagonal, mass, cm.weights, cm.mass_ratios,
                              cm.moving, cm.covered[0], cm.covered[1], cm.covered[2],
                              cm.covered[3], cm.limit, p, nbx, nby, cm.near, cm.guarded)
            FAST_ROW_FRACTIONS(cm.guarded, cm.diagonal, mass, cm.limit, cm.fast)
    else:
        cm.fast[:] = 0.0
    LUMPED_REACH(cm.fast, p, nbx, nby, dim, ns, cm.reach)
    nbz = nd // (nbx * nby)
    at = cm.merge_at
    if small_tol > 0.0:
        if at[0] == 0:
            return 6
        NEIGHBOUR_MAXIMA(at[0], mass, nbx, nby, nbz, p, cm.neighbour_max)
    for g in range(cm.group_size.shape[0]):
        c0 = cm.group_comps[g, 0]
        merged = False
        if small_tol > 0.0:
            count = MERGING_ROWS(at[1], mass, cm.neighbour_max, mask, c0, nbx, nby, nbz, p,
                                 small_tol, cm.merge_small[g], cm.entries[g], cm.row_dof[g],
                                 cm.row_weight[g])
            if count < 0:
                return 4
            merged = count > 0
        cm.merged[g] = merged
        n = 0
        group_rows = cm.rows[g]  # (each field read of a structref costs a reference count)
        group_index = cm.index[g]
        same = True  # the free rows of the last step: cols holds their columns
        for k in range(nd):
            if not mask[k, c0] and mass[k] > 0.0:
                if group_rows[n] != k:
                    same = False
                group_rows[n] = k
                group_index[k] = n
                n += 1
            else:
                group_index[k] = -1
        same = same and cm.n_rows[g] == n
        cm.n_rows[g] = n
        rows = cm.rows[g, :n]
        COMPACT_SYSTEM(stencil, p, nbx, nby, dim, rows, cm.index[g], cm.fast, cm.reach,
                       cm.A[g, :n], cm.cols[g, :n], cm.F[g, :n], cm.fcols[g, :n],
                       not same,
                       fixed_columns or merged)
        fit = cm.A[g, :n]
        if merged:  # T^T M' T on the kept free dofs
            n = MERGED_SYSTEM(at[2], cm.A[g, :n], cm.cols[g, :n], cm.F[g, :n], cm.fcols[g, :n],
                              rows, cm.index[g], mask, c0, mass, cm.merge_small[g],
                              cm.entries[g], cm.row_dof[g], cm.row_weight[g], p, nbx, nby, dim,
                              cm.kept_rows[g], cm.kept_index[g], cm.merged_inv_diag[g],
                              cm.merged_fit, cm.merged_A[g], cm.merged_cols[g], cm.merged_F[g],
                              cm.merged_fcols[g], cm.merged_sizes[g])
            if n < 0:
                return 4
            rows = cm.kept_rows[g, :n]
            fit = cm.merged_fit[:n * ns].reshape((n, ns))
        else:
            _inverse_masses(cm.inv_diag[g], mass, rows)
        cm.band_width[g] = -1
        cm.fringe_used[g] = False
        if n == 0:
            continue
        if DIM == 3:  # a box per coupled component, built each step (they follow A)
            cm.n_boxes[g] = KRONECKER_BOXES(fit, rows, cm.kept_index[g] if merged else
                                            cm.index[g], p, nbx, nby, nd, cm.box_coords[g, :n],
                                            cm.box_index[g, :n], cm.boxes[g], cm.box_shape[g])
        else:
            if cm.banded_on[g] and not merged:
                if _kept_band(cm, g, rows):
                    cm.band_width[g] = cm.band_kept[g, 1]
                    continue
                cm.band_kept[g, 0] = -1
                w = ELL_BAND_WIDTH(cm.cols[g, :n])
                wf = factor_columns(w)
                if w <= cm.band_max and FIT_BAND_FACTOR(cm.A[g, :n], cm.cols[g, :n],
                                                        cm.band[g, :n * wf].reshape((n, wf))):
                    cm.band_width[g] = w
                    cm.band_kept[g, 0] = n
                    cm.band_kept[g, 1] = w
                    copy_into(cm.band_rows[g, :n], rows)
                    continue
            # the fringe correction (StencilSystem._compact: on the one box)
            fringe = cm.fringe_layers > 0 and cm.fringe_on[g] and not merged
            if fringe:
                if not _kept_fringe(cm, g, rows):
                    return 7
                cm.fringe_used[g] = cm.fringe_sizes[g, 0] > 0
            if DIM == 2 and cm.by_component and not fringe:  # a box per coupled component
                cm.n_boxes[g] = KRONECKER_BOXES(fit, rows, cm.kept_index[g] if merged else
                                                cm.index[g], p, nbx, nby, nd,
                                                cm.box_coords[g, :n], cm.box_index[g, :n],
                                                cm.boxes[g], cm.box_shape[g])
                cm.n_boxed[g] = -1  # (the one box's numbering was written over)
            if cm.n_boxes[g] <= 1:
                _kronecker_box(cm, g, rows, nbx, nby)
        nz = cm.box_shape[g, 0]
        ny = cm.box_shape[g, 1]
        nx = cm.box_shape[g, 2]
        FIT_KRONECKER(fit, cm.box_coords[g, :n], cm.Lx[g, :nx], cm.Ly[g, :ny], cm.Lz[g, :nz],
                      cm.inv_scale[g, :n], cm.fit_bands, cm.fit_sums)
    return 0


@njit(cache=True)
def _inverse_masses(inv_diag, mass, rows):
    """inv_diag[r] = 1 / mass[rows[r]], the lumped preconditioner's (a
    function of its own: written in prepare_mass's loop over the groups,
    numba counted references to two arrays at every row)."""
    for r in range(rows.shape[0]):
        inv_diag[r] = 1.0 / mass[rows[r]]


@njit(cache=True)
def _kept_band(cm, g, rows):
    """Whether group g keeps a band factor made for the free ``rows``
    within the band limit (StencilSystem._band)."""
    return cm.band_kept[g, 1] <= cm.band_max and _same_rows(cm.band_rows[g], cm.band_kept[g, 0],
                                                            rows)


@njit(cache=True)
def _kept_fringe(cm, g, rows):
    """Whether group g has a fringe factor loaded for the free ``rows``
    (StencilSystem._fringe keeps the warm data's block while they stay)."""
    return _same_rows(cm.fringe_rows[g], cm.fringe_kept[g], rows)


@njit(cache=True, inline="always")
def _same_rows(kept, count, rows):
    """Whether the first ``count`` entries of ``kept`` are ``rows``."""
    n = rows.shape[0]
    if count != n:
        return False
    for r in range(n):
        if kept[r] != rows[r]:
            return False
    return True


@njit(cache=True)
def _nonzero(values):
    """Whether any entry of ``values`` is nonzero."""
    flat = values.reshape(values.size)
    for i in range(flat.size):
        if flat[i] != 0.0:
            return True
    return False


@njit(cache=True)
def mass_solve(cm, nt, count, rhs0, kind0, values0, has0, out0, rhs1, kind1, values1, has1,
               out1):
    """M x = rhs for ``count`` (1 or 2) problems (rhs, warm-start kind,
    constraint values and whether there are any, out) in one CG run per
    group, constrained dofs their values (or 0), massless dofs 0; each
    solution is kept as its kind's next warm start (StencilSystem.solve_many:
    the fixed columns move to the right-hand side when a problem's values
    are not all 0). Returns False when CG stopped above its tolerance (the
    executor then takes the step and raises)."""
    has0 = has0 and _nonzero(values0)
    has1 = count == 2 and has1 and _nonzero(values1)
    if has0:
        copy_into(out0, values0)
    else:
        out0[:] = 0.0
    if has1:
        copy_into(out1, values1)
    elif count == 2:
        out1[:] = 0.0
    for g in range(cm.group_size.shape[0]):
        merged = cm.merged[g]
        n = cm.merged_sizes[g, 0] if merged else cm.n_rows[g]
        if n == 0 and not merged:
            continue
        ncomp = cm.group_size[g]
        comps = cm.group_comps[g, :ncomp]
        nc = count * ncomp
        b = cm.b[:n * nc].reshape((n, nc))
        x = cm.x[:n * nc].reshape((n, nc))
        if merged:  # the merged system (see prepare_mass)
            W = cm.merged_sizes[g, 1]
            WF = cm.merged_sizes[g, 2]
            rows = cm.kept_rows[g, :n]
            A = cm.merged_A[g, :n * W].reshape((n, W))
            cols = cm.merged_cols[g, :n * W].reshape((n, W))
            F = cm.merged_F[g, :n * WF].reshape((n, WF))
            fcols = cm.merged_fcols[g, :n * WF].reshape((n, WF))
            inv_diag = cm.merged_inv_diag[g, :n]
            small = cm.merge_small[g]
            MERGED_PROBLEM(cm.merge_at[3], rows, cm.kept_index[g], small, cm.entries[g],
                           cm.row_dof[g], cm.row_weight[g], rhs0, values0, has0,
                           cm.warm[kind0] if cm.has_warm[kind0] else rhs0, cm.has_warm[kind0],
                           comps, 0, F, fcols, b, x)
            if count == 2:
                MERGED_PROBLEM(cm.merge_at[3], rows, cm.kept_index[g], small, cm.entries[g],
                               cm.row_dof[g], cm.row_weight[g], rhs1, values1, has1,
                               cm.warm[kind1] if cm.has_warm[kind1] else rhs1,
                               cm.has_warm[kind1], comps, ncomp, F, fcols, b, x)
        else:
            rows = cm.rows[g, :n]
            A = cm.A[g, :n]
            cols = cm.cols[g, :n]
            F = cm.F[g, :n]
            fcols = cm.fcols[g, :n]
            inv_diag = cm.inv_diag[g, :n]
            COMPACT_PROBLEM(rows, rhs0, values0, has0,
                            cm.warm[kind0] if cm.has_warm[kind0] else rhs0,
                            cm.has_warm[kind0], comps, 0, F, fcols, b, x)
            if count == 2:
                COMPACT_PROBLEM(rows, rhs1, values1, has1,
                                cm.warm[kind1] if cm.has_warm[kind1] else rhs1,
                                cm.has_warm[kind1], comps, ncomp, F, fcols, b, x)
        kinds = kind0 if count == 1 else 2 + 2 * kind0 + kind1  # (FRESH_KINDS)
        if n > 0 and not _solve_group(cm, g, n, nt, nc, ncomp, A, cols, inv_diag, b, x,
                                      kinds):
            return False
        if merged:
            MERGED_EXPAND(cm.merge_at[4], rows, cm.merge_small[g], cm.entries[g], cm.row_dof[g],
                          cm.row_weight[g], x, comps, 0, out0)
            if count == 2:
                MERGED_EXPAND(cm.merge_at[4], rows, cm.merge_small[g], cm.entries[g],
                              cm.row_dof[g], cm.row_weight[g], x, comps, ncomp, out1)
        else:
            EXPAND_PROBLEM(rows, x, comps, 0, out0)
            if count == 2:
                EXPAND_PROBLEM(rows, x, comps, ncomp, out1)
    copy_into(cm.warm[kind0], out0)
    cm.has_warm[kind0] = True
    if count == 2:
        copy_into(cm.warm[kind1], out1)
        cm.has_warm[kind1] = True
    return True


@njit(cache=True)
def _solve_group(cm, g, n, nt, nc, ncomp, A, cols, inv_diag, b, x, kinds):
    """Group g's CG run on its n rows A, cols (ell_pcg with the group's
    Kronecker preconditioner, with the fringe correction where it is used;
    inv_diag the lumped one's) on right-hand sides of ``kinds`` (the index
    of their names in FRESH_KINDS): False when it stopped above its
    tolerance; switches the band factor and the fringe correction as
    StencilSystem.solve_many does."""
    fringe = cm.fringe_used[g]
    if DIM == 1 and not cm.merged[g]:  # P = A: no CG, none of its work arrays
        its = KRONECKER_DIRECT(cm, g, n, nc, nt, b, x)
    else:
        problem = np.empty(nc, dtype=np.int64)
        for j in range(nc):
            problem[j] = j // ncomp
        limit = cm.max_iterations if cm.max_iterations > 0 else 10 * n + 100
        work = cm.work[:6 * n * nc].reshape((6, n, nc))
        its = KRONECKER_PCG(cm, g, n, nc, nt, A, cols, inv_diag, b, x, problem, limit, work)
    if its < 0:
        return False
    cm.iterations += its
    if 0 <= cm.cg_logged < cm.cg_log.shape[0]:  # (StepLoop.run leaves room)
        cm.cg_log[cm.cg_logged] = its
        cm.cg_logged += 1
    if cm.band_width[g] < 0 and not cm.merged[g] and not fringe and cm.band_max > 0 \
            and its >= cm.band_from and ELL_BAND_WIDTH(cols) <= cm.band_max:
        cm.banded_on[g] = True
    elif cm.band_width[g] >= 0 and its > cm.band_keep:
        cm.band_kept[g, 0] = -1  # the next step factorises anew
    elif cm.fringe_layers > 0 and not fringe and not cm.fringe_on[g] \
            and its >= cm.fringe_from and n >= cm.fringe_min_rows:
        cm.fringe_on[g] = True
        cm.fringe_switch[g] = True
    if fringe:  # StencilSystem._keep_fringe
        fresh = cm.fringe_fresh[g, kinds]
        if fresh < 0:
            cm.fringe_fresh[g, kinds] = its
        elif its > fresh + cm.fringe_slack:
            cm.fringe_dropped[g] = True
            cm.fringe_switch[g] = True
    return True


@njit(cache=True)
def mass_units(run):
    """Never called: compiling it for a run's type compiles (or loads) the
    consistent-mass solve its loop calls by symbol, mass_solve (with
    ell_pcg in 2D and 3D; in 1D ell_pcg runs only on a merged group and
    compiles with the merge kernels), by the very call of the scheme operations (see
    compiled_loop.precompile_mass), and first the step's preparation of
    the system, prepare_mass: the loop's own compilation reaches it only
    after the particles-to-grid pass it calls before (the consistent
    stencil, the guard's particle sums, with a reconstruction its fit),
    so the second process has compiled it by then."""
    run.prepare_grid()
    run.mass_solve(2, run.force, 0, run.a, run.momentum, 1, run.v_old)


@njit(cache=True)
def shift_warm(cm, kind, dt, a):
    """warm[kind] += dt a when there is one (StencilSystem.shift_guess)."""
    if cm.has_warm[kind]:
        w = cm.warm[kind]
        for k in range(w.shape[0]):
            for c in range(w.shape[1]):
                w[k, c] = w[k, c] + dt * a[k, c]
