"""Von Mises (J2) plasticity with linear isotropic hardening."""
import numpy as np

from ..validation import check_positive
from .compiled import PointUpdate
from .plastic import ElastoPlastic

__all__ = ["VonMises"]


class VonMises(ElastoPlastic):
    """Small-strain von Mises plasticity with linear isotropic hardening
    (undrained clay: Tresca-like in plane strain with yield_stress =
    sqrt(3) c_u), 2D plane strain and 3D. Tension positive.

        f = q - (sigma_y + H eps_p),   q = sqrt(3 J2) = sqrt(3/2) |s|

    Radial return (de Souza Neto, Peric, Owen 2008, Box 7.3; Simo and
    Hughes 1998, Box 3.2), exact for the discrete problem::

        q_t = sqrt(3/2) |s_t|,  f_t = q_t - (sigma_y + H eps_p)
        f_t <= 0:  sigma = sigma_t
        else:      d_gamma = f_t / (3 mu + H),  s = (1 - 3 mu d_gamma / q_t) s_t,
                   p = p_t,  eps_p += d_gamma

    (the plastic-strain measure of :mod:`.plastic` equals d_gamma here).
    The trial stress, sigma_zz, ``large_deformation`` (Hughes-Winget
    objective rotation) and the state are those of :mod:`.plastic`.
    In plane strain the limit state has s_zz = 0 and
    |sigma_yy - sigma_xx| = 2 sigma_y / sqrt(3) (= 2 c_u).
    """

    point_update = PointUpdate("skfem_mpm.materials.plastic_laws:von_mises")

    def __init__(self, E, nu, yield_stress, hardening=0.0, large_deformation=False):
        self._elastic(E, nu, large_deformation)
        self.yield_stress = check_positive("yield_stress", yield_stress)
        self.hardening = check_positive("hardening", hardening, allow_zero=True)

    def __repr__(self):
        return (f"VonMises(E={self.E:g}, nu={self.nu:g}, yield_stress={self.yield_stress:g}, "
                f"hardening={self.hardening:g})")

    def point_parameters(self, dim):
        """(lambda, mu, rotate, sigma_y, H)."""
        return np.array(self.elastic_parameters() + [self.yield_stress, self.hardening])

    def return_map(self, trial, state):
        mean = np.trace(trial, axis1=1, axis2=2) / 3
        s = trial - mean[:, None, None] * np.eye(3)
        q = np.sqrt(1.5 * np.einsum("nij,nij->n", s, s))
        f = q - (self.yield_stress + self.hardening * state["plastic_strain"])
        gamma = np.where(f > 0, f / (3 * self.mu + self.hardening), 0.0)
        scale = np.where(f > 0, 1 - 3 * self.mu * gamma / np.where(q > 0, q, 1.0), 1.0)
        return s * scale[:, None, None] + mean[:, None, None] * np.eye(3)
