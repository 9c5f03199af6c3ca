"""ORCA as a policy: each drone flies the velocity ORCA (`rl.analysis.orca`) picks from its own
observation, the classical baseline beside learned policies and rule sets.

Per decision, one drone, no central planner and no messages:

1. preferred velocity: of the velocities its action codes fly, the one whose step most shortens
   the obstacle-free path distance to its own goal (`envs.path_distance`, the drone's map of the
   scenario's static obstacles; in an empty world the straight line);
2. ORCA in the horizontal plane against every other drone of its transponder data (position and
   velocity) within `vertical_clearance_m` of its altitude; the vertical component stays the
   preferred one (2D ORCA with altitude hold: drones are not assumed to climb out of each other's
   way, and one far above or below is no conflict). Every other drone is assumed to run ORCA too
   (reciprocal, half of the avoidance each);
3. the scenario's discrete actions: of the action codes whose velocity (`envs.actions`, the
   velocity the env flies for that code and drone) lies inside every ORCA half-plane, the one
   nearest ORCA's velocity; when none does, the nearest of all. Codes whose step would end in a
   static obstacle on the drone's map (at its end or half a step beyond) are left out (ORCA here
   avoids drones, not walls). With continuous actions step 3 is the identity: fly
   `OrcaPolicy.velocity(obs)`.

The observation must hold `position`, `velocity`, `own_id` (which drone: its goal, its action
mapping) and `transponder` (an agent-relative observation instead: `rl.analysis.orca_travel`,
which `orca_policy` picks for it, e.g. in the encounter worlds); the goal comes from `goal_position` when observed, else from the world
file (fixed goals only). Static obstacles must be fixed (not drawn per episode): they are the map.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from sitl_bridge.envs.actions import action_velocity
from sitl_bridge.envs.features import observation_layout
from sitl_bridge.envs.path_distance import PathField, path_field
from sitl_bridge.envs.scenario import Scenario, load_scenario
from sitl_bridge.errors import ConfigError
from sitl_bridge.frames import ned_to_enu
from sitl_bridge.rl.analysis.orca import HalfPlane, Neighbour, orca_velocity
from sitl_bridge.rl.analysis.orca_actions import OVERSHOOT, OrcaSettings, choose_action
from sitl_bridge.rl.analysis.orca_travel import TravelOrcaPolicy, reads_travel_frame
from sitl_bridge.rl.common.action_names import ACTION_NAMES_BY_FRAME
from sitl_bridge.world.layout import GoalPlacement, realize

NEEDED = ("position", "velocity", "own_id", "transponder")
"""Observation features the ORCA policy reads."""
class OrcaPolicy:
    """The ORCA policy of one scenario: call it with one drone's observation, get an action code."""

    def __init__(self, scenario: Scenario, settings: OrcaSettings | None = None) -> None:
        self.scenario = scenario
        self.settings = settings or OrcaSettings()
        world = scenario.world
        if world.encounter is not None:  # goals and the bottleneck wall are drawn per episode
            raise ConfigError(f"{world.source}: world.encounter: the ORCA policy on world-frame observations flies "
                              "fixed-geometry worlds only (its map and goals are read once, an encounter draws them "
                              "per episode); observe travel_goal_offset, travel_velocity and travel_others for the "
                              "travel-frame ORCA (rl/analysis/orca_travel.py)")
        layout = observation_layout(scenario.task.observation)
        missing = [name for name in NEEDED if name not in layout]
        if missing:
            raise ConfigError(f"{scenario.task.source}: task.observation: the ORCA policy needs "
                              f"{', '.join(NEEDED)}; missing {', '.join(missing)}")
        self.layout = layout
        if any(o.randomize is not None for o in world.obstacles):
            raise ConfigError(f"{world.source}: obstacles drawn per episode: the ORCA policy's map needs fixed ones")
        if "goal_position" not in layout and any(g.randomize_min_m is not None for g in world.goals):
            raise ConfigError(f"{scenario.task.source}: task.observation: goals drawn per episode: the ORCA "
                              "policy needs goal_position observed")
        self._obstacles = realize(world, np.random.default_rng(0)).obstacles
        self.action = scenario.task.action
        self._fields: dict[tuple[float, ...], PathField] = {}

    # -- what the drone reads ----------------------------------------------------------------
    def _block(self, obs: np.ndarray, name: str) -> np.ndarray:
        return obs[self.layout[name]]

    def _drone(self, obs: np.ndarray) -> int:
        return int(round(float(self._block(obs, "own_id")[0])))

    def _goal(self, obs: np.ndarray, drone: int) -> GoalPlacement:
        world = self.scenario.world
        index = world.vehicles[drone].goal
        if index is None:
            raise ConfigError(f"{world.source}: vehicle {world.vehicles[drone].name} has no goal to fly to")
        spec = world.goals[index]
        center = self._block(obs, "goal_position") if "goal_position" in self.layout else spec.center_m
        return GoalPlacement(spec.name, tuple(float(c) for c in center), spec.size_m)  # type: ignore[arg-type]

    def _others(self, obs: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        rows = self._block(obs, "transponder").reshape(-1, 6)
        return [(row[:3], row[3:]) for row in rows if np.any(row != 0.0)]  # all zeros: no drone there

    # -- the three steps ---------------------------------------------------------------------
    def _field(self, goal: GoalPlacement) -> PathField:
        key = (*goal.center_m, *goal.size_m)
        field = self._fields.get(key)
        if field is None:
            field = self._fields[key] = path_field(self.scenario.world.workspace, self._obstacles, goal)
        return field

    def preferred_velocity(self, position: np.ndarray, goal: GoalPlacement, moves: np.ndarray) -> np.ndarray:
        """Of the velocities the drone can fly (`moves`, one per action code), the one whose step
        ends with the least path distance to `goal` on its map (zero inside the goal box). A step
        down the distance's gradient instead would wobble: near a narrow opening the gradient turns
        vertical, and whole-metre steps overshoot the band of heights it leads through."""
        field = self._field(goal)
        if field.distance(position) <= 0.0:
            return np.zeros(3)
        after = [field.distance(position + move * self.action.duration_s) for move in moves]
        return moves[int(np.argmin(after))]

    def velocity(self, obs: np.ndarray) -> tuple[np.ndarray, list[HalfPlane]]:
        """ORCA's velocity (ENU m/s) for the drone that observed `obs`, and its half-planes."""
        obs = np.asarray(obs, dtype=float).reshape(-1)
        drone = self._drone(obs)
        position = self._block(obs, "position")
        own_velocity = self._block(obs, "velocity")
        preferred = self.preferred_velocity(position, self._goal(obs, drone), self.action_velocities(obs))
        s = self.settings
        neighbours = [Neighbour(p[:2], v[:2], s.radius_m) for p, v in self._others(obs)
                      if abs(float(p[2] - position[2])) <= s.vertical_clearance_m]
        horizontal, planes = orca_velocity(position[:2], own_velocity[:2], preferred[:2], s.radius_m,
                                           self.action.speed_m_s, neighbours, time_horizon=s.time_horizon_s,
                                           time_step=self.action.duration_s)
        return np.array([horizontal[0], horizontal[1], preferred[2]]), planes

    def action_velocities(self, obs: np.ndarray) -> np.ndarray:
        """(codes, 3): the ENU velocity the env flies for each action code, for this drone here."""
        obs = np.asarray(obs, dtype=float).reshape(-1)
        drone = self._drone(obs)
        position = self._block(obs, "position")
        goal = np.asarray(self._goal(obs, drone).center_m, dtype=float)
        start = np.asarray(self.scenario.world.vehicles[drone].spawn.position_m, dtype=float)
        return np.array([ned_to_enu(action_velocity(code, config=self.action, drone=drone, position_enu_m=position,
                                                    start_enu_m=start, goal_enu_m=goal))
                         for code in range(len(ACTION_NAMES_BY_FRAME["world"]))])

    def clear_moves(self, obs: np.ndarray, moves: np.ndarray) -> np.ndarray:
        """Per move, whether its step ends clear of the static obstacles on the drone's map: the
        nearest node of the path grid free (outside every obstacle grown by the path clearance)
        at the step's end and half a step beyond it (the drone does not stop dead)."""
        obs = np.asarray(obs, dtype=float).reshape(-1)
        position = self._block(obs, "position")
        occ = self._field(self._goal(obs, self._drone(obs))).occupancy
        clear = np.ones(len(moves), dtype=bool)
        for reach in (1.0, OVERSHOOT):
            index = np.rint((position + reach * moves * self.action.duration_s - occ.origin_m)
                            / occ.grid.cell_m).astype(int)
            inside = np.all((index >= 0) & (index < np.array(occ.shape)), axis=1)
            index = np.clip(index, 0, np.array(occ.shape) - 1)
            clear &= inside & occ.free[index[:, 0], index[:, 1], index[:, 2]]
        return clear

    def __call__(self, obs: np.ndarray) -> int:
        wanted, planes = self.velocity(obs)
        moves = self.action_velocities(obs)
        return choose_action(wanted, planes, moves, self.action.speed_m_s, self.clear_moves(obs, moves))


def orca_policy(world: str | Path, settings: OrcaSettings | None = None) -> Callable[[np.ndarray], int]:
    """The ORCA policy of the scenario file `world`: the travel-frame one (`orca_travel`) when
    its observation is agent-relative (`travel_goal_offset`, `travel_velocity`,
    `travel_others`), else the world-frame one (position, velocity, own_id, transponder);
    `settings` None: each one's own defaults."""
    scenario = load_scenario(world)
    if reads_travel_frame(scenario):
        return TravelOrcaPolicy(scenario, settings)
    return OrcaPolicy(scenario, settings)
