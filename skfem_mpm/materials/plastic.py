"""What the elastoplastic materials share (:class:`MohrCoulomb`,
:class:`DruckerPrager`, :class:`VonMises`): the elastic trial stress, the
objective rotation, the plane-strain sigma_zz, the accumulated plastic
strain and the kinematics. Each material adds only its return mapping.

Tension is positive; stresses are handled as full 3x3 tensors. In 2D (plane
strain) the out-of-plane stress sigma_zz is a state field
(``particles.state["sigma_zz"]``): eps_zz = 0, so its trial value is
sigma_zz + lambda tr(d_eps) and the return mapping moves it like any other
component.

One step (Simo and Hughes, "Computational Inelasticity", 1998, sec. 3.3 and
8.3; de Souza Neto, Peric and Owen, "Computational Methods for Plasticity",
2008, ch. 7-8)::

    d_eps   = dt sym(L)                                 (3x3; zz row zero in 2D)
    sigma_R = Q sigma_n Q^T                             (large_deformation only)
    sigma_t = sigma_R + lambda tr(d_eps) I + 2 mu d_eps  the elastic trial
    sigma   = return_map(sigma_t)                       the material's own
    d_eps_p = C^-1 : (sigma_t - sigma)
            = dev(sigma_t - sigma) / (2 mu) + tr(sigma_t - sigma) I / (9 K)
    eps_p  += sqrt(2/3 d_eps_p : d_eps_p)               "plastic_strain"

Objective update (``large_deformation=True``): Q is the Hughes-Winget
incremental rotation (Hughes and Winget 1980, Int. J. Numer. Meth. Eng. 15,
1862-1867), the Cayley transform of the step's spin W = dt skew(L),

    Q = (I - W/2)^-1 (I + W/2) = I + 2 / (1 + |a|^2) (A + A^2),  A = W/2,

with a the axial vector of A. It integrates the Jaumann rate
sigma' = W sigma - sigma W to second order and, unlike the forward-Euler
Jaumann update sigma + dt (W sigma - sigma W), Q is exactly orthogonal: a
rigid rotation leaves every invariant of the stress (and so the yield
function and the return map) unchanged to round-off. It is chosen over a
logarithmic-strain (multiplicative) formulation because it keeps the
additive small-strain return maps as they are, costs a few dozen flops a
particle, and its error at the elastic strains of soils (< 1e-3) is far
below that of the plastic flow. The material is then finite strain (the
scene carries F and V = V0 det F). Without it (the default) the update is
the small-strain one (no rotation; V <- V det(I + dt L)).
"""
import numpy as np

from ..validation import check_positive
from .base import Material, check_nu, det, incremental_deformation, lame_parameters

__all__ = ["ElastoPlastic", "rotation", "trial_stress", "plastic_strain_increment",
           "principal", "from_principal"]


def rotation(L, dt):
    """The Hughes-Winget rotation Q (n, 3, 3) of velocity gradients L
    (n, dim, dim): Q = I + 2 / (1 + |a|^2) (A + A^2), A = dt skew(L) / 2."""
    n, dim = L.shape[0], L.shape[-1]
    A = np.zeros((n, 3, 3))
    A[:, :dim, :dim] = 0.25 * dt * (L - np.swapaxes(L, 1, 2))
    a2 = A[:, 0, 1] ** 2 + A[:, 0, 2] ** 2 + A[:, 1, 2] ** 2
    return np.eye(3) + (2.0 / (1.0 + a2))[:, None, None] * (A + A @ A)


def trial_stress(stress, sigma_zz, L, dt, lam, mu, rotate):
    """The elastic trial stress (n, 3, 3) from the stress (n, dim, dim),
    sigma_zz (n,) in 2D (ignored in 3D), L and dt (module docstring)."""
    n, dim = stress.shape[0], stress.shape[-1]
    s = np.zeros((n, 3, 3))
    s[:, :dim, :dim] = stress
    if dim == 2:
        s[:, 2, 2] = sigma_zz
    if rotate:
        Q = rotation(L, dt)
        s = Q @ s @ np.swapaxes(Q, 1, 2)
    d_eps = np.zeros((n, 3, 3))
    d_eps[:, :dim, :dim] = 0.5 * dt * (L + np.swapaxes(L, 1, 2))
    trace = np.trace(d_eps, axis1=1, axis2=2)
    return s + lam * trace[:, None, None] * np.eye(3) + 2 * mu * d_eps


def plastic_strain_increment(trial, stress, lam, mu):
    """sqrt(2/3 d_eps_p : d_eps_p), d_eps_p = C^-1 : (trial - stress)."""
    K = lam + 2 * mu / 3
    d = trial - stress
    trace = np.trace(d, axis1=1, axis2=2)
    eps = (d - (trace / 3)[:, None, None] * np.eye(3)) / (2 * mu) \
        + (trace / (9 * K))[:, None, None] * np.eye(3)
    return np.sqrt(2.0 / 3.0 * np.einsum("nij,nij->n", eps, eps))


def principal(stress):
    """Principal stresses in descending order s1 >= s2 >= s3 (n, 3) and the
    matching unit eigenvectors as columns (n, 3, 3)."""
    values, vectors = np.linalg.eigh(stress)
    return values[:, ::-1], vectors[:, :, ::-1]


def from_principal(values, vectors):
    """sum_i values_i n_i n_i^T."""
    return np.einsum("nik,nk,njk->nij", vectors, values, vectors)


def check_angle(name, value, upper=90.0):
    """An angle in degrees in [0, upper)."""
    value = check_positive(name, value, allow_zero=True)
    if not value < upper:
        raise ValueError(f"{name} must be an angle in degrees in [0, {upper:g}), got {value}")
    return value


class ElastoPlastic(Material):
    """Base of the small-strain elastoplastic materials: isotropic linear
    elasticity (E, nu), a return mapping given by the subclass
    (``return_map(trial, state) -> stress``, both (n, 3, 3), ``state`` the
    particles' state before the step), and the module's
    trial stress, objective rotation and plastic-strain measure. 2D (plane
    strain) and 3D."""

    finite_strain = False

    def _elastic(self, E, nu, large_deformation):
        self.E = check_positive("E", E)
        self.nu = check_nu(nu)
        self.lam, self.mu = lame_parameters(self.E, self.nu)
        self.K = self.lam + 2 * self.mu / 3
        if not isinstance(large_deformation, (bool, np.bool_)):
            raise ValueError(f"large_deformation must be True or False, "
                             f"got {large_deformation!r}")
        self.large_deformation = bool(large_deformation)
        self.finite_strain = self.large_deformation

    def _frictional(self, friction_angle, cohesion, dilation_angle):
        """The Mohr-Coulomb parameters (angles in degrees, 0 <= psi <= phi < 90,
        c >= 0), shared by MohrCoulomb and DruckerPrager."""
        self.friction_angle = check_angle("friction_angle", friction_angle)
        self.cohesion = check_positive("cohesion", cohesion, allow_zero=True)
        self.dilation_angle = check_angle("dilation_angle", dilation_angle)
        if self.dilation_angle > self.friction_angle:
            raise ValueError(f"dilation_angle must not exceed friction_angle "
                             f"({self.friction_angle:g}), got {self.dilation_angle:g}")

    def check_dim(self, dim):
        if dim not in (2, 3):
            raise ValueError(f"{type(self).__name__} models 2D (plane strain) and 3D, "
                             f"got dim={dim}")

    def state_fields(self, dim):
        """The accumulated plastic strain; in 2D also sigma_zz (plane strain)."""
        if dim == 2:
            return {"plastic_strain": ((), 0.0), "sigma_zz": ((), 0.0)}
        return {"plastic_strain": ((), 0.0)}

    def elastic_parameters(self):
        """(lambda, mu, 1.0 if large_deformation else 0.0): the first three
        entries of every elastoplastic ``point_parameters``."""
        return [self.lam, self.mu, 1.0 if self.large_deformation else 0.0]

    def return_map(self, trial, state):  # pragma: no cover - interface
        raise NotImplementedError

    def stress_update(self, stress, state, L, dt):
        """(new stress (n, dim, dim), new state dict) of one step; the law
        without the kinematics (what the element tests drive)."""
        dim = stress.shape[-1]
        sigma_zz = state.get("sigma_zz") if dim == 2 else None
        trial = trial_stress(stress, sigma_zz, L, dt, self.lam, self.mu,
                             self.large_deformation)
        new = self.return_map(trial, state)
        out = {"plastic_strain": state["plastic_strain"]
               + plastic_strain_increment(trial, new, self.lam, self.mu)}
        if dim == 2:
            out["sigma_zz"] = new[:, 2, 2].copy()
        return new[:, :dim, :dim].copy(), out

    def update(self, particles, L, dt):
        stress, state = self.stress_update(particles.stress, particles.state, L, dt)
        A = incremental_deformation(L, dt)
        if self.finite_strain:
            F = A @ particles.F
            return stress, particles.V0 * det(F), F, state
        return stress, particles.V * det(A), None, state

    def wave_speed(self, particles):
        """The elastic P-wave speed sqrt((lambda + 2 mu) / rho)."""
        rho = particles.m / particles.V
        return float(np.sqrt((self.lam + 2 * self.mu) / rho.min()))

    def strain_energy(self, particles):
        """Stored elastic energy sum_p (s:s / (4 mu) + tr(sigma)^2 / (18 K)) V_p
        (sigma with sigma_zz in 2D; the plastic work is dissipated)."""
        s = particles.stress
        dim = particles.dim
        full = np.zeros((particles.n, 3, 3))
        full[:, :dim, :dim] = s
        if dim == 2:
            full[:, 2, 2] = particles.state["sigma_zz"]
        trace = np.trace(full, axis1=1, axis2=2)
        dev = full - (trace / 3)[:, None, None] * np.eye(3)
        w = np.einsum("nij,nij->n", dev, dev) / (4 * self.mu) + trace ** 2 / (18 * self.K)
        return float(np.sum(w * particles.V))
