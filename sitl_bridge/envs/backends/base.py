"""The backend contract: the simulator as the envs see it.

A backend owns a simulation of one world with one autopilot per vehicle and flies velocity
setpoints for exact spans of simulated time; between calls the simulation is held (nothing
moves) while the agent decides. Every backend implements the same setpoint sequence per
simulated step, so `direct` and `stub` agree on the same seed and actions:

1. `reset(seed)`: in place (the episode clock restarts at 0), every vehicle re-spawned
   (randomised per the world, from `seed`) on the ground, autopilots rebooted (`direct`/`stub`:
   `StubAutopilot.reset`, a warm reboot with the short alignment; `px4`: restarted), sensor
   noise re-seeded; then the episode start, observed rather than timed: arm as soon as
   the autopilot accepts (retried every `ARM_POLL_S`), take off to the task's start altitude
   (PX4's AUTO.TAKEOFF with MIS_TAKEOFF_ALT), wait until in the air, in HOLD and within
   `TAKEOFF_TOLERANCE_M` of it, switch to offboard with a zero-velocity setpoint and let it
   settle for `SETTLE_S`; then held.
2. `fly(velocities_ned_m_s, duration_s)`: each vehicle's setpoint is set before the first step
   of the span and held for exactly `duration_s` simulated seconds; then held.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from sitl_bridge.physics import VehicleState
from sitl_bridge.sensors.lidar import LidarScan
from sitl_bridge.world import GoalPlacement

ARM_POLL_S = 0.1
"""Simulated seconds between arming attempts while the estimator converges."""
TAKEOFF_TOLERANCE_M = 0.1
"""Takeoff is done within this distance of the start altitude (tighter than MAVSDK's 0.3 m,
so episodes start from nearly the same hover)."""
SETTLE_S = 1.0
"""Simulated seconds of zero-velocity offboard hover before an episode's first action."""
STARTUP_TIMEOUT_S = 30.0
"""Simulated seconds the episode start may take before the backend gives up."""

ESTIMATORS = ("sensors", "ground_truth")
"""What the stub autopilot's state estimate comes from (`estimator=` of the envs):

* `sensors` (default, realistic): the stub's sensor-fusion estimator works from the simulated
  IMU, magnetometer, barometer and GPS (noise included), as PX4's EKF2 does.
* `ground_truth` (a labelled shortcut for speed, NOT what PX4 sees): the estimate is the
  simulator's noise-free state. `direct` then skips the sensor simulation and the fusion
  filter altogether; `stub` requests HIL_STATE_QUATERNION every step as PX4 does for its
  ground-truth mode (`SimSession(stub_ground_truth=True)`), so both still agree. Not available
  with `px4` (it always runs EKF2)."""


def check_estimator(estimator: str, autopilot: str) -> str:
    """`estimator` if `autopilot` supports it; ValueError otherwise."""
    if estimator not in ESTIMATORS:
        raise ValueError(f"estimator must be one of {', '.join(ESTIMATORS)}, got {estimator!r}")
    if estimator == "ground_truth" and autopilot == "px4":
        raise ValueError("estimator='ground_truth' needs the stub autopilot (direct or stub); PX4 runs EKF2")
    return estimator


class BackendError(RuntimeError):
    """A backend could not start, reset or fly (the message says which vehicle and why)."""


@dataclass(frozen=True)
class Snapshot:
    """Everything the env reads from a backend after `reset` or `fly` (ground truth)."""

    time_us: int
    """Simulated time since this episode's reset began (the episode start included)."""
    states: tuple[VehicleState, ...]
    scans: tuple[LidarScan, ...]
    collided: tuple[bool, ...]
    """Per vehicle: a collision (obstacle, other vehicle, hard ground contact) since the last call."""
    goals: tuple[GoalPlacement, ...]
    """Per vehicle: its goal region this episode (randomised per the world)."""


@runtime_checkable
class Backend(Protocol):
    """What `SitlEnv` / `SitlParallelEnv` need from a simulator + autopilots."""

    name: str
    """`direct`, `stub` or `px4`."""
    num_drones: int

    def reset(self, seed: int | None = None) -> Snapshot:
        """Re-spawn in place and hover every vehicle at its spawn point; return the state."""
        ...

    def fly(self, velocities_ned_m_s: Sequence[np.ndarray], duration_s: float) -> Snapshot:
        """Hold each vehicle's NED velocity setpoint for `duration_s` simulated seconds."""
        ...

    def close(self) -> None:
        """Release everything the backend opened (processes, ports, physics). Idempotent."""
        ...
