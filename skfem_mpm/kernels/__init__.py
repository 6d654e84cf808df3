"""Compiled (numba) kernels and the switch that selects them.

Every kernel here has a NumPy reference elsewhere in the package that the
tests compare it against. ``backend`` arguments accept ``"numba"`` or
``"numpy"``; ``None`` means the default, which is ``"numba"`` unless the
environment variable ``SKFEM_MPM_BACKEND=numpy`` says otherwise.
"""
import os

from ..validation import check_choice
from . import cache_files, wrappers

wrappers.install()  # before anything compiles (kernels.wrappers)
cache_files.install()  # before any cached function is defined (kernels.cache_files)

BACKENDS = ("numba", "numpy")


def resolve_backend(backend=None):
    """The backend to use: the argument, else the environment default."""
    if backend is None:
        backend = os.environ.get("SKFEM_MPM_BACKEND", "numba")
        return check_choice("SKFEM_MPM_BACKEND", backend, BACKENDS)
    return check_choice("backend", backend, BACKENDS)
