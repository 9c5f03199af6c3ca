"""Shared helpers of the RL tests: a tiny deterministic corridor task with the scenario envs'
interface (Discrete(8), Box observation, info outcome / reward_terms / sim_time_s), and a
function that trains on it (imported by the SIGKILL subprocess too).

The corridor is for fast trainer mechanics tests; learning on the real scenarios is checked
against `sitl_bridge.envs` in test_rl_envs.py.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np


class CorridorEnv(gym.Env):
    """Walk along a 1-D corridor of `length` cells to a goal cell drawn each episode.

    Actions: 0 step +1, 1 step -1, 6 step toward the goal, others stay. Reward: -1 per step,
    +10 on the goal (terminated, outcome "goal"), -5 when leaving the corridor (terminated,
    "out"); truncated after `max_steps` ("timeout"). Observation: [position, goal] / length.
    """

    def __init__(self, length: int = 7, max_steps: int = 12, step_delay_s: float = 0.0) -> None:
        self.length = length
        self.max_steps = max_steps
        self.step_delay_s = step_delay_s
        self.action_space = gym.spaces.Discrete(8)
        self.observation_space = gym.spaces.Box(0.0, 1.0, shape=(2,), dtype=np.float32)
        self.position = 0
        self.goal = 0
        self.steps = 0

    def _obs(self) -> np.ndarray:
        return np.array([self.position, self.goal], dtype=np.float32) / self.length

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.position = int(self.np_random.integers(0, self.length))
        self.goal = int(self.np_random.integers(0, self.length - 1))
        if self.goal >= self.position:
            self.goal += 1
        self.steps = 0
        return self._obs(), {"sim_time_s": 0.0}

    def step(self, action: int):
        if self.step_delay_s:
            import time

            time.sleep(self.step_delay_s)
        move = {0: 1, 1: -1, 6: int(np.sign(self.goal - self.position))}.get(int(action), 0)
        self.position += move
        self.steps += 1
        terms = {"per_step": -1.0, "goal_reached": 0.0, "out_of_workspace": 0.0}
        outcome = None
        if not 0 <= self.position < self.length:
            terms["out_of_workspace"] = -5.0
            outcome = "out"
        elif self.position == self.goal:
            terms["goal_reached"] = 10.0
            outcome = "goal"
        terminated = outcome is not None
        truncated = not terminated and self.steps >= self.max_steps
        if truncated:
            outcome = "timeout"
        self.position = min(max(self.position, 0), self.length - 1)
        info: dict[str, Any] = {"outcome": outcome, "reward_terms": terms, "sim_time_s": float(self.steps),
                                "position_enu_m": [float(self.position), 0.0, 0.0]}
        return self._obs(), float(sum(terms.values())), terminated, truncated, info


def corridor_factory(step_delay_s: float = 0.0):
    """Env factory (seed -> env) for the trainer."""
    return lambda seed: CorridorEnv(step_delay_s=step_delay_s)


def tiny_config(**changes: Any):
    """A small, fast TrainConfig for the corridor."""
    from sitl_bridge.rl.learner.config import TrainConfig

    base = dict(episodes=6, gamma=0.9, epsilon_decay=1e-2, learning_rate=3e-3, batch_size=8,
                target_update_period=10, replay_capacity=40, layers=2, hidden_units=16,
                replay_segment_rows=16, eval_episodes=0, checkpoints_kept=3)
    base.update(changes)
    return TrainConfig(**base)


def train_corridor(out: str, run_dir: str | None, episodes: int, step_delay_s: float, seed: int = 0,
                   **changes: Any) -> str:
    """Start (run_dir None) or resume a corridor run (`changes`: TrainConfig values of a new
    run); returns the run directory. It writes the heartbeat, as `sitl-bridge train` does."""
    from sitl_bridge.rl.training.run_dir import RunSpec
    from sitl_bridge.rl.training.trainer import Trainer

    factory = corridor_factory(step_delay_s)
    if run_dir is None:
        trainer = Trainer.start(out, RunSpec(world="corridor.yaml", seed=seed),
                                tiny_config(episodes=episodes, **changes), factory, progress=False, heartbeat=True)
        print(trainer.run_dir, flush=True)
    else:
        trainer = Trainer.resume(run_dir, factory, episodes=episodes, progress=False, heartbeat=True)
    with trainer:
        trainer.train()
    return str(trainer.run_dir)


def kill_when_replacing(name: str, when: str) -> None:
    """SIGKILL this process just before (`when` "before") or just after ("after") a file named
    `name` is renamed into place: a kill at an exact point of an atomic write (rl/common/atomic.py)."""
    import os
    import signal

    real_replace = os.replace

    def replace(src: Any, dst: Any) -> None:
        if Path(dst).name == name and when == "before":
            os.kill(os.getpid(), signal.SIGKILL)
        real_replace(src, dst)
        if Path(dst).name == name and when == "after":
            os.kill(os.getpid(), signal.SIGKILL)

    os.replace = replace


if __name__ == "__main__":
    # python tests/test_rl_helpers.py OUT RUN_DIR|- EPISODES STEP_DELAY_S [CONFIG_JSON [FILE:before|after]]
    import json

    sys.path.insert(0, str(Path(__file__).parent))
    out_dir, run, count, delay = sys.argv[1:5]
    config_changes = json.loads(sys.argv[5]) if len(sys.argv) > 5 else {}
    if len(sys.argv) > 6:
        kill_when_replacing(*sys.argv[6].split(":"))
    train_corridor(out_dir, None if run == "-" else run, int(count), float(delay), **config_changes)
