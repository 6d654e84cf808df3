"""kernels.wrappers: the package's numba functions (and functions compiled
without a CPython wrapper, as overload implementations are) compile
without numba's C callback wrapper; a user's function keeps it, and the
material laws' ``@cfunc`` callbacks are unaffected."""
import numba
import numpy as np
from numba.core import types

import skfem_mpm  # noqa: F401  (imports skfem_mpm.kernels, which installs kernels.wrappers)
from skfem_mpm import NeoHookean
from skfem_mpm.kernels import wrappers


def _doubled(a):
    return 2.0 * a


def _compiled(module, **options):
    """``_doubled`` as a function of ``module``, compiled (no cache) for a float."""
    py_func = type(_doubled)(_doubled.__code__, {}, "_doubled")
    py_func.__module__ = module
    dispatcher = numba.njit(cache=False, **options)(py_func)
    dispatcher.compile((types.float64,))
    return dispatcher


def _has_callback_wrapper(dispatcher):
    cres = dispatcher.overloads[(types.float64,)]
    return cres.library.get_pointer_to_function(cres.fndesc.llvm_cfunc_wrapper_name) != 0


def test_the_packages_functions_have_no_callback_wrapper():
    for module in ("skfem_mpm.kernels.anything", "_skfem_mpm_generated_anything"):
        own = _compiled(module)
        assert not _has_callback_wrapper(own), module
        assert own(1.5) == 3.0  # (the CPython wrapper stays: Python calls it)


def test_functions_without_a_cpython_wrapper_have_no_callback_wrapper():
    inner = _compiled("users_module", no_cpython_wrapper=True)  # (as an @overload's impl)
    assert not _has_callback_wrapper(inner)
    outer = numba.njit(cache=False)(lambda a: inner(a) + 1.0)
    assert outer(1.5) == 4.0


def test_a_users_function_and_the_material_laws_keep_theirs():
    assert _has_callback_wrapper(_compiled("users_module"))
    assert _has_callback_wrapper(_compiled("skfem_mpm_extension"))  # (not the package)
    assert wrappers.drops_callback_wrapper(_doubled, {}) is False
    material = NeoHookean(E=1.0, nu=0.3)
    assert material.point_update.address() != 0
    assert np.isfinite(material.point_wave_speed.address())
