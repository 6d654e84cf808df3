"""Pictures of studies and runs (matplotlib, written to PNG files).

Studies: :func:`plot_convergence` (error against cell size with reference
slopes) and :func:`plot_work_precision` (error against wall time).
Runs: :func:`plot_particles` (particles coloured by a field over the grid),
:func:`plot_field_snapshots` (a field at a few times; 1D: over position),
:func:`plot_energy` (energy history), :func:`plot_displacement_history`
(displacement of chosen particles against the exact solution).
"""
import math

import numpy as np

__all__ = [
    "cheapest_envelope",
    "plot_convergence",
    "plot_displacement_history",
    "plot_energy",
    "plot_field_snapshots",
    "plot_particles",
    "plot_work_precision",
]


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt

def _save(plt, fig, path):
    """Lay out, write the PNG and release the figure."""
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)



def _series(records, x_key):
    groups = {}
    for r in records:
        if r.get("status", "ok") != "ok" or not r.get("error"):
            continue
        groups.setdefault(r["method"], []).append((r[x_key], r["error"]))
    return {k: sorted(v) for k, v in groups.items()}


def _error_label(records):
    measure = next((r.get("error_measure") for r in records if r.get("error_measure")),
                   "error_rms")
    if measure == "error_max":
        return "max over time of RMS displacement error / amplitude (-)"
    return "RMS displacement error at t_end / amplitude (-)"


def _style(method):
    fem = method.startswith("fem")
    return {"linestyle": "--" if fem else "-", "marker": "s" if fem else "o"}


def _reference_slopes(series):
    """[(order, h pair, error pair, method)]: one reference line per observed order
    (the last two runs' order of each method, rounded to 1-4; flat methods,
    order < 0.5, get none), along the method with that order whose finest
    run has the smallest error, a factor 2 below its last two points, so
    that it runs beside the data without covering it."""
    best = {}
    for method, pts in series.items():
        if len(pts) < 2:
            continue
        (h0, e0), (h1, e1) = pts[0], pts[1]  # the two finest runs (sorted by h)
        if h0 == h1 or e0 <= 0 or e1 <= 0:
            continue
        observed = math.log(e1 / e0) / math.log(h1 / h0)
        if observed < 0.5:
            continue
        order = min(4, max(1, round(observed)))
        if order not in best or e0 < best[order][2][0]:
            best[order] = (order, (h0, h1), (0.5 * e0, 0.5 * e0 * (h1 / h0) ** order), method)
    return [best[k] for k in sorted(best)]


def plot_convergence(records, path, title=""):
    """Relative error against cell size h, with reference slopes h^p drawn a
    factor 2 below the two finest runs of a method observed at order p (each
    labelled beside its own line, below it, in that method's colour)."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 5))
    series = _series(records, "h")
    colours = {}
    for method, pts in series.items():
        h, e = zip(*pts)
        colours[method] = ax.loglog(h, e, label=method, **_style(method))[0].get_color()
    for order, hs, es, method in _reference_slopes(series):
        ax.loglog(hs, es, color=colours[method], linewidth=1.2, linestyle=":")
        ax.annotate(f"h^{order}", (math.sqrt(hs[0] * hs[1]), math.sqrt(es[0] * es[1])),
                    xytext=(4, -12), textcoords="offset points", color=colours[method],
                    fontsize=8)
    ax.set_xlabel("cell size h (length units of the benchmark)")
    ax.set_ylabel(_error_label(records))
    ax.set_title(f"Convergence: {title}")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    _save(plt, fig, path)
    return path


def _keep_inside(fig, ax, labels):
    """Move a label drawn to the left of its point (``ha="right"``) to its
    right when its left end would leave the axes (a point near the left
    edge: the label ran over the tick labels), after the final layout."""
    ax.get_xlim(), ax.get_ylim()  # the data limits, final before measuring
    fig.tight_layout()
    renderer = fig.canvas.get_renderer()
    left = ax.get_window_extent(renderer).x0
    for label in labels:
        if label.get_window_extent(renderer).x0 < left:
            label.set_horizontalalignment("left")
            label.xyann = (6, 0)


def cheapest_envelope(records, levels=200):
    """The lower-left envelope of the work-precision picture: at ``levels``
    error levels e (log-spaced over the study's errors), the cheapest method
    and its time to reach e (:func:`skfem_mpm.study.time_to_reach`: the
    log-log interpolation between a method's runs, a method's coarsest run
    for every e above its error). Returns [(e, time, method)]."""
    from .study import time_to_reach

    errors = [r["error"] for r in records if r.get("status", "ok") == "ok" and r.get("error")]
    if not errors:
        return []
    out = []
    for e in np.geomspace(min(errors), max(errors), levels):
        reach = {m: t for m, t in time_to_reach(records, float(e)).items() if t is not None}
        if reach:
            best = min(reach, key=reach.get)
            out.append((float(e), reach[best], best))
    return out


def plot_work_precision(records, path, title=""):
    """Error against wall time (median of the repeats, compilation
    excluded), with the lower-left envelope drawn under the curves: a wide
    band in the colour of the cheapest method at each error level, and the
    name of the cheapest method at each decade of error it spans."""
    from .study import REACH_TARGETS

    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 5.5))
    colours = {}
    for method, pts in _series(records, "wall_time_s").items():
        t, e = zip(*pts)
        line, = ax.loglog(t, e, label=method, **_style(method))
        colours[method] = line.get_color()
    envelope = cheapest_envelope(records)
    # the band: one segment per run of levels with the same cheapest method
    start = 0
    for k in range(1, len(envelope) + 1):
        if k == len(envelope) or envelope[k][2] != envelope[start][2]:
            seg = envelope[start:min(k + 1, len(envelope))]
            ax.loglog([s[1] for s in seg], [s[0] for s in seg], color=colours[seg[0][2]],
                      linewidth=9, alpha=0.25, solid_capstyle="butt", zorder=0)
            start = k
    if envelope:
        ax.plot([], [], color="0.5", linewidth=9, alpha=0.3,
                label="cheapest method per error (envelope)")
        lo, hi = envelope[0][0], envelope[-1][0]
        labels = []
        for e in REACH_TARGETS:
            if not lo <= e <= hi:
                continue
            level, t, method = min(envelope, key=lambda s: abs(math.log(s[0] / e)))
            labels.append(ax.annotate(
                f"{e:.0e}: {method}", (t, level), xytext=(-6, 0), textcoords="offset points",
                ha="right", va="center", fontsize=7, color=colours[method],
                bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none",
                      "alpha": 0.75}))
            ax.plot([t], [level], marker="|", color=colours[method], markersize=10)
    ax.set_xlabel("wall time of the run [s] (median of repeats, compilation excluded)")
    ax.set_ylabel(_error_label(records))
    ax.set_title(f"Work-precision: {title}")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    if envelope:
        _keep_inside(fig, ax, labels)
    _save(plt, fig, path)
    return path


def _field_values(result, field, save, exact=None):
    h = result.history
    if field == "stress":
        s = h["stress"][save]
        if s.shape[1] == 3:  # von Mises
            d = np.diagonal(s, axis1=1, axis2=2)
            return np.sqrt(0.5 * ((d[:, 0] - d[:, 1]) ** 2 + (d[:, 1] - d[:, 2]) ** 2
                                  + (d[:, 2] - d[:, 0]) ** 2)
                           + 3 * (s[:, 0, 1] ** 2 + s[:, 1, 2] ** 2 + s[:, 0, 2] ** 2))
        return s[:, 0, 0] if s.shape[1] == 1 else np.sqrt(
            s[:, 0, 0] ** 2 - s[:, 0, 0] * s[:, 1, 1] + s[:, 1, 1] ** 2 + 3 * s[:, 0, 1] ** 2)
    if field in ("velocity", "displacement"):
        a = h["v" if field == "velocity" else "u"][save]
        return np.linalg.norm(a, axis=1)
    if field == "error":
        if exact is None:
            raise ValueError("field='error' needs exact(X, t)")
        du = h["u"][save] - exact(h["X"][save], result.times[save])
        return np.linalg.norm(du, axis=1)
    raise ValueError(f"field must be 'stress', 'velocity', 'displacement' or 'error', "
                     f"got {field!r}")


def plot_particles(result, path, field="stress", save=-1, exact=None, title=""):
    """Particles coloured by a field (stress: von Mises in 2D and 3D, sigma_xx
    in 1D; velocity or displacement magnitude; displacement error) over the
    grid. In 3D the picture is the slice through the middle of the grid
    normal to z: the particles within a quarter cell of the layer nearest
    the middle plane, over the grid's x-y lines."""
    plt = _pyplot()
    values = _field_values(result, field, save, exact)
    x = result.history["x"][save]
    grid = result.grid
    fig, ax = plt.subplots(figsize=(7, 3 if x.shape[1] == 1 else 5))
    note = ""
    if x.shape[1] == 3:
        middle = 0.5 * sum(grid.bounds[2])
        layer = x[np.argmin(np.abs(x[:, 2] - middle)), 2]
        keep = np.abs(x[:, 2] - layer) < 0.25 * grid.h[2]
        x, values = x[keep], values[keep]
        note = f", slice z = {layer:.3g}"
        for axis, other in ((0, 1), (1, 0)):
            lo, hi = grid.bounds[other]
            for b in grid.breakpoints[axis]:
                ends = np.array([[b, b], [lo, hi]])
                ax.plot(*(ends if axis == 0 else ends[::-1]), color="0.85", linewidth=0.4)
        sc = ax.scatter(x[:, 0], x[:, 1], c=values, s=8, cmap="viridis")
        fig.colorbar(sc, ax=ax, label=field)
        ax.set_aspect("equal")
        ax.set_xlabel("x")
        ax.set_ylabel("y")
    elif x.shape[1] == 1:
        ax.plot(x[:, 0], values, ".", markersize=3)
        for b in grid.mesh.p[0]:
            ax.axvline(b, color="0.85", linewidth=0.5)
        ax.set_xlabel("x")
        ax.set_ylabel(field)
    else:
        m = grid.mesh
        for t in m.t.T:
            pts = m.p[:, np.append(t, t[0])]
            ax.plot(pts[0], pts[1], color="0.85", linewidth=0.4)
        sc = ax.scatter(x[:, 0], x[:, 1], c=values, s=4, cmap="viridis")
        fig.colorbar(sc, ax=ax, label=field)
        ax.set_aspect("equal")
        ax.set_xlabel("x")
        ax.set_ylabel("y")
    ax.set_title(title or f"{field} at t = {result.times[save]:.4g}{note}")
    _save(plt, fig, path)
    return path


def plot_energy(result, path, title=""):
    """Kinetic, strain and total energy and external work against time."""
    plt = _pyplot()
    e = result.energies
    fig, ax = plt.subplots(figsize=(7, 4))
    for key in ("kinetic", "strain", "total", "external_work"):
        ax.plot(result.times, e[key], label=key.replace("_", " "))
    ax.set_xlabel("time")
    ax.set_ylabel("energy (units of the scene)")
    ax.set_title(title or "Energy history")
    ax.grid(True, alpha=0.3)
    ax.legend()
    _save(plt, fig, path)
    return path


def plot_displacement_history(result, path, exact=None, particles=None, component=0, title=""):
    """Displacement of chosen particles (default: three spread over the body)
    against time, each labelled by its reference position X; the exact
    solution, when given, as a dashed black curve drawn over the computed
    one (which is drawn as markers on a thin line)."""
    plt = _pyplot()
    h = result.history
    n = h["u"][0].shape[0]
    chosen = particles if particles is not None else [n // 4, n // 2, (3 * n) // 4]
    fig, ax = plt.subplots(figsize=(7, 4))
    t = result.times
    X0 = np.asarray(h["X"][0])
    for i in chosen:
        series = [h["u"][k][i, component] for k in range(len(t))]
        where = ", ".join(f"{c:.3g}" for c in X0[i])
        ax.plot(t, series, "o-", markersize=3, linewidth=0.6, alpha=0.8,
                        label=f"X = ({where})" if X0.shape[1] > 1 else f"X = {where}")
        if exact is not None:
            ts = np.linspace(t[0], t[-1], 200)
            ax.plot(ts, [exact(X0[i:i + 1], s)[0, component] for s in ts], "--",
                    color="black", linewidth=1.0, zorder=3)
    if exact is not None:
        ax.plot([], [], "--", color="black", linewidth=1.0, label="exact")
    ax.set_xlabel("time")
    ax.set_ylabel(f"displacement u_{component}")
    ax.set_title(title or "Displacement of particles at reference position X"
                 + (" (dashed: exact)" if exact is not None else ""))
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    _save(plt, fig, path)
    return path


def _line_values(result, field, save, exact=None):
    """A 1D field with its sign: sigma_xx, v_x, u_x or u_x - exact."""
    h = result.history
    if field == "stress":
        return h["stress"][save][:, 0, 0]
    if field in ("velocity", "displacement"):
        return h["v" if field == "velocity" else "u"][save][:, 0]
    if field == "error":
        if exact is None:
            raise ValueError("field='error' needs exact(X, t)")
        return (h["u"][save] - exact(h["X"][save], result.times[save]))[:, 0]
    return _field_values(result, field, save, exact)


FIELD_LABELS = {"stress": ("sigma_xx", "von Mises stress"), "velocity": ("v_x", "|v|"),
                "displacement": ("u_x", "|u|"), "error": ("u_x - exact", "|u - exact|")}


def plot_field_snapshots(result, path, field="stress", count=4, exact=None, title=""):
    """``field`` (stress, velocity, displacement or error) at ``count`` saves
    spread over the run (the first and the last included). 1D: one line per
    time over the particles' current position x (the signed value:
    sigma_xx, v_x, u_x; with ``exact`` and the displacement, the exact u_x
    dashed); 2D and 3D: one panel per time, particles coloured on one
    shared scale (as :func:`plot_particles`, 3D as its middle z-slice)."""
    plt = _pyplot()
    saves = len(result.times)
    picks = sorted(set(np.linspace(0, saves - 1, min(count, saves)).round().astype(int)))
    dim = result.history["x"][0].shape[1]
    if dim == 1:
        fig, ax = plt.subplots(figsize=(7, 4))
        for k in picks:
            x = result.history["x"][k][:, 0]
            order = np.argsort(x)
            ax.plot(x[order], _line_values(result, field, k, exact)[order], "-",
                            linewidth=1.2, label=f"t = {result.times[k]:.4g}")
            if exact is not None and field == "displacement":
                X = result.history["X"][k]
                ax.plot(x[order], exact(X, result.times[k])[order, 0], "--", color="black",
                        linewidth=0.8, zorder=3)
        if exact is not None and field == "displacement":
            ax.plot([], [], "--", color="black", linewidth=0.8, label="exact")
        ax.set_xlabel("position x")
        ax.set_ylabel(FIELD_LABELS.get(field, (field,))[0])
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
        ax.set_title(title or f"{FIELD_LABELS.get(field, (field,))[0]} over x at "
                     f"{len(picks)} times")
        _save(plt, fig, path)
        return path
    values = [_field_values(result, field, k, exact) for k in picks]
    lo = min(float(v.min()) for v in values)
    hi = max(float(v.max()) for v in values)
    fig, axes = plt.subplots(1, len(picks), figsize=(3.2 * len(picks) + 1, 3.6), squeeze=False,
                             layout="constrained")
    for ax, k, v in zip(axes[0], picks, values):
        x = result.history["x"][k]
        where = ""
        if dim == 3:
            grid = result.grid
            middle = 0.5 * sum(grid.bounds[2])
            layer = x[np.argmin(np.abs(x[:, 2] - middle)), 2]
            keep = np.abs(x[:, 2] - layer) < 0.25 * grid.h[2]
            x, v = x[keep], v[keep]
            where = f", z = {layer:.3g}"
        sc = ax.scatter(x[:, 0], x[:, 1], c=v, s=4, cmap="viridis", vmin=lo, vmax=hi)
        ax.set_aspect("equal")
        ax.set_title(f"t = {result.times[k]:.4g}{where}", fontsize=9)
        ax.set_xlabel("x")
    axes[0][0].set_ylabel("y")
    fig.colorbar(sc, ax=list(axes[0]), label=FIELD_LABELS.get(field, ("", field))[1])
    fig.suptitle(title or f"{FIELD_LABELS.get(field, ('', field))[1]} at {len(picks)} times"
                 + (" (middle z-slice)" if dim == 3 else ""))
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
