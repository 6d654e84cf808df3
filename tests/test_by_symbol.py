"""kernels.by_symbol: a kernel called by symbol is compiled once, not linked
into its callers, gives the direct call's result, propagates its errors,
and its callers load from numba's cache in a fresh process."""
import os
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from numba import njit, types
from numba.core import config as numba_config

from skfem_mpm.kernels.by_symbol import call, compile_lock


@njit(cache=False)
def _axpy_sum(a, b, s):
    for i in range(a.shape[0]):
        a[i] += s * b[i]
    return a.sum()


@njit(cache=False)
def _checked(n):
    if n < 0:
        raise ValueError("n must be non-negative")
    return 2 * n


@njit(cache=False)
def _through_symbol(a, b):
    return call(_axpy_sum, a, b, 2)  # the literal 2 is cast to the kernel's float


@njit(cache=False)
def _outer(a, b):
    t = 0.0
    for _ in range(3):
        t += _through_symbol(a, b)
    return t


@njit(cache=False)
def _checked_by_symbol(n):
    return call(_checked, n)


def test_same_result_as_the_direct_call():
    a, b = np.linspace(0.0, 1.0, 7), np.arange(7.0)
    direct = a.copy()
    expected = sum(_axpy_sum(direct, b, 2.0) for _ in range(3))
    got = a.copy()
    assert _outer(got, b) == expected
    np.testing.assert_array_equal(got, direct)


def test_the_kernel_is_declared_not_linked():
    a, b = np.ones(3), np.ones(3)
    _outer(a, b)
    for caller in (_through_symbol, _outer):
        ir = caller.inspect_llvm(caller.signatures[0])
        defined = [line for line in ir.splitlines() if line.startswith("define")]
        assert defined and not any("_axpy_sum" in line for line in defined)
        assert "declare" in ir


def test_errors_propagate():
    assert _checked_by_symbol(4) == 8
    with pytest.raises(ValueError, match="non-negative"):
        _checked_by_symbol(-1)


def _fresh_process(tmp_path, script):
    """The words ``script`` prints, run in a new Python process with the
    modules of ``tmp_path`` importable and numba's cache in it."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"),
               PYTHONPATH=os.pathsep.join([str(tmp_path), *sys.path]))
    out = subprocess.run([sys.executable, "-c", script], env=env, cwd=tmp_path,
                         capture_output=True, text=True, check=True)
    return out.stdout.split()


def test_callers_load_from_the_cache_in_a_fresh_process(tmp_path):
    (tmp_path / "kern_mod.py").write_text(textwrap.dedent("""
        from numba import njit

        @njit(cache=True)
        def scaled_sum(a, s):
            t = 0.0
            for i in range(a.shape[0]):
                t += s * a[i]
            return t
        """))
    (tmp_path / "caller_mod.py").write_text(textwrap.dedent("""
        from numba import njit
        from skfem_mpm.kernels.by_symbol import call
        from kern_mod import scaled_sum

        @njit(cache=True)
        def middle(a):
            return call(scaled_sum, a, 3.0)

        @njit(cache=True)
        def top(a):
            return middle(a) + 1.0
        """))
    script = textwrap.dedent("""
        import numpy as np
        from caller_mod import top
        print(top(np.arange(4.0)), top.stats.cache_hits.total(), top.stats.cache_misses.total())
        """)
    def run():
        value, hits, misses = _fresh_process(tmp_path, script)
        return float(value), int(hits), int(misses)

    assert run() == (19.0, 0, 1)  # compiled, and cached
    assert run() == (19.0, 1, 0)  # loaded: the kernel's symbol registered on load


def test_a_caller_compiled_on_cached_code_keeps_its_hooks(tmp_path):
    """A function compiled in one process, loaded from the cache in a
    second where a new caller links it, and that caller loaded in a third:
    the kernel's symbol must be registered there too (numba rebuilds a
    cached library without its reload hooks: by_symbol gives them back)."""
    (tmp_path / "kern2_mod.py").write_text(textwrap.dedent("""
        from numba import njit

        @njit(cache=True)
        def doubled_sum(a):
            return 2.0 * a.sum()
        """))
    (tmp_path / "inner_mod.py").write_text(textwrap.dedent("""
        from numba import njit
        from skfem_mpm.kernels.by_symbol import call
        from kern2_mod import doubled_sum

        @njit(cache=True)
        def inner(a):
            return call(doubled_sum, a)
        """))
    (tmp_path / "outer_mod.py").write_text(textwrap.dedent("""
        from numba import njit
        from inner_mod import inner

        @njit(cache=True)
        def outer(a):
            return inner(a) + 1.0
        """))
    inner_only = "import numpy as np\nfrom inner_mod import inner\nprint(inner(np.ones(3)))"
    assert _fresh_process(tmp_path, inner_only) == ["6.0"]  # inner compiled and cached
    both = textwrap.dedent("""
        import numpy as np
        from outer_mod import outer
        print(outer(np.ones(3)), outer.stats.cache_hits.total())
        """)
    assert _fresh_process(tmp_path, both) == ["7.0", "0"]  # outer compiled on cached inner
    assert _fresh_process(tmp_path, both) == ["7.0", "1"]  # outer loaded: hooks kept


def test_one_caller_serves_kernels_at_run_time_addresses(tmp_path):
    """call_at: the kernel is data; one compiled caller runs either kernel
    of the same argument types, recorded at compile time and again when the
    caller loads from the cache in a fresh process."""
    (tmp_path / "at_mod.py").write_text(textwrap.dedent("""
        from numba import njit
        from skfem_mpm.kernels.by_symbol import call_at

        @njit(cache=True)
        def add(a, s):
            for i in range(a.shape[0]):
                a[i] += s

        @njit(cache=True)
        def scale(a, s):
            for i in range(a.shape[0]):
                a[i] *= s

        _AT = call_at("test:kernel")

        @njit(cache=True)
        def apply(address, a, n):
            for _ in range(n):
                _AT(address, a, 2)  # the literal 2 is cast to the recorded float
        """))
    script = textwrap.dedent("""
        import numpy as np
        from numba import types
        from skfem_mpm.kernels.by_symbol import ARGUMENT_TYPES, native_address
        from at_mod import add, apply, scale
        a = np.ones(3)
        apply(0, a, 0)  # compiles or loads apply: records the argument types
        argtypes = ARGUMENT_TYPES["test:kernel"]
        apply(native_address(add, argtypes), a, 3)
        apply(native_address(scale, argtypes), a, 2)
        print(a[0], len(apply.signatures), apply.stats.cache_hits.total())
        """)
    def run():
        value, signatures, hits = _fresh_process(tmp_path, script)
        return float(value), int(signatures), int(hits)

    assert run() == ((1 + 3 * 2.0) * 4, 1, 0)  # one compile serves both kernels
    assert run() == (28.0, 1, 1)  # loaded from the cache, argument types recorded again


def test_a_site_compiled_for_two_type_lists_is_ambiguous():
    from skfem_mpm.kernels.by_symbol import ARGUMENT_TYPES, call_at

    at = call_at("test:ambiguous")

    @njit(cache=False)
    def through(address, a):
        at(address, a)

    through.compile((types.int64, types.float64[::1]))  # compiled, never run
    assert ARGUMENT_TYPES["test:ambiguous"] == (types.float64[::1],)
    through.compile((types.int64, types.float64[:, ::1]))
    assert ARGUMENT_TYPES["test:ambiguous"] is None


def test_a_call_site_must_be_named():
    from skfem_mpm.kernels.by_symbol import call_at

    for site in ("", None, 3):
        with pytest.raises(ValueError, match="site must be a non-empty string"):
            call_at(site)


@pytest.mark.parametrize("need", ["entry point", "typing a call"])
def test_a_kernel_another_process_is_compiling_is_loaded_not_compiled(tmp_path, need):
    """by_symbol.compile_lock: while one process compiles a kernel (holding
    its lock), a second that needs it waits, then loads the first's
    machine code from the shared cache instead of compiling it again;
    both where the kernel's address is taken and where a caller types its
    ``call`` (which compiles the kernel)."""
    module = "kern3_mod" if need == "entry point" else "kern4_mod"
    (tmp_path / f"{module}.py").write_text(textwrap.dedent("""
        from numba import njit

        @njit(cache=True)
        def tripled_sum(a):
            return 3.0 * a.sum()
        """))
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"),
               PYTHONPATH=os.pathsep.join([str(tmp_path), *sys.path]))
    use = "_entry_point(tripled_sum, (types.float64[::1],))" if need == "entry point" else \
        "njit(lambda a: call(tripled_sum, a)).compile((types.float64[::1],))"
    script = textwrap.dedent(f"""
        from numba import njit, types
        from skfem_mpm.kernels.by_symbol import _entry_point, call
        from {module} import tripled_sum
        {use}
        print(tripled_sum.stats.cache_hits.total(), tripled_sum.stats.cache_misses.total())
        """)
    sys.path.insert(0, str(tmp_path))
    old_cache = numba_config.CACHE_DIR
    try:
        numba_config.CACHE_DIR = str(tmp_path / "cache")  # (the lock's name and the cache)
        tripled_sum = __import__(module).tripled_sum

        with compile_lock(tripled_sum, (types.float64[::1],)):
            second = subprocess.Popen([sys.executable, "-c", script], env=env, cwd=tmp_path,
                                      stdout=subprocess.PIPE, text=True)
            time.sleep(3.0)  # it has started and waits for the lock
            assert second.poll() is None
            tripled_sum.compile((types.float64[::1],))
        out, _ = second.communicate(timeout=120)
    finally:
        numba_config.CACHE_DIR = old_cache
        sys.path.remove(str(tmp_path))
    assert out.split() == ["1", "0"]  # loaded from the cache, not compiled
