"""The thesis's eight discrete actions as NED velocity setpoints.

Each action is a velocity held for one step (1 m/s for 1 s of simulated time in the thesis).
PX4's velocity frame is fixed to the world (NED), so "east" is always +E whatever the heading.
"""

from __future__ import annotations

from collections.abc import Sequence
from enum import IntEnum

import numpy as np

ACTION_SPEED_M_S = 1.0
"""Speed of every moving action (the thesis's 1 m/s)."""

ACTION_DURATION_S = 1.0
"""Simulated seconds each action is held (the thesis's 1 s)."""


class Action(IntEnum):
    """Action codes of the thesis (its Table 2)."""

    EAST = 0
    WEST = 1
    SOUTH = 2
    NORTH = 3
    DOWN = 4
    UP = 5
    TOWARD_GOAL = 6
    HOVER = 7


NUM_ACTIONS = len(Action)

# Unit directions in NED (north, east, down); TOWARD_GOAL is computed from the goal.
_DIRECTIONS_NED: dict[Action, tuple[float, float, float]] = {
    Action.EAST: (0.0, 1.0, 0.0),
    Action.WEST: (0.0, -1.0, 0.0),
    Action.SOUTH: (-1.0, 0.0, 0.0),
    Action.NORTH: (1.0, 0.0, 0.0),
    Action.DOWN: (0.0, 0.0, 1.0),
    Action.UP: (0.0, 0.0, -1.0),
    Action.HOVER: (0.0, 0.0, 0.0),
}

# Closer than this to the goal, "toward goal" has no direction left and means hover.
_GOAL_REACHED_M = 1e-3


def action_velocity_ned(
    action: int,
    *,
    position_ned_m: Sequence[float] | np.ndarray | None = None,
    goal_ned_m: Sequence[float] | np.ndarray | None = None,
    speed_m_s: float = ACTION_SPEED_M_S,
) -> np.ndarray:
    """NED velocity (m/s) that flies `action`.

    Action 6 (toward goal) needs `position_ned_m` and `goal_ned_m`: it flies the straight line
    from the vehicle to the goal (the thesis's trajectory planner) at `speed_m_s`.
    """
    code = Action(int(action))  # ValueError for codes outside 0..7
    if code is not Action.TOWARD_GOAL:
        return np.asarray(_DIRECTIONS_NED[code], dtype=float) * speed_m_s
    if position_ned_m is None or goal_ned_m is None:
        raise ValueError("action 6 (toward goal) needs position_ned_m and goal_ned_m")
    offset = np.asarray(goal_ned_m, dtype=float) - np.asarray(position_ned_m, dtype=float)
    distance = float(np.linalg.norm(offset))
    if distance < _GOAL_REACHED_M:
        return np.zeros(3)
    return offset / distance * speed_m_s
