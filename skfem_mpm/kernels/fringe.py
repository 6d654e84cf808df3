"""The fringe correction of the Kronecker preconditioner.

The Kronecker preconditioner P (:mod:`skfem_mpm.kernels.kronecker`) is
accurate where the particles fill the supports of the basis functions. Near
the edge of the free-dof set (partly filled supports, the fast-row lumping,
the edge of the index box) it is not, and those few eigenvalues take most of
the CG iterations. Measured on the 2D benchmark block at 128 x 128 cells
(4356 free dofs): 92% of the eigenvalues of P^-1 M lie in [0.987, 1.135], the
~500 of the outer rows in [0.50, 5.45]; CG needs 25 iterations to 1e-13.

The correction solves the fringe block of M exactly before and after the
Kronecker step (symmetric multiplicative Schwarz; e.g. Smith, Bjorstad and
Gropp, *Domain Decomposition*, 1996, ch. 1):

    z1 = R^T M_FF^-1 R r
    z2 = z1 + P^-1 (r - M z1)
    z  = z2 + R^T M_FF^-1 R (r - M z2)

R restricts to the fringe F, the free dofs within ``layers`` index steps
(per axis) of a dof that is not free. The error operator is
I - B M = (I - Q)(I - P^-1 M)(I - Q), Q = R^T M_FF^-1 R M the M-orthogonal
projection onto fringe vectors, so B is symmetric, and positive definite
when P^-1 M stays below 2 on the vectors M-orthogonal to the fringe, which
is where P is accurate. Measured on the same block (3 layers, 756 fringe
dofs): the eigenvalues of B M lie in [0.991, 1.015] (1 layer: [0.85, 1.41],
2 layers: [0.95, 1.05]), and CG needs 6 iterations to 1e-13 from a cold
start.

M_FF is factorised with SuperLU (``scipy.sparse.linalg.splu``, symmetric
mode, minimum-degree ordering of M + M^T, no pivoting: M_FF is symmetric
positive definite); its triangular factors are applied by a compiled kernel
(all right-hand sides at once) so that the whole CG stays compiled.
"""
import numpy as np
from numba import njit, prange

from .kronecker import apply_kronecker_replaced
from .weights import FAST, IN_ORDER

__all__ = ["fringe_rows", "FringePattern", "FringeFactor", "NO_FACTOR", "fringe_solve",
           "apply_corrected"]


def fringe_rows(rows, geometry, layers):
    """Positions (into ``rows``) of the free dofs within ``layers`` index
    steps per axis (Chebyshev distance) of a dof that is not free; dofs on
    the grid's edge count the outside as not free."""
    if int(layers) != layers or layers < 0:
        raise ValueError(f"layers must be a non-negative integer, got {layers!r}")
    p, nbx, nby, dim = geometry
    a, b = rows % nbx, rows // nbx
    ly = layers if dim == 2 else 0
    free = np.zeros((nby + 2 * ly, nbx + 2 * layers), dtype=bool)
    free[b + ly, a + layers] = True
    # erosion by the (2 layers + 1)^dim box, one axis after the other:
    # free with all neighbours within reach free
    across = free.copy()
    for da in range(-layers, layers + 1):
        across[:, layers:free.shape[1] - layers] &= \
            free[:, layers + da:free.shape[1] - layers + da]
    inner = across.copy()
    for db in range(-ly, ly + 1):
        inner[ly:inner.shape[0] - ly, :] &= across[ly + db:across.shape[0] - ly + db, :]
    return np.flatnonzero(~inner[b + ly, a + layers])


def _by_rows(keep, slots, columns):
    """CSR of the entries (slot, column) of a row-major table where ``keep``:
    row pointers and an (entries, 2) array, each row's slots ascending."""
    ptr = np.concatenate(([0], np.cumsum(keep.sum(axis=1)))).astype(np.int64)
    entries = np.stack((slots[keep], columns[keep]), axis=1).astype(np.int64)
    return ptr, np.ascontiguousarray(entries)


class FringePattern:
    """What the correction needs of one free-dof set, fixed while the set
    is: the fringe rows, the rows ``near`` it (with a column in the fringe:
    where M z1 is nonzero for a fringe-supported z1), the entries of both
    that the residuals read (:meth:`arrays`), and the block's CSC
    structure with the map from the compact matrix's entries to it (the
    compact matrix repeats the diagonal for its unused slots; those are
    summed). ``factor`` caches the :class:`FringeFactor` of the values it
    was made from."""

    def __init__(self, rows, cols, geometry, layers):
        n = rows.size
        self.fringe = fringe_rows(rows, geometry, layers).astype(np.int64)
        nf = self.fringe.size
        position = np.full(n, -1, dtype=np.int64)
        position[self.fringe] = np.arange(nf)
        c = position[cols[self.fringe]]
        self.keep = np.flatnonzero(c.ravel() >= 0)
        r = np.repeat(np.arange(nf), cols.shape[1])[self.keep]
        key = c.ravel()[self.keep] * nf + r  # column-major: CSC order
        unique, self.slot = np.unique(key, return_inverse=True)
        self.indices = (unique % nf).astype(np.int32)
        self.indptr = np.searchsorted(unique // nf, np.arange(nf + 1)).astype(np.int32)
        # the residuals' rows by rows (CSR), each entry (slot of A's row,
        # column): the fringe rows with their free columns, their other slots
        # being the zeros compact_system writes beside the diagonal (column:
        # the row itself); the rows near the fringe (a column in it: where
        # M z1 is nonzero for a fringe-supported z1) with their fringe
        # columns as fringe positions
        ns = cols.shape[1]
        centre = (ns - 1) // 2
        slots = np.arange(ns)
        free = (cols[self.fringe] != self.fringe[:, None]) | (slots == centre)
        self.fringe_ptr, self.fringe_entries = _by_rows(
            free, np.broadcast_to(slots, free.shape), cols[self.fringe])
        touches = np.zeros(n, dtype=bool)
        touches[self.fringe] = True
        self.near = np.flatnonzero(touches[cols].any(axis=1)).astype(np.int64)
        near_cols = cols[self.near]
        in_fringe = (position[near_cols] >= 0) & \
            ((near_cols != self.near[:, None]) | (slots == centre))
        self.near_ptr, self.near_entries = _by_rows(
            in_fringe, np.broadcast_to(slots, in_fringe.shape), position[near_cols])
        self.key = rows.tobytes()
        self.layers = layers
        self.factor = None

    def block_values(self, A):
        """The fringe block's entries (CSC order) from the compact matrix."""
        values = A[self.fringe].ravel()[self.keep]
        return np.bincount(self.slot, weights=values, minlength=self.indices.size)

    def arrays(self):
        """The fringe rows, their entries by rows (CSR: pointers and
        (slot, column) pairs), the near rows and theirs (columns as
        fringe positions), as :func:`apply_corrected` takes them."""
        return (self.fringe, self.fringe_ptr, self.fringe_entries, self.near, self.near_ptr,
                self.near_entries)


class FringeFactor:
    """The SuperLU factors of a fringe block: ``data`` its entries in the
    ``pattern``'s CSC structure (:meth:`FringePattern.block_values`)."""

    def __init__(self, data, pattern):
        from scipy.sparse import csc_matrix
        from scipy.sparse.linalg import splu

        self.pattern = pattern
        self.data = data
        nf = pattern.fringe.size
        block = csc_matrix((data, pattern.indices, pattern.indptr), shape=(nf, nf))
        lu = splu(block, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                  options=dict(SymmetricMode=True))
        L, U = lu.L, lu.U
        L.sort_indices()
        U.sort_indices()
        diagonal = np.arange(nf)
        if not (np.array_equal(L.indices[L.indptr[:-1]], diagonal) and
                np.array_equal(U.indices[U.indptr[1:] - 1], diagonal)):
            raise RuntimeError("SuperLU factors without the stored diagonal fringe_solve reads")
        self.inv_udiag = 1.0 / U.data[U.indptr[1:] - 1]  # the diagonal ends each column
        # by rows, without the diagonals (fringe_solve): L's strictly lower
        # and U's strictly upper entries, each row's columns ascending
        self.L = self._rows(L.tocsr(), lambda i, j: j < i)
        self.U = self._rows(U.tocsr(), lambda i, j: j > i)
        self.perm_r = lu.perm_r.astype(np.int64)
        self.perm_c = lu.perm_c.astype(np.int64)

    @staticmethod
    def _rows(T, keep):
        """(indptr, indices, data) of the CSR matrix T's entries (i, j) that
        ``keep``, each row's columns ascending."""
        T.sort_indices()
        i = np.repeat(np.arange(T.shape[0]), np.diff(T.indptr))
        kept = keep(i, T.indices)
        indptr = np.concatenate(([0], np.cumsum(np.bincount(i[kept], minlength=T.shape[0]))))
        return indptr.astype(np.int64), T.indices[kept].astype(np.int64), T.data[kept]

    def arrays(self):
        """The factor's arrays as :func:`apply_corrected` takes them after
        the Kronecker ones (before the work space): its pattern's
        (:meth:`FringePattern.arrays`), L and U by rows without their
        diagonals (CSR), 1 / U_jj and the permutations."""
        return (*self.pattern.arrays(), *self.L, *self.U, self.inv_udiag, self.perm_r,
                self.perm_c)

    def args(self, nc):
        """The arguments of :func:`apply_corrected` after the Kronecker ones:
        :meth:`arrays` and work space for ``nc`` right-hand sides (the last
        four)."""
        nf = self.pattern.fringe.size
        return self.arrays() + (np.empty((nf, nc)), np.empty((nf, nc)),
                                np.empty((2, nf, (nc + 1) // 2)),
                                np.empty((self.pattern.near.size, nc)))


NO_FACTOR = (np.zeros(1, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0),
             np.zeros(1, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0),
             np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))
"""The factor's part of :meth:`FringeFactor.arrays` for a pattern without
fringe rows (nothing to factorise)."""


@njit(cache=True, inline="always", error_model="numpy", fastmath=IN_ORDER)
def _solve_4(Lp, Li, Lx, Up, Ui, Ux, inv_udiag, y):
    """y = U^-1 L^-1 y for the four columns of y (see fringe_solve), row by
    row, each row's sums in registers."""
    n = y.shape[0]
    for i in range(n):
        s0, s1, s2, s3 = y[i, 0], y[i, 1], y[i, 2], y[i, 3]
        for q in range(Lp[i], Lp[i + 1]):
            v = Lx[q]
            j = Li[q]
            s0 -= v * y[j, 0]
            s1 -= v * y[j, 1]
            s2 -= v * y[j, 2]
            s3 -= v * y[j, 3]
        y[i, 0], y[i, 1], y[i, 2], y[i, 3] = s0, s1, s2, s3
    for i in range(n - 1, -1, -1):
        s0, s1, s2, s3 = y[i, 0], y[i, 1], y[i, 2], y[i, 3]
        for q in range(Up[i + 1] - 1, Up[i] - 1, -1):
            v = Ux[q]
            j = Ui[q]
            s0 -= v * y[j, 0]
            s1 -= v * y[j, 1]
            s2 -= v * y[j, 2]
            s3 -= v * y[j, 3]
        d = inv_udiag[i]
        y[i, 0], y[i, 1], y[i, 2], y[i, 3] = s0 * d, s1 * d, s2 * d, s3 * d


@njit(cache=True, inline="always", error_model="numpy", fastmath=IN_ORDER)
def _solve_2(Lp, Li, Lx, Up, Ui, Ux, inv_udiag, y):
    """:func:`_solve_4` for the two columns of y."""
    n = y.shape[0]
    for i in range(n):
        s0, s1 = y[i, 0], y[i, 1]
        for q in range(Lp[i], Lp[i + 1]):
            v = Lx[q]
            j = Li[q]
            s0 -= v * y[j, 0]
            s1 -= v * y[j, 1]
        y[i, 0], y[i, 1] = s0, s1
    for i in range(n - 1, -1, -1):
        s0, s1 = y[i, 0], y[i, 1]
        for q in range(Up[i + 1] - 1, Up[i] - 1, -1):
            v = Ux[q]
            j = Ui[q]
            s0 -= v * y[j, 0]
            s1 -= v * y[j, 1]
        d = inv_udiag[i]
        y[i, 0], y[i, 1] = s0 * d, s1 * d


@njit(cache=True, parallel=True, error_model="numpy", fastmath=IN_ORDER)
def fringe_solve(Lp, Li, Lx, Up, Ui, Ux, inv_udiag, perm_r, perm_c, y, b, x, threads=1):
    """x = M_FF^-1 b from SuperLU's factors Pr M_FF Pc = L U, L with a unit
    diagonal: w = Pr b, w = L^-1 w, w = U^-1 w, x = Pc w. L and U by rows
    without their diagonals (CSR, each row's columns ascending), 1 / U_ii
    in ``inv_udiag``: row i of the forward solve subtracts L_ij w_j in
    ascending j, row i of the backward one U_ij w_j in descending j, then
    scales by 1 / U_ii, each row's sums in registers (compiled without
    reassociation: every entry of w takes the operations of the column-
    oriented solve in the same order, so either gives the same bits).
    All right-hand sides in one pass over the factors (their rows' sums
    are chains of dependent operations: four columns cost less than two
    passes of two), in two halves of the columns, one a thread, when
    there are three or more and ``threads`` (the run's thread blocks) is
    2 or more. ``y`` is C-ordered work space of 2 n
    ceil(nc / 2) entries or more (FringeFactor.args' (2, n, ceil(nc / 2)));
    a block's unused fourth (second) column is zero and not read."""
    n, nc = b.shape
    flat = y.reshape(y.size)
    blocks = 2 if nc >= 3 and threads >= 2 else 1
    lanes = 4 if nc >= 3 and blocks == 1 else 2
    for t in prange(blocks):
        c0 = t * nc // blocks
        c1 = (t + 1) * nc // blocks
        w = flat[t * n * lanes:(t + 1) * n * lanes].reshape((n, lanes))
        for i in range(n):
            k = perm_r[i]
            for c in range(c0, c1):
                w[k, c - c0] = b[i, c]
            for c in range(c1 - c0, lanes):
                w[k, c] = 0.0
        if lanes == 4:
            _solve_4(Lp, Li, Lx, Up, Ui, Ux, inv_udiag, w)
        else:
            _solve_2(Lp, Li, Lx, Up, Ui, Ux, inv_udiag, w)
        for i in range(n):
            k = perm_c[i]
            for c in range(c0, c1):
                x[i, c] = w[k, c - c0]


@njit(cache=True, parallel=True, error_model="numpy", fastmath=IN_ORDER)
def _residual_rows(A, which, ptr, entries, r, z, out):
    """out[k] = r_i - sum_e A[i, s_e] z[j_e] for the rows i = which[k], over
    their entries e = ptr[k] .. ptr[k + 1] - 1, (s_e, j_e) = entries[e]
    (slot of A's row, row of z) in ascending slots: the ELL row's product
    without its slots of zeros (A = 0, or z = 0 there), subtracted term by
    term in slot order (compiled without reassociation: the ELL product in
    order gives the same bits; with reassociation LLVM gathered the slots
    into vector lanes, in an order of its own and slower)."""
    nc = r.shape[1]
    for k in prange(which.shape[0]):
        i = which[k]
        if nc == 4:  # two 2D problems: four running sums
            s0, s1, s2, s3 = r[i, 0], r[i, 1], r[i, 2], r[i, 3]
            for e in range(ptr[k], ptr[k + 1]):
                a = A[i, entries[e, 0]]
                j = entries[e, 1]
                s0 -= a * z[j, 0]
                s1 -= a * z[j, 1]
                s2 -= a * z[j, 2]
                s3 -= a * z[j, 3]
            out[k, 0] = s0
            out[k, 1] = s1
            out[k, 2] = s2
            out[k, 3] = s3
        else:
            for c in range(nc):
                s = r[i, c]
                for e in range(ptr[k], ptr[k + 1]):
                    s -= A[i, entries[e, 0]] * z[entries[e, 1], c]
                out[k, c] = s


@njit(cache=True, error_model="numpy", fastmath=FAST)
def apply_corrected(A, cols, Lx, Ly, local, inv_scale, box, nblocks, fringe, fringe_ptr,
                    fringe_entries, near, near_ptr, near_entries, Lp, Li, Lv, Up, Ui, Uv,
                    inv_udiag, perm_r, perm_c, rf, zf, yf, tn, r, z, t):
    """z = B r, the Kronecker preconditioner with the fringe correction (see
    the module docstring); A the compact matrix (ELL; ``cols`` is not read:
    the pattern holds the fringe rows' columns), Lx ... nblocks the
    arguments of :func:`~skfem_mpm.kernels.kronecker.apply_kronecker`,
    fringe ... tn those of :meth:`FringeFactor.args`; ``t`` is not used
    (the work space of the other preconditioners). z1 lives on the fringe
    only (zf), and r - M z1 differs from r on the
    near rows only (tn), which the Kronecker step takes in place of r's."""
    nc = r.shape[1]
    nf = fringe.shape[0]
    # z1 = R^T M_FF^-1 R r
    for k in range(nf):
        for c in range(nc):
            rf[k, c] = r[fringe[k], c]
    fringe_solve(Lp, Li, Lv, Up, Ui, Uv, inv_udiag, perm_r, perm_c, yf, rf, zf, nblocks)
    # z2 = z1 + P^-1 (r - M z1); M z1 is nonzero only on the rows near F
    _residual_rows(A, near, near_ptr, near_entries, r, zf, tn)
    apply_kronecker_replaced(Lx, Ly, local, inv_scale, box, nblocks, r, near, tn, z)
    for k in range(nf):
        for c in range(nc):
            z[fringe[k], c] += zf[k, c]
    # z = z2 + R^T M_FF^-1 R (r - M z2)
    _residual_rows(A, fringe, fringe_ptr, fringe_entries, r, z, rf)
    fringe_solve(Lp, Li, Lv, Up, Ui, Uv, inv_udiag, perm_r, perm_c, yf, rf, zf, nblocks)
    for k in range(nf):
        for c in range(nc):
            z[fringe[k], c] += zf[k, c]
