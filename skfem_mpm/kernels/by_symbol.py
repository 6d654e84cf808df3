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

``call_at(site)`` makes the other kind of call: through an address the
caller holds at run time (``native_address``), so that one compiled caller
serves several kernels of the same argument types (the compiled loop: the
transfer kernels of every degree).

Caching: the symbol's name depends only on the kernel's module, name and
argument types, so the caller's cached machine code stays valid across
processes; the caller's library carries a reload hook (numba's
``reload_init``, run before cached code is loaded) that compiles or loads
the kernel in the new process and registers its address under that name.
A function that links a caller compiled earlier inherits its hooks, also
when that caller was loaded from the cache (:func:`_keep_reload_hooks`).

Processes sharing numba's cache (a study's workers, test workers) compile a
kernel once: the first holds :class:`compile_lock` while it compiles, the
others wait and load its machine code from the cache.
"""
import contextlib
import functools
import hashlib
import importlib
import inspect
import os
import tempfile
import time

from llvmlite import binding as llvm
from numba import types
from numba.core import cgutils, config
from numba.extending import intrinsic

try:
    import fcntl
except ImportError:  # Windows
    fcntl = None

__all__ = ["ARGUMENT_TYPES", "call", "call_at", "native_address", "register"]

_ADDRESSES = {}  # symbol name -> the address registered in this process


def _keep_reload_hooks():
    """Give a function loaded from numba's cache its reload hooks back.

    numba runs a cached function's hooks when it loads it, but the code
    library it rebuilds starts with none (``CompileResult._rebuild`` in
    numba/core/compiler.py), while a function compiled later that calls
    the loaded one inherits the hooks of the libraries it links
    (``CPUCodeLibrary._finalize_specific``): its own cache entry would then
    lack them, and in a third process the symbols it calls would be
    unresolved (LLVM aborts: "Symbol not found"). Wrapping ``_rebuild``
    puts the loaded hooks on the rebuilt library."""
    from numba.core.compiler import CompileResult

    rebuild = CompileResult._rebuild.__func__
    if getattr(rebuild, "keeps_reload_hooks", False):
        return
    parameters = inspect.signature(rebuild)

    @functools.wraps(rebuild)
    def rebuild_with_hooks(cls, *args, **kwargs):
        result = rebuild(cls, *args, **kwargs)
        hooks = parameters.bind(cls, *args, **kwargs).arguments.get("reload_init")
        if hooks:
            result.library._reload_init.update(hooks)
        return result

    rebuild_with_hooks.keeps_reload_hooks = True
    CompileResult._rebuild = classmethod(rebuild_with_hooks)


_keep_reload_hooks()


def symbol_name(module, name, argtypes):
    """The symbol of ``module.name`` compiled for ``argtypes`` (stable
    across processes: no numba version counters in it)."""
    text = f"{module}.{name}{tuple(argtypes)}"
    return "skfem_mpm.kernel." + hashlib.sha1(text.encode()).hexdigest()[:24]


class compile_lock:
    """Held while this process compiles ``kernel`` for ``argtypes``, so
    that two processes sharing numba's cache compile a kernel once: the
    second waits, then loads the first's machine code from the cache
    (numba itself lets both compile). An advisory lock (``flock``) on a file
    named after the cache directory and the kernel's symbol, released when
    the process ends; a kernel waits only for its callees' locks (no cycle),
    and at most ``WAIT`` seconds. Without ``fcntl`` (Windows): no lock."""

    WAIT = 600.0

    def __init__(self, kernel, argtypes):
        func = kernel.py_func
        where = f"{config.CACHE_DIR or ''}:{symbol_name(func.__module__, func.__name__, argtypes)}"
        name = hashlib.sha1(where.encode()).hexdigest()[:24]
        self.path = os.path.join(tempfile.gettempdir(), f"skfem_mpm-compile-{os.getuid()}",
                                 name) if hasattr(os, "getuid") else None
        self.fd = None

    def __enter__(self):
        if fcntl is None or self.path is None:
            return self
        try:
            os.makedirs(os.path.dirname(self.path), exist_ok=True)
            self.fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o600)
        except OSError:  # an unwritable temporary folder: compile without
            return self
        deadline = time.monotonic() + self.WAIT
        while True:
            try:
                fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return self
            except OSError:
                if time.monotonic() > deadline:
                    return self
                time.sleep(0.02)

    def __exit__(self, *exc):
        if self.fd is not None:
            try:
                fcntl.flock(self.fd, fcntl.LOCK_UN)
            finally:
                os.close(self.fd)
                self.fd = None


def _typing_lock(kernel, args):
    """:class:`compile_lock` of ``kernel`` for a call site's ``args``,
    held while the caller types the call: typing a call of a numba
    function compiles it (or loads it from the cache), so that is where
    two processes would otherwise both compile it. No lock when this
    process has it already."""
    args = tuple(types.unliteral(a) for a in args)
    if args in kernel.overloads:
        return contextlib.nullcontext()
    return compile_lock(kernel, args)


def _entry_point(kernel, argtypes):
    """(compile result, address of the native entry point) of ``kernel``
    compiled (or loaded from numba's cache) for ``argtypes``."""
    argtypes = tuple(argtypes)
    if argtypes not in kernel.overloads:
        with compile_lock(kernel, argtypes):
            kernel.compile(argtypes)
    cres = kernel.overloads[argtypes]
    address = cres.library.get_pointer_to_function(cres.fndesc.llvm_func_name)
    if not address:
        raise RuntimeError(f"{kernel.py_func.__name__}{argtypes}: no native entry point")
    return cres, address


def _native_call(context, builder, fn, restype, argtypes, args, values):
    """Call ``fn`` with numba's calling convention: ``values`` (of the
    caller's types ``args``) cast to ``argtypes``; an error status returns
    from the caller with it. Returns the result."""
    values = [context.cast(builder, value, actual, wanted)
              for value, actual, wanted in zip(values, args, argtypes)]
    status, result = context.call_conv.call_function(builder, fn, restype, argtypes, values)
    with cgutils.if_unlikely(builder, status.is_error):
        context.call_conv.return_status_propagate(builder, status)
    return result


def register(symbol, module, name, argtypes):
    """Compile (or load) ``module.name`` for ``argtypes`` and make
    ``symbol`` resolve to its native entry point; returns the compile
    result."""
    cres, address = _entry_point(getattr(importlib.import_module(module), name), argtypes)
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
    with _typing_lock(kernel.dispatcher, args):
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
        fnty = context.call_conv.get_function_type(restype, argtypes)
        fn = cgutils.get_or_insert_function(builder.module, fnty, symbol)
        return _native_call(context, builder, fn, restype, argtypes, args,
                            cgutils.unpack_tuple(builder, llargs[1]))

    return restype(kernel, types.StarArgTuple(args)), codegen


# ---------------------------------------------------- calls through an address
ARGUMENT_TYPES = {}
"""label -> the argument types a :func:`call_at` site of that label was
compiled with (recorded when the caller compiles, and again when it loads
from numba's cache)."""


def record_argument_types(label, argtypes):
    """Remember the argument types of the call site ``label``; a site
    compiled for two lists of types is marked ambiguous (None): no address
    can then be chosen for it safely."""
    argtypes = tuple(argtypes)
    ARGUMENT_TYPES[label] = argtypes if ARGUMENT_TYPES.get(label, argtypes) == argtypes \
        else None


def native_address(kernel, argtypes, restype=types.none):
    """The native entry point of ``kernel`` compiled (or loaded) for
    ``argtypes``, for a :func:`call_at` site declared to return ``restype``."""
    cres, address = _entry_point(kernel, argtypes)
    if cres.signature.return_type != restype:
        raise TypeError(f"{kernel.py_func.__name__}: its call_at site expects {restype}, "
                        f"the kernel returns {cres.signature.return_type}")
    return address


def call_at(site, restype=types.none):
    """An intrinsic ``f(address, *args)`` calling the kernel whose native
    entry point is at ``address`` (an integer held at run time, from
    :func:`native_address`) with ``args``; the kernel returns ``restype``
    (declared here: the caller compiles before any kernel it may call). One
    compiled caller serves every kernel of the same argument types: which
    one runs is data, not code, and a kernel the caller reaches only in
    some runs compiles only when Python points the caller at it.
    ``site`` names the call site: its argument
    types are recorded under it in :data:`ARGUMENT_TYPES` when the caller
    compiles and when it loads from the cache, so that Python can compile
    the kernel it will point the caller at."""
    if not isinstance(site, str) or not site:
        raise ValueError(f"call_at: site must be a non-empty string naming the call site, "
                         f"got {site!r}")
    if not isinstance(restype, types.Type):
        raise ValueError(f"call_at: restype must be a numba type, got {restype!r}")

    @intrinsic
    def call_at_site(typingctx, address, *args):
        if not isinstance(address, types.Integer):
            raise TypeError(f"{site}: the address must be an integer, got {address}")
        argtypes = tuple(types.unliteral(a) for a in args)
        record_argument_types(site, argtypes)

        def codegen(context, builder, signature, llargs):
            context.active_code_library._reload_init.add(
                functools.partial(record_argument_types, site, argtypes))
            fnty = context.call_conv.get_function_type(restype, argtypes)
            fn = builder.inttoptr(llargs[0], fnty.as_pointer())
            result = _native_call(context, builder, fn, restype, argtypes, args,
                                  cgutils.unpack_tuple(builder, llargs[1]))
            return context.get_dummy_value() if restype == types.none else result

        return restype(address, types.StarArgTuple(args)), codegen

    return call_at_site
