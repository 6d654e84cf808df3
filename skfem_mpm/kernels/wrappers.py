"""No C-callback wrapper for functions only compiled code calls.

numba compiles, beside every ``@njit`` function, a CPython wrapper (the
entry point of a call from Python: it unboxes each argument) and a C
callback wrapper (``cfunc`` ABI: the entry point numba uses when the
function is passed as a first-class function value, ``types.FunctionType``),
each lowered, optimized and turned into machine code with the function
(``BaseNativeLowering.run_pass`` in numba/core/typed_passes.py:
``create_cpython_wrapper``, ``create_cfunc_wrapper``). This package never
passes its functions as first-class function values: they are called from
Python, from compiled code (linked, or by symbol or address through the
native entry point, :mod:`skfem_mpm.kernels.by_symbol`), and its material
laws are ``@cfunc`` callbacks, which compile their own wrapper. So the C
callback wrapper is dropped (numba's ``no_cfunc_wrapper`` flag) for

- the functions of this package and of its generated kernel modules, and
- functions compiled without a CPython wrapper (an ``@overload``'s
  implementation, numba's default): only compiled code reaches them.

The function's own code, and so every result, is unchanged; a first use
compiles less. Installed once, when :mod:`skfem_mpm.kernels` is imported
(numba reads the flags when it compiles, ``_FunctionCompiler._compile_core``
in numba/core/dispatcher.py); numba's ``@cfunc`` has its own compiler class
and keeps its wrapper.
"""
from numba.core import dispatcher

__all__ = ["OWN_MODULES", "drops_callback_wrapper", "install"]

OWN_MODULES = ("skfem_mpm.", "_skfem_mpm_generated_")
"""Module name prefixes of this package's functions (generated kernel
modules: :func:`skfem_mpm.kernels.generated.load`)."""


def drops_callback_wrapper(py_func, targetoptions):
    """Whether ``py_func`` compiles without the C callback wrapper: one of
    this package's functions, or one compiled without a CPython wrapper."""
    module = getattr(py_func, "__module__", None) or ""
    return module.startswith(OWN_MODULES) or bool(targetoptions.get("no_cpython_wrapper"))


def install():
    """Make numba's function compiler apply :func:`drops_callback_wrapper`
    (once per process)."""
    customize = dispatcher._FunctionCompiler._customize_flags
    if getattr(customize, "drops_callback_wrapper", False):
        return

    def customize_flags(self, flags):
        flags = customize(self, flags)
        if drops_callback_wrapper(self.py_func, self.targetoptions):
            flags.no_cfunc_wrapper = True
        return flags

    customize_flags.drops_callback_wrapper = True
    dispatcher._FunctionCompiler._customize_flags = customize_flags
