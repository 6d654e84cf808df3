"""Zero arrays whose memory is mapped page by page, on first write.

A grid array the kernels write only near the particles (the occupied node
range of :func:`skfem_mpm.kernels.scatter.reduce_fields`) costs memory only
for the pages written when its zeros come from an anonymous mapping in
small pages. ``np.zeros`` gives zero pages too, but NumPy asks the kernel
for transparent huge pages for arrays of 4 MiB and more (2 MiB pages on
x86-64), and the first write into a huge page maps all of it; a mapping
of our own asks for small pages (``MADV_NOHUGEPAGE``, where the system
has it).

Below :data:`LAZY_FROM` bytes an array comes from ``np.zeros`` instead: the
memory saved is at most a few pages, and a fresh mapping costs a system
call and a page fault per page at its first write, in every run (a small
run, started many times, would pay them in its steps).
"""
import mmap

import numpy as np

__all__ = ["LAZY_FROM", "lazy_zeros"]

LAZY_FROM = 1 << 18
"""Bytes from which :func:`lazy_zeros` maps its own memory."""


def lazy_zeros(shape, dtype=np.float64):
    """A C-contiguous array of zeros of ``shape`` and ``dtype``: on an
    anonymous memory mapping in small pages from :data:`LAZY_FROM` bytes,
    else ``np.zeros`` (see the module)."""
    dtype = np.dtype(dtype)
    shape = tuple(int(s) for s in np.atleast_1d(shape))
    count = int(np.prod(shape, dtype=np.int64))
    if count * dtype.itemsize < LAZY_FROM:
        return np.zeros(shape, dtype=dtype)
    # private: Python maps anonymous memory shared by default (shared memory
    # pages, allocated on a read too, and shared with a forked child)
    buffer = mmap.mmap(-1, max(count * dtype.itemsize, 1), flags=mmap.MAP_PRIVATE)
    if hasattr(mmap, "MADV_NOHUGEPAGE"):
        buffer.madvise(mmap.MADV_NOHUGEPAGE)
    return np.frombuffer(buffer, dtype=dtype, count=count).reshape(shape)
