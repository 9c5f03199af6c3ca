"""From a discrete action code (the thesis's table) to one drone's NED velocity setpoint.

The base meaning of each code comes from `sitl_bridge.client.actions` (the one definition shared
with the MAVSDK client); here the scenario's action settings are applied on top:

* `swap_drones`: the thesis's per-drone swap of 0/1 and 2/3 for a drone facing the other way;
* `frame: goal`: the four horizontal actions turn with the horizontal start-goal direction
  (3 = forward toward the goal, 2 = back, 0 = right, 1 = left), so a head-on pair is symmetric;
* action 6 flies toward the goal at the action speed, slowed on the last step so that it stops
  at the goal rather than overshooting it.
"""

from __future__ import annotations

import math

import numpy as np

from sitl_bridge.client.actions import NUM_ACTIONS, Action, action_velocity_ned
from sitl_bridge.envs.task import ActionConfig
from sitl_bridge.frames import enu_to_ned

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
