"""What observation features and reward terms read: one drone's situation after a step.

Everything is in the scenario's common world frame, ENU (x east, y north, z up, metres), the
frame of the world file, so observations of several drones are comparable.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np


@dataclass(frozen=True)
class ScenarioLimits:
    """Fixed facts about a scenario that observation bounds depend on."""

    num_drones: int
    workspace_low_enu_m: np.ndarray
    workspace_high_enu_m: np.ndarray
    lidar_rays: dict[str, int] = field(
        default_factory=lambda: {"horizontal": 35, "up": 6, "down": 6}
    )
    lidar_range_m: float = 5.0
    lidar_labels: dict[str, tuple[str, ...]] = field(default_factory=dict)
    """Each ray's direction in words, per group (`sensors.lidar.ray_labels`)."""
    max_speed_m_s: float = 5.0
    """Velocity observations are clipped to +- this."""

    @property
    def diagonal_m(self) -> float:
        """Length of the workspace's diagonal (bounds any distance inside it)."""
        return float(np.linalg.norm(self.workspace_high_enu_m - self.workspace_low_enu_m))


@dataclass(frozen=True)
class DroneView:
    """One drone after a step (or at reset), as features and reward terms see it."""

    index: int
    position_enu_m: np.ndarray
    previous_position_enu_m: np.ndarray
    euler_enu_rad: np.ndarray
    """Roll, pitch, yaw of the body (FLU) in ENU; yaw 0 = facing east, counter-clockwise."""
    velocity_enu_m_s: np.ndarray
    start_enu_m: np.ndarray
    goal_enu_m: np.ndarray
    lidar: dict[str, np.ndarray]
    """Ray distances per group (`horizontal`, `up`, `down`), max range when nothing is hit."""
    priority: float
    other_priorities: np.ndarray
    others_position_enu_m: np.ndarray
    """(k, 3) positions of the other drones (transponder data)."""
    others_velocity_enu_m_s: np.ndarray
    others_in_airspace: np.ndarray | None = None
    """(k,) per other drone: still in the airspace (False once it landed at its goal under
    `end.after_goal: land`); None: all are."""
    previous_lidar: dict[str, np.ndarray] | None = None
    """The same rays one action earlier (None at reset: no motion seen yet)."""
    crashed: bool = False
    near_obstacle: bool = False
    reached_goal: bool = False
    out_of_workspace: bool = False
    step: int = 0
    action: np.ndarray | None = None
    """The normalised continuous action of this step (clipped to [-1, 1]); None for discrete
    actions and at reset."""
    previous_action: np.ndarray | None = None
    """The one of the step before (None at an episode's first decision)."""
    path_distance: Callable[[np.ndarray], float] | None = None
    """Length of the shortest obstacle-free path (m) from a point to this drone's goal region
    (`envs/path_distance.py`), given when a reward term reads it (`closer_to_goal: {along: path}`)."""

    @cached_property  # read by the reward and the info: worked out once
    def distance_to_goal_m(self) -> float:
        return float(np.linalg.norm(self.goal_enu_m - self.position_enu_m))

    @property
    def previous_distance_to_goal_m(self) -> float:
        return float(np.linalg.norm(self.goal_enu_m - self.previous_position_enu_m))

    @property
    def path_distance_to_goal_m(self) -> float:
        return self._along_path(self.position_enu_m)

    @property
    def previous_path_distance_to_goal_m(self) -> float:
        return self._along_path(self.previous_position_enu_m)

    def _along_path(self, position: np.ndarray) -> float:
        if self.path_distance is None:
            raise RuntimeError("this view has no path distance (the runner gives one when a reward "
                               "term has `along: path`)")
        return self.path_distance(position)
