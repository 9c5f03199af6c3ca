"""Start or resume a training run with the trainer of its algorithm: `Trainer` (the project's
DQN) or `SB3Trainer` (PPO, SAC, TD3). Every caller that starts runs (`train`, `sweep`,
`experiment`, curricula) comes through here, so none of them branches on the algorithm."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from sitl_bridge.rl.common.drones_env import EnvFactory
from sitl_bridge.rl.learner.config import TrainConfig
from sitl_bridge.rl.training import run_dir as rd
from sitl_bridge.rl.training.sb3_trainer import SB3Trainer
from sitl_bridge.rl.training.trainer import Trainer


def trainer_class(algorithm: str) -> type[Trainer]:
    """The trainer of `algorithm` (dqn: the project's own, else Stable-Baselines3's)."""
    return Trainer if algorithm == "dqn" else SB3Trainer


def start_run(out: str | Path, spec: rd.RunSpec, config: TrainConfig, env_factory: EnvFactory,
              **kwargs: Any) -> Trainer:
    """A new run of `config.algorithm` under `out` (see `Trainer.start`)."""
    return trainer_class(config.algorithm).start(out, spec, config, env_factory, **kwargs)


def resume_run(run_dir: str | Path, env_factory: EnvFactory | None = None, episodes: int | None = None,
               **kwargs: Any) -> Trainer:
    """Continue the run in `run_dir` with the trainer of the algorithm its config.yaml names."""
    _, config = rd.read_run_files(run_dir)
    return trainer_class(config.algorithm).resume(run_dir, env_factory, episodes=episodes, **kwargs)
