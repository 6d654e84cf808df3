"""The material interface: each material a small object whose ``update`` is
one vectorised function of the particle arrays and the velocity gradient,
and whose ``point_update`` (optional) is the same law for one particle,
compiled (see :mod:`skfem_mpm.materials.compiled`).

A material has

    finite_strain           True if it needs the deformation gradient F
    update(p, L, dt)        new (stress, V, F) from the velocity gradient
                            L[p, i, j] = dv_i/dx_j over the step dt; a
                            material with state returns (stress, V, F, state)
                            with ``state`` a dict of the new values of its
                            fields (those it leaves out keep their values);
                            new arrays: never write into the particles'
                            arrays (the last good state must survive)
    state_fields(dim)       the per-particle state it keeps (default none):
                            {name: (shape, initial)}, read in ``update`` as
                            ``p.state[name]``, shape (n, *shape)
    wave_speed(p)           the largest P-wave speed of the particles, for
                            the critical time step
    wave_speed_bound(p)     a bound on wave_speed over the whole run, or None
                            (default): a finite-strain material with a bound
                            runs at the fixed step of that bound instead of a
                            step that follows the current wave speed
    strain_energy(p)        total stored energy sum_p W_p V0_p (or V_p)
    check_dim(dim)          raise for dimensions it does not model
    point_update            the compiled law of one particle, or None (then the
                            compiled executor calls ``update``)
    point_wave_speed        the compiled wave speed of one particle, or None: a
                            finite-strain material without a bound that gives
                            one has its adaptive steps run by the compiled loop
                            (else each step returns to Python), and the run's
                            time step takes it instead of ``wave_speed``
    point_parameters(dim)   the float64 array of parameters ``point_update`` and
                            ``point_wave_speed`` read
    cell_average            True: the compiled paths give ``point_update`` the
                            velocity gradient with its dilatation projected
                            over the particles onto the grid's vertex functions
                            or cells (B-bar: :class:`BBar`), False (default)
                            the particle's own

Write your own by following the same shape (see examples/custom_material.py).
2D is plane strain throughout; 1D is uniaxial strain; 3D is the full solid.

Per-particle state (accumulated plastic strain, sigma_zz in plane strain,
back stresses, damage, ...): declare it with ``state_fields`` and it lives in
``particles.state[name]``; the scene creates each declared field at its
initial value (keeping any a user supplied), every executor carries it
through particle removal, checkpoints and restarts, and it is recorded in
``Result.history[name]`` at every save and written to ParaView as point data.
The compiled point law sees a particle's fields flattened into ``state``
(n_state values, the fields in declared order, each in C order) and writes
``state_out`` (see :mod:`skfem_mpm.materials.compiled`).
"""
import numpy as np

__all__ = ["Material", "lame_parameters", "check_nu", "incremental_deformation", "det"]


def lame_parameters(E, nu):
    """Lame's lambda and mu: lambda = E nu / ((1 + nu)(1 - 2 nu)), mu = E / (2 (1 + nu))."""
    return E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))


def check_nu(nu):
    if isinstance(nu, bool) or not isinstance(nu, (int, float, np.floating, np.integer)):
        raise ValueError(f"nu must be a real number in (-1, 0.5), got {nu!r}")
    nu = float(nu)
    if not -1.0 < nu < 0.5:
        raise ValueError(f"nu must lie in (-1, 0.5), got {nu}")
    return nu


def incremental_deformation(L, dt):
    """I + dt L, the deformation gradient of one step."""
    dim = L.shape[-1]
    return np.eye(dim) + dt * L


def det(A):
    """Determinants of a stack of 1x1, 2x2 or 3x3 matrices (3x3 by the
    rule of Sarrus: expansion along the first row)."""
    if A.shape[-1] == 1:
        return A[:, 0, 0].copy()
    if A.shape[-1] == 2:
        return A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0]
    return (A[:, 0, 0] * (A[:, 1, 1] * A[:, 2, 2] - A[:, 1, 2] * A[:, 2, 1])
            - A[:, 0, 1] * (A[:, 1, 0] * A[:, 2, 2] - A[:, 1, 2] * A[:, 2, 0])
            + A[:, 0, 2] * (A[:, 1, 0] * A[:, 2, 1] - A[:, 1, 1] * A[:, 2, 0]))


class Material:
    """Base class: the interface every material follows."""

    finite_strain = False
    point_update = None
    cell_average = False
    point_wave_speed = None

    def point_parameters(self, dim):
        """The parameters of ``point_update`` (a float64 array)."""
        return np.zeros(0)

    def state_fields(self, dim):
        """The per-particle state this material keeps in ``dim`` dimensions:
        ``{name: (shape, initial)}`` with ``shape`` the shape of one
        particle's value (``()`` a scalar, ``(3,)``, ``(dim, dim)``) and
        ``initial`` its starting value (a number or an array of that shape).
        ``particles.state[name]`` then has shape ``(n, *shape)`` (float64).
        Names are identifiers other than the particle arrays' names. None
        by default (LinearElastic, NeoHookean); e.g. ::

            def state_fields(self, dim):
                return {"plastic_strain": ((), 0.0), "sigma_zz": ((), 0.0)}
        """
        return {}

    def check_dim(self, dim):
        if dim not in (1, 2, 3):
            raise ValueError(
                f"{type(self).__name__} models 1D, 2D (plane strain) and 3D, got dim={dim}")

    def update(self, particles, L, dt):  # pragma: no cover - interface
        raise NotImplementedError

    # Staged (Runge-Kutta) schemes evaluate the stress of each stage from the
    # stage's kinematic state; a material offers one of these two (see
    # skfem_mpm.solve.runge_kutta), or cannot be staged.

    def stress_rate(self, particles, L):  # pragma: no cover - interface
        """Small strain: d sigma / dt at the particles for the velocity
        gradient L (n, dim, dim), for a rate law with no other history."""
        raise NotImplementedError

    def cauchy_stress(self, F):  # pragma: no cover - interface
        """Finite strain: sigma(F) for deformation gradients F (n, dim, dim)."""
        raise NotImplementedError

    def wave_speed(self, particles):  # pragma: no cover - interface
        raise NotImplementedError

    def wave_speed_bound(self, particles):
        """A bound on :meth:`wave_speed` for the whole run, or None (the
        speed follows the deformation)."""
        return None

    def strain_energy(self, particles):  # pragma: no cover - interface
        raise NotImplementedError
