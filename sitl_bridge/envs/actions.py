"""From an action to one drone's NED velocity setpoint: a discrete code (the thesis's table) or
a continuous velocity vector (`task.action.type: velocity`).

The base meaning of each code comes from `sitl_bridge.client.actions` (the one definition shared
with the MAVSDK client); here the scenario's action settings are applied on top:

* `swap_drones`: the thesis's per-drone swap of 0/1 and 2/3 for a drone facing the other way;
* `frame: goal`: the four horizontal actions turn with the horizontal start-goal direction
  (3 = forward toward the goal, 2 = back, 0 = right, 1 = left), so a head-on pair is symmetric;
* action 6 flies toward the goal at the action speed, slowed on the last step so that it stops
  at the goal rather than overshooting it.

Continuous velocity actions (`type: velocity`) are `Box(-1, 1, (3,))` float32 vectors, or
`(4,)` with `yaw: rate`: `(x, y, z[, yaw rate])`. NaN or inf raises a one-line `ValueError`
(never a NaN setpoint); each component is first clipped to [-1, 1] (what SB3 does with a
Gaussian policy's samples), then the vector `(x, y, z)` is scaled by `max_speed_m_s` with its
NORM capped at 1: a vector inside the unit ball flies `max_speed_m_s * |a|` in its direction, one
beyond it (a corner of the box) flies `max_speed_m_s` in its direction, so the speed never
exceeds `max_speed_m_s` whatever the direction (clipping per component would let a diagonal fly
1.7 times faster). The axes per `frame` (z is always up):

* `world`: x east, y north (ENU);
* `goal`: x right, y forward of the horizontal start-goal direction (as the discrete goal frame;
  a head-on pair is symmetric);
* `body`: x right, y forward of the drone's heading now (its true yaw at the decision).

With `yaw: rate` the 4th component times `max_yaw_rate_deg_s` is a yaw rate, positive
counter-clockwise seen from above (turning left). It is flown the way MAVSDK's `VelocityNedYaw`
can fly it on every backend: each decision moves the held heading setpoint by rate x duration.
With `yaw: hold` the heading setpoint stays as it was (the spawn heading).
"""

from __future__ import annotations

import math

import numpy as np
from gymnasium import spaces

from sitl_bridge.client.actions import NUM_ACTIONS, Action, action_velocity_ned
from sitl_bridge.envs.task import ActionConfig
from sitl_bridge.frames import enu_to_ned, enu_to_ned_xyz, wrap_pi


def action_space(config: ActionConfig) -> spaces.Space:
    """The gymnasium action space of one drone: `Discrete(8)`, or for `type: velocity`
    `Box(-1, 1, (3,) or (4,), float32)` (module docstring)."""
    if not config.continuous:
        return spaces.Discrete(NUM_ACTIONS)
    return spaces.Box(low=-1.0, high=1.0, shape=(config.size,), dtype=np.float32)


def normalised_action(action: object, config: ActionConfig) -> np.ndarray:
    """A continuous action as float64 clipped to [-1, 1]; a one-line ValueError for a wrong
    shape or a NaN/inf component."""
    try:
        vector = np.asarray(action, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f"action must be {config.size} numbers in [-1, 1], got {action!r}") from None
    if vector.shape != (config.size,):
        raise ValueError(f"action must have {config.size} components (x, y, z"
                         f"{', yaw rate' if config.size == 4 else ''}), got shape {np.shape(action)}")
    values = vector.tolist()  # three or four numbers: plain floats beat array calls
    if not all(map(math.isfinite, values)):
        raise ValueError(f"action must be finite (no NaN or inf), got {values}")
    return np.array([-1.0 if v < -1.0 else 1.0 if v > 1.0 else v for v in values])


def _turn(vector_enu: np.ndarray, rotation_rad: float) -> np.ndarray:
    """`vector_enu` turned counter-clockwise (seen from above) by `rotation_rad` about z."""
    c, s = math.cos(rotation_rad), math.sin(rotation_rad)
    x, y = float(vector_enu[0]), float(vector_enu[1])
    return np.array([c * x - s * y, s * x + c * y, float(vector_enu[2])])


def velocity_command(action: np.ndarray, *, config: ActionConfig, yaw_enu_rad: float,
                     start_enu_m: np.ndarray, goal_enu_m: np.ndarray) -> tuple[np.ndarray, float]:
    """NED velocity (m/s) and yaw rate (rad/s, ENU: counter-clockwise; 0 under `yaw: hold`) of
    a normalised continuous action (`normalised_action`) under the scenario's settings;
    `yaw_enu_rad` is the drone's heading now (read by `frame: body`)."""
    direction = np.asarray(action[:3], dtype=float)
    norm = float(np.linalg.norm(direction))
    velocity_enu = direction * config.max_speed_m_s / max(1.0, norm)
    if config.frame == "goal":
        velocity_enu = _turn(velocity_enu, goal_frame_yaw_rad(start_enu_m, goal_enu_m))
    elif config.frame == "body":
        velocity_enu = _turn(velocity_enu, wrap_pi(yaw_enu_rad - math.pi / 2.0))  # y axis = the nose
    rate = float(action[3]) * math.radians(config.max_yaw_rate_deg_s) if config.size == 4 else 0.0
    return np.array(enu_to_ned_xyz(*velocity_enu.tolist())), rate

_SWAP = {Action.EAST: Action.WEST, Action.WEST: Action.EAST,
         Action.SOUTH: Action.NORTH, Action.NORTH: Action.SOUTH}


def goal_frame_yaw_rad(start_enu_m: np.ndarray, goal_enu_m: np.ndarray) -> float:
    """Rotation (rad, counter-clockwise seen from above) taking north onto the start-goal direction."""
    dx, dy = float(goal_enu_m[0] - start_enu_m[0]), float(goal_enu_m[1] - start_enu_m[1])
    if math.hypot(dx, dy) < 1e-6:
        return 0.0  # goal straight above/below: keep the world meaning
    return math.atan2(dy, dx) - math.pi / 2.0


def action_velocity(action: int, *, config: ActionConfig, drone: int, position_enu_m: np.ndarray,
                    start_enu_m: np.ndarray, goal_enu_m: np.ndarray) -> np.ndarray:
    """NED velocity (m/s) that drone `drone` flies for `action` under the scenario's settings."""
    if not 0 <= int(action) < NUM_ACTIONS:
        raise ValueError(f"action must be in 0..{NUM_ACTIONS - 1}, got {action!r}")
    code = Action(int(action))
    if drone in config.swap_drones:
        code = _SWAP.get(code, code)
    if code is Action.TOWARD_GOAL:
        distance = float(np.linalg.norm(goal_enu_m - position_enu_m))
        speed = min(config.speed_m_s, distance / config.duration_s)
        return action_velocity_ned(code, position_ned_m=enu_to_ned(position_enu_m),
                                   goal_ned_m=enu_to_ned(goal_enu_m), speed_m_s=speed)
    velocity_ned = action_velocity_ned(code, speed_m_s=config.speed_m_s)
    if config.frame == "goal":
        yaw = goal_frame_yaw_rad(start_enu_m, goal_enu_m)
        # NED horizontal (north, east): a counter-clockwise turn seen from above.
        c, s = math.cos(yaw), math.sin(yaw)
        north, east = velocity_ned[0], velocity_ned[1]
        velocity_ned = np.array([c * north + s * east, -s * north + c * east, velocity_ned[2]])
    return velocity_ned
