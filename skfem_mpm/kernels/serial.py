"""Serial copies of the parallel kernels, for runs too small for threads.

A parallel kernel (``parallel=True``, ``prange`` over its thread blocks)
costs two things a small run does not repay: starting the threads of each
parallel region (more than the region's work below a few thousand
particles, and far more when another process holds a core), and compiling
the parallel region (numba's parfor lowering: 3-5x the compile time of the
same source compiled serially). Below :data:`SERIAL_BELOW` particles a run
therefore calls serial copies of its kernels only, on the executor and in
the compiled step loop alike, and never compiles a parallel one.

A copy is the kernel's own source compiled with ``parallel=False``: its
``prange`` over the blocks becomes a loop over the same blocks, so it
returns the same bits. The copies of all kernel modules live in one
generated module (:mod:`skfem_mpm.kernels.generated`), where each copy
calls the copies of the parallel kernels it calls (a serial caller of a
parallel callee would still start threads); kernels that neither are
parallel nor call one are used as they are.
"""
import functools
import hashlib
import importlib
import inspect

from .generated import load

__all__ = ["SERIAL_BELOW", "for_threads", "serial"]

SERIAL_BELOW = 4096
"""Particle count below which a run uses the serial copies of its kernels."""

# the modules whose parallel kernels get serial copies (the generated
# transfer kernels are generated serial or parallel by their templates)
_MODULES = ("mpm", "scatter", "kronecker", "band_factor", "tiny_mass", "constitutive", "staging",
            "fringe", "tls", "mls", "cell_integrals")
_SKIPPED_NAMES = ("np", "njit", "prange", "FAST", "IN_ORDER", "overload", "len")
# helpers the serial copies call as functions compiled without numba's
# runtime (no reference counts; they allocate nothing): inlined into a
# particle loop, the helper's array arguments become new references
# counted at every call (atomic increments, the larger part of the serial
# consistent_2d's time on a 16 x 16 grid, where a quarter of the particles
# per axis sit in boundary cells). The parallel kernels keep the inlined
# helpers: there they cost nothing and the call would cost. (And the
# product of one column, which the copy of _ell_product_dot calls per
# block: see _NO_RUNTIME_COPIES.)
_NO_RUNTIME = ("_axis", "_tensor_point", "_one_column_product_dot")
# kernels whose serial copies are compiled without numba's runtime: the
# conjugate-gradient passes (they allocate nothing) that ell_pcg calls a
# few times per iteration, each call counting a reference to every array
# argument on entry and exit (atomic operations that cost more than a
# pass over a small system). Not _precondition: its fringe correction
# needs the runtime.
_NO_RUNTIME_COPIES = ("_ell_product_dot", "_cg_update", "_cg_direction", "_dots")


def _is_kernel(value):
    return hasattr(value, "py_func") and hasattr(value, "targetoptions")


def _overload_of(module, name):
    """The ``@overload(name)`` implementation in ``module``, or None (a
    stub a kernel calls whose implementation may call kernels: its copy
    and the stub's go into the serial module, so that the copy's kernels
    are the serial ones)."""
    stub = vars(module).get(name)
    if not inspect.isfunction(stub):
        return None
    for value in vars(module).values():
        if inspect.isfunction(value) and value is not stub:
            try:
                first = inspect.getsource(value).lstrip().split("\n", 1)[0]
            except (OSError, TypeError):
                continue
            if first.replace(" ", "") == f"@overload({name})":
                return value
    return None


def _names(code):
    """The global names ``code`` and its nested functions (lambdas) use."""
    names = list(code.co_names)
    for const in code.co_consts:
        if inspect.iscode(const):
            names += _names(const)
    return names


def _callees(func):
    """The kernels and the (stub, overload) pairs ``func`` calls, from its
    module's globals."""
    module = inspect.getmodule(func)
    found = []
    for name in dict.fromkeys(_names(func.__code__)):  # each once, in order
        value = vars(module).get(name)
        if _is_kernel(value):
            found.append(value)
        else:
            overload = _overload_of(module, name)
            if overload is not None:
                found.append((value, overload))
    return found


def closure(roots):
    """The kernels among ``roots`` and their callees that need a serial
    copy (parallel ones, and those calling one), callees first."""
    needs, order = {}, []

    def visit(kernel):
        overloaded = isinstance(kernel, tuple)
        func = kernel[1] if overloaded else kernel.py_func
        key = (func.__module__, func.__name__)
        if key in needs:
            return needs[key]
        needs[key] = False  # (no recursion among kernels)
        copy = not overloaded and bool(kernel.targetoptions.get("parallel", False))
        for callee in _callees(func):
            if visit(callee):
                copy = True
        needs[key] = copy
        if copy:
            order.append(kernel)
        return copy

    for kernel in roots:
        visit(kernel)
    return order


def source(kernels):
    """Source of a module holding copies of ``kernels`` compiled without
    ``parallel`` under their own names (so that they call each other's
    copies), with the imports their bodies need. Two kernels of one name,
    or one name imported from two modules, are refused (a copy would call
    the wrong function)."""
    names, funcs = {}, []
    for kernel in kernels:
        if isinstance(kernel, tuple):  # an overloaded stub and its overload
            funcs += [kernel[0], kernel[1]]
        else:
            funcs.append(kernel.py_func)
    for func in funcs:
        if func.__name__ in names and names[func.__name__] is not func:
            raise ValueError(f"two kernels named {func.__name__} need serial copies")
        names[func.__name__] = func
    imports, bodies = {}, []
    for func in funcs:
        text = inspect.getsource(func).replace("parallel=True", "parallel=False", 1)
        if func.__name__ in _NO_RUNTIME_COPIES:
            text = text.replace("@njit(", "@njit(_nrt=False, ", 1)
        bodies.append(text)
        module = inspect.getmodule(func)
        for name in _names(func.__code__):
            if name in vars(module) and name not in names and name not in _SKIPPED_NAMES:
                value = vars(module)[name]
                seen = imports.setdefault(name, (value, module.__name__))
                if seen[0] is not value:
                    raise ValueError(f"serial copies import {name} from both "
                                     f"{seen[1]} and {module.__name__}")
    lines = ['"""Generated by skfem_mpm.kernels.serial; do not edit."""',
             "import numpy as np",
             "from numba import njit, prange",
             "from numba.extending import overload",
             "",
             "from skfem_mpm.kernels.weights import FAST, IN_ORDER",
             *sorted(f"from {module} import {name}" for name, (_, module) in imports.items()),
             *(f"{name} = njit(_nrt=False, error_model='numpy', fastmath=FAST)({name}.py_func)"
               for name in _NO_RUNTIME if name in imports)]
    return "\n".join(lines) + "\n\n\n" + "\n\n".join(bodies)


@functools.cache
def _module():
    """The generated module of the serial copies of every kernel module's
    parallel kernels (compiled lazily: a copy compiles at its first call),
    and the (module, name) of the kernels copied."""
    modules = [importlib.import_module(f"{__package__}.{name}") for name in _MODULES]
    roots = [value for m in modules for value in vars(m).values()
             if _is_kernel(value) and inspect.getmodule(value.py_func) is m]
    # the copies' callees are not tracked by numba's cache: their modules'
    # sources go into the file's name (generated.load hashes the text)
    callees = "".join(inspect.getsource(m) for m in modules)
    tag = hashlib.sha1(callees.encode()).hexdigest()[:12]
    kernels = closure(roots)
    copied = {(f.__module__, f.__name__) for f in
              (k[1] if isinstance(k, tuple) else k.py_func for k in kernels)}
    return load("serial", f"# callees {tag}\n" + source(kernels)), copied


def serial(kernel):
    """The serial copy of ``kernel`` (the kernel itself when it neither is
    parallel nor calls a parallel kernel)."""
    module, copied = _module()
    func = kernel.py_func
    if (func.__module__, func.__name__) not in copied:
        return kernel
    return getattr(module, func.__name__)


def for_threads(kernel, parallel):
    """``kernel`` for a run with (True) or without (False) threads."""
    return kernel if parallel else serial(kernel)
