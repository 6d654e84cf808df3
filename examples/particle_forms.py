"""Particles as a quadrature rule for your own scikit-fem forms: the mass
matrix and load vector over particles equal their Gauss counterparts when
the particles sit at Gauss points, and approximate them otherwise.

    python examples/particle_forms.py
"""
import numpy as np
from skfem import BilinearForm, LinearForm, asm

from skfem_mpm import ParticleBasis, Particles, SplineGrid


@BilinearForm
def mass(u, v, w):
    return w.rho * u * v


@LinearForm
def weight(v, w):
    return w.rho * 9.81 * v


def main(cells=8):
    grid = SplineGrid.rectangle((0, 1), (0, 1), cells, degree=2)
    gauss = grid.basis(intorder=5)
    out = {}
    for layout in ("gauss", "uniform"):
        particles = Particles.seed(grid, ppc=3, density=2.0, layout=layout)
        pb = ParticleBasis(grid, particles)
        rho = (particles.m / particles.V)[:, None]  # per-particle data: trailing axis
        M_p, M_g = asm(mass, pb, rho=rho), asm(mass, gauss, rho=2.0)
        f_p, f_g = asm(weight, pb, rho=rho), asm(weight, gauss, rho=2.0)
        out[layout] = (abs(M_p - M_g).max(), np.abs(f_p - f_g).max())
        print(f"{layout:8s} particles: |M_p - M_gauss| = {out[layout][0]:.2e}, "
              f"|f_p - f_gauss| = {out[layout][1]:.2e}")
    # transfer matrices: grid-to-particle and particle-to-grid
    lumped = pb.N_matrix.T @ particles.m
    print(f"lumped mass sums to the total mass: {lumped.sum():.12f} = {particles.m.sum():.12f}")
    return out


if __name__ == "__main__":
    main()
