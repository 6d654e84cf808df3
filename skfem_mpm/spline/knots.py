"""Open knot vectors and Bezier extraction operators of 1D B-spline spaces.

A grid axis is given by its breakpoints u_0 < u_1 < ... < u_n (n cells). The
B-spline space of degree p with maximal smoothness C^(p-1) at the interior
breakpoints uses the open (clamped) knot vector

    tau = (u_0 x (p + 1), u_1, ..., u_(n-1), u_n x (p + 1)),

which has n + p basis functions N_0, ..., N_(n+p-1); on cell e (= [u_e,
u_(e+1)]) the p + 1 functions N_e, ..., N_(e+p) are non-zero. The clamped
ends make the space interpolate at the domain boundary: N_0(u_0) = 1.

Bezier extraction (Borden, Scott, Evans, Hughes 2011, IJNME 87:15-47,
Section 3) writes the restriction to cell e as

    N_(e+i)(x) = sum_j C_e[i, j] B_j(xi),     xi = (x - u_e) / (u_(e+1) - u_e),

with B_j the Bernstein polynomials. Borden et al. obtain C_e by inserting
every interior knot until its multiplicity is p. Knot insertion is
blossoming (Lyche & Morken, "Spline Methods", Thm. 4.x: the knot insertion
coefficients are blossoms of the B-splines at the new knots), and the
Bernstein polynomial B_j of cell e has the blossom arguments
(u_e repeated p - j times, u_(e+1) repeated j times); hence

    C_e[:, j] = R_1(x_1) R_2(x_2) ... R_p(x_p),  (x_1..x_p) = (u_e^(p-j), u_(e+1)^j)

where R_k(x) is the k x (k+1) matrix of the de Boor recursion on span
mu = e + p. The same product with x_1 = ... = x_p = x evaluates the B-splines
at x. Both are vectorised over cells here.
"""
import numpy as np

__all__ = [
    "check_breakpoints",
    "check_degree",
    "open_knot_vector",
    "extraction_operators",
    "bspline_values",
]

SUPPORTED_DEGREES = (1, 2, 3)


def check_degree(degree):
    """Return ``degree`` as int if it is 1, 2 or 3; raise ValueError otherwise."""
    if isinstance(degree, (bool, np.bool_)) or not isinstance(degree, (int, np.integer)):
        raise ValueError(f"degree must be an integer in {SUPPORTED_DEGREES}, got {degree!r}")
    if int(degree) not in SUPPORTED_DEGREES:
        raise ValueError(f"degree must be one of {SUPPORTED_DEGREES}, got {degree}")
    return int(degree)


def check_breakpoints(breakpoints, name="breakpoints"):
    """Validate a strictly increasing, finite array of at least two breakpoints."""
    try:
        u = np.asarray(breakpoints, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a 1-D array of real numbers, got "
                         f"{breakpoints!r}") from None
    if u.ndim != 1:
        raise ValueError(f"{name} must be a 1-D array, got shape {u.shape}")
    if u.size < 2:
        raise ValueError(f"{name} must hold at least 2 values (1 cell), got {u.size}")
    if not np.all(np.isfinite(u)):
        bad = int(np.flatnonzero(~np.isfinite(u))[0])
        raise ValueError(f"{name} must be finite, got {u[bad]} at index {bad}")
    steps = np.diff(u)
    if np.any(steps <= 0):
        bad = int(np.flatnonzero(steps <= 0)[0])
        raise ValueError(
            f"{name} must be strictly increasing, got {u[bad]} followed by "
            f"{u[bad + 1]} at index {bad}"
        )
    scale = np.abs(u).max()
    tiny = steps.min()
    if tiny < 1e-12 * scale or tiny < 1e-150 or steps.max() > 1e150:
        raise ValueError(
            f"{name} must have cells wider than 1e-12 of the coordinates' size and "
            f"between 1e-150 and 1e150 (the time step divides by the squared cell size), "
            f"got cells from {tiny:.3g} to {steps.max():.3g} at coordinates up to {scale:.3g}")
    return u


def open_knot_vector(breakpoints, degree):
    """The clamped knot vector (u_0 x (p+1), interior breakpoints, u_n x (p+1))."""
    u = np.asarray(breakpoints, dtype=np.float64)
    p = int(degree)
    return np.concatenate((np.full(p, u[0]), u, np.full(p, u[-1])))


def _de_boor_products(tau, span, p, args):
    """R_1(args[..., 0]) ... R_p(args[..., p-1]) on knot span ``span``.

    ``span`` has shape S, ``args`` shape S + (p,); returns S + (p + 1,), the
    blossoms of the p + 1 B-splines N_(span-p), ..., N_span.
    """
    row = np.ones(span.shape + (1,))
    for k in range(1, p + 1):
        x = args[..., k - 1]
        new = np.zeros(span.shape + (k + 1,))
        for l in range(k):
            upper = tau[span + l + 1]
            lower = tau[span + l + 1 - k]
            inv_width = 1.0 / (upper - lower)
            new[..., l] += row[..., l] * (upper - x) * inv_width
            new[..., l + 1] += row[..., l] * (x - lower) * inv_width
        row = new
    return row


def extraction_operators(breakpoints, degree):
    """Bezier extraction matrices C_e, shape (cells, p + 1, p + 1).

    ``C[e, i, j]`` is the coefficient of Bernstein polynomial j in the
    restriction of N_(e+i) to cell e (see the module docstring).
    """
    u = np.asarray(breakpoints, dtype=np.float64)
    p = int(degree)
    tau = open_knot_vector(u, p)
    ncells = u.size - 1
    cells = np.arange(ncells)
    span = np.broadcast_to((cells + p)[:, None], (ncells, p + 1))
    # blossom arguments of Bernstein j on cell e: (u_e)^(p-j), (u_(e+1))^j
    j = np.arange(p + 1)
    k = np.arange(p)
    use_right = k[None, :] < j[:, None]  # (p+1, p): first j arguments right end
    args = np.where(use_right[None, :, :], u[1:, None, None], u[:-1, None, None])
    cols = _de_boor_products(tau, span, p, args)  # (cells, j, i)
    return np.ascontiguousarray(np.swapaxes(cols, 1, 2))


def bspline_values(tau, span, p, x):
    """Values of the p + 1 B-splines non-zero on knot span ``span`` at ``x``."""
    x = np.asarray(x, dtype=np.float64)
    args = np.repeat(x[..., None], p, axis=-1)
    return _de_boor_products(tau, np.asarray(span), p, args)
