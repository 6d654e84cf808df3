"""The lumped grid solve with the tiny-mass merge, compiled.

The rule is the one of :mod:`skfem_mpm.solve.grid_system` (the reference,
which the tests compare this kernel with): per velocity component c, a free
dof k with mass is *small* when

    m_k < tol * max_{j ~ k} m_j          (j ~ k: |index offset| <= p per axis)

and moves with its heaviest neighbours (all of those within a relative
``TIE`` of the heaviest, equally shared), followed through small masters
until dofs that are not small: x_k = sum_j T_kj x_j. With the merging matrix
T the lumped solve becomes

    m_r = T^T m,   x_r = T^T rhs / m_r + g   (free kept dofs),
    x_r = the constraint value               (constrained kept dofs),
    x = T x_r,  0 on dofs without mass (constrained or not).

A master is heavier than its small dof by at least 1/tol, so resolving the
small dofs from the heaviest down finds every master's row already
resolved. A row is a short list of (kept dof, weight); ties can branch it,
and a row longer than ``MAX_ENTRIES`` makes the kernel return -1 (the
caller then takes the reference solve).

Dofs are numbered a + nbx (b + nby c) on a tensor grid of nbx x nby x nbz
functions (1D: nby = nbz = 1; 2D: nbz = 1); the cells sharing dofs with k
span index offsets -p..p on each axis.
"""
import numpy as np
from numba import njit

__all__ = ["merged_lumped_solve_axes", "merging_rows", "neighbour_maxima", "TIE",
           "MAX_ENTRIES"]

TIE = 1e-9          # as grid_system._Reduction.TIE
MAX_ENTRIES = 32    # (kept dof, weight) pairs of one small dof's row


@njit(cache=True, inline="always", error_model="numpy")
def _box(k, nbx, nby, nbz, p):
    """The index ranges (a0, a1, b0, b1, c0, c1) of the dofs sharing a cell
    with dof k (offsets -p..p per axis, cut at the grid)."""
    a = k % nbx
    b = (k // nbx) % nby
    c = k // (nbx * nby)
    return (max(0, a - p), min(nbx, a + p + 1), max(0, b - p), min(nby, b + p + 1),
            max(0, c - p), min(nbz, c + p + 1))


@njit(cache=True, error_model="numpy")
def _heaviest_first(dofs, mass):
    """``dofs`` (ascending) ordered by decreasing mass, ties in ascending dof
    order: ``dofs[np.argsort(-mass[dofs], kind="stable")]``, as a bottom-up
    merge sort (numba's argsort compiles a general sort, seconds cold)."""
    order = dofs.copy()
    spare = np.empty_like(order)
    n = order.shape[0]
    width = 1
    while width < n:
        for lo in range(0, n, 2 * width):
            mid = min(lo + width, n)
            hi = min(lo + 2 * width, n)
            i, j = lo, mid
            for k in range(lo, hi):  # the left run wins ties: stable
                if j >= hi or (i < mid and mass[order[i]] >= mass[order[j]]):
                    spare[k] = order[i]
                    i += 1
                else:
                    spare[k] = order[j]
                    j += 1
        order, spare = spare, order
        width *= 2
    return order


@njit(cache=True, error_model="numpy")
def _neighbour_max(mass, k, nbx, nby, nbz, p):
    """max of m_j over the dofs j sharing a cell with k (k included)."""
    a0, a1, b0, b1, c0, c1 = _box(k, nbx, nby, nbz, p)
    big = 0.0
    for cc in range(c0, c1):
        for bb in range(b0, b1):
            row = (cc * nby + bb) * nbx
            for aa in range(a0, a1):
                m = mass[row + aa]
                if m > big:
                    big = m
    return big


@njit(cache=True, error_model="numpy")
def neighbour_maxima(mass, nbx, nby, nbz, p, out):
    """out_k = max of m_j over the dofs j sharing a cell with k (k
    included) for dofs with mass, 0 for the others."""
    for k in range(mass.shape[0]):
        out[k] = _neighbour_max(mass, k, nbx, nby, nbz, p) if mass[k] > 0.0 else 0.0


@njit(cache=True, error_model="numpy")
def merging_rows(mass, neighbour_max, constrained, c, nbx, nby, nbz, p, tol, small, entries,
                 row_dof, row_weight):
    """The merging matrix T of velocity component c (module docstring):
    small[k] whether dof k is small (free in component c: not
    ``constrained[k, c]``), and for each small dof its row of T,
    (row_dof[k, e], row_weight[k, e]) for e < entries[k], in kept dofs
    (which may be constrained: a small dof then moves with them).
    ``neighbour_max`` as :func:`neighbour_maxima` gives it. Returns the
    number of small dofs, or -1 when a row outgrew MAX_ENTRIES (the rows
    are then not valid)."""
    nd = mass.shape[0]
    count = 0
    for k in range(nd):
        small[k] = mass[k] > 0.0 and not constrained[k, c] and \
            mass[k] < tol * neighbour_max[k]
        if small[k]:
            count += 1
    smalls = np.flatnonzero(small)
    order = _heaviest_first(smalls, mass)
    for s in order:  # heaviest first: masters are resolved before
        a0, a1, b0, b1, c0, c1 = _box(s, nbx, nby, nbz, p)
        top = (1.0 - TIE) * neighbour_max[s]
        masters = 0
        for cc in range(c0, c1):
            for bb in range(b0, b1):
                row = (cc * nby + bb) * nbx
                for aa in range(a0, a1):
                    if mass[row + aa] >= top:
                        masters += 1
        share = 1.0 / masters
        n = 0
        for cc in range(c0, c1):
            for bb in range(b0, b1):
                row = (cc * nby + bb) * nbx
                for aa in range(a0, a1):
                    j = row + aa
                    if mass[j] < top:
                        continue
                    if small[j]:
                        for e in range(entries[j]):
                            if n == MAX_ENTRIES:
                                return -1
                            row_dof[s, n] = row_dof[j, e]
                            row_weight[s, n] = share * row_weight[j, e]
                            n += 1
                    else:
                        if n == MAX_ENTRIES:
                            return -1
                        row_dof[s, n] = j
                        row_weight[s, n] = share
                        n += 1
        entries[s] = n
    return count


@njit(cache=True, error_model="numpy")
def merged_lumped_solve_axes(mass, rhs, gravity, constrained, values, has_values, nbx, nby,
                             nbz, p, tol, out):
    """out = the merged lumped solve of every component (module docstring)
    on a grid of nbx x nby x nbz functions; returns the largest number of
    small dofs over the components, or -1 when a row outgrew MAX_ENTRIES
    (``out`` is then not valid)."""
    nd, dim = rhs.shape
    neighbour_max = np.empty(nd)
    neighbour_maxima(mass, nbx, nby, nbz, p, neighbour_max)
    small = np.zeros(nd, dtype=np.bool_)
    entries = np.zeros(nd, dtype=np.int64)
    row_dof = np.empty((nd, MAX_ENTRIES), dtype=np.int64)
    row_weight = np.empty((nd, MAX_ENTRIES))
    b_r = np.empty(nd)
    m_r = np.empty(nd)
    most = 0
    for c in range(dim):
        count = merging_rows(mass, neighbour_max, constrained, c, nbx, nby, nbz, p, tol, small,
                             entries, row_dof, row_weight)
        if count < 0:
            return -1
        most = max(most, count)
        smalls = np.flatnonzero(small)
        # restrict: T^T rhs and T^T m on the kept dofs
        for k in range(nd):
            b_r[k] = rhs[k, c]
            m_r[k] = mass[k]
        for s in smalls:
            for e in range(entries[s]):
                j = row_dof[s, e]
                b_r[j] += row_weight[s, e] * rhs[s, c]
                m_r[j] += row_weight[s, e] * mass[s]
        # solve on the kept dofs, then prolong to the small ones
        for k in range(nd):
            if small[k]:
                continue
            if mass[k] <= 0.0:
                out[k, c] = 0.0
            elif constrained[k, c]:
                out[k, c] = values[k, c] if has_values else 0.0
            else:
                out[k, c] = b_r[k] / m_r[k] + gravity[c]
        for s in smalls:
            x = 0.0
            for e in range(entries[s]):
                x += row_weight[s, e] * out[row_dof[s, e], c]
            out[s, c] = x
    return most
