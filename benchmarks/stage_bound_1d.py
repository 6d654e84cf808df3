"""What a lean 1D rk4 step could cost (issue 18, S1 work-precision): a cost
bound, not the method.

S1 small (the vibrating string, p3, 2 particles per cell, consistent mass,
the 1D particle-knot spline, rk4, fixed ends) stepped by one compiled
function a step whose stages call the project's leaf kernels directly
(linked and inlined, arrays bound once): per stage the per-volume fields
[rho, rho v, sigma], the body's Gauss rule
(:func:`~skfem_mpm.kernels.gauss_rule.gauss_rule_1d_into`), the spline fit at
its points (:func:`~skfem_mpm.kernels.spline_1d.not_a_knot_spline_into`), one
pass over the points for the lumped mass, momentum, force and the consistent
mass band (basis: :func:`~skfem_mpm.kernels.stencil.closed_axis_functions`,
else :func:`~skfem_mpm.kernels.stencil.extracted_axis_functions`), the
banded Cholesky factor of the free rows
(:func:`~skfem_mpm.kernels.kronecker.banded_cholesky_into`) and its two
solves (a, v), the rates at the particles, and the combination
y_n + dt sum_s w_s k_s. Left out: the fast-dof guard (a pass over ~20
rows), tiny-mass merges, effects other than the fixed ends, every check
the loop makes (J, finiteness, inside the grid). The Gauss points' basis
goes through a table kept while the rule's points stay (``cached``): on S1
they move at every stage (the body's end particles move), so it is made
again each time. Two variants: the kernels as they are, and their copies
compiled without numba's runtime (no reference counts).

It prints the bound's CPU a step (one thread, by difference of a long and a
short run, medians), the compiled loop's for the same scene (the same
difference through ``simulate``), and the bound's final x and v against the
loop's (they differ by the solver's rounding and the guard, which lumps
nothing on S1 at the default cfl).

    NUMBA_NUM_THREADS=1 python benchmarks/stage_bound_1d.py --cells 16
"""
import argparse
import statistics
import time

import numpy as np
from numba import njit

from skfem_mpm.kernels.gauss_rule import gauss_points_most, gauss_rule_1d_into
from skfem_mpm.kernels.kronecker import banded_cholesky_into
from skfem_mpm.kernels.spline_1d import not_a_knot_spline_into, spline_work_size
from skfem_mpm.kernels.stencil import closed_axis_functions, extracted_axis_functions

P = 3


def compiled_steps(runtime=True):
    """run_steps of one variant: ``runtime`` False compiles the leaf
    kernels' copies (spline, banded Cholesky, extracted basis), the basis
    and the combination without numba's runtime (no reference counts:
    they allocate nothing); the stage and the step loop keep it (the Gauss
    rule may allocate, in its fall-back sort). Copies are not cached (they
    would share the kernels' cache entries)."""
    if runtime:
        jit = leaf = njit
        spline, cholesky, extracted = (not_a_knot_spline_into, banded_cholesky_into,
                                       extracted_axis_functions)
    else:
        jit = njit
        leaf = njit(_nrt=False, error_model="numpy")
        spline, cholesky, extracted = (njit(_nrt=False, error_model="numpy")(f.py_func) for f in
                                       (not_a_knot_spline_into, banded_cholesky_into,
                                        extracted_axis_functions))

    @leaf
    def _basis(x, first, ncells, inv_h, breaks, C):
        ok, e, w0, w1, w2, w3, g0, g1, g2, g3 = closed_axis_functions(x, first, ncells, True,
                                                                      inv_h, P)
        if not ok:
            e, w0, w1, w2, w3, g0, g1, g2, g3 = extracted(x, breaks, True, inv_h,
                                                                         C, P)
        return e, w0, w1, w2, w3, g0, g1, g2, g3


    @jit
    def _stage(x, v, m, V, stress, E, breaks, C, gap, ref, wref, rule, values, space, fit, table,
               cached, grid, L, out):
        """One stage's rates of the particles (x, v, m, V, stress) into ``out``
        (rows: dx/dt, dv/dt, dsigma/dt, dV/dt)."""
        order, starts, lows, highs, first, points, xg, wg, cell = rule
        n = x.shape[0]
        ncells = breaks.shape[0] - 1
        inv_h = ncells / (breaks[-1] - breaks[0])
        x0 = breaks[0]
        for i in range(n):
            rho = m[i] / V[i]
            values[i, 0] = rho
            values[i, 1] = rho * v[i]
            values[i, 2] = stress[i]
        npieces, ng = gauss_rule_1d_into(x, V, gap, breaks, ref, wref, order, starts, lows, highs,
                                         first, points, xg, wg, cell)
        spline(x, values, order, starts[:npieces + 1], points[:npieces + 1], xg,
                               fit, space)
        te, tw, tg, tx = table
        if cached[0] != ng or tx[ng - 1] != xg[ng - 1] or tx[0] != xg[0]:
            for g in range(ng):
                e, w0, w1, w2, w3, g0, g1, g2, g3 = _basis(xg[g], x0, ncells, inv_h, breaks, C)
                te[g] = e
                tw[g, 0], tw[g, 1], tw[g, 2], tw[g, 3] = w0, w1, w2, w3
                tg[g, 0], tg[g, 1], tg[g, 2], tg[g, 3] = g0, g1, g2, g3
                tx[g] = xg[g]
            cached[0] = ng if cached[1] else -1
        M, mom, force, a, vg = grid
        nd = M.shape[0]
        M[:] = 0.0
        mom[:] = 0.0
        force[:] = 0.0
        for g in range(ng):
            e = te[g]
            mg = wg[g] * fit[g, 0]
            pg = wg[g] * fit[g, 1]
            sg = wg[g] * fit[g, 2]
            for r in range(P + 1):
                wr = tw[g, r]
                mom[e + r] += pg * wr
                force[e + r] -= sg * tg[g, r]
                mw = mg * wr
                for s in range(r, P + 1):
                    M[e + r, s - r] += mw * tw[g, s]
        nf = nd - 2  # the fixed ends' rows out: the free rows' lower band
        for i in range(nf):
            for d in range(P + 1):
                L[i, d] = M[1 + i - d, d] if i >= d else 0.0
        cholesky(L, 0, nf, L)
        a[0] = a[nd - 1] = vg[0] = vg[nd - 1] = 0.0
        for i in range(nf):
            sa = force[1 + i]
            sv = mom[1 + i]
            for d in range(1, min(P, i) + 1):
                sa -= L[i, d] * a[1 + i - d]
                sv -= L[i, d] * vg[1 + i - d]
            a[1 + i] = sa / L[i, 0]
            vg[1 + i] = sv / L[i, 0]
        for i in range(nf - 1, -1, -1):
            sa = a[1 + i]
            sv = vg[1 + i]
            for d in range(1, min(P, nf - 1 - i) + 1):
                sa -= L[i + d, d] * a[1 + i + d]
                sv -= L[i + d, d] * vg[1 + i + d]
            a[1 + i] = sa / L[i, 0]
            vg[1 + i] = sv / L[i, 0]
        for i in range(n):
            e, w0, w1, w2, w3, g0, g1, g2, g3 = _basis(x[i], x0, ncells, inv_h, breaks, C)
            out[1, i] = w0 * a[e] + w1 * a[e + 1] + w2 * a[e + 2] + w3 * a[e + 3]
            out[0, i] = w0 * vg[e] + w1 * vg[e + 1] + w2 * vg[e + 2] + w3 * vg[e + 3]
            dvdx = g0 * vg[e] + g1 * vg[e + 1] + g2 * vg[e + 2] + g3 * vg[e + 3]
            out[2, i] = E * dvdx
            out[3, i] = V[i] * dvdx


    @leaf
    def _combine(c, y, rates, out):
        """out = y + sum_s c_s k_s (rows x, v, sigma, V)."""
        for f in range(4):
            for i in range(y.shape[1]):
                t = y[f, i]
                for s in range(4):
                    if c[s] != 0.0:
                        t += c[s] * rates[s, f, i]
                out[f, i] = t


    @jit
    def run_steps(nsteps, dt, y, m, E, breaks, C, gap, ref, wref, rule, values, space, fit, table,
                  cached, grid, L, rates, ys):
        """``nsteps`` classical rk4 steps of the state y (rows x, v, sigma, V)."""
        c = np.zeros(4)
        stage_w = ((0.0, 0.0, 0.0, 0.0), (0.5, 0.0, 0.0, 0.0), (0.0, 0.5, 0.0, 0.0),
                   (0.0, 0.0, 1.0, 0.0))
        for _ in range(nsteps):
            for st in range(4):
                z = y
                if st > 0:
                    for s in range(4):
                        c[s] = stage_w[st][s] * dt
                    _combine(c, y, rates, ys)
                    z = ys
                _stage(z[0], z[1], m, z[3], z[2], E, breaks, C, gap, ref, wref, rule, values, space,
                       fit, table, cached, grid, L, rates[st])
            c[0], c[1], c[2], c[3] = dt / 6.0, dt / 3.0, dt / 3.0, dt / 6.0
            _combine(c, y, rates, ys)
            y[:] = ys

    return run_steps


def _bound(scene, dt, run_steps, cached=False):
    """(run(nsteps) -> final y, the arrays) of the bound for ``scene``."""
    p = scene.particles()
    n = p.n
    body = scene.bodies[0]
    E = float(body.material.E)
    breaks = np.ascontiguousarray(scene.grid.breakpoints[0])
    C = np.ascontiguousarray(scene.grid.extraction[0])
    ncells = breaks.size - 1
    ref, wref = np.polynomial.legendre.leggauss(P + 1)
    ref, wref = 0.5 * (ref + 1.0), 0.5 * wref
    most = gauss_points_most(n, ncells, P + 1)
    rule = (np.empty(n, np.int64), np.empty(n + 1, np.int64), np.empty(n), np.empty(n),
            np.empty(n, np.int64), np.empty(n + 1, np.int64), np.empty(most), np.empty(most),
            np.empty(most, np.int64))
    table = (np.zeros(most, np.int64), np.zeros((most, P + 1)), np.zeros((most, P + 1)),
             np.full(most, np.nan))
    nd = ncells + P
    grid = (np.zeros((nd, P + 1)), np.zeros(nd), np.zeros(nd), np.zeros(nd), np.zeros(nd))
    fixed = (np.zeros(n), np.zeros(n), np.zeros((n, 3)), np.zeros(spline_work_size(n, 3)),
             np.zeros((most, 3)), np.zeros((nd, P + 1)), np.zeros((4, 4, n)), np.zeros((4, n)))
    values, space, fit, L, rates, ys = fixed[2:]
    y0 = np.stack([p.x[:, 0], p.v[:, 0], p.stress[:, 0, 0], p.V]).copy()

    def run(nsteps):
        y = y0.copy()
        state = np.array([-1, int(cached)])
        run_steps(nsteps, dt, y, p.m, E, breaks, C, float(breaks[1] - breaks[0]), ref, wref,
                  rule, values, space, fit, table, state, grid, L, rates, ys)
        return y
    return run


def _per_step(run, n1, n2, repeats):
    """Median CPU seconds a step by difference of ``n2`` and ``n1`` steps."""
    out = []
    for _ in range(repeats):
        c0 = time.process_time()
        run(n1)
        c1 = time.process_time()
        run(n2)
        c2 = time.process_time()
        out.append(((c2 - c1) - (c1 - c0)) / (n2 - n1))
    return statistics.median(out), min(out), max(out)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=5)
    a = ap.parse_args()
    from skfem_mpm.benchmarks import get_benchmark
    from skfem_mpm.solve import Method, prepare, simulate

    bench = get_benchmark("vibrating-string", "small")
    method = Method(scheme="rk4", mass="consistent", reconstruction="spline")
    scene = bench.scene(a.cells, P, 2)
    dt = prepare(scene, method).dt
    steps = int(round(scene.t_end / dt))
    for runtime in (True, False):
        run = _bound(scene, dt, compiled_steps(runtime))
        run(2)
        med, lo, hi = _per_step(run, 200, 2200, a.repeats)
        print(f"bound, {'reference counts' if runtime else 'leaf kernels without numba runtime'}: "
              f"{1e6 * med:.2f} us a step ({1e6 * lo:.2f}-{1e6 * hi:.2f})")
    y = _bound(scene, dt, compiled_steps(False))(steps)

    def loop(nsteps):
        return simulate(bench.scene(a.cells, P, 2, t_end=nsteps * dt), method)
    loop(2)
    med, lo, hi = _per_step(lambda k: loop(k), 20, 220, a.repeats)
    print(f"compiled loop: {1e6 * med:.2f} us a step ({1e6 * lo:.2f}-{1e6 * hi:.2f})")
    r = simulate(bench.scene(a.cells, P, 2), method)
    print(f"after {steps} steps, bound - loop: max |dx| {np.abs(y[0] - r.particles.x[:, 0]).max():.2e}"
          f", max |dv| {np.abs(y[1] - r.particles.v[:, 0]).max():.2e} (|v| max "
          f"{np.abs(r.particles.v).max():.2e})")


if __name__ == "__main__":
    main()
