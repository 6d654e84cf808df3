"""Each material's compiled point law (through the one constitutive kernel)
equals its NumPy ``update``: the same stress, volume, F and state."""
import re
import sys
from pathlib import Path

import numpy as np
import pytest
from numba import get_num_threads

from skfem_mpm import LinearElastic, NeoHookean, Particles
from skfem_mpm.kernels.constitutive import material_update
from skfem_mpm.kernels.serial import serial
from skfem_mpm.materials.state import split_update, state_layout

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
try:
    from custom_material import ElasticPlastic1D
finally:
    sys.path.pop(0)


def random_state(material, dim, n=50, seed=3):
    rng = np.random.default_rng(seed)
    x = rng.random((n, dim))
    stress = rng.normal(size=(n, dim, dim)) * 0.02
    stress = 0.5 * (stress + np.swapaxes(stress, 1, 2))
    F = None
    if material.finite_strain:
        F = np.eye(dim) + 0.2 * rng.normal(size=(n, dim, dim))
        F[np.linalg.det(F) < 0.2] = np.eye(dim)
        stress = np.zeros((n, dim, dim))
    V0 = rng.random(n) + 0.5
    V = V0 * (1.0 if F is None else np.linalg.det(F))
    layout = state_layout(material, dim)
    state = {name: rng.random((n,) + shape) for name, shape in zip(layout.names, layout.shapes)}
    particles = Particles(x, rng.random(n) + 1.0, V, stress=stress, F=F, V0=V0, state=state)
    L = rng.normal(size=(n, dim, dim))
    return particles, L


def compiled_update(material, particles, L, dt, index=None):
    """The constitutive kernel on ``particles`` (the rows of ``index``):
    (stress, V, F, first bad particle or -1, {name: new state of the rows})."""
    n, dim = particles.n, particles.dim
    stress, V = particles.stress.copy(), particles.V.copy()
    F = particles.F.copy() if material.finite_strain else None
    first_bad = np.full(get_num_threads(), -1)
    layout = state_layout(material, dim)
    state_in = layout.pack(particles.state, index) if layout else np.zeros((n, 0))
    state_out = np.full_like(state_in, np.nan)
    every = index is None
    # the serial copy (the same thread blocks in a loop, the same bits): what
    # the runs below SERIAL_BELOW particles compile (the parallel kernel is
    # for runs above it)
    update = serial(material_update)
    update(material.point_update.address(), material.point_parameters(dim),
           np.zeros(0, dtype=np.int64) if every else index, every, L, dt,
           material.finite_strain, particles.stress,
           particles.F if F is not None else L, particles.V, particles.V0, state_in,
           stress, F if F is not None else L.copy(), V, state_out, first_bad)
    bad = first_bad[first_bad >= 0]
    state = layout.views(state_out) if layout else {}
    return stress, V, F, (int(bad.min()) if bad.size else -1), state


MATERIALS = [(LinearElastic(100.0, 0.3), 1), (LinearElastic(100.0, 0.3), 2),
             (LinearElastic(100.0, 0.25), 3), (NeoHookean(100.0, 0.3), 1),
             (NeoHookean(100.0, 0.3), 2), (NeoHookean(100.0, 0.2), 3),
             (ElasticPlastic1D(100.0, 0.03), 1)]


@pytest.mark.parametrize("material,dim", MATERIALS,
                         ids=lambda v: re.sub(r" object at 0x[0-9a-fA-F]+", "", repr(v)))
def test_compiled_point_law_equals_the_numpy_update(material, dim):
    particles, L = random_state(material, dim)
    dt = 1e-3
    stress, V, F, bad, state = compiled_update(material, particles, L, dt)
    if dim == 3:  # the NumPy updates are 1D/2D; 3D against the formulas
        A = np.eye(3) + dt * L
        if material.finite_strain:
            F_ref = A @ particles.F
            J = np.linalg.det(F_ref)
            lam, mu = material.parameters(3)
            expect = (mu * (F_ref @ np.swapaxes(F_ref, 1, 2) - np.eye(3))
                      + (lam * np.log(J))[:, None, None] * np.eye(3)) / J[:, None, None]
            assert np.abs(F - F_ref).max() <= 1e-14 * np.abs(F_ref).max()
            assert np.abs(V - particles.V0 * J).max() <= 1e-13 * V.max()
        else:
            d = 0.5 * dt * (L + np.swapaxes(L, 1, 2))
            tr = np.trace(d, axis1=1, axis2=2)
            expect = particles.stress + 2 * material.mu * d \
                + material.lam * tr[:, None, None] * np.eye(3)
            assert np.abs(V - particles.V * np.linalg.det(A)).max() <= 1e-14 * V.max()
        assert bad == -1
        assert np.abs(stress - expect).max() <= 1e-13 * np.abs(expect).max()
        return
    s_ref, V_ref, F_ref, state_ref = split_update(material, material.update(particles, L, dt),
                                                   particles.n)
    assert bad == -1
    assert set(state) == set(state_ref) == set(state_layout(material, dim).names)
    for name in state:
        assert np.abs(state[name] - state_ref[name]).max() <= \
            1e-13 * np.abs(state_ref[name]).max()
    assert np.abs(stress - s_ref).max() <= 1e-13 * max(np.abs(s_ref).max(), 1e-300)
    assert np.abs(V - V_ref).max() <= 1e-14 * np.abs(V_ref).max()
    if material.finite_strain:
        assert np.abs(F - F_ref).max() <= 1e-14 * np.abs(F_ref).max()


def test_compiled_law_updates_only_its_body_and_flags_inverted_volumes():
    material = LinearElastic(100.0, 0.3)
    particles, L = random_state(material, 2)
    index = np.arange(0, particles.n, 3)
    L[index[2]] = -np.eye(2) / 1e-3 * 1.5  # det(I + dt L) = 0.25 > 0 ...
    L[index[4]] = np.array([[-2000.0, 0.0], [0.0, 0.0]])  # ... and here det = -1
    stress, V, _, bad, _ = compiled_update(material, particles, L, 1e-3, index=index)
    others = np.setdiff1d(np.arange(particles.n), index)
    assert np.array_equal(stress[others], particles.stress[others])
    assert np.array_equal(V[others], particles.V[others])
    assert bad == index[4]
