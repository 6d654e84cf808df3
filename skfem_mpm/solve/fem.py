"""``fem``: the same scene solved with standard FEM and Gauss quadrature.

The reference for every MPM study: the grid's own space (B-splines or
Lagrange), Gauss quadrature with p + 1 points per axis, a total Lagrangian
formulation for finite strain (small strain otherwise), the same mass type
and the same explicit integrator as the MPM method:

    M a^n = f_ext(t^n) - f_int(u^n)
    v^(n+1) = v^n + dt a^n,   u^(n+1) = u^n + dt v^(n+1)     (musl/usl/usf)
    the first velocity step is halved for 'cd' (central difference)

    f_int,i = sum_g w_g sigma_g grad N_i(X_g)                     (small strain)
    f_int,i = sum_g w_g P(I + grad_X u)(X_g) grad_X N_i(X_g)      (finite strain)

Small strain: the stress at each Gauss point comes from the material's own
update (``material.update``, the same law MPM calls) with the velocity
gradient L_g = grad v^(n+1)(X_g) of the step, so a user's material (plastic,
path dependent) is honoured; for linear elasticity the sum of increments
equals sigma_0 + C : eps(u) to round-off. A material's per-particle state
(``state_fields``) is carried at the Gauss points (each starting from the
nearest particle's value) and at the particles, and updated by the same
``update``. Finite strain: the first Piola
stress of the material's hyperelastic law at F = I + grad_X u.

Gauss points are particles that do not move, so the same transfer matrices
serve both methods. The scene's particles are carried as material points:
their displacement is interpolated at their reference positions, so errors
are measured at the same points as MPM's (with small strain their stress is
integrated by the material's update too, with L_p = grad v(X_p)). The body must fill the grid.
Initial velocity (and stress) fields are fitted from the particles by
mass-weighted discrete least squares (which reproduces every field of the
space, so it keeps the order p + 1).
"""
import time

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.spatial import cKDTree

from ..effects import modified_force
from ..errors import SimulationError
from ..kernels import resolve_backend
from ..materials.state import split_update, state_layout
from ..particles import Particles
from ..quadrature import transfer_matrices
from ..scene import Scene
from ..spline.grid import side_axis
from .grid_system import Constraints, GridSystem
from .method import Method
from .result import Recorder
from .timestep import critical_time_step, stable_time_step
from .timing import PhaseTimer

__all__ = ["fem"]


def _check_fills_grid(scene, particles):
    grid = scene.grid
    grid_volume = float(np.prod([hi - lo for lo, hi in grid.bounds])) if hasattr(
        grid, "breakpoints") else float(np.sum(grid.gauss_rule(1)[1]))
    volume = float(particles.V0.sum())
    cells, _ = grid.locate(particles.X)
    empty = grid.ncells - np.unique(cells).size
    if abs(volume - grid_volume) > 1e-9 * grid_volume or empty:
        raise ValueError(
            f"fem needs a body that fills the grid: the particles cover a volume of "
            f"{volume:.6g} of the grid's {grid_volume:.6g} and leave {empty} cell(s) empty; "
            f"build the FEM scene on a grid that matches the body")


def _side_rule(grid, side, k):
    """Gauss points and weights on a side of the grid: the tensor rule of k
    points per cell on each axis along the side."""
    if grid.dim == 1:
        lo, hi = grid.bounds[0]
        return np.array([[lo if side in ("left", "xmin") else hi]]), np.ones(1)
    axis, end = side_axis(side, grid.dim)
    ref, wref = np.polynomial.legendre.leggauss(k)
    ref, wref = 0.5 * (ref + 1.0), 0.5 * wref
    others = [a for a in range(grid.dim) if a != axis]
    points, weights = [], []
    for other in others:
        breaks = grid.breakpoints[other]
        h = np.diff(breaks)
        points.append((breaks[:-1, None] + h[:, None] * ref[None, :]).ravel())
        weights.append((h[:, None] * wref[None, :]).ravel())
    mesh_points = np.meshgrid(*points, indexing="ij")
    mesh_weights = np.meshgrid(*weights, indexing="ij")
    x = np.empty((mesh_points[0].size, grid.dim))
    x[:, axis] = grid.bounds[axis][end]
    for other, values in zip(others, mesh_points):
        x[:, other] = values.ravel()
    w = np.prod([mw.ravel() for mw in mesh_weights], axis=0)
    return x, w


class _FemModel:
    """Gauss-point data and operators of one FEM run."""

    def __init__(self, scene, method, particles, timer):
        grid = scene.grid
        self.grid, self.method, self.timer = grid, method, timer
        k = grid.degree + 1
        with timer("basis"):
            xg, wg, _ = grid.gauss_rule(k)
            self.Ng, self.Gg = transfer_matrices(grid, xg)
            self.Np, self.Gp = transfer_matrices(grid, particles.X)
        nearest = cKDTree(particles.X).query(xg)[1]
        rho = (particles.m / particles.V0)[nearest]
        body = particles.body[nearest]
        self.gauss = Particles(xg, rho * wg, wg.copy(), body=body,
                               state={k: a[nearest] for k, a in particles.state.items()})
        self.wg, self.rho = wg, rho
        self.materials = [b.material for b in scene.bodies]
        self.groups = [(m, np.flatnonzero(body == i)) for i, m in enumerate(self.materials)]
        self.groups = [(m, idx) for m, idx in self.groups if idx.size]
        self.finite = scene.finite_strain
        dim = grid.dim
        stateful = [type(m).__name__ for m in self.materials
                    if m.finite_strain and state_layout(m, dim)]
        if stateful:
            raise ValueError(
                f"fem integrates finite strain with the hyperelastic first Piola stress, "
                f"which has no place for the per-particle state that {stateful[0]} declares; "
                f"use simulate, or fem with small-strain materials")
        if self.finite:
            self.gauss.F = np.broadcast_to(np.eye(dim), (xg.shape[0], dim, dim)).copy()
        with timer("p2g"):
            NgT = self.Ng.T.tocsr()
            M = (NgT @ self.Ng.multiply((rho * wg)[:, None]).tocsr()).tocsr()
            self.lumped = np.asarray(M.sum(axis=1)).ravel()
            self.consistent = M if method.mass == "consistent" else None
        self.NgT = NgT
        self.GgT = tuple(G.T.tocsr() for G in self.Gg)
        # initial fields by mass-weighted least squares at the particles
        NpT = self.Np.T.tocsr()
        A = (NpT @ self.Np.multiply(particles.m[:, None]).tocsr()).tocsc()
        self._fit = spla.factorized(A + sp.identity(A.shape[0]) * 1e-300)
        self.v0 = self._fit(NpT @ (particles.m[:, None] * particles.v))
        s0 = particles.stress
        self.has_initial_stress = bool(np.any(s0 != 0))
        if self.has_initial_stress:
            if self.finite:
                raise ValueError("fem with a finite-strain material starts stress-free; "
                                 "the scene's particles carry an initial stress")
            coeffs = self._fit(NpT @ (particles.m[:, None] * s0.reshape(s0.shape[0], -1)))
            self.stress0_g = (self.Ng @ coeffs).reshape(-1, dim, dim)
            self.stress0_p = (self.Np @ coeffs).reshape(-1, dim, dim)
        if not self.finite:  # the stress state of the Gauss points and of the particles
            zero = np.zeros((xg.shape[0], dim, dim))
            self.gauss.stress = self.stress0_g.copy() if self.has_initial_stress else zero
            self.points = particles.replaced(
                stress=self.stress0_p.copy() if self.has_initial_stress
                else np.zeros_like(particles.stress))
            self.point_groups = [(mat, np.flatnonzero(particles.body == i))
                                 for i, mat in enumerate(self.materials)]
        self.tractions = []  # loads on named sides: Gauss quadrature on the side
        volume = []  # the other particle forces, at the Gauss points
        for e in scene.effects:
            side = e.side_traction()
            if side is None:
                volume += e.bind(self.gauss, grid)
                continue
            xs, ws = _side_rule(grid, side[0], k)
            Ns, _ = transfer_matrices(grid, xs)
            self.tractions.append((side[1], xs, ws, Ns))
        self.volume_forces = [f for f in volume if f.acceleration is None]
        self.force_modifiers = [m for e in scene.effects for m in e.force_modifiers()]
        uniform = [f for f in volume if f.acceleration is not None]
        self.f_uniform = None  # constant in time: m_i g
        if uniform:
            with timer("effects"):
                self.f_uniform = sum(NgT @ f.forces(self.gauss, 0.0) for f in uniform)

    def gradient(self, G, u):
        return np.stack([Gd @ u for Gd in G], axis=-1)  # (n, comps, dim)

    def first_piola(self, grad_u, body):
        """Finite strain: first Piola stress and F = I + grad_X u at points
        of the given bodies."""
        dim = grad_u.shape[-1]
        out = np.zeros_like(grad_u)
        F = np.eye(dim) + grad_u
        for i, m in enumerate(self.materials):
            idx = np.flatnonzero(body == i)
            if idx.size:
                out[idx] = m.first_piola(F[idx])
        return out, F

    @staticmethod
    def _material_update(points, groups, L, dt):
        """Each body's material update of ``points``' stress (and state)
        with L."""
        stress = points.stress.copy()
        new_state = {}
        for material, idx in groups:
            if idx.size:
                s, _, _, st = split_update(material, material.update(points.subset(idx), L[idx],
                                                                     dt), idx.size)
                stress[idx] = s
                for name, values in st.items():
                    if name not in new_state:
                        new_state[name] = points.state[name].copy()
                    new_state[name][idx] = values
        points.stress = stress
        if new_state:
            points.state = {**points.state, **new_state}

    def update_stress(self, v, dt):
        """Small strain: the materials' update at the Gauss points and at the
        particles with the step's velocity gradient (du = dt v)."""
        with self.timer("constitutive"):
            self._material_update(self.gauss, self.groups, self.gradient(self.Gg, v), dt)
            self._material_update(self.points, self.point_groups, self.gradient(self.Gp, v), dt)

    def cauchy(self, F, body):
        out = np.zeros_like(F)
        for i, m in enumerate(self.materials):
            idx = body == i
            if idx.any():
                out[idx] = m.cauchy_stress(F[idx])
        return out

    def internal_force(self, u):
        if self.finite:
            with self.timer("constitutive"):
                S, F = self.first_piola(self.gradient(self.Gg, u), self.gauss.body)
        else:
            S, F = self.gauss.stress, None
        with self.timer("p2g"):
            ws = self.wg[:, None, None] * S
            f = -sum(self.GgT[d] @ ws[:, :, d] for d in range(len(self.GgT)))
        return f, S, F

    def external_force(self, u, t):
        if self.f_uniform is None and not (self.volume_forces or self.tractions):
            return None
        with self.timer("effects"):
            f = np.zeros_like(u) if self.f_uniform is None else self.f_uniform.copy()
            for force in self.volume_forces:
                f += self.NgT @ force.forces(self.gauss, t)
            for traction, xs, ws, Ns in self.tractions:
                x = xs + Ns @ u
                tau = np.asarray(traction(x, t), dtype=np.float64)
                tau = np.broadcast_to(tau.reshape(-1, u.shape[1]) if tau.ndim else tau,
                                      (xs.shape[0], u.shape[1]))
                f += Ns.T @ (ws[:, None] * tau)
        return f


class _FemState:
    """Duck-typed stand-in for the MPM State in the Recorder."""

    def __init__(self, scene, method, model, particles, timer):
        self.scene, self.method, self.grid = scene, method, scene.grid
        self.model, self.timer = model, timer
        self.particles = particles
        self.index = np.arange(particles.n)
        self.t, self.step, self.removed = 0.0, 0, 0
        self.external_work = 0.0
        self.reactions = {}
        self.small_dofs_max = 0
        self.u = np.zeros((scene.grid.ndofs, scene.grid.dim))
        self.v = model.v0.copy()
        self.reference = particles

    def reported_velocity(self):
        return self.particles.v

    def energies(self):
        m = self.model
        if m.consistent is not None:
            kinetic = 0.5 * float(np.sum(self.v * (m.consistent @ self.v)))
        else:
            kinetic = 0.5 * float(np.sum(m.lumped[:, None] * self.v ** 2))
        return kinetic, self.strain

    def refresh_particles(self):
        """Particle positions, velocities and stresses from the grid fields,
        and the strain energy at the Gauss points."""
        m, ref = self.model, self.reference
        with self.timer("g2p"):
            u_p = m.Np @ self.u
            if m.finite:
                S, F = m.first_piola(m.gradient(m.Gp, self.u), ref.body)
                stress = m.cauchy(F, ref.body)
            else:
                stress, F = m.points.stress, None
            self.particles = ref.replaced(x=ref.X + u_p, u=u_p, v=m.Np @ self.v, stress=stress,
                                          F=F if m.finite else ref.F,
                                          state=ref.state if m.finite else m.points.state)
        g = m.gauss
        energy = 0.0
        for mat, idx in m.groups:
            sub = g.subset(idx)
            if m.finite:
                sub = sub.replaced(F=self._F_g[idx])
            else:
                sub = sub.replaced(stress=self._S_g[idx])
            energy += mat.strain_energy(sub)
        self.strain = energy


def fem(scene, method=None, save_every=None, progress=False):
    """Solve ``scene`` with Gauss-quadrature FEM on its grid (see the module
    docstring); returns the same :class:`Result` type as ``simulate``.
    The reconstruction option of ``method`` does not apply and is ignored."""
    if not isinstance(scene, Scene):
        raise TypeError(f"fem needs a Scene (grid, bodies, t_end, effects), got "
                        f"{type(scene).__name__} {scene!r}"[:200])
    method = Method() if method is None else method
    if not isinstance(method, Method):
        raise ValueError(f"method must be a Method, got {method!r}")
    if method.scheme == "rk4":
        raise ValueError("fem integrates in time with the explicit symplectic step (scheme "
                         "'musl', 'usl', 'usf' or 'cd'; 'cd' starts with a half step); "
                         "scheme 'rk4' is not available in fem yet")
    if method.mass == "hybrid":
        raise ValueError("fem: mass='hybrid' has no meaning here (FEM has no particle "
                         "velocities to re-project); use mass='lumped' or 'consistent'")
    if save_every is not None and (isinstance(save_every, bool) or int(save_every) != save_every
                                   or save_every < 1):
        raise ValueError(f"save_every must be a positive integer, got {save_every!r}")
    resolve_backend(method.backend)
    timer = PhaseTimer()
    particles = scene.particles()
    _check_fills_grid(scene, particles)
    model = _FemModel(scene, method, particles, timer)
    state = _FemState(scene, method, model, particles, timer)
    constraints = Constraints(scene.grid, scene.effects)
    solver = method.mass_solver if method.mass_solver != "auto" else "direct"
    system = GridSystem(model.lumped, constraints, model.consistent, None, 0.0, solver, {})
    state.constraints = constraints
    # time step
    def wave_speed():
        g = model.gauss
        return max(mat.wave_speed(g.subset(idx) if len(model.groups) > 1 else g)
                   for mat, idx in model.groups)
    dt_crit = critical_time_step(scene.grid, wave_speed(), method.mass)
    dt = stable_time_step(method, dt_crit)
    n_steps = max(1, int(np.ceil(scene.t_end / dt * (1 - 1e-12))))
    dt = scene.t_end / n_steps
    state.dt, state.dt_crit = dt, dt_crit
    # initial state
    f_int, S, F = model.internal_force(state.u)
    state._S_g, state._F_g = S, F
    state.refresh_particles()
    recorder = Recorder()
    recorder.save(state)
    values = constraints.values
    t0 = time.perf_counter()
    bar = None
    if progress:
        from tqdm import tqdm
        import sys

        bar = tqdm(total=n_steps, unit="step", disable=not sys.stderr.isatty(), leave=False)
    for n in range(n_steps):
        t = n * dt
        force = f_int
        f_ext = model.external_force(state.u, t)
        if f_ext is not None:
            force = force + f_ext
        if model.force_modifiers:
            for modifier in model.force_modifiers:
                force = modified_force(modifier, force, state.v, model.lumped, dt, t, 0.0)
        with timer("solve"):
            a_values = (values(t + dt) - values(t)) / dt if constraints.prescribed \
                else np.zeros_like(force)
            a = system.solve(force, a_values, "acceleration")
            if constraints.any:
                state.reactions = constraints.reactions(system.residual(a, force))
            factor = 0.5 if (method.scheme == "cd" and n == 0) else 1.0
            state.v = state.v + factor * dt * a
            du = dt * state.v
            if f_ext is not None:
                state.external_work += float(np.sum(f_ext * du))
            state.u = state.u + du
        if not model.finite:
            model.update_stress(state.v, dt)
        f_int, S, F = model.internal_force(state.u)
        if not (np.all(np.isfinite(state.u)) and np.all(np.isfinite(state.v))):
            result = recorder.result(state, time.perf_counter() - t0, 0.0, kind="fem")
            raise SimulationError(f"fem step {n + 1} produced NaN or Inf", result=result,
                                  step=n + 1, time=t)
        state._S_g, state._F_g = S, F
        state.step = n + 1
        state.t = state.step * dt if state.step < n_steps else scene.t_end
        if bar is not None:
            bar.update(1)
        if save_every is not None and state.step % save_every == 0:
            state.refresh_particles()
            recorder.save(state)
    if bar is not None:
        bar.close()
    if recorder.last_step_saved != state.step:
        state.refresh_particles()
        recorder.save(state)
    return recorder.result(state, time.perf_counter() - t0, 0.0, kind="fem",
                           extra={"grid_displacement": state.u, "grid_velocity": state.v,
                                  "path": "fem"})
