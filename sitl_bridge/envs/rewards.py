"""Reward terms: each its own small function of `DroneView`, scaled from the scenario file and
logged under its own name (`info["reward_terms"]["closer_to_goal"]`), MuJoCo-Playground style.

The scenario's `reward:` mapping gives each term a scale (`per_step: -5`) or a mapping with the
scale and options (`closer_to_goal: {scale: 10, mode: binary, along: path}`). The step reward is
the sum of `scale * term(view)` over the listed terms; unlisted terms are off.

| term | unscaled value |
|---|---|
| `closer_to_goal` | `progress` (default): metres gained toward the goal this step (negative when moving away; potential-based shaping); `binary`: 1 when the distance shrank by more than `min_progress_m` (default 0.1), else 0. `along: straight` (default): the straight-line distance to the goal's centre; `along: path`: the length of the shortest path to the goal box around the static obstacles grown by `clearance_m` (default 0.4), on a grid of `cell_m` (default 0.5; envs/path_distance.py), so shaping leads around obstacles instead of into them |
| `goal_reached` | 1 on the step the goal is reached |
| `per_step` | 1 every step |
| `near_obstacle` | 1 when the lidar's near flag is set (and the drone did not crash) |
| `crash` | 1 on a crash (collision, or the lidar crash flag when enabled) |
| `out_of_workspace` | 1 when the drone left the workspace |
| `smoothness` | (continuous actions only) the length of the change of the normalised action vector since the previous decision (0 at an episode's first decision): give it a negative scale for smoother commands. Its sum over an episode is the action path's total variation, the same for the same flight at any decision rate, so it is not scaled by the decision period |
| `separation` | `max(0, 1 - d / distance_m)` for the nearest other drone still in the airspace (not landing at its goal under `end.after_goal: land`) at distance d (0 beyond `distance_m`, default 3 m, 1 when touching): give it a negative scale to keep drones apart; with `give_way: true` times `1 - own priority`, so only the drone without right of way pays (it is the one responsible for keeping clear, as the give-way aircraft is in the rules of the air) |

Decision rate: the terms that pay every step (`per_step`, `near_obstacle`, `separation`) are
rates per second of simulated time: one step pays `scale * term * step_s`, where `step_s` is the
decision period (`task.action.duration_s` + `zero_velocity_s`). At the thesis's 1 s steps that
is `scale * term`, unchanged; at 0.1 s decisions the same flight earns the same return, so a
scenario's rate can change without re-tuning its weights. `closer_to_goal` (metres gained) and
the one-off events (`goal_reached`, `crash`, `out_of_workspace`) need no scaling.

Thesis ratios (chapter 5.3): closer +10..+20, goal +500..+1000, per step -5..-10, near -10..-50,
crash -100..-500. Keep penalties on the scale of the other terms (a -1e12 crash made NaN weights).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from sitl_bridge.envs.path_distance import PathGrid
from sitl_bridge.envs.view import DroneView
from sitl_bridge.errors import ConfigError, Node

REWARD_LIMIT = 1e5
"""Largest accepted |scale|: bigger penalties make value estimates explode (thesis: -1e12)."""


@dataclass(frozen=True)
class RewardTerm:
    """One scaled reward term."""

    name: str
    scale: float
    term: Callable[[DroneView], float]
    path: PathGrid | None = None
    """The path distance the term reads (`DroneView.path_distance`), None when it reads none."""
    period_s: float = 1.0
    """Seconds one step stands for: the decision period for the per-second terms (`PER_SECOND`),
    1 for the others."""

    @property
    def step_scale(self) -> float:
        """What a term value of 1 pays in one step (`scale * period_s`)."""
        return self.scale * self.period_s

    def __call__(self, view: DroneView) -> float:
        return self.step_scale * float(self.term(view))


def progress_toward_goal(view: DroneView) -> float:
    """Metres gained toward the goal during the step."""
    return view.previous_distance_to_goal_m - view.distance_to_goal_m


def progress_along_path(view: DroneView) -> float:
    """Metres gained along the shortest obstacle-free path to the goal during the step."""
    return view.previous_path_distance_to_goal_m - view.path_distance_to_goal_m


def closer_binary(min_progress_m: float,
                  progress: Callable[[DroneView], float] = progress_toward_goal) -> Callable[[DroneView], float]:
    """1 when the step brought the drone more than `min_progress_m` closer to its goal."""
    return lambda view: 1.0 if progress(view) > min_progress_m else 0.0


def goal_reached(view: DroneView) -> float:
    return 1.0 if view.reached_goal else 0.0


def per_step(view: DroneView) -> float:
    return 1.0


def near_obstacle(view: DroneView) -> float:
    return 1.0 if view.near_obstacle and not view.crashed else 0.0


def crash(view: DroneView) -> float:
    return 1.0 if view.crashed else 0.0


def out_of_workspace(view: DroneView) -> float:
    return 1.0 if view.out_of_workspace else 0.0


def smoothness(view: DroneView) -> float:
    """Length of the change of the normalised action since the previous decision (0 at the first)."""
    if view.action is None or view.previous_action is None:
        return 0.0
    return float(np.linalg.norm(view.action - view.previous_action))


def separation(distance_m: float, give_way: bool = False) -> Callable[[DroneView], float]:
    """Closeness of the nearest other drone: 1 - d / distance_m inside distance_m, else 0; with
    `give_way`, times 1 - own priority (the drone with right of way pays nothing)."""
    def term(view: DroneView) -> float:
        others = view.others_position_enu_m.reshape(-1, 3)
        if view.others_in_airspace is not None:
            others = others[view.others_in_airspace]  # a drone landing at its goal is no traffic
        if others.shape[0] == 0:
            return 0.0
        nearest = float(np.min(np.linalg.norm(others - view.position_enu_m, axis=1)))
        closeness = max(0.0, 1.0 - nearest / distance_m)
        return closeness * (1.0 - view.priority) if give_way else closeness
    return term


_SIMPLE_TERMS: dict[str, Callable[[DroneView], float]] = {
    "goal_reached": goal_reached,
    "per_step": per_step,
    "near_obstacle": near_obstacle,
    "crash": crash,
    "out_of_workspace": out_of_workspace,
    "smoothness": smoothness,
}
TERM_NAMES = ("closer_to_goal", "separation", *_SIMPLE_TERMS)
PER_SECOND = frozenset({"per_step", "near_obstacle", "separation"})
"""Terms paid every step, scaled by the decision period (module docstring)."""


def _scale(node: Node) -> float:
    return node.number(minimum=-REWARD_LIMIT, maximum=REWARD_LIMIT)


def _parse_term(name: str, node: Node) -> RewardTerm:
    if name == "closer_to_goal":
        if not isinstance(node.value, dict):
            return RewardTerm(name, _scale(node), progress_toward_goal)
        node.reject_unknown({"scale", "mode", "min_progress_m", "along", "cell_m", "clearance_m"})
        mode = node.get("mode", "progress").string(("progress", "binary"))
        scale = _scale(node.get("scale"))
        path = None
        if node.get("along", "straight").string(("straight", "path")) == "path":
            path = PathGrid(cell_m=node.get("cell_m", PathGrid.cell_m).number(minimum=0.05, maximum=10.0),
                            clearance_m=node.get("clearance_m", PathGrid.clearance_m).number(
                                non_negative=True, maximum=10.0))
        else:
            for key in ("cell_m", "clearance_m"):
                if node.has(key):
                    raise ConfigError(f"{node.source}: {node.get(key).path}: only with `along: path` "
                                      "(with `along: straight` it would be ignored)")
        progress = progress_along_path if path is not None else progress_toward_goal
        if mode == "progress":
            return RewardTerm(name, scale, progress, path)
        min_progress = node.get("min_progress_m", 0.1).number(non_negative=True, maximum=1000.0)
        return RewardTerm(name, scale, closer_binary(min_progress, progress), path)
    if name == "separation":
        if not isinstance(node.value, dict):
            return RewardTerm(name, _scale(node), separation(3.0))
        node.reject_unknown({"scale", "distance_m", "give_way"})
        return RewardTerm(name, _scale(node.get("scale")),
                          separation(node.get("distance_m", 3.0).number(positive=True, maximum=100.0),
                                     node.get("give_way", False).boolean()))
    if isinstance(node.value, dict):
        node.reject_unknown({"scale"})
        node = node.get("scale")
    return RewardTerm(name, _scale(node), _SIMPLE_TERMS[name])


def parse_rewards(node: Node, step_s: float = 1.0) -> list[RewardTerm]:
    """Parse the `reward:` mapping into scaled terms (in file order); `step_s` is the decision
    period the per-second terms (`PER_SECOND`) are scaled by."""
    terms = []
    for name, child in node.items():
        if name not in TERM_NAMES:
            raise ConfigError(f"{node.source}: {child.path}: unknown reward term "
                              f"(expected one of {', '.join(TERM_NAMES)})")
        term = _parse_term(name, child)
        terms.append(dataclasses.replace(term, period_s=step_s) if name in PER_SECOND else term)
    if not terms:
        raise node.error("at least one reward term")
    return terms
