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
"""
import importlib

from numba import carray, cfunc, njit, types

__all__ = ["POINT_SIGNATURE", "PointUpdate", "point_update"]

_ptr = types.CPointer(types.float64)
POINT_SIGNATURE = types.void(_ptr, types.intp, _ptr, _ptr, types.intp, types.float64,
                             _ptr, _ptr, types.intp, _ptr, _ptr)
"""params, n_params, L, F, dim, dt, stress, state, n_state, stress_out, state_out"""


def _compile_callback(law):
    inner = njit(inline="always", error_model="numpy")(law)

    @cfunc(POINT_SIGNATURE, error_model="numpy")
    def callback(params, n_params, L, F, dim, dt, stress, state, n_state, stress_out,
                 state_out):
        inner(carray(params, (n_params,)), carray(L, (dim, dim)), carray(F, (dim, dim)), dt,
              carray(stress, (dim, dim)), carray(state, (n_state,)),
              carray(stress_out, (dim, dim)), carray(state_out, (n_state,)))

    return callback


class PointUpdate:
    """A material's compiled point law. ``callback()`` is its C callback:
    the user's ``law`` compiled on first use, or, for a built-in material,
    the cached callback ``"module:name"`` (imported on first use; ``law`` is
    then that module's ``name + "_law"``)."""

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
                self._callback = _compile_callback(self._law)
        return self._callback


def point_update(law):
    """Declare ``law(params, L, F, dt, stress, state, stress_out, state_out)``
    a material's compiled point law (see the module docstring)."""
    return PointUpdate(law)
