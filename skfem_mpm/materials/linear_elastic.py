"""Small-strain isotropic linear elasticity."""
import numpy as np

from ..validation import check_positive
from .base import Material, check_nu, det, incremental_deformation, lame_parameters
from .compiled import PointUpdate

__all__ = ["LinearElastic"]


class LinearElastic(Material):
    """Small-strain isotropic linear elasticity (hypoelastic rate form).

        d_eps = dt sym(L),   d_sigma = lambda tr(d_eps) I + 2 mu d_eps     (3D; 2D plane strain)
        d_sigma = E d_eps                                                 (1D, E alone)
        V <- det(I + dt L) V

    P-wave speed c = sqrt((lambda + 2 mu) / rho) in 2D and 3D, sqrt(E / rho) in 1D.
    """

    finite_strain = False
    point_update = PointUpdate("skfem_mpm.materials.laws:linear_elastic")

    def __init__(self, E, nu=0.0):
        self.E = check_positive("E", E)
        self.nu = check_nu(nu)
        self.lam, self.mu = lame_parameters(self.E, self.nu)

    def __repr__(self):
        return f"LinearElastic(E={self.E:g}, nu={self.nu:g})"

    def modulus(self, dim):
        """The P-wave modulus: E in 1D, lambda + 2 mu in 2D and 3D."""
        return self.E if dim == 1 else self.lam + 2 * self.mu

    def stress_rate(self, particles, L):
        """sigma' = lambda tr(D) I + 2 mu D (E D in 1D), D = sym(L)."""
        dim = L.shape[-1]
        D = 0.5 * (L + np.swapaxes(L, 1, 2))
        if dim == 1:
            return self.E * D
        trace = np.trace(D, axis1=1, axis2=2)
        rate = 2 * self.mu * D
        for d in range(dim):
            rate[:, d, d] += self.lam * trace
        return rate

    def update(self, particles, L, dt):
        J_inc = det(incremental_deformation(L, dt))
        return particles.stress + dt * self.stress_rate(particles, L), particles.V * J_inc, None

    def point_parameters(self, dim):
        """(E,) in 1D, (lambda, mu) in 2D and 3D."""
        return np.array([self.E]) if dim == 1 else np.array([self.lam, self.mu])

    def wave_speed(self, particles):
        rho = particles.m / particles.V
        return float(np.sqrt(self.modulus(particles.dim) / rho.min()))

    def strain_energy(self, particles):
        """sum_p (1/2) sigma : eps V_p with eps = C^-1 sigma (plane strain in
        2D; in 3D eps = (sigma - lambda / (3 lambda + 2 mu) tr(sigma) I) / (2 mu))."""
        s = particles.stress
        if particles.dim == 1:
            w = 0.5 * s[:, 0, 0] ** 2 / self.E
        elif particles.dim == 3:
            trace = np.trace(s, axis1=1, axis2=2)
            eps = s - (self.lam / (3 * self.lam + 2 * self.mu) * trace)[:, None, None] * np.eye(3)
            w = 0.5 * np.einsum("nij,nij->n", s, eps) / (2 * self.mu)
        else:
            E, nu = self.E, self.nu
            sxx, syy, sxy = s[:, 0, 0], s[:, 1, 1], s[:, 0, 1]
            exx = ((1 - nu ** 2) * sxx - nu * (1 + nu) * syy) / E
            eyy = ((1 - nu ** 2) * syy - nu * (1 + nu) * sxx) / E
            exy = sxy / (2 * self.mu)
            w = 0.5 * (sxx * exx + syy * eyy + 2 * sxy * exy)
        return float(np.sum(w * particles.V))
