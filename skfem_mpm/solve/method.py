"""``Method``: how a scene is solved (scheme, mass, reconstruction, dt)."""
import inspect
import numbers

import numpy as np

from ..reconstruct import RECONSTRUCTORS
from ..validation import check_choice, check_positive

__all__ = ["Method", "SCHEMES", "MASSES", "HYBRID_SCHEMES", "RECONSTRUCTIONS", "DEFAULT_CFL",
           "default_cfl"]

SCHEMES = ("musl", "usl", "usf", "cd", "rk4")
MASSES = ("lumped", "consistent", "hybrid")
HYBRID_SCHEMES = ("musl",)  # the schemes that re-project the velocity
RECONSTRUCTIONS = ("none", "spline", "tls", "mls")
ON_EXIT = ("raise", "remove")
MASS_SOLVERS = ("auto", "direct", "cg")

DEFAULT_CFL = {"rk4": 0.6}
"""The default ``cfl`` of a scheme (a fraction of its own critical step), 0.5
where it is not listed. Each scheme's dt_crit is s / omega_max with s its
stability limit on undamped oscillations (2 for the central difference,
MUSL, USL; 2 sqrt(2) for classical RK4,
:data:`skfem_mpm.solve.timestep.STABILITY_LIMIT`) and omega_max the Gauss
estimate of :func:`skfem_mpm.solve.timestep.critical_time_step`, so one
fraction means the same margin on the top frequency for every scheme.

rk4: 0.6. Its time error is fourth order, below the spatial error at any
fraction up to 1 on the benchmarks (S1 small, cubic, spline, consistent:
6.76e-7 at 16 cells from cfl 0.5 to 0.9 with the fast-dof guard off), so
its cost for an accuracy falls as 1 / cfl; what bounds the fraction is the
fast-dof guard of consistent mass (:mod:`skfem_mpm.solve.grid_system`).
It compares r_i = cfl^2 w_i Q_i / q with 1/2 (Q_i a dof's K_ii / M_ii, q
an interior dof's, on unit cells, w_i its weight in
:func:`skfem_mpm.solve.timestep.covered_stiffness`) and lumps the fraction
smoothstep(2 r_i - 1) of the row
(:func:`skfem_mpm.solve.timestep.lumping_fraction`): a covered interior
dof has Q_i = q and w_i = 1, so r_i = cfl^2, and above cfl = 1 / sqrt(2)
= 0.707 every interior row is lumped a little, for any scheme (S1 at
0.75: all 17 interior rows by 3.8%, the error 6.8e-7 -> 1.3e-4 at 16
cells). A body that ends at a knot (S3 small: the bar's free end) leaves
a tail the guard weighs, with a reconstruction (S3's spline), as the open
knot vector's first function
(:func:`skfem_mpm.solve.timestep.tail_weight`, weight q / Q_1), but it
measures Q_i from the particles' own sums, which over-sample the tail's
steep end: for cubic splines and 2 particles per cell (at 1/4 and 3/4 of
the one cell the bar covers) sum 9 s^4 / sum s^6 = 16.2 against
Q_1 = 63 / 5 = 12.6 on the cell, so r = 1.29 cfl^2 (measured on S3 at 8
cells: 0.319 at cfl 0.5, 0.455 at 0.6, 0.539 at 0.65), and the end row
is lumped from cfl = sqrt(0.5 / 1.29) = 0.62 on (with 3 and 4 particles
per cell: 1.11 and 1.06, from 0.67 and 0.69). A lumped tail also
withdraws the tail weight from its neighbours (a cut cell: see
:func:`skfem_mpm.solve.timestep.covered_stiffness`), so past that cfl the
error jumps (S3 at 8 cells: 1.23e-5 with and without the guard at 0.5 and
0.6; 2.7e-3 at 0.65, 5.2e-3 at 0.7 against 1.24e-5 and 1.25e-5 without
it). So 0.6, the largest tenth below 0.62. RK4's amplification on the
imaginary axis, |R(i y)| = sqrt(1 - y^6 / 72 + y^8 / 576), is 0.89 at
its top frequency there (y = 0.6 * 2 sqrt(2)): it damps the top modes
a little. The second-order schemes keep 0.5: their time error is second
order, and a smaller step is their accuracy."""


def default_cfl(scheme):
    """The ``cfl`` of ``Method(scheme=scheme)`` when none is given (:data:`DEFAULT_CFL`)."""
    return DEFAULT_CFL.get(scheme, 0.5)


def _check_options(reconstruction, options):
    """The reconstruction options as a dict of keyword arguments the
    reconstruction function takes (for the named ones: its keyword
    parameters after ``(grid, particles, values, rule)``)."""
    if options is None:
        return {}
    if not isinstance(options, dict) or not all(isinstance(k, str) for k in options):
        raise ValueError(f"reconstruction_options must be a dict of keyword arguments "
                         f"(e.g. {{'penalty': 1e-6}}), got {options!r}")
    if isinstance(reconstruction, str):
        if reconstruction == "none":
            if options:
                raise ValueError(f"reconstruction_options {options!r} given without a "
                                 f"reconstruction (reconstruction='none')")
            return {}
        params = list(inspect.signature(RECONSTRUCTORS[reconstruction]).parameters)[4:]
        unknown = [k for k in options if k not in params]
        if unknown:
            raise ValueError(f"reconstruction_options: {unknown[0]!r} is not an option of "
                             f"reconstruction={reconstruction!r}; valid: {params}")
    return dict(options)


class Method:
    """The numerical method of a run.

    Parameters
    ----------
    scheme
        ``"musl"`` (modified update-stress-last, Al-Kafaji 2013: particle
        velocities from the nodal accelerations, nodal velocities recomputed
        from the updated particle momentum, then strains and positions; the
        default), ``"usl"`` (update stress last), ``"usf"`` (update stress
        first), ``"cd"`` (central difference: USL with staggered
        velocities, second order in time) or ``"rk4"`` (classical
        fourth-order Runge-Kutta on the particle system, four grid passes
        per step; stable up to sqrt(2) times the central-difference step,
        and ``cfl`` is a fraction of that; needs materials that can be
        staged, see :mod:`skfem_mpm.solve.runge_kutta`).
    mass
        ``"lumped"`` (row sums), ``"consistent"`` (sparse solve) or
        ``"hybrid"``: the lumped mass for the acceleration, m_i a_i = f_i,
        and the consistent mass for the velocity solves, M v = N^T (m v_p)
        (the MUSL re-projection of the updated particle velocities and,
        with damping, v^n): the seed author's MUSL (Tielen 2016,
        ``Vib_bar_Bspline.m``). With a reconstruction both masses come from
        the reconstructed density integrated by Gauss quadrature. Only
        ``scheme="musl"`` re-projects the velocity, so any other scheme with
        ``"hybrid"`` raises ``ValueError``. The critical time step is the
        lumped one (the acceleration's mass); ``frequency_guard`` does not
        apply (it protects a consistent-mass acceleration).
    reconstruction
        ``"none"`` (particles are the quadrature points), ``"spline"``,
        ``"tls"``, ``"mls"`` (see :mod:`skfem_mpm.reconstruct`), or a callable
        with the same signature as those functions.
    dt
        Time step; None means ``cfl * dt_crit``. A dt above dt_crit raises
        ``ValueError`` unless ``allow_unstable``.
    cfl
        Fraction of the critical time step used when ``dt`` is None; above 1
        it raises ``ValueError`` unless ``allow_unstable``. None (the
        default): the scheme's own default, 0.6 for ``"rk4"`` and 0.5 for
        the others (:data:`DEFAULT_CFL`, which gives the derivation). With a
        reconstruction on a 2D grid dt_crit is the Gauss-FEM one times a
        factor <= 1 estimated by power iteration where the reconstructed
        operator is stiffer (see :mod:`skfem_mpm.solve.timestep`).
    on_exit
        ``"raise"``: a particle leaving the grid stops the run with
        ``SimulationError``; ``"remove"``: it is removed and counted.
    small_mass
        Relative threshold of the tiny-mass guard (see
        :mod:`skfem_mpm.solve.grid_system`); 0 disables it.
    frequency_guard
        Consistent mass only (not ``"hybrid"``): the rows of dofs whose own frequency would
        outgrow the time step (a function seen only at the tail of its
        support) are lumped; the factor scales the limit, 0 disables it
        (see :mod:`skfem_mpm.solve.grid_system`).
    mass_solver
        ``"direct"`` (sparse LU), ``"cg"`` (preconditioned conjugate
        gradients, warm started) or ``"auto"``: on the compiled executor
        CG on the stencil, on the reference executor direct below 20000
        dofs. The choice never depends on timing: identical runs agree bit
        for bit (on one thread count).
    backend
        ``"numba"`` (compiled kernels where they apply), ``"numpy"`` (the
        reference) or None (the default, see :mod:`skfem_mpm.kernels`).
    reconstruction_options
        Keyword arguments passed to the reconstruction function.
    """

    def __init__(self, scheme="musl", mass="lumped", reconstruction="none", dt=None, cfl=None,
                 allow_unstable=False, on_exit="raise", small_mass=1e-3, frequency_guard=1.0,
                 mass_solver="auto", backend=None, reconstruction_options=None):
        self.scheme = check_choice("scheme", scheme, SCHEMES)
        self.mass = check_choice("mass", mass, MASSES)
        if self.mass == "hybrid" and self.scheme not in HYBRID_SCHEMES:
            raise ValueError(
                f"mass='hybrid' (lumped mass for the acceleration, consistent mass for the "
                f"re-projection of the updated particle velocities) needs a scheme that "
                f"re-projects the velocity, one of {HYBRID_SCHEMES}; scheme={self.scheme!r} "
                f"has no re-projection: use scheme='musl' or mass='lumped' or 'consistent'")
        if not callable(reconstruction):
            check_choice("reconstruction", reconstruction, RECONSTRUCTIONS)
        self.reconstruction = reconstruction
        self.dt = None if dt is None else check_positive("dt", dt)
        self.cfl = default_cfl(self.scheme) if cfl is None else check_positive("cfl", cfl)
        if not isinstance(allow_unstable, bool):
            raise ValueError(f"allow_unstable must be True or False, got {allow_unstable!r}")
        self.allow_unstable = allow_unstable
        self.on_exit = check_choice("on_exit", on_exit, ON_EXIT)
        if isinstance(small_mass, bool) or not isinstance(small_mass, numbers.Real) \
                or not 0 <= small_mass < 1:
            raise ValueError(f"small_mass must be a number in [0, 1), got {small_mass!r}")
        self.small_mass = float(small_mass)
        if isinstance(frequency_guard, bool) or not isinstance(frequency_guard, numbers.Real) \
                or not 0 <= frequency_guard < np.inf:
            raise ValueError(f"frequency_guard must be a finite number >= 0, got {frequency_guard!r}")
        self.frequency_guard = float(frequency_guard)
        self.mass_solver = check_choice("mass_solver", mass_solver, MASS_SOLVERS)
        if backend is not None:
            check_choice("backend", backend, ("numba", "numpy"))
        self.backend = backend
        self.reconstruction_options = _check_options(reconstruction, reconstruction_options)

    @property
    def needs_consistent_mass(self):
        """True when some grid solve uses the consistent mass matrix."""
        return self.mass in ("consistent", "hybrid")

    @property
    def acceleration_mass(self):
        """The mass of the acceleration solve, ``"lumped"`` or
        ``"consistent"`` (it sets the critical time step)."""
        return "lumped" if self.mass == "hybrid" else self.mass

    @property
    def reconstruction_name(self):
        r = self.reconstruction
        return r if isinstance(r, str) else getattr(r, "__name__", "custom")

    def as_dict(self):
        return {"scheme": self.scheme, "mass": self.mass,
                "reconstruction": self.reconstruction_name, "dt": self.dt, "cfl": self.cfl,
                "allow_unstable": self.allow_unstable, "on_exit": self.on_exit,
                "small_mass": self.small_mass, "frequency_guard": self.frequency_guard,
                "mass_solver": self.mass_solver,
                "backend": self.backend}

    def __repr__(self):
        args = ", ".join(f"{k}={v!r}" for k, v in self.as_dict().items())
        return f"Method({args})"
