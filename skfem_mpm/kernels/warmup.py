"""Compile (or load from numba's cache) the kernels a grid will use, on a
tiny input, so that timed runs exclude JIT compilation."""
import numpy as np

__all__ = ["warm_up_kernels"]


def warm_up_kernels(grid):
    if not hasattr(grid, "breakpoints"):
        return
    x = np.array([b[0] + 0.5 * (b[1] - b[0]) for b in grid.bounds])[None, :]
    for axis in range(grid.dim):
        grid.axis_functions(axis, x[:, axis], backend="numba")
