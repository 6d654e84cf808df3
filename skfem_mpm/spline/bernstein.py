"""Bernstein polynomials on the reference interval [0, 1].

    B_j^p(xi) = binom(p, j) xi^j (1 - xi)^(p - j),         j = 0, ..., p
    d/dxi B_j^p = p (B_{j-1}^{p-1}(xi) - B_j^{p-1}(xi))      (B_{-1} = B_p^{p-1} = 0)

They are the Bezier basis on one cell; a B-spline restricted to a cell is a
combination of them with the cell's extraction matrix (Borden et al. 2011,
"Isogeometric finite element data structures based on Bezier extraction of
NURBS", IJNME 87:15-47, eq. 8).
"""
from math import comb

import numpy as np

__all__ = ["bernstein", "bernstein_derivative"]


def bernstein(p, xi):
    """Values of the p + 1 Bernstein polynomials of degree ``p`` at ``xi``.

    ``xi`` has any shape S; the result has shape S + (p + 1,).
    """
    xi = np.asarray(xi, dtype=np.float64)
    one_minus = 1.0 - xi
    out = np.empty(xi.shape + (p + 1,))
    for j in range(p + 1):
        out[..., j] = comb(p, j) * xi ** j * one_minus ** (p - j)
    return out


def bernstein_derivative(p, xi):
    """First derivatives d/dxi of the Bernstein polynomials of degree ``p``."""
    xi = np.asarray(xi, dtype=np.float64)
    out = np.zeros(xi.shape + (p + 1,))
    if p == 0:
        return out
    lower = bernstein(p - 1, xi)
    out[..., 1:] += p * lower
    out[..., :-1] -= p * lower
    return out
