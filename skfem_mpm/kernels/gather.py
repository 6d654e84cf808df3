"""Grid to particles (g2p), any dimension.

For each particle, with the grid acceleration a_k and velocity v_k:

    a_p = sum_k a_k N_kp,  v_p^new = v_p + c dt a_p   (FLIP, c = 1 or 1/2;
                                                     or v_p^new given)
    du_p = dt sum_k v_k N_kp,  x_p += du_p,  u_p += du_p
    L_p = sum_k v_k (x) grad N_k(x_p)

and, for linear elasticity (``fused``), the small-strain update
sigma_p += lambda tr(D) I + 2 mu D with D = dt sym(L_p) (in 1D lambda is
the modulus E and mu = 0), V_p *= J = det(I + dt L_p); otherwise L_p is
stored. Along a stencil row (:mod:`skfem_mpm.kernels.scatter`) the sums
over the p + 1 nodes of axis 0 are formed first,

    A = sum_a w^0_a a_k,  U = sum_a w^0_a v_k,  D0 = sum_a g^0_a v_k,

and the row adds r A to a_p, r U to the velocity, r D0 to L_(:, 0) and
r_c U to L_(:, c) for c >= 1.

flags[t] = (first non-finite particle, first particle outside the grid,
first particle with J <= 0) of thread t's block, or -1.

The rates gather (one evaluation of a Runge-Kutta stage's right-hand side,
:mod:`skfem_mpm.solve.runge_kutta`) reads the same sums at the particles
and moves nothing:

    dx_p/dt = sum_k v_k N_kp,   dv_p/dt = sum_k a_k N_kp,
    L_p = sum_k v_k (x) grad N_k(x_p),   dV_p/dt = V_p tr L_p,

and, for linear elasticity (``fused``), the stress rate
d sigma_p/dt = lambda tr(D) I + 2 mu D with D = sym(L_p) (in 1D lambda is
E and mu = 0); otherwise L_p is stored.

The kernels are generated per (dim, p) from the template below
(:mod:`skfem_mpm.kernels.generated`); :func:`g2p_kernel` returns them
compiled.
"""
import functools
import itertools

from . import stencil as st
from .generated import indent, load, module_header, times
from .records import ParticleArrays, Update, unpack

__all__ = ["g2p_kernel", "g2p_source", "rates_kernel", "rates_source"]

G2P = '''
@njit(cache=True, parallel={parallel}, error_model="numpy", fastmath=FAST)
def {name}(particles, grid, grid_a, grid_v, update, new, L_out, acc_out, flags):
    """g2p, dim = {dim}, p = {p}: see skfem_mpm.kernels.gather."""
    {unpack_particles}
    {unpack_new}
    a_flat = grid_a.reshape(grid_a.size)
    v_flat = grid_v.reshape(grid_v.size)
    {unpack_update}
    lam2mu = lam + 2.0 * mu
    mu2 = 2.0 * mu
{strides}
{bounds}
    n = x.shape[0]
    nt = flags.shape[0]
    for t in prange(nt):
        lo = t * n // nt
        hi = (t + 1) * n // nt
        bad = -1
        outside = -1
        negative = -1
        for i in range(lo, hi):
            ip = np.uint64(i)
{weights}
            base = {base}
{sums}
            if store_acc:
{store_acc}
            if flip:
{flip}
            else:
{given}
{move}
            J = {det}
            if fused:
{fused}
                V_new[ip] = V[ip] * J
            else:
{store_L}
            finite = {finite}
            inside = not ({outside})
            if J <= 0.0 or not finite or not inside:  # one test on the common path
                if J <= 0.0 and negative < 0:
                    negative = i
                if not finite and bad < 0:
                    bad = i
                if not inside and outside < 0:
                    outside = i
        flags[t, 0] = bad
        flags[t, 1] = outside
        flags[t, 2] = negative
'''


def determinant(dim, entry):
    """Source of det of the dim x dim matrix with entries ``entry(c, d)``
    (Leibniz formula)."""
    terms = []
    for perm in itertools.permutations(range(dim)):
        inversions = sum(1 for a, b in itertools.combinations(perm, 2) if a > b)
        product = " * ".join(f"({entry(c, perm[c])})" for c in range(dim))
        terms.append(("- " if inversions % 2 else "+ ") + product)
    return " ".join(terms).lstrip("+ ")


def g2p_name(dim, p, parallel=True):
    return f"g2p_{dim}d_p{p}" + ("" if parallel else "_serial")


def gathered_sums(dim, p):
    """Lines forming A_c = sum_k a_k N_kp, U_c = sum_k v_k N_kp and
    L_cd = sum_k v_k,c dN_k/dx_d of one particle (its weights computed)."""
    def along(weights, array, j, c):
        """Source of sum_a weights_a array[node a of row j, field c]."""
        nodes = [f"{w} * {st.entry(array, dim, j, a, c, 'KG')}" for a, w in enumerate(weights)]
        return "(" + " + ".join(nodes) + ")"

    rows = list(enumerate(st.stencil_rows(dim, p)))
    sums = [st.first_entry(dim, first="KG")]
    for j, row in rows:
        r, rc = st.row_products(row, p)
        if r != "1.0":
            sums.append(f"r = {r}")
            r = "r"
        for c, expr in enumerate(rc):
            sums.append(f"r{c + 1} = {expr}")

        w = [f"w0_{a}" for a in range(p + 1)]
        g = [f"g0_{a}" for a in range(p + 1)]
        for c in range(dim):
            sums.append(f"A{j}_{c} = {times(r, along(w, 'a_flat', j, c))}")
            sums.append(f"RU{c} = {along(w, 'v_flat', j, c)}")
            sums.append(f"U{j}_{c} = {times(r, f'RU{c}')}")
            sums.append(f"L{j}_{c}0 = {times(r, along(g, 'v_flat', j, c))}")
            for d in range(1, dim):
                sums.append(f"L{j}_{c}{d} = r{d} * RU{c}")
    for c in range(dim):
        sums.append(f"A{c} = " + " + ".join(f"A{j}_{c}" for j, _ in rows))
        sums.append(f"U{c} = " + " + ".join(f"U{j}_{c}" for j, _ in rows))
        for d in range(dim):
            sums.append(f"L{c}{d} = " + " + ".join(f"L{j}_{c}{d}" for j, _ in rows))
    return sums


def g2p_source(dim, p, parallel=True):
    """Source of the g2p kernel for (dim, p)."""
    name = g2p_name(dim, p, parallel)
    sums = gathered_sums(dim, p)
    move = []
    for c in range(dim):
        move += [f"xn{c} = x[ip, {c}] + dt * U{c}", f"x_new[ip, {c}] = xn{c}",
                 f"u_new[ip, {c}] = u[ip, {c}] + dt * U{c}"]
    fused = [f"D{c}{d} = dt * L{c}{c}" if c == d else f"D{c}{d} = 0.5 * dt * (L{c}{d} + L{d}{c})"
             for c in range(dim) for d in range(c, dim)]
    for c in range(dim):
        for d in range(dim):
            if c == d:  # (lambda + 2 mu) D_cc + lambda sum of the other D_dd
                terms = [f"lam2mu * D{c}{c}"] + [f"lam * D{e}{e}" for e in range(dim) if e != c]
            else:
                terms = [f"mu2 * D{min(c, d)}{max(c, d)}"]
            fused.append(f"stress_new[ip, {c}, {d}] = stress[ip, {c}, {d}] + " + " + ".join(terms))
    bounds = []
    for d in range(dim):
        bounds += [f"lo{d} = b{d}[0]", f"hi{d} = b{d}[-1]"]
    finite = " and ".join([f"np.isfinite(xn{c})" for c in range(dim)]
                          + [f"np.isfinite(vn{c})" for c in range(dim)])
    outside = " or ".join(f"xn{d} < lo{d} or xn{d} > hi{d}" for d in range(dim))
    body = G2P.format(
        parallel=parallel, name=name, dim=dim, p=p, strides=indent(st.stride_names(dim), 1),
        unpack_particles=unpack(ParticleArrays, "particles"), unpack_update=unpack(Update, "update"),
        unpack_new=unpack(ParticleArrays, "new", [f + "_new" for f in ParticleArrays._fields]),
        bounds=indent(bounds + st.row_starts(dim, p, dim), 1), weights=indent(st.axis_calls(dim, p, i="ip"), 3),
        base=st.base_index(dim), sums=indent(sums, 3),
        store_acc=indent([f"acc_out[ip, {c}] = A{c}" for c in range(dim)], 4),
        flip=indent([s for c in range(dim) for s in (
            f"vn{c} = v[ip, {c}] + vfactor * dt * A{c}", f"v_new[ip, {c}] = vn{c}")], 4),
        given=indent([f"vn{c} = v_new[ip, {c}]" for c in range(dim)], 4),
        move=indent(move, 3),
        det=determinant(dim, lambda c, d: f"1.0 + dt * L{c}{d}" if c == d else f"dt * L{c}{d}"),
        fused=indent(fused, 4),
        store_L=indent([f"L_out[ip, {c}, {d}] = L{c}{d}" for c in range(dim) for d in range(dim)],
                       4),
        finite=finite, outside=outside)
    return name, module_header() + body


@functools.cache
def g2p_kernel(dim, p, parallel=True):
    """The compiled g2p kernel of (dim, p)."""
    name, source = g2p_source(dim, p, parallel)
    return getattr(load(name, source), name)


RATES = '''
@njit(cache=True, parallel={parallel}, error_model="numpy", fastmath=FAST)
def {name}(particles, grid, grid_a, grid_v, lame, nt, x_rate, v_rate, L_out, stress_rate,
          V_rate):
    """Runge-Kutta stage rates, dim = {dim}, p = {p}: see skfem_mpm.kernels.gather."""
    {unpack_particles}
    a_flat = grid_a.reshape(grid_a.size)
    v_flat = grid_v.reshape(grid_v.size)
    fused, lam, mu = lame
    mu2 = 2.0 * mu
{strides}
{bounds}
    n = x.shape[0]
    for t in prange(nt):
        lo = t * n // nt
        hi = (t + 1) * n // nt
        for i in range(lo, hi):
            ip = np.uint64(i)
{weights}
            base = {base}
{sums}
{rates}
            V_rate[ip] = V[ip] * ({trace})
            if fused:
{fused}
            else:
{store_L}
'''


def rates_name(dim, p, parallel=True):
    return f"rates_{dim}d_p{p}" + ("" if parallel else "_serial")


def rates_source(dim, p, parallel=True):
    """Source of the stage-rates kernel for (dim, p)."""
    name = rates_name(dim, p, parallel)
    rates = []
    for c in range(dim):
        rates += [f"x_rate[ip, {c}] = U{c}", f"v_rate[ip, {c}] = A{c}"]
    trace = " + ".join(f"L{c}{c}" for c in range(dim))
    fused = [f"trD = {trace}"]
    for c in range(dim):
        for d in range(dim):
            if c == d:
                fused.append(f"stress_rate[ip, {c}, {d}] = mu2 * L{c}{c} + lam * trD")
            else:
                fused.append(f"stress_rate[ip, {c}, {d}] = mu2 * (0.5 * (L{c}{d} + L{d}{c}))")
    body = RATES.format(
        parallel=parallel, name=name, dim=dim, p=p, strides=indent(st.stride_names(dim), 1),
        unpack_particles=unpack(ParticleArrays, "particles"),
        bounds=indent(st.row_starts(dim, p, dim), 1),
        weights=indent(st.axis_calls(dim, p, i="ip"), 3), base=st.base_index(dim),
        sums=indent(gathered_sums(dim, p), 3), rates=indent(rates, 3), trace=trace,
        fused=indent(fused, 4),
        store_L=indent([f"L_out[ip, {c}, {d}] = L{c}{d}" for c in range(dim) for d in range(dim)],
                       4))
    return name, module_header() + body


@functools.cache
def rates_kernel(dim, p, parallel=True):
    """The compiled stage-rates kernel of (dim, p)."""
    name, source = rates_source(dim, p, parallel)
    return getattr(load(name, source), name)
