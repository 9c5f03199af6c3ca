"""Episode logic shared by the single- and multi-drone envs: actions in, per-drone results out.

One `EpisodeRunner` drives one backend through episodes of one scenario: it turns actions
(discrete codes or continuous vectors, `envs/actions.py`) into velocity setpoints, flies them for the action's duration (plus the optional zero-velocity
phase), then builds each drone's view, observation, reward terms and episode end.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sitl_bridge.client.actions import NUM_ACTIONS, Action
from sitl_bridge.envs.actions import action_velocity, normalised_action, velocity_command
from sitl_bridge.envs.backends import make_backend
from sitl_bridge.envs.backends.base import Backend, Snapshot
from sitl_bridge.envs.features import ObservationAssembler
from sitl_bridge.envs.options import EnvOptions
from sitl_bridge.envs.path_distance import PathField, PathGrid, Unreachable, path_field
from sitl_bridge.envs.path_guide import guided_action
from sitl_bridge.envs.priority import priorities
from sitl_bridge.envs.scenario import Scenario
from sitl_bridge.envs.task import ActionConfig, EndConfig
from sitl_bridge.envs.view import DroneView
from sitl_bridge.envs.watched_flight import fly_watched
from sitl_bridge.errors import ConfigError
from sitl_bridge.frames import ned_to_enu, quat_to_euler_t, wrap_pi, yaw_enu_to_ned
from sitl_bridge.sensors.lidar import LidarScan
from sitl_bridge.world import GoalPlacement

OUTCOMES = ("goal", "crash", "out", "timeout")
"""`info["outcome"]` values when a drone's episode ends (None while it runs)."""


@dataclass
class DroneResult:
    """One drone's outcome of one env step (or of reset)."""

    observation: np.ndarray
    reward: float
    terminated: bool
    truncated: bool
    info: dict[str, Any] = field(default_factory=dict)


def _ground_contact(view: DroneView, end: EndConfig) -> bool:
    """Touching the ground while flying: a crash unless the drone is landing inside its goal."""
    return (end.crash_on_ground and not view.reached_goal
            and float(view.position_enu_m[2]) < end.ground_contact_m)


def _inside(goal: GoalPlacement, position: list[float], margin_m: float) -> bool:
    # per axis in plain floats: the same IEEE operations as the array form, a tenth of its cost
    return all(abs(p - c) <= s / 2.0 + margin_m
               for p, c, s in zip(position, goal.center_m, goal.size_m, strict=True))


def _frozen(array: np.ndarray) -> np.ndarray:
    array.setflags(write=False)
    return array


_NO_OTHERS = (_frozen(np.zeros(0)), _frozen(np.zeros((0, 3))), _frozen(np.zeros((0, 3))),
              _frozen(np.zeros(0, dtype=bool)))
"""A one-drone view's other_priorities, others' positions and velocities, others_in_airspace."""


def _yaw_enu(state: Any) -> float:
    """A vehicle state's true heading (ENU yaw, rad)."""
    return quat_to_euler_t(state.quaternion_enu_flu.tolist())[2]


def _rays(scan: LidarScan) -> dict[str, np.ndarray]:
    """A `LidarScan`'s ray distances by group, as `DroneView.lidar` holds them."""
    return {"horizontal": scan.horizontal_m, "up": scan.up_m, "down": scan.down_m}


class EpisodeRunner:
    """Runs episodes of `scenario` on `backend` for all its drones at once."""

    def __init__(self, scenario: Scenario, backend: Backend) -> None:
        self.scenario = scenario
        self.backend = backend
        self._closed = False
        self.num_drones = scenario.num_drones
        self.step_count = 0
        self.done = [False] * self.num_drones
        self.on_frame: Callable[[], None] | None = None
        """Called every `watched_flight.FRAME_PERIOD_S` of simulated time through each action (video frames)."""
        self.outcomes: list[str | None] = [None] * self.num_drones
        self._ended_truncated = [False] * self.num_drones
        self._snapshot: Snapshot | None = None
        self._ranked: tuple[Snapshot, list[np.ndarray], np.ndarray] | None = None
        self._starts: list[np.ndarray] = []
        self._goals: list[np.ndarray] = []
        self._paths: list[PathField | None] = [None] * self.num_drones
        self._last: list[DroneResult] = []
        self._previous_actions: list[np.ndarray | None] = [None] * self.num_drones
        self._yaw_targets_enu: list[float] = [0.0] * self.num_drones
        """Per drone, the heading setpoint (ENU yaw) that `yaw: rate` actions move."""
        self._delays_s: tuple[float, ...] = ()
        """Per drone, how long it is held at its start this episode (`Snapshot.start_delays_s`)."""
        self._observe = ObservationAssembler(scenario.task.observation)
        self._others = [[j for j in range(self.num_drones) if j != i] for i in range(self.num_drones)]

    @classmethod
    def open(cls, scenario: Scenario, options: EnvOptions, backend: Backend | None = None) -> EpisodeRunner:
        """A runner on `backend`, or on the backend `options` names (built for `scenario`)."""
        if backend is None:
            backend = make_backend(scenario.world, options, start_altitude_m=scenario.task.start_altitude_m,
                                   takeoff=scenario.task.start_with_takeoff)
        return cls(scenario, backend)

    @property
    def snapshot(self) -> Snapshot | None:
        """The backend's state after the last reset or step (None before the first reset)."""
        return self._snapshot

    def close(self) -> None:
        """Close the backend (once; later calls do nothing)."""
        if not self._closed:
            self._closed = True
            self.backend.close()

    # -- episode ------------------------------------------------------------------------
    def reset(self, seed: int | None = None) -> list[DroneResult]:
        """Start a new episode (in place); every drone hovers at its spawn point."""
        snapshot = self.backend.reset(seed)
        self._snapshot = snapshot
        self.step_count = 0
        self.done = [False] * self.num_drones
        self.outcomes = [None] * self.num_drones
        self._ended_truncated = [False] * self.num_drones
        self._ranked = None  # priorities depend on this episode's starts and goals
        self._starts = [np.array(s.position_enu_m, dtype=float) for s in snapshot.states]
        self._goals = [np.array(g.center_m, dtype=float) for g in snapshot.goals]
        self._paths = self._path_fields(snapshot)
        self._previous_actions = [None] * self.num_drones
        self._yaw_targets_enu = [_yaw_enu(s) for s in snapshot.states]
        self._delays_s = snapshot.start_delays_s
        self._commands_enu_m_s = [np.zeros(3) for _ in range(self.num_drones)]
        results = []
        for i in range(self.num_drones):
            view = self._view(i, snapshot, snapshot, crashed=False)
            results.append(DroneResult(self._observe(view), 0.0, False, False,
                                       self._info(view, None, {}, None)))
        self._last = results
        return results

    def step(self, actions: Mapping[int, Any]) -> list[DroneResult]:
        """Fly one action per active drone (missing or finished drones hover) and score it:
        a code (discrete) or a vector (`type: velocity`; a bad one raises ValueError before
        anything flies)."""
        if self._snapshot is None:
            raise RuntimeError("call reset() before step()")
        before = self._snapshot
        config = self.scenario.task.action
        flying = [not done for done in self.done]
        yaws: list[float] | None = None
        normalised: dict[int, np.ndarray] = {}
        if self._delays_s:  # a held drone (late entry) hovers whatever it was told
            actions = {i: a for i, a in actions.items() if not (0 <= i < self.num_drones and self._held(i))}
        if config.continuous:
            checked = {i: normalised_action(a, config) for i, a in actions.items()}  # every one, flying or not
            normalised = {i: a for i, a in checked.items() if 0 <= i < self.num_drones and flying[i]}
            velocities, yaws = self._velocity_setpoints(normalised, before, flying)
        else:
            velocities = []
            for i in range(self.num_drones):
                code = int(actions.get(i, Action.HOVER)) if flying[i] else self._after_end(i)
                velocities.append(self._code_velocity(code, i, before, config))
        # what each drone was told to fly (ENU): reported in its info, so a flight's smoothness can be measured
        self._commands_enu_m_s = [ned_to_enu(np.asarray(v, dtype=float)) for v in velocities]
        snapshot, collided = fly_watched(self.backend, velocities, config.duration_s, self.on_frame, yaws)
        if config.zero_velocity_s > 0.0:
            snapshot, stopped = fly_watched(self.backend, [np.zeros(3)] * self.num_drones, config.zero_velocity_s,
                                            self.on_frame)
            collided = [a or b for a, b in zip(collided, stopped, strict=True)]
        self._snapshot = snapshot
        self.step_count += 1
        crashed, by_drones_only = self._crashes(snapshot, collided)
        if self.scenario.task.end.min_separation_m > 0.0:
            self._lose_separation(snapshot, crashed, by_drones_only, flying)
        if self.scenario.task.end.conflict_blame == "give_way":
            crashed = self._charge_give_way(snapshot, crashed, by_drones_only, flying)

        results = []
        for i in range(self.num_drones):
            if self.done[i]:
                view = self._view(i, snapshot, before, crashed=False)
                truncated = self._ended_truncated[i]
                results.append(DroneResult(self._observe(view), 0.0, not truncated, truncated,
                                           self._info(view, self.outcomes[i], {}, None)))
                continue
            action = normalised.get(i) if config.continuous else actions.get(i)
            results.append(self._score(i, snapshot, before, action, crashed=crashed[i],
                                       by_drones_only=by_drones_only[i], flying=flying))
            if config.continuous:
                self._previous_actions[i] = normalised.get(i, np.zeros(config.size))
        self._last = results
        return results

    def _code_velocity(self, code: int, i: int, before: Snapshot, config: ActionConfig) -> np.ndarray:
        """NED velocity of discrete `code` for drone `i` from its state in `before`."""
        return action_velocity(code, config=config, drone=i,
                               position_enu_m=np.asarray(before.states[i].position_enu_m, dtype=float),
                               start_enu_m=self._starts[i], goal_enu_m=self._goals[i])

    def _velocity_setpoints(self, normalised: dict[int, np.ndarray], before: Snapshot,
                            flying: list[bool]) -> tuple[list[np.ndarray], list[float] | None]:
        """`type: velocity`: every drone's NED velocity for this decision (a flying drone without
        an action hovers; an ended one hovers or lands, as for discrete actions, at 1 m/s), and
        under `yaw: rate` the heading setpoints (NED yaw) moved by each commanded rate."""
        config = self.scenario.task.action
        velocities = []
        for i in range(self.num_drones):
            if not flying[i]:
                velocities.append(self._code_velocity(self._after_end(i), i, before, ActionConfig()))
                continue
            velocity, rate = velocity_command(
                normalised.get(i, np.zeros(config.size)), config=config,
                yaw_enu_rad=_yaw_enu(before.states[i]), start_enu_m=self._starts[i], goal_enu_m=self._goals[i])
            velocities.append(velocity)
            self._yaw_targets_enu[i] = wrap_pi(self._yaw_targets_enu[i] + rate * config.duration_s)
        if config.yaw != "rate":
            return velocities, None
        return velocities, [yaw_enu_to_ned(y) for y in self._yaw_targets_enu]

    @property
    def last_results(self) -> list[DroneResult]:
        """Every drone's result of the last reset or step."""
        if not self._last:
            raise RuntimeError("call reset() first")
        return self._last

    def path_guided_action(self, i: int) -> int:
        """The action that a goal-seeking guide takes for drone `i` now (`envs/path_guide.py`):
        the one whose straight move ends nearest its goal along the obstacle-free path (the
        reward's path field, or one on the default grid when no reward term reads one)."""
        if self._snapshot is None:
            raise RuntimeError("call reset() before path_guided_action()")
        field_ = self._paths[i]
        if field_ is None:
            try:
                field_ = path_field(self.scenario.world.workspace, self._snapshot.obstacles,
                                    self._snapshot.goals[i], PathGrid())
            except Unreachable as exc:
                raise ConfigError(f"{self.scenario.world.source}: the goal-seeking guide: {exc}") from None
        config = self.scenario.task.action
        here = np.asarray(self._snapshot.states[i].position_enu_m, dtype=float)
        moves = [ned_to_enu(action_velocity(code, config=config, drone=i, position_enu_m=here,
                                            start_enu_m=self._starts[i], goal_enu_m=self._goals[i]))
                 * config.duration_s for code in range(NUM_ACTIONS)]
        return guided_action(field_, here, moves)

    # -- pieces -------------------------------------------------------------------------
    def _held(self, i: int) -> bool:
        """Whether drone `i` has not entered yet: its start delay outlasts the decisions flown so
        far (it hovers at its start through the decision now asked for)."""
        if not self._delays_s:
            return False
        config = self.scenario.task.action
        elapsed_s = self.step_count * (config.duration_s + config.zero_velocity_s)
        return elapsed_s < self._delays_s[i] - 1e-9

    def _left_airspace(self, i: int) -> bool:
        """Whether drone `i` reached its goal and lands there (`end.after_goal: land`)."""
        return self.outcomes[i] == "goal" and self.scenario.task.end.after_goal == "land"

    def _after_end(self, i: int) -> int:
        """The action a drone whose episode has ended flies: down at its goal under
        `end.after_goal: land`, else hover."""
        if self._left_airspace(i):
            return int(Action.DOWN)
        return int(Action.HOVER)

    def _crashes(self, snapshot: Snapshot, collided: list[bool]) -> tuple[list[bool], list[bool]]:
        """Per drone: whether it crashed (a collision, or the lidar's crash flag under
        `crash_on_lidar`), and whether only other drones caused it (no obstacle or ground)."""
        lidar = self.scenario.task.end.crash_on_lidar
        hit_obstacle = snapshot.hit_obstacle if snapshot.hit_obstacle is not None else collided
        crashed, by_drones_only = [], []
        for c, obstacle, scan in zip(collided, hit_obstacle, snapshot.scans, strict=True):
            crashed.append(c or (lidar and bool(scan.crash)))
            by_drones_only.append(crashed[-1] and not obstacle and not (lidar and scan.crash and not scan.crash_by_vehicles))
        return crashed, by_drones_only

    def _lose_separation(self, snapshot: Snapshot, crashed: list[bool], by_drones_only: list[bool],
                         flying: list[bool]) -> None:
        """`end.min_separation_m`: a drone still flying its episode closer than `min_separation_m`
        to another drone in the airspace (any drone but one landing at its goal: one whose episode
        ended hovers where it is) crashes (marked in place), caused by drones only unless it had
        also hit something."""
        positions, _ = self._ranks(snapshot)
        limit = self.scenario.task.end.min_separation_m
        for i in range(self.num_drones):
            if flying[i] and not crashed[i] and any(
                    not self._left_airspace(j) and float(np.linalg.norm(positions[j] - positions[i])) < limit
                    for j in range(self.num_drones) if j != i):
                crashed[i] = by_drones_only[i] = True

    def _conflict_partners(self, i: int, positions: list[np.ndarray], flying: list[bool]) -> list[int]:
        """The other flying drones within `end.conflict_m` (or `min_separation_m`, if larger) of
        drone `i`."""
        end = self.scenario.task.end
        reach = max(end.conflict_m, end.min_separation_m)
        return [j for j in range(self.num_drones)
                if j != i and flying[j] and float(np.linalg.norm(positions[j] - positions[i])) < reach]

    def _ranks(self, snapshot: Snapshot) -> tuple[list[np.ndarray], np.ndarray]:
        """Every drone's position and priority (`task.priority`) in `snapshot`, worked out once
        per snapshot (every drone's view and the conflict rules read them)."""
        if self._ranked is None or self._ranked[0] is not snapshot:
            positions = [np.asarray(s.position_enu_m, dtype=float) for s in snapshot.states]
            ranks = priorities(self.scenario.task.priority, self._starts, positions, self._goals)
            self._ranked = (snapshot, positions, ranks)
        return self._ranked[1], self._ranked[2]

    def _charge_give_way(self, snapshot: Snapshot, crashed: list[bool], by_drones_only: list[bool],
                         flying: list[bool]) -> list[bool]:
        """Under `conflict_blame: give_way`, a drone that only other drones crashed crashes the
        ones without right of way over it too: one drone's lidar can see the other closer than its
        crash distance while the other's does not (above or below it)."""
        positions, ranks = self._ranks(snapshot)
        charged = list(crashed)
        for i in range(self.num_drones):
            if flying[i] and by_drones_only[i]:
                for j in self._conflict_partners(i, positions, flying):
                    charged[j] = charged[j] or bool(ranks[j] < ranks[i])
        return charged

    def _excused(self, i: int, snapshot: Snapshot, by_drones_only: bool, flying: list[bool]) -> bool:
        """Under `end.conflict_blame: give_way`: a crash caused only by other drones, all of which
        drone `i` has right of way over (the give-way drones are charged instead)."""
        if self.scenario.task.end.conflict_blame != "give_way" or not by_drones_only:
            return False
        positions, ranks = self._ranks(snapshot)
        partners = self._conflict_partners(i, positions, flying)
        return bool(partners) and all(ranks[i] > ranks[j] for j in partners)

    def _score(self, i: int, snapshot: Snapshot, before: Snapshot, action: Any, *, crashed: bool,
               by_drones_only: bool, flying: list[bool]) -> DroneResult:
        end = self.scenario.task.end
        if isinstance(action, np.ndarray):
            view = self._view(i, snapshot, before, crashed=crashed, action=action,
                              previous_action=self._previous_actions[i])
        else:
            view = self._view(i, snapshot, before, crashed=crashed)
        if not crashed and _ground_contact(view, end):
            view = dataclasses.replace(view, crashed=True)
        outcome: str | None = None
        if view.crashed:
            outcome = "crash"
        elif view.reached_goal:
            outcome = "goal"
        elif view.out_of_workspace:
            outcome = "out"
        excused = self._excused(i, snapshot, by_drones_only, flying)
        scored = dataclasses.replace(view, crashed=False) if excused else view
        terms = {t.name: t(scored) for t in self.scenario.task.rewards}
        terminated = outcome is not None and not excused
        truncated = excused or (not terminated and self.step_count >= self.scenario.task.max_steps)
        if truncated and not excused:
            outcome = "timeout"
        if terminated or truncated:
            self.done[i] = True
            self.outcomes[i] = outcome
            self._ended_truncated[i] = truncated
        return DroneResult(self._observe(view), float(sum(terms.values())), terminated, truncated,
                           self._info(view, outcome, terms, action))

    def _path_fields(self, snapshot: Snapshot) -> list[PathField | None]:
        """Per drone: the path distance to its goal this episode when a reward term reads it
        (`along: path`), from the episode's obstacle placements (cached by layout)."""
        grid = next((t.path for t in self.scenario.task.rewards if t.path is not None), None)
        if grid is None:
            return [None] * self.num_drones
        world = self.scenario.world
        fields: list[PathField | None] = []
        for i, goal in enumerate(snapshot.goals):
            start = np.asarray(snapshot.states[i].position_enu_m, dtype=float)
            try:
                field_ = path_field(world.workspace, snapshot.obstacles, goal, grid)
                reached = field_.reaches(start)
            except Unreachable:
                reached = False
            except ValueError as exc:  # a grid too fine for the workspace
                raise ConfigError(f"{world.source}: task.reward.closer_to_goal: {exc}") from None
            if not reached:
                raise ConfigError(
                    f"{world.source}: task.reward.closer_to_goal: along: path: in scenario {world.name!r}, "
                    f"{world.vehicles[i].name}'s goal {goal.name!r} cannot be reached from "
                    f"({', '.join(f'{c:.1f}' for c in start)}) around the static obstacles grown by "
                    f"clearance_m {grid.clearance_m:g} on a {grid.cell_m:g} m grid (a smaller "
                    "clearance_m or cell_m may open the way)")
            fields.append(field_)
        return fields

    def _view(self, i: int, snapshot: Snapshot, before: Snapshot, *, crashed: bool, action: np.ndarray | None = None,
              previous_action: np.ndarray | None = None) -> DroneView:
        """Drone `i` in `snapshot`, one action after `before` (at reset both are the same), with
        the continuous `action` flown (and the one before it) when there is one."""
        end = self.scenario.task.end
        state = snapshot.states[i]
        scan = snapshot.scans[i]
        position = np.asarray(state.position_enu_m, dtype=float)
        xyz = position.tolist()  # plain floats for the scalar tests below
        others = self._others[i]
        _, ranks = self._ranks(snapshot)
        if others:
            other_priorities = ranks[others]
            others_position = np.array([snapshot.states[j].position_enu_m for j in others], dtype=float)
            others_velocity = np.array([snapshot.states[j].velocity_enu_m_s for j in others], dtype=float)
            in_airspace = np.array([not self._left_airspace(j) for j in others], dtype=bool)
        else:  # one drone: the same empty arrays every step
            other_priorities, others_position, others_velocity, in_airspace = _NO_OTHERS
        return DroneView(
            index=i,
            position_enu_m=position,
            previous_position_enu_m=np.asarray(before.states[i].position_enu_m, dtype=float),
            euler_enu_rad=np.array(quat_to_euler_t(state.quaternion_enu_flu.tolist())),
            velocity_enu_m_s=np.asarray(state.velocity_enu_m_s, dtype=float),
            start_enu_m=self._starts[i],
            goal_enu_m=self._goals[i],
            lidar=_rays(scan),
            previous_lidar=None if before is snapshot else _rays(before.scans[i]),
            priority=float(ranks[i]),
            other_priorities=other_priorities,
            others_position_enu_m=others_position,
            others_velocity_enu_m_s=others_velocity,
            others_in_airspace=in_airspace,
            crashed=crashed,
            near_obstacle=bool(scan.near),
            reached_goal=_inside(snapshot.goals[i], xyz, end.goal_margin_m),
            out_of_workspace=end.out_of_workspace and not self.scenario.world.workspace.contains(xyz),
            step=self.step_count,
            action=action,
            previous_action=previous_action,
            path_distance=None if self._paths[i] is None else self._paths[i].distance,
        )

    def _info(self, view: DroneView, outcome: str | None, terms: dict[str, float],
              action: Any) -> dict[str, Any]:
        assert self._snapshot is not None
        return {
            "step": self.step_count,
            "sim_time_s": self._snapshot.time_us / 1e6,
            # a continuous action as flown: clipped to [-1, 1], a list (JSON-ready)
            "action": action.tolist() if isinstance(action, np.ndarray) else action,
            "outcome": outcome,
            "reward_terms": terms,
            "position_enu_m": view.position_enu_m.copy(),
            "command_enu_m_s": self._commands_enu_m_s[view.index].copy(),
            "start_enu_m": view.start_enu_m.copy(),
            "goal_enu_m": view.goal_enu_m.copy(),
            "distance_to_goal_m": view.distance_to_goal_m,
            "crashed": view.crashed,
            "near_obstacle": view.near_obstacle,
            # a late entry (`world.encounter` start delay): False while the drone is held at its start
            "entered": not self._held(view.index),
            # the encounter type drawn this episode (`world.encounter`; None in other worlds) and
            # whether a drone of it enters late (per-type evaluation tables group by both)
            "encounter": self._snapshot.encounter,
            "late_entry": self._snapshot.encounter is not None and self._snapshot.encounter != "overtaking"
                          and any(d > 0.0 for d in self._delays_s),
        }
