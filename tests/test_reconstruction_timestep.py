"""The time step of a reconstructed 2D method: power iterations on the
reconstructed scalar wave operator (timestep.reconstruction_factor)."""
import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.linalg import eigsh

from skfem_mpm import Method
from skfem_mpm.benchmarks import get_benchmark
from skfem_mpm.reconstruct import RECONSTRUCTORS, reconstruct_spline, reconstruct_tls
from skfem_mpm.solve import prepare
from skfem_mpm.solve.timestep import (ReconstructedOperator, compiled_twin, critical_time_step,
                                      power_iteration, reconstruction_factor)


def small_case(ppc=2):
    b = get_benchmark("axis-aligned-2d", "large")
    s = b.scene(6, 2, ppc)
    return s.grid, s.bodies[0].particles


def dense(apply, n):
    return np.column_stack([apply(e) for e in np.eye(n)])


def test_power_iteration_matches_the_top_eigenvalue():
    """20 iterations from the checkerboard: within 5% of the exact largest
    eigenvalue magnitude, for the reconstructed (non-symmetric) operator and
    for the Gauss one (symmetric in the M_L inner product: eigsh on
    M_L^-1/2 K_G M_L^-1/2)."""
    grid, p = small_case()
    op = ReconstructedOperator(grid, p, reconstruct_spline, {})
    ev = np.linalg.eigvals(dense(op.apply, grid.ndofs))
    exact = np.abs(ev).max()
    lam, _ = power_iteration(op.apply, op.lumped, op.start_vector(), 20)
    assert 0.95 * exact < lam <= exact * (1 + 1e-9)
    a = op.active
    s = sp.diags(1.0 / np.sqrt(op.lumped[a]))
    KG = dense(op.gauss_stiffness, grid.ndofs)[np.ix_(a, a)]
    top = eigsh(s @ sp.csr_matrix(KG) @ s, k=1, which="LA")[0][0]
    lam_g, _ = power_iteration(op.apply_gauss, op.lumped, op.start_vector(), 20)
    assert 0.95 * top < lam_g <= top * (1 + 1e-9)


def test_factor_follows_a_stiffer_reconstruction():
    """A reconstruction that doubles the stresses doubles lambda_R: f = 1/sqrt(2)
    within 3%; the published tls on these particles is no stiffer than Gauss
    (f = 1). The estimate is the same bit for bit when repeated."""
    grid, p = small_case(3)

    def stiff(grid, particles, values, rule):  # rho as is, gradients doubled
        out = reconstruct_tls(grid, particles, values, rule)
        return out if values.shape[1] == 1 else 2.0 * out

    f, _ = reconstruction_factor(grid, p, stiff, {})
    assert abs(f - 2 ** -0.5) < 0.03 * 2 ** -0.5
    f_tls, vectors = reconstruction_factor(grid, p, reconstruct_tls, {})
    assert f_tls == 1.0
    again, vectors2 = reconstruction_factor(grid, p, reconstruct_tls, {})
    assert again == f_tls and all(np.array_equal(a, b) for a, b in zip(vectors, vectors2))


def test_the_run_takes_the_factor():
    """prepare() multiplies the Gauss dt_crit by the estimated factor (and
    no longer by a fixed 0.6)."""
    b = get_benchmark("axis-aligned-2d", "large")
    scene = b.scene(6, 2, 3)
    state = prepare(scene, Method(mass="consistent", reconstruction="spline"))
    gauss = critical_time_step(scene.grid, state.wave_speed_now, "consistent")
    f, _ = reconstruction_factor(scene.grid, scene.bodies[0].particles, reconstruct_spline, {})
    assert state.dt_crit == gauss * f


@pytest.mark.parametrize("name", ("spline", "tls", "mls"))
def test_the_compiled_estimate_is_the_numpy_one(name):
    """The factor's power iterations with the compiled reconstruction (what
    runs) and with the NumPy one (the oracle): the same eigenvalue estimates
    to 1e-10 relative after the 20 iterations (rounding only; measured
    <= 3e-15), on 3 x 3 and 2 x 2 particles per cell of D1 (the 2 x 2 case
    has a partly filled ring of cells: tls's linear fallback, spline's
    penalty)."""
    for ppc in (3, 2):
        grid, p = small_case(ppc)
        recon = RECONSTRUCTORS[name]
        assert compiled_twin(grid, recon, {}) is not None
        results = []
        for compiled in (True, False):
            twin = compiled_twin(grid, recon, {}) if compiled else None
            op = ReconstructedOperator(grid, p, twin or recon, {})
            start = op.start_vector()
            lam_r, _ = power_iteration(op.apply, op.lumped, start, 20)
            lam_g, _ = power_iteration(op.apply_gauss, op.lumped, start, 20)
            results.append((lam_r, lam_g))
        (cr, cg), (nr, ng) = results
        assert abs(cr - nr) <= 1e-10 * nr and abs(cg - ng) <= 1e-10 * ng, (results, ppc)
        f_c, _ = reconstruction_factor(grid, p, recon, {})
        f_n, _ = reconstruction_factor(grid, p, recon, {}, compiled=False)
        assert abs(f_c - f_n) <= 1e-10


def test_a_users_reconstruction_has_no_compiled_twin():
    grid, _ = small_case()
    assert compiled_twin(grid, lambda grid, p, values, rule: values[:0], {}) is None
    assert compiled_twin(grid, RECONSTRUCTORS["tls"], {"degree": 1}) is None
