"""Wall time split by phase.

Phase names (the same in every table): locate, basis, p2g, mass_matrix
(assembly of the consistent mass), solve, g2p, constitutive, reconstruct,
effects. A fused compiled kernel reports its time
under the first phase it covers and records which phases it fused.
"""
import time

__all__ = ["PHASES", "PhaseTimer"]

PHASES = ("locate", "basis", "p2g", "mass_matrix", "solve", "g2p", "constitutive", "reconstruct",
          "effects")


class _Phase:
    """``with timer(phase):`` adds the block's wall time to the phase (one
    reusable object per phase: a step enters several phases, so entering one
    must cost little next to a small step's arithmetic)."""

    __slots__ = ("timer", "phase", "starts")

    def __init__(self, timer, phase):
        self.timer, self.phase, self.starts = timer, phase, []

    def __enter__(self):
        self.starts.append(time.perf_counter())
        return self

    def __exit__(self, *exc):
        seconds = time.perf_counter() - self.starts.pop()
        timer, phase = self.timer, self.phase
        timer.seconds[phase] = timer.seconds.get(phase, 0.0) + seconds
        timer.counts[phase] = timer.counts.get(phase, 0) + 1
        return False


class PhaseTimer:
    """Accumulates seconds and entry counts per phase."""

    def __init__(self):
        self.seconds = {}
        self.counts = {}
        self.fused = {}
        self._phases = {}

    def __call__(self, phase):
        """Context manager timing a block as ``phase``."""
        entry = self._phases.get(phase)
        if entry is None:
            if phase not in PHASES:
                raise ValueError(f"phase must be one of {PHASES}, got {phase!r}")
            entry = self._phases[phase] = _Phase(self, phase)
        return entry

    def add(self, phase, seconds):
        if phase not in PHASES:
            raise ValueError(f"phase must be one of {PHASES}, got {phase!r}")
        self.seconds[phase] = self.seconds.get(phase, 0.0) + seconds
        self.counts[phase] = self.counts.get(phase, 0) + 1

    def note_fused(self, phase, covers):
        self.fused[phase] = tuple(covers)

    def ran(self, phase):
        """True if the phase was entered at least once."""
        return self.counts.get(phase, 0) > 0

    def table(self):
        """{phase: seconds} for every phase (0.0 where it never ran)."""
        return {p: self.seconds.get(p, 0.0) for p in PHASES}

    def state(self):
        return {"seconds": dict(self.seconds), "counts": dict(self.counts),
                "fused": {k: list(v) for k, v in self.fused.items()}}

    @classmethod
    def from_state(cls, state):
        t = cls()
        t.seconds = dict(state["seconds"])
        t.counts = dict(state["counts"])
        t.fused = {k: tuple(v) for k, v in state.get("fused", {}).items()}
        return t
