"""Start or resume a training run: `Trainer` trains every algorithm (the project's DQN through
rl/training/dqn_training.py, Stable-Baselines3's PPO, SAC and TD3 through
rl/training/sb3_training.py), so no caller (`train`, `sweep`, `experiment`, curricula) branches
on the algorithm."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from sitl_bridge.rl.common.drones_env import EnvFactory
from sitl_bridge.rl.learner.config import TrainConfig
from sitl_bridge.rl.training import run_dir as rd
from sitl_bridge.rl.training.trainer import Trainer


def start_run(out: str | Path, spec: rd.RunSpec, config: TrainConfig, env_factory: EnvFactory,
              **kwargs: Any) -> Trainer:
    """A new run of `config.algorithm` under `out` (see `Trainer.start`)."""
    return Trainer.start(out, spec, config, env_factory, **kwargs)


def resume_run(run_dir: str | Path, env_factory: EnvFactory | None = None, episodes: int | None = None,
               **kwargs: Any) -> Trainer:
    """Continue the run in `run_dir` with the algorithm its config.yaml names (see `Trainer.resume`)."""
    return Trainer.resume(run_dir, env_factory, episodes=episodes, **kwargs)
