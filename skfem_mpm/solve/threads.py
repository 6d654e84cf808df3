"""How many threads the compiled kernels use, step by step.

The parallel kernels split their loops into a fixed number of blocks (the
number of numba threads when the run's kernels were bound, see
:class:`skfem_mpm.kernels.mpm.Kernels`), and each block's arithmetic does
not depend on which thread runs it. So the number of threads that *run*
the blocks can change between steps without changing a single bit of the
result; only the wall time changes.

That freedom is what makes a run survive a shared machine. numba's OpenMP
threads spin while they wait at the end of a parallel region; a step has
dozens of regions (a consistent-mass CG iteration alone has several).
When other processes want the cores, a spinning thread holds a core that
the thread it waits for needs, and each region can cost a scheduler time
slice. Making the threads sleep instead (``OMP_WAIT_POLICY=passive``) costs
a wake-up per region, which on an idle machine is slower than spinning.
The policy here keeps the spinning threads while the cores are free, and
runs the blocks on fewer threads while other processes are runnable:

    threads = max(1, min(T, cpus - others))

with T the run's block count, ``cpus`` the processors this process may
use, and ``others`` the runnable threads of other processes: the running
count of ``/proc/loadavg`` minus this process's own running threads
(``/proc/self/task/*/stat``), the smallest of the last three samples taken
at least :attr:`ThreadPolicy.interval` seconds apart (a process that ran
for an instant does not count). Where ``/proc`` is not readable (not
Linux) the thread count stays fixed. ``SKFEM_MPM_THREADS=fixed`` switches
the policy off.
"""
import os
import time

import numba

__all__ = ["ThreadPolicy", "other_runnable_threads"]


def _own_running_threads():
    count = 0
    for task in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{task}/stat", "rb") as f:
                text = f.read()
        except OSError:  # the thread ended meanwhile
            continue
        # state is the field after the parenthesised command name
        if text[text.rindex(b")") + 2:text.rindex(b")") + 3] == b"R":
            count += 1
    return count


def other_runnable_threads():
    """Runnable threads of other processes now (None where unknown)."""
    try:
        with open("/proc/loadavg") as f:
            running = int(f.read().split()[3].split("/")[0])
        return max(0, running - _own_running_threads())
    except (OSError, ValueError, IndexError):
        return None


class ThreadPolicy:
    """Sets numba's thread count for the coming steps (see the module).

    ``blocks`` is the run's fixed block count T. Use::

        policy = ThreadPolicy(blocks)
        ... each step: policy.update() ...
        policy.restore()
    """

    interval = 0.05  # seconds between samples of the machine's load

    def __init__(self, blocks, cpus=None, enabled=None):
        self.blocks = int(blocks)
        self.initial = numba.get_num_threads()
        if cpus is None:
            cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") \
                else os.cpu_count() or 1
        self.cpus = cpus
        if enabled is None:
            setting = os.environ.get("SKFEM_MPM_THREADS", "adaptive")
            if setting not in ("adaptive", "fixed"):
                raise ValueError(f"SKFEM_MPM_THREADS must be 'adaptive' or 'fixed', "
                                 f"got {setting!r}")
            enabled = setting == "adaptive"
        self.enabled = enabled and self.blocks > 1 and other_runnable_threads() is not None
        self.threads = self.initial
        self.samples = []
        self.next_sample = 0.0

    def choose(self, others):
        """Thread count for ``others`` runnable threads of other processes."""
        return max(1, min(self.blocks, self.initial, self.cpus - others))

    def update(self):
        """Sample the load when due and set the thread count it calls for."""
        if not self.enabled:
            return self.threads
        now = time.perf_counter()
        if now < self.next_sample:
            return self.threads
        self.next_sample = now + self.interval
        others = other_runnable_threads()
        if others is None:
            return self.threads
        self.samples = (self.samples + [others])[-3:]
        threads = self.choose(min(self.samples))
        if threads != self.threads:
            numba.set_num_threads(threads)
            self.threads = threads
        return threads

    def restore(self):
        """Back to the thread count in force before the run."""
        if self.threads != self.initial:
            numba.set_num_threads(self.initial)
            self.threads = self.initial
