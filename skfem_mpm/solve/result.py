"""``Result`` of a run (MPM or FEM) and the recorder that fills it."""
import json

import numpy as np

from .timing import PHASES

__all__ = ["Result", "Recorder"]

HISTORY_FIELDS = ("X", "x", "u", "v", "stress", "index")
# also saved, for output (ParaView); optional in a checkpoint written before them
OUTPUT_FIELDS = ("m", "V", "body")
ENERGY_FIELDS = ("kinetic", "strain", "external_work", "total")


class Result:
    """What a run returns.

    Attributes
    ----------
    particles
        The final (or, after a failure, last good) particle state.
    times
        Saved times, shape (saves,).
    history
        Per save: ``X`` reference positions, ``x`` positions, ``u``
        displacements, ``v`` velocities, ``stress``, ``index`` (each
        particle's index in the initial set; differs only after removals),
        ``m`` masses, ``V`` volumes, ``body`` body ids,
        and each material state field by its name (``particles.state``,
        e.g. ``history["plastic_strain"]``). Stacked into arrays of shape
        (saves, n, ...) when no particle was removed, otherwise lists.
    energies
        Per save: ``kinetic``, ``strain``, ``external_work`` (work done by
        the declared forces since t = 0) and ``total`` = kinetic + strain;
        see also :attr:`energy_balance`.
    reactions
        Per save, {effect: total reaction force (dim,)} of Fixed/Prescribed.
    timings
        Seconds per phase (locate, basis, p2g, solve, g2p, constitutive,
        reconstruct, effects); ``phase_counts`` how often each ran.
    counts
        particles, cells, dofs, steps, removed, small_dofs_max.
    time, final_time
        The time of ``particles``.
    dt, dt_crit, wall_time, jit_time, method, kind ('mpm' or 'fem').
    cpu_time
        MPM runs: the CPU seconds of this process (``time.process_time``,
        every thread) over the interval ``wall_time`` measures, the steps
        (the compiled loop's compiles at a first need excluded, as there);
        on one thread it depends little on the machine's load, the wall
        time does.
    """

    def __init__(self, **fields):
        for k, v in fields.items():
            setattr(self, k, v)

    @property
    def final_time(self):
        """The time of ``particles``: the end time, or the last good state's
        time after a failure (which need not be a saved time)."""
        time = getattr(self, "time", None)
        return float(self.times[-1]) if time is None else float(time)

    @property
    def energy_balance(self):
        """Per save: E_0 + W_ext - E (E = kinetic + strain energy, E_0 its
        value at the first save, W_ext the work of the declared forces,
        gravity, body forces and tractions, since then). Zero for a run
        that conserves energy; positive: energy dissipated by the method
        (or taken out by a moving Prescribed side, whose work is not
        counted); negative: energy the method created, e.g. an elastic
        block bouncing on a fixed floor with linear MPM. Divide by
        ``energies["total"][0] + abs(external_work)`` for a relative figure."""
        e = self.energies
        return e["total"][0] + e["external_work"] - e["total"]

    def phase_table(self):
        return {p: float(self.timings.get(p, 0.0)) for p in PHASES}

    def save(self, path, grid=True):
        """Write the saved states as a VTU time series with a ParaView
        ``.pvd`` collection (see :func:`skfem_mpm.io.save_result`)."""
        from ..io import save_result

        return save_result(self, path, grid=grid)

    def summary(self):
        """A flat dict of the run's numbers (for tables and JSON)."""
        return {
            "kind": self.kind,
            **{k: v for k, v in self.method.items()},
            "particles": self.counts["particles"], "cells": self.counts["cells"],
            "dofs": self.counts["dofs"], "steps": self.counts["steps"],
            "dt": self.dt, "wall_time_s": self.wall_time, "jit_time_s": self.jit_time,
            "phase_times": self.phase_table(),
        }

    def __repr__(self):
        return (f"Result({self.kind}, t={self.final_time:g}, steps={self.counts['steps']}, "
                f"particles={self.counts['particles']}, wall={self.wall_time:.3g}s)")


class History(dict):
    """The saved states: each entry is a list of per-save arrays, stacked
    into one array (saves, n, ...) on first access when all saves have the
    same particles (otherwise the list is returned)."""

    def __getitem__(self, key):
        value = super().__getitem__(key)
        if isinstance(value, list) and value and len({a.shape for a in value}) == 1:
            value = np.stack(value)
            super().__setitem__(key, value)
        return value


class Recorder:
    """Collects saves during a run and builds the Result.

    The reference positions and particle indices are stored once for as
    long as they do not change, and the initial and the final save share
    the arrays of the state they were given (nothing writes into them:
    the scene's own arrays, and those of the last step, which the result
    holds as its particles too)."""

    def __init__(self):
        self.times = []
        self.history = {k: [] for k in HISTORY_FIELDS + OUTPUT_FIELDS}
        self.energies = {k: [] for k in ENERGY_FIELDS}
        self.reactions = []
        self.last_step_saved = None

    def save(self, state, share=False):
        """Record the state; ``share`` keeps references instead of copies
        (for the initial and the final state, which no step writes into)."""
        p = state.particles
        self.times.append(float(state.t))
        v = state.reported_velocity()
        keep = (lambda a: a) if share else (lambda a: np.array(a, copy=True))
        self.history["X"].append(p.X)  # constant while the particle set is
        self.history["index"].append(state.index)
        self.history["x"].append(keep(p.x))
        self.history["u"].append(keep(p.u))
        self.history["v"].append(keep(v))
        self.history["stress"].append(keep(p.stress))
        self.history["m"].append(p.m)  # constant while the particle set is
        self.history["body"].append(p.body)
        self.history["V"].append(keep(p.V))
        for name, values in p.state.items():  # the material state, by field name
            self.history.setdefault(name, []).append(keep(values))
        kinetic, strain = state.energies()
        self.energies["kinetic"].append(kinetic)
        self.energies["strain"].append(strain)
        self.energies["external_work"].append(float(state.external_work))
        self.energies["total"].append(kinetic + strain)
        self.reactions.append({k: v.copy() for k, v in state.reactions.items()})
        self.last_step_saved = state.step

    def result(self, state, wall_time, jit_time, kind="mpm", extra=None):
        history = History({k: list(v) for k, v in self.history.items()})
        timer = state.timer
        counts = {
            "particles": int(state.particles.n), "cells": int(state.grid.ncells),
            "dofs": int(state.grid.ndofs), "steps": int(state.step),
            "removed": int(state.removed),
            "small_dofs_max": int(getattr(state, "small_dofs_max", 0)),
            "compiled_loop_steps": int(getattr(state, "loop_steps", 0)),
        }
        fields = dict(
            particles=state.particles, times=np.array(self.times), history=history,
            energies={k: np.array(v) for k, v in self.energies.items()},
            reactions=list(self.reactions), timings=timer.table(),
            phase_counts=dict(timer.counts), fused=dict(timer.fused), counts=counts,
            dt=float(state.dt), dt_crit=float(state.dt_crit), wall_time=float(wall_time),
            jit_time=float(jit_time), method=state.method.as_dict(), kind=kind,
            grid=state.grid, time=float(state.t),
        )
        if extra:
            fields.update(extra)
        return Result(**fields)

    # checkpoint support ------------------------------------------------------
    @staticmethod
    def _keys(name):
        """The checkpoint keys of a history entry: (sizes, values); a
        material state field's keys hold a dot, which no other key has."""
        if name in HISTORY_FIELDS + OUTPUT_FIELDS:
            return f"rec_n_{name}", f"rec_{name}"
        return f"rec_state_n.{name}", f"rec_state.{name}"

    def state_arrays(self):
        last = self.last_step_saved
        state_names = [k for k in self.history if k not in HISTORY_FIELDS + OUTPUT_FIELDS]
        out = {"rec_times": np.array(self.times),
               "rec_last_step": np.array(-1 if last is None else last, dtype=np.int64),
               "rec_state_names": np.array(json.dumps(state_names))}
        for k, v in self.history.items():
            sizes, values = self._keys(k)
            out[sizes] = np.array([a.shape[0] for a in v], dtype=np.int64)
            out[values] = np.concatenate(v) if v else np.zeros(0)
        for k, v in self.energies.items():
            out[f"rec_e_{k}"] = np.array(v)
        return out

    @classmethod
    def from_arrays(cls, data, reactions):
        rec = cls()
        rec.times = [float(t) for t in data["rec_times"]]
        # the step of the last save: a run resumed at its last step (from a
        # checkpoint written after that step's save) must not record it twice
        last = int(data["rec_last_step"]) if "rec_last_step" in data else -1
        rec.last_step_saved = None if last < 0 else last
        names = json.loads(str(data["rec_state_names"])) if "rec_state_names" in data else []
        present = tuple(k for k in OUTPUT_FIELDS if cls._keys(k)[0] in data)
        for k in HISTORY_FIELDS + present + tuple(names):
            sizes_key, values_key = cls._keys(k)
            sizes = data[sizes_key]
            flat = data[values_key]
            rec.history[k] = [a.copy() for a in np.split(flat, np.cumsum(sizes)[:-1])] \
                if sizes.size else []
        for k in ENERGY_FIELDS:
            rec.energies[k] = [float(x) for x in data[f"rec_e_{k}"]]
        rec.reactions = reactions
        return rec
