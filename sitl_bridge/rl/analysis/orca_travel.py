"""ORCA on agent-relative observations: each drone runs ORCA in its own travel frame from what
its own observation holds, so it flies worlds whose geometry is drawn per episode (encounters).

The drone reads only its own observation (no map, no shared state, no messages):

- `travel_goal_offset`: its goal relative to itself (right, forward, up of its travel direction);
- `travel_velocity`: its own velocity in that frame;
- `travel_others`: per other drone (its transponder data) the relative position and velocity;
  an empty slot (`absent: far` or `zeros` padding, `envs.features`) is no drone;
- `lidar` (optional, the horizontal ring): the static obstacles it sees now.

Per decision: the preferred velocity is the toward-goal move (code 6: straight at the goal, no
map to plan around walls; sideways toward the nearest open ray's side while the lidar shows it blocked);
ORCA in the horizontal plane against every other drone within
`vertical_clearance_m` of its altitude, each assumed to run ORCA too (`OrcaSettings`); then the
nearest action code (`orca_actions.choose_action`), never one whose step the lidar shows blocked
(the rays within `RAY_CONE_DEG` of the move read less than `OVERSHOOT` steps plus the drone's
radius), nor a climb or descent the goal's height does not ask for (altitude hold). With the lidar the drone slides along a wall toward its goal's side until the way ahead
is open (the gap); without it a wall is invisible. Frame `goal` discrete actions only (the
travel frame is the goal frame's; `envs.actions`): the drone's body keeps its start heading,
toward its goal, so the lidar's forward is the travel frame's forward.
"""

from __future__ import annotations

import math

import numpy as np

from sitl_bridge.envs.actions import action_velocity
from sitl_bridge.envs.features import observation_layout
from sitl_bridge.envs.scenario import Scenario
from sitl_bridge.errors import ConfigError
from sitl_bridge.frames import ned_to_enu
from sitl_bridge.rl.analysis.orca import HalfPlane, Neighbour, orca_velocity
from sitl_bridge.rl.analysis.orca_actions import OVERSHOOT, OrcaSettings, choose_action
from sitl_bridge.rl.common.action_names import ACTION_NAMES_BY_FRAME
from sitl_bridge.sensors.lidar import ray_directions_flu

NEEDED = ("travel_goal_offset", "travel_velocity", "travel_others")
"""Observation features the travel-frame ORCA policy reads (`lidar` too when observed)."""
TRAVEL_SETTINGS = OrcaSettings(time_horizon_s=2.5)
"""The travel-frame policy's ORCA: a 2.5 s horizon. With whole-metre 1 m/s moves a 5 s horizon
forbids full speed ahead on a crossing course long before the drones are near, both hover and the
episode times out (verification episodes of encounters.yaml, 10 per type: crossing 40 % vs 70 %
success, overtaking 20 % vs 100 %, late-entry head-on 60 % vs 100 %; no collision either way)."""
RIGHT, LEFT, DOWN, UP, TOWARD_GOAL = 0, 1, 4, 5, 6
"""Goal-frame action codes (`envs.actions`)."""
RAY_CONE_DEG = 12.0
"""A horizontal move is checked against the lidar rays within this angle of its direction (narrow:
at the blocking distance the cone must fit through a 1.2 m gap)."""
OPEN_SHARE = 0.95
"""A ray reading at least this share of the lidar's range sees open space."""
OPEN_CONE_DEG = 60.0
"""Open rays count for the sliding side only this far from forward: a ray along the wall reads
open whether or not there is a gap."""


def reads_travel_frame(scenario: Scenario) -> bool:
    """Whether the scenario's observation holds what the travel-frame ORCA reads."""
    layout = observation_layout(scenario.task.observation)
    return all(name in layout for name in NEEDED)


class TravelOrcaPolicy:
    """ORCA from one drone's agent-relative observation: call it with the observation, get a code."""

    def __init__(self, scenario: Scenario, settings: OrcaSettings | None = None) -> None:
        task = scenario.task
        self.layout = observation_layout(task.observation)
        missing = [name for name in NEEDED if name not in self.layout]
        if missing:
            raise ConfigError(f"{task.source}: task.observation: the travel-frame ORCA policy needs "
                              f"{', '.join(NEEDED)}; missing {', '.join(missing)}")
        self.action = task.action
        if self.action.continuous or self.action.frame != "goal" or self.action.swap_drones:
            raise ConfigError(f"{task.source}: task.action: the travel-frame ORCA policy flies discrete "
                              "frame: goal actions without swap_drones (its velocities are the goal frame's)")
        self.settings = settings or TRAVEL_SETTINGS
        feature = next(f for f in task.observation if f.name == "travel_others")
        self._far = float(feature.high[1])  # the diagonal: `absent: far` pads forward = -it
        self._moves = self._code_velocities()
        self._rays = self._horizontal_rays(scenario)

    # -- what the drone reads ----------------------------------------------------------------
    def _block(self, obs: np.ndarray, name: str) -> np.ndarray:
        return obs[self.layout[name]]

    def others(self, obs: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """(relative position, absolute velocity in the travel frame) of each drone in the slots."""
        own = self._block(obs, "travel_velocity")
        rows = self._block(obs, "travel_others").reshape(-1, 6)
        empty = [np.all(row == 0.0) or (row[1] <= -self._far + 1e-3 and np.all(row[[0, 2, 3, 4, 5]] == 0.0))
                 for row in rows]
        return [(row[:3], row[3:] + own) for row, gone in zip(rows, empty, strict=True) if not gone]

    def _code_velocities(self) -> np.ndarray:
        """(codes, 3): each code's velocity in the travel frame (x right, y forward, z up), code 6
        left at zero (it depends on the goal: `action_velocities`)."""
        origin, ahead = np.zeros(3), np.array([0.0, 1.0, 0.0])  # the frame's forward as a goal
        moves = [ned_to_enu(action_velocity(code, config=self.action, drone=0, position_enu_m=origin,
                                            start_enu_m=origin, goal_enu_m=ahead))
                 for code in range(len(ACTION_NAMES_BY_FRAME["goal"]))]
        moves[TOWARD_GOAL] = np.zeros(3)
        return np.array(moves)

    def action_velocities(self, obs: np.ndarray) -> np.ndarray:
        """(codes, 3): the travel-frame velocity the env flies for each code, from here."""
        goal = self._block(obs, "travel_goal_offset").astype(float)
        moves = self._moves.copy()
        moves[TOWARD_GOAL] = ned_to_enu(action_velocity(TOWARD_GOAL, config=self.action, drone=0,
                                                        position_enu_m=np.zeros(3), start_enu_m=np.zeros(3),
                                                        goal_enu_m=goal))
        return moves

    def _horizontal_rays(self, scenario: Scenario) -> tuple[np.ndarray, np.ndarray] | None:
        """Unit directions (right, forward) of the observed horizontal rays, and their columns
        in the observation (None: no horizontal ring observed)."""
        observed = next((f for f in scenario.task.observation if f.name == "lidar"), None)
        if observed is None or "horizontal" not in observed.groups:
            return None
        world = scenario.world
        lidar = world.encounter.lidar if world.encounter is not None else world.vehicles[0].lidar
        flu = ray_directions_flu(lidar)[0]
        start = self.layout["lidar"].start
        columns = np.array([start + k for k, group in enumerate(observed.groups) if group == "horizontal"])
        self._range_m = float(lidar.range_m)
        return np.stack([-flu[:, 1], flu[:, 0]], axis=1), columns

    def clear_moves(self, obs: np.ndarray, moves: np.ndarray) -> np.ndarray:
        """Per move: False when the lidar shows its step blocked (every move clear without a lidar)."""
        clear = np.ones(len(moves), dtype=bool)
        if self._rays is None:
            return clear
        directions, columns = self._rays
        ring = np.asarray(obs, dtype=float).reshape(-1)[columns]
        cone = math.cos(math.radians(RAY_CONE_DEG))
        for k, move in enumerate(moves):
            speed = float(np.linalg.norm(move[:2]))
            if speed < 1e-9:
                continue
            near = directions @ (move[:2] / speed) >= cone
            needed = OVERSHOOT * speed * self.action.duration_s + self.settings.radius_m
            clear[k] = not np.any(ring[near] < needed)
        return clear

    # -- the decision ----------------------------------------------------------------------
    def preferred_velocity(self, obs: np.ndarray) -> np.ndarray:
        """The toward-goal move; when the lidar shows it blocked, the sideways move (right or
        left) toward the side of the open ray nearest ahead (a wall's gap reads the full range),
        so a drone slides along a wall to its gap."""
        moves = self.action_velocities(obs)
        toward = moves[TOWARD_GOAL]
        if self._rays is None or self.clear_moves(obs, toward[None, :])[0]:
            return toward
        directions, columns = self._rays
        ring = obs[columns]
        bearing = np.degrees(np.arctan2(directions[:, 0], directions[:, 1]))  # + right of forward
        # the open ray nearest ahead (a wall's gap, seen past its edge) says which way to slide;
        # none open: toward the goal's side
        open_ahead = (ring >= OPEN_SHARE * self._range_m) & (np.abs(bearing) <= OPEN_CONE_DEG)
        if np.any(open_ahead):
            side = float(bearing[open_ahead][np.argmin(np.abs(bearing[open_ahead]))])
        else:
            side = float(self._block(obs, "travel_goal_offset")[0])
        return moves[RIGHT] if side >= 0.0 else moves[LEFT]

    def velocity(self, obs: np.ndarray) -> tuple[np.ndarray, list[HalfPlane]]:
        """ORCA's velocity (travel frame, m/s) for the drone that observed `obs`, and its half-planes."""
        obs = np.asarray(obs, dtype=float).reshape(-1)
        own = self._block(obs, "travel_velocity")
        preferred = self.preferred_velocity(obs)
        s = self.settings
        neighbours = [Neighbour(p[:2], v[:2], s.radius_m) for p, v in self.others(obs)
                      if abs(float(p[2])) <= s.vertical_clearance_m]
        horizontal, planes = orca_velocity(np.zeros(2), own[:2], preferred[:2], s.radius_m, self.action.speed_m_s,
                                           neighbours, time_horizon=s.time_horizon_s,
                                           time_step=self.action.duration_s)
        return np.array([horizontal[0], horizontal[1], preferred[2]]), planes

    def __call__(self, obs: np.ndarray) -> int:
        obs = np.asarray(obs, dtype=float).reshape(-1)
        wanted, planes = self.velocity(obs)
        moves = self.action_velocities(obs)
        clear = self.clear_moves(obs, moves)
        # altitude hold: a climb or descent only toward the goal's height, never as a way round
        # a drone (ORCA here is horizontal) or a wall (a bottleneck's wall is full height)
        climbing = abs(float(wanted[2])) >= 0.5 * self.action.speed_m_s
        clear[[DOWN, UP]] &= climbing
        return choose_action(wanted, planes, moves, self.action.speed_m_s, clear)
