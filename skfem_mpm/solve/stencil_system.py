"""Consistent-mass solves on the spline grid's fixed stencil, compiled
(the compiled executor's mass system; :mod:`skfem_mpm.solve.compiled`).

The preconditioner of its conjugate gradients is chosen for a block of
code by :func:`preconditioned_with` (benchmarks compare the variants);
outside such a block it is the default, the Kronecker preconditioner with
the fringe correction.
"""
from contextlib import contextmanager

import numpy as np

from ..errors import InvalidState
from ..kernels.band_factor import (ell_band_width, factor_columns, factor_layout_ok,
                                   fit_band_factor)
from ..kernels.fringe import FringeFactor, FringePattern
from ..kernels.kronecker import KroneckerData, apply_kronecker, fit_kronecker
from ..kernels.merged_mass import EXTRA, merged_expand, merged_problem, merged_system
from ..kernels.mpm import (compact_problem, compact_system, ell_pcg, expand_problem,
                           lumped_reach, stencil_rows_product)
from ..kernels.serial import for_threads
from ..kernels.tiny_mass import MAX_ENTRIES, merging_rows, neighbour_maxima
from ..validation import check_choice
from .grid_system import shift_guess

__all__ = ["PRECONDITIONERS", "StencilSystem", "preconditioned_with", "stencil_residual"]

PRECONDITIONERS = ("kronecker+fringe", "kronecker", "lumped")
"""The stencil CG's preconditioners (see :func:`preconditioned_with`)."""


class StencilSystem:
    """Consistent-mass solves on the grid's fixed stencil, compiled.

    Same equations as :class:`~skfem_mpm.solve.grid_system.GridSystem`:
    the fast-dof rows are lumped, constrained and massless dofs keep their
    known values (moved to the right-hand side), and conjugate gradients
    preconditioned with the lumped mass, warm started from the previous
    step, solve all components (and several right-hand sides, see
    :meth:`solve_many`) at once. Only the free dofs enter the iteration:
    for each constraint pattern a kernel copies their rows of the stencil
    into a compact row-by-row (ELL) matrix. The preconditioner is the
    Kronecker one of :mod:`skfem_mpm.kernels.kronecker` with the factors
    fitted to that matrix each step (:func:`~skfem_mpm.kernels.kronecker.fit_kronecker`;
    ``"kronecker"``, default; in 3D one box per coupled component of the
    matrix, :func:`~skfem_mpm.kernels.kronecker.kronecker_boxes`), with the
    fringe correction of :mod:`skfem_mpm.kernels.fringe`
    on ``FRINGE_LAYERS`` layers of the free-dof set's edge (2D) once the
    Kronecker step alone has needed ``FRINGE_FROM`` iterations (0 layers:
    never), or the inverse lumped mass (``"lumped"``). On a 2D grid a
    group whose Kronecker-preconditioned CG needed ``BAND_FROM``
    iterations and whose system is banded within ``BAND_MAX`` switches, for
    the rest of the run, to the banded Cholesky factor of its system
    (:mod:`skfem_mpm.kernels.band_factor`; 0: never), kept over the steps
    while its free-dof set stays and CG needs at most ``BAND_KEEP``
    iterations with it. In 1D the Kronecker factor is the banded Cholesky
    factor of the free-dof matrix A itself (the marginal of A on its one
    axis is A: P = A up to round-off, for any particles and lumped rows),
    so a group that is not merged is solved directly, x = P^-1 b (one
    application, counted as one iteration), and its warm start is not
    read: the solution is A^-1 b to round-off (a backward-stable Cholesky
    solve of a mass matrix), within the CG tolerance of any warm start.

    Tiny masses (``small_mass`` > 0, the relative threshold of
    ``Method(small_mass=...)``): each constraint pattern with small dofs
    solves the merged system T^T M' T of :mod:`skfem_mpm.kernels.merged_mass`
    on its kept free dofs (the merge of :mod:`skfem_mpm.kernels.tiny_mass`,
    GridSystem's rule), with the Kronecker preconditioner fitted to its
    stencil part and no fringe correction; ``mergeable`` is False when a
    merged row outgrew the kernels' lists (the caller then takes
    GridSystem's sparse solve).
    """

    preconditioner = "kronecker"
    # the merged system's buffers (its packed rows, its constrained
    # columns) hold MERGE_BUFFER x dofs x stencil entries each: room for
    # rows EXTRA stencils longer than the stencil (kernels.merged_mass); a
    # merge that needs more takes GridSystem's sparse solve. The compiled
    # loop sizes its buffers by it too, so both paths decide alike.
    MERGE_BUFFER = 1 + EXTRA
    FRINGE_LAYERS = 3
    max_iterations = None  # per CG run; None: 10 x the free dofs + 100
    iteration_log = None  # a list: each CG run appends its iterations (benchmarks)

    def __init__(self, kernels, stencil, lumped, constraints, fast, warm, rtol=1e-13,
                 small_mass=0.0, by_component=False):
        self.k = kernels
        self.by_component = by_component
        self.geometry = kernels.stencil_geometry
        self.stencil = stencil
        self.constraints = constraints
        self.warm = warm
        self.rtol = rtol
        self.small_dofs = 0
        self.lumped = lumped
        self.inactive = lumped <= 0
        self.fast = np.ascontiguousarray(fast, dtype=np.float64)
        # the rows the fast-row lumping changes, for every group
        self.near = np.empty(lumped.size, dtype=np.bool_)
        lumped_reach(self.fast, *self.geometry, stencil.shape[1], self.near)
        mask = constraints.mask
        # what depends only on the free-dof sets is kept on the kernels
        # between steps (it changes only when particles enter or leave a
        # support or the constraints change)
        self.memo = kernels.__dict__.setdefault("stencil_memo", {})
        key = mask.tobytes() + self.inactive.tobytes()
        kept = self.memo.get("groups")
        if kept is None or kept[0] != key:
            groups = {}  # constraint pattern -> (components, free rows, dof -> row)
            for c in range(mask.shape[1]):
                pattern = mask[:, c].tobytes()
                if pattern not in groups:
                    rows = np.flatnonzero(~(mask[:, c] | self.inactive))
                    index = np.full(lumped.size, -1, dtype=np.int64)
                    index[rows] = np.arange(rows.size)
                    groups[pattern] = ([], rows, index)
                groups[pattern][0].append(c)
            reaction_rows = np.flatnonzero(np.logical_or.reduce(list(mask.T)))  # 20x any(axis=1)
            kept = self.memo["groups"] = (key, groups, reaction_rows)
        # [components, free rows, dof -> row, the built system, the merge or None]
        self.groups = {pattern: [comps, rows, index, None, None]
                       for pattern, (comps, rows, index) in kept[1].items()}
        self.reaction_rows = kept[2]
        self._stale_fringe = {}
        self.iterations = 0
        self.mergeable = small_mass <= 0 or self._merge(small_mass)

    def _merge(self, tol):
        """The tiny-mass merge of each group (the rows of T, kernels.tiny_mass)
        and, for a group with small dofs, its merged system; False when a
        merged row outgrew the kernels' lists."""
        k, p = self.k, self.geometry[0]
        nbx, nby, nbz = k.axes_shape
        nd = self.lumped.size
        neighbour_max = k.scratch("neighbour_max", nd)
        k.kernel(neighbour_maxima)(self.lumped, nbx, nby, nbz, p, neighbour_max)
        for g, group in enumerate(self.groups.values()):
            merge = _Merge(k, g, nd)
            count = k.kernel(merging_rows)(self.lumped, neighbour_max, self.constraints.mask,
                                           group[0][0], nbx, nby, nbz, p, tol, merge.small,
                                           merge.entries, merge.row_dof, merge.row_weight)
            if count < 0:
                return False
            if count == 0:
                continue
            self.small_dofs = max(self.small_dofs, count)
            group[4] = merge
            if not self._merged_system(g, group):
                return False
        return True

    def _merged_system(self, g, group):
        """Group g's merged system (kernels.merged_mass) from its free rows
        with their fixed columns; False when a row outgrew the lists."""
        comps, rows, index, _, merge = group
        k = self.k
        nd, ns = self.stencil.shape
        A, F = k.scratch(f"A{g}", (rows.size, ns)), k.scratch(f"F{g}", (rows.size, ns))
        cols = k.scratch(f"cols{g}", (rows.size, ns), np.int32)
        fcols = k.scratch(f"fcols{g}", (rows.size, ns), np.int32)
        k.kernel(compact_system)(self.stencil, *self.geometry, rows, index, self.fast,
                                 self.near, A, cols, F, fcols, True, True)
        self.memo[f"cols{g}"] = rows.tobytes()
        size = int(self.MERGE_BUFFER * nd * ns)
        Ar, Fr = k.scratch(f"merged_A{g}", size), k.scratch(f"merged_F{g}", size)
        colsr = k.scratch(f"merged_cols{g}", size, np.int32)
        fcolsr = k.scratch(f"merged_fcols{g}", size, np.int32)
        inv_diag = k.scratch(f"merged_inv_diag{g}", nd)
        fit = k.scratch("merged_fit", nd * ns)
        sizes = k.scratch("merged_sizes", 3, np.int64)
        n = k.kernel(merged_system)(A, cols, F, fcols, rows, index, self.constraints.mask,
                                    comps[0], self.lumped, merge.small, merge.entries,
                                    merge.row_dof, merge.row_weight, *self.geometry,
                                    merge.kept_rows, merge.kept_index, inv_diag, fit, Ar, colsr,
                                    Fr, fcolsr, sizes)
        if n < 0:
            return False
        n, W, WF = (int(v) for v in sizes)
        merge.kept = merge.kept_rows[:n]
        kron = None
        if self.preconditioner == "kronecker" and n:
            kron = KroneckerData.of_system(fit[:n * ns].reshape((n, ns)), merge.kept,
                                           self.geometry, previous=self.memo.get(f"kronecker{g}"),
                                           index=merge.kept_index, by_component=self.by_component,
                                           fit=self.k.kernel(fit_kronecker))
            self.memo[f"kronecker{g}"] = kron
        group[3] = (Ar[:n * W].reshape((n, W)), colsr[:n * W].reshape((n, W)),
                    Fr[:n * WF].reshape((n, WF)), fcolsr[:n * WF].reshape((n, WF)),
                    inv_diag[:n], kron, None, True)
        return True

    @property
    def fringe_layers(self):
        """FRINGE_LAYERS on a 2D grid, none in 1D: there the Kronecker step
        is the banded inverse of the axis mass up to the lumped rows, and CG
        converges long before FRINGE_FROM iterations (at most 7 per run on
        S1, S2 large and small, quadratic and cubic, consistent mass), so a
        1D run never compiles the fringe solve."""
        return self.FRINGE_LAYERS if self.geometry[-1] == 2 else 0

    def _compact(self, group, need_fixed=False):
        """The group's free-dof matrix (built once per step and pattern; its
        fixed-column part F only when ``need_fixed``: nonzero fixed values)."""
        comps, rows, index, built, _ = group
        if built is not None and (built[7] or not need_fixed):
            return built
        ns = self.stencil.shape[1]
        g = list(self.groups.values()).index(group)  # scratch arrays per group
        A, F = self.k.scratch(f"A{g}", (rows.size, ns)), self.k.scratch(f"F{g}", (rows.size, ns))
        cols = self.k.scratch(f"cols{g}", (rows.size, ns), np.int32)
        fcols = self.k.scratch(f"fcols{g}", (rows.size, ns), np.int32)
        key = rows.tobytes()
        write_cols = self.memo.get(f"cols{g}") != key  # cols{g} holds this set's columns
        self.k.kernel(compact_system)(self.stencil, *self.geometry, rows, index, self.fast,
                                      self.near, A, cols, F, fcols,
                                      write_cols, need_fixed)
        self.memo[f"cols{g}"] = key
        if built is not None:  # F added to this step's system (A rewritten, equal)
            built = group[3] = built[:7] + (True,)
            return built
        inv_diag = 1.0 / self.lumped[rows]
        kron = fringe = None
        if self.preconditioner == "kronecker" and rows.size and f"banded{g}_on" in self.warm:
            kron = self._band(g, A, cols, rows)
        if self.preconditioner == "kronecker" and rows.size and kron is None:
            # the fringe correction works on the one box of the free dofs;
            # without it, in 2D with several bodies (by_component), a box
            # per coupled component (KroneckerData.of_system)
            with_fringe = self.fringe_layers > 0 and (self.FRINGE_FROM <= 0
                                                      or f"fringe{g}_on" in self.warm)
            kron = KroneckerData.of_system(A, rows, self.geometry,
                                           previous=self.memo.get(f"kronecker{g}"), index=index,
                                           by_component=self.by_component and not with_fringe,
                                           fit=self.k.kernel(fit_kronecker))
            self.memo[f"kronecker{g}"] = kron
            if with_fringe:
                fringe = self._fringe(g, rows, A, cols)
        built = group[3] = (A, cols, F, fcols, inv_diag, kron, fringe, need_fixed)
        return built

    # The particles move little in a step, so the fringe factors of an
    # earlier step's M_FF stay a close symmetric positive definite
    # approximation of M_FF^-1: they are kept while CG needs at most
    # FRINGE_SLACK iterations more than in the first solve with them (the
    # factorisation with its set-up costs about as much as three CG
    # iterations at 128 x 128 cells). The block they came from is kept in
    # the warm data, so a restart from a checkpoint factorises the same
    # block and continues bit for bit.
    FRINGE_SLACK = 1
    # The fringe correction costs two sparse triangular solves and two
    # partial products per iteration, worth it where the Kronecker
    # preconditioner alone needs many iterations (25 on the 2D bench block,
    # 6 with the correction) but not where it needs few (8 on the small soil
    # column, 6 with it, and 25% more solve time). A group turns it on, for
    # the rest of the run, after a CG run with the Kronecker preconditioner
    # alone took at least FRINGE_FROM iterations (the switch is warm data,
    # so restarts follow it), and only a group of at least FRINGE_MIN_ROWS
    # free dofs: on small grids the factorisation and its triangular solves
    # cost more than the iterations they save (the expanding block of
    # `bench --consistent`: 324 free dofs at 32 x 32 cells ran slower with
    # it, 1,156 at 64 x 64 faster). The compiled step loop
    # (solve/compiled_loop.py) applies the factors this class makes.
    FRINGE_FROM = 12
    FRINGE_MIN_ROWS = 600

    # The band factor (kernels.band_factor) costs about n w^2 / 2
    # multiply-adds a step, w the band (2 n_x + 2 for quadratic splines on
    # a box n_x dofs wide), and makes each solve one CG iteration. On D2
    # small at 16 x 16 cells (2 x 2 particles per cell, MUSL: two free-dof
    # groups of 288 rows, w = 34) its factor costs about as much as 10
    # Kronecker-preconditioned iterations, where those needed 8-10 per solve
    # (the fast-row lumping breaks their tensor structure); with 3 x 3
    # particles per cell they need 1.5 and the factor does not pay. A group
    # switches after a Kronecker CG run of at least BAND_FROM iterations,
    # on 2D grids only (in 1D the Kronecker factors are A's own band
    # factor); BAND_MAX bounds w (the factor grows as w^2, the iterations do
    # not). The switch is warm data (f"banded{g}_on"), so restarts and the
    # compiled loop follow it.
    BAND_FROM = 6
    BAND_MAX = 40
    # The particles move little in a step, so the factor of an earlier
    # step's system stays a close preconditioner of this step's: with it
    # CG needs 2 iterations where the step's own factor needs 1 (D2 small
    # at 16 x 16, 112 steps: 2.01 a solve with a factor never refitted),
    # and the factorisation costs about as much as 10 iterations. The
    # factor is kept while the free-dof set stays and a CG run with it
    # needs at most BAND_KEEP iterations (the next step factorises anew
    # after one that needed more); it is warm data (f"band{g}_rows", the
    # rows it was made for, and f"band{g}_factor"), so restarts and the
    # compiled loop continue with the same factor, bit for bit.
    BAND_KEEP = 2

    def _band_width(self):
        """BAND_MAX on a 2D grid, else 0 (never the band factor)."""
        return self.BAND_MAX if self.geometry[-1] == 2 else 0

    def _band(self, g, A, cols, rows):
        """Group g's band factor as ell_pcg's Kronecker arguments take it
        (:class:`_BandFactor`): the kept one when it was made for the same
        free rows ``rows`` (see BAND_KEEP), else that of A; None when its
        system is wider than the band limit or not positive definite to
        round-off."""
        key = f"band{g}"
        kept_rows, L = self.warm.get(key + "_rows"), self.warm.get(key + "_factor")
        if kept_rows is not None and L is not None and np.array_equal(kept_rows, rows) \
                and L.shape[0] == A.shape[0] \
                and L.shape[1] <= factor_columns(self._band_width()) and factor_layout_ok(L):
            return _BandFactor(L)
        self.warm.pop(key + "_rows", None)
        self.warm.pop(key + "_factor", None)
        w = int(self.k.kernel(ell_band_width)(cols))
        if w > self._band_width():
            return None
        # (a new array: warm data may sit in a checkpoint)
        L = np.empty((A.shape[0], factor_columns(w)))
        if not fit_band_factor(A, cols, L):
            return None
        self.warm.update({key + "_rows": rows.copy(), key + "_factor": L})
        return _BandFactor(L)

    def _fringe(self, g, rows, A, cols):
        """The fringe correction's factors for group g, or None (the
        pattern is kept on the kernels while the free-dof set stays)."""
        cache = self.k.__dict__.setdefault("fringe_patterns", {})
        pattern = cache.get(g)
        if pattern is None or pattern.key != rows.tobytes() or \
                pattern.layers != self.FRINGE_LAYERS:
            pattern = cache[g] = FringePattern(rows, cols, self.geometry, self.FRINGE_LAYERS)
        if not pattern.fringe.size:
            return None
        key = f"fringe{g}"
        stored_rows, data = self.warm.get(key + "_rows"), self.warm.get(key + "_block")
        self._stale_fringe[g] = True  # factors of an earlier step's block
        if stored_rows is None or not np.array_equal(stored_rows, rows) or \
                data.size != pattern.indices.size:
            self._stale_fringe[g] = False
            data = pattern.block_values(A)
            for name in [k for k in self.warm if k.startswith(key + "_fresh")]:
                del self.warm[name]
            self.warm.update({key + "_rows": rows.copy(), key + "_block": data})
        if pattern.factor is None or pattern.factor.data is not data:
            pattern.factor = FringeFactor(data, pattern)
        return pattern.factor

    def _keep_fringe(self, g, kinds, iterations):
        """After a CG run with group g's fringe factors (on the right-hand
        sides ``kinds``): drop them (the next step factorises anew) when it
        took more than FRINGE_SLACK iterations beyond the first run with
        them on the same kinds."""
        name = f"fringe{g}_fresh_" + "+".join(kinds)
        fresh = self.warm.get(name)
        if fresh is None:
            self.warm[name] = np.array([iterations])
        elif iterations > fresh[0] + self.FRINGE_SLACK:
            self.warm.pop(f"fringe{g}_rows", None)

    def solve(self, rhs, values, kind):
        """x with M x = rhs on the free dofs and x = values on the fixed ones."""
        return self.solve_many([(rhs, values, kind)])[0]

    def solve_many(self, problems):
        """Several solves with this matrix in one CG run: ``problems`` is a
        list of (rhs, values, kind) (kind names the warm start; values None:
        all 0); returns the solutions in order (new arrays)."""
        outs = [np.zeros(rhs.shape) if values is None  # fixed dofs keep their values
                else np.array(values, dtype=np.float64, copy=True) for rhs, values, _ in problems]
        has_values = [values is not None and bool(values.any()) for _, values, _ in problems]
        # compact_problem reads values only when has_values: rhs stands in for None
        problems = [(rhs, rhs if values is None else values, kind)
                    for rhs, values, kind in problems]
        for g, group in enumerate(self.groups.values()):
            comps, rows, index, _, merge = group
            A, cols, F, fcols, inv_diag, kron, fringe, _ = self._compact(group, any(has_values))
            if merge is not None:  # the kept free dofs of the merged system
                rows = merge.kept
            comps = np.asarray(comps, dtype=np.int64)
            nc = len(problems) * comps.size
            b = self.k.scratch(f"b{g}", (rows.size, nc))
            x = self.k.scratch(f"x{g}", (rows.size, nc))
            for i, (rhs, values, kind) in enumerate(problems):
                prev = self.warm.get(kind)
                has_prev = prev is not None and prev.shape == rhs.shape
                if merge is not None:
                    self.k.kernel(merged_problem)(rows, merge.kept_index, merge.small,
                                    merge.entries, merge.row_dof, merge.row_weight, rhs, values,
                                    has_values[i], prev if has_prev else rhs, has_prev, comps,
                                    i * comps.size, F, fcols, b, x)
                    continue
                self.k.kernel(compact_problem)(rows, rhs, values, has_values[i],
                                prev if has_prev else rhs, has_prev, comps, i * comps.size,
                                F, fcols, b, x)
            if rows.size:
                before = self.iterations
                nt = self.k.nthreads  # the run's fixed blocks (solve/threads.py)
                pre = kron.pcg_args(b.shape[1], nt) if kron is not None else None
                extra = fringe.args(b.shape[1]) if fringe is not None else None
                work = self.k.scratch("cg", (6,) + b.shape)
                limit = self.max_iterations or 10 * rows.size + 100
                problem = np.repeat(np.arange(len(problems)), comps.size)
                pcg = self.k.kernel(ell_pcg)
                if self.geometry[-1] == 1 and merge is None and isinstance(kron, KroneckerData):
                    # P = A (fit_kronecker: in 1D the marginal is A), so
                    # x = P^-1 b is the solution; no iteration
                    self.k.kernel(apply_kronecker)(*kron.args(b.shape[1], nt), b, x)
                    its = 1
                else:
                    its = pcg(A, cols, inv_diag, pre, extra, b, x, problem, self.rtol, limit,
                              nt, work)
                if its < 0 and fringe is not None and self._stale_fringe[g]:
                    # factors of an earlier step: retry with the current block's
                    self.warm.pop(f"fringe{g}_rows", None)
                    fringe = self._fringe(g, rows, A, cols)
                    group[3] = group[3][:6] + (fringe,) + group[3][7:]
                    more = pcg(A, cols, inv_diag, pre, fringe.args(b.shape[1]), b, x, problem,
                               self.rtol, limit, nt, work)
                    its = -its + more if more > 0 else its - abs(more)
                if its < 0:
                    raise InvalidState(f"consistent-mass CG stopped above its tolerance "
                                       f"{self.rtol:g} after {-its} iterations")
                self.iterations += its
                if isinstance(kron, KroneckerData) and merge is None and fringe is None \
                        and its >= self.BAND_FROM and self._band_width() > 0 \
                        and self.k.kernel(ell_band_width)(cols) <= self._band_width():
                    self.warm[f"banded{g}_on"] = np.array([1])
                elif isinstance(kron, _BandFactor) and its > self.BAND_KEEP:
                    self.warm.pop(f"band{g}_rows", None)  # the next step factorises anew
                elif kron is not None and fringe is None and self.fringe_layers > 0 \
                        and its >= self.FRINGE_FROM and rows.size >= self.FRINGE_MIN_ROWS:
                    self.warm[f"fringe{g}_on"] = np.array([1])
                if fringe is not None:
                    self._keep_fringe(g, [kind for _, _, kind in problems],
                                      self.iterations - before)
                if self.iteration_log is not None:
                    self.iteration_log.append(self.iterations - before)
            for i, out in enumerate(outs):
                if merge is not None:
                    self.k.kernel(merged_expand)(rows, merge.small, merge.entries, merge.row_dof,
                                                 merge.row_weight, x, comps, i * comps.size, out)
                else:
                    self.k.kernel(expand_problem)(rows, x, comps, i * comps.size, out)
        return outs

    def remember(self, kind, x):
        self.warm[kind] = x.copy()

    def keep(self, kind, x):
        """:meth:`remember` of an array nothing else writes (a solution
        :meth:`solve_many` returned): kept without a copy."""
        self.warm[kind] = x

    def shift_guess(self, kind, dx):
        shift_guess(self.warm, kind, dx)

    def residual(self, x, rhs):
        """M x - rhs with the fast rows lumped, on the constrained dofs (the
        rows the reactions read; zero elsewhere)."""
        return stencil_residual(self.stencil, self.geometry, self.constraints.mask,
                                self.inactive, self.fast, x, rhs, self.reaction_rows,
                                parallel=self.k.parallel)


class _BandFactor:
    """A group's band factor L (kernels.band_factor) in the place of its
    Kronecker data: ``pcg_args`` gives ell_pcg's Kronecker arguments with the
    band switched on (the Kronecker fields empty)."""

    _EMPTY = np.empty((0, 1))
    _NONE = np.empty(0)
    _NO_INDEX = np.empty(0, dtype=np.int64)

    def __init__(self, L):
        self.L = L

    def pcg_args(self, nc, nt):
        return (self._EMPTY, self._EMPTY, self._NO_INDEX, self._NONE, np.empty((1, 1, nc)), 1,
                self.L, True)


class _Merge:
    """One group's tiny-mass merge: the rows of T (kernels.tiny_mass.merging_rows)
    and the kept free dofs of its merged system (kept_rows[:n], kept_index),
    in the kernels' scratch arrays of group g."""

    def __init__(self, kernels, g, nd):
        self.small = kernels.scratch(f"small{g}", nd, np.bool_)
        self.entries = kernels.scratch(f"entries{g}", nd, np.int64)
        self.row_dof = kernels.scratch(f"row_dof{g}", (nd, MAX_ENTRIES), np.int64)
        self.row_weight = kernels.scratch(f"row_weight{g}", (nd, MAX_ENTRIES))
        self.kept_rows = kernels.scratch(f"kept_rows{g}", nd, np.int64)
        self.kept_index = kernels.scratch(f"kept_index{g}", nd, np.int64)
        self.kept = self.kept_rows[:0]


def stencil_residual(stencil, geometry, mask, inactive, fast, x, rhs, rows=None, parallel=True):
    """M x - rhs on the dofs constrained in any component (``rows``, when
    known; zero elsewhere): what the reactions read. M is the stencil with
    the fast rows lumped (fractions ``fast``) and the columns of the
    massless (``inactive``) dofs removed, as the solves see it (with
    ``parallel`` False, by the serial kernel)."""
    if rows is None:
        rows = np.flatnonzero(mask.any(axis=1))
    y = np.empty((rows.size, x.shape[1]))
    for_threads(stencil_rows_product, parallel)(stencil, *geometry, rows, inactive, fast,
                                                np.ascontiguousarray(x), y)
    out = np.zeros_like(rhs)
    out[rows] = y - rhs[rows]
    return out


_DEFAULT_FRINGE_LAYERS = StencilSystem.FRINGE_LAYERS
_DEFAULT_BAND_MAX = StencilSystem.BAND_MAX


@contextmanager
def preconditioned_with(preconditioner):
    """Within the ``with`` block, the stencil CG of consistent mass on the
    compiled executor uses ``preconditioner``:

    ``"kronecker+fringe"``
        the default: the Kronecker product of the axes' mass matrices
        (:mod:`skfem_mpm.kernels.kronecker`), with the fringe correction
        (:mod:`skfem_mpm.kernels.fringe`) once the Kronecker step alone has
        needed ``StencilSystem.FRINGE_FROM`` iterations, or on narrow 2D
        systems the band factor (:mod:`skfem_mpm.kernels.band_factor`)
        once it has needed ``StencilSystem.BAND_FROM``;
    ``"kronecker"``
        the Kronecker preconditioner alone (no fringe layers, no band factor);
    ``"lumped"``
        the inverse lumped mass (a Jacobi step with the row sums).

    Yields a list to which every CG run in the block appends its number of
    iterations. The choice changes the iterations, not the solution (each
    run stops at the same relative residual). Leaving the block, also by an
    exception, restores the previous settings; the block sets class
    attributes, so it is not meant for simulations running in other threads
    meanwhile.

        with preconditioned_with("lumped") as iterations:
            simulate(scene, Method(mass="consistent", mass_solver="cg"))
    """
    check_choice("preconditioner", preconditioner, PRECONDITIONERS)
    cls = StencilSystem
    saved = (cls.preconditioner, cls.FRINGE_LAYERS, cls.BAND_MAX, cls.iteration_log)
    cls.preconditioner = "lumped" if preconditioner == "lumped" else "kronecker"
    default = preconditioner == "kronecker+fringe"
    cls.FRINGE_LAYERS = _DEFAULT_FRINGE_LAYERS if default else 0
    cls.BAND_MAX = _DEFAULT_BAND_MAX if default else 0
    log = cls.iteration_log = []
    try:
        yield log
    finally:
        cls.preconditioner, cls.FRINGE_LAYERS, cls.BAND_MAX, cls.iteration_log = saved
