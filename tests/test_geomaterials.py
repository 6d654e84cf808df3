"""G3 element tests of the elastoplastic materials (MohrCoulomb,
DruckerPrager, VonMises): each point update (the NumPy ``stress_update`` and
the compiled point law) driven by prescribed strain increments and compared
with closed forms, with the exact discrete return map, and under rigid
rotation. Tension positive; "compression" figures are written with minus
signs."""
import numpy as np
import pytest

from skfem_mpm import Body, Fixed, Gravity, Method, Particles, Scene, SplineGrid, simulate
from skfem_mpm.materials import DruckerPrager, MohrCoulomb, VonMises
from skfem_mpm.materials import plastic_laws
from skfem_mpm.materials.drucker_prager import drucker_prager_fit

E, NU = 1.0e4, 0.3
P0 = 100.0  # the isotropic starting pressure of the plastic paths
EXECUTORS = ["numpy", "compiled"]


# ------------------------------------------------------------------ drivers
def start(material, dim, n=1, pressure=P0):
    """An isotropic state sigma = -pressure I (sigma_zz too) for n points."""
    stress = np.broadcast_to(-pressure * np.eye(dim), (n, dim, dim)).copy()
    state = {"plastic_strain": np.zeros(n)}
    if dim == 2:
        state["sigma_zz"] = np.full(n, -pressure)
    return stress, state


def step(material, executor, stress, state, L, dt=1.0):
    """One step of the NumPy update or of the compiled point law (one
    particle after another, as the constitutive kernel calls it)."""
    if executor == "numpy":
        return material.stress_update(stress, state, L, dt)
    name = material.point_update._law.split(":")[1]
    law = getattr(plastic_laws, name + "_law")
    dim = stress.shape[-1]
    params = material.point_parameters(dim)
    keys = list(material.state_fields(dim))
    packed = np.stack([state[k] for k in keys], axis=1)
    out, packed_out = np.empty_like(stress), packed.copy()
    for i in range(stress.shape[0]):
        law(params, L[i], np.eye(dim), dt, stress[i], packed[i], out[i], packed_out[i])
    return out, {k: packed_out[:, j].copy() for j, k in enumerate(keys)}


def full(stress, state):
    """The 3x3 stresses (with sigma_zz in 2D)."""
    n, dim = stress.shape[0], stress.shape[-1]
    s = np.zeros((n, 3, 3))
    s[:, :dim, :dim] = stress
    if dim == 2:
        s[:, 2, 2] = state["sigma_zz"]
    return s


def biaxial(material, executor, dim, rate=-1e-4, steps=400, confining=P0):
    """Plane-strain (2D; in 3D with eps_zz = 0 too) biaxial compression:
    eps_yy prescribed, sigma_xx held at -confining by solving for eps_xx each
    step (secant iterations). Returns the stresses after each step."""
    stress, state = start(material, dim, pressure=confining)
    path = []
    L = np.zeros((1, dim, dim))
    L[0, 1, 1] = rate
    for _ in range(steps):
        guesses = [0.0, 1e-5]
        values = []
        for x in guesses:
            L[0, 0, 0] = x
            values.append(step(material, executor, stress, state, L)[0][0, 0, 0] + confining)
        for _ in range(30):
            if values[-1] == values[-2]:
                break
            x = guesses[-1] - values[-1] * (guesses[-1] - guesses[-2]) / (values[-1] - values[-2])
            L[0, 0, 0] = x
            guesses.append(x)
            values.append(step(material, executor, stress, state, L)[0][0, 0, 0] + confining)
            if abs(values[-1]) <= 1e-13 * confining:
                break
        L[0, 0, 0] = guesses[-1]
        stress, state = step(material, executor, stress, state, L)
        path.append(full(stress, state)[0])
    return np.array(path), state


MATERIALS = {
    "mohr-coulomb": lambda: MohrCoulomb(E, NU, 30.0, 5.0),
    "drucker-prager": lambda: DruckerPrager(E, NU, 30.0, 5.0),
    "von-mises": lambda: VonMises(E, NU, 20.0),
}


# -------------------------------------------------------------- oedometer
@pytest.mark.parametrize("executor", EXECUTORS)
@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("name", ["mohr-coulomb", "drucker-prager"])
def test_oedometric_loading_follows_the_elastic_k0_path(name, dim, executor):
    """eps_yy only (oedometer): sigma_yy = (lambda + 2 mu) eps_yy and
    sigma_xx = sigma_zz = lambda eps_yy, so K0 = nu / (1 - nu) (= 0.43, inside
    the friction cone of 30 degrees: the path stays elastic)."""
    material = MATERIALS[name]()
    stress, state = start(material, dim, pressure=0.0)
    L = np.zeros((1, dim, dim))
    L[0, 1, 1] = -1e-4
    for k in range(1, 51):
        stress, state = step(material, executor, stress, state, L)
        s = full(stress, state)[0]
        eps = -1e-4 * k
        exact_v = (material.lam + 2 * material.mu) * eps
        assert abs(s[1, 1] - exact_v) <= 1e-10 * abs(exact_v)
        assert abs(s[0, 0] / s[1, 1] - NU / (1 - NU)) <= 1e-10
        assert abs(s[2, 2] / s[1, 1] - NU / (1 - NU)) <= 1e-10
    assert state["plastic_strain"][0] == 0.0


@pytest.mark.parametrize("executor", EXECUTORS)
@pytest.mark.parametrize("dim", [2, 3])
def test_oedometric_loading_of_von_mises_past_yield(dim, executor):
    """Von Mises in the oedometer: elastic (K0 path) until
    q = (1 - 2 nu) / (1 - nu) |sigma_yy| = sigma_y, then q stays sigma_y
    and p = K eps_yy (the radial return keeps p): sigma_yy = K eps - 2/3
    sigma_y, sigma_xx = sigma_zz = K eps + 1/3 sigma_y."""
    material = VonMises(E, NU, 20.0)
    stress, state = start(material, dim, pressure=0.0)
    L = np.zeros((1, dim, dim))
    L[0, 1, 1] = -1e-4
    yielded = 0
    for k in range(1, 101):
        stress, state = step(material, executor, stress, state, L)
        s = full(stress, state)[0]
        eps = -1e-4 * k
        elastic = np.array([material.lam * eps, (material.lam + 2 * material.mu) * eps,
                            material.lam * eps])
        if (1 - 2 * NU) / (1 - NU) * abs(elastic[1]) <= 20.0:
            exact = elastic
        else:
            yielded += 1
            exact = material.K * eps + np.array([20.0 / 3, -40.0 / 3, 20.0 / 3])
        assert np.abs(np.diag(s) - exact).max() <= 1e-10 * np.abs(exact).max()
    assert yielded > 50


# ------------------------------------------------------------------ biaxial
def mc_limit(confining, phi=30.0, c=5.0):
    """sigma_1 = sigma_3 N + 2 c sqrt(N), N = (1 + sin phi) / (1 - sin phi),
    compression positive."""
    N = (1 + np.sin(np.radians(phi))) / (1 - np.sin(np.radians(phi)))
    return confining * N + 2 * c * np.sqrt(N)


@pytest.mark.parametrize("executor", EXECUTORS)
@pytest.mark.parametrize("dim", [2, 3])
def test_biaxial_mohr_coulomb_reaches_its_limit_state_exactly(dim, executor):
    """psi = 0: sigma_zz stays intermediate and the main-plane return puts
    every plastic step on sigma_1 = sigma_3 N + 2 c sqrt(N) (compression
    positive) with sigma_3 the confining pressure."""
    path, state = biaxial(MATERIALS["mohr-coulomb"](), executor, dim)
    plastic = path[:, 1, 1] <= -mc_limit(P0) * (1 - 1e-9)
    assert plastic.sum() > 100 and not plastic[:20].any()
    assert np.abs(path[:, 0, 0] + P0).max() <= 1e-12 * P0
    assert np.abs(-path[plastic, 1, 1] / mc_limit(P0) - 1).max() <= 1e-10
    assert np.all(-path[:, 1, 1] <= mc_limit(P0) * (1 + 1e-12))
    assert state["plastic_strain"][0] > 0.01


@pytest.mark.parametrize("executor", EXECUTORS)
@pytest.mark.parametrize("dilation", [0.0, 10.0])
def test_biaxial_drucker_prager_plane_strain_fit_matches_mohr_coulomb(dilation, executor):
    """The plane-strain fit's limit state (d eps_zz^p = 0, reached
    asymptotically as sigma_zz settles) is Mohr-Coulomb's, to 1e-6."""
    material = DruckerPrager(E, NU, 30.0, 5.0, dilation_angle=dilation)
    path, _ = biaxial(material, executor, 2, rate=-1e-3, steps=400)
    assert abs(-path[-1, 1, 1] / mc_limit(P0) - 1) <= 1e-6


@pytest.mark.parametrize("executor", EXECUTORS)
@pytest.mark.parametrize("fit, steps", [("compression", 1000), ("extension", 400)])
def test_biaxial_drucker_prager_cones_reach_their_plane_strain_limit(fit, steps, executor):
    """Any cone's plane-strain limit: with m, r the in-plane Mohr circle's
    centre and radius, r (3 - eta eta_bar) / sqrt(9 - 3 eta_bar^2) + eta m =
    xi c (drucker_prager_fit's derivation); the compression cone gets there slower."""
    material = DruckerPrager(E, NU, 30.0, 5.0, dilation_angle=5.0, fit=fit)
    path, _ = biaxial(material, executor, 2, rate=-1e-3, steps=steps)
    eta, xi, eta_bar = drucker_prager_fit(30.0, 5.0, fit)
    sxx, syy = path[-1, 0, 0], path[-1, 1, 1]
    m, r = (sxx + syy) / 2, abs(sxx - syy) / 2
    limit = r * (3 - eta * eta_bar) / np.sqrt(9 - 3 * eta_bar ** 2) + eta * m
    assert abs(limit / (xi * 5.0) - 1) <= 1e-6


@pytest.mark.parametrize("executor", EXECUTORS)
@pytest.mark.parametrize("dim", [2, 3])
def test_biaxial_von_mises_reaches_tresca_in_plane_strain(dim, executor):
    """|sigma_yy - sigma_xx| = 2 sigma_y / sqrt(3) (= 2 c_u) once s_zz -> 0."""
    path, _ = biaxial(MATERIALS["von-mises"](), executor, dim, steps=300)
    assert abs(abs(path[-1, 1, 1] - path[-1, 0, 0]) / (40.0 / np.sqrt(3)) - 1) <= 1e-6


# ------------------------------------------------------------- simple shear
@pytest.mark.parametrize("executor", EXECUTORS)
@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("name", sorted(MATERIALS))
def test_simple_shear_limit_states(name, dim, executor):
    """Simple shear (L_xy only) from sigma = -p0 I: tau = G gamma while
    elastic, then Mohr-Coulomb and the plane-strain Drucker-Prager with
    psi = 0 hold tau = c cos(phi) + p0 sin(phi), von Mises
    tau = sigma_y / sqrt(3); the normal stresses stay -p0."""
    material = MATERIALS[name]()
    stress, state = start(material, dim)
    L = np.zeros((1, dim, dim))
    L[0, 0, 1] = 1e-4
    limit = 20.0 / np.sqrt(3) if name == "von-mises" else \
        5.0 * np.cos(np.radians(30)) + P0 * np.sin(np.radians(30))
    yielded = 0
    for k in range(1, 201):
        stress, state = step(material, executor, stress, state, L)
        s = full(stress, state)[0]
        tau = min(material.mu * 1e-4 * k, limit)
        yielded += tau == limit
        assert abs(s[0, 1] - tau) <= 1e-10 * tau
        assert np.abs(np.diag(s) + P0).max() <= 1e-10 * P0
    assert yielded > 50


# ------------------------------------------------------- the discrete return
def random_trials(dim, n=3000, seed=1):
    rng = np.random.default_rng(seed)
    stress = rng.normal(size=(n, dim, dim)) * 30 - 20 * np.eye(dim)
    stress = 0.5 * (stress + np.swapaxes(stress, 1, 2))
    state = {"plastic_strain": np.zeros(n)}
    if dim == 2:
        state["sigma_zz"] = rng.normal(size=n) * 30 - 20
    L = rng.normal(size=(n, dim, dim)) * 3e-3
    return stress, state, L


def trial_of(material, stress, state, L):
    """The elastic trial stress (3x3): the update of an elastic material."""
    elastic = MohrCoulomb(E, NU, 0.0, 1e30)
    s, st = elastic.stress_update(stress, state, L, 1.0)
    return full(s, st)


@pytest.mark.parametrize("executor", EXECUTORS)
@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("dilation", [0.0, 12.0])
def test_mohr_coulomb_return_is_the_exact_discrete_return(dilation, dim, executor):
    """For every trial: the result is admissible (f <= 0 on all six planes),
    keeps the trial's principal directions, and either equals the trial
    (elastic), lies on the main plane or an edge with sigma_t - sigma =
    sum_k d_gamma_k D N_k, d_gamma_k >= 0 (to 1e-10), or is the apex. Each
    of main plane, both edges and apex occurs."""
    material = MohrCoulomb(E, NU, 30.0, 5.0, dilation_angle=dilation)
    stress, state, L = random_trials(dim)
    trial = trial_of(material, stress, state, L)
    new, st = step(material, executor, stress, state, L)
    sigma = full(new, st)
    values, vectors = np.linalg.eigh(trial)
    values, vectors = values[:, ::-1], vectors[:, :, ::-1]
    returned = np.einsum("nki,nkl,nlj->nij", vectors, sigma, vectors)  # in the trial's frame
    scale = np.abs(trial).max()
    off = returned - np.einsum("nii->ni", returned)[:, :, None] * np.eye(3)
    assert np.abs(off).max() <= 1e-10 * scale
    s = np.einsum("nii->ni", returned)
    sp, ss = np.sin(np.radians(30.0)), np.sin(np.radians(dilation))
    ccp = 5.0 * np.cos(np.radians(30.0))
    f = lambda i, j: (s[:, i] - s[:, j]) + (s[:, i] + s[:, j]) * sp - 2 * ccp  # noqa: E731
    assert max(f(i, j).max() for i in range(3) for j in range(3) if i != j) <= 1e-10 * scale
    K, G = material.K, material.mu
    D = (K - 2 * G / 3) * np.ones((3, 3)) + 2 * G * np.eye(3)
    N = {"a": (1 + ss, 0, ss - 1), "b": (0, 1 + ss, ss - 1), "c": (1 + ss, ss - 1, 0)}
    DN = {k: D @ np.array(v) for k, v in N.items()}
    delta = values - s
    seen = set()
    apex = 5.0 / np.tan(np.radians(30.0))
    for i in range(len(s)):
        if np.abs(delta[i]).max() <= 1e-12 * scale:
            continue  # elastic
        if np.abs(s[i] - apex).max() <= 1e-10 * scale:
            seen.add("apex")
            continue
        for planes in (("a",), ("a", "b"), ("a", "c")):
            A = np.column_stack([DN[k] for k in planes])
            gamma, *_ = np.linalg.lstsq(A, delta[i], rcond=None)
            on = all(abs(f(*{"a": (0, 2), "b": (1, 2), "c": (0, 1)}[k])[i]) <= 1e-10 * scale
                     for k in planes)
            if on and np.abs(A @ gamma - delta[i]).max() <= 1e-10 * scale and \
                    gamma.min() >= -1e-10:
                seen.add(planes)
                break
        else:
            raise AssertionError(f"trial {values[i]} returned to {s[i]}: not a discrete return")
    assert seen == {("a",), ("a", "b"), ("a", "c"), "apex"}


@pytest.mark.parametrize("executor", EXECUTORS)
@pytest.mark.parametrize("dim", [2, 3])
def test_drucker_prager_and_von_mises_returns_are_exact(dim, executor):
    """Drucker-Prager: on the cone f = 0 with s parallel to s_t and
    p_t - p = K eta_bar (sqrt(J2_t) - sqrt(J2)) / mu, or at the apex; von
    Mises with hardening: q = sigma_y + H eps_p, s parallel to s_t, p = p_t."""
    stress, state, L = random_trials(dim)
    dp = DruckerPrager(E, NU, 30.0, 5.0, dilation_angle=10.0)
    vm = VonMises(E, NU, 60.0, hardening=500.0)
    state["plastic_strain"] = np.random.default_rng(2).random(len(stress)) * 1e-3
    for material in (dp, vm):
        trial = trial_of(material, stress, state, L)
        new, st = step(material, executor, stress, state, L)
        sigma = full(new, st)
        scale = np.abs(trial).max()
        p_t, p = np.trace(trial, axis1=1, axis2=2) / 3, np.trace(sigma, axis1=1, axis2=2) / 3
        s_t, s = trial - p_t[:, None, None] * np.eye(3), sigma - p[:, None, None] * np.eye(3)
        j_t = np.sqrt(0.5 * np.einsum("nij,nij->n", s_t, s_t))
        j = np.sqrt(0.5 * np.einsum("nij,nij->n", s, s))
        plastic = np.abs(sigma - trial).max(axis=(1, 2)) > 1e-12 * scale
        assert plastic.any() and not plastic.all()
        parallel = s - (j / j_t)[:, None, None] * s_t
        assert np.abs(parallel).max() <= 1e-10 * scale
        if material is dp:
            f = j + dp.eta * p - dp.xi * 5.0
            apex = plastic & (j <= 1e-12 * scale)
            cone = plastic & ~apex
            assert apex.sum() > 0 and cone.sum() > 0
            assert np.abs(f[plastic]).max() <= 1e-10 * scale
            assert np.abs((p_t - p - dp.K * dp.eta_bar * (j_t - j) / dp.mu)[cone]).max() \
                <= 1e-10 * scale
        else:
            q = np.sqrt(3) * j
            eps_p = st["plastic_strain"]
            assert np.abs((q - 60.0 - 500.0 * eps_p)[plastic]).max() <= 1e-10 * scale
            assert np.abs(p - p_t).max() <= 1e-10 * scale
            gamma = (np.sqrt(3) * j_t - 60.0 - 500.0 * state["plastic_strain"]) / (3 * vm.mu + 500)
            assert np.abs((eps_p - state["plastic_strain"] - gamma)[plastic]).max() <= 1e-12


# ---------------------------------------------------------------- objectivity
def invariants(s):
    p = np.trace(s, axis1=1, axis2=2) / 3
    dev = s - p[:, None, None] * np.eye(3)
    return np.column_stack([p, 0.5 * np.einsum("nij,nij->n", dev, dev), np.linalg.det(dev)])


@pytest.mark.parametrize("executor", EXECUTORS)
@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("name", sorted(MATERIALS))
def test_rigid_rotation_of_a_yielded_state_keeps_its_invariants(name, dim, executor):
    """large_deformation=True: a spin L = W (no strain) over 100 steps turns
    a yielded state by the Hughes-Winget angle per step, 2 atan(w dt / 2),
    exactly; p, J2 and J3 (and sigma_zz in 2D) are unchanged to 1e-10."""
    factory = {"mohr-coulomb": MohrCoulomb, "drucker-prager": DruckerPrager}
    if name == "von-mises":
        material = VonMises(E, NU, 20.0, large_deformation=True)
    else:
        material = factory[name](E, NU, 30.0, 5.0, large_deformation=True)
    assert material.finite_strain
    stress, state = start(material, dim)
    L = np.zeros((1, dim, dim))
    L[0, 0, 1], L[0, 1, 1] = 3e-4, -2e-4
    if dim == 3:
        L[0, 2, 0] = 1e-4
    for _ in range(200):  # to yield
        stress, state = step(material, executor, stress, state, L)
    assert state["plastic_strain"][0] > 1e-3
    before = full(stress, state)
    omega = np.array([0.0, 0.0, 0.3]) if dim == 2 else np.array([0.1, -0.2, 0.3])
    W = np.array([[0, -omega[2], omega[1]], [omega[2], 0, -omega[0]],
                  [-omega[1], omega[0], 0]])[:dim, :dim]
    L = W[None]
    dt, steps = 0.05, 100
    for _ in range(steps):
        stress, state = step(material, executor, stress, state, L, dt)
    after = full(stress, state)
    scale = np.abs(before).max()
    i0, i1 = invariants(before), invariants(after)
    assert np.all(np.abs(i1 - i0) <= 1e-10 * np.array([scale, scale ** 2, scale ** 3]))
    if dim == 2:
        assert abs(after[0, 2, 2] - before[0, 2, 2]) <= 1e-12 * scale
    # the rotation itself: angle 2 atan(|w| dt / 2) a step about w
    angle = steps * 2 * np.arctan(np.linalg.norm(omega) * dt / 2)
    k = omega / np.linalg.norm(omega)
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    R = np.eye(3) + np.sin(angle) * Kx + (1 - np.cos(angle)) * Kx @ Kx
    assert np.abs(R @ before[0] @ R.T - after[0]).max() <= 1e-10 * scale
    deviator = before[0] - np.trace(before[0]) / 3 * np.eye(3)
    assert np.abs(after - before).max() > 0.5 * np.abs(deviator).max()  # it did turn


# --------------------------------------------------------------- simulate
@pytest.mark.parametrize("name", sorted(MATERIALS))
def test_both_executors_run_the_plastic_materials_alike(name):
    """A block squashed under gravity on a no-slip floor, 30 steps: the
    compiled executor (compiled point law) and the reference (NumPy update)
    agree to 1e-12 in stress, sigma_zz and plastic strain; particles yield."""
    material = {"mohr-coulomb": MohrCoulomb(2e3, 0.3, 30.0, 0.5),
                "drucker-prager": DruckerPrager(2e3, 0.3, 30.0, 0.5),
                "von-mises": VonMises(2e3, 0.3, 2.0)}[name]
    grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (6, 6), 2)
    particles = Particles.seed(grid, 2, 1.0, region=((0.2, 0.8), (0.0, 0.6)),
                               velocity=lambda X: np.column_stack((0 * X[:, 0], -2.0 * X[:, 1])))
    scene = Scene(grid, Body(particles, material), 1.0,
                  effects=[Fixed("bottom"), Gravity((0.0, -9.81))])
    method = dict(scheme="musl", mass="lumped", dt=1e-3)
    scene = Scene(grid, Body(particles, material), 30 * 1e-3, effects=scene.effects)
    ref = simulate(scene, Method(backend="numpy", **method), save_every=10)
    fast = simulate(scene, Method(backend="numba", **method), save_every=10)
    assert fast.path == "fast (compiled loop)" and ref.path.startswith("reference")
    for key in ("stress", "sigma_zz", "plastic_strain"):
        a, b = ref.history[key], fast.history[key]
        assert np.abs(a - b).max() <= 1e-12 * np.abs(a).max(), key
    assert fast.particles.state["plastic_strain"].max() > 1e-4
