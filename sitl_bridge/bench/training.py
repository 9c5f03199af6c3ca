"""The bench's training figures: DQN env steps per wall second with the updates included.

`train_steps_per_s` trains one env at a time (the scenario's `num_envs`, 1 for O);
`train_vector_steps_per_s` trains `VECTOR_ENVS` copies at once (`num_envs`, waves of episodes
with one network call per vector step: rl/training/vector_collect.py). Both use O's `train:`
settings from worlds/obstacle.yaml (one update per env step) without evaluations, and time only
episodes flown once updates run.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

VECTOR_ENVS = 4
"""Copies of the vector training case: a small N, as a 2-core machine runs it."""


def train_rates(world: Path, episodes: int, reps: int, num_envs: int | None = None) -> tuple[list[float], int]:
    """Env steps per wall second of each of `reps` timed stretches of about `episodes` training
    episodes (whole waves with `num_envs` > 1), and the DQN updates made by the end."""
    from sitl_bridge.rl.common.drones_env import scenario_env_factory
    from sitl_bridge.rl.learner.config import load_train_config
    from sitl_bridge.rl.training.run_dir import RunSpec
    from sitl_bridge.rl.training.trainer import Trainer

    overrides: dict[str, Any] = {"eval_every": 0}  # no evaluation pauses
    if num_envs is not None:
        overrides["num_envs"] = num_envs
    config = load_train_config(world, overrides)
    rates = []
    with tempfile.TemporaryDirectory(prefix="sitl-bench-") as out, \
            Trainer.start(out, RunSpec(world=str(world), autopilot="direct", seed=0), config,
                          scenario_env_factory(str(world), "direct"), progress=False) as trainer:
        trainer.run_episodes()  # warm-up (network, replay, env start) ...
        for _ in range(500):  # ... until updates run: the timed episodes include them
            if trainer.updates:
                break
            trainer.run_episodes()
        for _ in range(reps):
            steps0, t0 = trainer.global_step, time.perf_counter()
            goal = trainer.episode + max(1, episodes // reps)
            while trainer.episode < goal:
                trainer.run_episodes()
            rates.append((trainer.global_step - steps0) / (time.perf_counter() - t0))
        return rates, trainer.updates
