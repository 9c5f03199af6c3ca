"""Simulator side of PX4's simulator MAVLink protocol: `HilLink` (one TCP server per vehicle),
`Lockstep` (the shared clock, speed factor, run_for/hold) and `SimRunner` (a background
thread that drives a Lockstep for callers that cannot step it themselves). `peer` holds the
trivial `ConstantAutopilot` used by `sitl-bridge bench --link`
(`python -m sitl_bridge.hil.peer -i N` runs it as an external autopilot)."""

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
