"""Drucker-Prager plasticity fitted to Mohr-Coulomb."""
import numpy as np

from ..validation import check_choice
from .compiled import PointUpdate
from .plastic import ElastoPlastic

__all__ = ["DruckerPrager", "drucker_prager_fit"]

FITS = ("plane strain", "compression", "extension")


def drucker_prager_fit(friction_angle, dilation_angle, fit):
    """(eta, xi, eta_bar) of the Drucker-Prager cone fitted to Mohr-Coulomb
    (angles in degrees).

    "compression" (outer cone, through the compression corners) and
    "extension" (inner cone, through the extension corners), de Souza Neto,
    Peric, Owen 2008, eq. (6.121)-(6.122)::

        eta = 6 sin(phi) / (sqrt(3) (3 -+ sin(phi))),  xi = 6 cos(phi) / (sqrt(3) (3 -+ sin(phi)))
        eta_bar the same with psi

    "plane strain": the cone whose plane-strain limit state (d eps_zz^p = 0)
    is Mohr-Coulomb's, r + m sin(phi) = c cos(phi) with m, r the centre and
    radius of the in-plane Mohr circle. With eta_bar = 3 tan(psi) /
    sqrt(9 + 12 tan^2 psi), the limit state of the cone is
    r (3 - eta eta_bar) / sqrt(9 - 3 eta_bar^2) + eta m = xi c, so::

        eta = 3 sin(phi) / (sqrt(9 - 3 eta_bar^2) + eta_bar sin(phi))
        xi  = cos(phi) (3 - eta eta_bar) / sqrt(9 - 3 eta_bar^2)

    For associated flow (psi = phi) this is the textbook plane-strain fit
    eta = 3 tan(phi) / sqrt(9 + 12 tan^2 phi), xi = 3 / sqrt(9 + 12 tan^2 phi)
    (de Souza Neto et al. eq. (6.123)); for psi = 0 it is eta = sin(phi),
    xi = cos(phi). (The derivation: eps_zz^p = 0 gives
    s_zz / (2 sqrt(J2)) = -eta_bar / 3, hence sigma_zz - m = -eta_bar r /
    sqrt(1 - eta_bar^2 / 3) and sqrt(J2) = r sqrt(3 / (3 - eta_bar^2)).)
    """
    check_choice("fit", fit, FITS)
    sp, cp = np.sin(np.radians(friction_angle)), np.cos(np.radians(friction_angle))
    spsi = np.sin(np.radians(dilation_angle))
    if fit == "plane strain":
        t = np.tan(np.radians(dilation_angle))
        eta_bar = 3 * t / np.sqrt(9 + 12 * t * t)
        root = np.sqrt(9 - 3 * eta_bar ** 2)
        eta = 3 * sp / (root + eta_bar * sp)
        xi = cp * (3 - eta * eta_bar) / root
        return float(eta), float(xi), float(eta_bar)
    sign = -1.0 if fit == "compression" else 1.0
    k = 6 / np.sqrt(3)
    return (float(k * sp / (3 + sign * sp)), float(k * cp / (3 + sign * sp)),
            float(k * spsi / (3 + sign * spsi)))


class DruckerPrager(ElastoPlastic):
    """Small-strain Drucker-Prager plasticity (perfectly plastic), 2D plane
    strain and 3D, angles in degrees, tension positive.

        f   = sqrt(J2) + eta p - xi c,     p = tr(sigma) / 3
        g   = sqrt(J2) + eta_bar p         (the plastic potential)

    with (eta, xi, eta_bar) fitted to Mohr-Coulomb by ``fit``
    (:func:`drucker_prager_fit`: "plane strain", "compression" or
    "extension"). Return mapping (de Souza Neto, Peric, Owen 2008, Box 8.8,
    perfect plasticity), exact for the discrete problem::

        d_gamma = f_t / (mu + K eta eta_bar)
        smooth cone (if sqrt(J2_t) >= mu d_gamma):
            s = (1 - mu d_gamma / sqrt(J2_t)) s_t,   p = p_t - K eta_bar d_gamma
        apex otherwise:  s = 0,  p = xi c / eta

    The trial stress, sigma_zz, ``large_deformation`` and the state are
    those of :mod:`.plastic`.
    """

    point_update = PointUpdate("skfem_mpm.materials.plastic_laws:drucker_prager")

    def __init__(self, E, nu, friction_angle, cohesion, dilation_angle=0.0,
                 fit="plane strain", large_deformation=False):
        self._elastic(E, nu, large_deformation)
        self._frictional(friction_angle, cohesion, dilation_angle)
        self.fit = fit
        self.eta, self.xi, self.eta_bar = drucker_prager_fit(
            self.friction_angle, self.dilation_angle, fit)

    def __repr__(self):
        return (f"DruckerPrager(E={self.E:g}, nu={self.nu:g}, "
                f"friction_angle={self.friction_angle:g}, cohesion={self.cohesion:g}, "
                f"dilation_angle={self.dilation_angle:g}, fit={self.fit!r})")

    def point_parameters(self, dim):
        """(lambda, mu, rotate, eta, xi c, eta_bar, K)."""
        return np.array(self.elastic_parameters()
                        + [self.eta, self.xi * self.cohesion, self.eta_bar, self.K])

    def return_map(self, trial, state):
        p_t = np.trace(trial, axis1=1, axis2=2) / 3
        s_t = trial - p_t[:, None, None] * np.eye(3)
        root = np.sqrt(0.5 * np.einsum("nij,nij->n", s_t, s_t))
        xc = self.xi * self.cohesion
        f = root + self.eta * p_t - xc
        gamma = f / (self.mu + self.K * self.eta * self.eta_bar)
        cone = (f > 0) & (root - self.mu * gamma >= 0)
        apex = (f > 0) & ~cone
        scale = np.where(cone, 1 - self.mu * gamma / np.where(root > 0, root, 1.0), 1.0)
        scale = np.where(apex, 0.0, scale)
        p = np.where(cone, p_t - self.K * self.eta_bar * gamma, p_t)
        if self.eta > 0:
            p = np.where(apex, xc / self.eta, p)
        return s_t * scale[:, None, None] + p[:, None, None] * np.eye(3)
