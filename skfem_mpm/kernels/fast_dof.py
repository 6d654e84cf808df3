"""The fast-dof guard's frequency estimate from a dof's effective mass.

A dof k whose function the particles see only at the tail of its support
can make the consistent mass nearly singular, and its frequency outgrow the
time step. Its own Rayleigh quotient K_kk / M_kk is a lower bound of the
top eigenvalue of M^-1 K, not an estimate: the fast mode is dof k together
with the neighbours that cancel its mass. So the estimate here is

    omega_k^2 ~ c^2 K_kk / S_k,   S_k = M_kk - M_kN M_NN^+ M_Nk,

S_k the Schur complement of M on the patch N of dofs within PATCH_RADIUS
(default p) indices per axis of k that have mass: the mass of the part of
N_k that its neighbours cannot represent ("effective mass"; with the whole
grid as N, S_k = 1 / (M^-1)_kk, and K_kk / S_k is exact when K is
K_kk e_k e_k^T). Measured on 1D bars of quadratic and cubic splines whose
body ends at a knot or inside a cell (Gauss points, or 2 particles per
cell; free end), the estimate is 1.0-1.7 times the exact top eigenvalue
where that eigenvalue exceeds the time step's Lambda (a mode localised at
the end; a radius-1 patch: 0.2-1.1), while K_kk / M_kk times the interior
amplification Lambda / q (the guard's plain rule) overestimates a body
ending at a knot 1.5-9 fold. An indefinite patch (a reconstructed density
can make M so) gives no estimate (-1). How the guard uses it, and why that
is off by default: :func:`skfem_mpm.solve.timestep.guarded_stiffness`.

S_k comes from a Cholesky factorisation of the patch with k last
(Golub & Van Loan, "Matrix Computations", 4th ed., Alg. 4.2.1): S_k is the
last pivot. A neighbour whose pivot is not above DROP times its diagonal
depends on the ones before it (the patch matrix is a Gram matrix
N^T W N of particle or Gauss values and may be singular) and is left out,
which is M_NN^+ on the range of M_NN.
"""
import numpy as np
from numba import njit, prange

__all__ = ["PATCH_RADIUS", "DROP", "effective_mass", "limit_by_effective_mass"]

PATCH_RADIUS = 0
"""The patch: the dofs within this many indices per axis of k (0: the
degree p, i.e. every dof that shares a cell with k)."""

DROP = 1e-10
"""A patch neighbour is left out when its Cholesky pivot is at most DROP
times its diagonal (linearly dependent on the neighbours before it)."""


@njit(cache=True, error_model="numpy")
def effective_mass(M, k, p, nbx, nby, dim, mass, offsets, dofs, A):
    """S_k of the module docstring from the mass stencil M (dofs,
    (2p + 1)^dim; slot ((dc + p) w + db + p) w + da + p, w = 2p + 1, the
    y and z parts only in 2D and 3D), on dofs with ``mass`` > 0. Work
    arrays: ``offsets`` (3^dim, 3) int, ``dofs`` (3^dim,) int, ``A``
    (3^dim, 3^dim) float."""
    width = 2 * p + 1
    pb = p if dim >= 2 else 0
    pc = p if dim == 3 else 0
    nbz = M.shape[0] // (nbx * nby)
    a = k % nbx
    b = (k // nbx) % nby
    c = k // (nbx * nby)
    ra = PATCH_RADIUS if PATCH_RADIUS > 0 else p
    rb = ra if dim >= 2 else 0
    rc = ra if dim == 3 else 0
    n = 0
    for dc in range(-rc, rc + 1):  # the neighbours in slot order, then k
        for db in range(-rb, rb + 1):
            for da in range(-ra, ra + 1):
                if da == 0 and db == 0 and dc == 0:
                    continue
                aa = a + da
                bb = b + db
                cc = c + dc
                if aa < 0 or aa >= nbx or bb < 0 or bb >= nby or cc < 0 or cc >= nbz:
                    continue
                j = (cc * nby + bb) * nbx + aa
                if not mass[j] > 0.0:
                    continue
                dofs[n] = j
                offsets[n, 0] = da
                offsets[n, 1] = db
                offsets[n, 2] = dc
                n += 1
    dofs[n] = k
    offsets[n, 0] = 0
    offsets[n, 1] = 0
    offsets[n, 2] = 0
    n += 1
    for u in range(n):  # the patch matrix (lower triangle)
        for v in range(u + 1):
            oa = offsets[v, 0] - offsets[u, 0]
            ob = offsets[v, 1] - offsets[u, 1]
            oc = offsets[v, 2] - offsets[u, 2]
            if abs(oa) > p or abs(ob) > p or abs(oc) > p:
                A[u, v] = 0.0
            else:
                A[u, v] = M[dofs[u], ((oc + pc) * width + ob + pb) * width + oa + p]
    pivot = 0.0
    for u in range(n):  # Cholesky, dependent neighbours left out (column 0)
        pivot = A[u, u]
        for q in range(u):
            pivot -= A[u, q] * A[u, q]
        if u == n - 1:
            break
        if pivot < -DROP * A[u, u]:  # an indefinite patch: no estimate
            return -1.0
        if not pivot > DROP * A[u, u]:
            for i in range(u, n):
                A[i, u] = 0.0
            continue
        root = np.sqrt(pivot)
        A[u, u] = root
        for i in range(u + 1, n):
            s = A[i, u]
            for q in range(u):
                s -= A[i, q] * A[u, q]
            A[i, u] = s / root
    return pivot


@njit(cache=True, parallel=True, error_model="numpy")
def limit_by_effective_mass(guarded, stiffness, M, mass, limit, ratio, p, nbx, nby, dim):
    """guarded_k <- min(guarded_k, ratio K_k M_kk / S_k) on the dofs the
    guard would lump (mass > 0 and guarded_k > limit M_kk / 2; S_k from
    :func:`effective_mass`), in place: the rule of
    :func:`skfem_mpm.solve.timestep.guarded_stiffness` (ratio = q / Lambda)."""
    if not ratio < np.inf:  # the rule is off
        return
    centre = (M.shape[1] - 1) // 2
    size = (2 * (PATCH_RADIUS if PATCH_RADIUS > 0 else p) + 1) ** dim
    for k in prange(mass.shape[0]):
        diag = M[k, centre]
        if not (mass[k] > 0.0 and guarded[k] > 0.5 * limit * diag):
            continue
        offsets = np.empty((size, 3), dtype=np.int64)
        dofs = np.empty(size, dtype=np.int64)
        A = np.empty((size, size))
        S = effective_mass(M, k, p, nbx, nby, dim, mass, offsets, dofs, A)
        if S > 0.0:
            bound = ratio * stiffness[k] * (diag / S)
            if bound < guarded[k]:
                guarded[k] = bound
