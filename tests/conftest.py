"""Test tiers: the default tier (``python -m pytest``, the README's
command), ``slow`` (``-m slow``; CI runs both) and ``exhaustive`` (full
option products; collected only when ``-m`` names it).

Per-case timeouts: ``@pytest.mark.timeout(seconds)`` bounds each phase
(set-up, call) of a test. When it expires, the case fails with its name
and its time (SIGALRM raises in the test's Python code); a case stuck
inside compiled code, which never returns to Python, is stopped
``TIMEOUT_GRACE`` seconds later by ``faulthandler``, which prints every
thread's stack (naming the test function) and ends the process, instead of
hanging the suite. Without SIGALRM (Windows) the marker does nothing."""
import faulthandler
import signal
import sys
import threading

import pytest

TIMEOUT_GRACE = 60.0


class CaseTimeout(Exception):
    """A test phase outlived its ``timeout`` marker."""


def pytest_configure(config):
    config.addinivalue_line("markers", "timeout(seconds): fail a case (set-up or call) "
                            "that lasts longer, naming it, instead of hanging the suite")


def pytest_collection_modifyitems(config, items):
    """Without ``-m``, the default tier: neither ``slow`` nor ``exhaustive``
    (a case named by its node id, ``file::test``, still runs). ``-m slow``:
    the slow tier; ``exhaustive`` only when ``-m`` names it."""
    marks = config.getoption("-m") or ""
    if "exhaustive" in marks:
        return
    named = [a for a in config.args if "::" in a]

    def default_tier(item):
        return item.get_closest_marker("slow") is None or any(
            item.nodeid.endswith(a.split("/tests/")[-1]) or a in item.nodeid for a in named)

    kept = [item for item in items if item.get_closest_marker("exhaustive") is None
            and (marks or default_tier(item))]
    if len(kept) != len(items):
        config.hook.pytest_deselected(items=[i for i in items if i not in kept])
        items[:] = kept


def _bounded(item, phase):
    marker = item.get_closest_marker("timeout")
    if (marker is None or not hasattr(signal, "SIGALRM")
            or threading.current_thread() is not threading.main_thread()):
        return None
    seconds = float(marker.args[0])

    def expire(signum, frame):
        raise CaseTimeout(f"{item.nodeid}: {phase} lasted more than {seconds:g} s (its "
                          f"timeout marker)")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    faulthandler.dump_traceback_later(seconds + TIMEOUT_GRACE, exit=True, file=sys.stderr)
    return previous


def _release(previous):
    if previous is None:
        return
    signal.setitimer(signal.ITIMER_REAL, 0.0)
    faulthandler.cancel_dump_traceback_later()
    signal.signal(signal.SIGALRM, previous)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_setup(item):
    previous = _bounded(item, "set-up")
    try:
        yield
    finally:
        _release(previous)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_call(item):
    previous = _bounded(item, "the test")
    try:
        yield
    finally:
        _release(previous)
