"""The compressible neo-Hookean solid (finite strain)."""
import numpy as np

from ..errors import InvalidState
from ..validation import check_positive
from .base import Material, check_nu, det, incremental_deformation, lame_parameters
from .compiled import PointUpdate, PointWaveSpeed, max_point_wave_speed

__all__ = ["NeoHookean"]


class NeoHookean(Material):
    """Compressible neo-Hookean solid (finite strain, plane strain in 2D).

        F <- (I + dt L) F,   J = det F,   V = V0 J
        P = mu (F - F^-T) + lambda ln(J) F^-T,   sigma = P F^T / J
          = (mu (F F^T - I) + lambda ln(J) I) / J
        W = mu/2 (tr(F^T F) - dim) - mu ln J + lambda/2 (ln J)^2

    In 1D the uniaxial model of the S4 benchmark: lambda = 0, mu = E / 2
    whatever nu is, so P = mu (F - 1/F).
    """

    finite_strain = True
    point_update = PointUpdate("skfem_mpm.materials.laws:neo_hookean")
    point_wave_speed = PointWaveSpeed("skfem_mpm.materials.laws:neo_hookean_wave_speed")

    def __init__(self, E, nu=0.0):
        self.E = check_positive("E", E)
        self.nu = check_nu(nu)
        self.lam, self.mu = lame_parameters(self.E, self.nu)

    def __repr__(self):
        return f"NeoHookean(E={self.E:g}, nu={self.nu:g})"

    def parameters(self, dim):
        """(lambda, mu) used in ``dim`` dimensions."""
        return (0.0, self.E / 2) if dim == 1 else (self.lam, self.mu)

    def point_parameters(self, dim):
        return np.array(self.parameters(dim), dtype=np.float64)

    def cauchy_stress(self, F):
        """sigma(F) = (mu (F F^T - I) + lambda ln(J) I) / J."""
        dim = F.shape[-1]
        lam, mu = self.parameters(dim)
        J = det(F)
        B = F @ np.swapaxes(F, 1, 2)
        sigma = mu * (B - np.eye(dim))
        idx = np.arange(dim)
        sigma[:, idx, idx] += (lam * np.log(J))[:, None]
        return sigma / J[:, None, None]

    def first_piola(self, F):
        """P(F) = mu (F - F^-T) + lambda ln(J) F^-T."""
        dim = F.shape[-1]
        lam, mu = self.parameters(dim)
        J = det(F)
        FinvT = np.swapaxes(np.linalg.inv(F), 1, 2)
        return mu * (F - FinvT) + (lam * np.log(J))[:, None, None] * FinvT

    def update(self, particles, L, dt):
        F = incremental_deformation(L, dt) @ particles.F
        J = det(F)
        if np.any(J <= 0):
            bad = int(np.flatnonzero(J <= 0)[0])
            raise InvalidState(f"J = det F = {J[bad]:.3g} <= 0 at particle {bad}", particle=bad)
        return self.cauchy_stress(F), particles.V0 * J, F

    def wave_speed(self, particles):
        """Largest uniaxial tangent wave speed over principal stretches s:
        c^2 = (mu (1 + 1/s^2) + lambda (1 - ln J) / s^2) / rho0, by the
        compiled point wave speed
        (:func:`skfem_mpm.materials.laws.neo_hookean_wave_speed_law`)."""
        return max_point_wave_speed(self, particles)

    def strain_energy(self, particles):
        dim = particles.dim
        lam, mu = self.parameters(dim)
        F = particles.F
        J = det(F)
        lnJ = np.log(J)
        w = 0.5 * mu * (np.einsum("nij,nij->n", F, F) - dim) - mu * lnJ + 0.5 * lam * lnJ ** 2
        return float(np.sum(w * particles.V0))
