"""One training episode's per-drone totals, kept as it is flown, then its `EpisodeRecord`s."""

from __future__ import annotations

from typing import Any

import numpy as np

from sitl_bridge.rl.common.drones_env import episode_outcome, reward_terms, sim_time_s
from sitl_bridge.rl.common.episode_log import EpisodeRecord


class EpisodeTally:
    """Actions, rewards (and their terms), outcome and final info of each drone of one episode."""

    def __init__(self, num_drones: int, reset_infos: dict[int, dict[str, Any]]) -> None:
        drones = range(num_drones)
        self.drones = drones
        self.actions: dict[int, list[int]] = {i: [] for i in drones}
        self.rewards = dict.fromkeys(drones, 0.0)
        self.terms: dict[int, dict[str, float]] = {i: {} for i in drones}
        self.outcome: dict[int, str] = {}
        self.final_info: dict[int, dict[str, Any]] = {}
        # The env's clock may include the take-off before the first step: count from reset.
        self.sim_start = sim_time_s(reset_infos.get(0, {})) or 0.0
        self.sim_time = 0.0

    def add(self, drone: int, action: int, reward: float, terminated: bool, truncated: bool,
            info: dict[str, Any]) -> None:
        """One step of `drone`."""
        self.actions[drone].append(action)
        self.rewards[drone] += reward
        for name, value in reward_terms(info).items():
            self.terms[drone][name] = self.terms[drone].get(name, 0.0) + value
        self.sim_time = sim_time_s(info) or self.sim_time
        if terminated or truncated:
            self.outcome[drone] = episode_outcome(info, terminated, truncated)
            self.final_info[drone] = info

    def records(self, *, episode: int, wall_time_s: float, epsilon: float, mean_loss: float | None,
                global_step: int, env_seed: int, cpu_time_s: float | None = None) -> list[EpisodeRecord]:
        """One record per drone (a drone still flying is a timeout)."""
        return [EpisodeRecord(
            episode=episode, drone=i, actions=self.actions[i], reward=self.rewards[i],
            reward_terms=self.terms[i], outcome=self.outcome.get(i, "timeout"), steps=len(self.actions[i]),
            sim_time_s=max(self.sim_time - self.sim_start, 0.0), wall_time_s=wall_time_s, epsilon=epsilon,
            mean_loss=mean_loss, global_step=global_step, env_seed=env_seed, cpu_time_s=cpu_time_s,
            extra=_jsonable_extra(self.final_info.get(i, {})),
        ) for i in self.drones]


def _jsonable_extra(info: dict[str, Any]) -> dict[str, Any]:
    """Final positions etc. from the env's info, as plain JSON values (for rules and plots)."""
    extra: dict[str, Any] = {}
    for key in ("position_enu_m", "goal_enu_m", "distance_to_goal_m", "start_enu_m"):
        if key in info and info[key] is not None:
            value = np.asarray(info[key], dtype=float)
            extra[key] = [round(float(v), 3) for v in value.reshape(-1)] if value.ndim else round(float(value), 3)
    return extra
