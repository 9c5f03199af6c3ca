"""Errors of the simulator link and the lockstep loop."""

from __future__ import annotations


class HilError(RuntimeError):
    """Base class of simulator-link failures."""


class LockstepTimeout(HilError):
    """An autopilot did not answer a HIL_SENSOR step with HIL_ACTUATOR_CONTROLS in time.

    `instances` are the vehicle instances still waiting; `time_us` the simulated time of the
    unanswered step."""

    def __init__(self, message: str, *, instances: tuple[int, ...] = (), time_us: int = 0) -> None:
        super().__init__(message)
        self.instances = instances
        self.time_us = time_us


class LinkClosed(HilError):
    """The autopilot closed its TCP connection (or it broke) while the simulation needed it."""

    def __init__(self, message: str, *, instance: int) -> None:
        super().__init__(message)
        self.instance = instance
