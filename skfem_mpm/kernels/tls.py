"""Conservative Taylor least squares (TLS) per cell, compiled: the twin of
:func:`skfem_mpm.reconstruct.reconstruct_tls` with its default options
(``degree=2, neighbour_weight=0``), which is the oracle.

The method (Wobbes, Moller, Galavi, Vuik 2019, IJNME 117:271-290, Sec. 3):
for each cell e that holds Gauss points of the rule, in the local
coordinates xi = (x - c_e) / h_e (c_e the centre and h_e the sizes per axis
of the box spanned by the cell's Gauss points, as the oracle) and the
monomials

    phi = (1, xi_1, .., xi_d, xi_a xi_b for a <= b)      (m = 3 in 1D, 6 in 2D, 10 in 3D),

the coefficients a_e (m, k) of all k value columns at once solve the
Lagrange system of the volume-weighted fit under the conservation
constraint

    [[A, G], [G^T, 0]] [a_e; lambda] = [b; S],
    A = sum_{p in e} V_p phi_p phi_p^T,  b = sum_{p in e} V_p phi_p f_p,
    G = sum_{g in e} w_g phi_g,          S = sum_{p in e} V_p f_p,

so that the Gauss integral of the fit over the cell is the cell's particle
integral. Fallback levels (never a singular solve): the quadratic when the
leading m x m block of A, scaled to unit diagonal, has its smallest
eigenvalue above TLS_RANK_TOL; else the same with the 1 + d linear
monomials; else the conserving constant S / G_0. A level's fit is kept
for value column c only when its values at the cell's Gauss points stay
within [min_p f_pc - s_c, max_p f_pc + s_c], s_c = TLS_BOUND_TOL (max - min)
+ TLS_BOUND_ABS max |f_pc| over the cell's particles; the columns that
leave it take the next level (the bound test of the oracle). The eigenvalue test is
made as a Cholesky factorisation of D^(-1/2) A D^(-1/2) - TLS_RANK_TOL I
(D = diag A, all > 0): it succeeds exactly when the smallest eigenvalue
exceeds TLS_RANK_TOL. The Lagrange system (symmetric indefinite) is solved
by Gaussian elimination with partial pivoting.

Particles are binned to their cells by a counting sort (stable: each
cell's sums run in particle order, as the oracle's np.add.at does), the
Gauss points likewise; the fit of cell e is then evaluated at its points.

A, G, the eigenvalue tests and the factorisation P K = L U of each level's
Lagrange matrix depend on the positions alone: :func:`tls_factor` computes
them once for a set of particles and a rule, and :func:`tls_apply` fits
each field on them (b, S, the solves with the stored factors, the bound
test); a step fits [rho, rho v, sigma] and its MUSL projection fits
rho v^new on one factor. Each row of the right-hand side takes the
operations of eliminating [K | R] at once, in the same order, so the fit
has the bits of a solve of the whole system (:func:`tls_reconstruct`, both
halves, is the one-call form). The loops over cells run in blocks of
CELLS_PER_BLOCK cells (prange in the parallel kernels; each cell's
arithmetic is the same in any block, so the bits are too).
"""
import numpy as np
from numba import njit, prange

from .cholesky import cholesky

__all__ = ["TLS_BOUND_ABS", "TLS_BOUND_TOL", "TLS_RANK_TOL", "empty_factor", "tls_apply",
           "slot_cells", "tls_coefficients", "tls_factor", "tls_reconstruct"]

TLS_RANK_TOL = 1e-8  # the value of skfem_mpm.reconstruct.TLS_RANK_TOL (a test checks)
TLS_BOUND_TOL = 1.0  # skfem_mpm.reconstruct.TLS_BOUND_TOL and TLS_BOUND_ABS (a test checks)
TLS_BOUND_ABS = 1e-9


@njit(cache=True, inline="always", error_model="numpy")
def _monomials(x0, x1, x2, centre0, centre1, centre2, size0, size1, size2, dim):
    """phi = (1, xi, eta, zeta, xi xi, xi eta, xi zeta, eta eta, eta zeta,
    zeta zeta) of the point (x0, x1, x2), xi = (x0 - centre0) / size0 and so
    on (the oracle's order: 1, the coordinates, then xi_a xi_b for a <= b);
    in 2D (1, xi, eta, xi xi, xi eta, eta eta), in 1D (1, xi, xi xi), the
    rest zeros. Scalars only: an inlined function of array arguments makes
    numba count references to them per call."""
    xi = (x0 - centre0) / size0
    if dim == 1:
        return 1.0, xi, xi * xi, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    eta = (x1 - centre1) / size1
    if dim == 2:
        return 1.0, xi, eta, xi * xi, xi * eta, eta * eta, 0.0, 0.0, 0.0, 0.0
    zeta = (x2 - centre2) / size2
    return (1.0, xi, eta, zeta, xi * xi, xi * eta, xi * zeta, eta * eta, eta * zeta,
            zeta * zeta)


MONOMIALS = 10
"""The most monomials (3D quadratic): the length of phi."""


@njit(cache=True, error_model="numpy")
def _well_posed(A, n, tol, work):
    """Smallest eigenvalue of the leading n x n block of A scaled to unit
    diagonal > tol, by Cholesky of the scaled block minus tol I (in
    ``work``, at least (n + 1) x n)."""
    for i in range(n):
        if not A[i, i] > 0.0:
            return False
        work[n, i] = 1.0 / np.sqrt(A[i, i])  # (a spare row of work)
    for i in range(n):
        for j in range(i + 1):  # the lower triangle: what cholesky reads
            work[i, j] = A[i, j] * work[n, i] * work[n, j]
    return cholesky(work, n, tol, work)


@njit(cache=True, error_model="numpy")
def _factor(K, n, pivot):
    """K[:n, :n] = P^T L U in place by Gaussian elimination with partial
    pivoting (Golub & Van Loan, Alg. 3.4.1): U on and above the diagonal,
    the multipliers of L below it (moved with their rows by later
    interchanges), pivot[j] the row swapped with row j at step j."""
    for j in range(n):
        best = j
        for i in range(j + 1, n):
            if abs(K[i, j]) > abs(K[best, j]):
                best = i
        pivot[j] = best
        if best != j:
            for q in range(n):
                K[j, q], K[best, q] = K[best, q], K[j, q]
        for i in range(j + 1, n):
            f = K[i, j] / K[j, j]
            K[i, j] = f
            if f != 0.0:
                for q in range(j + 1, n):
                    K[i, q] -= f * K[j, q]


@njit(cache=True, error_model="numpy")
def _solve(K, pivot, R, n):
    """R[:n] := K^-1 R[:n] for K factorised by :func:`_factor`: the
    interchanges, then forward and backward substitution. Each row of R
    takes the operations of eliminating [K | R] at once, in the same order
    (the multipliers of step j applied to the rows as they stand after
    step j's interchange), so the same bits."""
    k = R.shape[1]
    for j in range(n):
        best = pivot[j]
        if best != j:
            for c in range(k):
                R[j, c], R[best, c] = R[best, c], R[j, c]
    for j in range(n):
        for i in range(j + 1, n):
            f = K[i, j]
            if f != 0.0:
                for c in range(k):
                    R[i, c] -= f * R[j, c]
    for j in range(n - 1, -1, -1):
        for c in range(k):
            s = R[j, c]
            for q in range(j + 1, n):
                s -= K[j, q] * R[q, c]
            R[j, c] = s / K[j, j]


@njit(cache=True, error_model="numpy")
def _bins(cell, slot, nslots):
    """Counting sort of the items with slot[cell[i]] >= 0 by that slot
    (stable): items order[start[s]:start[s + 1]] are in slot s."""
    start = np.zeros(nslots + 1, dtype=np.int64)
    for i in range(cell.shape[0]):
        s = slot[cell[i]]
        if s >= 0:
            start[s + 1] += 1
    for s in range(nslots):
        start[s + 1] += start[s]
    fill = start[:-1].copy()
    order = np.empty(start[nslots], dtype=np.int64)
    for i in range(cell.shape[0]):
        s = slot[cell[i]]
        if s >= 0:
            order[fill[s]] = i
            fill[s] += 1
    return order, start


CELLS_PER_BLOCK = 32
"""Cells per block of the loops over cells (each block its own work
arrays; prange over the blocks in the parallel kernels)."""


@njit(cache=True, error_model="numpy")
def _frame(xg, gorder, g0, ng, dim, centre, size):
    """centre, size: the box spanned by the cell's Gauss points
    gorder[g0:g0 + ng] per axis (the oracle's frame); beyond the dimension
    they stay as they are."""
    for a in range(dim):
        lo = np.inf
        hi = -np.inf
        for i in range(ng):
            lo = min(lo, xg[gorder[g0 + i], a])
            hi = max(hi, xg[gorder[g0 + i], a])
        centre[a] = 0.5 * (lo + hi)
        size[a] = hi - lo


@njit(cache=True, error_model="numpy", parallel=True)
def tls_factor(x, V, pcell, xg, wg, gcell, ncells):
    """The half of the TLS fit that depends on the positions alone (the
    particles' x, V and the rule), computed once for every field fitted on
    them (:func:`tls_apply`): the cells' bins, frames, G, whether each
    level is well posed and the factorised Lagrange matrices
    K = [[A, G], [G^T, 0]] of both levels. Arguments as
    :func:`tls_reconstruct`'s; returns the tuple :func:`tls_apply` takes."""
    dim = x.shape[1]
    y = min(1, dim - 1)  # the coordinates' columns (beyond the dimension: read, not used)
    z = dim - 1
    m = 1 + dim + dim * (dim + 1) // 2
    slot = np.full(ncells, -1, dtype=np.int64)
    nact = 0
    for g in range(gcell.shape[0]):
        if slot[gcell[g]] < 0:
            slot[gcell[g]] = nact
            nact += 1
    porder, pstart = _bins(pcell, slot, nact)
    gorder, gstart = _bins(gcell, slot, nact)
    frame = np.zeros((nact, 6))  # centre (3), size (3) per cell
    G = np.zeros((nact, m))
    posed = np.zeros((nact, 2), dtype=np.bool_)
    lu = np.zeros((nact, 2, m + 1, m + 1))  # K of the level's n + 1 rows, factorised
    pivots = np.zeros((nact, 2, m + 1), dtype=np.int64)
    nblocks = (nact + CELLS_PER_BLOCK - 1) // CELLS_PER_BLOCK
    for block in prange(nblocks):
        phi = np.zeros(MONOMIALS)
        centre = np.zeros(3)
        size = np.ones(3)
        A = np.empty((m, m))
        work = np.empty((m + 1, m + 1))
        for s in range(block * CELLS_PER_BLOCK, min(nact, (block + 1) * CELLS_PER_BLOCK)):
            g0 = gstart[s]
            ng = gstart[s + 1] - g0
            _frame(xg, gorder, g0, ng, dim, centre, size)
            for a in range(3):
                frame[s, a] = centre[a]
                frame[s, 3 + a] = size[a]
            A[:] = 0.0
            for i in range(pstart[s], pstart[s + 1]):
                q = porder[i]
                phi[0], phi[1], phi[2], phi[3], phi[4], phi[5], phi[6], phi[7], phi[8], \
                    phi[9] = _monomials(x[q, 0], x[q, y], x[q, z], centre[0], centre[1],
                                        centre[2], size[0], size[1], size[2], dim)
                for r in range(m):  # the lower triangle (A is symmetric)
                    wr = V[q] * phi[r]
                    for t in range(r + 1):
                        A[r, t] += wr * phi[t]
            for r in range(m):
                for t in range(r + 1, m):
                    A[r, t] = A[t, r]
            for i in range(ng):
                g = gorder[g0 + i]
                phi[0], phi[1], phi[2], phi[3], phi[4], phi[5], phi[6], phi[7], phi[8], \
                    phi[9] = _monomials(xg[g, 0], xg[g, y], xg[g, z], centre[0], centre[1],
                                        centre[2], size[0], size[1], size[2], dim)
                for r in range(m):
                    G[s, r] += wg[g] * phi[r]
            for level in range(2):
                n = m if level == 0 else 1 + dim
                if not _well_posed(A, n, TLS_RANK_TOL, work):
                    continue
                posed[s, level] = True
                K = lu[s, level]
                for r in range(n):
                    for t in range(n):
                        K[r, t] = A[r, t]
                    K[r, n] = G[s, r]
                    K[n, r] = G[s, r]
                K[n, n] = 0.0
                _factor(K, n + 1, pivots[s, level])
    return porder, pstart, gorder, gstart, frame, G, posed, lu, pivots


@njit(cache=True, error_model="numpy", parallel=True)
def tls_apply(x, V, values, xg, factor, out):
    """out[g] (ng, k) = the TLS fit of the particle ``values`` (n, k) at
    the Gauss point xg[g], with the position half ``factor`` of
    :func:`tls_factor` on the same particles and rule (see the module
    docstring): the sums b and S, the solves of both levels' factorised
    Lagrange systems, the bound test."""
    nact = factor[5].shape[0]
    nblocks = (nact + CELLS_PER_BLOCK - 1) // CELLS_PER_BLOCK
    no_coef = np.empty((0, 0, 0))
    for block in prange(nblocks):
        _fit_block(block, x, V, values, xg, factor, out, no_coef, True)


@njit(cache=True, error_model="numpy", parallel=True)
def tls_coefficients(x, V, values, xg, factor, coef):
    """coef[s] (m, k) = the monomial coefficients, in cell slot s's frame
    (factor[4]), of the TLS fit of the particle ``values`` (n, k) that
    :func:`tls_apply` evaluates at the cell's Gauss points (the same level
    per column, chosen by the same bound test at those points; the
    conserving constant is c_0 = S / G_0); coef (nact, m, k), the slots of
    :func:`tls_factor` (cell of slot s: the cell of its Gauss points)."""
    nact = factor[5].shape[0]
    nblocks = (nact + CELLS_PER_BLOCK - 1) // CELLS_PER_BLOCK
    no_points = np.empty((0, 0))
    for block in prange(nblocks):
        _fit_block(block, x, V, values, xg, factor, no_points, coef, False)


@njit(cache=True, inline="always", error_model="numpy")
def _fit_block(block, x, V, values, xg, factor, out, coef, at_points):
    """The fits of the cells of one block (see the module docstring): at
    the Gauss points into ``out`` (``at_points``), else their coefficients
    into ``coef`` (the other of the two is not written)."""
    porder, pstart, gorder, gstart, frame, G, posed, lu, pivots = factor
    dim = x.shape[1]
    y = min(1, dim - 1)
    z = dim - 1
    k = values.shape[1]
    m = G.shape[1]
    nact = G.shape[0]
    first = block * CELLS_PER_BLOCK
    stop = min(nact, (block + 1) * CELLS_PER_BLOCK)
    most = 0  # the most Gauss points of one cell of the block
    for s in range(first, stop):
        most = max(most, gstart[s + 1] - gstart[s])
    phig = np.zeros((most, MONOMIALS))  # the monomials at the cell's Gauss points
    fit = np.empty((most, k))  # a level's fit at them
    phi = np.zeros(MONOMIALS)
    b = np.empty((m, k))
    S = np.empty(k)
    R = np.empty((m + 1, k))
    fmin = np.empty(k)
    fmax = np.empty(k)
    slack = np.empty(k)
    low = np.empty(k)
    high = np.empty(k)
    pending = np.empty(k, dtype=np.bool_)
    for s in range(first, stop):
        c0, c1, c2 = frame[s, 0], frame[s, 1], frame[s, 2]
        s0, s1, s2 = frame[s, 3], frame[s, 4], frame[s, 5]
        g0 = gstart[s]
        ng = gstart[s + 1] - g0
        b[:] = 0.0
        S[:] = 0.0
        fmin[:] = np.inf
        fmax[:] = -np.inf
        for i in range(pstart[s], pstart[s + 1]):
            q = porder[i]
            phi[0], phi[1], phi[2], phi[3], phi[4], phi[5], phi[6], phi[7], phi[8], \
                phi[9] = _monomials(x[q, 0], x[q, y], x[q, z], c0, c1, c2, s0, s1, s2, dim)
            for r in range(m):
                wr = V[q] * phi[r]
                for col in range(k):
                    b[r, col] += wr * values[q, col]
            for col in range(k):
                S[col] += V[q] * values[q, col]
                fmin[col] = min(fmin[col], values[q, col])
                fmax[col] = max(fmax[col], values[q, col])
        evaluated = False  # phig holds the monomials at the cell's Gauss points
        for col in range(k):
            slack[col] = TLS_BOUND_TOL * (fmax[col] - fmin[col]) + TLS_BOUND_ABS * max(
                abs(fmin[col]), abs(fmax[col]))
            pending[col] = True
        npending = k
        for level in range(2):
            if npending == 0 or not posed[s, level]:
                continue
            n = m if level == 0 else 1 + dim
            for r in range(n):
                for col in range(k):
                    R[r, col] = b[r, col]
            for col in range(k):
                R[n, col] = S[col]
            # R := K^-1 R as _solve does, written out on lu[s, level] (no views)
            for j in range(n + 1):
                best = pivots[s, level, j]
                if best != j:
                    for col in range(k):
                        R[j, col], R[best, col] = R[best, col], R[j, col]
            for j in range(n + 1):
                for i in range(j + 1, n + 1):
                    f = lu[s, level, i, j]
                    if f != 0.0:
                        for col in range(k):
                            R[i, col] -= f * R[j, col]
            for j in range(n, -1, -1):
                for col in range(k):
                    acc = R[j, col]
                    for q in range(j + 1, n + 1):
                        acc -= lu[s, level, j, q] * R[q, col]
                    R[j, col] = acc / lu[s, level, j, j]
            # the bound test: first the bound |f - c_0| <= B of the monomials
            # on the frame (|xi_a| <= 1/2 at the points), with a margin above
            # the rounding of an evaluation; a column it does not settle (or
            # at_points, which needs the values) is evaluated at the points
            unsure = at_points
            for col in range(k):
                low[col] = np.inf
                high[col] = -np.inf
                if pending[col] and not at_points:
                    spread = 0.0
                    for r in range(1, n):
                        spread += abs(R[r, col]) * (0.5 if r <= dim else 0.25)
                    margin = 1e-14 * (abs(R[0, col]) + spread)
                    lo_c = R[0, col] - spread - margin
                    hi_c = R[0, col] + spread + margin
                    if lo_c >= fmin[col] - slack[col] and hi_c <= fmax[col] + slack[col]:
                        low[col] = lo_c
                        high[col] = hi_c
                    else:  # (also NaN)
                        unsure = True
            if unsure:
                if not evaluated:
                    for i in range(ng):
                        g = gorder[g0 + i]
                        phig[i, 0], phig[i, 1], phig[i, 2], phig[i, 3], phig[i, 4], \
                            phig[i, 5], phig[i, 6], phig[i, 7], phig[i, 8], \
                            phig[i, 9] = _monomials(xg[g, 0], xg[g, y], xg[g, z], c0, c1, c2,
                                                    s0, s1, s2, dim)
                    evaluated = True
                for col in range(k):  # the level's fit at the points
                    if pending[col] and not low[col] < np.inf:
                        for i in range(ng):
                            acc = 0.0
                            for r in range(n):
                                acc += phig[i, r] * R[r, col]
                            fit[i, col] = acc
                            low[col] = min(low[col], acc)
                            high[col] = max(high[col], acc)
            for col in range(k):  # the columns within their bounds keep this level's fit
                if pending[col] and low[col] >= fmin[col] - slack[col] \
                        and high[col] <= fmax[col] + slack[col]:
                    if at_points:
                        for i in range(ng):
                            out[gorder[g0 + i], col] = fit[i, col]
                    else:
                        for r in range(m):
                            coef[s, r, col] = R[r, col] if r < n else 0.0
                    pending[col] = False
                    npending -= 1
        for col in range(k):  # the conserving constant
            if pending[col]:
                constant = S[col] / G[s, 0]
                if at_points:
                    for i in range(ng):
                        out[gorder[g0 + i], col] = constant
                else:
                    coef[s, 0, col] = constant
                    for r in range(1, m):
                        coef[s, r, col] = 0.0


@njit(cache=True, error_model="numpy")
def slot_cells(factor, gcell):
    """The cell of each slot of :func:`tls_factor` (that of its Gauss
    points ``gcell``), for the cell integrals of :func:`tls_coefficients`'
    coefficients (kernels.cell_integrals)."""
    gorder, gstart = factor[2], factor[3]
    nact = gstart.shape[0] - 1
    cells = np.empty(nact, dtype=np.int64)
    for s in range(nact):
        cells[s] = gcell[gorder[gstart[s]]]
    return cells


def empty_factor(dim):
    """A :func:`tls_factor` result of no cells, of the types the kernel
    returns in ``dim`` dimensions (a placeholder for the compiled loop's
    run data)."""
    m = 1 + dim + dim * (dim + 1) // 2
    index = np.zeros(0, dtype=np.int64)
    start = np.zeros(1, dtype=np.int64)
    return (index, start, index.copy(), start.copy(), np.zeros((0, 6)), np.zeros((0, m)),
            np.zeros((0, 2), dtype=np.bool_), np.zeros((0, 2, m + 1, m + 1)),
            np.zeros((0, 2, m + 1), dtype=np.int64))


@njit(cache=True, error_model="numpy")
def tls_reconstruct(x, V, values, pcell, xg, wg, gcell, ncells, out):
    """out[g] (ng, k) = the TLS fit of the particle ``values`` (n, k) of the
    cell gcell[g] at the Gauss point xg[g] (see the module docstring):
    :func:`tls_apply` on :func:`tls_factor`.

    ``x`` (n, d) particle positions, ``V`` (n,) volumes, ``pcell`` (n,) the
    cell of each particle (scikit-fem numbering: ix + nx iy + nx ny iz),
    ``xg`` (ng, d), ``wg`` (ng,), ``gcell`` (ng,) the rule; ``ncells`` the
    grid's number of cells."""
    tls_apply(x, V, values, xg, tls_factor(x, V, pcell, xg, wg, gcell, ncells), out)
