"""The B-spline functions of one particle on a tensor grid, in any dimension.

Per axis d the particle at x_d lies in cell e_d; the p + 1 non-zero 1D
B-splines there are N^d_(e_d + a), a = 0..p, with values w^d_a and
derivatives g^d_a = dN^d/dx_d. The grid function of the tensor node
k = (e_0 + a_0, ..., e_(dim-1) + a_(dim-1)) is the product

    N_k(x) = prod_d w^d_(a_d),   dN_k/dx_c = g^c_(a_c) prod_(d != c) w^d_(a_d)

(Piegl & Tiller, The NURBS Book, 1997, sec. 3.4). Nodes are numbered with
axis 0 fastest, so the flat index of node k is sum_d (e_d + a_d) s_d with
the strides s_0 = 1, s_d = s_(d-1) n_(d-1) (n_d functions on axis d): the
stencil's offset from its first node, sum_d a_d s_d, is the same for every
particle.

The 1D values come from :func:`axis_functions`: on the interior cells of a
uniform axis (p <= e < cells - p) the closed form of the uniform B-spline
pieces (de Boor, A Practical Guide to Splines, 1978, ch. IX), elsewhere
the cell's Bezier extraction matrix applied to the Bernstein polynomials
(Borden et al. 2011, eq. 8; :mod:`skfem_mpm.kernels.weights`). Both return
scalars, so a kernel keeps a particle's weights in registers. The generated
kernels call the closed form (:func:`closed_axis_functions`) with scalars
only and the extraction, not inlined, where it does not apply: an inlined
function of arrays makes numba count references to them on every call,
which the serial kernels (no parallel region to outline the loop into)
paid per particle and axis.

:func:`stencil_rows` and :func:`row_products` write the source text of the
loops over the (p + 1)^dim nodes for the kernels generated per dimension
and degree (:mod:`skfem_mpm.kernels.generated`).
"""
import itertools

from numba import njit

from .weights import FAST, bernstein4, locate_axis_point

__all__ = ["axis_functions", "closed_axis_functions", "extracted_axis_functions",
           "row_products", "stencil_rows"]

@njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def axis_functions(x, breaks, uniform, inv_h, C, p):
    """(e, w_0..w_3, g_0..g_3): the cell of coordinate x on an axis (the
    fields of :data:`skfem_mpm.kernels.records.Axis`) and the values and d/dx of its p + 1 B-splines
    (entries beyond p are 0).

    Uniform interior cells, t = (x - u_0) / h, xi = t - e, r = 1 - xi:
    p = 1: (r, xi); p = 2: (r^2 / 2, 1/2 + xi r, xi^2 / 2);
    p = 3: (r^3, 3 xi^3 - 6 xi^2 + 4, -3 xi^3 + 3 xi^2 + 3 xi + 1, xi^3) / 6.
    Other cells: extraction of the Bernstein polynomials. A NaN coordinate
    takes the extraction path (the comparisons on t are false)."""
    closed, e, w0, w1, w2, w3, g0, g1, g2, g3 = closed_axis_functions(
        x, breaks[0], breaks.shape[0] - 1, uniform, inv_h, p)
    if closed:
        return e, w0, w1, w2, w3, g0, g1, g2, g3
    return extracted_axis_functions(x, breaks, uniform, inv_h, C, p)


@njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def closed_axis_functions(x, first_break, ncells, uniform, inv_h, p):
    """(True, e, w_0..w_3, g_0..g_3) of :func:`axis_functions` on an
    interior cell of a uniform axis (its first breakpoint ``first_break``,
    ``ncells`` cells), else (False, 0, zeros): the closed form only, of
    scalars only (see the module)."""
    t = (x - first_break) * inv_h
    if uniform and t >= p and t < ncells - p:
        e = int(t)
        xi = t - e
        r = 1.0 - xi
        if p == 1:
            return True, e, r, xi, 0.0, 0.0, -inv_h, inv_h, 0.0, 0.0
        if p == 2:
            return (True, e, 0.5 * r * r, 0.5 + xi * r, 0.5 * xi * xi, 0.0,
                    -r * inv_h, (1.0 - 2.0 * xi) * inv_h, xi * inv_h, 0.0)
        xi2 = xi * xi
        xi3 = xi2 * xi
        return (True, e, r * r * r / 6.0, (3.0 * xi3 - 6.0 * xi2 + 4.0) / 6.0,
                (-3.0 * xi3 + 3.0 * xi2 + 3.0 * xi + 1.0) / 6.0, xi3 / 6.0,
                -0.5 * r * r * inv_h, (1.5 * xi2 - 2.0 * xi) * inv_h,
                (-1.5 * xi2 + xi + 0.5) * inv_h, 0.5 * xi2 * inv_h)
    return False, 0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0


@njit(cache=True, error_model="numpy", fastmath=FAST)
def extracted_axis_functions(x, breaks, uniform, inv_h, C, p):
    """:func:`axis_functions` by Bezier extraction, in any cell (not
    inlined: kept out of the kernels' loops, whose common case is the
    closed form)."""
    e = locate_axis_point(x, breaks, uniform, inv_h)
    h = breaks[e + 1] - breaks[e]
    xi = (x - breaks[e]) / h
    b0, b1, b2, b3, c0, c1, c2, c3 = bernstein4(p, xi)
    # d/dxi of the Bernstein polynomials: p (B^(p-1)_(j-1) - B^(p-1)_j)
    q0 = -p * c0
    q1 = p * (c0 - c1)
    q2 = p * (c1 - c2)
    q3 = p * (c2 - c3)
    inv = 1.0 / h
    w0, g0 = _extracted(C, e, 0, p, b0, b1, b2, b3, q0, q1, q2, q3)
    w1, g1 = _extracted(C, e, 1, p, b0, b1, b2, b3, q0, q1, q2, q3)
    w2 = g2 = w3 = g3 = 0.0
    if p >= 2:
        w2, g2 = _extracted(C, e, 2, p, b0, b1, b2, b3, q0, q1, q2, q3)
    if p >= 3:
        w3, g3 = _extracted(C, e, 3, p, b0, b1, b2, b3, q0, q1, q2, q3)
    return e, w0, w1, w2, w3, g0 * inv, g1 * inv, g2 * inv, g3 * inv


@njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def _extracted(C, e, a, p, b0, b1, b2, b3, q0, q1, q2, q3):
    """(sum_j C_e[a, j] B_j, sum_j C_e[a, j] dB_j/dxi) over j = 0..p."""
    v = C[e, a, 0] * b0 + C[e, a, 1] * b1
    d = C[e, a, 0] * q0 + C[e, a, 1] * q1
    if p >= 2:
        v += C[e, a, 2] * b2
        d += C[e, a, 2] * q2
    if p >= 3:
        v += C[e, a, 3] * b3
        d += C[e, a, 3] * q3
    return v, d


# ------------------------------------------------------------ source text
def weight_names(d, p):
    """Names of axis d's cell, values and derivatives in generated source."""
    return f"e{d}", [f"w{d}_{a}" for a in range(p + 1)], [f"g{d}_{a}" for a in range(p + 1)]


def axis_fields(dim):
    """Lines unpacking the grid record's axes (before a parallel loop, which
    takes arrays and scalars only)."""
    lines = []
    for d in range(dim):
        lines += [f"b{d}, u{d}, ih{d}, C{d} = grid[0][{d}]",
                  f"first_break{d} = b{d}[0]", f"ncells{d} = b{d}.shape[0] - 1"]
    return lines


def axis_calls(dim, p, x="x", i="i"):
    """Lines computing every axis' cell, values and derivatives of particle i
    (:func:`axis_functions`: the closed form, else the extraction)."""
    lines = []
    for d in range(dim):
        e, w, g = weight_names(d, p)
        pad = ["_"] * (3 - p)
        lhs = ", ".join([e] + w + pad + g + pad)
        xd = f"{x}[{i}, {d}]"
        lines += [f"closed{d}, {lhs} = closed_axis_functions({xd}, first_break{d}, ncells{d}, "
                  f"u{d}, ih{d}, {p})",
                  f"if not closed{d}:",
                  f"    {lhs} = extracted_axis_functions({xd}, b{d}, u{d}, ih{d}, C{d}, {p})"]
    return lines


def stencil_rows(dim, p):
    """The rows of the stencil: multi-indices (a_1, ..., a_(dim-1)) of the
    axes after the first, in node order; along a row a_0 = 0..p are adjacent
    nodes."""
    return [tuple(reversed(b)) for b in itertools.product(range(p + 1), repeat=dim - 1)]


def row_offset(row):
    """Source of a row's first node relative to the stencil's first node."""
    terms = [f"{b} * s{d + 1}" if b > 1 else f"s{d + 1}"
             for d, b in enumerate(row) if b > 0]
    return " + ".join(terms) if terms else "0"


def row_products(row, p):
    """Source expressions of a row's weight product and its derivative
    products: (r, [r_1, ..., r_(dim-1)]) with r = prod_(d >= 1) w^d_(a_d)
    and r_c = g^c_(a_c) prod_(d >= 1, d != c) w^d_(a_d). In 1D r = "1.0"."""
    if not row:
        return "1.0", []
    values = [f"w{d + 1}_{b}" for d, b in enumerate(row)]
    r = " * ".join(values)
    grads = []
    for c in range(len(row)):
        factors = [f"g{c + 1}_{row[c]}" if d == c else values[d] for d in range(len(row))]
        grads.append(" * ".join(factors))
    return r, grads


def last_node(dim, p):
    """Source of the offset of the stencil's last node plus one."""
    return " + ".join([f"{p + 1}"] + [f"{p} * s{d}" for d in range(1, dim)])


def stride_names(dim):
    """Lines unpacking the grid record: its axes and the strides
    s_1..s_(dim-1)."""
    lines = axis_fields(dim)
    if dim > 1:
        names = ", ".join(["_"] + [f"s{d}" for d in range(1, dim)])
        lines.append(f"{names} = grid[1]")
    return lines


def base_index(dim):
    """Source of the flat index of the stencil's first node."""
    return " + ".join(["e0"] + [f"e{d} * s{d}" for d in range(1, dim)])


# Grid arrays are read and written through flat views (node k, field f at
# k nf + f) with unsigned indices: numba then neither multiplies by a
# run-time row length nor adds the wrap-around of negative indices.
def row_starts(dim, p, nf):
    """Lines (before the particle loop) of each stencil row's first entry
    relative to the stencil's first, in a flat array of nf fields per node."""
    return [f"O{nf}_{j} = ({row_offset(row)}) * {nf}"
            for j, row in enumerate(stencil_rows(dim, p))]


def entry(array, nf, j, a, f, first):
    """Source of field f of node a of stencil row j in the flat ``array``
    (nf fields per node; ``first`` + nf: the flat index of the stencil's
    first node, see :func:`first_entry`)."""
    offset = a * nf + f
    return f"{array}[np.uint64({first}{nf} + O{nf}_{j}" + (f" + {offset})]" if offset else ")]")


def first_entry(nf, node="base", first="K"):
    """Line of the flat index of a stencil's first node."""
    return f"{first}{nf} = {node} * {nf}"
