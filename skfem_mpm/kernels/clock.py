"""A monotonic clock readable inside compiled code (phase times of a
compiled step loop).

``monotonic_ns()`` is ``clock_gettime(CLOCK_MONOTONIC)`` in nanoseconds,
the clock behind :func:`time.perf_counter` on Linux, called by symbol name
so that functions using it stay cacheable (a ctypes function pointer would
not be). Elsewhere it returns 0 and :data:`CLOCK_AVAILABLE` is False: the
loop's time is then reported as a whole.
"""
import sys

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

__all__ = ["CLOCK_AVAILABLE", "monotonic_ns"]

CLOCK_AVAILABLE = sys.platform.startswith("linux")
_CLOCK_MONOTONIC = 1  # Linux's clock id


@intrinsic
def monotonic_ns(typingctx):
    """Nanoseconds of the monotonic clock (0 where unavailable)."""
    def codegen(context, builder, signature, args):
        i32, i64 = ir.IntType(32), ir.IntType(64)
        if not CLOCK_AVAILABLE:
            return ir.Constant(i64, 0)
        spec = cgutils.alloca_once(builder, ir.ArrayType(i64, 2))  # struct timespec
        voidptr = ir.IntType(8).as_pointer()
        fn = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(i32, [i32, voidptr]), "clock_gettime")
        builder.call(fn, [ir.Constant(i32, _CLOCK_MONOTONIC), builder.bitcast(spec, voidptr)])
        zero = ir.Constant(i32, 0)
        seconds = builder.load(builder.gep(spec, [zero, zero]))
        nanos = builder.load(builder.gep(spec, [zero, ir.Constant(i32, 1)]))
        return builder.add(builder.mul(seconds, ir.Constant(i64, 1_000_000_000)), nanos)
    return types.int64(), codegen
