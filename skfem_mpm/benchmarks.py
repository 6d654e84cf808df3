"""The benchmark problems of the project (shared/BENCHMARKS.md), each able to
build a :class:`Scene` and knowing its exact solution.

    get_benchmark("vibrating-string", variant="small", L=1.0)

Every benchmark has ``defaults`` (parameters), ``variants`` (named parameter
sets; the first is the default), ``scene(cells, degree, ppc, ...)``,
``displacement(X, t)``, ``velocity(X, t)``, ``stress(X, t)`` where an exact
stress exists, ``amplitude`` (the displacement scale errors are divided by)
and ``errors(result)``. ``cells`` counts the cells over the body's length per
axis; grids that must extend beyond the body (traction bar) add cells of the
same size.

Error measure (relative to ``amplitude`` unless the name says ``_abs``):

    e_RMS(t) = sqrt( (1/n_p) sum_p |u_h(X_p, t) - u(X_p, t)|^2 )
"""
import numpy as np

from .effects import BodyForce, Damping, Fixed, Footing, Gravity, Traction, Wall
from .geostatic import geostatic_stress
from .materials import (
    BBar,
    LinearElastic,
    MohrCoulomb,
    NeoHookean,
    VonMises,
    lame_parameters,
)
from .particles import Particles
from .scene import Body, Scene
from .spline import SplineGrid

__all__ = ["BENCHMARKS", "get_benchmark", "Benchmark"]


class Benchmark:
    """Base class: parameters, variants, scene building and error measures."""

    name = ""
    title = ""
    dim = 1
    defaults = {}
    variants = {}
    has_exact = True
    #: the error measure studies converge on: "error_rms" (at t_end) or
    #: "error_max" (over the saves) where t_end is a zero of the exact
    #: displacement (S2 after whole periods, S3 after one period)
    primary_error = "error_rms"
    #: saves per run a study needs for ``primary_error``
    saves = 1
    #: {variant: why its exact solution is not the model's}: a study of such
    #: a variant measures the model's departure, and says so in its header
    model_gaps = {}
    #: the parameters that set the exact displacement's amplitude (errors are
    #: relative to it, so it must not vanish)
    amplitude_params = ()

    def __init__(self, variant=None, **params):
        names = list(self.variants)
        if variant is None:
            variant = names[0]
        if variant not in self.variants:
            raise ValueError(f"variant must be one of {names} for {self.name}, got {variant!r}")
        unknown = set(params) - set(self.defaults)
        if unknown:
            raise ValueError(f"unknown parameter(s) {sorted(unknown)} for {self.name}; "
                             f"valid: {sorted(self.defaults)}")
        self.variant = variant
        self.explicit = set(params)
        self.params = {**self.defaults, **self.variants[variant], **params}
        for k, v in self.params.items():
            if v is None:
                continue
            if not isinstance(v, (int, float, np.floating, np.integer)) or not np.isfinite(v):
                raise ValueError(f"parameter {k} must be a finite number, got {v!r}")
        self._check_params()
        t_end = self.params.get("t_end")
        if t_end is not None and not t_end > 0:  # 0 once silently meant the default
            raise ValueError(f"parameter t_end must be > 0 (or omitted for {self.name}'s own end "
                             f"time), got {t_end}")
        self.t_end = float(t_end) if t_end is not None else self.default_t_end()
        if self.has_exact and not abs(self.amplitude) > 0:
            given = ", ".join(f"{k}={self.params[k]}" for k in self.amplitude_params)
            raise ValueError(f"parameters {given}: the exact displacement of {self.name} is 0 "
                             f"everywhere, and its errors are relative to its amplitude; give "
                             f"a nonzero {' or '.join(self.amplitude_params)}")

    def _check_params(self):
        for k in ("E", "rho", "rho0", "L", "H"):
            if k in self.params and not self.params[k] > 0:
                raise ValueError(f"parameter {k} must be > 0, got {self.params[k]}")
        if "nu" in self.params and not -1 < self.params["nu"] < 0.5:
            raise ValueError(f"parameter nu must lie in (-1, 0.5), got {self.params['nu']}")

    def __getattr__(self, key):
        params = self.__dict__.get("params")
        if params is not None and key in params:
            return params[key]
        raise AttributeError(key)

    def __repr__(self):
        return f"{type(self).__name__}(variant={self.variant!r}, {self.params})"

    # to be provided by subclasses ---------------------------------------------
    def default_t_end(self):
        raise NotImplementedError

    def scene(self, cells, degree, ppc=2, layout="uniform", fem=False, t_end=None):
        raise NotImplementedError

    def stress(self, X, t):
        return None

    def velocity_amplitude(self):
        return None

    def stress_amplitude(self):
        return None

    # errors -------------------------------------------------------------------
    def errors(self, result):
        """Error measures of a run (relative to the amplitudes)."""
        if not self.has_exact:
            raise ValueError(f"{self.name} has no exact solution; use its checks()")
        h = result.history
        rms = []
        for k, t in enumerate(result.times):
            X = h["X"][k]
            du = h["u"][k] - self.displacement(X, t)
            rms.append(float(np.sqrt(np.mean(np.sum(du * du, axis=1)))))
        X, t = h["X"][-1], result.times[-1]
        out = {
            "error_rms": rms[-1] / abs(self.amplitude),
            "error_max": max(rms) / abs(self.amplitude),
            "error_rms_abs": rms[-1],
        }
        dv = h["v"][-1] - self.velocity(X, t)
        out["velocity_error_rms"] = float(np.sqrt(np.mean(np.sum(dv * dv, axis=1)))) \
            / abs(self.velocity_amplitude())
        s_exact = self.stress(X, t)
        if s_exact is not None:
            ds = h["stress"][-1] - s_exact
            out["stress_error_rms"] = float(np.sqrt(np.mean(np.sum(ds * ds, axis=(1, 2))))) \
                / abs(self.stress_amplitude())
        return out


def _column(a):
    return np.asarray(a, dtype=np.float64).reshape(-1, 1)


# ----------------------------------------------------------------------- S1
class VibratingString(Benchmark):
    """S1: rho u_tt = E u_xx on (0, L), both ends fixed, initial velocity
    v0 sin(pi x / L); u = (v0 / w) sin(w t) sin(pi x / L), w = (pi / L) c."""

    name = "vibrating-string"
    title = "S1 vibrating string"
    defaults = {"L": 25.0, "E": 100.0, "rho": 1.0, "v0": 0.1, "t_end": None}
    variants = {"small": {}, "seed": {"v0": 0.1}}
    amplitude_params = ("v0",)

    @property
    def c(self):
        return float(np.sqrt(self.E / self.rho))

    @property
    def omega(self):
        return np.pi / self.L * self.c

    def _check_params(self):
        super()._check_params()
        if self.variant == "small" and "v0" not in self.explicit:
            self.params["v0"] = 1e-6 * self.c  # peak strain v0 / c = 1e-6

    def default_t_end(self):
        return 0.25 * 2 * np.pi / self.omega  # quarter period: largest displacement

    @property
    def amplitude(self):
        return self.v0 / self.omega

    def velocity_amplitude(self):
        return self.v0

    def stress_amplitude(self):
        return self.E * self.amplitude * np.pi / self.L

    def displacement(self, X, t):
        X = _column(X)
        return self.amplitude * np.sin(self.omega * t) * np.sin(np.pi * X / self.L)

    def velocity(self, X, t):
        X = _column(X)
        return self.v0 * np.cos(self.omega * t) * np.sin(np.pi * X / self.L)

    def stress(self, X, t):
        X = _column(X)
        eps = self.amplitude * np.sin(self.omega * t) * np.pi / self.L * np.cos(np.pi * X / self.L)
        return (self.E * eps)[:, :, None]

    def scene(self, cells, degree, ppc=2, layout="uniform", fem=False, t_end=None):
        grid = SplineGrid.line(0.0, self.L, cells, degree)
        particles = Particles.seed(grid, ppc, self.rho, layout=layout, seed=0,
                                   velocity=lambda X: self.velocity(X, 0.0))
        return Scene(grid, Body(particles, LinearElastic(self.E)), self.t_end if t_end is None else t_end,
                     effects=[Fixed("left"), Fixed("right")])


# ----------------------------------------------------------------------- S2
class SoilColumn(Benchmark):
    """S2: a column fixed at its base, gravity switched on at t = 0 (series
    solution; optional top traction p0)."""

    name = "soil-column"
    title = "S2 soil column under self-weight"
    primary_error = "error_max"
    saves = 40
    defaults = {"H": 1.0, "E": 1e5, "rho": 1e3, "g": 9.81, "p0": 0.0, "periods": 2.0,
                "t_end": None, "terms": 200}
    variants = {"large": {"E": 1e5}, "small": {"E": 1e10}}
    amplitude_params = ("g", "p0")
    model_gaps = {"large": (
        "the exact solution is the linear wave equation's, but at this variant's 10% strain "
        "the updated-Lagrangian LinearElastic follows sigma = E ln F (Hencky in 1D), which "
        "departs from it by about 15% of the amplitude: errors near that level measure the "
        "model, not the method (tests/hard compares with a fine FEM of the same model); "
        "use --variant small for the method's convergence")}

    def _check_params(self):
        super()._check_params()
        if not self.params["periods"] > 0:
            raise ValueError(f"parameter periods (the end time in periods of the column) must be "
                             f"> 0, got {self.params['periods']}")
        terms = self.params["terms"]
        if not (terms >= 1 and float(terms).is_integer()):  # int() truncated 2.5 and kept 0
            raise ValueError(f"parameter terms (modes of the series solution) must be a whole "
                             f"number >= 1, got {terms}")

    @property
    def c(self):
        return float(np.sqrt(self.E / self.rho))

    @property
    def period(self):
        """The column's fundamental period 4 H / c (a quarter wave)."""
        return 4 * self.H / self.c

    def default_t_end(self):
        return self.periods * self.period

    def _modes(self):
        n = np.arange(1, int(self.terms) + 1)
        k = (2 * n - 1) * np.pi / (2 * self.H)
        coef = 2 * self.g / (self.H * self.c ** 2 * k ** 3) \
            - 2 * self.p0 * (-1.0) ** (n + 1) / (self.E * self.H * k ** 2)
        return k, coef

    def _static(self, y):
        return -(self.g / self.c ** 2) * (self.H * y - 0.5 * y ** 2) + self.p0 * y / self.E

    def displacement(self, X, t):
        y = _column(X)[:, 0]
        k, coef = self._modes()
        modes = np.sin(np.outer(y, k)) @ (coef * np.cos(self.c * k * t))
        return (self._static(y) + modes)[:, None]

    def velocity(self, X, t):
        y = _column(X)[:, 0]
        k, coef = self._modes()
        return (np.sin(np.outer(y, k)) @ (-coef * self.c * k * np.sin(self.c * k * t)))[:, None]

    def stress(self, X, t):
        y = _column(X)[:, 0]
        k, coef = self._modes()
        static = -(self.g / self.c ** 2) * (self.H - y) + self.p0 / self.E
        modes = np.cos(np.outer(y, k)) @ (coef * k * np.cos(self.c * k * t))
        return (self.E * (static + modes))[:, None, None]

    @property
    def amplitude(self):
        """The largest exact displacement, max over t of |u(H, t)|."""
        ts = np.linspace(0.0, 4 * self.H / self.c, 2001)
        top = [abs(self.displacement(np.array([self.H]), t)[0, 0]) for t in ts]
        return float(max(top))

    def velocity_amplitude(self):
        return self.amplitude * self.c * np.pi / (2 * self.H)

    def stress_amplitude(self):
        return self.rho * self.g * self.H + abs(self.p0)

    def scene(self, cells, degree, ppc=2, layout="uniform", fem=False, t_end=None):
        """``cells`` over the column; with a top tension (p0 > 0) the MPM grid
        extends a quarter of the height above the column (the top rises)."""
        h = self.H / cells
        extra = int(np.ceil(0.25 * cells)) if (self.p0 > 0 and not fem) else 0
        grid = SplineGrid(np.linspace(0.0, self.H + extra * h, cells + extra + 1), degree)
        particles = Particles.seed(grid, ppc, self.rho, layout=layout, seed=0,
                                   region=((0.0, self.H),))
        effects = [Fixed("left"), Gravity(-self.g)]
        if self.p0:
            effects.append(Traction("right", self.p0))
        return Scene(grid, Body(particles, LinearElastic(self.E)), self.t_end if t_end is None else t_end,
                     effects=effects)


# ----------------------------------------------------------------------- S3
class TractionBar(Benchmark):
    """S3: a bar fixed at x = 0 and loaded at its free end by the traction
    that keeps u = A sin(k x) sin(c k t), k = 3 pi / (4 L), exact."""

    name = "traction-bar"
    title = "S3 vibrating bar with a dynamic end traction"
    primary_error = "error_max"
    saves = 20
    defaults = {"L": 1.0, "E": 100.0, "rho": 1.0, "A": 0.01, "margin": 0.25, "t_end": None}
    variants = {"small": {"A": 1e-7}, "large": {"A": 0.01}}
    amplitude_params = ("A",)
    model_gaps = {"large": (
        "the exact solution is the linear wave equation's, but at this variant's 2.4% strain "
        "(A k) the updated-Lagrangian LinearElastic follows sigma = E ln F (Hencky in 1D), "
        "which departs from it by 0.88% of the amplitude (max over the period; a fine FEM "
        "of that model, 32 and 64 cubic cells alike): errors near that level measure the "
        "model, not the method; use --variant small for the method's convergence")}

    @property
    def c(self):
        return float(np.sqrt(self.E / self.rho))

    @property
    def k(self):
        return 3 * np.pi / (4 * self.L)

    @property
    def period(self):
        """The period 2 pi / (c k) of the forced mode."""
        return 2 * np.pi / (self.c * self.k)

    def default_t_end(self):
        return self.period

    @property
    def amplitude(self):
        return self.A

    def velocity_amplitude(self):
        return self.A * self.c * self.k

    def stress_amplitude(self):
        return self.E * self.A * self.k

    def traction(self, t):
        return self.E * self.A * self.k * np.cos(self.k * self.L) * np.sin(self.c * self.k * t)

    def displacement(self, X, t):
        return self.A * np.sin(self.k * _column(X)) * np.sin(self.c * self.k * t)

    def velocity(self, X, t):
        return self.A * self.c * self.k * np.sin(self.k * _column(X)) * np.cos(self.c * self.k * t)

    def stress(self, X, t):
        eps = self.A * self.k * np.cos(self.k * _column(X)) * np.sin(self.c * self.k * t)
        return (self.E * eps)[:, :, None]

    def scene(self, cells, degree, ppc=2, layout="uniform", fem=False, t_end=None):
        h = self.L / cells
        extra = 0 if fem else int(np.ceil(self.margin * cells))
        grid = SplineGrid(np.linspace(0.0, self.L + extra * h, cells + extra + 1), degree)
        particles = Particles.seed(grid, ppc, self.rho, layout=layout, seed=0,
                                   region=((0.0, self.L),),
                                   velocity=lambda X: self.velocity(X, 0.0))
        effects = [Fixed("left"), Traction("right", self.traction)]
        return Scene(grid, Body(particles, LinearElastic(self.E)), self.t_end if t_end is None else t_end,
                     effects=effects)


# ----------------------------------------------------------------------- S4
class NeoHookeanBar(Benchmark):
    """S4: manufactured large-deformation solution of a neo-Hookean bar,
    u = G sin(pi X) sin(c pi t), with the body force that makes it exact."""

    name = "neo-hookean-bar"
    title = "S4 large-deformation neo-Hookean bar"
    defaults = {"E": 1e7, "rho0": 1e3, "G": 0.05, "t_end": 0.02}
    variants = {"large": {"G": 0.05}, "small": {"G": 1e-4}}
    amplitude_params = ("G",)

    @property
    def c(self):
        return float(np.sqrt(self.E / self.rho0))

    def default_t_end(self):
        return 0.02

    @property
    def amplitude(self):
        return self.G

    def velocity_amplitude(self):
        return self.G * self.c * np.pi

    def stress_amplitude(self):
        return self.E * self.G * np.pi

    def displacement(self, X, t):
        return self.G * np.sin(np.pi * _column(X)) * np.sin(self.c * np.pi * t)

    def velocity(self, X, t):
        return self.G * self.c * np.pi * np.sin(np.pi * _column(X)) * np.cos(self.c * np.pi * t)

    def deformation_gradient(self, X, t):
        return 1 + np.pi * self.G * np.cos(np.pi * _column(X)) * np.sin(self.c * np.pi * t)

    def first_piola(self, F):
        mu = self.E / 2
        return mu * (F - 1 / F)

    def stress(self, X, t):
        return self.first_piola(self.deformation_gradient(X, t))[:, :, None]

    def body_force(self, X, t):
        """b = (pi^2 u / rho0) (lambda (1 - ln F) / F^2 + mu (1 + 1/F^2) - E), lambda = 0."""
        u = self.displacement(X, t)
        F = self.deformation_gradient(X, t)
        mu = self.E / 2
        return (np.pi ** 2 * u / self.rho0) * (mu * (1 + 1 / F ** 2) - self.E)

    def scene(self, cells, degree, ppc=2, layout="uniform", fem=False, t_end=None):
        grid = SplineGrid.line(0.0, 1.0, cells, degree)
        particles = Particles.seed(grid, ppc, self.rho0, layout=layout, seed=0,
                                   velocity=lambda X: self.velocity(X, 0.0))
        return Scene(grid, Body(particles, NeoHookean(self.E)), self.t_end if t_end is None else t_end,
                     effects=[Fixed("left"), Fixed("right"), BodyForce(self.body_force)])


# ----------------------------------------------------------------------- D1
def _sliding_walls():
    return [Fixed("left", 0), Fixed("right", 0), Fixed("bottom", 1), Fixed("top", 1)]


def _sliding_walls_3d():
    return [Fixed(side, axis) for axis, pair in enumerate((("xmin", "xmax"), ("ymin", "ymax"),
                                                           ("zmin", "zmax")))
            for side in pair]


class AxisAligned2D(Benchmark):
    """D1: manufactured axis-aligned finite deformation of the unit square
    (compressible neo-Hookean, plane strain), sliding walls."""

    name = "axis-aligned-2d"
    title = "D1 axis-aligned displacement (neo-Hookean, 2D)"
    dim = 2
    defaults = {"E": 1e4, "nu": 0.3, "rho0": 1.0, "A": 0.05, "t_end": None}
    variants = {"large": {"A": 0.05}, "small": {"A": 1e-4}}
    amplitude_params = ("A",)

    @property
    def c(self):
        return float(np.sqrt(self.E / self.rho0))

    def default_t_end(self):
        return 2.0 / self.c

    @property
    def amplitude(self):
        return self.A

    def velocity_amplitude(self):
        return self.A * self.c * np.pi

    def stress_amplitude(self):
        lam, mu = lame_parameters(self.E, self.nu)
        return (lam + 2 * mu) * self.A * np.pi

    #: phase of each component: u_i = A sin(pi X_i) sin(c pi t + theta_i)
    phases = (0.0, np.pi, 0.0)

    def _theta(self):
        return np.array(self.phases[:self.dim])

    def displacement(self, X, t):
        return self.A * np.sin(np.pi * X) * np.sin(self.c * np.pi * t + self._theta())

    def velocity(self, X, t):
        w = self.A * self.c * np.pi
        return w * np.sin(np.pi * X) * np.cos(self.c * np.pi * t + self._theta())

    def deformation_gradient(self, X, t):
        F = np.zeros((X.shape[0], self.dim, self.dim))
        stretch = 1 + self.A * np.pi * np.cos(np.pi * X) * np.sin(self.c * np.pi * t + self._theta())
        for i in range(self.dim):
            F[:, i, i] = stretch[:, i]
        return F

    def stress(self, X, t):
        return NeoHookean(self.E, self.nu).cauchy_stress(self.deformation_gradient(X, t))

    def body_force(self, X, t):
        """b_i = pi^2 U_i (mu / rho0 - c^2 - (lambda (ln J - 1) - mu) / (rho0 F_ii^2)),
        J = prod_i F_ii."""
        lam, mu = lame_parameters(self.E, self.nu)
        U = self.displacement(X, t)
        F = self.deformation_gradient(X, t)
        diagonal = np.stack([F[:, i, i] for i in range(self.dim)], axis=1)
        lnJ = np.log(diagonal.prod(axis=1))
        return np.pi ** 2 * U * (mu / self.rho0 - self.c ** 2
                                 - (lam * (lnJ - 1) - mu)[:, None] / (self.rho0 * diagonal ** 2))

    def scene(self, cells, degree, ppc=2, layout="uniform", fem=False, t_end=None):
        unit = ((0, 1),) * self.dim
        grid = (SplineGrid.rectangle(*unit, cells, degree) if self.dim == 2
                else SplineGrid.box(*unit, cells, degree))
        particles = Particles.seed(grid, ppc, self.rho0, layout=layout, seed=0,
                                   velocity=lambda X: self.velocity(X, 0.0))
        walls = _sliding_walls() if self.dim == 2 else _sliding_walls_3d()
        return Scene(grid, Body(particles, NeoHookean(self.E, self.nu)), self.t_end if t_end is None else t_end,
                     effects=walls + [BodyForce(self.body_force)])


class AxisAligned3D(AxisAligned2D):
    """T2: D1 with a third component, u_i = A sin(pi X_i) sin(c pi t + theta_i),
    theta = (0, pi, 0), in the unit cube with sliding walls (compressible
    neo-Hookean, 3D; shared/BENCHMARKS.md, T2)."""

    name = "axis-aligned-3d"
    title = "T2 axis-aligned displacement (neo-Hookean, 3D)"
    dim = 3


# ----------------------------------------------------------------------- D2
class VibratingPlate2D(Benchmark):
    """D2: the dilatational mode of a plate with sliding walls (linear
    elastic, plane strain), exact."""

    name = "vibrating-plate-2d"
    title = "D2 vibrating plate (linear elastic, 2D)"
    dim = 2
    defaults = {"E": 100.0, "nu": 0.3, "rho": 1.0, "A": 1e-3, "t_end": None}
    variants = {"small": {"A": 1e-7}, "large": {"A": 1e-3}}
    amplitude_params = ("A",)

    @property
    def omega(self):
        lam, mu = lame_parameters(self.E, self.nu)
        return float(np.pi * np.sqrt(2 * (lam + 2 * mu) / self.rho))

    def default_t_end(self):
        return np.pi / (2 * self.omega)

    @property
    def amplitude(self):
        return self.A

    def velocity_amplitude(self):
        return self.A * self.omega

    def stress_amplitude(self):
        lam, mu = lame_parameters(self.E, self.nu)
        return (lam + 2 * mu) * self.A * np.pi

    def _shape(self, X):
        x, y = X[:, 0], X[:, 1]
        return np.column_stack((np.sin(np.pi * x) * np.cos(np.pi * y),
                                np.cos(np.pi * x) * np.sin(np.pi * y)))

    def displacement(self, X, t):
        return self.A * np.sin(self.omega * t) * self._shape(X)

    def velocity(self, X, t):
        return self.A * self.omega * np.cos(self.omega * t) * self._shape(X)

    def stress(self, X, t):
        lam, mu = lame_parameters(self.E, self.nu)
        x, y = X[:, 0], X[:, 1]
        s = self.A * np.pi * np.sin(self.omega * t)
        exx = s * np.cos(np.pi * x) * np.cos(np.pi * y)
        eyy = exx
        exy = -s * np.sin(np.pi * x) * np.sin(np.pi * y)
        out = np.zeros((X.shape[0], 2, 2))
        out[:, 0, 0] = lam * (exx + eyy) + 2 * mu * exx
        out[:, 1, 1] = lam * (exx + eyy) + 2 * mu * eyy
        out[:, 0, 1] = out[:, 1, 0] = 2 * mu * exy
        return out

    def scene(self, cells, degree, ppc=2, layout="uniform", fem=False, t_end=None):
        grid = SplineGrid.rectangle((0, 1), (0, 1), cells, degree)
        particles = Particles.seed(grid, ppc, self.rho, layout=layout, seed=0,
                                   velocity=lambda X: self.velocity(X, 0.0))
        return Scene(grid, Body(particles, LinearElastic(self.E, self.nu)), self.t_end if t_end is None else t_end,
                     effects=_sliding_walls())


# ----------------------------------------------------------------------- T1
class VibratingCube3D(Benchmark):
    """T1: the irrotational mode of a unit cube with sliding walls (linear
    elastic, 3D), exact:

        u_i = A sin(pi x_i) prod_(j != i) cos(pi x_j) sin(w t),
        w = pi sqrt(3 (lambda + 2 mu) / rho),

    u = grad phi with phi = -(A / pi) prod_j cos(pi x_j) sin(w t), so
    rho u_tt = (lambda + 2 mu) grad div u = -(lambda + 2 mu) 3 pi^2 u, and the
    shear tractions vanish on the walls (shared/BENCHMARKS.md, T1)."""

    name = "vibrating-cube"
    title = "T1 vibrating cube (linear elastic, 3D)"
    dim = 3
    defaults = {"E": 100.0, "nu": 0.3, "rho": 1.0, "A": 1e-3, "t_end": None}
    variants = {"small": {"A": 1e-7}, "large": {"A": 1e-3}}
    amplitude_params = ("A",)

    @property
    def omega(self):
        lam, mu = lame_parameters(self.E, self.nu)
        return float(np.pi * np.sqrt(3 * (lam + 2 * mu) / self.rho))

    def default_t_end(self):
        return np.pi / (2 * self.omega)

    @property
    def amplitude(self):
        return self.A

    def velocity_amplitude(self):
        return self.A * self.omega

    def stress_amplitude(self):
        lam, mu = lame_parameters(self.E, self.nu)
        return (lam + 2 * mu) * self.A * np.pi

    def _shape(self, X):
        s, c = np.sin(np.pi * X), np.cos(np.pi * X)
        return np.column_stack((s[:, 0] * c[:, 1] * c[:, 2],
                                c[:, 0] * s[:, 1] * c[:, 2],
                                c[:, 0] * c[:, 1] * s[:, 2]))

    def displacement(self, X, t):
        return self.A * np.sin(self.omega * t) * self._shape(X)

    def velocity(self, X, t):
        return self.A * self.omega * np.cos(self.omega * t) * self._shape(X)

    def strain(self, X, t):
        """eps_ii = A pi prod_j cos(pi x_j) sin(w t);
        eps_ik = -A pi sin(pi x_i) sin(pi x_k) cos(pi x_l) sin(w t), l the third axis."""
        s, c = np.sin(np.pi * X), np.cos(np.pi * X)
        a = self.A * np.pi * np.sin(self.omega * t)
        eps = np.empty((X.shape[0], 3, 3))
        diagonal = a * c.prod(axis=1)
        for i in range(3):
            eps[:, i, i] = diagonal
            for k in range(i + 1, 3):
                third = 3 - i - k
                eps[:, i, k] = eps[:, k, i] = -a * s[:, i] * s[:, k] * c[:, third]
        return eps

    def stress(self, X, t):
        lam, mu = lame_parameters(self.E, self.nu)
        eps = self.strain(X, t)
        return 2 * mu * eps + lam * np.trace(eps, axis1=1, axis2=2)[:, None, None] * np.eye(3)

    def scene(self, cells, degree, ppc=2, layout="uniform", fem=False, t_end=None):
        grid = SplineGrid.box((0, 1), (0, 1), (0, 1), cells, degree)
        particles = Particles.seed(grid, ppc, self.rho, layout=layout, seed=0,
                                   velocity=lambda X: self.velocity(X, 0.0))
        return Scene(grid, Body(particles, LinearElastic(self.E, self.nu)),
                     self.t_end if t_end is None else t_end, effects=_sliding_walls_3d())


# ----------------------------------------------------------------------- D3
class CollidingDisks(Benchmark):
    """D3: two elastic disks collide and separate (Sulsky, Chen, Schreyer
    1994). No exact solution: :meth:`checks` measures energy, momentum,
    point symmetry and separation."""

    name = "colliding-disks"
    title = "D3 colliding disks"
    dim = 2
    has_exact = False
    defaults = {"E": 1000.0, "nu": 0.3, "rho": 1000.0, "radius": 0.2, "speed": 0.1,
                "t_end": 3.5}
    variants = {"default": {}}

    #: the centres of the two bodies (the first moves along +(1, ..., 1))
    centres = ((0.2, 0.2), (0.8, 0.8))

    def default_t_end(self):
        return 3.5

    amplitude = 1.0

    def scene(self, cells=20, degree=2, ppc=2, layout="uniform", fem=False, t_end=None):
        unit = ((0, 1),) * self.dim
        grid = (SplineGrid.rectangle(*unit, cells, degree) if self.dim == 2
                else SplineGrid.box(*unit, cells, degree))
        bodies = []
        for centre, sign in zip(self.centres, (1.0, -1.0)):
            ball = (lambda X, c=np.array(centre): ((X - c) ** 2).sum(axis=1) < self.radius ** 2)
            p = Particles.seed(grid, ppc, self.rho, layout=layout, region=ball, seed=0,
                               velocity=np.full(self.dim, sign * self.speed))
            bodies.append(Body(p, LinearElastic(self.E, self.nu)))
        return Scene(grid, bodies, self.t_end if t_end is None else t_end)

    def checks(self, result):
        """Energy growth, momentum and symmetry figures of a run."""
        e = result.energies["total"]
        h = result.history
        m = result.particles.m
        first = result.particles.body == 0
        p0 = np.linalg.norm(m[first] @ h["v"][0][first])
        momentum = max(np.linalg.norm(m @ v) for v in h["v"]) / p0
        # point reflection about the centre: particle i of body 0 <-> its mirror in body 1
        x = h["x"][-1]
        X = h["X"][0]
        mirror = _mirror_index(X)
        sym = float(np.abs(x + x[mirror] - 1.0).max())
        d0 = x[first].mean(axis=0)
        d1 = x[~first].mean(axis=0)
        gap = float(np.linalg.norm(d1 - d0) - 2 * self.radius)
        return {"energy_growth": float((e.max() - e[0]) / e[0]), "momentum": float(momentum),
                "symmetry": sym, "centre_gap": gap}


class CollidingSpheres3D(CollidingDisks):
    """T3: D3 in the unit cube, two elastic spheres of radius 0.2 at
    (0.25, 0.25, 0.25) and (0.75, 0.75, 0.75) moving at +-(0.1, 0.1, 0.1)
    (shared/BENCHMARKS.md, T3). No exact solution: :meth:`checks` as D3."""

    name = "colliding-spheres"
    title = "T3 colliding spheres"
    dim = 3
    centres = ((0.25, 0.25, 0.25), (0.75, 0.75, 0.75))


# ----------------------------------------------------------------------- G4
class GeostaticStress(Benchmark):
    """G4: an elastic soil layer of depth H between sliding side walls on a
    fixed base, under gravity (shared/BENCHMARKS.md, G4). Exact at rest:
    sigma_v = -rho g (H - Y), sigma_h = K0 sigma_v, K0 = nu / (1 - nu)
    (Y the reference height; tension positive).

    Variants: "loading" starts stress-free and brings the layer to rest with
    Cundall's local damping (``damping`` = alpha, :class:`Damping`);
    "k0-procedure" starts from :func:`geostatic_stress` (``K0``, default the
    elastic value) with Gauss-point particles (``layout="gauss"``: with a
    stress linear in depth the particle quadrature is then exact, so the
    discrete equations are in equilibrium) and no damping, and must stay at
    rest. ``transits`` sets t_end in P-wave transit times H / c,
    c = sqrt((lambda + 2 mu) / rho). ``cells`` counts the cells over the
    depth; the layer is ``width`` wide. :meth:`checks` reports the ratio
    sigma_h / sigma_v over the particles at least one cell below the
    surface (``k0_error_max``: the largest |ratio / K0 - 1|)."""

    name = "geostatic-stress"
    title = "G4 geostatic stress (K0)"
    dim = 2
    has_exact = False
    defaults = {"H": 10.0, "rho": 2.0, "g": 9.81, "E": 1e4, "nu": 0.3, "width": 2.5,
                "damping": 0.7, "transits": 20.0, "K0": None, "k0_start": 0.0,
                "t_end": None}
    variants = {"loading": {}, "k0-procedure": {"k0_start": 1.0, "damping": 0.0,
                                                "transits": 10.0}}
    amplitude = 1.0

    @property
    def k0(self):
        return self.nu / (1 - self.nu) if self.K0 is None else float(self.K0)

    @property
    def c(self):
        lam, mu = lame_parameters(self.E, self.nu)
        return float(np.sqrt((lam + 2 * mu) / self.rho))

    def default_t_end(self):
        return self.transits * self.H / self.c

    def scene(self, cells=20, degree=2, ppc=2, layout=None, fem=False, t_end=None):
        h = self._h = self.H / cells
        across = max(1, int(round(self.width / h)))
        grid = SplineGrid.rectangle((0.0, across * h), (0.0, self.H), (across, cells), degree)
        if layout is None:
            layout = "gauss" if self.k0_start else "uniform"
        particles = Particles.seed(grid, ppc, self.rho, layout=layout, seed=0)
        if self.k0_start:
            particles = geostatic_stress(particles, self.H, self.g, K0=self.k0)
        effects = [Fixed("left", 0), Fixed("right", 0), Fixed("bottom"),
                   Gravity((0.0, -self.g))]
        if self.damping:
            effects.append(Damping(self.damping))
        return Scene(grid, Body(particles, LinearElastic(self.E, self.nu)),
                     self.t_end if t_end is None else t_end, effects=effects)

    def checks(self, result):
        """K0 ratio, vertical stress and speed figures of a run's last save
        (of the scene this benchmark built last)."""
        p = result.particles
        X, s = p.X, p.stress
        h = self._h  # the cell size of the last scene built
        deep = X[:, 1] <= self.H - h * (1 - 1e-9)
        ratio = s[deep, 0, 0] / s[deep, 1, 1]
        exact_v = -self.rho * self.g * (self.H - X[:, 1])
        speed = np.sqrt(np.einsum("ij,ij->i", p.v, p.v)).max()
        return {"k0": self.k0, "k0_ratio_mean": float(ratio.mean()),
                "k0_ratio_min": float(ratio.min()), "k0_ratio_max": float(ratio.max()),
                "k0_error_max": float(np.abs(ratio / self.k0 - 1).max()),
                "sigma_v_error_max": float(np.abs(s[:, 1, 1] - exact_v).max()
                                           / (self.rho * self.g * self.H)),
                "speed_max_over_sqrt_gH": float(speed / np.sqrt(self.g * self.H)),
                "particles_checked": int(deep.sum())}


# ----------------------------------------------------------------------- G2
class ColumnCollapse(Benchmark):
    """G2: a column of dry cohesionless grains, width L0 and height
    H0 = a L0, against a smooth wall on its left (``Wall("left")``, no
    friction), released at t = 0 onto a rough floor (``Wall("bottom",
    friction=tan(floor_angle))``) under gravity (shared/BENCHMARKS.md, G2;
    Lube, Huppert, Sparks, Freundt 2005; Balmforth and Kerswell 2005).

    Material: :class:`MohrCoulomb` with ``phi`` (30 deg), dilation 0,
    cohesion ``c`` (0), the Hughes-Winget objective update
    (``large_deformation=True``) and grains that lose contact above the
    volume ratio ``disconnect`` (``disconnect_at``, 1.01: a dilation well
    above the elastic strains, 0 switches it off), E = ``stiffness`` rho g H0
    (2e3: rho g H0 / E = 5e-4 < 1e-3 as G2 asks), nu 0.3; started from the
    geostatic state with Jaky's K0 = 1 - sin(phi) (or ``K0``). ``cells``
    counts the cells across L0; the grid is (2 + 2 a) L0 wide and
    H0 + L0 / 4 high (at least a cell above the column). t_end =
    ``duration`` sqrt(H0 / g) (10: the grid's kinetic energy is then below
    1e-4 of the potential energy released). :meth:`checks` reports the
    runout (L_inf - L0) / L0 by several fronts, the final height ratio
    H_inf / H0, the experiments' scalings 1.2 a and 1.9 a^(2/3), and the
    kinetic energy left."""

    name = "column-collapse"
    title = "G2 granular column collapse"
    dim = 2
    has_exact = False
    defaults = {"a": 1.0, "L0": 1.0, "rho": 1.0, "g": 9.81, "phi": 30.0, "c": 0.0,
                "floor_angle": 30.0, "nu": 0.3, "stiffness": 2e3, "duration": 10.0,
                "K0": None, "disconnect": 1.01, "front_thickness": 0.05, "t_end": None}
    variants = {"default": {}}
    amplitude = 1.0

    @property
    def H0(self):
        return self.a * self.L0

    def default_t_end(self):
        return self.duration * np.sqrt(self.H0 / self.g)

    def scene(self, cells=16, degree=2, ppc=2, layout="uniform", fem=False, t_end=None):
        h = self.L0 / cells
        self._spacing = h / ppc
        self._grid = None
        across = int(np.ceil((2 + 2 * self.a) * cells))
        up = int(np.ceil(self.H0 / h)) + max(1, int(np.ceil(0.25 * cells)))
        grid = SplineGrid.rectangle((0.0, across * h), (0.0, up * h), (across, up), degree)
        self._grid = grid
        particles = Particles.seed(grid, ppc, self.rho, layout=layout, seed=0,
                                   region=((0.0, self.L0), (0.0, self.H0)))
        K0 = 1 - np.sin(np.radians(self.phi)) if self.K0 is None else self.K0
        particles = geostatic_stress(particles, self.H0, self.g, K0=K0)
        E = self.stiffness * self.rho * self.g * self.H0
        material = MohrCoulomb(E, self.nu, self.phi, self.c, large_deformation=True,
                               disconnect_at=self.disconnect or None)
        effects = [Gravity((0.0, -self.g)), Wall("left", friction=0.0),
                   Wall("bottom", friction=float(np.tan(np.radians(self.floor_angle))))]
        return Scene(grid, Body(particles, material),
                     self.t_end if t_end is None else t_end, effects=effects)

    def checks(self, result):
        """Fronts, final height, the experiments' scalings and the kinetic
        energy left (of the scene this benchmark built last).

        Fronts, each as (x_front - L0) / L0:

        - ``runout``: the rightmost particle (plus half a particle spacing);
          it reads the deposit where it is one particle thick, so it grows
          as the grid is refined (the continuum's tail thins without end);
        - ``runout_thickness_front``: the rightmost place where the deposit
          is at least ``front_thickness`` L0 thick (0.05: 1.6 particle
          layers of the 16-cell grid, the coarsest G2 allows); thickness =
          the particles' volume at the initial density (sum of V0) within a
          window L0 / 8 wide, over its width;
        - ``runout_97pct_mass``, ``runout_99pct_mass``: the particle behind
          which 97% and 99% of the mass lie.

        ``runout_ratio`` divides ``runout_thickness_front`` by the
        experiments' scaling of the regime (1.2 a for a < 1.8, 1.9 a^(2/3)
        for a > 2.8, the nearer one between; Lube et al. 2005).
        The experiments' runout is (d_inf - d_i) / d_i, d the distance
        from the back wall to the front of the deposit (its maximum
        horizontal extension; Lube et al. 2005, abstract): the form of
        every front here; where the experiments' front is one or two grains
        thick, a continuum deposit thins without end, hence the thickness
        criterion. ``runout_friction_model`` = a / tan(phi): the runout a
        purely frictional flow of friction coefficient mu = tan(phi) would
        reach at small a (the energy released, g rho (L - L0) H0^2 / 6,
        equals the work of friction over the flowing wedge,
        mu g rho (L - L0)^2 H0 / 6, so mu (L - L0) = H0: Staron and Hinch
        2005, J. Fluid Mech. 545; Kumar 2015, PhD thesis, Cambridge, ch. 4);
        Lube's 1.2 a is that of mu = 0.83 (40 deg).
        ``final_height_ratio`` is the highest particle within L0 of the wall
        (plus half a spacing) over H0. ``kinetic_grid_over_released``: the
        kinetic energy of the grid velocity (lumped mass m_i = sum_p N_ip m_p,
        v_i = sum_p N_ip m_p v_p / m_i, E = sum_i m_i |v_i|^2 / 2) over the
        potential energy released, the rest criterion of G2 (below 1e-4);
        ``kinetic_over_released`` is the particles' (FLIP keeps velocity
        noise the grid does not see, which no force removes)."""
        from .quadrature import transfer_matrices

        p = result.particles
        x, X = p.x, p.X
        L0 = self.L0
        front = x[:, 0].max() + 0.5 * self._spacing
        top = x[x[:, 0] <= L0, 1].max() + 0.5 * self._spacing
        released = float(self.g * p.m @ (X[:, 1] - x[:, 1]))
        kinetic = 0.5 * float(np.einsum("i,ij,ij->", p.m, p.v, p.v))
        N, _ = transfer_matrices(self._grid, x)
        mass = N.T @ p.m
        momentum = N.T @ (p.m[:, None] * p.v)
        filled = mass > 0
        kinetic_grid = 0.5 * float(np.sum(momentum[filled] ** 2 / mass[filled, None]))
        low, high = 1.2 * self.a, 1.9 * self.a ** (2 / 3)
        law = low if self.a < 1.8 else high if self.a > 2.8 else \
            (low if self.a < 2.3 else high)
        order = np.argsort(x[:, 0])
        behind = np.cumsum(p.m[order]) / p.m.sum()
        quantile = {f: float((x[order[min(np.searchsorted(behind, f), p.n - 1)], 0] - L0)
                             / L0) for f in (0.97, 0.99)}
        thick = thickness_front(x[:, 0], p.V0, self.front_thickness * L0, L0 / 8)
        return {"runout": float((front - L0) / L0),
                "runout_thickness_front": float((thick - L0) / L0),
                "runout_97pct_mass": quantile[0.97],
                "runout_99pct_mass": quantile[0.99],
                "final_height_ratio": float(top / self.H0),
                "runout_lube_low_1.2a": low,
                "runout_lube_high_1.9a^(2/3)": high,
                "runout_friction_model": self.a / np.tan(np.radians(self.phi)),
                "runout_ratio": float((thick - L0) / L0) / law,
                "kinetic_grid_over_released": kinetic_grid / released if released > 0
                else float("inf"),
                "kinetic_over_released": kinetic / released if released > 0 else float("inf"),
                "plastic_strain_max": float(p.state["plastic_strain"].max())}


def deposit_thickness(x, volume, centres, window):
    """The thickness of a layer of points x (n,) with volumes ``volume`` at
    ``centres``: the sum of the volumes with |x - c| < window / 2, over
    ``window``."""
    order = np.argsort(x)
    xs, cumulative = x[order], np.concatenate(([0.0], np.cumsum(volume[order])))
    inside = cumulative[np.searchsorted(xs, centres + window / 2)] \
        - cumulative[np.searchsorted(xs, centres - window / 2, side="right")]
    return inside / window


def thickness_front(x, volume, thickness, window):
    """The largest centre c (on steps of window / 8 from 0) where the
    :func:`deposit_thickness` is at least ``thickness``; 0 if nowhere."""
    centres = np.arange(0.0, x.max() + window, window / 8)
    thick = np.flatnonzero(deposit_thickness(x, volume, centres, window) >= thickness)
    return float(centres[thick[-1]]) if thick.size else 0.0


# ----------------------------------------------------------------------- G1
class StripFooting(Benchmark):
    """G1: a rough rigid strip footing of width B pushed into weightless
    undrained clay (von Mises, plane strain, yield_stress = sqrt(3) c_u: the
    Tresca limit |sigma_1 - sigma_3| = 2 c_u), whose limit pressure is
    q_ult = (2 + pi) c_u = 5.14 c_u (Prandtl 1920) for any E and nu
    (shared/BENCHMARKS.md, G1).

    Half model by symmetry: ``width`` x ``depth`` (in B), the symmetry plane
    (left) and the far side sliding (``Fixed(side, 0)``), the base fixed;
    the grid reaches ``headroom`` cells above the ground for the heave.
    The footing (:class:`Footing`, x in [0, B/2], rough unless ``rough`` is
    0) settles at ``speed`` B/s reached over ``ramp`` s, to ``settlement``
    B. E = ``stiffness`` c_u, nu, rho; g = 0. ``bbar`` 1 wraps the material
    in :class:`BBar` (the volumetric strain rate projected onto the grid's
    vertex functions) against
    volumetric locking; 0 leaves it out. ``cells`` counts the cells over
    ``width`` B, rounded so that B/2 ends on a knot (16 -> 20 cells over 5 B,
    2 under the half footing; ``cells_across_width`` in the checks).
    :meth:`checks` reads the bearing capacity factor
    N_c = q / c_u at a settlement of ``read_at`` B (q the mean footing
    pressure over the steps within 0.01 B of it) and gives the
    load-settlement curve (``curve``: settlement / B against q / c_u, one
    point per 0.005 B).

    Past the limit load the pressure keeps rising: the footing sinks into
    the ground and the ground beside it heaves, so its base lies
    D = s + heave below the ground beside it, and an embedded footing
    carries N_c d_c (the depth factor, :func:`hansen_depth_factor`). When
    the run saved particle positions (``save_every``), :meth:`checks` also
    gives ``embedment`` (settlement / B against D / B, D from
    :func:`footing_embedment`) and ``curve_depth_corrected`` (q / (c_u
    d_c(D / B)), the pressure with the embedment divided out: flat once
    the soil has yielded), with its value at ``read_at``
    (``bearing_capacity_depth_corrected``)."""

    name = "strip-footing"
    title = "G1 strip footing on undrained clay (Prandtl)"
    dim = 2
    has_exact = False
    defaults = {"B": 1.0, "c_u": 10.0, "stiffness": 300.0, "nu": 0.3, "rho": 1.0,
                "width": 5.0, "depth": 5.0, "speed": 0.05, "ramp": 0.4, "settlement": 0.15,
                "read_at": 0.1, "rough": 1.0, "bbar": 1.0, "headroom": 2.0, "t_end": None}
    variants = {"default": {}}
    amplitude = 1.0

    def default_t_end(self):
        return self.settlement * self.B / self.speed + 0.5 * self.ramp

    def scene(self, cells=40, degree=2, ppc=2, layout="uniform", fem=False, t_end=None):
        B = self.B
        under = max(1, int(round(0.5 * B * cells / (self.width * B))))  # cells under B/2
        h = 0.5 * B / under
        cells = self._cells = max(under, int(round(self.width * B / h)))
        up = int(round(self.depth * B / h))
        extra = int(self.headroom)
        grid = SplineGrid.rectangle((0.0, cells * h), (0.0, (up + extra) * h),
                                    (cells, up + extra), degree)
        particles = Particles.seed(grid, ppc, self.rho, layout=layout, seed=0,
                                   region=((0.0, cells * h), (0.0, up * h)))
        material = VonMises(self.stiffness * self.c_u, self.nu, np.sqrt(3.0) * self.c_u)
        if self.bbar:
            material = BBar(material, grid)
        self.footing = Footing((0.0, 0.5 * B), up * h, self.speed * B, rough=bool(self.rough),
                               ramp=self.ramp)
        effects = [Fixed("left", 0), Fixed("right", 0), Fixed("bottom"), self.footing]
        return Scene(grid, Body(particles, material),
                     self.t_end if t_end is None else t_end, effects=effects)

    def checks(self, result):
        """N_c at ``read_at`` B, the curve, and the pressure at the end."""
        history = self.footing.history
        s = np.array([h[1] for h in history]) / self.B
        q = -np.array([h[2][1] for h in history]) / self.footing.width / self.c_u
        near = np.abs(s - self.read_at) <= 0.01
        bins = np.floor(s / 0.005 + 1e-9).astype(np.int64)  # (0.11 / 0.005 < 22 in floats)
        counts = np.bincount(bins)
        sums = np.bincount(bins, weights=q)
        keep = counts > 0
        curve = [[float(0.005 * (k + 0.5)), float(sums[k] / counts[k])]
                 for k in np.flatnonzero(keep)]
        end = s >= s.max() - 0.01
        extra = {}
        if len(result.times) > 2 and len(result.history.get("x", ())) == len(result.times):
            settled = np.array([self.footing.settlement_at(t) for t in result.times])
            depth = np.array([footing_embedment(x, X, self.B, d) for x, X, d in
                              zip(result.history["x"], result.history["X"], settled)])
            at = np.array([c[0] for c in curve])
            factor = hansen_depth_factor(np.interp(at, settled / self.B, depth / self.B))
            corrected = np.array([c[1] for c in curve]) / factor
            extra = {"embedment": [[float(a), float(d)] for a, d in
                                   zip(settled / self.B, depth / self.B)],
                     "curve_depth_corrected": [[float(a), float(v)]
                                               for a, v in zip(at, corrected)],
                     "bearing_capacity_depth_corrected": float(np.interp(self.read_at, at,
                                                                         corrected))}
        return {"bearing_capacity_factor": float(q[near].mean()) if near.any() else None,
                "bearing_capacity_prandtl": 2 + np.pi,
                "bearing_capacity_error": (float(q[near].mean()) / (2 + np.pi) - 1)
                if near.any() else None,
                "read_at_settlement_over_B": self.read_at,
                "pressure_at_end_over_c_u": float(q[end].mean()),
                "settlement_at_end_over_B": float(s.max()),
                "cells_across_width": self._cells,
                "cells_under_half_footing": int(round(0.5 * self.B * self._cells
                                                      / (self.width * self.B))),
                "curve": curve, **extra}


def footing_embedment(x, X, B, settlement):
    """The depth D of a strip footing's base below the ground beside it:
    D = s + heave, the heave being how far the highest particle within
    B/2 <= x <= B (the ground beside the footing, whose centre line is
    x = 0) stands above the highest particle of the initial ground (the
    highest reference position X). ``x``, ``X``: (n, 2) positions."""
    beside = (x[:, 0] >= 0.5 * B) & (x[:, 0] <= B)
    if not beside.any():
        raise ValueError(f"footing_embedment: no particle beside the footing (B/2 <= x <= B "
                         f"with B = {B!r}): the ground beside it is needed to read its heave")
    return float(settlement + x[beside, 1].max() - X[:, 1].max())


def hansen_depth_factor(depth_over_width):
    """Brinch Hansen's (1970) depth factor of the cohesion term of an
    embedded footing, d_c = 1 + 0.4 D/B for D/B <= 1 and
    1 + 0.4 arctan(D/B) beyond (Brinch Hansen 1970, "A revised and
    extended formula for bearing capacity", Danish Geotechnical Institute
    Bulletin 28; the form in Das, Principles of Foundation Engineering):
    q_ult = N_c c_u d_c for a footing whose base lies D below the ground."""
    k = np.asarray(depth_over_width, dtype=np.float64)
    if not np.all(k >= 0.0):  # (NaN too)
        raise ValueError(f"hansen_depth_factor: depth_over_width must be >= 0 (the base below "
                         f"the ground), got {depth_over_width!r}")
    return 1.0 + 0.4 * np.where(k <= 1.0, k, np.arctan(k))


def _mirror_index(X):
    from scipy.spatial import cKDTree

    _, idx = cKDTree(X).query(1.0 - X)
    return idx


BENCHMARKS = {cls.name: cls for cls in (VibratingString, SoilColumn, TractionBar, NeoHookeanBar,
                                        AxisAligned2D, VibratingPlate2D, CollidingDisks,
                                        VibratingCube3D, AxisAligned3D, CollidingSpheres3D,
                                        GeostaticStress, ColumnCollapse, StripFooting)}


def get_benchmark(name, variant=None, **params):
    """The benchmark ``name`` (see ``BENCHMARKS``) with a variant and overrides."""
    if name not in BENCHMARKS:
        raise ValueError(f"unknown benchmark {name!r}; valid: {', '.join(BENCHMARKS)}")
    return BENCHMARKS[name](variant, **params)
