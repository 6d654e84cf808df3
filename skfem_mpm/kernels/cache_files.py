"""numba's on-disk cache, safe when several processes fill it at once.

numba keeps a function's compiled overloads in one index file (signature
-> data file name) and one data file per overload. Saving a new overload
reads the index, takes the first unused number for its data file, writes
the index back and then the data (``IndexDataCacheFile.save`` in
numba/core/caching.py). Two processes compiling two overloads of one
function at the same time (pytest-xdist workers, a dask sweep, a cluster's
jobs, all starting on an empty cache) both read the same index and both
take the same number; when one wins the index and the other the data
file, the index sends one signature to the other's machine code, and every
later process that loads it crashes (numba issue #4807, open). This
package's compiled step has several overloads per function (one per
effect set and material), so a cold cache filled in parallel meets this.

:class:`KeyNamedCacheFile` saves without that race:

- the data file is named after a hash of the overload's index key, so two
  overloads never share a file, whatever the order of the two saves;
- the data file is written before the index names it, so an index entry
  never points at a file not yet written;
- the data file holds its key's text, checked on load: a file that does
  not hold it (one written by numba's own scheme, a stale file) is a miss,
  and the overload is compiled again and saved anew.

Two processes saving at once can still drop one another's index entry (the
index is read, extended and written back); the overload is then compiled
once more by a later process. Nothing is ever loaded for the wrong
signature.

Installed once, when :mod:`skfem_mpm.kernels` is imported, for the
functions of this package and of its generated modules
(:data:`skfem_mpm.kernels.wrappers.OWN_MODULES`): a cache object numba
builds for one of them (at ``@njit(cache=True)`` / ``@cfunc(cache=True)``)
gets this index file. Other functions keep numba's.
"""
import hashlib

from numba.core import caching

from .wrappers import OWN_MODULES

__all__ = ["KeyNamedCacheFile", "install", "key_text"]

_TAG = "skfem_mpm key-named cache entry"


def key_text(key):
    """The text of an index key (signature, target, code hashes): what the
    data file's name hashes and what the file holds to be checked."""
    return repr(key)


class KeyNamedCacheFile(caching.IndexDataCacheFile):
    """An index and data files whose data file names come from the key."""

    def _key_name(self, key):
        digest = hashlib.sha256(key_text(key).encode()).hexdigest()
        return self._data_name(int(digest[:15], 16))

    def save(self, key, data):
        """Write the data file of ``key``, then add it to the index."""
        name = self._key_name(key)
        self._save_data(name, (_TAG, key_text(key), data))
        overloads = self._load_index()
        if overloads.get(key) != name:
            overloads[key] = name
            self._save_index(overloads)

    def load(self, key):
        """The data saved for ``key``, or None (a miss) when the index has
        no entry, its file is gone, or the file is not ``key``'s."""
        overloads = self._load_index()
        name = overloads.get(key)
        if name is None:
            return None
        try:
            entry = self._load_data(name)
        except OSError:  # removed since the index was read
            return None
        if not (isinstance(entry, tuple) and len(entry) == 3 and entry[0] == _TAG
                and entry[1] == key_text(key)):
            return None
        return entry[2]


def owns(py_func):
    """Whether ``py_func`` is one of this package's (or its generated
    modules') functions."""
    return (getattr(py_func, "__module__", None) or "").startswith(OWN_MODULES)


def install():
    """Make the cache objects numba builds for this package's functions use
    :class:`KeyNamedCacheFile` (once per process)."""
    init = caching.Cache.__init__
    if getattr(init, "key_named", False):
        return

    def __init__(self, py_func):
        init(self, py_func)
        if owns(py_func):
            self._cache_file.__class__ = KeyNamedCacheFile

    __init__.key_named = True
    caching.Cache.__init__ = __init__
