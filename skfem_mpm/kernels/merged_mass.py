"""The consistent mass with the tiny-mass merge, compiled.

The rule is the one of :mod:`skfem_mpm.solve.grid_system` (the reference,
which the tests compare these kernels with): with the merging matrix T of
one velocity component (dofs x kept dofs, :func:`skfem_mpm.kernels.tiny_mass.merging_rows`:
a small dof moves with its heaviest neighbours, x_s = sum_j T_sj x_j) the
consistent-mass equations M' x = rhs become

    (T^T M' T)_FF x_F = (T^T rhs)_F - (T^T M' T)_FC x_C,    x = T x_r,

with M' the stencil with the fast rows lumped (as
:func:`skfem_mpm.kernels.mpm.compact_system` lumps them), F the kept free
dofs (free, with mass, not small) and C the kept constrained ones (their
known values x_C). Dofs without mass stay 0 (or their constraint value).

:func:`merged_system` writes T^T M' T row by row: row i sums the rows k of
M' that move with i (k = i and the small dofs whose T row holds i, weight
T_ki), each column l taken through T (a small l spreads onto its kept
dofs). Its columns are the kept dofs near i (a merge reaches past the
(2p + 1)^dim stencil), so the rows are packed (ELL, width the longest row;
an unused entry is 0 on the row's own column) for the conjugate gradients
of :func:`skfem_mpm.kernels.mpm.ell_pcg`; the entries of the stencil's
offsets are also written in the stencil's slot order, the rows the
Kronecker preconditioner is fitted to
(:func:`skfem_mpm.kernels.kronecker.fit_kronecker`; the entries beyond the
stencil are left out of the fit only). :func:`merged_problem` restricts a
right-hand side and :func:`merged_expand` prolongs a solution.

The restriction and the reduced lumped mass m_r = T^T m (the Jacobi
preconditioner) add the small dofs' shares in the order of
:func:`skfem_mpm.kernels.tiny_mass.merged_lumped_solve_axes`.
"""
import numpy as np
from numba import njit

__all__ = ["merged_system", "merged_problem", "merged_expand", "EXTRA"]

EXTRA = 1
"""A row of T^T M' T holds at most (1 + EXTRA) (2p + 1)^dim entries, and as
many constrained columns; :func:`merged_system` returns -1 for a longer
one (the caller then takes the general grid system's sparse solve)."""


@njit(cache=True, inline="always")
def _coords(k, nbx, nby):
    return k % nbx, (k // nbx) % nby, k // (nbx * nby)


@njit(cache=True, inline="always")
def _slot(da, db, dc, p, dim):
    """The stencil slot of the index offsets (da, db, dc), or -1 outside
    the stencil."""
    if da < -p or da > p or db < -p or db > p or dc < -p or dc > p:
        return -1
    width = 2 * p + 1
    slot = da + p
    if dim >= 2:
        slot += (db + p) * width
    if dim == 3:
        slot += (dc + p) * width * width
    return slot


@njit(cache=True, error_model="numpy")
def _listed(value, j, r, dof, value_of, count):
    """Add ``value`` to the entry of column j in row r's list (dof[r],
    value_of[r], count[r] entries used: the extra entries or the
    constrained columns); False when the list is full. (Called
    for these rarer entries only: a call with array arguments costs about
    as much as a hundred additions.)"""
    n = count[r]
    for e in range(n):
        if dof[r, e] == j:
            value_of[r, e] += value
            return True
    if n == dof.shape[1]:
        return False
    dof[r, n] = j
    value_of[r, n] = value
    count[r] = n + 1
    return True


@njit(cache=True, error_model="numpy")
def merged_system(A, cols, F, fcols, rows, index, constrained, c, mass, small, entries, row_dof,
                  row_weight, p, nbx, nby, dim, kept_rows, kept_index, inv_diag, fit, Ar, colsr,
                  Fr, fcolsr, sizes):
    """T^T M' T on the kept free dofs of component c (module docstring).

    In: the ELL rows (A, cols, F, fcols) that compact_system writes (with
    its fixed columns) for the free dofs ``rows`` (``index``: dof -> row or
    -1), the merge of :func:`~skfem_mpm.kernels.tiny_mass.merging_rows`
    (small, entries, row_dof, row_weight), ``constrained`` (dofs, dim), the
    lumped ``mass``. Out: kept_rows[:n] (the kept free dofs, ascending),
    kept_index (dof -> reduced row or -1), inv_diag[:n] = 1 / (T^T m), the
    stencil-slot rows ``fit`` (n, (2p + 1)^dim), the packed rows Ar, colsr
    (flat buffers holding n x W: entries, reduced columns) and the
    constrained columns Fr, fcolsr (n x WF: entries, dofs), sizes = (n, W,
    WF). Returns n, or -1 when a row outgrew its lists (EXTRA) or a buffer."""
    nd = mass.shape[0]
    ns = A.shape[1]
    n = 0
    for k in range(nd):
        kept_index[k] = -1
    for r in range(rows.shape[0]):
        k = rows[r]
        if not small[k]:
            kept_rows[n] = k
            kept_index[k] = n
            n += 1
    # the small dofs that move with each kept free dof (ascending), weights T_ki
    count = np.zeros(n + 1, dtype=np.int64)
    for s in range(nd):
        if small[s]:
            for e in range(entries[s]):
                r = kept_index[row_dof[s, e]]
                if r >= 0:
                    count[r + 1] += 1
    for r in range(n):
        count[r + 1] += count[r]
    spread_dof = np.empty(count[n], dtype=np.int64)
    spread_weight = np.empty(count[n])
    fill = count[:n].copy()
    m_r = np.empty(n)
    for r in range(n):
        m_r[r] = mass[kept_rows[r]]
    for s in range(nd):
        if small[s]:
            for e in range(entries[s]):
                r = kept_index[row_dof[s, e]]
                if r >= 0:
                    spread_dof[fill[r]] = s
                    spread_weight[fill[r]] = row_weight[s, e]
                    fill[r] += 1
                    m_r[r] += row_weight[s, e] * mass[s]
    for r in range(n):
        inv_diag[r] = 1.0 / m_r[r]
    out = fit[:n * ns].reshape((n, ns))
    out[:] = 0.0
    width = 2 * p + 1
    slot_a = np.empty(ns, dtype=np.int64)  # each slot's index offsets
    slot_b = np.zeros(ns, dtype=np.int64)
    slot_c = np.zeros(ns, dtype=np.int64)
    for s in range(ns):
        slot_a[s] = s % width - p
        if dim >= 2:
            slot_b[s] = (s // width) % width - p
        if dim == 3:
            slot_c[s] = s // (width * width) - p
    lists = EXTRA * ns
    extra_dof = np.empty((n, lists), dtype=np.int64)
    extra_value = np.empty((n, lists))
    n_extra = np.zeros(n, dtype=np.int64)
    fixed_dof = np.empty((n, lists), dtype=np.int64)
    fixed_value = np.empty((n, lists))
    n_fixed = np.zeros(n, dtype=np.int64)
    for r in range(n):
        i = kept_rows[r]
        ai, bi, ci = _coords(i, nbx, nby)
        for q in range(-1, count[r + 1] - count[r]):
            if q < 0:
                k, w = i, 1.0
            else:
                k, w = spread_dof[count[r] + q], spread_weight[count[r] + q]
            ak, bk, ck = _coords(k, nbx, nby)
            ak, bk, ck = ak - ai, bk - bi, ck - ci  # k's offsets from i
            fr = index[k]
            for part in range(2):
                for s in range(ns):
                    if part == 0:
                        v, l = A[fr, s], rows[cols[fr, s]]
                    else:
                        v, l = F[fr, s], fcols[fr, s]
                    if v == 0.0:
                        continue
                    v = w * v
                    spread = small[l]  # onto its kept dofs
                    for e in range(entries[l] if spread else 1):
                        # entry (i, j) += value: a kept free column into the
                        # stencil slot of its offset from i or else the row's
                        # extra entries, a constrained one into its fixed
                        # entries (columns without mass hold 0: skipped)
                        if spread:
                            j = row_dof[l, e]
                            value = v * row_weight[l, e]
                            aj, bj, cj = _coords(j, nbx, nby)
                            slot = _slot(aj - ai, bj - bi, cj - ci, p, dim)
                        else:
                            j = l
                            value = v
                            slot = _slot(ak + slot_a[s], bk + slot_b[s], ck + slot_c[s], p, dim)
                        if kept_index[j] >= 0:
                            if slot >= 0:
                                out[r, slot] += value
                            elif not _listed(value, j, r, extra_dof, extra_value, n_extra):
                                return -1
                        elif constrained[j, c] and mass[j] > 0.0:
                            if not _listed(value, j, r, fixed_dof, fixed_value, n_fixed):
                                return -1
    # packed rows: the stencil's nonzero entries in slot order, then the extra ones
    W = 1
    WF = 1
    for r in range(n):
        used = n_extra[r]
        for s in range(ns):
            if out[r, s] != 0.0:
                used += 1
        W = max(W, used)
        WF = max(WF, n_fixed[r])
    if n * W > Ar.shape[0] or n * WF > Fr.shape[0]:
        return -1
    packed = Ar[:n * W].reshape((n, W))
    packed_cols = colsr[:n * W].reshape((n, W))
    fixed = Fr[:n * WF].reshape((n, WF))
    fixed_cols = fcolsr[:n * WF].reshape((n, WF))
    for r in range(n):
        i = kept_rows[r]
        ai, bi, ci = _coords(i, nbx, nby)
        e = 0
        for s in range(ns):
            if out[r, s] != 0.0:  # a kept free dof at the slot's offset
                aa = ai + s % width - p
                bb = bi + (s // width) % width - p if dim >= 2 else bi
                cc = ci + s // (width * width) - p if dim == 3 else ci
                j = (cc * nby + bb) * nbx + aa
                packed[r, e] = out[r, s]
                packed_cols[r, e] = kept_index[j]
                e += 1
        for q in range(n_extra[r]):
            packed[r, e] = extra_value[r, q]
            packed_cols[r, e] = kept_index[extra_dof[r, q]]
            e += 1
        for q in range(e, W):
            packed[r, q] = 0.0
            packed_cols[r, q] = r
        for q in range(WF):
            if q < n_fixed[r]:
                fixed[r, q] = fixed_value[r, q]
                fixed_cols[r, q] = fixed_dof[r, q]
            else:
                fixed[r, q] = 0.0
                fixed_cols[r, q] = i
    sizes[0] = n
    sizes[1] = W
    sizes[2] = WF
    return n


@njit(cache=True, error_model="numpy")
def merged_problem(kept_rows, kept_index, small, entries, row_dof, row_weight, rhs, values,
                   has_values, prev, has_prev, comps, j0, Fr, fcolsr, b, x):
    """One problem's columns j = j0 + l (component c = comps[l]) of the
    merged system: b[r, j] = (T^T rhs)[i, c] - sum_q Fr[r, q] values[fcolsr[r, q], c]
    (i = kept_rows[r]) and the warm start x[r, j] = prev[i, c] (0 without
    one); as :func:`skfem_mpm.kernels.mpm.compact_problem` for the merged rows."""
    nr = b.shape[0]
    nc = comps.shape[0]
    for r in range(nr):
        i = kept_rows[r]
        for l in range(nc):
            b[r, j0 + l] = rhs[i, comps[l]]
            x[r, j0 + l] = prev[i, comps[l]] if has_prev else 0.0
    for s in range(small.shape[0]):
        if small[s]:
            for e in range(entries[s]):
                r = kept_index[row_dof[s, e]]
                if r >= 0:
                    for l in range(nc):
                        b[r, j0 + l] += row_weight[s, e] * rhs[s, comps[l]]
    if has_values:
        for r in range(nr):
            for l in range(nc):
                acc = b[r, j0 + l]
                for q in range(Fr.shape[1]):
                    acc -= Fr[r, q] * values[fcolsr[r, q], comps[l]]
                b[r, j0 + l] = acc


@njit(cache=True, error_model="numpy")
def merged_expand(kept_rows, small, entries, row_dof, row_weight, x, comps, j0, out):
    """out = T x_r for one problem: out[kept_rows[r], comps[l]] = x[r, j0 + l],
    then each small dof the weighted sum of its kept dofs (constrained ones
    hold their values in ``out`` already)."""
    for r in range(x.shape[0]):
        for l in range(comps.shape[0]):
            out[kept_rows[r], comps[l]] = x[r, j0 + l]
    for s in range(small.shape[0]):
        if small[s]:
            for l in range(comps.shape[0]):
                c = comps[l]
                acc = 0.0
                for e in range(entries[s]):
                    acc += row_weight[s, e] * out[row_dof[s, e], c]
                out[s, c] = acc
