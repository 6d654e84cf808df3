"""Calling a compiled kernel by symbol name, without linking its code.

When a numba function calls another, the callee's optimized LLVM module is
linked into the caller's, and the whole is optimized and turned into
machine code again; a function three calls above a kernel compiles that
kernel four times. ``call(kernel, *args)`` inside a compiled function
instead compiles ``kernel`` once, on its own (or loads it from numba's
cache), and calls its native entry point through an external symbol: the
caller's module holds a declaration, the dynamic linker's table the
address (``llvmlite.binding.add_symbol``, as numba does for its own C
helpers). The call is an ordinary native call with numba's calling
convention (status and exception propagated); it is not inlined, so it
suits kernels that do a pass over particles or dofs, not per-element
helpers.

Caching: the symbol's name depends only on the kernel's module, name and
argument types, so the caller's cached machine code stays valid across
processes; the caller's library carries a reload hook (numba's
``reload_init``, run before cached code is loaded) that compiles or loads
the kernel in the new process and registers its address under that name.
"""
import functools
import hashlib
import importlib

from llvmlite import binding as llvm
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

__all__ = ["call", "register"]

_ADDRESSES = {}  # symbol name -> the address registered in this process


def symbol_name(module, name, argtypes):
    """The symbol of ``module.name`` compiled for ``argtypes`` (stable
    across processes: no numba version counters in it)."""
    text = f"{module}.{name}{tuple(argtypes)}"
    return "skfem_mpm.kernel." + hashlib.sha1(text.encode()).hexdigest()[:24]


def register(symbol, module, name, argtypes):
    """Compile (or load) ``module.name`` for ``argtypes`` and make
    ``symbol`` resolve to its native entry point; returns the compile
    result."""
    kernel = getattr(importlib.import_module(module), name)
    kernel.compile(argtypes)
    cres = kernel.overloads[tuple(argtypes)]
    address = cres.library.get_pointer_to_function(cres.fndesc.llvm_func_name)
    if not address:
        raise RuntimeError(f"{module}.{name}{tuple(argtypes)}: no native entry point")
    if _ADDRESSES.get(symbol) != address:
        llvm.add_symbol(symbol, address)
        _ADDRESSES[symbol] = address
    return cres


@intrinsic
def call(typingctx, kernel, *args):
    """``kernel(*args)``, compiled separately and called by symbol (see the
    module). ``kernel`` must be a global ``@njit`` function."""
    if not isinstance(kernel, types.Dispatcher):
        raise TypeError(f"call: kernel must be an @njit function, got {kernel}")
    sig = typingctx.resolve_function_type(kernel, args, {})
    if sig is None:
        raise TypeError(f"call: {kernel.dispatcher.py_func.__name__} does not accept {args}")
    func = kernel.dispatcher.py_func
    module, name, argtypes = func.__module__, func.__name__, tuple(sig.args)
    symbol = symbol_name(module, name, argtypes)
    restype = sig.return_type

    def codegen(context, builder, signature, llargs):
        register(symbol, module, name, argtypes)
        context.active_code_library._reload_init.add(
            functools.partial(register, symbol, module, name, argtypes))
        values = [context.cast(builder, value, actual, wanted) for value, actual, wanted in
                  zip(cgutils.unpack_tuple(builder, llargs[1]), args, argtypes)]
        fnty = context.call_conv.get_function_type(restype, argtypes)
        fn = cgutils.get_or_insert_function(builder.module, fnty, symbol)
        status, result = context.call_conv.call_function(builder, fn, restype, argtypes, values)
        with cgutils.if_unlikely(builder, status.is_error):
            context.call_conv.return_status_propagate(builder, status)
        return result

    return restype(kernel, types.StarArgTuple(args)), codegen
