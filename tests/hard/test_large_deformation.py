"""Large deformation: S4 (neo-Hookean bar, G = 0.05) and D1 (2D
axis-aligned, A = 0.05) to t_end with J > 0 everywhere and the error
(max over saves, relative to the amplitude) decreasing under refinement."""
import numpy as np
import pytest

from skfem_mpm import Method, simulate
from skfem_mpm.benchmarks import get_benchmark
from skfem_mpm.materials import det

# a hard study: the slow tier (`pytest -m slow`, run by .ci/run too)
pytestmark = pytest.mark.slow


def errors_and_J(b, cells, degree, method):
    out = []
    for n in cells:
        r = simulate(b.scene(n, degree, 2), method, save_every=20)
        out.append((b.errors(r)["error_max"], float(det(r.particles.F).min())))
    print(f"\n{b.name} p={degree} {method.mass} {method.reconstruction}: "
          + ", ".join(f"{n} cells {e:.2e} (J min {J:.3f})" for n, (e, J) in zip(cells, out)))
    return out


@pytest.mark.parametrize("degree, reconstruction", [(2, "none"), (3, "none"), (2, "spline"),
                                                    (3, "spline")])
def test_neo_hookean_bar(degree, reconstruction):
    b = get_benchmark("neo-hookean-bar", "large")
    assert b.G == 0.05
    out = errors_and_J(b, (8, 16, 32), degree, Method(mass="consistent",
                                                      reconstruction=reconstruction))
    assert all(J > 0 for _, J in out)
    assert out[1][0] < out[0][0] and out[2][0] < out[1][0]


@pytest.mark.parametrize("degree", [2, 3])
def test_axis_aligned_2d(degree):
    """Particle quadrature with consistent mass."""
    b = get_benchmark("axis-aligned-2d", "large")
    assert b.A == 0.05
    out = errors_and_J(b, (4, 8, 16), degree, Method(mass="consistent"))
    assert all(J > 0 for _, J in out)
    assert out[1][0] < out[0][0] and out[2][0] < out[1][0]


@pytest.mark.slow
def test_axis_aligned_2d_with_spline_reconstruction():
    """The 2D least-squares spline at the Gauss-FEM step times the
    power-iteration factor of timestep.reconstruction_factor (about 1 here;
    a fixed 0.6 before)."""
    b = get_benchmark("axis-aligned-2d", "large")
    out = errors_and_J(b, (4, 8, 16), 2, Method(mass="consistent", reconstruction="spline"))
    assert all(J > 0.9 for _, J in out)
    assert out[1][0] < out[0][0] and out[2][0] < out[1][0]
