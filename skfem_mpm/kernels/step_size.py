"""The step-size rule of a run, compiled once for both paths: the state of a
run stepping in Python (:class:`skfem_mpm.solve.state.State`) and the
compiled step loop (:mod:`skfem_mpm.solve.compiled_loop`) call these same
functions, so they take the same steps, bit for bit.

    dt_crit = s / (c sqrt(sum_d Lambda(p, mass) / h_d^2))      critical_step
    dt      = cfl dt_crit, or the time left when that reaches
              the end (within a relative 1e-12)                  adaptive_step
    t      <- t + dt, or t_end exactly after the last step       time_after_step
    done   <=> t >= t_end (within a relative 1e-14)              reached_end

(:mod:`skfem_mpm.solve.timestep` gives s, Lambda and their sources; a
reconstructed 2D method multiplies dt_crit by its factor before
``adaptive_step``.) The fast-dof guard of consistent mass compares the
rows' stiffness with ``guard_limit`` M_kk, q / (dt c)^2 with q = guard
s^2 q(p) / Lambda(p, consistent) (:func:`skfem_mpm.solve.timestep.fast_dof_limit`).
"""
from numba import njit

__all__ = ["critical_step", "adaptive_step", "finished_after_step", "time_after_step",
           "reached_end", "guard_limit"]

# error_model "numpy": a zero wave speed (an infinite density) gives an
# infinite dt_crit, as the NumPy rule did, for the callers' checks to name
_JIT = dict(cache=True, inline="always", error_model="numpy")


@njit(**_JIT)
def critical_step(limit, wave_speed, stiffness_root):
    """dt_crit = s / (c r), r = sqrt(sum_d Lambda / h_d^2) (``stiffness_root``)."""
    return limit / (wave_speed * stiffness_root)


@njit(**_JIT)
def adaptive_step(cfl, dt_crit, t, t_end):
    """The step from t: cfl dt_crit, or t_end - t when cfl dt_crit reaches
    at least (1 - 1e-12) of it (the last step ends exactly at t_end)."""
    remaining = t_end - t
    dt = cfl * dt_crit
    return remaining if dt >= remaining * (1 - 1e-12) else dt


@njit(**_JIT)
def finished_after_step(t, dt, t_end):
    """Whether the step of dt from t ends the run (t + dt >= (1 - 1e-14) t_end)."""
    return t + dt >= t_end * (1 - 1e-14)


@njit(**_JIT)
def time_after_step(t, dt, t_end):
    """The time after a step of dt from t: t_end exactly after the last."""
    return t_end if finished_after_step(t, dt, t_end) else t + dt


@njit(**_JIT)
def reached_end(t, t_end):
    """Whether an adaptive run is done: t >= (1 - 1e-14) t_end."""
    return t >= t_end * (1 - 1e-14)


@njit(**_JIT)
def guard_limit(q, dt, wave_speed):
    """The fast-dof guard's limit q / (dt c)^2 of a step dt at wave speed c."""
    d = dt * wave_speed
    return q / (d * d)
