"""A material's law for one particle, compiled: what the compiled executor
calls inside its constitutive kernel (:mod:`skfem_mpm.kernels.constitutive`).

Write the law as a numba-compilable function of small arrays and decorate
it::

    from skfem_mpm.materials import point_update

    @point_update
    def my_law(params, L, F, dt, stress, state, stress_out, state_out):
        # params (k,)   the material's point_parameters(dim)
        # L (dim, dim)  the velocity gradient of the step
        # F (dim, dim)  the deformation gradient after the step (finite-strain
        #               materials), else the step's increment I + dt L
        # stress (dim, dim): the stress before the step; write the new Cauchy
        #               stress into stress_out (every entry)
        # state (n_state,): the particle's material state, the fields of
        #               state_fields(dim) flattened in declared order (each
        #               in C order); state_out arrives holding the same
        #               values: write the entries that change (the new
        #               state). Both are empty for a material without state.
        ...

and set ``point_update = my_law`` and ``point_parameters(dim)`` on the
material class (see examples/custom_material.py). The law is wrapped in a C
callback of one fixed signature (``POINT_SIGNATURE``), so a single cached
constitutive kernel calls every material. A user's law compiles on its first
use in each process (about a second); the built-in laws' callbacks
(:mod:`skfem_mpm.materials.laws`) are cached on disk.

The volume (V <- V det(I + dt L); V0 det F for finite strain) and F
(F <- (I + dt L) F) are kinematics: the kernel updates them, not the law.
With ``scheme="rk4"`` a finite-strain law without state is called at each
stage's F with dt = 0 and must give sigma(F) there (its ``cauchy_stress``).

A finite-strain material without a wave speed bound sets the time step from
the current wave speed before every step. Its compiled wave speed of one
particle lets the compiled step loop run those steps too::

    from skfem_mpm.materials import point_wave_speed

    @point_wave_speed
    def my_wave_speed(params, F, m, V0, state):
        # params, state as for point_update; F (dim, dim) the particle's
        # current deformation gradient, m its mass, V0 its reference volume
        return ...  # the particle's largest P-wave speed

and set ``point_wave_speed = my_wave_speed`` on the material class (it reads
the same ``point_parameters(dim)``). Where a material declares one, the run's
time step takes the largest over the particles (:func:`max_point_wave_speed`)
on every executor, so the loop and a Python step choose the same dt; its
``wave_speed(particles)`` should return the same (NeoHookean's is this
function).
"""
import importlib

import numba
import numpy as np
from numba import carray, cfunc, njit, types

from ..kernels.constitutive import max_wave_speed
from ..kernels.serial import SERIAL_BELOW, for_threads
from .state import state_layout

__all__ = ["POINT_SIGNATURE", "WAVE_SPEED_SIGNATURE", "PointUpdate", "PointWaveSpeed",
           "point_update", "point_wave_speed", "max_point_wave_speed"]

_ptr = types.CPointer(types.float64)
POINT_SIGNATURE = types.void(_ptr, types.intp, _ptr, _ptr, types.intp, types.float64,
                             _ptr, _ptr, types.intp, _ptr, _ptr)
"""params, n_params, L, F, dim, dt, stress, state, n_state, stress_out, state_out"""
WAVE_SPEED_SIGNATURE = types.float64(_ptr, types.intp, _ptr, types.intp, types.float64,
                                     types.float64, _ptr, types.intp)
"""params, n_params, F, dim, m, V0, state, n_state -> the particle's wave speed"""


def _compile_callback(law):
    inner = njit(inline="always", error_model="numpy")(law)

    @cfunc(POINT_SIGNATURE, error_model="numpy")
    def callback(params, n_params, L, F, dim, dt, stress, state, n_state, stress_out,
                 state_out):
        inner(carray(params, (n_params,)), carray(L, (dim, dim)), carray(F, (dim, dim)), dt,
              carray(stress, (dim, dim)), carray(state, (n_state,)),
              carray(stress_out, (dim, dim)), carray(state_out, (n_state,)))

    return callback


def _compile_wave_speed(law):
    inner = njit(inline="always", error_model="numpy")(law)

    @cfunc(WAVE_SPEED_SIGNATURE, error_model="numpy")
    def callback(params, n_params, F, dim, m, V0, state, n_state):
        return inner(carray(params, (n_params,)), carray(F, (dim, dim)), m, V0,
                     carray(state, (n_state,)))

    return callback


class PointUpdate:
    """A material's compiled point law. ``callback()`` is its C callback:
    the user's ``law`` compiled on first use, or, for a built-in material,
    the cached callback ``"module:name"`` (imported on first use; ``law`` is
    then that module's ``name + "_law"``)."""

    _compile = staticmethod(_compile_callback)

    def __init__(self, law):
        self._law = law
        self._callback = None

    def __repr__(self):
        return f"PointUpdate({self._law if isinstance(self._law, str) else self._law.__name__})"

    def _cached(self):
        module, name = self._law.split(":")
        return importlib.import_module(module), name

    @property
    def law(self):
        """The point law as a Python function (for reading and testing)."""
        if isinstance(self._law, str):
            module, name = self._cached()
            return getattr(module, name + "_law").py_func
        return self._law

    def address(self):
        """The C callback's address (what the constitutive kernel calls)."""
        return self.callback().address

    def callback(self):
        if self._callback is None:
            if isinstance(self._law, str):
                module, name = self._cached()
                self._callback = getattr(module, name)
            else:
                self._callback = self._compile(self._law)
        return self._callback


class PointWaveSpeed(PointUpdate):
    """A material's compiled wave speed of one particle (see the module):
    like :class:`PointUpdate`, a C callback of WAVE_SPEED_SIGNATURE."""

    _compile = staticmethod(_compile_wave_speed)

    def __repr__(self):
        return "PointWaveSpeed" + super().__repr__()[len("PointUpdate"):]


def point_update(law):
    """Declare ``law(params, L, F, dt, stress, state, stress_out, state_out)``
    a material's compiled point law (see the module docstring)."""
    return PointUpdate(law)


def point_wave_speed(law):
    """Declare ``law(params, F, m, V0, state) -> c`` a material's compiled
    wave speed of one particle (see the module docstring)."""
    return PointWaveSpeed(law)


def max_point_wave_speed(material, particles):
    """The largest of ``material.point_wave_speed`` over ``particles`` (F the
    identity where the particles carry none), by the compiled loop's kernel
    (:func:`skfem_mpm.kernels.constitutive.max_wave_speed`; its serial copy
    below SERIAL_BELOW particles, as the loop calls it)."""
    p, dim = particles, particles.dim
    F = p.F if p.F is not None else np.broadcast_to(np.eye(dim), (p.n, dim, dim))
    layout = state_layout(material, dim)
    packed = layout.pack(p.state) if layout else np.empty((p.n, 0))
    parallel = p.n >= SERIAL_BELOW
    kernel = for_threads(max_wave_speed, parallel)
    c = np.ascontiguousarray
    return float(kernel(material.point_wave_speed.address(),
                        c(material.point_parameters(dim), dtype=np.float64),
                        c(F, dtype=np.float64), c(p.m, dtype=np.float64),
                        c(p.V0, dtype=np.float64), c(packed, dtype=np.float64),
                        np.empty(numba.get_num_threads() if parallel else 1)))
