"""Constitutive models: each a small object whose ``update`` is one vectorised
function of the particle arrays and the velocity gradient.

A material has

    finite_strain           True if it needs the deformation gradient F
    update(p, L, dt)        new (stress, V, F) from the velocity gradient
                            L[p, i, j] = dv_i/dx_j over the step dt
    wave_speed(p)           the largest P-wave speed of the particles, for
                            the critical time step
    strain_energy(p)        total stored energy sum_p W_p V0_p (or V_p)
    check_dim(dim)          raise for dimensions it does not model

Write your own by following the same shape (see examples/custom_material.py).
2D is plane strain throughout; 1D is uniaxial strain.
"""
import numpy as np

from .errors import InvalidState
from .validation import check_positive

__all__ = ["LinearElastic", "NeoHookean", "Material", "lame_parameters"]


def lame_parameters(E, nu):
    """Lame's lambda and mu: lambda = E nu / ((1 + nu)(1 - 2 nu)), mu = E / (2 (1 + nu))."""
    return E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))


def _check_nu(nu):
    if isinstance(nu, bool) or not isinstance(nu, (int, float, np.floating, np.integer)):
        raise ValueError(f"nu must be a real number in (-1, 0.5), got {nu!r}")
    nu = float(nu)
    if not -1.0 < nu < 0.5:
        raise ValueError(f"nu must lie in (-1, 0.5), got {nu}")
    return nu


def incremental_deformation(L, dt):
    """I + dt L, the deformation gradient of one step."""
    dim = L.shape[-1]
    return np.eye(dim) + dt * L


def det(A):
    """Determinants of a stack of 1x1 or 2x2 matrices."""
    if A.shape[-1] == 1:
        return A[:, 0, 0].copy()
    return A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0]


class Material:
    """Base class: the interface every material follows."""

    finite_strain = False

    def check_dim(self, dim):
        if dim not in (1, 2):
            raise ValueError(f"{type(self).__name__} models 1D and 2D (plane strain), got dim={dim}")

    def update(self, particles, L, dt):  # pragma: no cover - interface
        raise NotImplementedError

    def wave_speed(self, particles):  # pragma: no cover - interface
        raise NotImplementedError

    def strain_energy(self, particles):  # pragma: no cover - interface
        raise NotImplementedError


class LinearElastic(Material):
    """Small-strain isotropic linear elasticity (hypoelastic rate form).

        d_eps = dt sym(L),   d_sigma = lambda tr(d_eps) I + 2 mu d_eps     (2D, plane strain)
        d_sigma = E d_eps                                                 (1D, E alone)
        V <- det(I + dt L) V

    P-wave speed c = sqrt((lambda + 2 mu) / rho) in 2D, sqrt(E / rho) in 1D.
    """

    finite_strain = False

    def __init__(self, E, nu=0.0):
        self.E = check_positive("E", E)
        self.nu = _check_nu(nu)
        self.lam, self.mu = lame_parameters(self.E, self.nu)

    def __repr__(self):
        return f"LinearElastic(E={self.E:g}, nu={self.nu:g})"

    def modulus(self, dim):
        """The P-wave modulus: E in 1D, lambda + 2 mu in 2D."""
        return self.E if dim == 1 else self.lam + 2 * self.mu

    def update(self, particles, L, dt):
        dim = L.shape[-1]
        d_eps = 0.5 * dt * (L + np.swapaxes(L, 1, 2))
        if dim == 1:
            d_sigma = self.E * d_eps
        else:
            trace = d_eps[:, 0, 0] + d_eps[:, 1, 1]
            d_sigma = 2 * self.mu * d_eps
            d_sigma[:, 0, 0] += self.lam * trace
            d_sigma[:, 1, 1] += self.lam * trace
        J_inc = det(incremental_deformation(L, dt))
        return particles.stress + d_sigma, particles.V * J_inc, None

    def wave_speed(self, particles):
        rho = particles.m / particles.V
        return float(np.sqrt(self.modulus(particles.dim) / rho.min()))

    def strain_energy(self, particles):
        """sum_p (1/2) sigma : eps V_p with eps = C^-1 sigma (plane strain)."""
        s = particles.stress
        if particles.dim == 1:
            w = 0.5 * s[:, 0, 0] ** 2 / self.E
        else:
            E, nu = self.E, self.nu
            sxx, syy, sxy = s[:, 0, 0], s[:, 1, 1], s[:, 0, 1]
            exx = ((1 - nu ** 2) * sxx - nu * (1 + nu) * syy) / E
            eyy = ((1 - nu ** 2) * syy - nu * (1 + nu) * sxx) / E
            exy = sxy / (2 * self.mu)
            w = 0.5 * (sxx * exx + syy * eyy + 2 * sxy * exy)
        return float(np.sum(w * particles.V))


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

    def __init__(self, E, nu=0.0):
        self.E = check_positive("E", E)
        self.nu = _check_nu(nu)
        self.lam, self.mu = lame_parameters(self.E, self.nu)

    def __repr__(self):
        return f"NeoHookean(E={self.E:g}, nu={self.nu:g})"

    def parameters(self, dim):
        """(lambda, mu) used in ``dim`` dimensions."""
        return (0.0, self.E / 2) if dim == 1 else (self.lam, self.mu)

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
        c^2 = (mu (1 + 1/s^2) + lambda (1 - ln J) / s^2) / rho0."""
        dim = particles.dim
        lam, mu = self.parameters(dim)
        F = particles.F
        if F is None:
            F = np.broadcast_to(np.eye(dim), (particles.n, dim, dim))
        J = det(F)
        C = np.swapaxes(F, 1, 2) @ F
        stretch = np.sqrt(np.linalg.eigvalsh(C))  # (n, dim)
        tangent = mu * (1 + 1 / stretch ** 2) + (lam * (1 - np.log(J)))[:, None] / stretch ** 2
        rho0 = particles.m / particles.V0
        return float(np.sqrt((tangent.max(axis=1) / rho0).max()))

    def strain_energy(self, particles):
        dim = particles.dim
        lam, mu = self.parameters(dim)
        F = particles.F
        J = det(F)
        lnJ = np.log(J)
        w = 0.5 * mu * (np.einsum("nij,nij->n", F, F) - dim) - mu * lnJ + 0.5 * lam * lnJ ** 2
        return float(np.sum(w * particles.V0))
