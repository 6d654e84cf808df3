"""The timeout marker of tests/conftest.py: a hanging case fails with its
name and the suite goes on."""
import importlib
import os
import shutil
import subprocess
import sys
import time

import pytest

HANGING = '''
import pytest


@pytest.mark.timeout(1)
@pytest.mark.parametrize("case", ["quick", "hangs"])
def test_probe(case):
    while case == "hangs":
        pass


def test_after():
    pass
'''


def test_a_hanging_case_fails_with_its_name_and_the_suite_goes_on(tmp_path):
    shutil.copy(os.path.join(os.path.dirname(__file__), "conftest.py"), tmp_path)
    (tmp_path / "test_probe.py").write_text(HANGING)
    t0 = time.perf_counter()
    run = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                          "--rootdir", str(tmp_path), str(tmp_path)], cwd=tmp_path,
                         capture_output=True, text=True, timeout=120, check=False)
    assert time.perf_counter() - t0 < 60
    out = run.stdout
    assert run.returncode == 1, out
    assert "2 passed, 1 failed" in out or "1 failed, 2 passed" in out, out
    assert "test_probe.py::test_probe[hangs]: the test lasted more than 1 s" in out, out


@pytest.mark.parametrize("name", ["inputs", "checkpoints", "runs", "restarts"])
def test_every_case_of_the_hostile_probe_is_bounded(name):
    module = importlib.import_module(f"test_hostile_{name}")
    assert module.pytestmark.name == "timeout" and 0 < module.pytestmark.args[0] <= 600
