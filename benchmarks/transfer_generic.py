"""Per-dimension hand-written against generated particle-grid kernels.

(The hand-written kernels are gone from the package; on a checkout that
still has them the old/new pairs are timed, otherwise the generated
kernels alone, and ``--small`` pairs the executor's binding
``kernels.mpm.Kernels`` with ``kernels.transfer.Transfers``.)

Times the transfer kernels of ``skfem_mpm.kernels.mpm`` (``p2g_1d/2d``,
``g2p2g_1d/2d``, ``g2p_1d/2d``, and the p2g reduction) and the kernels
generated per dimension and degree from one source
(``skfem_mpm.kernels.scatter`` / ``gather``) on the same inputs: the
particles of ``skfem-mpm bench`` (2D: 128^2 cells, 4 x 4 particles per cell
in the middle half, 65,536 particles; 1D: 250,000 cells, 4 per cell, 1e6
particles) with random velocities and stresses, at degree p = 1, 2, 3.
Old and new calls alternate, their order swapped every round; each figure
is the median over the rounds of ns per particle, with the range; the ratio
is the median of the per-round ratios new / old. 3D (the bench problem of
the 3D issue: 64^3 cells, 2 x 2 x 2 particles per cell in [0.25, 0.75]^3,
262,144 particles) has the new kernels only. ``--small`` also times whole
calls (the Python wrappers) on small problems (1D 32 cells x 4, 2D 16^2 x
2 x 2), in microseconds per call.

g2p is timed as in USL with linear elasticity fused (FLIP update, stress
and volume written), and with L stored instead (``g2p L``).

    python benchmarks/transfer_generic.py [--dims 1 2 3] [--degrees 1 2 3]
        [--rounds 30] [--window] [--small] [--json]

Run it with NUMBA_NUM_THREADS=1 for the kernels' own cost; with two
threads on a shared machine the figures follow the other processes' load.
"""
import argparse
import json
import time
from types import SimpleNamespace

import numpy as np

from skfem_mpm import SplineGrid
from skfem_mpm.bench import scene_1d, scene_2d
from skfem_mpm.kernels import mpm

try:
    from skfem_mpm.kernels.gather import g2p_kernel
    from skfem_mpm.kernels.records import grid_record, particle_record
    from skfem_mpm.kernels.scatter import g2p2g_kernel, p2g_kernel, reduce_fields
    from skfem_mpm.kernels.transfer import Transfers
    HAVE_NEW = True
except ImportError:  # before the generated kernels exist
    HAVE_NEW = False


def line_grid(breaks, degree):
    """A tensor grid description of any dimension from 1D spline lines
    (what the kernels read of a SplineGrid)."""
    lines = [SplineGrid(np.asarray(b, dtype=float), degree) for b in breaks]
    nb = tuple(g.basis_per_axis[0] for g in lines)
    return SimpleNamespace(dim=len(lines), degree=degree, ndofs=int(np.prod(nb)),
                           basis_per_axis=nb, breakpoints=tuple(g.breakpoints[0] for g in lines),
                           _uniform=tuple(g._uniform[0] for g in lines),
                           extraction=tuple(g.extraction[0] for g in lines),
                           bounds=tuple(g.bounds[0] for g in lines))


def scene_3d(cells=64, ppc=2, degree=2):
    """Grid and particles of the 3D bench problem (x-major order, as
    Particles.seed orders them)."""
    grid = line_grid([np.linspace(0.0, 1.0, cells + 1)] * 3, degree)
    h = 1.0 / cells
    lo = round(0.25 / h)
    hi = round(0.75 / h)
    axis = ((np.arange(lo, hi)[:, None] + (np.arange(ppc)[None, :] + 0.5) / ppc) * h).ravel()
    X = np.meshgrid(axis, axis, axis, indexing="ij")
    x = np.stack([a.ravel() for a in X], axis=1)
    n = x.shape[0]
    V = np.full(n, (h / ppc) ** 3)
    return grid, SimpleNamespace(n=n, dim=3, x=x, v=np.zeros((n, 3)), u=np.zeros((n, 3)),
                                 m=V.copy(), V=V, stress=np.zeros((n, 3, 3)))


def randomise(p, rng):
    p.v[:] = rng.standard_normal(p.v.shape)
    p.stress[:] = rng.standard_normal(p.stress.shape)


def new_state(p):
    return SimpleNamespace(x=np.empty_like(p.x), v=np.empty_like(p.v), u=np.empty_like(p.u),
                           m=p.m, V=np.empty_like(p.V), stress=np.empty_like(p.stress))


def old_calls(grid, p, ga, gv, dt, lame):
    """The old kernels' calls (as skfem_mpm.kernels.mpm.Kernels made them);
    none once the generated kernels replaced them."""
    if not hasattr(mpm, "p2g_1d"):
        return {}
    k = mpm.Kernels(grid)
    dim, deg = grid.dim, grid.degree
    no_force = np.zeros((1, dim))
    copies, touched = k._buffer(1 + 2 * dim)
    copies2, touched2 = k._buffer(dim)
    new = new_state(p)
    vnew = np.empty_like(p.v)
    L = np.empty((p.n, dim, dim))
    flags = k.flags
    acc = k._no_acc
    out = (np.empty(grid.ndofs), np.empty((grid.ndofs, dim)), np.empty((grid.ndofs, dim)))
    mass_range = np.zeros((k.nthreads, 2))
    if dim == 1:
        (bx, ux, ihx, Cx), = k.args
        lo_x, hi_x = grid.bounds[0]
        E = lame[0]
        calls = {
            "p2g": lambda: mpm.p2g_1d(p.x, p.v, p.m, p.V, p.stress, no_force, False, bx, ux,
                                      ihx, Cx, deg, copies, touched),
            "g2p2g": lambda: mpm.g2p2g_1d(p.x, p.v, p.m, ga, dt, bx, ux, ihx, Cx, deg, vnew,
                                          copies2, touched2),
            "g2p": lambda: mpm.g2p_1d(p.x, p.v, p.u, p.stress, p.V, ga, gv, dt, 1.0, True, bx,
                                      ux, ihx, Cx, deg, lo_x, hi_x, True, E, new.x, new.v,
                                      new.u, new.stress, new.V, L, acc, False, flags),
            "g2p L": lambda: mpm.g2p_1d(p.x, p.v, p.u, p.stress, p.V, ga, gv, dt, 1.0, True, bx,
                                        ux, ihx, Cx, deg, lo_x, hi_x, False, E, new.x, new.v,
                                        new.u, new.stress, new.V, L, acc, False, flags),
        }
    else:
        (bx, ux, ihx, Cx), (by, uy, ihy, Cy) = k.args
        (lo_x, hi_x), (lo_y, hi_y) = grid.bounds
        lam, mu = lame
        nbx = k.nbx
        calls = {
            "p2g": lambda: mpm.p2g_2d(p.x, p.v, p.m, p.V, p.stress, no_force, False, bx, by, ux,
                                      uy, ihx, ihy, Cx, Cy, deg, nbx, copies, touched),
            "g2p2g": lambda: mpm.g2p2g_2d(p.x, p.v, p.m, ga, dt, bx, by, ux, uy, ihx, ihy, Cx,
                                          Cy, deg, nbx, vnew, copies2, touched2),
            "g2p": lambda: mpm.g2p_2d(p.x, p.v, p.u, p.stress, p.V, ga, gv, dt, 1.0, True, bx,
                                      by, ux, uy, ihx, ihy, Cx, Cy, deg, nbx, lo_x, hi_x, lo_y,
                                      hi_y, True, lam, mu, new.x, new.v, new.u, new.stress,
                                      new.V, L, acc, False, flags),
            "g2p L": lambda: mpm.g2p_2d(p.x, p.v, p.u, p.stress, p.V, ga, gv, dt, 1.0, True, bx,
                                        by, ux, uy, ihx, ihy, Cx, Cy, deg, nbx, lo_x, hi_x, lo_y,
                                        hi_y, False, lam, mu, new.x, new.v, new.u, new.stress,
                                        new.V, L, acc, False, flags),
        }
    calls["reduce"] = lambda: mpm._reduce_fields(copies, touched, *out, mass_range)
    return calls


def new_calls(grid, p, ga, gv, dt, lame, window=None):
    """The generated kernels' calls on the same inputs."""
    t = Transfers(grid, window=window)
    dim, deg = grid.dim, grid.degree
    record = grid_record(grid)
    parts = particle_record(p)
    no_force = np.zeros((1, dim))
    copies, touched = t.copies(1 + 2 * dim)
    copies2, touched2 = t.copies(dim)
    new = particle_record(new_state(p))
    vnew = np.empty_like(p.v)
    L = np.empty((p.n, dim, dim))
    acc = np.zeros((1, dim))
    out = (np.empty(grid.ndofs), np.empty((grid.ndofs, dim)), np.empty((grid.ndofs, dim)))
    everywhere = np.array([0, grid.ndofs, 0, grid.ndofs])  # every node written, as before
    p2g = p2g_kernel(dim, deg, window)
    g2p2g = g2p2g_kernel(dim, deg, window)
    g2p = g2p_kernel(dim, deg)
    fused = (dt, 1.0, True, True, float(lame[0]), float(lame[1]), False)  # records.Update
    stored = (dt, 1.0, True, False, 0.0, 0.0, False)
    return {
        "p2g": lambda: p2g(parts, record, no_force, False, copies, touched),
        "g2p2g": lambda: g2p2g(parts, record, ga, dt, vnew, copies2, touched2),
        "g2p": lambda: g2p(parts, record, ga, gv, fused, new, L, acc, t.flags),
        "g2p L": lambda: g2p(parts, record, ga, gv, stored, new, L, acc, t.flags),
        "reduce": lambda: reduce_fields(copies, touched, *out, t.mass_range, everywhere),
    }


def inputs(grid, p, dt, seed=0):
    rng = np.random.default_rng(seed)
    randomise(p, rng)
    ga = rng.standard_normal((grid.ndofs, grid.dim))
    gv = 0.1 * rng.standard_normal((grid.ndofs, grid.dim))
    lame = (1e4, 0.0) if grid.dim == 1 else (5769.2307692307695, 3846.153846153846)
    return ga, gv, lame


def paired(a, b, rounds):
    """Alternating timings of a() and b() (order swapped every round)."""
    ta, tb = [], []
    a()
    b()  # compile / first touch
    for r in range(rounds):
        for fn, out in (((a, ta), (b, tb)) if r % 2 == 0 else ((b, tb), (a, ta))):
            t0 = time.perf_counter()
            fn()
            out.append(time.perf_counter() - t0)
    return np.array(ta), np.array(tb)


def alone(a, rounds):
    a()
    times = []
    for _ in range(rounds):
        t0 = time.perf_counter()
        a()
        times.append(time.perf_counter() - t0)
    return np.array(times)


def summary(times, n):
    ns = times / n * 1e9
    return {"median": float(np.median(ns)), "min": float(ns.min()), "max": float(ns.max())}


def problem(dim, degree):
    if dim == 1:
        scene, dt = scene_1d(degree=degree)
    else:
        scene, dt = scene_2d(degree=degree)
    return scene.grid, scene.bodies[0].particles, dt


def compare(dim, degree, rounds, window=None):
    grid, p, dt = problem(dim, degree)
    ga, gv, lame = inputs(grid, p, dt)
    old = old_calls(grid, p, ga, gv, dt, lame)
    new = new_calls(grid, p, ga, gv, dt, lame, window) if HAVE_NEW else {}
    rows = []
    if not old:  # the generated kernels alone
        return [{"dim": dim, "p": degree, "kernel": kernel, "particles": p.n,
                 "new": summary(alone(call, rounds), p.n)} for kernel, call in new.items()]
    for kernel, call in old.items():
        if kernel in new:
            to, tn = paired(call, new[kernel], rounds)
            ratio = tn / to
            rows.append({"dim": dim, "p": degree, "kernel": kernel, "particles": p.n,
                         "old": summary(to, p.n), "new": summary(tn, p.n),
                         "ratio": float(np.median(ratio)),
                         "ratio_range": [float(np.percentile(ratio, 10)),
                                         float(np.percentile(ratio, 90))]})
        else:
            rows.append({"dim": dim, "p": degree, "kernel": kernel, "particles": p.n,
                         "old": summary(alone(call, rounds), p.n)})
    return rows


def compare_windows(dim, degree, rounds):
    """The generated scatter kernels with and without the run window."""
    grid, p, dt = problem(dim, degree) if dim < 3 else (*scene_3d(degree=degree), 1e-5)
    ga, gv, lame = inputs(grid, p, dt)
    plain = new_calls(grid, p, ga, gv, dt, lame, window=False)
    windowed = new_calls(grid, p, ga, gv, dt, lame, window=True)
    rows = []
    for kernel in ("p2g", "g2p2g"):
        tp, tw = paired(plain[kernel], windowed[kernel], rounds)
        rows.append({"dim": dim, "p": degree, "kernel": kernel + " window",
                     "particles": p.n, "old": summary(tp, p.n), "new": summary(tw, p.n),
                     "ratio": float(np.median(tw / tp)),
                     "ratio_range": [float(np.percentile(tw / tp, 10)),
                                     float(np.percentile(tw / tp, 90))]})
    return rows


def three_d(degree, rounds):
    grid, p = scene_3d(degree=degree)
    ga, gv, lame = inputs(grid, p, 1e-5)
    new = new_calls(grid, p, ga, gv, 1e-5, lame)
    return [{"dim": 3, "p": degree, "kernel": kernel, "particles": p.n,
             "new": summary(alone(call, rounds), p.n)} for kernel, call in new.items()]


def small_pairs(dim, cells, ppc):
    """(particles, {kernel: (old call, new call)}) of a small problem."""
    from skfem_mpm import LinearElastic

    scene, dt = (scene_1d if dim == 1 else scene_2d)(cells=cells, ppc=ppc)
    grid, p = scene.grid, scene.bodies[0].particles
    ga, gv, lame = inputs(grid, p, dt)
    old, new = mpm.Kernels(grid), Transfers(grid)
    a, b = new_state(p), new_state(p)
    L = np.empty((p.n, dim, dim))
    material = LinearElastic(1e4, 0.0 if dim == 1 else 0.3)
    vnew = np.empty_like(p.v)
    return p, {
        "p2g": (lambda: old.p2g(p, None), lambda: new.p2g(p, None)),
        "g2p2g": (lambda: old.g2p2g(p, ga, dt, vnew), lambda: new.g2p2g(p, ga, dt, vnew)),
        "g2p": (lambda: old.g2p(p, ga, gv, dt, 1.0, True, True, material, a, L),
                lambda: new.g2p(p, ga, gv, dt, 1.0, True, b, L, lame=lame)),
    }


def small_calls(rounds):
    """Microseconds per wrapper call (dispatch included) on small problems."""
    rows = []
    for dim, cells, ppc in ((1, 32, 4), (2, 16, 2)):
        p, pairs = small_pairs(dim, cells, ppc)
        for kernel, (fa, fb) in pairs.items():
            to, tn = paired(fa, fb, rounds)
            rows.append({"dim": dim, "kernel": kernel, "particles": p.n,
                         "old_us": float(np.median(to) * 1e6),
                         "new_us": float(np.median(tn) * 1e6)})
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dims", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--degrees", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--rounds", type=int, default=30)
    parser.add_argument("--window", action="store_true",
                        help="also time the scatter kernels with and without the run window")
    parser.add_argument("--small", action="store_true", help="also time small-problem calls")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    rows = []
    for dim in args.dims:
        for degree in args.degrees:
            if dim < 3:
                rows += compare(dim, degree, args.rounds)
            elif HAVE_NEW:
                rows += three_d(degree, args.rounds)
            if args.window and HAVE_NEW:
                rows += compare_windows(dim, degree, args.rounds)
    small = small_calls(args.rounds * 10) if args.small and HAVE_NEW else []
    if args.json:
        print(json.dumps({"rows": rows, "small": small}, indent=2))
        return
    from numba import get_num_threads
    print(f"threads {get_num_threads()}, {args.rounds} rounds; ns per particle: median [min, max]"
          "; new/old: median of the per-round ratios [10th, 90th percentile]")
    for r in rows:
        line = f"{r['dim']}D p={r['p']} {r['kernel']:14s} {r['particles']:>8d}"
        for key in ("old", "new"):
            if key in r:
                s = r[key]
                line += f"  {key} {s['median']:7.2f} [{s['min']:7.2f}, {s['max']:7.2f}]"
        if "ratio" in r:
            line += f"  new/old {r['ratio']:.3f} [{r['ratio_range'][0]:.3f}, {r['ratio_range'][1]:.3f}]"
        print(line)
    for r in small:
        print(f"small {r['dim']}D {r['kernel']:6s} {r['particles']:>5d} particles: "
              f"old {r['old_us']:.1f} us, new {r['new_us']:.1f} us per call")


if __name__ == "__main__":
    main()
