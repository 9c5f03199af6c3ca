"""Simulator side of PX4's simulator MAVLink protocol: `HilLink` (one TCP server per vehicle),
`Lockstep` (the shared clock, speed factor, run_for/hold) and `SimRunner` (a background
thread that drives a Lockstep for callers that cannot step it themselves)."""

from sitl_bridge.hil.errors import HilError, LinkClosed, LockstepTimeout
from sitl_bridge.hil.link import HilLink, LinkStats
from sitl_bridge.hil.lockstep import Lockstep
from sitl_bridge.hil.runner import SimRunner

__all__ = [
    "HilError",
    "HilLink",
    "LinkClosed",
    "LinkStats",
    "Lockstep",
    "LockstepTimeout",
    "SimRunner",
]
