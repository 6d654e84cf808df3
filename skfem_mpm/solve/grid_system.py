"""The grid equations of one step: M x = rhs with constraints, lumped or
consistent mass, and a guard against tiny nodal masses.

Constraints. For every velocity component c, the constrained dofs C_c carry
known values (0 for ``Fixed``, ``velocity(t)`` for ``Prescribed``); the free
ones solve M_FF x_F = rhs_F - M_FC x_C.

Tiny masses. A dof whose particles touch its basis function only at the edge
of its support has a nodal mass m_i that can be arbitrarily small, and
m_i^-1 f_i blows up. A dof is *small* when

    m_i < tol * max_{j ~ i} m_j          (j ~ i: the dofs sharing a cell with i)

(``Method(small_mass=tol)``, default 1e-3; lumped masses m = N^T m_p). Each
small free dof is merged into the heaviest dof it shares a cell with (its
"master", followed until a dof that is not small): the two functions move
as one, N_master + N_small. When several neighbours tie for heaviest (to a
relative 1e-9, as in any symmetric body), the small dof is shared equally
between them, N_a + N_small / 2 and N_b + N_small / 2, so that the merge
keeps the body's symmetry. This is the extension idea of extended B-splines
(Hollig, Reif, Wipper 2001) applied to mass: with the merging matrix T
(dofs x kept dofs) the reduced system is T^T M T x_r = T^T rhs, x = T x_r.
Because T 1 = 1 (every dof's row of weights sums to one), constant
velocities are still represented and the total momentum change
1^T M x = 1^T T^T rhs = sum_i rhs_i is exactly what it would be without the
merge: no momentum is lost or created (a test measures this to round-off).
Dofs with zero mass (no particle) are inactive: x = 0.

Fast dofs (consistent mass). The particle consistent mass
M = N^T diag(m_p) N becomes nearly singular when a function is seen only at
the tail of its support (a free surface drifting into a cell, few particles
there): its smallest eigenvalue relative to the lumped mass drops (measured
on the large-deformation soil column: 0.11 at the start, 0.009 one step
before the blow-up) and that dof's frequency outgrows the time step.
The time step assumes omega^2 <= c^2 Lambda(p) / h^2; in the interior the
coupled spectrum exceeds a dof's own Rayleigh quotient K_ii / M_ii by
Lambda(p) / q(p). So with

    r_i = w_i dt^2 K_ii / M_ii / (g * 4 q(p) / Lambda(p)),   K_ii ~ c^2 sum_p m_p |grad N_i(x_p)|^2,
    M_ii = sum_p m_p N_i(x_p)^2,

(``Method(frequency_guard=g)``, default 1; the limit is 0.34 for p = 2,
0.12 for p = 3 at g = 1; the 4 is s^2 for a scheme stable up to
omega dt = s, 8 for rk4) the fraction theta_i = smoothstep(2 r_i - 1) of
the row and column of dof i is lumped: nothing below half the limit, all of
it above the limit, continuously in between. (A hard switch at the limit
lumps and unlumps rows as a free surface sweeps through cells; those jumps
accumulate with the number of cells crossed.) The weight w_i <= 1 measures
each dof against its own fully covered quotient: the first functions of an
open knot vector have a full-grid K_ii / M_ii of 2.2 and 3.7 q(p) (p = 2),
4.9 and 9.1 q(p) (p = 3), so with w_i = 1 a grid the particles fill
lumped the rows next to a fixed end at the default cfl 0.5 (S1, cubic,
spline: error 1.65e-2 instead of 2.9e-4). So w_i = min(1, q(p) sum_d
h_d^-2 / Q_i), Q_i the Gauss full-grid quotient, while particles cover the
function, blending where they see only its tail (from M_ii / (m_i mu_i))
to 1 without a reconstruction (particle quadrature over-samples a tail's
steep end: its mode outruns Lambda) and, with one (a Gauss-integrated
system), to the open knot vector's first function's weight q(p) / Q_1: a
body ending at a knot (S3) leaves such a tail, no faster than the step
allows, and a body ending a fraction l into a cell gives r ~ cfl^2 / l^2,
lumped where the cut cell would break the step, and the dofs within p
indices of a dof so lumped (the cut cell's other functions) go back to
weight 1 by the fraction it is lumped; and w_i = 0 on dofs constrained
in every component (they never move; lumping their rows only moved mass
onto their free neighbours). K_ii, M_ii and m_i are the particles' own
sums with a reconstruction too (the reconstruction's Gauss points span a
cut cell as they span a filled one). See
:func:`skfem_mpm.solve.timestep.covered_stiffness`.

Consistent mass is solved with a sparse LU factorisation (reused for every
solve of the step with the same free set) or with conjugate gradients
preconditioned by the lumped mass and warm-started from the previous step
(``Method(mass_solver=...)``).
"""
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..errors import InvalidState
from ..effects import prescribed_value

__all__ = ["Constraints", "GridSystem", "dof_adjacency"]


def dof_adjacency(grid):
    """Boolean CSR (dofs x dofs): i ~ j when they share a cell (diagonal included)."""
    ed = np.asarray(grid.dofs.element_dofs)  # (k, cells)
    k = ed.shape[0]
    rows = np.repeat(ed, k, axis=0).ravel()
    cols = np.tile(ed, (k, 1)).ravel()
    A = sp.csr_matrix((np.ones(rows.size, dtype=np.int8), (rows, cols)),
                      shape=(grid.ndofs, grid.ndofs))
    A.data[:] = 1
    return A



class Constraints:
    """The constrained dofs of every component, from the scene's effects."""

    def __init__(self, grid, effects):
        dim = grid.dim
        self.ndofs = grid.ndofs
        self.dim = dim
        self.items = []  # (effect, component, dofs, velocity or None)
        for e in effects:
            for c, dofs, fn in e.constraints(grid):
                self.items.append((e, c, np.asarray(dofs), fn))
        self.mask = np.zeros((grid.ndofs, dim), dtype=bool)
        prescribed = np.zeros((grid.ndofs, dim), dtype=bool)
        for e, c, dofs, fn in self.items:
            if fn is not None and self.mask[dofs, c].any() or \
                    fn is None and prescribed[dofs, c].any():
                raise ValueError(f"effects: {e!r} constrains component {c} of dofs that "
                                 f"another effect already prescribes or fixes; a dof "
                                 f"component takes one constraint (which one wins is not "
                                 f"defined)")
            self.mask[dofs, c] = True
            if fn is not None:
                prescribed[dofs, c] = True
        self.prescribed = [(c, dofs, fn) for _, c, dofs, fn in self.items if fn is not None]

    @property
    def any(self):
        return bool(self.items)

    def values(self, t):
        """Grid velocities (dofs, dim) on constrained dofs at time t (0 elsewhere)."""
        out = np.zeros((self.ndofs, self.dim))
        for (c, dofs, _), value in zip(self.prescribed, self.item_values(t)):
            out[dofs, c] = value
        return out

    def item_values(self, t):
        """The velocity(t) of each prescribed item (component, dofs,
        velocity), in the order of ``prescribed``: shape (items,)."""
        return np.array([prescribed_value(fn, t) for _, _, fn in self.prescribed],
                        dtype=np.float64)

    def reactions_at(self, mass, a, force, gravity=None):
        """Reactions for lumped mass, m a - f (f including m g), evaluated on
        the constrained dofs only."""
        totals = {}
        for e, c, dofs, _ in self.items:
            key = repr(e)
            totals.setdefault(key, np.zeros(self.dim))
            f = force[dofs, c]
            if gravity is not None:
                f = f + mass[dofs] * gravity[c]
            totals[key][c] += float(np.sum(mass[dofs] * a[dofs, c] - f))
        return totals

    def reactions(self, residual):
        """Total reaction force (dim,) of each constraint effect, from the
        residual M x - rhs on its dofs."""
        totals = {}
        for e, c, dofs, _ in self.items:
            key = repr(e)
            totals.setdefault(key, np.zeros(self.dim))
            totals[key][c] += residual[dofs, c].sum()
        return totals


class _Reduction:
    """Merging of tiny-mass dofs and the free/constrained split for one
    constraint pattern (shared by the components that have it)."""

    TIE = 1e-9  # masters within this relative mass of the heaviest share the dof

    def __init__(self, lumped, constrained, adjacency, tol):
        nd = lumped.size
        active = lumped > 0
        small = np.zeros(nd, dtype=bool)
        if tol > 0 and adjacency is not None:
            weighted = adjacency.multiply(lumped[None, :]).tocsr()
            neighbour_max = np.asarray(weighted.max(axis=1).todense()).ravel()
            small = active & ~constrained & (lumped < tol * neighbour_max)
        self.active = np.flatnonzero(active)
        if small.any():
            T = self._merging(weighted, neighbour_max, small, active)
        else:
            T = sp.identity(nd, format="csr")[:, self.active]
        self.small = int(np.count_nonzero(small))
        kept = np.flatnonzero(active & ~small)
        self.kept = kept
        self.T = T.tocsr()  # dofs x kept dofs, rows of active dofs sum to 1
        self._Ta = self.T[self.active]
        self.nr = kept.size
        self.constrained = constrained[kept]
        self.free = np.flatnonzero(~self.constrained)
        self.fixed = np.flatnonzero(self.constrained)
        self.m_r = self._Ta.T @ lumped[self.active]

    def _merging(self, weighted, neighbour_max, small, active):
        """T: each small dof goes to its heaviest neighbour, shared equally
        between neighbours whose masses tie to TIE (a symmetric body stays
        symmetric), followed through small masters until a kept dof."""
        nd = small.size
        rows = np.flatnonzero(small)
        sub = weighted[rows].tocoo()
        top = sub.data >= (1.0 - self.TIE) * neighbour_max[rows[sub.row]]
        r, c = rows[sub.row[top]], sub.col[top]
        share = 1.0 / np.bincount(r, minlength=nd)[r]
        keep = np.flatnonzero(active & ~small)
        step = sp.csr_matrix((np.concatenate([share, np.ones(keep.size)]),
                              (np.concatenate([r, keep]), np.concatenate([c, keep]))),
                             shape=(nd, nd))
        T = step
        for _ in range(64):  # masters are strictly heavier: no cycles
            nxt = (T @ step).tocsr()
            if (nxt != T).nnz == 0:
                break
            T = nxt
        return T[:, keep]

    def restrict(self, rhs):
        """T^T rhs for rhs of shape (dofs, k)."""
        return np.asarray(self._Ta.T @ rhs[self.active])

    def prolong(self, x_r, nd):
        out = np.zeros((nd, x_r.shape[1]))
        out[self.active] = self._Ta @ x_r
        return out


class GridSystem:
    """M x = rhs for one step (see the module docstring)."""

    def __init__(self, lumped, constraints, consistent=None, adjacency=None,
                 small_mass=1e-3, mass_solver="direct", warm=None, cg_rtol=1e-13,
                 fast_rows=None):
        self.lumped = lumped
        self.lumped_rows = 0
        if consistent is not None and fast_rows is not None:
            consistent = self._lump_rows(consistent, lumped, fast_rows(consistent.diagonal()))
        self.consistent = consistent
        self.constraints = constraints
        self.mass_solver = mass_solver
        self.warm = warm if warm is not None else {}
        self.cg_rtol = cg_rtol
        dim = constraints.dim
        self.groups = {}  # constraint pattern -> (components, reduction)
        for c in range(dim):
            key = constraints.mask[:, c].tobytes()
            if key not in self.groups:
                self.groups[key] = ([], _Reduction(lumped, constraints.mask[:, c],
                                                   adjacency, small_mass))
            self.groups[key][0].append(c)
        self._factors = {}
        self.cg_iterations = 0

    def _lump_rows(self, M, lumped, theta):
        """Lump the fraction theta_i in [0, 1] of the rows and columns of M:
        the off-diagonal entry M_ij loses max(theta_i, theta_j) of itself to
        the diagonals of both rows, so M stays symmetric, keeps its row sums
        (M 1 = m: momentum is exact) and only gains a positive semi-definite
        graph Laplacian; the change is continuous in theta."""
        theta = np.where(lumped > 0, np.asarray(theta, dtype=np.float64), 0.0)
        self.lumped_rows = int(np.count_nonzero(theta))
        if not self.lumped_rows:
            return M
        C = M.tocoo()
        off = C.row != C.col
        share = np.where(off, np.maximum(theta[C.row], theta[C.col]), 0.0) * C.data
        moved = np.bincount(C.row, weights=share, minlength=lumped.size)
        out = sp.csr_matrix((C.data - share, (C.row, C.col)), shape=C.shape) + sp.diags(moved)
        return out.tocsr()

    @property
    def small_dofs(self):
        """Number of merged tiny-mass dofs (largest over components)."""
        return max(r.small for _, r in self.groups.values())

    def _reduced_matrix(self, key, red):
        if key not in self._factors:
            M_r = (red.T.T @ self.consistent @ red.T).tocsr()
            M_ff = M_r[red.free][:, red.free].tocsc()
            M_fc = M_r[red.free][:, red.fixed]
            try:
                lu = spla.splu(M_ff) if self.mass_solver == "direct" else None
            except RuntimeError as exc:  # "Factor is exactly singular"
                raise InvalidState(f"the consistent mass is singular on the free dofs "
                                   f"({exc})") from exc
            self._factors[key] = (M_ff, M_fc, lu)
        return self._factors[key]

    def solve(self, rhs, values, kind):
        """x with M x = rhs on free dofs and x = values on constrained ones.

        ``rhs`` and ``values`` have shape (dofs, dim); ``kind`` names the
        solve ('velocity', 'acceleration') for the CG warm start.
        """
        nd, dim = rhs.shape
        x = np.zeros((nd, dim))
        for key, (comps, red) in self.groups.items():
            b = red.restrict(rhs[:, comps])
            xr = np.zeros_like(b)
            xr[red.fixed] = values[red.kept[red.fixed]][:, comps]
            if self.consistent is None:
                xr[red.free] = b[red.free] / red.m_r[red.free, None]
            else:
                M_ff, M_fc, lu = self._reduced_matrix(key, red)
                bf = b[red.free] - M_fc @ xr[red.fixed]
                if lu is not None:
                    xr[red.free] = lu.solve(bf)
                else:
                    xr[red.free] = self._cg(M_ff, bf, red, comps, kind)
            x[:, comps] = red.prolong(xr, nd)
        return x

    def _cg(self, M_ff, bf, red, comps, kind):
        inv_diag = 1.0 / red.m_r[red.free]
        precond = spla.LinearOperator(M_ff.shape, matvec=lambda r: inv_diag * r.ravel())
        prev = self.warm.get(kind)
        out = np.empty_like(bf)
        for j, c in enumerate(comps):
            x0 = None
            if prev is not None and prev.shape[0] == self.lumped.size:
                x0 = prev[red.kept[red.free], c]
            iters = [0]

            def count(_):
                iters[0] += 1

            sol, info = spla.cg(M_ff, bf[:, j], x0=x0, rtol=self.cg_rtol, atol=0.0,
                                M=precond, maxiter=10 * M_ff.shape[0] + 100, callback=count)
            if info != 0:
                raise InvalidState(f"CG on the consistent mass did not converge ({info})")
            self.cg_iterations += iters[0]
            out[:, j] = sol
        return out

    def remember(self, kind, x):
        """Keep a solution as the warm start of the next step's CG."""
        if self.mass_solver == "cg" and self.consistent is not None:
            self.warm[kind] = x.copy()

    def shift_guess(self, kind, dx):
        """Add dx to the kept warm start of ``kind`` (if there is one)."""
        shift_guess(self.warm, kind, dx)

    def residual(self, x, rhs):
        """M x - rhs (for reactions on constrained dofs)."""
        if self.consistent is None:
            return self.lumped[:, None] * x - rhs
        return self.consistent @ x - rhs


def shift_guess(warm, kind, dx):
    """warm[kind] += dx (a new array; warm data may be shared with a
    checkpoint) when a warm start of dx's shape is kept."""
    prev = warm.get(kind)
    if prev is not None and prev.shape == dx.shape:
        warm[kind] = prev + dx
