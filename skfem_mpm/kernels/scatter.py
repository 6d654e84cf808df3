"""Particles to grid (p2g) and the MUSL re-projection (g2p2g), any dimension.

    p2g    out[k] = (m_k, P_k (dim), f_k (dim))   lumped mass, momentum, force
           m_k = sum_p m_p N_kp,  P_k = sum_p m_p v_p N_kp,
           f_k = sum_p (f_p N_kp - V_p sym(sigma_p) grad N_k(x_p))
    g2p2g  v_p^new = v_p + dt sum_k a_k N_kp,  out[k] = sum_p m_p v_p^new N_kp

(Sulsky et al. 1994; MUSL: Sulsky et al. 1995.) The weights of each
particle are recomputed in each pass (:mod:`skfem_mpm.kernels.stencil`)
instead of storing N. Along a stencil row (the p + 1 nodes adjacent on
axis 0) N_k = w^0_a r and grad N_k = (g^0_a r, w^0_a r_1, ...), with r and
r_c the row's products over the other axes, so a row's particle terms are
formed once and each node takes

    m_k += w^0_a (r m),  P_k += w^0_a (r m v),
    f_k += w^0_a (r f - sum_(c >= 1) S_(:, c) r_c) - g^0_a (S_(:, 0) r)

with S = V sym(sigma).

Race-free scatter: the particles are split into one contiguous block per
thread; each thread adds into its own copy of the grid, over the node range
its block touches (``touched[t] = first, last + 1``; the copy is zero
outside it), and :func:`reduce_fields` / :func:`reduce_copies` sum the
copies node by node over the threads whose range holds the node
(deterministic for a fixed thread count). The next call clears only that
range.

Run window (``window=True``): sorted particles come in runs sharing a cell;
a run's contributions to its stencil are summed in registers and written
once per run, instead of each particle's adds waiting on the previous
particle's stores to the same nodes. Any order gives the same sums;
unsorted particles only write more often.

The kernels are generated per (dim, p, window) from the templates below
(:mod:`skfem_mpm.kernels.generated`); :func:`p2g_kernel` and
:func:`g2p2g_kernel` return them compiled.
"""
import functools

import numpy as np
from numba import njit, prange

from . import stencil as st
from .generated import indent, load, module_header, times
from .records import ParticleArrays, unpack
from .weights import FAST

__all__ = [
    "g2p2g_kernel",
    "g2p2g_source",
    "p2g_kernel",
    "p2g_source",
    "node_hull",
    "reduce_copies",
    "reduce_fields",
    "touched_hull",
]


# ---------------------------------------------------------------- templates
P2G = '''
@njit(cache=True, parallel={parallel}, error_model="numpy", fastmath=FAST)
def {name}(particles, grid, fext, has_fext, copies, touched):
    """p2g, dim = {dim}, p = {p}: see skfem_mpm.kernels.scatter."""
    {unpack}
{grid}
    n = x.shape[0]
    nt, nk, nf = copies.shape
    for t in prange(nt):
        copies[t, touched[t, 0]:touched[t, 1], :] = 0.0  # what the last call wrote
        g = copies[t].reshape(nk * nf)
        first = nk
        last = 0
        lo = t * n // nt
        hi = (t + 1) * n // nt
{start}
        for i in range(lo, hi):
            ip = np.uint64(i)
{particle}
{weights}
            base = {base}
{scatter}
{finish}
        touched[t, 0] = first
        touched[t, 1] = last
'''

G2P2G = '''
@njit(cache=True, parallel={parallel}, error_model="numpy", fastmath=FAST)
def {name}(particles, grid, grid_a, dt, v_new, copies, touched):
    """g2p2g, dim = {dim}, p = {p}: see skfem_mpm.kernels.scatter."""
    {unpack}
    a_flat = grid_a.reshape(grid_a.size)
{grid}
    n = x.shape[0]
    nt, nk, nf = copies.shape
    for t in prange(nt):
        copies[t, touched[t, 0]:touched[t, 1], :] = 0.0  # what the last call wrote
        g = copies[t].reshape(nk * nf)
        first = nk
        last = 0
        lo = t * n // nt
        hi = (t + 1) * n // nt
{start}
        for i in range(lo, hi):
            ip = np.uint64(i)
{weights}
            base = {base}
{gather}
{particle}
{scatter}
{finish}
        touched[t, 0] = first
        touched[t, 1] = last
'''


def _scatter(dim, p, nf, terms, window):
    """Lines adding each node's share into g (nf fields per node; into the
    window's registers with ``window``): ``terms(r, rc)`` returns the lines
    that set up a row's names and ``per_node(a)``, the source added to each
    field of the row's node a."""
    lines = [] if window else [st.first_entry(nf, first="KG")]
    for j, row in enumerate(st.stencil_rows(dim, p)):
        setup, per_node = terms(*st.row_products(row, p))
        lines += setup
        for a in range(p + 1):
            for f, expr in enumerate(per_node(a)):
                node = j * (p + 1) + a
                if window:
                    lines.append(f"W{node}_{f} += {expr}")
                else:
                    lines.append(f"{st.entry('g', nf, j, a, f, 'KG')} += {expr}")
    return lines


def _window(dim, p, nf, window):
    """(start, before the scatter, finish) lines of the run window, or of
    the touched range without one."""
    last = f"last = max(last, base + {st.last_node(dim, p)})"
    if not window:
        return [], ["first = min(first, base)", last], []
    names = [f"W{k}_{f}" for k in range((p + 1) ** dim) for f in range(nf)]
    zero = [" = ".join(names[j:j + 8]) + " = 0.0" for j in range(0, len(names), 8)]
    flush = [st.first_entry(nf, "run", "KR")]
    for j, row in enumerate(st.stencil_rows(dim, p)):
        for a in range(p + 1):
            node = j * (p + 1) + a
            flush += [f"{st.entry('g', nf, j, a, f, 'KR')} += W{node}_{f}" for f in range(nf)]
    start = ["run = -1"] + zero
    before = (["if base != run:", "    if run >= 0:"] + ["        " + s for s in flush]
              + ["    run = base", "    first = min(first, base)", "    " + last]
              + ["    " + z for z in zero])
    finish = ["if run >= 0:"] + ["    " + s for s in flush]
    return start, before, finish


def _stress_names(dim):
    """S_cd = V sym(sigma)_cd source lines (c <= d)."""
    lines = ["Vi = V[ip]"]
    for c in range(dim):
        for d in range(c, dim):
            if c == d:
                lines.append(f"S{c}{d} = Vi * stress[ip, {c}, {c}]")
            else:
                lines.append(f"S{c}{d} = Vi * 0.5 * (stress[ip, {c}, {d}] + stress[ip, {d}, {c}])")
    return lines


def _S(c, d):
    return f"S{min(c, d)}{max(c, d)}"


def _grid_lines(dim, p, *nfs):
    return st.stride_names(dim) + [line for nf in nfs for line in st.row_starts(dim, p, nf)]


def p2g_name(dim, p, window, parallel=True):
    return f"p2g_{dim}d_p{p}" + ("_window" if window else "") + ("" if parallel else "_serial")


def p2g_source(dim, p, window, parallel=True):
    """Source of the p2g kernel for (dim, p)."""
    name = p2g_name(dim, p, window, parallel)
    nf = 1 + 2 * dim
    particle = ["mi = m[ip]"] + [f"P{c} = mi * v[ip, {c}]" for c in range(dim)]
    particle += _stress_names(dim)
    particle += [f"f{c} = fext[ip, {c}] if has_fext else 0.0" for c in range(dim)]

    def terms(r, rc):
        setup = []
        if r != "1.0":
            setup.append(f"r = {r}")
            r = "r"
        for c, expr in enumerate(rc):
            setup.append(f"r{c + 1} = {expr}")
        setup.append(f"R = {times(r, 'mi')}")
        setup += [f"RP{c} = {times(r, f'P{c}')}" for c in range(dim)]
        for c in range(dim):
            force = times(r, f"f{c}")
            for d in range(1, dim):
                force += f" - {_S(c, d)} * r{d}"
            setup.append(f"RF{c} = {force}")
            setup.append(f"RH{c} = {times(_S(c, 0), r)}")

        def per_node(a):
            w, dw = f"w0_{a}", f"g0_{a}"
            return ([f"{w} * R"] + [f"{w} * RP{c}" for c in range(dim)]
                    + [f"{w} * RF{c} - {dw} * RH{c}" for c in range(dim)])
        return setup, per_node

    start, before, finish = _window(dim, p, nf, window)
    body = P2G.format(
        parallel=parallel, name=name, dim=dim, p=p, grid=indent(_grid_lines(dim, p, nf), 1),
        unpack=unpack(ParticleArrays, "particles"),
        start=indent(start, 2), particle=indent(particle, 3),
        weights=indent(st.axis_calls(dim, p, i="ip"), 3), base=st.base_index(dim),
        scatter=indent(before + _scatter(dim, p, nf, terms, window), 3),
        finish=indent(finish, 2))
    return name, module_header() + body


def g2p2g_name(dim, p, window, parallel=True):
    return f"g2p2g_{dim}d_p{p}" + ("_window" if window else "") + ("" if parallel else "_serial")


def g2p2g_source(dim, p, window, parallel=True):
    """Source of the g2p2g kernel for (dim, p)."""
    name = g2p2g_name(dim, p, window, parallel)
    rows = st.stencil_rows(dim, p)
    gather = [st.first_entry(dim, first="KA")]
    for j, row in enumerate(rows):
        r, _ = st.row_products(row, p)
        for c in range(dim):
            parts = [f"w0_{a} * {st.entry('a_flat', dim, j, a, c, 'KA')}" for a in range(p + 1)]
            gather.append(f"A{j}_{c} = {times(r, '(' + ' + '.join(parts) + ')')}")
    particle = []
    for c in range(dim):
        total = " + ".join(f"A{j}_{c}" for j in range(len(rows)))
        particle += [f"vn{c} = v[ip, {c}] + dt * ({total})", f"v_new[ip, {c}] = vn{c}",
                     f"P{c} = m[ip] * vn{c}"]

    def terms(r, rc):
        setup = []
        if r != "1.0":
            setup.append(f"r = {r}")
        setup += [f"RP{c} = {times('r' if r != '1.0' else '1.0', f'P{c}')}" for c in range(dim)]

        def per_node(a):
            return [f"w0_{a} * RP{c}" for c in range(dim)]
        return setup, per_node

    start, before, finish = _window(dim, p, dim, window)
    body = G2P2G.format(
        parallel=parallel, name=name, dim=dim, p=p, grid=indent(_grid_lines(dim, p, dim), 1),
        unpack=unpack(ParticleArrays, "particles"),
        start=indent(start, 2), weights=indent(st.axis_calls(dim, p, i="ip"), 3),
        base=st.base_index(dim), gather=indent(gather, 3), particle=indent(particle, 3),
        scatter=indent(before + _scatter(dim, p, dim, terms, window), 3),
        finish=indent(finish, 2))
    return name, module_header() + body


@functools.cache
def p2g_kernel(dim, p, window=None, parallel=True):
    """The compiled p2g kernel; ``window`` None: the default (1D only)."""
    window = dim == 1 if window is None else window
    name, source = p2g_source(dim, p, window, parallel)
    return getattr(load(name, source), name)


@functools.cache
def g2p2g_kernel(dim, p, window=None, parallel=True):
    """The compiled g2p2g kernel; ``window`` None: the default (1D only)."""
    window = dim == 1 if window is None else window
    name, source = g2p2g_source(dim, p, window, parallel)
    return getattr(load(name, source), name)


# ---------------------------------------------------------------- reduction
@njit(cache=True, error_model="numpy")
def _sorted_distinct(values):
    """np.unique of a short integer array (insertion sort: a few dozen
    values; numba's np.unique compiles a general sort, seconds cold)."""
    out = values.copy()
    for i in range(1, out.shape[0]):
        v = out[i]
        j = i - 1
        while j >= 0 and out[j] > v:
            out[j + 1] = out[j]
            j -= 1
        out[j + 1] = v
    n = 0
    for i in range(out.shape[0]):
        if n == 0 or out[i] != out[n - 1]:
            out[n] = out[i]
            n += 1
    return out[:n]


@njit(cache=True, error_model="numpy")
def holders(touched, lo, hi):
    """Nodes lo..hi-1 cut where the set of threads whose touched range holds
    them changes: (cuts, threads, counts); piece j is nodes
    cuts[j]..cuts[j + 1] - 1, held by threads[j, :counts[j]]."""
    nt = touched.shape[0]
    bounds = np.empty(2 * nt + 2, dtype=np.int64)
    bounds[0] = lo
    bounds[1] = hi
    for t in range(nt):
        bounds[2 + 2 * t] = min(max(touched[t, 0], lo), hi)
        bounds[3 + 2 * t] = min(max(touched[t, 1], lo), hi)
    cuts = _sorted_distinct(bounds)
    threads = np.empty((cuts.shape[0], nt), dtype=np.int64)
    counts = np.zeros(cuts.shape[0], dtype=np.int64)
    for j in range(cuts.shape[0] - 1):
        for t in range(nt):
            if touched[t, 0] <= cuts[j] and cuts[j + 1] <= touched[t, 1]:
                threads[j, counts[j]] = t
                counts[j] += 1
    return cuts, threads, counts


@njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def _sum_copies(flat, starts, count, at):
    """sum over the held copies j < count of flat[starts[j] + at] (flat:
    the copies as one array; starts: the held copies' first entries)."""
    s = 0.0
    for j in range(count):
        s += flat[np.uint64(starts[j] + at)]
    return s


@njit(cache=True, inline="always", error_model="numpy")
def _starts(threads, count, size):
    """First flat entry of each held copy (of ``size`` entries)."""
    starts = np.empty(threads.shape[0], dtype=np.int64)
    for j in range(count):
        starts[j] = threads[j] * size
    return starts


@njit(cache=True, inline="always", error_model="numpy")
def node_hull(lo0, hi0, lo1, hi1):
    """The smallest node range [lo, hi) holding [lo0, hi0) and [lo1, hi1)
    (a range with lo >= hi is empty; two empty ones give (0, 0))."""
    if lo0 >= hi0:
        return (lo1, hi1) if lo1 < hi1 else (0, 0)
    if lo1 >= hi1:
        return lo0, hi0
    return min(lo0, lo1), max(hi0, hi1)


@njit(cache=True, error_model="numpy")
def touched_hull(touched):
    """The node range [lo, hi) holding every thread's touched range."""
    lo, hi = 0, 0
    for t in range(touched.shape[0]):
        lo, hi = node_hull(lo, hi, touched[t, 0], touched[t, 1])
    return lo, hi


@njit(cache=True, inline="always", error_model="numpy", fastmath=FAST)
def _reduce_one_copy(flat, t0, t1, w0, w1, nc, dim, mass, P, f, mass_range):
    """:func:`reduce_fields` of one copy (held on t0..t1 - 1): the same sums
    (0.0 plus the copy's entry; 0.0 on the nodes it does not hold)."""
    smallest = np.inf
    largest = 0.0
    for k in range(w0, w1):
        held = t0 <= k and k < t1
        s = 0.0
        if held:
            s += flat[np.uint64(k * nc)]
        mass[np.uint64(k)] = s
        if s > 0.0:
            smallest = min(smallest, s)
            largest = max(largest, s)
        for c in range(dim):
            pc = 0.0
            fc = 0.0
            if held:
                pc += flat[np.uint64(k * nc + 1 + c)]
                fc += flat[np.uint64(k * nc + 1 + dim + c)]
            P[np.uint64(k * dim + c)] = pc
            f[np.uint64(k * dim + c)] = fc
    mass_range[0, 0] = smallest
    mass_range[0, 1] = largest


@njit(cache=True, inline="always", parallel=True, error_model="numpy", fastmath=FAST)
def _reduce_held(flat, touched, w0, span, nk, nc, dim, mass, P, f, mass_range):
    """:func:`reduce_fields` of several copies: chunk r of the nodes
    w0..w0 + span - 1 summed over the copies that hold each node."""
    nr = mass_range.shape[0]
    for r in prange(nr):
        smallest = np.inf
        largest = 0.0
        cuts, threads, counts = holders(touched, w0 + r * span // nr, w0 + (r + 1) * span // nr)
        for j in range(cuts.shape[0] - 1):
            count = counts[j]
            starts = _starts(threads[j], count, nk * nc)
            for k in range(cuts[j], cuts[j + 1]):
                s = _sum_copies(flat, starts, count, k * nc)
                mass[np.uint64(k)] = s
                if s > 0.0:
                    smallest = min(smallest, s)
                    largest = max(largest, s)
                for c in range(dim):
                    P[np.uint64(k * dim + c)] = _sum_copies(flat, starts, count, k * nc + 1 + c)
                    f[np.uint64(k * dim + c)] = _sum_copies(flat, starts, count,
                                                            k * nc + 1 + dim + c)
        mass_range[r, 0] = smallest
        mass_range[r, 1] = largest


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def reduce_fields(copies, touched, mass, momentum, force, mass_range, occupied):
    """Sum the per-thread copies of p2g's (m, P, f) into three arrays;
    mass_range[r] = (smallest positive, largest) mass of chunk r's nodes.

    ``occupied`` (4,) holds two node ranges [lo, hi): entries 0-1 where
    (m, P, f) may be nonzero, 2-3 where the grid acceleration and velocity
    may be nonzero (other than constraint values; see
    :func:`skfem_mpm.kernels.mpm.usl_grid`). Only the nodes of the copies'
    ranges and of entries 0-1 are written (zero outside the copies'
    ranges); entries 0-1 become the copies' hull and entries 2-3 grow by
    it. A grid array whose first write is a call of this kernel (zeros on
    a mapping of small pages, :func:`skfem_mpm.kernels.pages.lazy_zeros`)
    then costs memory only near the particles. Whoever writes nonzero
    values into (m, P, f) outside entries 0-1 widens them."""
    _, nk, nc = copies.shape
    dim = momentum.shape[1]
    nr = mass_range.shape[0]
    flat = copies.reshape(copies.size)
    P = momentum.reshape(momentum.size)
    f = force.reshape(force.size)
    lo, hi = touched_hull(touched)
    w0, w1 = node_hull(occupied[0], occupied[1], lo, hi)
    span = w1 - w0
    if copies.shape[0] == 1 and nr == 1:  # one copy (serial kernels): no holders' lists
        _reduce_one_copy(flat, touched[0, 0], touched[0, 1], w0, w1, nc, dim, mass, P, f,
                         mass_range)
    else:
        _reduce_held(flat, touched, w0, span, nk, nc, dim, mass, P, f, mass_range)
    occupied[0] = lo
    occupied[1] = hi
    occupied[2], occupied[3] = node_hull(occupied[2], occupied[3], lo, hi)


@njit(cache=True, parallel=True, error_model="numpy", fastmath=FAST)
def reduce_copies(copies, touched, out):
    """out = the sum of the per-thread grid copies."""
    nt, nk, nc = copies.shape
    flat = copies.reshape(copies.size)
    o = out.reshape(out.size)
    for r in prange(nt):
        cuts, threads, counts = holders(touched, r * nk // nt, (r + 1) * nk // nt)
        for j in range(cuts.shape[0] - 1):
            count = counts[j]
            starts = _starts(threads[j], count, nk * nc)
            for a in range(cuts[j] * nc, cuts[j + 1] * nc):
                o[np.uint64(a)] = _sum_copies(flat, starts, count, a)
