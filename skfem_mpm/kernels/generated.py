"""Kernels generated per dimension and degree from one source template.

A template (a function of dim, p and options that returns Python source)
is written once; each variant it yields is saved to a file named after the
variant and a hash of its text, and imported from there, so that numba's
``cache=True`` keeps its machine code between runs (numba caches only
functions defined in files) and a changed template never meets the cache
of an old one. The file is written once and never rewritten (numba's cache
is keyed on the file's time stamp). Its directory is ``_generated`` beside
this module when that is writable, else ``skfem_mpm/kernels`` under the
user's cache directory (``$XDG_CACHE_HOME`` or ``~/.cache``).
"""
import hashlib
import importlib.util
import os
import sys
import tempfile

__all__ = ["indent", "load", "module_header", "times"]

_HERE = os.path.dirname(os.path.abspath(__file__))
_loaded = {}


def _directory():
    local = os.path.join(_HERE, "_generated")
    try:
        os.makedirs(local, exist_ok=True)
        if os.access(local, os.W_OK):
            return local
    except OSError:
        pass
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    path = os.path.join(base, "skfem_mpm", "kernels")
    os.makedirs(path, exist_ok=True)
    return path


def _dependencies():
    """Source of the modules the generated kernels import: their changes
    must reach a new file too (numba does not track a cached function's
    callees)."""
    text = []
    for name in ("stencil.py", "weights.py", "generated.py"):
        with open(os.path.join(_HERE, name), encoding="utf-8") as f:
            text.append(f.read())
    return "".join(text)


def load(name, source):
    """The module of ``source`` (which defines the function ``name``),
    written to the generated-kernel directory once and imported."""
    digest = hashlib.sha1((source + _dependencies()).encode()).hexdigest()[:12]
    key = f"{name}_{digest}"
    if key in _loaded:
        return _loaded[key]
    directory = _directory()
    path = os.path.join(directory, key + ".py")
    if not os.path.exists(path):
        fd, tmp = tempfile.mkstemp(dir=directory, suffix=".tmp")
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(source)
        try:
            os.link(tmp, path)  # atomic, and never replaces a file another process wrote
        except FileExistsError:
            pass
        except OSError:  # no hard links on this file system
            os.replace(tmp, path)
        if os.path.exists(tmp):
            os.unlink(tmp)
    module_name = f"_skfem_mpm_generated_{key}"
    spec = importlib.util.spec_from_file_location(module_name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[module_name] = module
    spec.loader.exec_module(module)
    _loaded[key] = module
    return module


# ------------------------------------------------------ writing the source
def times(*factors):
    """Source of a product, without factors "1.0"."""
    kept = [f for f in factors if f != "1.0"]
    return " * ".join(kept) if kept else "1.0"


def indent(lines, level):
    """The lines joined, each indented by ``level`` levels of four spaces."""
    pad = "    " * level
    return "\n".join(pad + line if line else "" for line in lines)


def module_header(*imports):
    """The first lines of a generated module (with ``imports``)."""
    return "\n".join([
        '"""Generated from a template in skfem_mpm.kernels; do not edit."""',
        "import numpy as np",
        "from numba import njit, prange",
        "",
        "from skfem_mpm.kernels.stencil import closed_axis_functions, extracted_axis_functions",
        "from skfem_mpm.kernels.weights import FAST",
        *imports,
        "",
        "",
    ])
