"""Reconstruction on a compiled run: part of the source of the generated loop
modules (not imported as a module; see
:mod:`skfem_mpm.solve.compiled_loop_ops`).

The compiled executor's reconstructed particles-to-grid
(:mod:`skfem_mpm.solve.compiled_reconstruct`, whose docstring gives the
formulas), in the same order on the same kernels, so that a run gives the
same bits on either path. Covered: the particle-knot spline in 1D.

    reconstruct_points   the step's Gauss rule over the body (x_g, w_g:
                         kernels.gauss_rule.gauss_rule_1d), the fit of the
                         per-volume fields h = [rho, rho v, sigma] at its
                         points (kernels.spline_1d.not_a_knot_spline), and
                         the points as "quadrature particles" of mass
                         w_g rho_h, velocity (rho v)_h / rho_h, volume w_g and
                         stress sigma_h, which the p2g kernel and the
                         consistent-mass assembly integrate
    project_points       MUSL: the fit of rho v^new at the same points, as
                         points of mass w_g and velocity (rho v^new)_h (the
                         g2p2g kernel with a = 0 integrates their momentum)

A step whose fitted density is 0 at a point (the executor then integrates
the momentum apart) stops the loop: the executor takes it.
"""


@structref.register
class ReconstructionType(types.StructRef):
    def preprocess_fields(self, fields):
        return tuple((name, types.unliteral(t)) for name, t in fields)


ReconstructionType.__name__ = ReconstructionType.__qualname__ = \
    f"ReconstructionType_{VARIANT}"
globals()[ReconstructionType.__name__] = ReconstructionType


RECONSTRUCTION_FIELDS = (
    # the rule: Gauss-Legendre points and weights on [0, 1], the largest
    # gap inside one piece of the body (a cell), the breakpoints
    "ref", "wref", "gap", "breaks",
    # per particle: the fitted fields [rho, rho v, sigma] (n, 1 + dim + dim^2), rho
    "values", "rho",
    # the step's rule (sorted order, pieces, points) and the fit at its points
    "order", "piece_particles", "piece_points", "xg", "fit",
    # the points as quadrature particles (x, v, m, V, stress)
    "xq", "vq", "mq", "Vq", "sq",
    # the MUSL projection: rho v^new per particle, its fit at the points,
    # zero stresses, the g2p2g kernel's (unused) point velocities
    "momentum_values", "momentum_fit", "no_stress", "point_velocities",
)


class Reconstruction(structref.StructRefProxy):
    """The reconstruction data of a compiled run."""

    def __new__(cls, *fields):
        return structref.StructRefProxy.__new__(cls, *fields)


structref.define_proxy(Reconstruction, ReconstructionType, list(RECONSTRUCTION_FIELDS))


@njit(cache=True)
def new_reconstruction(*fields):
    """A Reconstruction with ``fields`` in the order of RECONSTRUCTION_FIELDS."""
    return Reconstruction(*fields)


@njit(cache=True)
def reconstruct_points(rc, x, v, m, V, stress):
    """The step's rule and the quadrature points of the fitted fields (see
    the module); False when the fitted density is 0 at a point."""
    n, dim = x.shape
    values = rc.values
    for i in range(n):
        rho = m[i] / V[i]
        rc.rho[i] = rho
        values[i, 0] = rho
        for c in range(dim):
            values[i, 1 + c] = rho * v[i, c]
        for a in range(dim):
            for b in range(dim):
                values[i, 1 + dim + a * dim + b] = stress[i, a, b]
    positions = x.reshape(n)  # 1D: x is (n, 1)
    order, pieces, points, xg, wg, _ = GAUSS_RULE_1D(positions, V, rc.gap, rc.breaks, rc.ref,
                                                     rc.wref)
    ng = xg.shape[0]
    fit = np.empty((ng, values.shape[1]))
    NOT_A_KNOT_SPLINE(positions, values, order, pieces, points, xg, fit)
    rc.order = order
    rc.piece_particles = pieces
    rc.piece_points = points
    rc.xg = xg
    rc.fit = fit
    rc.xq = xg.reshape((ng, 1))
    rc.Vq = wg
    rc.vq = np.empty((ng, dim))
    rc.mq = np.empty(ng)
    rc.sq = np.empty((ng, dim, dim))
    rc.momentum_fit = np.empty((ng, dim))
    rc.no_stress = np.zeros((ng, dim, dim))
    rc.point_velocities = np.empty((ng, dim))
    for g in range(ng):
        if fit[g, 0] == 0.0:
            return False
    for g in range(ng):
        rho = fit[g, 0]
        rc.mq[g] = wg[g] * rho
        for c in range(dim):
            rc.vq[g, c] = fit[g, 1 + c] / rho
        for a in range(dim):
            for b in range(dim):
                rc.sq[g, a, b] = fit[g, 1 + dim + a * dim + b]
    return True


@njit(cache=True)
def project_points(rc, x, v_new):
    """MUSL: the fit of rho v^new at the step's points (rc.momentum_fit)."""
    n, dim = v_new.shape
    for i in range(n):
        for c in range(dim):
            rc.momentum_values[i, c] = rc.rho[i] * v_new[i, c]
    NOT_A_KNOT_SPLINE(x.reshape(n), rc.momentum_values, rc.order, rc.piece_particles,
                      rc.piece_points, rc.xg, rc.momentum_fit)
