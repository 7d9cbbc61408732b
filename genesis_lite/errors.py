"""Exceptions that speak to the user."""


class GenesisException(RuntimeError):
    """A misuse of the API or a failure of the simulation, with what to do about it."""


class SimulationNaNError(GenesisException, FloatingPointError):
    """The state of an entity became NaN or infinite."""
