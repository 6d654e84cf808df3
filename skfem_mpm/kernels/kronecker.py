"""A Kronecker-product preconditioner for the consistent particle mass.

On a tensor grid a mass matrix whose quadrature points form a tensor
layout with product weights is a Kronecker product of 1D banded matrices:
the Gauss mass M_G = M_y (x) M_x, and also the particle mass
M = sum_p m_p N(x_p) N(x_p)^T of particles seeded per axis with masses
m_p = mu_x(x_p) mu_y(y_p). The preconditioner (for the free dofs F of one
constraint pattern, inside their index box B) is

    P^-1 = S^-1 R (K_y,B (x) K_x,B)^-1 R^T S^-1,
    S = diag(sqrt(s_k / l_k)),  l_k = l_x,a l_y,b the row sums of K,

with R the zero extension from F into the box. It is symmetric positive
definite for any particle layout (so conjugate gradients converge), and
each application costs two banded triangular solves per axis. In 3D,
K = K_z (x) K_y (x) K_x and l_k = l_x,a l_y,b l_z,c;
:func:`apply_kronecker_axes` applies the three factors one axis after the
other (the same passes as :func:`apply_kronecker`, which it equals on one
z layer), and in 3D the preconditioner is block diagonal over the coupled
components of the free-dof matrix (:func:`kronecker_boxes`): each
component its own box and factors, a row coupled to nothing (a fast row
lumped whole) its own diagonal, so that two bodies apart get a Kronecker
product each instead of one fitted to both. Two choices of the factors:

* the system's own axis marginals (:func:`fit_kronecker`, the consistent
  mass solves): K_x[a, a'] = sum of A_kj over the free pairs with
  a_k = a, a_j = a' (any b), likewise K_y, where A is the free-dof matrix
  the solve sees (fast rows lumped), and s_k = sum_j A_kj. The marginal
  of a Kronecker product is its factor times a number (the partition of
  unity: sum_b N_b = 1), so P = A wherever A is a Kronecker product: in
  1D always (P is A's banded factorisation), in 2D for particles on a
  tensor layout with product masses away from lumped rows. Van Loan and
  Pitsianis (1993) call this the first step of the nearest Kronecker
  product's power iteration from the all-ones factor.
* the unit-density Gauss mass (:func:`axis_mass_bands`) with s_k the
  particle lumped mass, for a matrix close to rho M_G (the spline
  reconstruction's fit, :mod:`skfem_mpm.solve.compiled_reconstruct`).

Measured, CG iterations per run to 1e-13 (MUSL, warm started), Gauss
factors -> marginals: vibrating string 32 quadratic cells, 4 particles
per cell, 3.0 -> 1.0; vibrating plate 16 x 16, 2 x 2 particles per cell,
12.6 -> 8.6; the same with 3 x 3, 5.3 -> 1.5; the expanding block of
``bench --consistent`` at 64 x 64 (USL), 21.0 -> 21.8, and with the 3-layer
fringe correction (:mod:`skfem_mpm.kernels.fringe`) from the first solve 4.7 -> 4.7.
3D, marginals, one box over every free dof -> a box per coupled component:
T3 colliding spheres at 8^3 cells, consistent MUSL, t_end 0.3 (before
contact), 54.6 -> 23.7 iterations per solve.
"""
import numpy as np
from numba import njit, prange

from .weights import FAST, IN_ORDER

__all__ = ["axis_mass_bands", "banded_cholesky", "coupled_components", "fit_kronecker",
           "KroneckerData", "apply_kronecker", "apply_kronecker_replaced", "apply_kronecker_axes",
           "kronecker_boxes", "BOX_FIELDS", "MAX_BOXES"]


def axis_mass_bands(grid, axis):
    """The unit-density Gauss mass matrix of one axis' B-splines as bands
    (n, p + 1), bands[i, d] = M_(i, i - d), and its row sums (n,)."""
    p = grid.degree
    u = grid.breakpoints[axis]
    xg, wg = np.polynomial.legendre.leggauss(p + 1)
    h = np.diff(u)
    x = (u[:-1, None] + 0.5 * h[:, None] * (xg[None, :] + 1.0)).ravel()
    w = (0.5 * h[:, None] * wg[None, :]).ravel()
    first, values, _ = grid.axis_functions(axis, x, backend="numpy")
    n = grid.basis_per_axis[axis]
    bands = np.zeros((n, p + 1))
    for a in range(p + 1):
        for a2 in range(a + 1):  # row first + a, column first + a2 (lower part)
            np.add.at(bands, (first + a, a - a2), w * values[:, a] * values[:, a2])
    rows = np.zeros(n)
    np.add.at(rows, (first[:, None] + np.arange(p + 1)[None, :]).ravel(),
              (w[:, None] * values).ravel())
    return bands, rows


@njit(cache=True, error_model="numpy", fastmath=FAST)
def banded_cholesky_into(bands, lo, hi, L):
    """L[:hi - lo] = the lower Cholesky factor of the principal block
    [lo, hi) of a banded SPD matrix, L[i, d] = L_(i, i - d) (rows relative
    to lo; Golub & Van Loan, Matrix Computations, 4th ed., Alg. 4.3.5)."""
    n = hi - lo
    p = bands.shape[1] - 1
    for i in range(n):
        for d in range(min(p, i), 0, -1):
            j = i - d
            s = bands[lo + i, d]
            for e in range(d + 1, min(p, i) + 1):
                s -= L[i, e] * L[j, e - d]
            L[i, d] = s / L[j, 0]
        s = bands[lo + i, 0]
        for d in range(1, min(p, i) + 1):
            s -= L[i, d] * L[i, d]
        L[i, 0] = np.sqrt(s)


@njit(cache=True, error_model="numpy", fastmath=FAST)
def banded_cholesky(bands, lo, hi):
    """Lower Cholesky factor L of the principal block [lo, hi) of a banded
    SPD matrix, L[i, d] = L_(i, i - d) (rows relative to lo)."""
    L = np.zeros((hi - lo, bands.shape[1]))
    banded_cholesky_into(bands, lo, hi, L)
    return L


FIT_BLOCKS = 4
"""Blocks of rows whose axis marginals :func:`fit_kronecker` sums in
parallel (a constant: the factors' bits do not depend on the threads)."""

FIT_BLOCKS_FROM = 2048
"""Systems of fewer rows sum their marginals in one block, straight into
the work space: on a small system the blocks' partial arrays and the
parallel region cost more than the sums (S1, 32 cells: about 1 us a step)."""


@njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def _block_marginals(A, coords, p, lo, hi, along, bands, sums, row_sums):
    """Rows lo..hi-1 of :func:`_axis_marginals` added into ``bands`` and
    ``sums`` (one block's), their row sums into ``row_sums``."""
    ns = A.shape[1]
    width = 2 * p + 1
    nsb = width if ns > width else 1  # slots per axis: 1 on an axis the grid lacks
    nsc = width if ns > width * width else 1
    for r in range(lo, hi):
        a = coords[r, 0]
        b = coords[r, 1]
        c = coords[r, 2]
        if a < 0:  # a diagonal row (no box): its row sum only
            total = 0.0
            for s in range(ns):
                total += A[r, s]
            row_sums[r] = total
            continue
        along[:] = 0.0
        for sc in range(nsc):
            for sb in range(nsb):
                first = (sc * nsb + sb) * width
                line = 0.0
                for sa in range(width):
                    v = A[r, first + sa]
                    along[0, sa] += v
                    line += v
                along[1, sb] += line
                along[2, sc] += line
        total = 0.0
        for sa in range(width):
            total += along[0, sa]
        for o in range(p + 1):  # slot p - o: the offset -o
            bands[0, a, o] += along[0, p - o]
            if nsb > 1:
                bands[1, b, o] += along[1, p - o]
            if nsc > 1:
                bands[2, c, o] += along[2, p - o]
        if nsb == 1:
            bands[1, b, 0] += total
        if nsc == 1:
            bands[2, c, 0] += total
        row_sums[r] = total
        sums[0, a] += total
        sums[1, b] += total
        sums[2, c] += total


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def _axis_marginals(A, coords, p, bands, sums):
    """bands[d] += the lower bands of the marginal of A on axis d (box-local
    numbering), sums[d] += its row sums; returns the row sums of A (one per
    row). A's slot (s_c w + s_b) w + s_a holds the dof at index offsets
    (s_a, s_b, s_c) - p from its row's (w = 2 p + 1; compact_system's ELL
    rows), so a slot's axes are known without decoding its column; each
    row is first summed per offset (short dependency chains). The rows
    are summed in FIT_BLOCKS blocks in parallel, each into its own bands
    and sums, which are then added in block order (below FIT_BLOCKS_FROM
    rows :func:`fit_kronecker` calls :func:`_one_block_marginals`)."""
    nr = A.shape[0]
    width = 2 * p + 1
    n = bands.shape[1]
    part_bands = np.zeros((FIT_BLOCKS, 3, n, p + 1))
    part_sums = np.zeros((FIT_BLOCKS, 3, n))
    row_sums = np.empty(nr)
    for t in prange(FIT_BLOCKS):
        along = np.empty((3, width))  # one row's sums per index offset of each axis
        _block_marginals(A, coords, p, t * nr // FIT_BLOCKS, (t + 1) * nr // FIT_BLOCKS, along,
                         part_bands[t], part_sums[t], row_sums)
    for t in range(FIT_BLOCKS):
        for d in range(3):
            for i in range(n):
                sums[d, i] += part_sums[t, d, i]
                for o in range(p + 1):
                    bands[d, i, o] += part_bands[t, d, i, o]
    return row_sums


@njit(cache=True, error_model="numpy", fastmath=FAST)
def _one_block_marginals(A, coords, p, bands, sums):
    """:func:`_axis_marginals` of a small system: every row in one block,
    straight into ``bands`` and ``sums``, outside any parallel region (the
    bits depend on the system's size, never on the threads)."""
    row_sums = np.empty(A.shape[0])
    _block_marginals(A, coords, p, 0, A.shape[0], np.empty((3, 2 * p + 1)), bands, sums,
                     row_sums)
    return row_sums


@njit(cache=True, error_model="numpy", fastmath=FAST)
def fit_kronecker(A, coords, Lx, Ly, Lz, inv_scale, bands, sums):
    """The Kronecker preconditioner of the free-dof matrix A (ELL rows in
    the slot order of :func:`skfem_mpm.kernels.mpm.compact_system`, of the
    dofs at box-local indices ``coords`` (rows, 3): a, b, c) from its own
    axis marginals (the module docstring): the
    factors Lx, Ly, Lz of the box (nx, ny, nz = their lengths; an axis of
    length 1 is not applied and has no factor) with 1 / L_ii in column 0,
    and inv_scale = 1 / sqrt(s_k / l_k). ``bands`` (3, n, p + 1) and
    ``sums`` (3, n) are work space, n >= the box's longest side. A box line
    without a free dof has a zero marginal row: it gets a unit diagonal
    (it couples to nothing). A row with coords[r, 0] < 0 is a diagonal row
    (:func:`kronecker_boxes`): left out of the marginals, inv_scale = 1 /
    its row sum. With several boxes (3D) the coordinates are those of the
    concatenated factors (a box's x0 + a, ...): the boxes' rows do not
    couple, so their marginals, and the factors, are blocks of the
    concatenated ones."""
    bands[:] = 0.0
    sums[:] = 0.0
    if A.shape[0] < FIT_BLOCKS_FROM:
        row_sums = _one_block_marginals(A, coords, Lx.shape[1] - 1, bands, sums)
    else:
        row_sums = _axis_marginals(A, coords, Lx.shape[1] - 1, bands, sums)
    for d, L in enumerate((Lx, Ly, Lz)):
        n = L.shape[0]
        if n == 1:  # not applied: the identity (1 / L_00 = 1), its sums left out below
            L[0, 0] = 1.0
            for k in range(1, L.shape[1]):
                L[0, k] = 0.0
            continue
        for i in range(n):
            if bands[d, i, 0] <= 0.0:
                bands[d, i, 0] = 1.0
        banded_cholesky_into(bands[d], 0, n, L)
        for i in range(n):
            L[i, 0] = 1.0 / L[i, 0]
    for r in range(A.shape[0]):
        if coords[r, 0] < 0:  # a diagonal row: the inverse of its one entry
            inv_scale[r] = 1.0 / row_sums[r]
            continue
        lk = 1.0
        if Lx.shape[0] > 1:
            lk *= sums[0, coords[r, 0]]
        if Ly.shape[0] > 1:
            lk *= sums[1, coords[r, 1]]
        if Lz.shape[0] > 1:
            lk *= sums[2, coords[r, 2]]
        inv_scale[r] = 1.0 / np.sqrt(row_sums[r] / lk)


MAX_BOXES = 8
"""The most Kronecker boxes of one free-dof set (:func:`kronecker_boxes`):
the largest coupled components but the last get a box each, the others
share the last one."""


@njit(cache=True, error_model="numpy")
def coupled_components(A, rows, index, p, nbx, nby, label):
    """label[r] = the connected component of row r of the ELL matrix A in
    the graph of its nonzero off-diagonal entries (A's slot (s_c w + s_b) w
    + s_a of row r couples dof rows[r] to the dof at index offsets (s_a,
    s_b, s_c) - p, w = 2 p + 1, as compact_system writes it; ``index``:
    dof -> row or -1, over the whole grid), numbered in the order of their
    first row; returns the number of components (breadth-first search)."""
    nr, ns = A.shape
    width = 2 * p + 1
    nsb = width if ns > width else 1
    nsc = width if ns > width * width else 1
    pb = p if nsb > 1 else 0
    pc = p if nsc > 1 else 0
    centre = (ns - 1) // 2
    nbz = index.shape[0] // (nbx * nby)
    queue = np.empty(nr, dtype=np.int64)
    for r in range(nr):
        label[r] = -1
    count = 0
    for start in range(nr):
        if label[start] >= 0:
            continue
        label[start] = count
        queue[0] = start
        head = 0
        tail = 1
        while head < tail:
            r = queue[head]
            head += 1
            k = rows[r]
            a = k % nbx
            b = (k // nbx) % nby
            c = k // (nbx * nby)
            for sc in range(nsc):
                cc = c + sc - pc
                if cc < 0 or cc >= nbz:
                    continue
                for sb in range(nsb):
                    bb = b + sb - pb
                    if bb < 0 or bb >= nby:
                        continue
                    for sa in range(width):
                        s = (sc * nsb + sb) * width + sa
                        aa = a + sa - p
                        if s == centre or aa < 0 or aa >= nbx or A[r, s] == 0.0:
                            continue
                        q = index[(cc * nby + bb) * nbx + aa]
                        if q >= 0 and label[q] < 0:
                            label[q] = count
                            queue[tail] = q
                            tail += 1
        count += 1
    return count


@njit(cache=True, error_model="numpy")
def kronecker_boxes(A, rows, index, p, nbx, nby, capacity, coords, box_index, boxes, shape):
    """The Kronecker boxes of the free-dof rows ``rows`` of the ELL matrix A
    (2D and 3D; see :func:`coupled_components`, whose ``index`` it takes): a row
    coupled to no other is a diagonal row (coords -1, box_index -1); each
    coupled component gets the index box of its rows, the largest
    MAX_BOXES - 1 (by rows; the first of equal ones) one each, the others
    one together; when the boxes hold more than ``capacity`` entries, one
    box holds every coupled row. Writes each row's coordinates in the
    concatenated factors (``coords``, (rows, 3): x0 + a, y0 + b, z0 + c),
    its entry in the work space (``box_index``), the boxes' rows of
    :func:`apply_kronecker_axes` (``boxes``, at least MAX_BOXES rows) and
    the concatenated factors' lengths (``shape``: nz, ny, nx); returns the
    number of boxes. Two bodies apart thus get a preconditioner each,
    fitted to their own rows."""
    n = rows.shape[0]
    label = np.empty(n, dtype=np.int64)
    count = coupled_components(A, rows, index, p, nbx, nby, label)
    size = np.zeros(count, dtype=np.int64)
    for r in range(n):
        size[label[r]] += 1
    which = np.full(count, -1, dtype=np.int64)  # component -> box
    nb = 0
    for _ in range(MAX_BOXES - 1):  # the largest coupled components, one box each
        best = -1
        for i in range(count):
            if which[i] < 0 and size[i] > 1 and (best < 0 or size[i] > size[best]):
                best = i
        if best < 0:
            break
        which[best] = nb
        nb += 1
    shared = False
    for i in range(count):  # the rest share the last box
        if which[i] < 0 and size[i] > 1:
            which[i] = nb
            shared = True
    if shared:
        nb += 1
    for attempt in range(2):
        lo = np.full((nb, 3), 1 << 62, dtype=np.int64)
        hi = np.zeros((nb, 3), dtype=np.int64)
        for r in range(n):
            k = which[label[r]]
            if k < 0:
                continue
            d = rows[r]
            abc = (d % nbx, (d // nbx) % nby, d // (nbx * nby))
            for e in range(3):
                lo[k, e] = min(lo[k, e], abc[e])
                hi[k, e] = max(hi[k, e], abc[e] + 1)
        entries = 0
        for k in range(nb):
            entries += (hi[k, 0] - lo[k, 0]) * (hi[k, 1] - lo[k, 1]) * (hi[k, 2] - lo[k, 2])
        if entries <= capacity or nb <= 1 or attempt == 1:
            break
        for i in range(count):  # too large: one box for every coupled row
            if which[i] >= 0:
                which[i] = 0
        nb = 1
    first = 0
    x0 = y0 = z0 = 0
    planar = index.shape[0] == nbx * nby  # 2D: every box one layer, one z factor of length 1
    for k in range(nb):
        nx, ny, nz = hi[k, 0] - lo[k, 0], hi[k, 1] - lo[k, 1], hi[k, 2] - lo[k, 2]
        boxes[k, 0] = first
        boxes[k, 1] = nz
        boxes[k, 2] = ny
        boxes[k, 3] = nx
        boxes[k, 4] = x0
        boxes[k, 5] = y0
        boxes[k, 6] = z0
        first += nz * ny * nx
        x0 += nx
        y0 += ny
        if not planar:
            z0 += nz
    shape[0] = max(z0, 1)
    shape[1] = y0
    shape[2] = x0
    for r in range(n):
        k = which[label[r]]
        if k < 0:
            coords[r, 0] = -1
            coords[r, 1] = -1
            coords[r, 2] = -1
            box_index[r] = -1
            continue
        d = rows[r]
        a = d % nbx - lo[k, 0]
        b = (d // nbx) % nby - lo[k, 1]
        c = d // (nbx * nby) - lo[k, 2]
        coords[r, 0] = boxes[k, 4] + a
        coords[r, 1] = boxes[k, 5] + b
        coords[r, 2] = boxes[k, 6] + c
        box_index[r] = boxes[k, 0] + (c * boxes[k, 2] + b) * boxes[k, 3] + a
    return nb


def _inverse_diagonal(L):
    out = L.copy()
    out[:, 0] = 1.0 / L[:, 0]
    return out


class KroneckerData:
    """The factors, box and scaling of the preconditioner for one free-dof
    set (``rows`` in the grid's dof numbering, k = (c nby + b) nbx + a):
    from the Gauss axis masses (this constructor: ``bands``, ``row_sums``
    per axis as :func:`axis_mass_bands` gives them, ``lumped`` the
    particle lumped mass) or from a system's own marginals
    (:meth:`of_system`)."""

    def __init__(self, bands, row_sums, geometry, rows, lumped, previous=None):
        """``previous``: the data of an earlier step; its factors and box
        numbering are reused when it was built for the same free dofs."""
        if not self._reuse_box(geometry, rows, previous):
            self._box(geometry, rows)
            self._gauss_factors(bands, row_sums, rows)
        else:
            self.Lx, self.Ly, self.Lz, self.gauss = (previous.Lx, previous.Ly, previous.Lz,
                                                     previous.gauss)
        self.inv_scale = 1.0 / np.sqrt(lumped[rows] / self.gauss)

    @classmethod
    def of_system(cls, A, rows, geometry, previous=None, index=None, by_component=False,
                  fit=None):
        """The preconditioner of the free-dof matrix A itself (ELL rows of
        ``rows`` as compact_system writes them) by :func:`fit_kronecker`; the box
        numbering of ``previous`` is reused for the same free dofs. In 3D
        one box per coupled component of A (:func:`kronecker_boxes`;
        ``index``: dof -> row of A or -1, over the grid), built anew each
        time (the components follow A, not only its rows); in 2D the same
        with ``by_component`` where A has two or more coupled components,
        else the one box of the free dofs (StencilSystem asks for it with
        several bodies and without the fringe correction, which takes the
        one box: the search costs about as much as one of the factors'
        fits, a tenth of a consistent step at 128 x 128 cells). ``fit``:
        :func:`fit_kronecker` as the run calls it (its serial copy for a run
        on serial kernels: the same blocks, so the same bits, and a first
        use compiles one copy, the one the compiled loop calls, instead of
        both); None: :func:`fit_kronecker` itself."""
        fit = fit_kronecker if fit is None else fit
        self = cls.__new__(cls)
        p = geometry[0]
        boxes = 0
        if geometry[3] == 3 or (geometry[3] == 2 and by_component):
            boxes = self._coupled_boxes(A, rows, geometry, index)
        if geometry[3] == 3 or boxes > 1:
            nz, ny, nx = self.factor_shape
            self.Lx, self.Ly, self.Lz = (np.empty((nx, p + 1)), np.empty((ny, p + 1)),
                                         np.empty((nz, p + 1)))
            self.inv_scale = np.empty(rows.size)
            longest = max(self.factor_shape + (1,))
            fit(A, self.coords, self.Lx, self.Ly, self.Lz, self.inv_scale,
                          np.empty((3, longest, p + 1)), np.empty((3, longest)))
            return self
        self.boxes = None
        if not self._reuse_box(geometry, rows, previous):
            self._box(geometry, rows)
        shape = self.shape if len(self.shape) == 3 else (1,) + self.shape
        self.Lx, self.Ly = np.empty((shape[2], p + 1)), np.ones((shape[1], p + 1))
        self.Lz = np.ones((shape[0], p + 1))
        self.inv_scale = np.empty(rows.size)
        longest = max(shape)
        fit(A, self.coords, self.Lx, self.Ly, self.Lz, self.inv_scale,
                      np.empty((3, longest, p + 1)), np.empty((3, longest)))
        if len(self.shape) < 3:
            self.Lz = None
        return self

    def _reuse_box(self, geometry, rows, previous):
        """Take the box of ``previous`` when it was built for these rows."""
        self.key, self.geometry = rows.tobytes(), geometry
        if previous is None or previous.key != self.key or previous.geometry != geometry:
            return False
        self.a0, self.b0, self.c0 = previous.a0, previous.b0, previous.c0
        self.shape, self.box_index = previous.shape, previous.box_index
        self.coords, self.local = previous.coords, self.box_index
        return True

    def _coupled_boxes(self, A, rows, geometry, index):
        """The boxes of A's coupled components (:func:`kronecker_boxes`),
        every row's coordinates in the concatenated factors and its entry
        in the work space (``local``; -1: a diagonal row); returns their
        number."""
        p, nbx, nby, _ = geometry
        self.key, self.geometry = None, geometry
        n = rows.size
        self.coords = np.empty((n, 3), dtype=np.int64)
        self.local = self.box_index = np.empty(n, dtype=np.int64)
        boxes = np.zeros((MAX_BOXES, BOX_FIELDS), dtype=np.int64)
        shape = np.zeros(3, dtype=np.int64)
        nd = index.size
        nb = kronecker_boxes(np.ascontiguousarray(A), np.ascontiguousarray(rows, dtype=np.int64),
                             index, p, nbx, nby, nd, self.coords, self.box_index, boxes, shape)
        self.boxes = boxes[:nb]
        self.factor_shape = tuple(int(v) for v in shape)
        self.entries = int((self.boxes[:, 1] * self.boxes[:, 2] * self.boxes[:, 3]).sum())
        self.shape = None
        return nb

    def _box(self, geometry, rows):
        """The free dofs' index box: its first index per axis, its shape
        ((nz,) ny, nx; 1D: ny = 1), each row's indices in it (``coords``,
        (rows, 3): a, b, c) and its position in it."""
        p, nbx, nby, dim = geometry
        nby = nby if dim >= 2 else 1
        a, b, c = rows % nbx, (rows // nbx) % nby, rows // (nbx * nby)
        self.a0, self.b0, self.c0 = int(a.min()), int(b.min()), int(c.min())
        a1, b1, c1 = int(a.max()) + 1, int(b.max()) + 1, int(c.max()) + 1
        self.shape = (b1 - self.b0, a1 - self.a0)
        if dim == 3:
            self.shape = (c1 - self.c0,) + self.shape
        self.coords = np.stack((a - self.a0, b - self.b0, c - self.c0), axis=1).astype(np.int64)
        self.box_index = (((c - self.c0) * (b1 - self.b0) + (b - self.b0)) * (a1 - self.a0)
                          + (a - self.a0)).astype(np.int64)
        self.local = self.box_index

    def _gauss_factors(self, bands, row_sums, rows):
        """The banded Cholesky factors of the Gauss axis masses on the box
        (1 / L_ii in column 0: the kernel multiplies by it) and the Gauss
        row sums l_k of the rows."""
        p, nbx, nby, dim = self.geometry
        a = rows % nbx
        self.Lx = _inverse_diagonal(banded_cholesky(bands[0], self.a0, self.a0 + self.shape[-1]))
        self.gauss = row_sums[0][a]
        self.Ly, self.Lz = np.ones((1, p + 1)), None
        if dim >= 2:
            b = (rows // nbx) % nby
            self.Ly = _inverse_diagonal(banded_cholesky(bands[1], self.b0,
                                                        self.b0 + self.shape[-2]))
            self.gauss = self.gauss * row_sums[1][b]
        if dim == 3:
            c = rows // (nbx * nby)
            self.Lz = _inverse_diagonal(banded_cholesky(bands[2], self.c0,
                                                        self.c0 + self.shape[0]))
            self.gauss = self.gauss * row_sums[2][c]

    def args(self, nc, nt):
        """The arguments of :func:`apply_kronecker` before r and z (3D: of
        :func:`apply_kronecker_axes`, with the z factor after Ly and the
        boxes last)."""
        if getattr(self, "boxes", None) is not None:  # 3D, by components
            return (self.Lx, self.Ly, self.Lz, self.local, self.inv_scale,
                    np.empty(self.entries * nc), nt, self.boxes)
        box = np.empty(self.shape + (nc,))
        if len(self.shape) == 3:  # 3D, one box (the Gauss factors)
            nz, ny, nx = self.shape
            boxes = np.array([[0, nz, ny, nx, 0, 0, 0]], dtype=np.int64)
            return (self.Lx, self.Ly, self.Lz, self.local, self.inv_scale, box.ravel(), nt,
                    boxes)
        return self.Lx, self.Ly, self.local, self.inv_scale, box, max(1, min(nt, self.shape[1]))

    def pcg_args(self, nc, nt):
        """``ell_pcg``'s Kronecker arguments: :meth:`args`, in 2D
        followed by an empty band factor and False (the band factor of
        :mod:`skfem_mpm.kernels.band_factor` switched off)."""
        args = self.args(nc, nt)
        if len(args) == 8 or self.geometry[3] == 1:  # 3D and 1D: no band factor
            return args
        return args + (NO_BAND, False)


NO_BAND = np.empty((0, 1))
"""The band factor of ``ell_pcg``'s 2D Kronecker arguments when it is off."""


@njit(cache=True, error_model="numpy", fastmath=FAST)
def apply_kronecker(Lx, Ly, local, inv_scale, box, nt, r, z):
    """z = S^-1 R (M_y (x) M_x)^-1 R^T S^-1 r (see the module docstring);
    Lx, Ly are the banded Cholesky factors with 1 / L_ii in column 0,
    ``box`` (ny, nx, nc) is work space, nt the number of column blocks."""
    apply_kronecker_replaced(Lx, Ly, local, inv_scale, box, nt, r, _NO_ROWS, _NO_VALUES, z)


_NO_ROWS = np.empty(0, dtype=np.int64)
_NO_VALUES = np.empty((0, 1))


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def apply_kronecker_replaced(Lx, Ly, local, inv_scale, box, nt, r, rows, values, z):
    """:func:`apply_kronecker` of u, the vector r with its rows ``rows[k]``
    replaced by ``values[k]`` (the fringe correction's r - M z1, which
    differs from r on a few rows only), without forming u. Three parallel
    regions: each thread fills its block of box rows (zeroing it, scaling
    the rows of u that fall in it) and solves along x there; the y solves
    by blocks of box columns; z from the box."""
    ny, nx, nc = box.shape
    flat = box.reshape((ny * nx, nc))  # entry li of the box (no division by nx)
    for t in prange(nt):
        _fill_rows(local, inv_scale, r, rows, values, flat, t * ny // nt * nx,
                   (t + 1) * ny // nt * nx)
        _along_rows(Lx, box, t * ny // nt, (t + 1) * ny // nt)
    if ny > 1:
        for t in prange(nt):
            _along_columns(Ly, box, t * nx // nt, (t + 1) * nx // nt)
    _from_box(local, inv_scale, r, rows, values, flat, z)


@njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def _fill_rows(local, inv_scale, r, rows, values, flat, first, last):
    """Box entries first..last-1 (a thread's block of box rows) = S^-1 u on
    the rows of u in them, 0 elsewhere; u = r with rows[k] replaced by
    values[k]."""
    nc = flat.shape[1]
    for li in range(first, last):
        for c in range(nc):
            flat[li, c] = 0.0
    for q in range(r.shape[0]):
        li = local[q]
        if li >= first and li < last:
            for c in range(nc):
                flat[li, c] = r[q, c] * inv_scale[q]
    for k in range(rows.shape[0]):
        q = rows[k]
        li = local[q]
        if li >= first and li < last:
            for c in range(nc):
                flat[li, c] = values[k, c] * inv_scale[q]


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def _from_box(local, inv_scale, r, rows, values, flat, z):
    """z = S^-1 R box; a row outside the box (a lumped row) takes its own
    diagonal, z = S^-1 u there (u = r with rows[k] replaced by values[k])."""
    nc = z.shape[1]
    for q in prange(r.shape[0]):
        li = local[q]
        for c in range(nc):
            if li >= 0:
                z[q, c] = flat[li, c] * inv_scale[q]
            else:  # a lumped row: its own diagonal
                z[q, c] = r[q, c] * inv_scale[q]
    for k in range(rows.shape[0]):
        q = rows[k]
        if local[q] < 0:
            for c in range(nc):
                z[q, c] = values[k, c] * inv_scale[q]


@njit(cache=True, error_model="numpy", fastmath=IN_ORDER)
def _along_rows(L, box, lo, hi):
    """Solve (L L^T) y = box along axis 1 of ``box`` (rows, n, nc) for the
    rows lo..hi-1 (L: banded factor with 1 / L_ii in column 0), all rows
    advanced together one entry at a time: forward y_i = (y_i - sum_d
    L_i,i-d y_i-d) / L_ii, then backward y_i = (y_i - sum_d L_i+d,i y_i+d)
    / L_ii, d = 1, 2, ... in turn (compiled without reassociation: the
    order of the terms is the result's)."""
    n = box.shape[1]
    p = L.shape[1] - 1
    if p > 3:
        _along_axis_any(L, box, lo, hi)
        return
    for i in range(n):
        m = min(p, i)
        _row_entry(L, box, lo, hi, i, m, -1, L[i, min(m, 1)], L[i, min(m, 2)],
                   L[i, min(m, 3)])
    for i in range(n - 1, -1, -1):
        m = min(p, n - 1 - i)
        _row_entry(L, box, lo, hi, i, m, 1, L[i + min(m, 1), min(m, 1)],
                   L[i + min(m, 2), min(m, 2)], L[i + min(m, 3), min(m, 3)])


@njit(cache=True, inline="always", error_model="numpy", fastmath=IN_ORDER)
def _row_entry(L, box, lo, hi, i, m, s, a1, a2, a3):
    """Entry i of the rows lo..hi-1 of ``box`` (see _along_rows): its m
    neighbours i + s d (s = -1 forward, 1 backward; m <= 3, coefficients
    a_d) subtracted in order of d, times 1 / L_ii."""
    nc = box.shape[2]
    scale = L[i, 0]
    if m == 0:
        for j in range(lo, hi):
            for c in range(nc):
                box[j, i, c] = box[j, i, c] * scale
    elif m == 1:
        for j in range(lo, hi):
            for c in range(nc):
                box[j, i, c] = (box[j, i, c] - a1 * box[j, i + s, c]) * scale
    elif m == 2:
        for j in range(lo, hi):
            for c in range(nc):
                box[j, i, c] = (box[j, i, c] - a1 * box[j, i + s, c]
                                - a2 * box[j, i + 2 * s, c]) * scale
    else:
        for j in range(lo, hi):
            for c in range(nc):
                box[j, i, c] = (box[j, i, c] - a1 * box[j, i + s, c]
                                - a2 * box[j, i + 2 * s, c] - a3 * box[j, i + 3 * s, c]) * scale


@njit(cache=True, error_model="numpy", fastmath=IN_ORDER)
def _along_columns(L, box, lo, hi):
    """Solve (L L^T) y = box along axis 0 of ``box`` (n, columns, nc) for
    the columns lo..hi-1, as :func:`_along_rows` along the other axis: row
    by row, each row's columns one contiguous run (:func:`_band_run`)."""
    n = box.shape[0]
    nc = box.shape[2]
    p = L.shape[1] - 1
    if p > 3:
        _along_axis_any(L, box.transpose((1, 0, 2)), lo, hi)
        return
    flat = box.reshape((n, box.shape[1] * nc))
    a, b = lo * nc, hi * nc
    for j in range(n):
        m = min(p, j)
        _band_run(flat[j, a:b], flat[j - min(m, 1), a:b], flat[j - min(m, 2), a:b],
                  flat[j - m, a:b], m, L[j, min(m, 1)], L[j, min(m, 2)], L[j, m], L[j, 0])
    for j in range(n - 1, -1, -1):
        m = min(p, n - 1 - j)
        _band_run(flat[j, a:b], flat[j + min(m, 1), a:b], flat[j + min(m, 2), a:b],
                  flat[j + m, a:b], m, L[j + min(m, 1), min(m, 1)],
                  L[j + min(m, 2), min(m, 2)], L[j + m, m], L[j, 0])


@njit(cache=True, error_model="numpy", fastmath=IN_ORDER)
def _along_axis_any(L, box, lo, hi):
    """:func:`_along_rows` for any band p of L (the same operations in the
    same order; :func:`_along_columns` passes its box transposed)."""
    n = box.shape[1]
    nc = box.shape[2]
    p = L.shape[1] - 1
    for i in range(n):
        for j in range(lo, hi):
            for c in range(nc):
                t = box[j, i, c]
                for d in range(1, min(p, i) + 1):
                    t -= L[i, d] * box[j, i - d, c]
                box[j, i, c] = t * L[i, 0]
    for i in range(n - 1, -1, -1):
        for j in range(lo, hi):
            for c in range(nc):
                t = box[j, i, c]
                for d in range(1, min(p, n - 1 - i) + 1):
                    t -= L[i + d, d] * box[j, i + d, c]
                box[j, i, c] = t * L[i, 0]


@njit(cache=True, error_model="numpy", fastmath=IN_ORDER)
def _band_run(y, y1, y2, y3, m, a1, a2, a3, scale):
    """y = (y - a1 y1 - a2 y2 - a3 y3) scale with the first m (<= 3) terms
    (contiguous runs: a function of its own, so that the loop is
    vectorised)."""
    if m == 0:
        for e in range(y.shape[0]):
            y[e] = y[e] * scale
    elif m == 1:
        for e in range(y.shape[0]):
            y[e] = (y[e] - a1 * y1[e]) * scale
    elif m == 2:
        for e in range(y.shape[0]):
            y[e] = (y[e] - a1 * y1[e] - a2 * y2[e]) * scale
    else:
        for e in range(y.shape[0]):
            y[e] = (y[e] - a1 * y1[e] - a2 * y2[e] - a3 * y3[e]) * scale


BOX_FIELDS = 7
"""Entries of a row of ``boxes`` (:func:`apply_kronecker_axes`): the box's
first entry in the work space (in units of nc), its shape nz, ny, nx, and
its first row in the concatenated factors Lx, Ly, Lz."""


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def apply_kronecker_axes(Lx, Ly, Lz, local, inv_scale, box, nt, boxes, r, z):
    """z = S^-1 R (M_z (x) M_y (x) M_x)^-1 R^T S^-1 r, one Kronecker
    product per box: each row of ``boxes`` (BOX_FIELDS entries) is a box
    (nz, ny, nx) in the flat work space ``box`` (at least the boxes'
    entries times nc = r.shape[1]) with its own factors, rows x0..x0+nx-1
    of Lx (y0.. of Ly, z0.. of Lz); ``local`` is each row's entry in the
    work space (its box's first entry plus its box-local index; -1: a
    diagonal row, z = r inv_scale). In each box the banded solves run
    along x (each of the nz ny box rows), along y (each z layer's
    columns) and along z (each of the ny nx columns), in at most nt blocks
    each; a factor of length 1 (all boxes one layer thick) is not applied.
    One box with nz = 1 (Lz of length 1) is :func:`apply_kronecker` with
    the same operations in the same order."""
    nc = r.shape[1]
    nr = r.shape[0]
    nb = boxes.shape[0]
    total = 0
    for k in range(nb):
        total = max(total, boxes[k, 0] + boxes[k, 1] * boxes[k, 2] * boxes[k, 3])
    flat = box[:total * nc].reshape((total, nc))  # entry li of the work space
    for j in prange(total):
        for c in range(nc):
            flat[j, c] = 0.0
    for q in prange(nr):
        li = local[q]
        if li >= 0:
            for c in range(nc):
                flat[li, c] = r[q, c] * inv_scale[q]
    for k in range(nb):
        first, nz, ny, nx = boxes[k, 0], boxes[k, 1], boxes[k, 2], boxes[k, 3]
        x0, y0, z0 = boxes[k, 4], boxes[k, 5], boxes[k, 6]
        part = box[first * nc:(first + nz * ny * nx) * nc]
        rows = part.reshape((nz * ny, nx, nc))
        columns = part.reshape((nz, ny * nx, nc))
        layers = part.reshape((nz, ny, nx, nc))
        blocks = max(1, min(nt, ny * nx))
        Lxk = Lx[x0:x0 + nx]
        for t in prange(blocks):
            _along_rows(Lxk, rows, t * (nz * ny) // blocks, (t + 1) * (nz * ny) // blocks)
        if Ly.shape[0] > 1:  # (fit_kronecker: factors of length 1 are not applied)
            Lyk = Ly[y0:y0 + ny]
            for m in range(nz):
                layer = layers[m]
                for t in prange(blocks):
                    _along_columns(Lyk, layer, t * nx // blocks, (t + 1) * nx // blocks)
        if Lz.shape[0] > 1:
            Lzk = Lz[z0:z0 + nz]
            for t in prange(blocks):
                _along_columns(Lzk, columns, t * (ny * nx) // blocks,
                               (t + 1) * (ny * nx) // blocks)
    for q in prange(nr):
        li = local[q]
        for c in range(nc):
            if li >= 0:
                z[q, c] = flat[li, c] * inv_scale[q]
            else:  # a diagonal row: its own inverse
                z[q, c] = r[q, c] * inv_scale[q]
