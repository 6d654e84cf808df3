"""The command line says when it compiles kernels (first use only), and how
long that took; with a warm cache it says nothing."""
import io
import json
import os
import subprocess
import sys
import time

import pytest

from skfem_mpm.cli import _CompileNotice

MESSAGE = "compiling kernels (first use only)..."


def test_a_long_block_is_announced_with_its_time():
    stream = io.StringIO()
    with _CompileNotice(after=0.05, stream=stream):
        time.sleep(0.3)
    text = stream.getvalue()
    assert text.startswith(MESSAGE) and text.endswith(" s\n"), text
    seconds = float(text[len(MESSAGE):].split()[0])
    assert 0.25 <= seconds < 5.0, text


def test_a_short_block_prints_nothing():
    stream = io.StringIO()
    with _CompileNotice(after=5.0, stream=stream):
        pass
    assert stream.getvalue() == ""


def test_a_warm_cache_is_never_announced():
    """cold=False (the kernels load from the cache): a study's first jobs
    under load last longer than 2 s without compiling; nothing is said."""
    stream = io.StringIO()
    with _CompileNotice(after=0.05, stream=stream, cold=False):
        time.sleep(0.3)
    assert stream.getvalue() == ""


COLD_PROBE = """
import sys
from skfem_mpm.cli import _kernel_cache_is_cold
from skfem_mpm.spline import SplineGrid
import numpy as np
before = _kernel_cache_is_cold()
SplineGrid.line(0.0, 1.0, 4, 2).axis_functions(0, np.array([0.3]), backend="numba")
print(before, _kernel_cache_is_cold())
"""


def test_an_empty_cache_is_cold_until_the_basis_kernels_are_compiled(tmp_path):
    """A child process with an empty NUMBA_CACHE_DIR: cold; after one basis
    evaluation has compiled (and cached) its kernel: not cold."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path), NUMBA_NUM_THREADS="1")
    run = subprocess.run([sys.executable, "-c", COLD_PROBE], env=env, capture_output=True,
                         text=True, timeout=600, check=False,
                         cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["True", "False"], run.stdout


def _run_cli(cache, *argv):
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), NUMBA_NUM_THREADS="1")
    return subprocess.run([sys.executable, "-m", "skfem_mpm.cli", *argv], env=env,
                          # a cold compile took 237 s at load 2.5 and over 900 s at load 9
                          capture_output=True, text=True, timeout=3600, check=False,
                          cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


@pytest.mark.slow
def test_first_use_says_compiling_then_a_warm_cache_is_silent(tmp_path):
    """A child process with an empty NUMBA_CACHE_DIR compiles (tens of
    seconds) and says so on stderr with the time; the same command again
    loads the kernels from that cache and prints no such line. stdout stays
    one JSON object either way."""
    argv = ("run", "vibrating-string", "--cells", "8", "--degree", "1", "--json")
    cold = _run_cli(tmp_path, *argv)
    assert cold.returncode == 0, cold.stderr
    line = next((s for s in cold.stderr.splitlines() if s.startswith(MESSAGE)), None)
    assert line is not None, cold.stderr
    assert float(line[len(MESSAGE):].split()[0]) > 2.0, line
    assert json.loads(cold.stdout)["jit_time_s"] > 2.0
    warm = _run_cli(tmp_path, *argv)
    assert warm.returncode == 0, warm.stderr
    assert MESSAGE not in warm.stderr, warm.stderr
    json.loads(warm.stdout)
