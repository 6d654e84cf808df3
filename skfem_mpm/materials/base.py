"""The material interface: each material a small object whose ``update`` is
one vectorised function of the particle arrays and the velocity gradient,
and whose ``point_update`` (optional) is the same law for one particle,
compiled (see :mod:`skfem_mpm.materials.compiled`).

A material has

    finite_strain           True if it needs the deformation gradient F
    update(p, L, dt)        new (stress, V, F) from the velocity gradient
                            L[p, i, j] = dv_i/dx_j over the step dt
    wave_speed(p)           the largest P-wave speed of the particles, for
                            the critical time step
    strain_energy(p)        total stored energy sum_p W_p V0_p (or V_p)
    check_dim(dim)          raise for dimensions it does not model
    point_update            the compiled law of one particle, or None (then the
                            compiled executor calls ``update``)
    point_parameters(dim)   the float64 array of parameters ``point_update`` reads

Write your own by following the same shape (see examples/custom_material.py).
2D is plane strain throughout; 1D is uniaxial strain.
"""
import numpy as np

__all__ = ["Material", "lame_parameters", "check_nu", "incremental_deformation", "det"]


def lame_parameters(E, nu):
    """Lame's lambda and mu: lambda = E nu / ((1 + nu)(1 - 2 nu)), mu = E / (2 (1 + nu))."""
    return E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))


def check_nu(nu):
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
    point_update = None

    def point_parameters(self, dim):
        """The parameters of ``point_update`` (a float64 array)."""
        return np.zeros(0)

    def check_dim(self, dim):
        if dim not in (1, 2):
            raise ValueError(f"{type(self).__name__} models 1D and 2D (plane strain), got dim={dim}")

    def update(self, particles, L, dt):  # pragma: no cover - interface
        raise NotImplementedError

    def wave_speed(self, particles):  # pragma: no cover - interface
        raise NotImplementedError

    def strain_energy(self, particles):  # pragma: no cover - interface
        raise NotImplementedError
