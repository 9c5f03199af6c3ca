"""Greedy rollouts: fly a policy for whole episodes and keep what each drone did.

Shared by evaluation (success/crash rates) and rule extraction (what the behaviour looks like).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sitl_bridge.rl.common.action_names import logged_action
from sitl_bridge.rl.common.drones_env import DronesEnv, episode_outcome


@dataclass
class Trace:
    """One drone's episode under a fixed policy."""

    episode: int
    drone: int
    seed: int
    actions: list = field(default_factory=list)
    """Discrete codes, or continuous commands as lists (`logged_action`)."""
    reward: float = 0.0
    outcome: str = "timeout"
    positions_enu_m: list[list[float]] = field(default_factory=list)
    """Position after reset and after every step, when the env reports `position_enu_m`."""
    goal_enu_m: list[float] | None = None
    sim_times_s: list[float] = field(default_factory=list)
    """Simulated time after reset and after every step, when the env reports `sim_time_s`."""
    commands_enu_m_s: list[list[float]] = field(default_factory=list)
    """The velocity setpoint each step flew (ENU m/s), when the env reports `command_enu_m_s`."""
    encounter: str | None = None
    """The episode's encounter type (`encounter_label`; None outside `world.encounter` worlds)."""

    @property
    def steps(self) -> int:
        return len(self.actions)


def position_of(info: dict[str, Any]) -> list[float] | None:
    """The drone's position (ENU m) an env step or reset reported in its info, if any."""
    return _vector(info, "position_enu_m")


def _vector(info: dict[str, Any], key: str) -> list[float] | None:
    value = info.get(key)
    return None if value is None else [float(v) for v in np.asarray(value).reshape(-1)]


def _record_time(trace: Trace, info: dict[str, Any]) -> None:
    if info.get("sim_time_s") is not None:
        trace.sim_times_s.append(float(info["sim_time_s"]))


def encounter_label(info: dict[str, Any]) -> str | None:
    """The encounter type an env reported in a drone's info (`world.encounter`): its kind, with
    ", late entry" when a drone of it entered late (overtaking's waiting leader is its kind)."""
    kind = info.get("encounter")
    if kind is None:
        return None
    return f"{kind}, late entry" if info.get("late_entry") else str(kind)


def record_step(traces: dict[int, Trace], chosen: dict[int, int], result: Any) -> None:
    """Add one simultaneous step (`DronesEnv.step`'s result for the `chosen` actions) to each
    acting drone's trace: action, reward, position, and the outcome when its episode ended."""
    for i, action in chosen.items():
        info = result.infos.get(i, {})
        trace = traces[i]
        trace.actions.append(logged_action(action))
        trace.reward += result.rewards[i]
        position = position_of(info)
        if position is not None:
            trace.positions_enu_m.append(position)
        _record_time(trace, info)
        command = _vector(info, "command_enu_m_s")
        if command is not None:
            trace.commands_enu_m_s.append(command)
        if result.terminated[i] or result.truncated[i]:
            trace.outcome = episode_outcome(info, result.terminated[i], result.truncated[i])


def rollout(env: DronesEnv, policy: Callable[[np.ndarray], int], seeds: Iterable[int],
            on_episode: Callable[[list[Trace]], None] | None = None, videos: Any = None) -> list[Trace]:
    """One episode per seed, every drone acting with `policy`; one Trace per drone per episode.
    `on_episode(traces)` runs after each episode with that episode's traces (progress, logs);
    `videos` (`rl.evaluation.video.EpisodeVideos`) gets the env's rendered frame after reset and each step."""
    traces: list[Trace] = []
    for episode, seed in enumerate(seeds):
        obs, infos = env.reset(seed)
        mine = fly_episode(env, policy, episode, seed, obs, infos, videos)
        traces.extend(mine)
        if on_episode is not None:
            on_episode(mine)
    return traces


def fly_episode(env: DronesEnv, policy: Callable[[np.ndarray], int], episode: int, seed: int,
                obs: dict[int, np.ndarray], infos: dict[int, dict[str, Any]], videos: Any = None) -> list[Trace]:
    """Fly the episode `env` was just reset into (`obs`, `infos`: what the reset returned) to its
    end, every drone acting with `policy` on its own observation; one Trace per drone."""
    obs = dict(obs)
    if videos is not None:
        videos.add(env.render())
    mine = {i: Trace(episode, i, seed) for i in range(env.num_drones)}
    for i, trace in mine.items():
        start = position_of(infos.get(i, {}))
        if start is not None:
            trace.positions_enu_m.append(start)
        _record_time(trace, infos.get(i, {}))
        goal = infos.get(i, {}).get("goal_enu_m")
        trace.encounter = encounter_label(infos.get(i, {}))
        trace.goal_enu_m = None if goal is None else [float(v) for v in np.asarray(goal).reshape(-1)]
    while env.live:
        chosen = {i: policy(obs[i]) for i in env.live}
        result = env.step(chosen)
        if videos is not None:
            videos.add(env.render())
        record_step(mine, chosen, result)
        obs.update(result.obs)
    if videos is not None:
        videos.end_episode(episode)
    return list(mine.values())


EVAL_SEED_OFFSET = 1_000_003
"""Evaluation and rule-extraction episodes use seeds far from the training episodes'."""


def eval_seeds(seed: int, episodes: int) -> list[int]:
    """Reset seeds of `episodes` evaluation episodes (disjoint from training's)."""
    return [int(s) for s in np.random.SeedSequence([seed, EVAL_SEED_OFFSET]).generate_state(episodes)]


def episode_seed(run_seed: int, episode: int) -> int:
    """The reset seed of training `episode` in a run seeded `run_seed` (independent streams per
    episode)."""
    return int(np.random.SeedSequence([run_seed, episode]).generate_state(1)[0])
