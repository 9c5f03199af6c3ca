"""One view of single- and multi-drone environments for the learner.

The trainer, evaluation and rule extraction see every scenario as "N drones, each with its own
observation and reward, acting simultaneously"; a Gymnasium env is the N = 1 case and a
PettingZoo ParallelEnv the general one. Episodes are reset explicitly with a seed (Gymnasium 1.x
has no autoreset outside vector envs, and per-episode seeds make a resumed run exact).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from sitl_bridge.errors import ConfigError


@dataclass
class StepResult:
    """What the drones still flying got from one simultaneous step (keyed by drone index)."""

    obs: dict[int, np.ndarray]
    rewards: dict[int, float]
    terminated: dict[int, bool]
    truncated: dict[int, bool]
    infos: dict[int, dict[str, Any]] = field(default_factory=dict)


class DronesEnv:
    """A Gymnasium Env or a PettingZoo ParallelEnv behind one multi-drone interface."""

    def __init__(self, env: Any) -> None:
        self.env = env
        self.parallel = hasattr(env, "possible_agents")
        if self.parallel:
            self.agent_names = list(env.possible_agents)
            space = env.observation_space(self.agent_names[0])
            action_space = env.action_space(self.agent_names[0])
        else:
            self.agent_names = ["drone_0"]
            space, action_space = env.observation_space, env.action_space
        if not isinstance(action_space, (gym.spaces.Discrete, gym.spaces.Box)):
            raise TypeError(f"expected a Discrete or Box action space, got {action_space}")
        self.action_space = action_space
        self.continuous = isinstance(action_space, gym.spaces.Box)
        """Box actions (arrays); else Discrete codes (ints)."""
        self.num_drones = len(self.agent_names)
        self.obs_dim = int(np.prod(space.shape))
        self.n_actions = 0 if self.continuous else int(action_space.n)
        """Discrete actions: how many (0 for a Box)."""
        self.live: list[int] = []

    def reset(self, seed: int) -> tuple[dict[int, np.ndarray], dict[int, dict[str, Any]]]:
        """Start an episode; every drone is live."""
        if self.parallel:
            obs, infos = self.env.reset(seed=seed)
            self.live = [self.agent_names.index(a) for a in obs]
            return ({self.agent_names.index(a): self._flat(o) for a, o in obs.items()},
                    {self.agent_names.index(a): dict(i) for a, i in (infos or {}).items()})
        obs, info = self.env.reset(seed=seed)
        self.live = [0]
        return {0: self._flat(obs)}, {0: dict(info)}

    def step(self, actions: dict[int, Any]) -> StepResult:
        """One simultaneous step of the live drones; drones that end leave `live`."""
        if self.parallel:
            named = {self.agent_names[i]: self._action(a) for i, a in actions.items()}
            obs, rewards, terms, truncs, infos = self.env.step(named)
            index = self.agent_names.index
            result = StepResult(
                obs={index(a): self._flat(o) for a, o in obs.items()},
                rewards={index(a): float(r) for a, r in rewards.items()},
                terminated={index(a): bool(t) for a, t in terms.items()},
                truncated={index(a): bool(t) for a, t in truncs.items()},
                infos={index(a): dict(i) for a, i in infos.items()},
            )
        else:
            obs, reward, term, trunc, info = self.env.step(self._action(actions[0]))
            result = StepResult({0: self._flat(obs)}, {0: float(reward)}, {0: bool(term)},
                                {0: bool(trunc)}, {0: dict(info)})
        self.live = [i for i in self.live if not (result.terminated.get(i) or result.truncated.get(i))]
        return result

    def _action(self, action: Any) -> Any:
        return np.asarray(action, dtype=np.float32) if self.continuous else int(action)

    def guided_action(self, i: int) -> int:
        """Drone `i`'s goal-seeking guide action now (`EpisodeRunner.path_guided_action`)."""
        runner = getattr(getattr(self.env, "unwrapped", self.env), "runner", None)
        if runner is None:
            raise ConfigError("guided_explore_episodes: this env has no scenario runner to guide exploration")
        return int(runner.path_guided_action(i))

    def render(self) -> Any:
        """The env's `render()` (an RGB frame with `render_mode="rgb_array"`)."""
        return self.env.render()

    def close(self) -> None:
        self.env.close()

    @staticmethod
    def _flat(obs: Any) -> np.ndarray:
        return np.asarray(obs, dtype=np.float32).reshape(-1)


EnvFactory = Callable[[int], Any]
"""Builds a fresh Gymnasium or PettingZoo env given a seed. One that also has a
`vector(seed, num_envs)` method (`ScenarioEnvFactory`) builds the trainer's `num_envs` copies
with it; for any other, the copies are `factory(seed + k)`."""


class ScenarioEnvFactory:
    """Builds the envs of a scenario file: a Gymnasium env for one drone, a PettingZoo
    ParallelEnv for several (`sitl_bridge.envs.make_env` / `make_parallel_env`); `vector` builds
    N copies at once (`make_vec_env`)."""

    def __init__(self, world: str | Path, autopilot: str = "direct", **kwargs: Any) -> None:
        from sitl_bridge.world import load_world

        self.world, self.autopilot, self.kwargs = str(world), autopilot, kwargs
        self.multi = load_world(world).num_vehicles > 1

    def __call__(self, seed: int) -> Any:
        from sitl_bridge import envs

        make = envs.make_parallel_env if self.multi else envs.make_env
        return make(self.world, autopilot=self.autopilot, seed=seed, **self.kwargs)

    def vector(self, seed: int, num_envs: int) -> gym.vector.VectorEnv:
        """`num_envs` copies (copy k seeded `seed + k`, on instance `instance_base + k`)."""
        from sitl_bridge.envs import make_vec_env

        if self.multi:
            raise ConfigError(f"{self.world}: num_envs {num_envs}: several copies at once need a "
                              "single-drone scenario (this one has several drones; use num_envs 1)")
        return make_vec_env(self.world, num_envs=num_envs, autopilot=self.autopilot, seed=seed, **self.kwargs)


def scenario_env_factory(world: str | Path, autopilot: str = "direct", **kwargs: Any) -> ScenarioEnvFactory:
    """Factory for the scenario file `world` (`kwargs`: env options such as `instance_base`)."""
    return ScenarioEnvFactory(world, autopilot, **kwargs)


def episode_outcome(info: dict[str, Any], terminated: bool, truncated: bool) -> str:
    """goal / crash / out / timeout: the env's `info["outcome"]` when it gives one."""
    outcome = info.get("outcome")
    if isinstance(outcome, str) and outcome:
        return outcome
    if truncated and not terminated:
        return "timeout"
    return "terminated"


def reward_terms(info: dict[str, Any]) -> dict[str, float]:
    """Per-term rewards of one step (`info["reward_terms"]`), {} when the env gives none."""
    terms = info.get("reward_terms") or {}
    return {str(k): float(v) for k, v in terms.items()}


def sim_time_s(info: dict[str, Any]) -> float | None:
    """Simulated time the env reports (`sim_time_s` or `time_us`), None when it reports none."""
    if "sim_time_s" in info:
        return float(info["sim_time_s"])
    if "time_us" in info:
        return float(info["time_us"]) / 1e6
    return None
