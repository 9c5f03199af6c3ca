"""One crash-safe training run in a run directory: the loop.

    for each episode (with `num_envs` N > 1: each wave of N episodes flown at once):
        reset with the episode's own seed (so a resumed run repeats it exactly)
        until every drone is done: the learner's actions -> env step -> replay -> updates
        append the episode's transitions to the replay shards, its records to episodes.jsonl,
        then write a checkpoint (atomic) naming how much of both it covers
        every `eval_every` episodes: a greedy evaluation (the best one's checkpoint is the
        run's result) and, once per run, the constant-action baseline it must beat to stop

The parts, one job each: the algorithm's side (`dqn_training.py`: env(s), DQN learner, replay
shards, the episode loop, N-copy waves in `vector_collect.py`; `sb3_training.py`: PPO, SAC,
TD3), where finished episodes go (`episode_sink.py`), the checkpoints and resume
(`run_state.py`), the evaluations, best checkpoint and baseline (`run_evaluation.py`), and
`--init-from` (`init_from.py`).

`--resume` restores the newest checkpoint that verifies (falling back to older ones), cuts the
replay shards and the episode log back to what it covers and continues: a run killed at any
moment loses at most the episode (or wave) in flight.
"""

from __future__ import annotations

import shutil
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sitl_bridge.rl.common.drones_env import EnvFactory
from sitl_bridge.rl.common.episode_log import EpisodeRecord, read_records
from sitl_bridge.rl.common.progress import Progress
from sitl_bridge.rl.evaluation.evaluate import ConstantBaseline, EvalResult
from sitl_bridge.rl.learner import checkpoint as ckpt
from sitl_bridge.rl.learner.config import TrainConfig
from sitl_bridge.rl.training import run_dir as rd
from sitl_bridge.rl.training.dqn_training import DQNTraining
from sitl_bridge.rl.training.early_end import EarlyEndWatch
from sitl_bridge.rl.training.episode_sink import EpisodeSink
from sitl_bridge.rl.training.heartbeat import TRAINING
from sitl_bridge.rl.training.init_from import (
    ShapeMismatch,
    adopt_architecture,
    check_same_algorithm,
)
from sitl_bridge.rl.training.run_evaluation import RunEvaluator
from sitl_bridge.rl.training.run_state import RunState, refuse_edited_config
from sitl_bridge.rl.training.sb3_training import SB3Training


@dataclass
class TrainResult:
    """Where a run stands when `train()` returns."""

    run_dir: Path
    episodes: int
    """Episodes of the whole run so far (earlier sessions of a resumed run included)."""
    global_step: int
    """Env steps of the whole run so far."""
    episodes_this_session: int
    steps_this_session: int
    wall_time_s: float
    """Wall time of this call (not of earlier sessions of a resumed run)."""
    success_rate: float
    """Rolling success rate over the last `success_window` drone-episodes."""


class Trainer:
    """Trains one run of any algorithm; build with `Trainer.start(...)` or `Trainer.resume(...)`."""

    def __init__(self, run_dir: Path, spec: rd.RunSpec, config: TrainConfig, env_factory: EnvFactory,
                 *, progress: bool = True, warn: Callable[[str], None] | None = None,
                 heartbeat: bool = False) -> None:
        """`heartbeat`: write `heartbeat.json` (rl/training/heartbeat.py) between training episodes
        and after each evaluation and baseline episode, for a watchdog."""
        self.run_dir, self.spec, self.config, self.progress = Path(run_dir), spec, config, progress
        self.warn = warn or (lambda msg: print(f"warning: {msg}", file=sys.stderr))
        side = DQNTraining if config.algorithm == "dqn" else SB3Training
        self.training = side(self.run_dir, spec, config, env_factory, self.warn)
        self.env, self.learner = self.training.env, self.training.learner
        gamma = float(config.sb3_arguments.get("gamma", 0.99)) if config.algorithm != "dqn" else config.gamma
        guided = config.guided_explore_episodes if config.algorithm == "dqn" else None  # a DQN option
        early_end = EarlyEndWatch.of(getattr(self.env.env, "scenario", None), gamma, guided_episodes=guided)
        self.sink = EpisodeSink(self.run_dir, config.success_window, early_end, self.training.store_rows,
                                heartbeat=heartbeat, warn=self.warn)
        self.saved = RunState(self.run_dir, spec, config, self.training, self.sink)
        self.evaluator = RunEvaluator(self.run_dir, spec, config, self.env, self.training.greedy_action,
                                      self.learner, progress=progress, beat=self.beat, warn=self.warn)
        self.stopped_early = False
        """True when a greedy evaluation reached `stop_on_success` (the run counts as done)."""
        self.last_eval: EvalResult | None = None
        """The latest greedy evaluation of this session."""
        self.evaluation_due = False
        """The state checkpointed last is one that gets a periodic evaluation (kept in the
        checkpoint, so a run killed during that evaluation flies it again on resume)."""

    # -- construction ----------------------------------------------------------------------------
    @classmethod
    def start(cls, out: str | Path, spec: rd.RunSpec, config: TrainConfig, env_factory: EnvFactory,
              **kwargs: Any) -> Trainer:
        """A new run directory under `out`; with `spec.init_from`, the network starts from that
        run's (or checkpoint's) network (DQN: epsilon from `transfer_epsilon_max`)."""
        init = ckpt.resolve_checkpoint(spec.init_from) if spec.init_from else None
        if init is not None:
            check_same_algorithm(init[0], init[2], config.algorithm)
            if config.algorithm == "dqn":
                config = adopt_architecture(config, init[2]["network"])
        run_dir = rd.create_run_dir(out, spec, config)
        try:
            trainer = cls(run_dir, spec, config, env_factory, **kwargs)
        except BaseException:
            shutil.rmtree(run_dir, ignore_errors=True)  # a failed start leaves no run directory
            raise
        if init is not None:
            try:
                trainer.training.load_init(*init)
            except (ShapeMismatch, ckpt.CheckpointError):
                trainer.close()
                shutil.rmtree(run_dir)  # just created, holds nothing yet
                raise
        return trainer

    @classmethod
    def resume(cls, run_dir: str | Path, env_factory: EnvFactory | None = None,
               episodes: int | None = None, **kwargs: Any) -> Trainer:
        """Continue the run in `run_dir` from its newest good checkpoint (`episodes` extends the
        budget). A run with no checkpoint yet starts over in the same directory."""
        run_dir = Path(run_dir)
        spec, config = rd.read_run_files(run_dir)
        refuse_edited_config(run_dir, config)
        if episodes is not None and episodes != config.episodes:
            config = config.replace(episodes=episodes)
            rd.write_run_files(run_dir, spec, config)
        if env_factory is None:
            from sitl_bridge.rl.common.drones_env import scenario_env_factory
            env_factory = scenario_env_factory(rd.run_scenario(run_dir), spec.autopilot,
                                               **({"standby": True} if spec.standby else {}))
        for stale in [*run_dir.glob(".*.tmp*"), *run_dir.glob("*/.*.tmp*")]:
            stale.unlink()  # half-written temp files of a killed session (never renamed into place)
        trainer = cls(run_dir, spec, config, env_factory, **kwargs)
        try:
            due = trainer.saved.restore_newest(trainer.warn)
            if due is not None:
                trainer.evaluation_due = due
            else:
                trainer.saved.start_over_without_history()
                if spec.init_from:
                    trainer.training.load_init(*ckpt.resolve_checkpoint(spec.init_from))
        except BaseException:
            trainer.close()
            raise
        return trainer

    # -- the loop --------------------------------------------------------------------------------
    def train(self, on_episode: Callable[[list[EpisodeRecord]], bool | None] | None = None) -> TrainResult:
        """Train until `config.episodes` episodes are done. `on_episode(records)` runs after each
        checkpoint (one episode's records, or a wave's with `num_envs` > 1); returning False
        stops early (resumable). Periodic evaluations run when the episode count reaches or
        passes a multiple of `eval_every`."""
        start = time.perf_counter()
        first_episode, first_step = self.episode, self.global_step
        bar = Progress(self.config.episodes, Path(self.spec.world).stem, initial=self.episode,
                       enabled=self.progress)
        self.beat()
        try:
            # A session killed during the periodic evaluation of its last checkpoint left it
            # undone: fly it now, so the run goes on exactly as an uninterrupted one.
            self.stopped_early = self.evaluation_due and self._periodic_evaluation(bar)
            while self.episode < self.config.episodes and not self.stopped_early:
                before = self.episode
                records = self.run_episodes()
                every = self.config.eval_every
                self.evaluation_due = bool(every and self.config.eval_episodes
                                           and before // every != self.episode // every
                                           and self.episode < self.config.episodes)
                self.save_checkpoint()
                self.beat()
                self.sink.tensorboard(records, self.learning_rate())
                exploring = {"epsilon": f"{records[0].epsilon:.3f}"} if self.config.algorithm == "dqn" else {}
                bar.update(self.episode - before, explore_success=f"{self.success_rate():.2f}", **exploring)
                if self.evaluation_due and self._periodic_evaluation(bar):
                    self.stopped_early = True
                    break
                if on_episode is not None and on_episode(records) is False:
                    break
        finally:
            bar.close()
            self.sink.flush()
        return TrainResult(self.run_dir, self.episode, self.global_step, self.episode - first_episode,
                           self.global_step - first_step, time.perf_counter() - start, self.success_rate())

    def _periodic_evaluation(self, bar: Progress) -> bool:
        """The greedy evaluation of the state just checkpointed (read back when an earlier
        session finished it) and the constant-action baseline; True when it solves the scenario."""
        result = self.recorded_evaluation() or self.evaluate()
        self.last_eval = result
        baseline = self.constant_baseline()  # measured once per run, then read back
        bar.update(0, greedy=f"{result.success_rate:.0%}", constant_best=f"{baseline.success_rate:.0%}")
        return self.evaluator.solved(result)

    # -- the parts' operations, as callers use them ----------------------------------------------
    def run_episodes(self) -> list[EpisodeRecord]:
        """Fly the next episode (with `num_envs` > 1, the next wave), learn from it and persist
        it; the caller checkpoints."""
        return self.training.run_episodes(self.persist)

    def run_episode(self) -> list[EpisodeRecord]:
        """Fly one training episode with every drone, learn from it, persist it."""
        return self.training.run_episode(self.persist)

    def persist(self, records: list[EpisodeRecord], new_rows: list[np.ndarray]) -> None:
        """Persist finished episodes' replay rows and then their records (before the checkpoint)."""
        self.sink.persist(records, new_rows)

    def save_checkpoint(self) -> Path:
        """Checkpoint the state after `self.episode` episodes; prune old checkpoints and shards."""
        return self.saved.save(self.evaluation_due)

    def evaluate(self, episodes: int | None = None) -> EvalResult:
        """Greedy evaluation of the current network in the training scenario: appended to
        evals.jsonl, written to eval.json (the latest), logged to TensorBoard."""
        result = self.evaluator.evaluate(episodes)
        self.sink.evaluation(self.episode - 1, result)
        self.last_eval = result
        return result

    def recorded_evaluation(self) -> EvalResult | None:
        """The evaluation of the current state that `evals.jsonl` already holds, if any."""
        return self.evaluator.recorded_evaluation()

    def constant_baseline(self) -> ConstantBaseline:
        """The best constant-action policy's greedy success (measured once per run)."""
        return self.evaluator.constant_baseline()

    def greedy_action(self, obs: np.ndarray) -> Any:
        """The current network's deterministic action for one observation."""
        return self.training.greedy_action(obs)

    def beat(self, phase: str = TRAINING) -> None:
        """With `heartbeat` on, tell a watchdog the run is alive and what it is doing."""
        self.sink.beat(self.episode, self.global_step, phase)

    def epsilon(self) -> float:
        return self.training.epsilon()

    def learning_rate(self) -> float:
        return self.training.learning_rate()

    def success_rate(self) -> float:
        return self.sink.success_rate()

    episode = property(lambda self: self.learner.episode)
    global_step = property(lambda self: self.learner.global_step)
    updates = property(lambda self: self.learner.updates)
    early_end = property(lambda self: self.sink.early_end)
    # DQN's learning state, read by tests and benchmarks.
    agent = property(lambda self: self.learner.agent)
    replay = property(lambda self: self.learner.replay)
    explorer = property(lambda self: self.learner.explorer)

    def close(self) -> None:
        """Close the env(s) and the TensorBoard writer."""
        self.sink.close()
        self.training.close()

    def __enter__(self) -> Trainer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def read_run_records(run_dir: str | Path) -> list[dict]:
    """The episode records of a run directory."""
    return read_records(Path(run_dir) / rd.EPISODES_FILE)
