"""Time stepping: ``simulate`` (MPM) and ``fem`` (Gauss-quadrature reference)."""
from .fem import fem
from .method import Method
from .result import Result
from .simulate import simulate
from .state import State, prepare
from .steps import (commit, grid_to_particles, particles_to_grid, solve_grid, update_stress)
from .timestep import critical_time_step

__all__ = ["Method", "Result", "State", "simulate", "fem", "prepare", "particles_to_grid",
           "solve_grid", "grid_to_particles", "update_stress", "commit",
           "critical_time_step"]
