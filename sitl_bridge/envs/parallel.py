"""`SitlParallelEnv`: the multi-drone PettingZoo ParallelEnv over any scenario file."""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from sitl_bridge.client.actions import NUM_ACTIONS
from sitl_bridge.envs.actions import action_space
from sitl_bridge.envs.backends.base import Backend
from sitl_bridge.envs.manual import describe
from sitl_bridge.envs.options import EnvOptions
from sitl_bridge.envs.render import EnvRenderer, FrameList
from sitl_bridge.envs.runner import EpisodeRunner
from sitl_bridge.envs.scenario import Scenario, load_scenario
from sitl_bridge.envs.single import observation_space
from sitl_bridge.physics.render import RenderConfig


class SitlParallelEnv(ParallelEnv):
    """Several drones, each with its own observation and reward, acting simultaneously.

    ## Description
    The multi-drone form of `SitlEnv` (read its manual for actions, observation features,
    rewards and episode end; they are the same per drone). Agents are the world's vehicle names
    (e.g. `drone0`, `drone1`); every agent has the same action space (`Discrete(8)`, or the
    `Box(-1, 1)` velocity vector of `task.action.type: velocity`) and the same
    observation `Box`, so one shared policy can fly all of them (the thesis's TE and TW). All
    drones fly their actions at once for the action's duration, then the simulation is held
    while the agents decide.

    An agent whose episode ends (goal, crash, out of the workspace, step limit) leaves
    `env.agents`; its drone hovers where it is for the rest of the episode (or lands, at its goal,
    under the scenario's `end.after_goal: land`). The episode is over
    when `env.agents` is empty. Head-on crashes end the episode for both drones.

    ## Arguments
    ```python
    sitl_bridge.envs.make_parallel_env("worlds/two_drones_empty.yaml", autopilot="direct",
                                       speed_factor=0.0, seed=None, instance_base=0, px4_bin=None,
                                       estimator="sensors")
    ```
    Same meanings as for `SitlEnv`.

    ## Version History
    * v0: initial version (thesis scenarios TE and TW; any scenario file works).
    """

    metadata = {"render_modes": ["rgb_array", "rgb_array_list", "human"], "name": "sitl_bridge_parallel_v0",
                "render_fps": RenderConfig().fps}

    def __init__(self, scenario: str | Path | Scenario, *, backend: Backend | None = None,
                 options: EnvOptions | None = None, **option_values: Any) -> None:
        self.options = EnvOptions.of(options, **option_values)  # autopilot=, speed_factor=, seed=, ...
        self.scenario = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
        self.runner = EpisodeRunner.open(self.scenario, self.options, backend)
        self.backend = self.runner.backend
        self.possible_agents = [v.name for v in self.scenario.world.vehicles]
        self.agents: list[str] = []
        self._index = {name: i for i, name in enumerate(self.possible_agents)}
        self._observation_space = observation_space(self.scenario)
        self._action_space = action_space(self.scenario.task.action)  # Discrete(8) or Box(-1, 1), per agent
        self._rng = np.random.default_rng(self.options.seed)
        self.render_mode = self.options.render_mode
        self.metadata = {**self.metadata, "render_fps": self.scenario.task.render.fps}
        self._renderer = EnvRenderer(self.scenario.world, self.scenario.task.render, self.backend,
                                     self.render_mode) if self.render_mode else None
        self._frames = FrameList(self._renderer, self._followed, lambda: self.runner.snapshot) \
            if self.render_mode == "rgb_array_list" else None
        if self._frames is not None:
            self.runner.on_frame = self._frames.capture

    @functools.cache  # noqa: B019 - PettingZoo's idiom: one space per agent
    def observation_space(self, agent: str) -> spaces.Box:
        return self._observation_space

    @functools.cache  # noqa: B019
    def action_space(self, agent: str) -> spaces.Space:
        return self._action_space

    def reset(self, seed: int | None = None,
              options: dict[str, Any] | None = None) -> tuple[dict[str, np.ndarray], dict[str, dict]]:
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        results = self.runner.reset(int(self._rng.integers(2**31 - 1)))
        self.agents = list(self.possible_agents)
        if self.render_mode == "human":
            self.render()
        if self._frames is not None:
            self._frames.restart()
        return ({a: results[self._index[a]].observation for a in self.agents},
                {a: results[self._index[a]].info for a in self.agents})

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        continuous = self.scenario.task.action.continuous
        for agent, action in actions.items():
            if agent not in self._index:
                raise KeyError(f"unknown agent {agent!r} (agents: {self.possible_agents})")
            if not continuous and not self._action_space.contains(action):
                raise ValueError(f"{agent}: action must be in 0..{NUM_ACTIONS - 1}, got {action!r}")
        live = list(self.agents)
        # continuous vectors: the runner checks them (finite, their shape) before anything flies
        results = self.runner.step({self._index[a]: actions[a] if continuous else int(actions[a])
                                    for a in live if a in actions})
        observations, rewards, terminations, truncations, infos = {}, {}, {}, {}, {}
        for agent in live:
            r = results[self._index[agent]]
            observations[agent] = r.observation
            rewards[agent] = r.reward
            terminations[agent] = r.terminated
            truncations[agent] = r.truncated
            infos[agent] = r.info
        self.agents = [a for a in live if not (terminations[a] or truncations[a])]
        if self.render_mode == "human":
            self.render()
        return observations, rewards, terminations, truncations, infos

    def render(self) -> np.ndarray | None:
        """`rgb_array`: a frame of the whole scenario (all drones; the scenario's `task.render`
        camera, `scene` by default); `human`: the GUI camera on the first drone, returns None."""
        if self._renderer is None:
            return None
        if self._frames is not None:
            return self._frames.take()
        return self._renderer.render(self._followed(), self.runner.snapshot)

    def _followed(self) -> int | None:
        return 0 if self.scenario.task.render.camera == "follow" else None

    def state(self) -> np.ndarray:
        """Global state: every drone's observation, concatenated in `possible_agents` order."""
        return np.concatenate([r.observation for r in self.runner.last_results])

    def describe(self) -> str:
        """This scenario's manual (Markdown)."""
        return describe(self.scenario)

    def close(self) -> None:
        self.runner.close()
