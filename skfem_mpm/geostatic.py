"""Geostatic (K0) initial stress of a soil layer under gravity."""
import numbers

import numpy as np

from .materials.base import check_nu
from .validation import check_positive

__all__ = ["geostatic_stress"]


def geostatic_stress(particles, surface, g, K0=None, nu=None):
    """The particles with the geostatic stress of a layer under gravity g
    (pointing to -y in 2D, -z in 3D), tension positive: the K0 procedure
    of geotechnical codes, from the vertical equilibrium of a horizontal
    layer (d sigma_v / d depth = -rho g) and the earth pressure coefficient
    at rest K0 (the elastic oedometric value nu / (1 - nu), or a user's,
    e.g. Jaky's 1 - sin(phi) for a normally consolidated soil)::

        depth    = surface - x_v           (x_v = y in 2D, z in 3D)
        sigma_v  = -rho g depth            below the surface, 0 above it
        sigma_h  = K0 sigma_v              every horizontal normal stress
        sigma_zz = K0 sigma_v              in 2D (plane strain), as
                                           ``particles.state["sigma_zz"]``
        shear stresses 0

    ``rho`` is each particle's density m / V, so sigma_v is exact for a
    layer of uniform density. ``surface`` is the height of the ground
    surface: a number, or a callable of the particles' positions (n, dim)
    returning (n,) heights (a sloping or uneven surface; the formula is then
    the usual approximation). ``K0`` is given, or taken as the elastic
    nu / (1 - nu) from ``nu`` (exactly one of them). Returns new particles
    (``Particles.replaced``); the given ones are not changed. In 2D the
    state field ``sigma_zz`` is set (the plane-strain plastic materials read
    it; a material that does not declare it carries it along unchanged).
    """
    dim = particles.dim
    if dim not in (2, 3):
        raise ValueError(f"geostatic_stress needs 2D or 3D particles, got dim={dim}")
    g = check_positive("g", g)
    if (K0 is None) == (nu is None):
        raise ValueError(f"give exactly one of K0 and nu (K0 = nu / (1 - nu)), got K0={K0!r}, "
                         f"nu={nu!r}")
    if K0 is None:
        nu = check_nu(nu)
        if not nu >= 0:
            raise ValueError(f"nu must be >= 0 for K0 = nu / (1 - nu) >= 0, got {nu}")
        K0 = nu / (1 - nu)
    K0 = check_positive("K0", K0, allow_zero=True)
    x = particles.x
    if callable(surface):
        top = np.asarray(surface(x), dtype=np.float64)
        if top.shape != (particles.n,) or not np.all(np.isfinite(top)):
            raise ValueError(f"surface(x) must return finite heights of shape "
                             f"({particles.n},), got shape {top.shape}")
    elif isinstance(surface, numbers.Real) and not isinstance(surface, bool) \
            and np.isfinite(surface):
        top = np.full(particles.n, float(surface))
    else:
        raise ValueError(f"surface must be a finite number or a callable of x (n, dim), "
                         f"got {surface!r}")
    depth = np.maximum(top - x[:, dim - 1], 0.0)
    sigma_v = -(particles.m / particles.V) * g * depth
    stress = np.zeros((particles.n, dim, dim))
    for d in range(dim - 1):
        stress[:, d, d] = K0 * sigma_v
    stress[:, dim - 1, dim - 1] = sigma_v
    state = dict(particles.state)
    if dim == 2:
        state["sigma_zz"] = K0 * sigma_v
    return particles.replaced(stress=stress, state=state)
