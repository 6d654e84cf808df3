"""Exceptions of the simulator."""

__all__ = ["SimulationError", "InvalidState"]


class InvalidState(ArithmeticError):
    """Raised inside a step when the new state is not admissible (NaN/Inf,
    J <= 0, a particle outside the grid); ``simulate`` turns it into a
    :class:`SimulationError` that carries the last good state."""

    def __init__(self, message, particle=None):
        super().__init__(message)
        self.particle = particle


class SimulationError(RuntimeError):
    """A run that could not continue.

    Attributes: ``step`` and ``time`` of the failed step, ``particle`` (the
    first offending particle index, or None) and ``result``, a Result whose
    particles are the last good (finite, admissible) state.
    """

    def __init__(self, message, result=None, step=None, time=None, particle=None):
        super().__init__(message)
        self.result = result
        self.step = step
        self.time = time
        self.particle = particle
