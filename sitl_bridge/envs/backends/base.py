"""The backend contract: the simulator as the envs see it.

A backend owns a simulation of one world with one autopilot per vehicle and flies velocity
setpoints for exact spans of simulated time; between calls the simulation is held (nothing
moves) while the agent decides. Every backend implements the same setpoint sequence per
simulated step, so `direct` and `stub` agree on the same seed and actions:

1. `reset(seed)`: in place (the episode clock restarts at 0), every vehicle re-spawned
   (randomised per the world, from `seed`) on the ground, autopilots rebooted (`direct`/`stub`:
   `StubAutopilot.reset`, a warm reboot with the short alignment; `px4`: restarted), sensor
   noise re-seeded (`px4` after its first episode: in the air instead, PX4 flying on, see
   `backends.session`, then only the settle below). Then, `direct` and `stub` by default
   (`takeoff=False`): every vehicle placed hovering at the start altitude, its stub in the
   state a take-off ends in (`autopilot.stub.in_air_start`), no take-off flown, then offboard
   and the settle below. With `takeoff=True` (the scenario's `task.start: {takeoff: true}`)
   and for `px4`'s first episode, the episode start, observed rather than timed: arm as soon as
   the autopilot accepts (retried every `EPISODE_START.arm_poll_s`), take off to the task's
   start altitude (PX4's AUTO.TAKEOFF with MIS_TAKEOFF_ALT), wait until in the air, in HOLD
   and within `takeoff_tolerance_m` of it, switch to offboard with a zero-velocity setpoint and
   let it settle for `settle_s`; then held.

Backends are built as `Backend(world, options, start_altitude_m=..., takeoff=...)` with the
env's whole `EnvOptions`; the registry (`sitl_bridge.autopilot.registry`) says which class serves which
`autopilot=` kind.
2. `fly(velocities_ned_m_s, duration_s, yaws_ned_rad=None)`: each vehicle's setpoint (and
   heading, when given) is set before the first step of the span and held for exactly
   `duration_s` simulated seconds; then held.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol, TypeVar, runtime_checkable

import numpy as np

from sitl_bridge.physics import VehicleState
from sitl_bridge.physics.simulation import Simulation
from sitl_bridge.physics.state import Collision
from sitl_bridge.sensors.lidar import LidarScan
from sitl_bridge.world import GoalPlacement, ObstaclePlacement


@dataclass(frozen=True)
class EpisodeStart:
    """How every backend starts an episode (see the module docstring), in simulated time."""

    arm_poll_s: float = 0.1
    """Between arming attempts while the estimator converges."""
    takeoff_tolerance_m: float = 0.1
    """Takeoff is done within this distance of the start altitude (tighter than MAVSDK's
    0.3 m, so episodes start from nearly the same hover)."""
    settle_s: float = 1.0
    """Zero-velocity offboard hover before an episode's first action."""
    timeout_s: float = 30.0
    """The episode start may take this long before the backend gives up."""
    in_air_stop_speed_m_s: float = 0.1
    """A reset in the air (kinds that fly on, `px4`) teleports only vehicles this slow (as
    their autopilots estimate: `SessionBackend._stop_in_air` says why) ..."""
    in_air_stop_rate_rad_s: float = 0.25
    """... and turning slower than this (a vehicle that has just braked still pitches back to
    level; the fleet's own check refuses the reset while it turns, and a refusal costs a
    restart) ..."""
    in_air_stop_check_s: float = 0.2
    """... checked this often under a zero velocity setpoint after the episode's end ..."""
    in_air_stop_timeout_s: float = 3.0
    """... for at most this long (then the autopilots restart instead)."""


EPISODE_START = EpisodeStart()


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
    hit_obstacle: tuple[bool, ...] | None = None
    """Per vehicle: a collision with something other than a vehicle since the last call (None:
    the backend does not tell, so every collision counts as one)."""
    start_delays_s: tuple[float, ...] = ()
    """Per vehicle: how long after the episode start it is held hovering, its actions ignored (a
    late entry of `world.encounter`; empty: every vehicle flies from the start)."""
    encounter: str | None = None
    """The `world.encounter` type drawn this episode (None: not an encounter world)."""
    obstacles: tuple[ObstaclePlacement, ...] = ()
    """The obstacles as placed this episode (randomised per the world; a mover's placement is
    where its route is anchored, not where it is now)."""


class CollisionFlags:
    """Per vehicle: whether it collided with anything, and with anything but a vehicle, since
    `clear()` (what `Snapshot.collided` and `Snapshot.hit_obstacle` report)."""

    def __init__(self, num_vehicles: int) -> None:
        self.any = [False] * num_vehicles
        self.obstacle = [False] * num_vehicles

    def clear(self) -> None:
        self.any = [False] * len(self.any)
        self.obstacle = [False] * len(self.obstacle)

    def add(self, collision: Collision) -> None:
        self.any[collision.vehicle] = True
        if collision.kind != "vehicle":
            self.obstacle[collision.vehicle] = True


T = TypeVar("T")


@runtime_checkable
class Backend(Protocol):
    """What `SitlEnv` / `SitlParallelEnv` need from a simulator + autopilots."""

    name: str
    """The autopilot kind it runs (`direct`, `stub`, `px4`, ...)."""
    num_drones: int

    def reset(self, seed: int | None = None) -> Snapshot:
        """Re-spawn in place and hover every vehicle at its spawn point; return the state."""
        ...

    def fly(self, velocities_ned_m_s: Sequence[np.ndarray], duration_s: float,
            yaws_ned_rad: Sequence[float] | None = None) -> Snapshot:
        """Hold each vehicle's NED velocity setpoint for `duration_s` simulated seconds; with
        `yaws_ned_rad`, each vehicle's heading setpoint (NED yaw, rad) too (MAVSDK's
        `VelocityNedYaw`), else each keeps the heading it holds."""
        ...

    def close(self) -> None:
        """Release everything the backend opened (processes, ports, physics). Idempotent."""
        ...

    def with_simulation(self, use: Callable[[Simulation], T]) -> T:
        """`use(simulation)` while it is held and safe to read from this thread (rendering)."""
        ...
