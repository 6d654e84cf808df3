"""Helpers for convergence tests, for this project's tests and users' own.

Example (pytest)::

    from skfem_mpm.testing import assert_order

    def test_my_solver_is_second_order():
        sizes = [1/8, 1/16, 1/32]
        errors = [run(h) for h in sizes]
        assert_order(errors, sizes, expected=2.0, tol=0.15)
"""
import numpy as np

__all__ = ["observed_orders", "assert_order", "order_table", "rms_error"]


def observed_orders(errors, sizes):
    """Observed orders log(e_i / e_(i+1)) / log(h_i / h_(i+1)) between
    successive resolutions (one fewer than the inputs)."""
    e = np.asarray(errors, dtype=np.float64)
    h = np.asarray(sizes, dtype=np.float64)
    if e.shape != h.shape or e.ndim != 1 or e.size < 2:
        raise ValueError(
            f"errors and sizes must be 1-D of equal length >= 2, got {e.shape} and {h.shape}"
        )
    if np.any(e <= 0) or np.any(h <= 0):
        raise ValueError("errors and sizes must be positive to take logarithms")
    return np.log(e[:-1] / e[1:]) / np.log(h[:-1] / h[1:])


def order_table(errors, sizes):
    """A plain-text table of sizes, errors and observed orders."""
    orders = observed_orders(errors, sizes)
    lines = [f"{'h':>12} {'error':>12} {'order':>7}"]
    for i, (h, e) in enumerate(zip(sizes, errors)):
        order = "" if i == 0 else f"{orders[i - 1]:7.3f}"
        lines.append(f"{h:12.5g} {e:12.5g} {order:>7}")
    return "\n".join(lines)


def assert_order(errors, sizes, expected, tol=0.15, which="all"):
    """Assert that the observed orders are at least ``expected - tol``.

    ``which="all"`` checks every successive pair, ``"last"`` only the finest
    pair. The failure message carries the table of errors and orders.
    """
    orders = observed_orders(errors, sizes)
    checked = orders if which == "all" else orders[-1:]
    if np.any(checked < expected - tol):
        raise AssertionError(
            f"observed order below {expected} - {tol}:\n" + order_table(errors, sizes)
        )
    return orders


def rms_error(result, exact, time=None, relative_to=None):
    """Root-mean-square displacement error over particles,

        e_RMS = sqrt( (1/n_p) sum_p |u_h(X_p, t) - u(X_p, t)|^2 ),

    for a run ``result`` (from ``simulate`` or ``fem``) and ``exact(X, t)``
    returning displacements of shape (n, dim) (or (n,) in 1D). ``time``
    defaults to the last saved time; ``relative_to`` divides by an amplitude.
    """
    k = -1 if time is None else int(np.argmin(np.abs(np.asarray(result.times) - time)))
    X = result.history["X"]
    u = result.history["u"][k]
    t = result.times[k]
    ue = np.asarray(exact(X, t), dtype=np.float64).reshape(u.shape)
    err = float(np.sqrt(np.mean(np.sum((u - ue) ** 2, axis=1))))
    return err if relative_to is None else err / relative_to
