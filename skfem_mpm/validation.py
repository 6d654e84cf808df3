"""Input checks shared by the public API: each raises ValueError naming the
argument, the bad value and what would be valid."""
import numbers
import os
import tempfile

import numpy as np

__all__ = [
    "check_positive",
    "check_finite_array",
    "check_choice",
    "check_positive_int",
    "as_points",
    "can_write_in",
]


def _short(value, limit=80):
    text = repr(value)
    return text if len(text) <= limit else text[:limit] + "..."


def check_positive(name, value, allow_zero=False):
    """A finite real number > 0 (or >= 0 with ``allow_zero``)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name} must be a real number, got {value!r}")
    value = float(value)
    if not np.isfinite(value) or value < 0 or (value == 0 and not allow_zero):
        bound = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{name} must be finite and {bound}, got {value}")
    return value


def check_positive_int(name, value):
    """An integer >= 1."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (numbers.Integral,)):
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    if int(value) < 1:
        raise ValueError(f"{name} must be a positive integer, got {value}")
    return int(value)


def check_choice(name, value, choices):
    """One of the strings in ``choices``."""
    if value not in choices:
        valid = ", ".join(repr(c) for c in choices)
        raise ValueError(f"{name} must be one of {valid}, got {value!r}")
    return value


def check_finite_array(name, array, shape=None):
    """A float64 array with no NaN or Inf (and the given shape, if any;
    ``None`` in ``shape`` matches any length)."""
    if np.iscomplexobj(array):
        raise ValueError(f"{name} must be real numbers, got complex values "
                         f"(dtype {np.asarray(array).dtype})")
    try:
        a = np.asarray(array, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be an array of real numbers, got "
                         f"{_short(array)}") from None
    if shape is not None:
        ok = a.ndim == len(shape) and all(
            want is None or want == got for want, got in zip(shape, a.shape)
        )
        if not ok:
            want = "(" + ", ".join("n" if s is None else str(s) for s in shape) + \
                ("," if len(shape) == 1 else "") + ")"
            raise ValueError(f"{name} must have shape {want}, got {a.shape}")
    if a.size and not np.all(np.isfinite(a)):
        flat = int(np.flatnonzero(~np.isfinite(a.reshape(-1)))[0])
        index = np.unravel_index(flat, a.shape)
        row = index[0] if a.ndim else ()
        raise ValueError(
            f"{name} must be finite, got {a.reshape(-1)[flat]} at index {row}"
        )
    return a


def as_points(name, x, dim):
    """Points as an (n, dim) float array; (n,) is accepted when dim == 1."""
    a = check_finite_array(name, x)
    if a.ndim == 1 and dim == 1:
        a = a[:, None]
    if a.ndim != 2 or a.shape[1] != dim:
        raise ValueError(f"{name} must have shape (n, {dim}), got {a.shape}")
    return check_finite_array(name, a)


def can_write_in(folder):
    """True when a file can be created in the existing ``folder``: tried
    (a temporary file, removed at once), not asked of ``os.access``, which
    says yes to root on read-only file systems such as /proc and /sys."""
    try:
        fd, probe = tempfile.mkstemp(prefix=".skfem-mpm-check-", dir=folder)
    except OSError:
        return False
    os.close(fd)
    os.remove(probe)
    return True
