"""The two executors of the one scheme code agree.

Every scheme's sequence is written once (skfem_mpm.solve.schemes); the
reference executor (NumPy transfer matrices) and the compiled one (numba
kernels) run it. They must agree on every combination of scheme x mass x
degree x dimension x material x effect: the default tier runs a
pairwise-covering set (every pair of option values in at least one case),
the slow tier the full product. Tolerances: 1e-12 relative with lumped
mass; with consistent (and hybrid) mass the compiled executor solves by
conjugate gradients to rtol 1e-13 against the reference's sparse LU, so
the bound is 1e-9 relative. Hybrid mass (MUSL only) has its own covering
list, ``HYBRID``; so has the Runge-Kutta scheme (``RK4``: materials it can
stage, every mass), and the reconstructions that run compiled,
``RECONSTRUCTED`` (every scheme, mass, material and effect, degrees 2 and 3).

Tiers: pairwise (default), every triple of option values (``slow``, about
100 cases), the full product of 648 cases (``exhaustive``: run it with
``pytest -m exhaustive tests/test_executors.py`` after changing an
executor; it takes about half an hour on 2 cores).
"""
import itertools

import numpy as np
import pytest
from tiers import tiered

from skfem_mpm import (Body, BodyForce, Damping, Fixed, Gravity, LinearElastic, Method,
                       NeoHookean, Particles, Prescribed, Scene, SplineGrid, Traction, simulate)
from skfem_mpm.materials import Material, point_update
from skfem_mpm.materials.laws import linear_elastic_law
from skfem_mpm.solve.state import prepare

FACTORS = {
    "scheme": ("musl", "usl", "cd"),
    "mass": ("lumped", "consistent"),
    "degree": (1, 2, 3),
    "dim": (1, 2),
    "material": ("linear", "neo-hookean", "custom", "custom-compiled"),
    "effect": ("none", "gravity", "body-force", "traction", "prescribed", "damping"),
}


class CappedStress(Material):
    """A user's small-strain material (not fused into any kernel): linear
    elasticity with every stress component clamped to +-cap."""

    def __init__(self, E, nu, cap):
        self.inner = LinearElastic(E, nu)
        self.cap = cap

    def update(self, particles, L, dt):
        stress, V, F = self.inner.update(particles, L, dt)
        return np.clip(stress, -self.cap, self.cap), V, F

    def wave_speed(self, particles):
        return self.inner.wave_speed(particles)

    def strain_energy(self, particles):
        return self.inner.strain_energy(particles)


class SoftenedRate(Material):
    """A user's small-strain rate law that ``rk4`` can stage (not fused into
    any kernel): the linear elastic stress rate scaled by
    1 / (1 + |sigma|^2 / s^2), a hypoelastic softening."""

    def __init__(self, E, nu, s):
        self.inner = LinearElastic(E, nu)
        self.s = s

    def stress_rate(self, particles, L):
        size = np.einsum("nij,nij->n", particles.stress, particles.stress)
        return self.inner.stress_rate(particles, L) / (1 + size / self.s ** 2)[:, None, None]

    def update(self, particles, L, dt):
        _, V, F = self.inner.update(particles, L, dt)
        return particles.stress + dt * self.stress_rate(particles, L), V, F

    def wave_speed(self, particles):
        return self.inner.wave_speed(particles)

    def strain_energy(self, particles):
        return self.inner.strain_energy(particles)


@point_update
def capped_stress_law(params, L, F, dt, stress, state, stress_out, state_out):
    """CappedStress for one particle: the built-in linear elastic law (a
    user's law may call compiled library functions), then the cap;
    params: the linear law's, then the cap."""
    dim = L.shape[0]
    linear_elastic_law(params[:-1], L, F, dt, stress, state, stress_out, state_out)
    cap = params[-1]
    for i in range(dim):
        for j in range(dim):
            stress_out[i, j] = min(max(stress_out[i, j], -cap), cap)


class CappedStressCompiled(CappedStress):
    """The same material with its compiled point law."""

    point_update = capped_stress_law

    def point_parameters(self, dim):
        return np.append(self.inner.point_parameters(dim), self.cap)


def covering_cases(factors, strength=2):
    """A greedy covering set: every combination of values of any
    ``strength`` factors occurs in at least one case (deterministic). Each
    case starts from the first combination not yet covered and fills the
    other factors with the value that covers the most new combinations."""
    names = list(factors)
    groups = list(itertools.combinations(names, strength))

    def key(case, group):
        return tuple((name, case[name]) for name in group)

    uncovered = {tuple(zip(group, values)) for group in groups
                 for values in itertools.product(*(factors[n] for n in group))}

    def new_combinations(case):
        return sum(key(case, g) in uncovered for g in groups if all(n in case for n in g))

    def order(combination):
        return tuple((names.index(n), factors[n].index(v)) for n, v in combination)

    cases = []
    while uncovered:
        case = dict(min(uncovered, key=order))
        for name in names:
            if name not in case:
                case[name] = max(factors[name],
                                 key=lambda value: (new_combinations(dict(case, **{name: value})),
                                                    -factors[name].index(value)))
        case = {name: case[name] for name in names}
        cases.append(case)
        uncovered -= {key(case, g) for g in groups}
    return cases


def scene_for(case, steps=20):
    dim, degree = case["dim"], case["degree"]
    if dim == 1:
        grid = SplineGrid.line(0.0, 1.0, 8, degree)
        region = ((0.0, 0.75 if case.get("aligned") else 0.7),)
        velocity = lambda X: 0.05 * np.sin(np.pi * X)  # noqa: E731
    else:
        grid = SplineGrid.rectangle((0.0, 1.0), (0.0, 1.0), (6, 5), degree)
        region = ((0.0, 4 / 6), (0.0, 0.6)) if case.get("aligned") else ((0.0, 0.7), (0.0, 0.62))
        velocity = lambda X: np.column_stack((0.05 * X[:, 1], -0.03 * X[:, 0]))  # noqa: E731
    particles = Particles.seed(grid, case.get("ppc", 2), 1.0, region=region, velocity=velocity)
    material = {"linear": LinearElastic(10.0, 0.3),
                "neo-hookean": NeoHookean(10.0, 0.3),
                "custom": CappedStress(10.0, 0.3, 0.05),
                "custom-compiled": CappedStressCompiled(10.0, 0.3, 0.05),
                "custom-staged": SoftenedRate(10.0, 0.3, 0.05)}[case["material"]]
    base_side = "left" if dim == 1 else "bottom"
    effects = []
    effect = case["effect"]
    if effect == "prescribed":
        if dim == 1:
            effects.append(Prescribed("left", 0, lambda t: 0.02 * t))
        else:
            effects += [Fixed("bottom", 1), Prescribed("bottom", 0, lambda t: 0.02 * t)]
    else:
        effects.append(Fixed(base_side))
    g = -2.0 if dim == 1 else (0.0, -2.0)
    effects += {"none": [], "prescribed": [], "gravity": [Gravity(g)],
                "body-force": [BodyForce(lambda X, t: 0.5 * np.cos(3 * X + t))],
                "traction": [Traction("right", (lambda t: 0.01 * t) if dim == 1
                                      else (lambda t: (0.01 * t, -0.005)))],
                "damping": [Damping(0.05)]}[effect]
    scene = Scene(grid, Body(particles, material), 1.0, effects=effects)
    dt = prepare(scene, Method(scheme=case["scheme"], mass=case["mass"])).dt
    return Scene(grid, Body(particles, material), steps * dt, effects=effects)


def check_agreement(case):
    scene = scene_for(case)
    recon = case.get("reconstruction", "none")
    method = dict(scheme=case["scheme"], mass=case["mass"], reconstruction=recon)
    ref = simulate(scene, Method(backend="numpy", **method), save_every=5)
    fast = simulate(scene, Method(backend="numba", **method), save_every=5)
    paths = ("fast", "fast (compiled loop)") if recon == "none" else \
        (f"fast (reconstruction {recon})", "fast (compiled loop)")
    assert fast.path in paths and ref.path.startswith("reference"), (fast.path, ref.path)
    tol = case.get("tol", 1e-12 if case["mass"] == "lumped" else 1e-9)
    for key in ("x", "v", "stress"):
        a, b = ref.history[key], fast.history[key]
        scale = max(np.abs(a).max(), 1e-300)
        assert np.abs(a - b).max() <= tol * scale, (key, np.abs(a - b).max() / scale)
    w_ref, w_fast = ref.energies["external_work"], fast.energies["external_work"]
    assert np.abs(w_ref - w_fast).max() <= tol * max(np.abs(w_ref).max(), 1e-300) + 1e-300


PAIRWISE = covering_cases(FACTORS, 2)


def _id(case):
    return "-".join(str(v) for v in case.values())


@pytest.mark.parametrize("strength", (2, 3))
def test_the_covering_sets_cover_every_combination(strength):
    cases = covering_cases(FACTORS, strength)
    for group in itertools.combinations(FACTORS, strength):
        seen = {tuple(c[n] for n in group) for c in cases}
        assert seen == set(itertools.product(*(FACTORS[n] for n in group))), group
    assert len(cases) < {2: 35, 3: 150}[strength]


@pytest.mark.parametrize("case", PAIRWISE, ids=_id)
def test_executors_agree_pairwise(case):
    check_agreement(case)


# hybrid mass exists for MUSL only: every degree, material and effect in
# each dimension (lumped acceleration, consistent velocity re-projection)
HYBRID = [dict(scheme="musl", mass="hybrid", degree=degree, dim=dim, material=material,
               effect=effect)
          for dim, cases in ((1, ((2, "linear", "none"), (3, "neo-hookean", "gravity"),
                                  (1, "custom", "prescribed"), (2, "custom-compiled", "damping"),
                                  (3, "linear", "traction"), (2, "linear", "body-force"))),
                             (2, ((2, "linear", "gravity"), (3, "neo-hookean", "damping"),
                                  (1, "custom-compiled", "prescribed"),
                                  (2, "custom", "traction"), (3, "linear", "none"),
                                  (2, "linear", "body-force"))))
          for degree, material, effect in cases]


DEFAULT_HYBRID = {  # the default tier's cases (tests/tiers.py)
    "musl-hybrid-1-1-custom-prescribed",
    "musl-hybrid-2-1-custom-compiled-damping",
    "musl-hybrid-2-1-linear-body-force",
    "musl-hybrid-2-1-linear-none",
    "musl-hybrid-2-2-linear-gravity",
    "musl-hybrid-3-1-linear-traction",
    "musl-hybrid-3-2-neo-hookean-damping",
}


@pytest.mark.parametrize("case", tiered(
    "executors with hybrid mass", HYBRID, _id, DEFAULT_HYBRID),
                         ids=_id)
def test_executors_agree_with_hybrid_mass(case):
    check_agreement(case)


# rk4 (materials it can stage: linear, neo-Hookean, a user's rate law):
# every degree, mass (hybrid is MUSL only) and effect in each dimension
RK4 = [dict(scheme="rk4", mass=mass, degree=degree, dim=dim, material=material, effect=effect)
       for dim, cases in ((1, ((1, "lumped", "linear", "gravity"),
                               (2, "consistent", "neo-hookean", "prescribed"),
                               (3, "lumped", "custom-staged", "damping"),
                               (2, "lumped", "linear", "traction"),
                               (3, "consistent", "linear", "body-force"),
                               (1, "consistent", "custom-staged", "none"),
                               (2, "consistent", "neo-hookean", "gravity"))),
                          (2, ((2, "lumped", "neo-hookean", "gravity"),
                               (3, "lumped", "linear", "prescribed"),
                               (1, "consistent", "linear", "damping"),
                               (2, "consistent", "custom-staged", "traction"),
                               (2, "lumped", "linear", "body-force"),
                               (3, "consistent", "neo-hookean", "none"),
                               (1, "lumped", "custom-staged", "body-force"))))
       for degree, mass, material, effect in cases]


DEFAULT_RK4 = {  # the default tier's cases (tests/tiers.py)
    "rk4-consistent-1-1-custom-staged-none",
    "rk4-consistent-2-1-neo-hookean-prescribed",
    "rk4-consistent-2-2-custom-staged-traction",
    "rk4-lumped-1-1-linear-gravity",
    "rk4-lumped-1-2-custom-staged-body-force",
    "rk4-lumped-3-1-custom-staged-damping",
}


@pytest.mark.parametrize("case", tiered(
    "executors with rk4", RK4, _id, DEFAULT_RK4),
                         ids=_id)
def test_executors_agree_with_rk4(case):
    check_agreement(case)


# reconstructions on the compiled executor: 1D spline (particle knots),
# tls (the published default) and mls in 1D and 2D, the 2D spline; ppc 3
# exercises TLS's quadratic level, 2 its linear fallback. In 2D the body's
# free surfaces cut cells (x = 0.7, y = 0.62) except in the "aligned" cases
# (whole cells), so the rule's cut boxes and TLS's bound test run on both
# executors. (Before the boxes, a cut cell's conserving quadratic of a
# constant density reached rho_h = -1.7: the prescribed-motion cases
# disagreed by 7e-5 and consistent mass failed on an indefinite matrix.)
# The 2D spline in partly filled cells solves a penalised least-squares
# system of condition ~1e7 (sparse LU on both executors, assembled in
# different orders): 1e-9 there (measured 1.8e-12 in v).
RECONSTRUCTED = [dict(scheme=scheme, mass=mass, degree=degree, dim=1, material=material,
                      effect=effect, reconstruction="spline")
                 for scheme, mass, degree, material, effect in (
                     ("musl", "lumped", 2, "linear", "gravity"),
                     ("musl", "consistent", 3, "neo-hookean", "traction"),
                     ("musl", "consistent", 2, "custom", "body-force"),
                     ("usl", "consistent", 2, "custom-compiled", "prescribed"),
                     ("cd", "lumped", 3, "linear", "damping"),
                     ("cd", "consistent", 2, "linear", "gravity"),
                     ("musl", "hybrid", 3, "linear", "none"),
                     ("usl", "lumped", 3, "neo-hookean", "body-force"),
                     ("rk4", "consistent", 3, "linear", "traction"),
                     ("rk4", "lumped", 2, "custom-staged", "gravity"),
                     ("rk4", "consistent", 2, "neo-hookean", "prescribed"))] + [
    dict(scheme=scheme, mass=mass, degree=degree, dim=dim, material=material, effect=effect,
         reconstruction="tls", ppc=ppc, aligned=dim == 2 and aligned)
    for dim, scheme, mass, degree, material, effect, ppc, aligned in (
        (1, "musl", "lumped", 2, "linear", "gravity", 3, False),
        (1, "usl", "consistent", 3, "neo-hookean", "traction", 2, False),
        (1, "cd", "lumped", 3, "custom", "body-force", 4, False),
        (1, "rk4", "consistent", 2, "linear", "prescribed", 3, False),
        (1, "musl", "hybrid", 2, "custom-compiled", "damping", 3, False),
        (2, "musl", "lumped", 2, "linear", "gravity", 3, False),
        (2, "musl", "consistent", 2, "neo-hookean", "traction", 3, False),
        (2, "usl", "lumped", 3, "custom-compiled", "body-force", 2, True),
        (2, "cd", "consistent", 3, "linear", "damping", 3, False),
        (2, "rk4", "lumped", 2, "custom-staged", "prescribed", 3, False),
        (2, "rk4", "consistent", 3, "linear", "none", 2, False),
        (2, "musl", "hybrid", 3, "custom", "gravity", 3, True),
        (2, "usl", "consistent", 2, "linear", "prescribed", 3, False))] + [
    dict(scheme=scheme, mass=mass, degree=degree, dim=dim, material=material, effect=effect,
         reconstruction="mls", ppc=ppc)
    for dim, scheme, mass, degree, material, effect, ppc in (
        (1, "musl", "lumped", 2, "linear", "gravity", 2),
        (1, "usl", "consistent", 3, "neo-hookean", "traction", 3),
        (1, "rk4", "lumped", 2, "custom-staged", "damping", 2),
        (2, "musl", "lumped", 2, "linear", "body-force", 2),
        (2, "musl", "consistent", 3, "custom", "gravity", 3),
        (2, "cd", "lumped", 2, "neo-hookean", "traction", 2),
        (2, "rk4", "consistent", 2, "linear", "prescribed", 2),
        (2, "musl", "hybrid", 2, "custom-compiled", "none", 3))] + [
    dict(scheme=scheme, mass=mass, degree=degree, dim=2, material=material, effect=effect,
         reconstruction="spline", ppc=ppc, aligned=aligned,
         **({} if aligned else {"tol": 1e-9}))
    for scheme, mass, degree, material, effect, ppc, aligned in (
        ("musl", "lumped", 2, "linear", "gravity", 3, True),
        ("musl", "consistent", 3, "neo-hookean", "traction", 2, True),
        ("usl", "lumped", 2, "custom-compiled", "body-force", 2, False),
        ("rk4", "consistent", 2, "linear", "prescribed", 3, True),
        ("musl", "hybrid", 2, "custom", "damping", 3, True))]


DEFAULT_RECONSTRUCTED = {  # the default tier's cases (tests/tiers.py)
    "usl-lumped-2-2-custom-compiled-body-force-spline-2-False-1e-09",
    "cd-consistent-2-1-linear-gravity-spline",
    "cd-lumped-2-2-neo-hookean-traction-mls-2",
    "cd-lumped-3-1-custom-body-force-tls-4-False",
    "musl-consistent-2-2-neo-hookean-traction-tls-3-False",
    "musl-hybrid-3-1-linear-none-spline",
    "musl-hybrid-3-2-custom-gravity-tls-3-True",
    "musl-lumped-2-1-linear-gravity-spline",
    "rk4-consistent-2-1-neo-hookean-prescribed-spline",
    "rk4-lumped-2-1-custom-staged-damping-mls-2",
    "rk4-lumped-2-2-custom-staged-prescribed-tls-3-False",
    "usl-consistent-3-1-neo-hookean-traction-mls-3",
    "usl-lumped-3-2-custom-compiled-body-force-tls-2-True",
}


@pytest.mark.parametrize("case", tiered(
    "executors with reconstruction", RECONSTRUCTED, _id, DEFAULT_RECONSTRUCTED),
                         ids=_id)
def test_executors_agree_with_reconstruction(case):
    check_agreement(case)


@pytest.mark.slow
@pytest.mark.parametrize("case", [c for c in covering_cases(FACTORS, 3) if c not in PAIRWISE],
                         ids=_id)
def test_executors_agree_three_wise(case):
    check_agreement(case)


@pytest.mark.exhaustive
@pytest.mark.parametrize("case", [dict(zip(FACTORS, values))
                                  for values in itertools.product(*FACTORS.values())], ids=_id)
def test_executors_agree_on_every_combination(case):
    check_agreement(case)
