"""The MPM step as named functions a user can call in their own loop.

    state = prepare(scene, method)
    while not state.done:
        state.next_step_size()
        grid = particles_to_grid(state)          # mass, momentum, forces on the grid
        solve_grid(state, grid)                  # nodal accelerations (and velocities)
        L = grid_to_particles(state, grid)       # particle velocities, positions
        update_stress(state, L, grid)            # constitutive update
        commit(state, grid)                      # external work, checks, new state current

This is MUSL on the reference executor. ``simulate`` runs the scheme of
:mod:`skfem_mpm.solve.schemes` on an executor, with saves and guards; these
functions are the reference executor's operations
(:class:`skfem_mpm.solve.reference.ReferenceExecutor`).
The formulas (sums over particles p and grid dofs i, N_ip = N_i(x_p)):

    lumped mass        m_i = sum_p m_p N_ip
    consistent mass    M_ij = sum_p m_p N_ip N_jp
    momentum           P_i = sum_p m_p v_p N_ip
    internal force     f_i = - sum_p V_p sigma_p grad N_i(x_p)
    external force     f_i += sum_p f_p N_ip         (Gravity, BodyForce, Traction)
    velocity gradient  L_p = sum_i v_i (x) grad N_i(x_p)

The new state is built in fresh arrays; the previous one stays untouched
until ``commit`` accepts the new one, so a failed step leaves the last good
state intact.
"""
import numpy as np

from ..effects import modified_force
from ..errors import InvalidState
from ..kernels.step_size import guard_limit
from ..materials.state import split_update
from ..quadrature import _csr, _csr_pattern, transfer_matrices
from ..reconstruct import RECONSTRUCTORS, integration_rule
from .timestep import fast_dof_limit, lumping_fraction

__all__ = ["Transfer", "GridData", "particles_to_grid", "solve_velocity", "solve_grid",
           "update_particle_velocities", "project_velocity", "move_particles",
           "grid_to_particles", "update_stress", "material_updates", "external_work", "commit",
           "particle_forces", "internal_force", "particle_coverage"]


class Transfer:
    """N and grad N at the current particle positions (one step).

    ``to_grid(a)`` = N^T a, ``to_particles(g)`` = N g,
    ``divergence_to_grid(s)`` = sum_d grad_d N^T s[..., d],
    ``gradient_to_particles(g)`` = (grad N g) with shape (n, comps, dim).
    """

    def __init__(self, grid, x, timer, backend=None):
        with timer("locate"):
            located = grid.locate_axes(x)
        with timer("basis"):
            dofs, values, grads = grid.shape_functions(x, check=False, backend=backend,
                                                       located=located)
            pattern = _csr_pattern(dofs)
            shape = (x.shape[0], grid.ndofs)
            self.N = _csr(values, pattern, shape)
            self.grad_N = tuple(_csr(np.ascontiguousarray(grads[:, :, d]), pattern, shape)
                                for d in range(grid.dim))
        self.dofs, self.values = dofs, values
        self.NT = self.N.T.tocsr()
        self.grad_NT = tuple(G.T.tocsr() for G in self.grad_N)

    def to_grid(self, a):
        return self.NT @ a

    def to_particles(self, g):
        return self.N @ g

    def divergence_to_grid(self, s):
        """sum_d (grad_d N)^T s[:, :, d]; s has shape (n, comps, dim)."""
        out = self.grad_NT[0] @ s[:, :, 0]
        for d in range(1, len(self.grad_NT)):
            out += self.grad_NT[d] @ s[:, :, d]
        return out

    def gradient_to_particles(self, g):
        """L[p, c, d] = sum_i g[i, c] dN_i/dx_d (x_p)."""
        return np.stack([G @ g for G in self.grad_N], axis=-1)

    def consistent_mass(self, m):
        """M = N^T diag(m) N."""
        return (self.NT @ self.N.multiply(m[:, None]).tocsr()).tocsr()


class GridData:
    """What the particles put on the grid in one step."""

    def __init__(self, transfer, lumped, consistent, momentum, force, external, system=None,
                 project_momentum=None, point_mass=None):
        self.transfer = transfer
        self._project_momentum = project_momentum
        self._point_mass = point_mass
        self.lumped = lumped
        self.consistent = consistent
        self.momentum = momentum
        self.force = force
        self.external = external
        self.system = system       # the step's grid system (hybrid: the acceleration's)
        self.velocity_system = None  # hybrid: the consistent system of the velocity solves
        self.acceleration = None
        self.velocity = None       # grid velocity used to move the particles
        self.velocity_old = None   # grid velocity from the particle momentum
        self.new = {}              # arrays of the new particle state
        self.external_grid = None  # grid force of the declared loads
        self.L = None              # velocity gradient at the particles
        self.particle_acceleration = None  # N a at the particles
        self.keep_acceleration = False     # CD: the state keeps N a (reported velocities)
        self.work = None                   # external work when a scheme computes its own

    def coverage(self):
        """The fast-dof guard's per-dof sums over the particles (K_i, M_ii,
        m_i) of :func:`particle_coverage`, with a reconstruction too."""
        return particle_coverage(self.transfer, self._point_mass)

    def project_momentum(self, particles, v):
        """Grid momentum of particle velocities v: N^T (m v), or its
        reconstructed counterpart."""
        if self._project_momentum is not None:
            return self._project_momentum(v)
        return self.transfer.to_grid(particles.m[:, None] * v)


def particle_coverage(transfer, m):
    """(K, D, m_L): per dof, K_i = sum_p m_p |grad N_i(x_p)|^2 (K_ii / c^2 of
    the particle stiffness), D_i = sum_p m_p N_i(x_p)^2 (the particle
    consistent diagonal) and m_i = sum_p m_p N_i(x_p) (the lumped mass):
    what the fast-dof guard measures a dof's coverage and frequency with
    (:func:`skfem_mpm.solve.timestep.covered_stiffness`; compiled twin
    :func:`skfem_mpm.kernels.mpm.particle_coverage`)."""
    K = sum(G.multiply(G).T @ m for G in transfer.grad_N)
    return K, transfer.N.multiply(transfer.N).T @ m, transfer.to_grid(m)


def particle_forces(state, which=None, particles=None, t=None):
    """Sum of the declared particle forces f_p (n, dim), or None without any.
    ``which`` = 'volume' (gravity, body forces) or 'surface' (tractions:
    for work accounting; side tractions reach the grid through
    :func:`surface_forces`) selects one kind. ``particles`` and ``t``
    default to the state's (a Runge-Kutta stage passes its own)."""
    p = state.particles if particles is None else particles
    t = state.t if t is None else t
    chosen = [f for f in state.forces if which is None or (which == "surface") == f.surface]
    if not chosen:
        return None
    with state.timer("effects"):
        total = None
        for f in chosen:
            term = f.forces(p, t)
            total = term if total is None else total + term
    return total


def surface_forces(state, external, particles=None, t=None):
    """Grid forces of the declared tractions: side tractions at the particles'
    faces, mask tractions through N^T; ``external`` is the Transfer."""
    p = state.particles if particles is None else particles
    t = state.t if t is None else t
    total = None
    with state.timer("effects"):
        for f in state.forces:
            if not f.surface:
                continue
            term = f.grid_forces(p, t, state.grid)
            if term is None:
                term = external.to_grid(f.forces(p, t))
            total = term if total is None else total + term
    return total


def reconstructed_grid_data(state, transfer, particles=None, t=None):
    """Mass, momentum and forces integrated with Gauss quadrature of
    reconstructed particle fields (see :mod:`skfem_mpm.reconstruct`)."""
    p = state.particles if particles is None else particles
    grid = state.grid
    dim = grid.dim
    method = state.method
    recon = method.reconstruction
    recon = RECONSTRUCTORS[recon] if isinstance(recon, str) else recon
    options = method.reconstruction_options
    volume = particle_forces(state, "volume", p, t)
    surface = particle_forces(state, "surface", p, t)
    surface_grid = surface_forces(state, transfer, p, t) if surface is not None else None
    with state.timer("reconstruct"):
        rule = integration_rule(grid, p, grid.degree + 2)
        Ng, Gg = transfer_matrices(grid, rule.x)
        rho = p.m / p.V
        fields = [rho[:, None], rho[:, None] * p.v, p.stress.reshape(p.n, dim * dim)]
        if volume is not None:
            fields.append(volume / p.V[:, None])
        g = recon(grid, p, np.concatenate(fields, axis=1), rule, **options)
    with state.timer("p2g"):
        w = rule.w
        NgT = Ng.T.tocsr()
        rho_g = g[:, 0]
        lumped = NgT @ (w * rho_g)
        momentum = NgT @ (w[:, None] * g[:, 1:1 + dim])
        sigma = g[:, 1 + dim:1 + dim + dim * dim].reshape(-1, dim, dim)
        ws = w[:, None, None] * sigma
        force = -sum(Gg[d].T @ ws[:, :, d] for d in range(dim))
        if volume is not None:
            force += NgT @ (w[:, None] * g[:, 1 + dim + dim * dim:])
        if surface_grid is not None:
            force += surface_grid
    consistent = None
    if method.needs_consistent_mass:
        with state.timer("mass_matrix"):
            consistent = (NgT @ Ng.multiply((w * rho_g)[:, None]).tocsr()).tocsr()

    def project_momentum(v):
        with state.timer("reconstruct"):
            rv = recon(grid, p, rho[:, None] * v, rule, **options)
        with state.timer("p2g"):
            return NgT @ (w[:, None] * rv)

    external = volume if surface is None else (surface if volume is None else volume + surface)
    return GridData(transfer, lumped, consistent, momentum, force, external,
                    project_momentum=project_momentum, point_mass=p.m)


def internal_force(state, transfer, particles=None):
    """f_i = - sum_p V_p sigma_p grad N_i(x_p), shape (dofs, dim)."""
    p = state.particles if particles is None else particles
    return -transfer.divergence_to_grid(p.V[:, None, None] * p.stress)


def particles_to_grid(state, particles=None, t=None):
    """Mass (lumped, and consistent if the method needs it), momentum, and
    internal plus external forces on the grid at the current positions
    (of ``particles`` at time ``t``: default the state's)."""
    p = state.particles if particles is None else particles
    transfer = Transfer(state.grid, p.x, state.timer, state.backend)
    if state.method.reconstruction != "none":
        return reconstructed_grid_data(state, transfer, p, t)
    volume = particle_forces(state, "volume", p, t)
    surface = particle_forces(state, "surface", p, t)
    surface_grid = surface_forces(state, transfer, p, t) if surface is not None else None
    with state.timer("p2g"):
        lumped = transfer.to_grid(p.m)
        momentum = transfer.to_grid(p.m[:, None] * p.v)
        force = internal_force(state, transfer, p)
        external_grid = None
        if volume is not None:
            external_grid = transfer.to_grid(volume)
        if surface_grid is not None:
            external_grid = surface_grid if external_grid is None else external_grid + surface_grid
        if external_grid is not None:
            force += external_grid
    consistent = None
    if state.method.needs_consistent_mass:
        with state.timer("mass_matrix"):
            consistent = transfer.consistent_mass(p.m)
    external = volume if surface is None else (surface if volume is None else volume + surface)
    data = GridData(transfer, lumped, consistent, momentum, force, external, point_mass=p.m)
    data.external_grid = external_grid
    return data


def step_system(state, data, kind="acceleration"):
    """The step's grid system for a solve of ``kind`` (built once per
    GridData): one system for every solve, except with ``mass="hybrid"``: a
    lumped one for the acceleration (``data.system``) and a consistent one
    for the velocity (``data.velocity_system``, no frequency guard: it
    guards a consistent-mass acceleration)."""
    from .grid_system import GridSystem

    hybrid = state.method.mass == "hybrid"
    if hybrid and kind == "velocity":
        if data.velocity_system is None:
            data.velocity_system = GridSystem(data.lumped, state.constraints, data.consistent,
                                              state.adjacency, state.method.small_mass,
                                              state.mass_solver, state.warm)
        return data.velocity_system
    if data.system is None:
        consistent = None if hybrid else data.consistent
        fast_rows = None
        guard = state.method.frequency_guard
        if consistent is not None and guard > 0:
            limit = guard_limit(guard * fast_dof_limit(state.grid.degree, state.method.scheme),
                                state.dt, state.wave_speed_now)

            def fast_rows(_):
                # the particles' coverage sums, with a reconstruction too
                stiffness, diagonal, lumped = data.coverage()
                k = state.guard_stiffness(stiffness, diagonal, lumped, limit)
                return lumping_fraction(k / (limit * np.maximum(diagonal, 1e-300)))

        data.system = GridSystem(data.lumped, state.constraints, consistent,
                                 state.adjacency, state.method.small_mass,
                                 state.mass_solver, state.warm, fast_rows=fast_rows)
    return data.system


def grid_velocity(state, data, momentum, t):
    """v with M v = P, constrained dofs set to their velocity at time t."""
    with state.timer("solve"):
        system = step_system(state, data, "velocity")
        v = system.solve(momentum, state.constraints.values(t), "velocity")
        system.remember("velocity", v)
    return v


def remember_end_velocity(data):
    """Keep the step's end grid velocity v_old + dt a as the warm start of
    the next step's velocity solve (M v = P with the next step's particle
    momentum, which the particles carry from this v: a closer start than
    this step's v_old, which misses the whole change dt a)."""
    system = data.velocity_system or data.system
    if system is not None:
        system.remember("velocity", data.velocity)


def solve_velocity(state, data):
    """Grid velocity v^n with M v^n = P (constrained dofs: their velocity at t),
    kept as ``data.velocity_old``."""
    data.velocity_old = grid_velocity(state, data, data.momentum, state.t)
    return data.velocity_old


def solve_grid(state, data, need_old_velocity=False, end_velocity=None):
    """Nodal accelerations a with M a = f (damping applied if declared):
    fixed dofs get a = 0, prescribed ones (v(t + dt) - v(t)) / dt.

    With ``end_velocity=c`` (USL, CD, USF) also the grid velocity that moves
    the particles, v = v^n + c dt a, with v^n from M v^n = P."""
    t, dt = state.t, state.dt
    if end_velocity is not None:
        need_old_velocity = True
    if (need_old_velocity or state.force_modifiers) and data.velocity_old is None:
        solve_velocity(state, data)
    force = data.force
    if state.force_modifiers:
        with state.timer("effects"):
            for modifier in state.force_modifiers:
                force = modified_force(modifier, force, data.velocity_old, data.lumped, dt,
                                       t, 0.0)
    with state.timer("solve"):
        system = step_system(state, data)
        c = state.constraints
        values = (c.values(t + dt) - c.values(t)) / dt if c.prescribed else np.zeros_like(force)
        a = system.solve(force, values, "acceleration")
        system.remember("acceleration", a)
        data.acceleration = a
        if c.any:
            state.reactions = c.reactions(system.residual(a, force))
    if end_velocity is not None:
        data.velocity = data.velocity_old + (end_velocity * dt) * a
        remember_end_velocity(data)
    return a


def update_particle_velocities(state, data, velocity_factor=1.0, keep_acceleration=False):
    """v_p^new = v_p + c dt sum_i N_ip a_i (c = velocity_factor), into
    ``data.new``; ``keep_acceleration`` (CD) keeps N a for the reported
    velocities."""
    p, dt = state.particles, state.dt
    with state.timer("g2p"):
        dv = data.transfer.to_particles(data.acceleration)
        data.new["v"] = p.v + (velocity_factor * dt) * dv
    data.particle_acceleration = dv
    data.keep_acceleration = keep_acceleration


def project_velocity(state, data):
    """MUSL: the grid velocity v with M v = N^T (m v_p^new) at t + dt, from
    the updated particle velocities (or their reconstructed momentum)."""
    with state.timer("p2g"):
        momentum = data.project_momentum(state.particles, data.new["v"])
    system = data.velocity_system or data.system
    if system is not None:  # CG warm start: last step's v plus this step's dt a
        system.shift_guess("velocity", state.dt * data.acceleration)
    data.velocity = grid_velocity(state, data, momentum, state.t + state.dt)
    for modifier in state.velocity_modifiers:  # walls
        data.velocity = modifier.modify_velocity(data.velocity, data.lumped)


def move_particles(state, data):
    """Positions x_p + dt N v and displacements with the grid velocity v;
    returns (and keeps as ``data.L``) the velocity gradient L = grad N v at
    the old positions."""
    p, dt = state.particles, state.dt
    tr = data.transfer
    with state.timer("g2p"):
        dx = dt * tr.to_particles(data.velocity)
        L = tr.gradient_to_particles(data.velocity)
    data.new.update(x=p.x + dx, u=p.u + dx)
    data.L = L
    return L


def grid_to_particles(state, data, velocity_factor=1.0):
    """Particle velocities v_p + f dt N a (f = velocity_factor) and positions
    x_p + dt N v_grid; returns the velocity gradient L at the old positions.

    When ``data.velocity`` is None (MUSL after :func:`solve_grid`) the grid
    velocity is re-projected from the updated particle momentum; USL/CD set
    it in :func:`solve_grid` (``end_velocity``)."""
    update_particle_velocities(state, data, velocity_factor)
    if data.velocity is None:
        project_velocity(state, data)
    return move_particles(state, data)


def material_updates(state, L, particles=None):
    """Each body's material ``update`` of ``particles`` (default: the
    current ones) with L: (stress, V, F, new state dict or None when no
    material returned state)."""
    p = state.particles if particles is None else particles
    new_state = None
    if len(state.bodies) == 1:
        material = state.bodies[0][0]
        stress, V, F, st = split_update(material, material.update(p, L, state.dt), p.n)
        if st:
            new_state = {**p.state, **st}
    else:
        stress, V = p.stress.copy(), p.V.copy()
        F = None if p.F is None else p.F.copy()
        for material, index in state.bodies:
            sub = p.subset(index)
            s_b, V_b, F_b, st = split_update(material, material.update(sub, L[index], state.dt),
                                             sub.n)
            stress[index], V[index] = s_b, V_b
            if F_b is not None:
                F[index] = F_b
            if st:
                if new_state is None:
                    new_state, copied = dict(p.state), set()
                for name, values in st.items():
                    if name not in copied:
                        new_state[name] = new_state[name].copy()
                        copied.add(name)
                    new_state[name][index] = values
    if F is None:
        F = p.F
    return stress, V, F, new_state


def update_stress(state, L, data=None, particles=None):
    """Stress, volume (and F, and the material state) of every body from
    its material and L."""
    with state.timer("constitutive"):
        stress, V, F, new_state = material_updates(state, L, particles)
        bad = ~(V > 0)
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise InvalidState(f"volume {V[k]:.3g} <= 0 (J <= 0) at particle {k}", particle=k)
    if data is not None:
        data.new.update(stress=stress, V=V, F=F)
        if new_state is not None:
            data.new["state"] = new_state
    return stress, V, F


def _first_bad(*arrays):
    for a in arrays:
        if a is None:
            continue
        flat = np.isfinite(a.reshape(a.shape[0], -1)).all(axis=1)
        if not flat.all():
            return int(np.flatnonzero(~flat)[0])
    return None


def external_work(state, data):
    """Work of the particle forces over the step: sum_p f_p . (x_p^(n+1) - x_p^n),
    the displacement the scheme actually gives the particles (a Runge-Kutta
    step brings its own quadrature of the power as ``data.work``)."""
    if data.work is not None:
        state.external_work += data.work
        return
    f_p = data.external
    if f_p is not None:
        state.external_work += float(np.sum(f_p * (data.new["u"] - state.particles.u)))


def commit(state, data):
    """Add the step's external work; check the new state (finite, inside the
    grid) and make it current."""
    external_work(state, data)
    new = dict(data.new)
    p = state.particles
    with state.timer("g2p"):
        bad = _first_bad(new.get("x"), new.get("v"), new.get("stress"), new.get("F"),
                         *new.get("state", {}).values())
        if bad is not None:
            raise InvalidState(
                f"non-finite state (NaN or Inf) at particle {bad}", particle=bad)
        nxt = state.without_exits(p.replaced(**new))
    if getattr(data, "keep_acceleration", False) and nxt.n == data.particle_acceleration.shape[0]:
        state.particle_acceleration = data.particle_acceleration
    state.particles = nxt
    state.advance()
