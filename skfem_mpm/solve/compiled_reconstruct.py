"""Reconstructed particles-to-grid on the compiled executor.

The reference step (:func:`skfem_mpm.solve.steps.reconstructed_grid_data`)
integrates the reconstructed per-volume fields h = [rho, rho v, sigma,
rho b] with the Gauss rule over the body (points x_g, weights w_g):

    m_i = sum_g w_g rho_h(x_g) N_i(x_g),    P_i = sum_g w_g (rho v)_h(x_g) N_i(x_g),
    M_ij = sum_g w_g rho_h(x_g) N_i(x_g) N_j(x_g),
    f_i = - sum_g w_g sigma_h(x_g) grad N_i(x_g) + sum_g w_g (rho b)_h(x_g) N_i(x_g)

(Tielen et al. 2017; the module docstring of :mod:`skfem_mpm.reconstruct`).
These are the particle sums of p2g and of the consistent mass with the
Gauss points as "quadrature particles" of mass m_g = w_g rho_h, velocity
(rho v)_h / rho_h, volume w_g, stress sigma_h and force w_g (rho b)_h, so
the generated scatter kernels and the stencil assembly compute them. The
MUSL re-projection P_i = sum_g w_g (rho v^new)_h N_i reconstructs the
updated particle momentum with the same rule (g2p2g on points of mass w_g).

The rule: in 1D the body's pieces (:func:`skfem_mpm.kernels.gauss_rule.gauss_rule_1d`),
in 2D the part of each cell holding particles that the body covers
(:func:`skfem_mpm.kernels.gauss_rule.body_boxes_2d`,
:func:`skfem_mpm.kernels.gauss_rule.gauss_rule_cells`), p + 2 points per
axis, both bit for bit those of :func:`skfem_mpm.reconstruct.integration_rule`.
The reconstructions: the particle-knot spline in 1D
(:mod:`skfem_mpm.kernels.spline_1d`) and the published TLS (default
options) in 1D and 2D (:mod:`skfem_mpm.kernels.tls`). Which run here is
:func:`unsupported`'s answer; the rest stays on the reference executor.
"""
import numpy as np

from ..kernels.gauss_rule import (
    body_boxes_2d,
    gauss_rule_1d,
    gauss_rule_cells,
    locate_cells,
)
from ..kernels.spline_1d import not_a_knot_spline
from ..kernels.tls import tls_reconstruct

TLS_DEFAULTS = {"degree": 2, "neighbour_weight": 0.0}

__all__ = ["CompiledReconstruction", "unsupported"]


def unsupported(method, dim):
    """None when the compiled executor runs ``method``'s reconstruction in
    ``dim`` dimensions, else the reason it does not."""
    recon = method.reconstruction
    if callable(recon):
        return "reconstruction: a user's callable"
    options = dict(method.reconstruction_options)
    if recon == "spline" and dim == 1:
        if options.get("knots", "particles") != "particles":
            return "reconstruction spline with knots='grid'"
        if set(options) - {"knots", "penalty"}:
            return "reconstruction options"
        return None
    if recon == "tls":
        for name, value in options.items():
            if name not in TLS_DEFAULTS or value != TLS_DEFAULTS[name]:
                return f"reconstruction tls with {name}={value!r} (compiled: the published default)"
        return None
    return f"reconstruction {recon} in {dim}D"


class QuadraturePoints:
    """Gauss points as the particle record of the scatter kernels
    (x, v, u, m, V, stress: see :data:`skfem_mpm.kernels.records.ParticleArrays`)."""

    def __init__(self, x, v, m, V, stress):
        self.x, self.v, self.m, self.V, self.stress = x, v, m, V, stress
        self.u = v  # not read by p2g or g2p2g


class Rule:
    """The step's Gauss rule: points ``x``, weights ``w``, their cells
    ``cell``, the particles' cells ``pcell`` (TLS) and what the 1D spline
    needs (sorted order and piece bounds; None in 2D)."""

    def __init__(self, x, w, cell, pcell=None, order=None, piece_particles=None,
                 piece_points=None):
        self.x, self.w, self.cell, self.pcell = x, w, cell, pcell
        self.order, self.piece_particles, self.piece_points = order, piece_particles, piece_points


class CompiledReconstruction:
    """The Gauss rule, the reconstruction and the Gauss-side integration of
    one run on a :class:`skfem_mpm.kernels.mpm.Kernels` set."""

    def __init__(self, state, kernels):
        grid = state.grid
        self.kernels = kernels
        self.dim = grid.dim
        self.name = state.method.reconstruction
        ref, wref = np.polynomial.legendre.leggauss(grid.degree + 2)
        self.ref, self.wref = 0.5 * (ref + 1), 0.5 * wref
        axes = [np.ascontiguousarray(b, dtype=np.float64) for b in grid.breakpoints]
        self.breaks = axes[0]
        self.breaks1 = axes[-1]  # unused in 1D
        self.uniform = (bool(grid._uniform[0]), bool(grid._uniform[-1]))
        self.gap = float(grid.cell_sizes[0].max())
        self._zero_a = np.zeros((grid.ndofs, grid.dim))

    def rule(self, p):
        pcell = None
        if self.name == "tls" or self.dim == 2:
            pcell = locate_cells(p.x, self.breaks, self.breaks1, *self.uniform)
        if self.dim == 1:
            order, pp, pg, xg, wg, cell = gauss_rule_1d(p.x[:, 0], p.V, self.gap, self.breaks,
                                                        self.ref, self.wref)
            return Rule(xg[:, None], wg, cell, pcell, order, pp, pg)
        lo, hi = body_boxes_2d(p.x, p.V, pcell, self.breaks, self.breaks1)
        xg, wg, cell = gauss_rule_cells(pcell, lo, hi, self.ref, self.wref)
        return Rule(xg, wg, cell, pcell)

    def reconstruct(self, p, values, rule):
        """The reconstructed ``values`` (n, k) at the rule's points (ng, k)."""
        out = np.empty((rule.x.shape[0], values.shape[1]))
        values = np.ascontiguousarray(values)
        if self.name == "tls":
            tls_reconstruct(p.x, p.V, values, rule.pcell, rule.x, rule.w, rule.cell,
                            self.breaks, self.breaks1, out)
            return out
        not_a_knot_spline(p.x[:, 0], values, rule.order, rule.piece_particles,
                          rule.piece_points, rule.x[:, 0], out)
        return out

    def to_grid(self, state, p, volume):
        """(lumped mass, momentum, force, consistent stencil or None, the
        projection data): ``volume`` the particle volume forces (n, dim)
        other than uniform accelerations, or None."""
        k, dim = self.kernels, self.dim
        with state.timer("reconstruct"):
            rule = self.rule(p)
            rho = p.m / p.V
            fields = [rho[:, None], rho[:, None] * p.v, p.stress.reshape(p.n, dim * dim)]
            if volume is not None:
                fields.append(volume / p.V[:, None])
            h = self.reconstruct(p, np.concatenate(fields, axis=1), rule)
        with state.timer("p2g"):
            w = rule.w
            rho_h = h[:, 0]
            ng = rho_h.shape[0]
            positive = bool(np.all(rho_h != 0.0))
            v = h[:, 1:1 + dim] / rho_h[:, None] if positive else np.zeros((ng, dim))
            stress = np.ascontiguousarray(h[:, 1 + dim:1 + dim + dim * dim]).reshape(ng, dim, dim)
            points = QuadraturePoints(rule.x, v, w * rho_h, w, stress)
            fext = None if volume is None else w[:, None] * h[:, 1 + dim + dim * dim:]
            mass, momentum, force = k.p2g(points, fext)
            if not positive:  # rho_h = 0 somewhere: the momentum from points of mass w_g
                momentum = self._momentum(rule, np.ascontiguousarray(h[:, 1:1 + dim])).copy()
        stencil = None
        if state.method.needs_consistent_mass:
            with state.timer("mass_matrix"):
                stencil = k.consistent_stencil(points)
        return mass, momentum, force, stencil, (rule, rho)

    def _momentum(self, rule, momentum_density):
        """sum_g w_g (rho v)_h(x_g) N_i(x_g) by g2p2g (a = 0) on points of mass w_g."""
        ng = rule.w.shape[0]
        points = QuadraturePoints(rule.x, momentum_density, rule.w, rule.w,
                                  np.zeros((ng, self.dim, self.dim)))
        scratch = self.kernels.scratch("projected_v", (ng, self.dim))
        return self.kernels.g2p2g(points, self._zero_a, 0.0, scratch)

    def project(self, state, p, v_new, projection):
        """MUSL: the grid momentum of the reconstructed rho v^new."""
        rule, rho = projection
        with state.timer("reconstruct"):
            h = self.reconstruct(p, rho[:, None] * v_new, rule)
        with state.timer("p2g"):
            return self._momentum(rule, h)
