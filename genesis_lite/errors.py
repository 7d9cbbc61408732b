"""Exceptions that speak to the user."""


class GenesisException(RuntimeError):
    """A misuse of the API or a failure of the simulation, with what to do about it."""


class SimulationNaNError(GenesisException, FloatingPointError):
    """The state of an entity became NaN or infinite."""


class GenesisWarning(UserWarning):
    """Something that runs but is probably not what the user meant; silence a kind with
    `warnings.filterwarnings("ignore", category=...)`."""


class GradientGrowthWarning(GenesisWarning):
    """A backward pass amplified the gradient of the state by more than
    `genesis_lite.grad.growth.GROWTH_WARN_FACTOR` (1e6) over some window of steps:
    the rollout is chaotic or unstable over its horizon and its gradient is not informative."""


class ZeroGainWarning(GenesisWarning):
    """A PD target was set on dofs whose gain is 0, so the target has no effect."""


class ImportOrderWarning(GenesisWarning):
    """torch was imported before genesis_lite, whose setting of OMP_WAIT_POLICY then came too late: torch's
    OpenMP threads spin after each of its ops on the cores the simulator's kernels need (scenes of many
    envs run slower). Import genesis_lite first, or start Python with OMP_WAIT_POLICY=PASSIVE."""


# Raised by the rigid solver, which does not import this package: a UserWarning, re-exported here so
# that users find every warning of the library in one module.
from solvers.rigid.contact import ContactPenetrationWarning  # noqa: E402,F401
