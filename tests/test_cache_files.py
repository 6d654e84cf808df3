"""numba's on-disk cache filled by several processes at once
(skfem_mpm.kernels.cache_files): no interleaving of two saves ever sends a
signature to another signature's machine code."""
import itertools
import threading

import pytest
from numba.core import caching

from skfem_mpm.kernels import cache_files, mpm
from skfem_mpm.kernels.cache_files import KeyNamedCacheFile

OPERATIONS = ("_load_index", "_save_index", "_save_data")


class Scheduled:
    """Two cache files (one per 'process') on one directory whose file
    operations run one at a time in a given order of owners."""

    def __init__(self, cls, directory, order):
        self.order, self.position = list(order), 0
        self.turn = threading.Condition()
        self.files = {owner: self._scheduled(cls, directory, owner) for owner in "AB"}

    def _scheduled(self, cls, directory, owner):
        file = cls(str(directory), "kernel-1.py311", "stamp")
        for name in OPERATIONS:
            original = getattr(file, name)

            def operation(*args, _original=original):
                with self.turn:
                    if not self.turn.wait_for(self._mine(owner), timeout=5.0):
                        raise TimeoutError(f"{owner} waited for its turn")
                    result = _original(*args)
                    self.position += 1
                    self.turn.notify_all()
                    return result
            setattr(file, name, operation)
        return file

    def _mine(self, owner):
        return lambda: self.position >= len(self.order) or self.order[self.position] == owner

    def save_both(self, keys, data):
        threads = [threading.Thread(target=self.files[o].save, args=(keys[o], data[o]))
                   for o in "AB"]
        for t in threads:
            t.start()
        for t in threads:
            t.join()


def orders(per_save):
    """Every order of two saves' ``per_save`` file operations each."""
    for slots in itertools.combinations(range(2 * per_save), per_save):
        yield ["A" if i in slots else "B" for i in range(2 * per_save)]


@pytest.mark.parametrize("order", list(orders(3)), ids="".join)
def test_two_saves_at_once_never_give_a_key_the_other_keys_data(tmp_path, order):
    keys = {"A": ("sig A", ("cpu",), ("h1", "h2")), "B": ("sig B", ("cpu",), ("h1", "h2"))}
    data = {"A": b"machine code of A", "B": b"machine code of B"}
    scheduled = Scheduled(KeyNamedCacheFile, tmp_path, order)
    scheduled.save_both(keys, data)
    later = KeyNamedCacheFile(str(tmp_path), "kernel-1.py311", "stamp")  # a later process
    loaded = {o: later.load(keys[o]) for o in "AB"}
    for o in "AB":
        assert loaded[o] in (data[o], None), (o, loaded[o])  # a miss compiles again
    assert any(loaded[o] == data[o] for o in "AB")  # the index keeps at least one
    # a miss is saved again and found
    for o in "AB":
        later.save(keys[o], data[o])
    assert {o: later.load(keys[o]) for o in "AB"} == data


def test_a_data_file_not_holding_its_key_is_a_miss(tmp_path):
    """A file written by numba's own scheme under the name the index gives
    (an older cache), or holding another key, is never loaded."""
    key = ("sig A", ("cpu",), ("h1", "h2"))
    file = KeyNamedCacheFile(str(tmp_path), "kernel-1.py311", "stamp")
    file.save(key, b"code")
    name = file._key_name(key)
    file._save_data(name, b"numba's own entry")  # not a tagged entry
    assert file.load(key) is None
    file._save_data(name, ("skfem_mpm key-named cache entry", "another key", b"other"))
    assert file.load(key) is None
    assert file.load(("sig B", ("cpu",), ("h1", "h2"))) is None


def test_the_package_functions_get_the_key_named_cache():
    """Cached kernels of the package use it (installed when skfem_mpm is
    imported); numba's cache objects for other functions keep numba's."""
    assert type(mpm.reduce_stencil._cache._cache_file) is KeyNamedCacheFile

    def elsewhere(x):
        return x
    elsewhere.__module__ = "a_users_module"
    assert not cache_files.owns(elsewhere)
    assert type(caching.FunctionCache(elsewhere)._cache_file) is caching.IndexDataCacheFile
