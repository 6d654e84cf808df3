"""Mohr-Coulomb plasticity, returned in principal stresses."""
import numpy as np

from ..validation import check_positive
from .compiled import PointUpdate
from .base import det
from .plastic import ElastoPlastic, from_principal, principal

__all__ = ["MohrCoulomb"]


class MohrCoulomb(ElastoPlastic):
    """Small-strain Mohr-Coulomb plasticity (perfectly plastic), 2D plane
    strain and 3D, angles in degrees, tension positive, principal stresses
    s1 >= s2 >= s3.

        f_a = (s1 - s3) + (s1 + s3) sin(phi) - 2 c cos(phi)     the main plane
        g_a = (s1 - s3) + (s1 + s3) sin(psi)                    its potential

    (f_b, f_c: the planes with s1 -> s2, and s3 -> s2). Return mapping in
    principal stresses, every case in closed form (de Souza Neto, Peric,
    Owen 2008, ch. 8, the Mohr-Coulomb return in principal stresses;
    perfect plasticity), with the elastic principal stiffness
    D = (K - 2 mu / 3) 1 1^T + 2 mu I and the flow vectors
    N_a = (1 + sin psi, 0, -1 + sin psi), N_b = (0, 1 + sin psi, -1 + sin psi),
    N_c = (1 + sin psi, -1 + sin psi, 0)::

        a     = 4 mu (1 + sin phi sin psi / 3) + 4 K sin phi sin psi
        main plane:  d_gamma = f_a / a,  s = s_t - d_gamma D N_a
                     valid if s1 >= s2 >= s3
        an edge otherwise, s2 = s3 if (1 - sin psi)(s1 - s2)_t > (1 + sin psi)(s2 - s3)_t,
                     else s1 = s2:
            b = 4 K sin phi sin psi + 2 mu (1 -+ (sin phi + sin psi) - sin phi sin psi / 3)
                (- for s1 = s2, + for s2 = s3)
            [a b; b a] (d_gamma_a, d_gamma_x) = (f_a, f_x)_t,
            s = s_t - d_gamma_a D N_a - d_gamma_x D N_x       (x = b or c)
            valid if the order s1 >= s2 >= s3 holds
        the apex otherwise:  s1 = s2 = s3 = c cot(phi)

    The new stress is sum_i s_i n_i n_i^T with the trial's principal
    directions n_i (isotropy). ``tension_cutoff`` T (>= 0, optional): after
    the Mohr-Coulomb return, principal stresses above T are returned to the
    Rankine planes s_i = T in closed form (one, two or three planes,
    associated flow): a sequential, not simultaneous, two-surface return;
    its result is admissible for both criteria (it only lowers f_a).

    ``disconnect_at`` J_c (> 1, optional; needs ``large_deformation=True``):
    grains out of contact. A cohesionless granular material whose density
    falls below a critical density rho_c = rho_0 / J_c carries no stress
    (Dunatunga and Kamrin 2015, J. Fluid Mech. 779, 483-513: the
    "disconnected" phase); so a particle with J = det F = V / V0 > J_c gets
    sigma = 0 (sigma_zz = 0 in 2D; the plastic strain kept) instead of the
    return above, and bears load again once compressed back to J <= J_c
    (its stress then grows from zero). Such a particle has no stiffness, so
    :meth:`wave_speed` counts a density of at least rho_0 / J_c. Without it,
    a grain flung out of the mass keeps the stiffness of the dense material
    over a volume that keeps growing (the apex return lets J grow freely):
    once compressed again it pushes with a stress times that volume.

    The trial stress, sigma_zz, ``large_deformation`` and the state are
    those of :mod:`.plastic`. In plane-strain biaxial loading with
    psi = 0 (sigma_zz intermediate) the limit state is, compression
    positive, sigma_1 = sigma_3 N + 2 c sqrt(N), N = (1 + sin phi) / (1 - sin phi).
    """

    point_update = PointUpdate("skfem_mpm.materials.plastic_laws:mohr_coulomb")

    def __init__(self, E, nu, friction_angle, cohesion, dilation_angle=0.0,
                 tension_cutoff=None, large_deformation=False, disconnect_at=None):
        self._elastic(E, nu, large_deformation)
        self._frictional(friction_angle, cohesion, dilation_angle)
        if tension_cutoff is not None:
            tension_cutoff = check_positive("tension_cutoff", tension_cutoff, allow_zero=True)
        self.tension_cutoff = tension_cutoff
        if disconnect_at is not None:
            disconnect_at = check_positive("disconnect_at", disconnect_at)
            if not disconnect_at > 1.0:
                raise ValueError(f"disconnect_at must be a volume ratio J_c > 1 (the grains "
                                 f"lose contact when V / V0 exceeds it), got {disconnect_at}")
            if not self.large_deformation:
                raise ValueError(f"disconnect_at={disconnect_at} reads J = det F, which only "
                                 f"large_deformation=True tracks; got large_deformation=False")
        self.disconnect_at = disconnect_at

    def __repr__(self):
        return (f"MohrCoulomb(E={self.E:g}, nu={self.nu:g}, "
                f"friction_angle={self.friction_angle:g}, cohesion={self.cohesion:g}, "
                f"dilation_angle={self.dilation_angle:g}, tension_cutoff={self.tension_cutoff}, "
                f"disconnect_at={self.disconnect_at})")

    def point_parameters(self, dim):
        """(lambda, mu, rotate, sin phi, sin psi, c cos phi, K, T or -1, J_c or -1)."""
        phi, psi = np.radians(self.friction_angle), np.radians(self.dilation_angle)
        cutoff = -1.0 if self.tension_cutoff is None else self.tension_cutoff
        disconnect = -1.0 if self.disconnect_at is None else self.disconnect_at
        return np.array(self.elastic_parameters()
                        + [np.sin(phi), np.sin(psi), self.cohesion * np.cos(phi), self.K,
                           cutoff, disconnect])

    def update(self, particles, L, dt):
        """The elastoplastic update (:mod:`.plastic`), then zero stress on
        the disconnected particles (det F > ``disconnect_at``)."""
        stress, V, F, state = super().update(particles, L, dt)
        if self.disconnect_at is not None:
            apart = det(F) > self.disconnect_at
            stress = np.where(apart[:, None, None], 0.0, stress)
            if "sigma_zz" in state:
                state = dict(state, sigma_zz=np.where(apart, 0.0, state["sigma_zz"]))
        return stress, V, F, state

    def wave_speed(self, particles):
        """sqrt((lambda + 2 mu) / rho), rho at least rho_0 / J_c with
        ``disconnect_at`` (the disconnected particles have no stiffness)."""
        if self.disconnect_at is None:
            return super().wave_speed(particles)
        rho = np.maximum(particles.m / particles.V,
                         particles.m / (particles.V0 * self.disconnect_at))
        return float(np.sqrt((self.lam + 2 * self.mu) / rho.min()))

    def wave_speed_bound(self, particles):
        """With ``disconnect_at``: sqrt((lambda + 2 mu) J_c / rho_0), the
        largest speed any particle reaches (a particle that bears load has
        J <= J_c); None without it."""
        if self.disconnect_at is None:
            return None
        rho = particles.m / (particles.V0 * self.disconnect_at)
        return float(np.sqrt((self.lam + 2 * self.mu) / rho.min()))

    def return_map(self, trial, state):
        values, vectors = principal(trial)
        new = self.principal_return(values)
        changed = np.any(new != values, axis=1)
        return np.where(changed[:, None, None], from_principal(new, vectors), trial)

    def principal_return(self, st):
        """The returned principal stresses (n, 3) of trial principal
        stresses ``st`` (n, 3), s1 >= s2 >= s3 (the class docstring)."""
        phi, psi = np.radians(self.friction_angle), np.radians(self.dilation_angle)
        sp, ss, ccp = np.sin(phi), np.sin(psi), self.cohesion * np.cos(phi)
        K, G = self.K, self.mu
        lam2 = 2 * (K - 2 * G / 3) * ss  # the mean part of D N for every plane
        DNa = np.array([lam2 + 2 * G * (1 + ss), lam2, lam2 + 2 * G * (ss - 1)])
        DNb = np.array([lam2, lam2 + 2 * G * (1 + ss), lam2 + 2 * G * (ss - 1)])
        DNc = np.array([lam2 + 2 * G * (1 + ss), lam2 + 2 * G * (ss - 1), lam2])
        s1, s2, s3 = st[:, 0], st[:, 1], st[:, 2]
        fa = (s1 - s3) + (s1 + s3) * sp - 2 * ccp
        fb = (s2 - s3) + (s2 + s3) * sp - 2 * ccp
        fc = (s1 - s2) + (s1 + s2) * sp - 2 * ccp
        a = 4 * G * (1 + sp * ss / 3) + 4 * K * sp * ss
        out = st.copy()
        plastic = fa > 0
        main = st - (fa / a)[:, None] * DNa
        main_ok = (main[:, 0] >= main[:, 1]) & (main[:, 1] >= main[:, 2])
        to_c = (1 - ss) * (s1 - s2) > (1 + ss) * (s2 - s3)
        b_ab = 4 * K * sp * ss + 2 * G * (1 - sp - ss - sp * ss / 3)
        b_ac = 4 * K * sp * ss + 2 * G * (1 + sp + ss - sp * ss / 3)
        b = np.where(to_c, b_ac, b_ab)
        fx = np.where(to_c, fc, fb)
        det = a * a - b * b
        ga, gx = (a * fa - b * fx) / det, (a * fx - b * fa) / det
        DNx = np.where(to_c[:, None], DNc, DNb)
        edge = st - ga[:, None] * DNa - gx[:, None] * DNx
        edge_ok = np.where(to_c, edge[:, 0] >= edge[:, 1], edge[:, 1] >= edge[:, 2])
        if sp > 0:
            apex = np.full_like(st, ccp / sp)
        else:  # Tresca: no apex, the edges are always valid
            edge_ok = np.ones_like(edge_ok)
            apex = edge
        returned = np.where(main_ok[:, None], main, np.where(edge_ok[:, None], edge, apex))
        out[plastic] = returned[plastic]
        if self.tension_cutoff is not None:
            out = self._cutoff(out)
        return out

    def _cutoff(self, s):
        """Rankine return of principal stresses s (n, 3) to s_i <= T:
        lambda = K - 2 mu / 3, M = lambda + 2 mu;
        one plane: d1 = (s1 - T) / M, s1 = T, s2, s3 -= lambda d1;
        two planes: [M lambda; lambda M] (d1, d2) = (s1 - T, s2 - T),
        s1 = s2 = T, s3 -= lambda (d1 + d2); three: s = T."""
        T = self.tension_cutoff
        lam = self.K - 2 * self.mu / 3
        M = lam + 2 * self.mu
        s1, s2, s3 = s[:, 0], s[:, 1], s[:, 2]
        d1 = (s1 - T) / M
        one = np.stack([np.full_like(s1, T), s2 - lam * d1, s3 - lam * d1], axis=1)
        dsum = (s1 - T + s2 - T) / (M + lam)  # d1 + d2 of the two-plane system
        two = np.stack([np.full_like(s1, T), np.full_like(s1, T), s3 - lam * dsum], axis=1)
        three = np.full_like(s, T)
        out = np.where((s1 > T)[:, None], one, s)
        out = np.where((out[:, 1] > T)[:, None], two, out)
        out = np.where((out[:, 2] > T)[:, None], three, out)
        return out
