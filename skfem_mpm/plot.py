"""Pictures of studies and runs (matplotlib, written to PNG files).

Studies: :func:`plot_convergence` (error against cell size with reference
slopes) and :func:`plot_work_precision` (error against wall time).
Runs: :func:`plot_particles` (particles coloured by a field over the grid),
:func:`plot_energy` (energy history), :func:`plot_displacement_history`
(displacement of chosen particles against the exact solution).
"""
import math

import numpy as np

__all__ = ["plot_convergence", "plot_work_precision", "plot_particles", "plot_energy",
           "plot_displacement_history"]


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


def plot_convergence(records, path, title=""):
    """Relative RMS error at t_end against cell size h, with slopes 1-4."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 5))
    series = _series(records, "h")
    for method, pts in series.items():
        h, e = zip(*pts)
        ax.loglog(h, e, label=method, **_style(method))
    if series:
        h_all = np.array([h for pts in series.values() for h, _ in pts])
        e_all = np.array([e for pts in series.values() for _, e in pts])
        h0, h1 = h_all.min(), h_all.max()
        anchor = np.exp(np.mean(np.log(e_all)))
        for order in (1, 2, 3, 4):
            hs = np.array([h0, h1])
            ax.loglog(hs, anchor * (hs / math.sqrt(h0 * h1)) ** order, color="0.6",
                      linewidth=0.8, linestyle=":")
            ax.annotate(f"h^{order}", (h1, anchor * (h1 / math.sqrt(h0 * h1)) ** order),
                        color="0.4", fontsize=8)
    ax.set_xlabel("cell size h (length units of the benchmark)")
    ax.set_ylabel(_error_label(records))
    ax.set_title(f"Convergence: {title}")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    _save(plt, fig, path)
    return path


def plot_work_precision(records, path, title=""):
    """Relative RMS error at t_end against wall time (JIT excluded)."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 5))
    for method, pts in _series(records, "wall_time_s").items():
        t, e = zip(*pts)
        ax.loglog(t, e, label=method, **_style(method))
    ax.set_xlabel("wall time of the run [s] (JIT compilation excluded)")
    ax.set_ylabel(_error_label(records))
    ax.set_title(f"Work-precision: {title}")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
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
    against time, with the exact solution when given."""
    plt = _pyplot()
    h = result.history
    n = h["u"][0].shape[0]
    chosen = particles if particles is not None else [n // 4, n // 2, (3 * n) // 4]
    fig, ax = plt.subplots(figsize=(7, 4))
    t = result.times
    for i in chosen:
        series = [h["u"][k][i, component] for k in range(len(t))]
        line, = ax.plot(t, series, "o-", markersize=3, label=f"particle {i}")
        if exact is not None:
            ts = np.linspace(t[0], t[-1], 200)
            X = h["X"][0][i:i + 1]
            ax.plot(ts, [exact(X, s)[0, component] for s in ts], "--", color=line.get_color(),
                    linewidth=0.8)
    ax.set_xlabel("time")
    ax.set_ylabel(f"displacement u_{component}")
    ax.set_title(title or "Displacement of particles (dashed: exact)")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    _save(plt, fig, path)
    return path
