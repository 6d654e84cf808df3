"""Reconstruction of particle data, to integrate with Gauss quadrature.

Particles are a poor quadrature rule: the internal force sum_p V_p sigma_p
grad N_i(x_p) carries an O((h/ppc)^2) error that caps B-spline MPM at second
order (Tielen et al. 2017). Reconstructing the particle data as smooth fields
and integrating them with Gauss quadrature removes that error:

    M_ij = int rho_h N_i N_j,   P_i = int (rho v)_h N_i,
    f_i  = - int sigma_h grad N_i + int (rho b)_h N_i   (+ tractions on particles)

Every reconstruction here has the same signature

    values_at_points = reconstruct(grid, particles, values, rule, **options)

with ``values`` (n, k) per-volume particle data (density, momentum density,
stress components, body force density) and ``rule`` the
:class:`IntegrationRule` of the step; a user's own callable with this
signature can be passed as ``Method(reconstruction=callable)``.

The integration region: in 1D the union of the particles' current extents
[x_p - V_p/2, x_p + V_p/2], with gaps narrower than a cell closed (the body
exactly, also when it ends inside a cell); in 2D and 3D on spline grids
the cells that hold particles and that the body fills (:func:`body_boxes`
gives the whole cell), while in a cell a free surface or a contact front
cuts (:func:`cut_cells`) the particles themselves are the rule (points
x_p, weights V_p) and every reconstruction returns the particle's own
value there: particle quadrature in the cut cells
(:attr:`IntegrationRule.particle_points`). Why: a fit in a cut cell is
extrapolated to the Gauss points of the cell's estimated box, and the
force of such fits is not the work-conjugate of the particles' strain
rates; on a 0.4 x 0.2 elastic block falling onto a fixed floor (16 x 16
quadratic cells, 3 x 3 particles per cell, consistent MUSL, tls) the
impact gained 487 J against 312 J of kinetic energy by t = 0.30 (and the
run failed at t = 0.42); with particles in the cut cells it loses 21 J, as
particle quadrature does (test_recon_compiled). A user's callable
receives the whole rule and should return its fit at every point.
Gauss rules use p + 2 points per axis (exact for a cubic field times two
degree-p functions).

``spline``  1D (default ``knots="particles"``, the seed's approach): the
            not-a-knot cubic spline through the particle values (sorted,
            coincident positions merged), one per connected piece of the
            body. It moves continuously with the particles, which is what
            grid crossing needs: on the large-deformation soil column (S2,
            10-20% strain) quadratic MPM with it converges (consistent mass,
            20-160 cells: 0.15%, 0.09%, 0.05%, 0.02% against a converged
            solution of the same model) with smooth stress, where particle
            quadrature diverges (0.4% to 9.9%) with oscillating stress.
            Being C2 across the grid knots, where the stress of a degree-p
            spline solution has its kinks, it smooths them: an error of about
            h^2 / ppc^2 that caps quadratic MPM at order 2 with 4 particles
            per cell on small deformations (S1: orders 2.15, 2.03).
            ``knots="grid"``: least squares in the cubic splines on the grid's
            knots with the data's continuity C^(p-2) there and a small
            penalty (``penalty``) on derivative jumps for what the particles
            leave open. It lifts the cap (S1, 4 ppc: 2.93, 2.74; S3 at 16
            cells 4.1e-7 against 7.8e-6) but fails where a free surface moves
            through partly filled cells (S2 large: J <= 0 after ~120 steps);
            use it for small deformations.
            2D: least squares in the cubic B-spline space of the grid (C2),
            with a second-difference penalty on the coefficients that the
            particles barely see (empty cells). Reproduces cubic polynomials.
``tls``     Conservative Taylor least squares as published (Wobbes, Moller,
            Galavi, Vuik 2019, IJNME 117:271-290): per cell, the quadratic
            polynomial fitted to the cell's own particles in the
            (volume-weighted) least-squares sense under the constraint that
            its Gauss integral over the cell equals the particle integral
            sum_p f_p V_p of the cell. Hence total mass and momentum are
            exactly those of the particles, cell by cell (over the part
            of each cell the body covers, see :func:`body_boxes`). A cell whose
            particles do not determine the quadratic (in 2D fewer than 6, so
            2 x 2 particles per cell) takes the constrained linear fit, and
            failing that the constant that satisfies the constraint (never a
            singular solve), and a value column whose fit leaves the
            range of the cell's particle values by more than that range
            also takes the lower degree (the bound test of
            :func:`reconstruct_tls`). Options:
            ``degree=1`` (linear), ``neighbour_weight=w`` (the 3^d
            neighbouring cells' particles enter each fit with weight w;
            the earlier default was degree 1 with w = 1e-3),
            ``constraint="mean"`` (cell means instead of cell integrals:
            no jump when particles cross cells; not conservative) or
            ``"none"`` (plain least squares, not conservative; the accurate
            choice on D1 large). Reproduces
            quadratics when the particles integrate them exactly over each
            cell (e.g. Gauss layout, 3 per axis).
``mls``     Moving least squares with a linear basis and the cubic B-spline
            weight of radius ``radius`` (default 1.5 cells); where fewer than
            dim + 1 particles are in reach it falls back to the weighted mean
            (Shepard). Reproduces linear polynomials; ``degree=2``: the
            quadratic basis (then linear, then Shepard where the moments
            are ill conditioned), reproduces quadratics. What it is for: a
            reconstruction that needs no cell structure (any grid, any
            dimension). At 16 x 16 (p2, 3 x 3 ppc, consistent MUSL) the
            linear default is less accurate than particle quadrature on D2
            small (3.5e-4 against 3.2e-4) and D1 large (1.4e-2 against
            3.9e-3); ``degree=2`` beats it on both (2.1e-4, 1.7e-3).
"""
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.interpolate import CubicSpline
from scipy.spatial import cKDTree

from .quadrature import transfer_matrices

__all__ = ["IntegrationRule", "integration_rule", "reconstruct_spline", "reconstruct_tls",
           "reconstruct_mls", "RECONSTRUCTORS"]


class IntegrationRule:
    """Points ``x`` (ng, dim), weights ``w`` (ng,), the grid cell of each
    point ``cell`` (ng,), and for 1D the connected pieces of the body
    (``pieces``: list of (lo, hi, point index array)).

    ``particle_points``: None, or the indices of the particles that are
    points of the rule themselves (those of the cells a free surface cuts,
    see :func:`integration_rule`): they follow the ``ngauss`` Gauss points,
    with the particle's position and its volume V_p as weight, and a
    reconstruction returns the particle's own value there."""

    def __init__(self, x, w, cell, pieces=None, particle_points=None):
        self.x, self.w, self.cell = x, w, cell
        self.pieces = pieces
        self.particle_points = particle_points
        self.ngauss = x.shape[0] - (0 if particle_points is None else particle_points.size)

    def gauss_part(self):
        """The rule of the Gauss points alone (self when it has no particle points)."""
        if self.particle_points is None:
            return self
        n = self.ngauss
        return IntegrationRule(self.x[:n], self.w[:n], self.cell[:n], self.pieces)


def at_rule_points(reconstruct):
    """A reconstruction that honours a rule's particle points: ``reconstruct``
    on the Gauss points, the particles' own values at the particle points."""
    def on_rule(grid, particles, values, rule, **options):
        if getattr(rule, "particle_points", None) is None:
            return reconstruct(grid, particles, values, rule, **options)
        values = np.asarray(values, dtype=np.float64)
        gauss = reconstruct(grid, particles, values, rule.gauss_part(), **options)
        return np.concatenate((gauss, values[rule.particle_points]))

    on_rule.__name__, on_rule.__doc__ = reconstruct.__name__, reconstruct.__doc__
    on_rule.__wrapped__ = reconstruct
    return on_rule


def _body_pieces_1d(particles, gap):
    """Connected pieces of the union of the particle extents
    [x_p - V_p/2, x_p + V_p/2]; gaps narrower than ``gap`` (a cell: random
    layouts leave small ones) are closed."""
    x = particles.x[:, 0]
    half = 0.5 * particles.V
    order = np.argsort(x, kind="stable")
    lo, hi = (x - half)[order], (x + half)[order]
    run_hi = np.maximum.accumulate(hi)
    starts = np.flatnonzero(np.r_[True, lo[1:] > run_hi[:-1] + gap])
    ends = np.r_[starts[1:], len(order)]
    return [(lo[s], run_hi[e - 1]) for s, e in zip(starts, ends)]


def integration_rule(grid, particles, points_per_axis):
    """The step's Gauss rule over the body (see the module docstring)."""
    k = int(points_per_axis)
    if grid.dim == 1:
        ref, wref = np.polynomial.legendre.leggauss(k)
        ref, wref = 0.5 * (ref + 1), 0.5 * wref
        u = grid.breakpoints[0]
        xs, ws, cs, pieces = [], [], [], []
        start = 0
        for lo, hi in _body_pieces_1d(particles, float(grid.cell_sizes[0].max())):
            lo, hi = max(lo, u[0]), min(hi, u[-1])
            left = np.maximum(u[:-1], lo)
            right = np.minimum(u[1:], hi)
            cells = np.flatnonzero(right > left)
            width = right[cells] - left[cells]
            xs.append((left[cells, None] + width[:, None] * ref).ravel())
            ws.append((width[:, None] * wref).ravel())
            cs.append(np.repeat(cells, k))
            n = cells.size * k
            pieces.append((lo, hi, np.arange(start, start + n)))
            start += n
        return IntegrationRule(np.concatenate(xs)[:, None], np.concatenate(ws),
                               np.concatenate(cs), pieces)
    cells, _ = grid.locate(particles.x)
    held = np.unique(cells)
    if not hasattr(grid, "breakpoints"):  # a LagrangeGrid: whole cells
        x, w, cell = grid.gauss_rule(k, held)
        return IntegrationRule(x, w, cell)
    lo, hi = body_boxes(grid, particles, cells, held)  # whole cells inside the body
    cut = cut_cells(grid, held, lo, hi)
    if cut.any():  # the particles are the rule of the cells a free surface cuts
        inside = ~cut
        rule = _box_rule(grid, held[inside], lo[inside], hi[inside], k)
        flag = np.zeros(grid.ncells, dtype=bool)
        flag[held[cut]] = True
        own = np.flatnonzero(flag[cells])
        return IntegrationRule(np.concatenate((rule.x, particles.x[own])),
                               np.concatenate((rule.w, particles.V[own])),
                               np.concatenate((rule.cell, cells[own])), particle_points=own)
    return _box_rule(grid, held, lo, hi, k)


def cut_cells(grid, held, lo, hi):
    """Which of the ``held`` cells (ascending) a free surface cuts: their
    :func:`body_boxes` box ``lo``..``hi`` is not the whole cell."""
    whole = np.ones(held.size, dtype=bool)
    stride = 1
    for axis in range(grid.dim):
        n = grid.cells_per_axis[axis]
        e = (held // stride) % n
        whole &= (lo[:, axis] == grid.breakpoints[axis][e]) & \
            (hi[:, axis] == grid.breakpoints[axis][e + 1])
        stride *= n
    return ~whole


def _box_rule(grid, held, lo, hi, k):
    """The tensor Gauss rule of k points per axis on each box lo..hi of the cells ``held``."""
    ref, wref = np.polynomial.legendre.leggauss(k)
    ref, wref = 0.5 * (ref + 1.0), 0.5 * wref
    dim = grid.dim
    shape = (held.size,) + (k,) * dim  # local point a + k b (+ k^2 c): x fastest
    x = np.empty(shape + (dim,))
    w = np.ones(shape)
    for axis in range(dim):
        width = hi[:, axis] - lo[:, axis]
        view = [held.size] + [1] * dim
        view[dim - axis] = k
        x[..., axis] = (lo[:, axis, None] + width[:, None] * ref[None, :]).reshape(view)
        w = w * (width[:, None] * wref[None, :]).reshape(view)
    return IntegrationRule(x.reshape(-1, dim), w.ravel(), np.repeat(held, k ** dim))


def particle_half_extents(grid, particles, cells):
    """Half the extent of each particle along each axis (n, dim), the
    particle taken as a box of volume V_p similar to its cell:
    l_(p,a) / 2 with l_(p,a) = h_(e,a) (V_p / |e|)^(1/d). Exact for a uniform
    layout filling whole cells; an estimate in cut cells and once the
    particles deform (:func:`body_boxes` uses it only to tell which faces
    the body reaches and the proportions of a corner's box)."""
    dim = grid.dim
    e, stride = [], 1
    for axis in range(dim):
        e.append((cells // stride) % grid.cells_per_axis[axis])
        stride *= grid.cells_per_axis[axis]
    size = np.stack([grid.cell_sizes[a][e[a]] for a in range(dim)], axis=1)
    area = np.prod(size, axis=1)
    ratio = particles.V / area
    scale = np.sqrt(ratio) if dim == 2 else np.cbrt(ratio)
    return 0.5 * (size * scale[:, None])


def body_boxes(grid, particles, cells, held):
    """The part of each held cell that the body covers, as a box: lower and
    upper corners (nheld, dim) for the cells ``held`` (ascending), given the
    cell of every particle ``cells``.

    A face of cell e is *closed* (the body reaches it) when the cell across
    it holds particles, or when the particles' extents x_p +- l_p / 2
    (:func:`particle_half_extents`) come within the largest half extent of
    it (plus, when the opposite face is closed by a held neighbour, the
    gap the extents leave at that face: the estimate's own error, as in
    cells cut by a seeding box); else it is *open* (a free surface runs
    through e). A cell without
    open faces keeps the whole cell. Else the box takes the whole cell along
    its closed axes; along its open axes it starts at the closed face (both
    faces open: centred on the particles' extent) and its widths are the
    particles' extent scaled by one common factor so that the box's volume
    is the cell's particle volume sum_(p in e) V_p (clipped to the cell).
    So a free surface parallel to a grid line is located exactly (as in 1D,
    where the rule covers the body), and in every cell with an open face
    the box holds the particles' volume: a constant density reconstructs
    as that constant.

    Why: the TLS constraint makes the fit's integral over the rule equal
    to the particles' integral. Over a whole cell that the body fills to a
    fraction f, the constrained quadratic of a constant density rho must
    integrate to f rho |e| while matching rho at the particles, and dips
    to negative values in the empty part (rho_h = -1.7 rho measured in a
    cell filled to 0.2 x 0.1, 6 x 5 cells, ppc 3).
    """
    dim = grid.dim
    slot = np.full(grid.ncells, -1)
    slot[held] = np.arange(held.size)
    s = slot[cells]
    half = particle_half_extents(grid, particles, cells)
    pmin = np.full((held.size, dim), np.inf)
    pmax = np.full((held.size, dim), -np.inf)
    hmax = np.zeros((held.size, dim))
    volume = np.zeros(held.size)
    np.minimum.at(pmin, s, particles.x - half)
    np.maximum.at(pmax, s, particles.x + half)
    np.maximum.at(hmax, s, half)
    np.add.at(volume, s, particles.V)
    is_held = np.zeros(grid.ncells, dtype=bool)
    is_held[held] = True
    lower = np.empty((held.size, dim))
    upper = np.empty((held.size, dim))
    closed_lo = np.empty((held.size, dim), dtype=bool)
    closed_hi = np.empty((held.size, dim), dtype=bool)
    stride = 1
    for axis in range(dim):
        n = grid.cells_per_axis[axis]
        e = (held // stride) % n
        lower[:, axis] = grid.breakpoints[axis][e]
        upper[:, axis] = grid.breakpoints[axis][e + 1]
        below = (e > 0) & is_held[np.maximum(held - stride, 0)]
        above = (e < n - 1) & is_held[np.minimum(held + stride, grid.ncells - 1)]
        gap_lo = pmin[:, axis] - lower[:, axis]
        gap_hi = upper[:, axis] - pmax[:, axis]
        closed_lo[:, axis] = below | (gap_lo < hmax[:, axis] + np.where(
            above, np.maximum(gap_hi, 0.0), 0.0))
        closed_hi[:, axis] = above | (gap_hi < hmax[:, axis] + np.where(
            below, np.maximum(gap_lo, 0.0), 0.0))
        stride *= n
    est_lo = np.where(closed_lo, lower, np.maximum(lower, pmin))
    est_hi = np.where(closed_hi, upper, np.minimum(upper, pmax))
    opened = ~(closed_lo & closed_hi)
    n_open = opened.sum(axis=1)
    est_volume = np.prod(est_hi - est_lo, axis=1)
    ratio = volume / est_volume
    factor = np.where(n_open == 1, ratio, np.where(n_open == 2, np.sqrt(ratio), np.cbrt(ratio)))
    width = np.minimum(upper - lower, factor[:, None] * (est_hi - est_lo))
    centre_lo = np.minimum(np.maximum(lower, 0.5 * (est_lo + est_hi) - 0.5 * width), upper - width)
    lo = np.where(~opened | closed_lo, lower, np.where(closed_hi, upper - width, centre_lo))
    hi = np.where(~opened | closed_hi, upper, lo + width)
    return lo, hi


# ------------------------------------------------------------------- spline
def reconstruct_spline(grid, particles, values, rule, knots="particles", penalty=1e-6):
    """Cubic-spline reconstruction (see the module docstring).

    1D, ``knots="particles"``: the seed's not-a-knot cubic spline through
    the particles, C2 everywhere. ``knots="grid"`` (default): the same, but
    in every cell holding at least four particles the cubic is refitted to
    that cell's particles alone (least squares; interpolation with four),
    so the reconstruction may break at the grid knots, where the stress of
    a degree-p spline solution is only C^(p-2).
    """
    values = np.asarray(values, dtype=np.float64)
    if knots not in ("grid", "particles"):
        raise ValueError(f"knots must be 'grid' or 'particles', got {knots!r}")
    if grid.dim == 1:
        if knots == "grid":
            return _grid_knot_spline(grid, particles, values, rule, penalty)
        return _spline_1d(particles, values, rule)
    return _spline_ls(grid, particles, values, rule, penalty)


def _derivative_operator(t, k):
    """Sparse D with coefficients of s' (degree k - 1, knots t[1:-1]) = D c."""
    nb = len(t) - k - 1
    j = np.arange(nb - 1)
    denom = t[j + k + 1] - t[j + 1]
    scale = np.where(denom > 0, k / np.where(denom > 0, denom, 1.0), 0.0)
    return sp.csr_matrix((np.concatenate((-scale, scale)),
                          (np.concatenate((j, j)), np.concatenate((j, j + 1)))),
                         shape=(nb - 1, nb))


def _grid_knot_spline(grid, particles, values, rule, penalty):
    """Least squares in the cubic splines on the grid knots with the
    continuity of the data, C^(p-2) (interior knots repeated 5 - p times),
    plus a small penalty on the jumps of s' and s'' at the knots."""
    from scipy.interpolate import BSpline

    p = grid.degree
    u = grid.breakpoints[0]
    mult = min(4, 5 - p)
    t = np.concatenate((np.full(4, u[0]), np.repeat(u[1:-1], mult), np.full(4, u[-1])))
    B = BSpline.design_matrix(particles.x[:, 0], t, 3).tocsr()
    BtW = (B.T.multiply(particles.V[None, :])).tocsr()
    A = (BtW @ B).tocsr()
    scale = float(np.mean(A.diagonal()[A.diagonal() > 0]))
    h = float(np.mean(np.diff(u)))
    knots = u[1:-1]
    reg = sp.csr_matrix(A.shape)
    D, tk = sp.identity(A.shape[0], format="csr"), t
    for order in (1, 2):
        D = _derivative_operator(tk, 4 - order) @ D
        tk = tk[1:-1]
        if 3 - order < 0 or knots.size == 0:
            break
        right = BSpline.design_matrix(knots, tk, 3 - order).tocsr()
        left = BSpline.design_matrix(np.nextafter(knots, -np.inf), tk, 3 - order).tocsr()
        J = (right - left) @ D
        reg = reg + (h ** (2 * order)) * (J.T @ J)
    A = A + penalty * scale * reg + 1e-14 * scale * sp.identity(A.shape[0])
    coeffs = spla.splu(A.tocsc()).solve(BtW @ values)
    return BSpline.design_matrix(rule.x[:, 0], t, 3).tocsr() @ coeffs


def _spline_1d(particles, values, rule):
    x = particles.x[:, 0]
    out = np.zeros((rule.x.shape[0], values.shape[1]))
    for lo, hi, idx in rule.pieces:
        inside = (x >= lo) & (x <= hi)
        xs, inv = np.unique(x[inside], return_inverse=True)  # sorted, merged
        ys = np.zeros((xs.size, values.shape[1]))
        np.add.at(ys, inv, values[inside])
        ys /= np.bincount(inv, minlength=xs.size)[:, None]
        pts = rule.x[idx, 0]
        if xs.size == 1:
            out[idx] = ys[0]
        elif xs.size == 2:
            t = (pts - xs[0]) / (xs[1] - xs[0])
            out[idx] = ys[0] + t[:, None] * (ys[1] - ys[0])
        else:
            out[idx] = CubicSpline(xs, ys, bc_type="not-a-knot", extrapolate=True)(pts)
    return out


def _cubic_space(grid):
    from .spline import SplineGrid

    return SplineGrid(grid.breakpoints, 3)


def _second_differences(shape):
    """Stacked second-difference operators along each axis of a coefficient
    array with ``shape`` (x index fastest)."""
    blocks = []
    for axis, n in enumerate(shape):
        if n < 3:
            continue
        d = sp.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(n - 2, n))
        eyes = [sp.identity(m) for m in shape]
        eyes[axis] = d
        op = eyes[0]
        for e in eyes[1:]:
            op = sp.kron(e, op)  # x fastest
        blocks.append(op)
    return sp.vstack(blocks).tocsr()


def _spline_ls(grid, particles, values, rule, penalty):
    cubic = _cubic_space(grid)
    B, _ = transfer_matrices(cubic, particles.x)
    BtW = (B.T.multiply(particles.V[None, :])).tocsr()
    A = (BtW @ B).tocsr()
    diag = A.diagonal()
    typical = np.median(diag[diag > 0])
    weak = diag < 0.1 * typical
    if weak.any():
        D = _second_differences(cubic.basis_per_axis)
        rows = np.flatnonzero(np.asarray(abs(D)[:, np.flatnonzero(weak)].sum(axis=1)).ravel())
        D = D[rows]
        A = A + (penalty * typical) * (D.T @ D) + sp.diags(np.where(diag > 0, 0.0,
                                                                    penalty * typical))
    coeffs = spla.splu(A.tocsc()).solve(BtW @ values)
    Bg, _ = transfer_matrices(cubic, rule.x)
    return Bg @ coeffs


# ---------------------------------------------------------------------- TLS
def _monomials(local, degree):
    """Columns 1, x, (y), and the quadratic terms for degree 2."""
    dim = local.shape[1]
    cols = [np.ones(local.shape[0])] + [local[:, d] for d in range(dim)]
    if degree == 2:
        for a in range(dim):
            for b in range(a, dim):
                cols.append(local[:, a] * local[:, b])
    return np.stack(cols, axis=1)


def _neighbour_cells(grid, cells):
    """(len(cells), 3^dim) the ids of each cell's neighbours and itself
    (offsets -1, 0, 1 per axis, x fastest; -1 outside the grid): the cell
    itself is column 3^dim // 2."""
    counts = np.asarray(grid.cells_per_axis, dtype=np.int64)
    index = np.stack(np.unravel_index(cells, counts[::-1]), axis=1)[:, ::-1]  # (n, dim), x first
    offsets = np.stack(np.meshgrid(*[[-1, 0, 1]] * grid.dim, indexing="ij"),
                       axis=-1).reshape(-1, grid.dim)[:, ::-1]  # x fastest
    near = index[:, None, :] + offsets[None, :, :]
    inside = ((near >= 0) & (near < counts)).all(axis=2)
    strides = np.cumprod(np.concatenate(([1], counts[:-1])))
    return np.where(inside, near @ strides, -1)


TLS_RANK_TOL = 1e-8
"""A cell's least-squares fit of a degree uses that degree when the smallest
eigenvalue of its normal matrix, scaled to unit diagonal, exceeds this."""


TLS_BOUND_TOL = 1.0
TLS_BOUND_ABS = 1e-9
"""A cell's fit of a degree is kept for a value column when its values at
the cell's Gauss points stay within [min_p f_p - s, max_p f_p + s] of the
cell's particle values, s = TLS_BOUND_TOL (max - min) + TLS_BOUND_ABS
max |f_p|; else that column takes the next lower degree. A smooth field's
quadratic overshoots its particle range at the Gauss points by a fraction
of the range (x^2 with 3 particles per cell: 0.26 of it); a fit bent by the
constraint to make up for a wrong integration region overshoots by the
field itself (a constant density: spread 0, fit -1.7 rho)."""


def _levels(dim):
    """Number of monomials of degree 0, 1, 2 (leading columns of
    :func:`_monomials`)."""
    return (1, 1 + dim, 1 + dim + dim * (dim + 1) // 2)


def _well_posed(A, m):
    """Cells whose leading m x m normal matrix is positive definite after
    scaling to unit diagonal (smallest eigenvalue > TLS_RANK_TOL)."""
    sub = A[:, :m, :m]
    d = np.einsum("cii->ci", sub)
    ok = (d > 0).all(axis=1)
    out = np.zeros(A.shape[0], dtype=bool)
    if ok.any():
        s = 1.0 / np.sqrt(d[ok])
        scaled = sub[ok] * s[:, :, None] * s[:, None, :]
        out[ok] = np.linalg.eigvalsh(scaled)[:, 0] > TLS_RANK_TOL
    return out


def reconstruct_tls(grid, particles, values, rule, degree=2, neighbour_weight=0.0,
                    constraint="integral"):
    """Conservative Taylor least squares (Wobbes, Moller, Galavi, Vuik 2019,
    IJNME 117:271-290, Sec. 3).

    Default (``degree=2, neighbour_weight=0``, the published method): for
    each cell e holding particles, in the local coordinates
    xi = (x - c_e) / h_e (c_e the centre, h_e the sizes per axis of the box
    spanned by the cell's Gauss points: the cell, or the part of it the
    body covers) and
    the monomials phi = (1, xi_1, .., xi_d, xi_a xi_b for a <= b), find
    coefficients a_e that minimise

        sum_{p in e} V_p (phi(xi_p) . a_e - f_p)^2

    subject to   sum_g w_g phi(xi_g) . a_e = sum_{p in e} V_p f_p

    (Gauss points g of ``rule`` in the cell: the reconstruction integrates
    to the particle integral cell by cell, so total mass and momentum are
    those of the particles). It is the Lagrange system
    [[A, G], [G^T, 0]] [a; lambda] = [b; S] with A = sum V_p phi phi^T,
    b = sum V_p phi f_p, G = sum_g w_g phi_g, S = sum V_p f_p. With equal
    particle volumes in a cell the V_p weights cancel and this is the
    paper's unweighted fit.

    Fallback (never a singular solve): when the particles of a cell do not
    determine the quadratic (A restricted to the quadratic monomials has a
    scaled smallest eigenvalue <= TLS_RANK_TOL: fewer than 6 particles in
    2D, 3 in 1D, or them on a conic/line), the same constrained fit is made
    with the linear monomials; when those are not determined either, the
    constant S / |e| (the conserving constant). The constraint holds in
    every case. In 2D the quadratic needs 3 x 3 particles per cell to be
    determined on uniform layouts (2 x 2 falls back to linear everywhere).

    Bound test (this project's rule; the paper fits whole cells that the
    body fills): a level's fit is kept for value column c only when its
    values at the cell's Gauss points stay within
    [min_p f_pc - s, max_p f_pc + s] over the cell's particles,
    s = TLS_BOUND_TOL (max - min) + TLS_BOUND_ABS max |f_pc|; otherwise
    that column takes the next lower level, the constant last (which
    conserves and, on a rule that holds the particles' volume, lies in the
    range). A smooth field's quadratic leaves the range by a fraction of
    it; a fit bent by the constraint where the rule and the body differ
    (a cell cut diagonally by a free surface) leaves it by the field's
    size: without the test a constant density gave rho_h = -1.7 rho on
    whole-cell rules, i.e. negative lumped masses and an indefinite
    consistent mass matrix.

    ``constraint="mean"`` (an option; the reference executor runs it)
    replaces S by (G_0 / sum_(p in e) V_p) S: the fit's mean over the cell
    is the particles' volume-weighted mean instead of its integral being
    their integral. The published constraint is a particle quadrature of
    the cell's zeroth moment: when a particle crosses into a cell of
    3 x 3, S jumps by a ninth, and so do rho_h and sigma_h there (D1 large,
    16 x 16, consistent MUSL: error 0.106 published, 0.0155 with "mean",
    3.85e-3 without reconstruction). Mass and momentum are then conserved
    only where the cells' particle volumes equal their rule volumes.
    ``constraint="none"`` drops the constraint: the plain volume-weighted
    least-squares quadratic of the cell's particles (the constant fallback:
    their volume-weighted mean), Taylor least squares without its
    conservation (Wobbes et al. 2019, Sec. 2). It reproduces quadratics on
    any layout and does not jump by a particle's share as particles cross
    (D1 large as above: 2.0e-3, against 3.85e-3 without reconstruction);
    mass and momentum are conserved only up to the fit's error.

    ``degree=1`` uses the linear fit (and the constant fallback).
    ``neighbour_weight`` > 0 adds the particles of the 3^d neighbouring
    cells to each cell's fit with that weight (the constraint stays the
    cell's own); with 1e-3 it was this project's earlier default. It
    determines the fit of cells with few particles from their neighbours.
    """
    if degree not in (1, 2):
        raise ValueError(f"tls degree must be 1 or 2, got {degree!r}")
    if constraint not in ("integral", "mean", "none"):
        raise ValueError(f"tls constraint must be 'integral', 'mean' or 'none', got "
                         f"{constraint!r}")
    neighbour_weight = float(neighbour_weight)
    if not (neighbour_weight >= 0.0 and np.isfinite(neighbour_weight)):
        raise ValueError(f"tls neighbour_weight must be a finite number >= 0, got "
                         f"{neighbour_weight!r}")
    values = np.asarray(values, dtype=np.float64)
    k = values.shape[1]
    dim = grid.dim
    active = np.unique(rule.cell)
    slot = np.full(grid.ncells, -1)
    slot[active] = np.arange(active.size)
    # each cell's frame: the box spanned by its Gauss points (the part of
    # the cell the body covers; better conditioned than the whole cell)
    gslot = slot[rule.cell]
    low_corner = np.full((active.size, dim), np.inf)
    high_corner = np.full((active.size, dim), -np.inf)
    np.minimum.at(low_corner, gslot, rule.x)
    np.maximum.at(high_corner, gslot, rule.x)
    centre = 0.5 * (low_corner + high_corner)
    size = high_corner - low_corner
    m = _levels(dim)[degree]
    pcell, _ = grid.locate(particles.x)
    if neighbour_weight > 0:
        nb = _neighbour_cells(grid, pcell)  # cells whose neighbourhood holds particle p
        own_column = nb.shape[1] // 2
    else:
        nb, own_column = pcell[:, None], 0
    A = np.zeros((active.size, m, m))
    b = np.zeros((active.size, m, k))
    for j in range(nb.shape[1]):
        c = nb[:, j]
        s = np.where(c >= 0, slot[np.maximum(c, 0)], -1)
        use = s >= 0
        s = s[use]
        phi = _monomials((particles.x[use] - centre[s]) / size[s], degree)
        weight = 1.0 if j == own_column else neighbour_weight
        wphi = (weight * particles.V[use])[:, None] * phi
        np.add.at(A, s, wphi[:, :, None] * phi[:, None, :])
        np.add.at(b, s, wphi[:, :, None] * values[use, None, :])
    # constraint: Gauss integral over the cell = particle integral of the cell
    gphi = _monomials((rule.x - centre[gslot]) / size[gslot], degree)
    G = np.zeros((active.size, m))
    np.add.at(G, gslot, rule.w[:, None] * gphi)
    own = slot[pcell]
    S = np.zeros((active.size, k))
    np.add.at(S, own[own >= 0], particles.V[own >= 0, None] * values[own >= 0])
    if constraint in ("mean", "none"):  # the cell's mean is the particles' volume-weighted mean
        # (for "none" only the constant fallback uses it: the least-squares constant)
        volume = np.zeros(active.size)
        np.add.at(volume, own[own >= 0], particles.V[own >= 0])
        S = S * np.where(volume > 0, G[:, 0] / np.where(volume > 0, volume, 1.0), 0.0)[:, None]
    # the bound test: the particle values' range per cell and column
    own_ok = own >= 0
    fmin = np.full((active.size, k), np.inf)
    fmax = np.full((active.size, k), -np.inf)
    np.minimum.at(fmin, own[own_ok], values[own_ok])
    np.maximum.at(fmax, own[own_ok], values[own_ok])
    with np.errstate(invalid="ignore"):  # cells without own particles (1D): nan, no fit kept
        slack = TLS_BOUND_TOL * (fmax - fmin) + TLS_BOUND_ABS * np.maximum(abs(fmin), abs(fmax))
    coef = np.zeros((active.size, m, k))
    pending = np.ones((active.size, k), dtype=bool)  # columns still without a fit
    for size_m in [n for n in _levels(dim)[1:] if n <= m][::-1]:
        use = pending.any(axis=1) & _well_posed(A, size_m)
        if not use.any():
            continue
        K = np.zeros((int(use.sum()), size_m + 1, size_m + 1))
        K[:, :size_m, :size_m] = A[use][:, :size_m, :size_m]
        K[:, :size_m, size_m] = G[use][:, :size_m]
        K[:, size_m, :size_m] = G[use][:, :size_m]
        rhs = np.concatenate((b[use][:, :size_m], S[use][:, None, :]), axis=1)
        if constraint == "none":  # plain least squares: [[A, 0], [0, 1]] [a; 0] = [b; 0]
            K[:, :size_m, size_m] = 0.0
            K[:, size_m, :size_m] = 0.0
            K[:, size_m, size_m] = 1.0
            rhs[:, size_m] = 0.0
        trial = np.zeros((active.size, m, k))
        trial[use, :size_m] = np.linalg.solve(K, rhs)[:, :size_m, :]
        at_points = np.einsum("gm,gmk->gk", gphi, trial[gslot])
        low = np.full((active.size, k), np.inf)
        high = np.full((active.size, k), -np.inf)
        np.minimum.at(low, gslot, at_points)
        np.maximum.at(high, gslot, at_points)
        accept = (use[:, None] & pending & (low >= fmin - slack) & (high <= fmax + slack))
        coef = np.where(accept[:, None, :], trial, coef)
        pending &= ~accept
    # the last fallback: the conserving constant
    coef[:, 0, :] = np.where(pending, S / G[:, 0][:, None], coef[:, 0, :])
    return np.einsum("gm,gmk->gk", gphi, coef[gslot])


# ---------------------------------------------------------------------- MLS
def _cubic_weight(r):
    """The cubic B-spline kernel on [0, 1] (normalised so w(0) = 1)."""
    w = np.zeros_like(r)
    a = r <= 0.5
    w[a] = 1 - 6 * r[a] ** 2 + 6 * r[a] ** 3
    b = (r > 0.5) & (r < 1)
    w[b] = 2 * (1 - r[b]) ** 3
    return w


def reconstruct_mls(grid, particles, values, rule, radius=1.5, degree=1):
    """Moving least squares (see the module docstring); ``radius`` in cells
    (of the smallest cell size). At each Gauss point x_g, with the weights
    w_p = W(|x_p - x_g| / r) and the monomials phi of (x_p - x_g) / r up to
    ``degree`` (1: linear, the default; 2: quadratic), the value is the
    constant coefficient of the weighted fit, a_0 with
    (sum_p w_p phi_p phi_p^T) a = sum_p w_p phi_p f_p. Where the moment
    matrix of a degree is not well conditioned (smallest eigenvalue of it
    over its mean diagonal <= 1e-6) the next lower degree is used, the
    weighted mean (Shepard) last."""
    if degree not in (1, 2):
        raise ValueError(f"mls degree must be 1 or 2, got {degree!r}")
    values = np.asarray(values, dtype=np.float64)
    r = float(radius) * min(grid.h)
    dim = grid.dim
    pairs = cKDTree(rule.x).sparse_distance_matrix(cKDTree(particles.x), r,
                                                   output_type="coo_matrix")
    g, p = pairs.row, pairs.col
    w = _cubic_weight(pairs.data / r)
    keep = w > 0
    g, p, w = g[keep], p[keep], w[keep]
    ng, k = rule.x.shape[0], values.shape[1]
    phi = _monomials((particles.x[p] - rule.x[g]) / r, degree)
    m = phi.shape[1]
    M = np.zeros((ng, m, m))
    np.add.at(M, g, w[:, None, None] * phi[:, :, None] * phi[:, None, :])
    rhs = np.zeros((ng, m, k))
    np.add.at(rhs, g, w[:, None, None] * phi[:, :, None] * values[p, None, :])
    out = np.zeros((ng, k))
    weight_sum = M[:, 0, 0]
    shepard = weight_sum > 0
    out[shepard] = rhs[shepard, 0, :] / weight_sum[shepard, None]
    for size in _levels(dim)[1:degree + 1]:  # linear, then quadratic
        sub = M[:, :size, :size]
        scale = np.maximum(np.einsum("gii->g", sub) / size, 1e-300)
        ok = np.zeros(ng, dtype=bool)
        if ng:
            ok = np.linalg.eigvalsh(sub / scale[:, None, None])[:, 0] > 1e-6
        if ok.any():
            out[ok] = np.linalg.solve(sub[ok], rhs[ok][:, :size])[:, 0, :]
    return out


reconstruct_spline = at_rule_points(reconstruct_spline)
reconstruct_tls = at_rule_points(reconstruct_tls)
reconstruct_mls = at_rule_points(reconstruct_mls)
RECONSTRUCTORS = {"spline": reconstruct_spline, "tls": reconstruct_tls, "mls": reconstruct_mls}
