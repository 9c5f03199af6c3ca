"""One crash-safe DQN training run in a run directory.

The loop (CleanRL-like, explicit Gymnasium 1.x resets, several drones sharing one network):

    for each episode:
        reset with the episode's own seed (so a resumed run repeats it exactly)
        until every drone is done: epsilon-greedy actions -> env step -> replay -> DQN update
        append the episode's transitions to the replay shards, its records to episodes.jsonl,
        then write a checkpoint (atomic) naming how much of both it covers

With `num_envs` N > 1 the episodes run in waves of N copies flown at once
(rl/training/vector_collect.py), each still reset with its own seed, and a checkpoint follows each wave.

`--resume` restores the newest checkpoint that verifies (falling back to older ones), cuts the
replay shards and the episode log back to what it covers and continues: a run killed at any
moment loses at most the episode (or wave) in flight.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import random
import shutil
import sys
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sitl_bridge.errors import ConfigError
from sitl_bridge.rl.common.atomic import append_durably, atomic_write_bytes, atomic_write_json
from sitl_bridge.rl.common.drones_env import DronesEnv, EnvFactory
from sitl_bridge.rl.common.episode_log import EpisodeLog, EpisodeRecord, read_records
from sitl_bridge.rl.common.progress import Progress
from sitl_bridge.rl.common.stats import wilson_interval
from sitl_bridge.rl.evaluation.evaluate import (
    ConstantBaseline,
    EvalResult,
    constant_action_baseline,
    constant_actions,
    evaluate_on,
)
from sitl_bridge.rl.evaluation.rollout import Trace, episode_seed
from sitl_bridge.rl.learner import checkpoint as ckpt
from sitl_bridge.rl.learner.checkpoint_fit import check_fits
from sitl_bridge.rl.learner.config import TrainConfig
from sitl_bridge.rl.learner.dqn import NetworkShape
from sitl_bridge.rl.learner.dqn_learner import DQNLearner
from sitl_bridge.rl.learner.policy_file import network_algorithm
from sitl_bridge.rl.learner.replay_store import ReplayCorrupt, ReplayStore, ReplayStoreState
from sitl_bridge.rl.learner.torch_threads import use_torch_threads
from sitl_bridge.rl.training import run_dir as rd
from sitl_bridge.rl.training.early_end import EarlyEndWatch
from sitl_bridge.rl.training.episode_tally import EpisodeTally
from sitl_bridge.rl.training.eval_journal import drop_evaluations_after, recorded_evaluation
from sitl_bridge.rl.training.heartbeat import TRAINING, write_heartbeat
from sitl_bridge.rl.training.tensorboard_log import TensorBoardLog
from sitl_bridge.rl.training.train_plan import baseline_notice
from sitl_bridge.rl.training.vector_collect import VectorCollector

log = logging.getLogger(__name__)


class ShapeMismatch(ValueError):
    """A network cannot be transferred: its input/output sizes differ from the scenario's."""


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


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


def selection_score(success_rate: float, drone_episodes: int, mean_reward: float) -> tuple[float, float]:
    """How a greedy evaluation ranks for the best checkpoint: the low end of its success rate's
    Wilson 95 % interval, ties by mean reward. Among evaluations of one length this orders as the
    rate itself; across lengths (`stop_confirm_episodes`) a confirmed 87 of 100 outranks 35 of 40."""
    trials = max(int(drone_episodes), 1)
    return wilson_interval(round(success_rate * trials), trials)[0], mean_reward


class Trainer:
    """Trains one run; build with `Trainer.start(...)` or `Trainer.resume(...)`."""

    def __init__(self, run_dir: Path, spec: rd.RunSpec, config: TrainConfig, env_factory: EnvFactory,
                 *, progress: bool = True, warn: Callable[[str], None] | None = None,
                 heartbeat: bool = False) -> None:
        self.run_dir = Path(run_dir)
        self.heartbeat = heartbeat
        """Write `heartbeat.json` (rl/training/heartbeat.py) between training episodes and after each
        evaluation and baseline episode, for a watchdog."""
        self.spec = spec
        self.config = config
        self.progress = progress
        self.warn = warn or (lambda msg: print(f"warning: {msg}", file=sys.stderr))
        use_torch_threads(config.torch_threads)
        self.device = resolve_device(config.device)

        self.collector: VectorCollector | None = None
        if config.num_envs > 1:
            self.collector = VectorCollector(env_factory, spec.seed, config.num_envs)
            self.env = self.collector.copies[0]  # evaluations fly copy 0 between waves
        else:
            self.env = DronesEnv(env_factory(spec.seed))
        if self.env.continuous:
            (self.collector or self.env).close()
            raise ConfigError(f"{spec.world}: dqn needs discrete actions and this scenario's are continuous "
                              f"({self.env.action_space}); train it with --algorithm ppo, sac or td3")
        # Seed everything before the network exists, so its initial weights are reproducible.
        random.seed(spec.seed)
        torch.manual_seed(spec.seed)
        self.rng = np.random.default_rng(spec.seed)
        shape = NetworkShape(self.env.obs_dim, self.env.n_actions, config.layers, config.hidden_units,
                             dueling=config.dueling, normalize=config.normalize_observations)
        self.learner = DQNLearner(shape, config, self.device, self.rng)
        self.store = ReplayStore(self.run_dir / rd.REPLAY, shape.obs_dim, config.replay_segment_rows)
        self._init_run_state()

    def _init_run_state(self) -> None:
        """What every run keeps beside its learner: episode log, checkpoints, rolling success,
        evaluation state (after `self.env` and the learner exist)."""
        config = self.config
        self.episode_log = EpisodeLog(self.run_dir / rd.EPISODES_FILE)
        self.checkpoint_dir = self.run_dir / rd.CHECKPOINTS
        self.recent_success: deque[bool] = deque(maxlen=config.success_window)
        gamma = float(config.sb3_arguments.get("gamma", 0.99)) if config.algorithm != "dqn" else config.gamma
        guided = config.guided_explore_episodes if config.algorithm == "dqn" else None  # a DQN option
        self.early_end = EarlyEndWatch.of(getattr(self.env.env, "scenario", None), gamma, guided_episodes=guided)
        self._kept: list[tuple[Path, int]] = []  # (checkpoint, replay rows it needs)
        self._writer: TensorBoardLog | None = None
        self.stopped_early = False
        """True when a greedy evaluation reached `stop_on_success` (the run counts as done)."""
        self.last_eval: EvalResult | None = None
        """The latest greedy evaluation of this session."""
        self.evaluation_due = False
        """The state checkpointed last is one that gets a periodic evaluation (kept in the
        checkpoint, so a run killed during that evaluation flies it again on resume)."""

    # The learning state lives in the learner; the run's own code reads and restores it here.
    agent = property(lambda self: self.learner.agent)
    replay = property(lambda self: self.learner.replay)
    explorer = property(lambda self: self.learner.explorer)
    episode = property(lambda self: self.learner.episode,
                       lambda self, value: setattr(self.learner, "episode", value))
    global_step = property(lambda self: self.learner.global_step,
                           lambda self, value: setattr(self.learner, "global_step", value))
    updates = property(lambda self: self.learner.updates,
                       lambda self, value: setattr(self.learner, "updates", value))
    epsilon_max = property(lambda self: self.learner.epsilon_max,
                           lambda self, value: setattr(self.learner, "epsilon_max", value))

    # -- construction -------------------------------------------------------------------
    @classmethod
    def start(cls, out: str | Path, spec: rd.RunSpec, config: TrainConfig, env_factory: EnvFactory,
              **kwargs: Any) -> Trainer:
        """A new run directory under `out`; with `spec.init_from`, the network starts from that
        run's (or checkpoint's) network and epsilon from `transfer_epsilon_max`."""
        init = ckpt.resolve_checkpoint(spec.init_from) if spec.init_from else None
        if init is not None:
            check_same_algorithm(init[0], init[2], config.algorithm)
            if config.algorithm == "dqn":
                config = _adopt_architecture(config, init[2]["network"])
        run_dir = rd.create_run_dir(out, spec, config)
        try:
            trainer = cls(run_dir, spec, config, env_factory, **kwargs)
        except BaseException:
            shutil.rmtree(run_dir, ignore_errors=True)  # a failed start leaves no run directory
            raise
        if init is not None:
            try:
                trainer._load_init(*init)
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
        _refuse_edited_config(run_dir, config)
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
            if ckpt.list_checkpoints(trainer.checkpoint_dir):
                ckpt.restore_newest(trainer.checkpoint_dir, trainer._restore, warn=trainer.warn)
            else:
                trainer._start_over_without_history()
                if spec.init_from:
                    trainer._load_init(*ckpt.resolve_checkpoint(spec.init_from))
        except BaseException:
            trainer.close()
            raise
        return trainer

    def _start_over_without_history(self) -> None:
        """A run with no checkpoint starts over, unless it already logged finished episodes:
        it must never train over its own history (duplicate episodes in the log)."""
        logged = {r["episode"] for r in read_records(self.episode_log.path, warn=lambda _msg: None)}
        if logged - {0}:
            raise ckpt.CheckpointError(
                f"{self.run_dir}: {len(logged)} episodes are logged but no checkpoint is usable; refusing "
                "to start the run over its own history (start a new run, or put the checkpoints back)")
        self.episode_log.truncate(0)  # killed before its first checkpoint: nothing to keep

    def _load_init(self, path: Path, tensors: dict[str, torch.Tensor], state: dict[str, Any]) -> None:
        if self.config.transfer_replay and state.get("policy_only"):
            raise ckpt.CheckpointError(f"--transfer-replay: {path} is a policy file (the network alone, no replay); "
                                       "give an unslimmed run directory or training checkpoint, or leave "
                                       "--transfer-replay off")
        check_same_algorithm(path, state, "dqn")
        source = state["network"]
        mine = self.agent.shape.to_dict()
        if (source["obs_dim"], source["n_actions"]) != (mine["obs_dim"], mine["n_actions"]):
            raise ShapeMismatch(
                f"--init-from {path}: its network takes {source['obs_dim']} inputs and gives "
                f"{source['n_actions']} outputs, but {self.spec.world} needs {mine['obs_dim']} "
                f"inputs and {mine['n_actions']} outputs (pad the observations with dummy features "
                "to transfer between scenarios)")
        self.agent.online.load_state_dict(_prefixed(tensors, "online."))
        self.agent.align_target()
        self.epsilon_max = self.config.transfer_epsilon_max
        if self.config.transfer_replay:
            self._adopt_replay(path)

    def _adopt_replay(self, init_path: Path) -> None:
        """Start the replay with the transitions of the run `init_path` belongs to (written to
        this run's own shards, so checkpoints and resumes cover them like any other rows)."""
        source = next((d for d in (init_path, *init_path.parents) if (d / rd.RUN_FILE).is_file()), None)
        if source is None:
            raise ckpt.CheckpointError(f"--transfer-replay: {init_path} is not inside a run directory")
        try:
            store = ReplayStore.open_existing(source / rd.REPLAY)
            if store.dtype != self.store.dtype:
                raise ShapeMismatch(f"--transfer-replay: {source}'s replay rows do not fit this run's")
            _, _, state = ckpt.resolve_checkpoint(source, latest=True)
            rows = store.read(ReplayStoreState.from_json(state["replay"]), self.config.replay_capacity)
        except ReplayCorrupt as exc:
            raise ckpt.CheckpointError(f"--transfer-replay: {exc} (committed results keep no replay: "
                                       "train the source run here, or leave --transfer-replay off)") from None
        self.replay.add_rows(rows)
        self.store.append(rows)
        log.info("started the replay with %d transitions of %s", len(rows), source)

    # -- checkpoint contents (the explicit save list) --------------------------------------
    def _state_tensors(self) -> dict[str, torch.Tensor]:
        buffer = io.BytesIO()
        torch.save(self.agent.optimizer.state_dict(), buffer)
        tensors = {f"online.{k}": v for k, v in self.agent.online.state_dict().items()}
        tensors.update({f"target.{k}": v for k, v in self.agent.target.state_dict().items()})
        tensors["optimizer"] = torch.frombuffer(bytearray(buffer.getvalue()), dtype=torch.uint8)
        tensors["rng.torch"] = torch.get_rng_state()
        if self.replay.priorities is not None:
            tensors["replay.priorities"] = torch.from_numpy(self.replay.priorities.values.copy())
            tensors["replay.max_priority"] = torch.tensor(self.replay.priorities.max_priority,
                                                          dtype=torch.float64)
        return tensors

    def _state_json(self, log_bytes: int) -> dict[str, Any]:
        version, internal, gauss = random.getstate()
        return {
            "episode": self.episode,
            "global_step": self.global_step,
            "updates": self.updates,
            "epsilon_max": self.epsilon_max,
            "epsilon": self.epsilon(),
            "learning_rate": self.agent.optimizer.param_groups[0]["lr"],
            "network": self.agent.shape.to_dict(),
            "world": self.spec.world,
            "seed": self.spec.seed,
            "config": self.config.to_dict(),
            "replay": self.store.state.to_json(),
            "log_bytes": log_bytes,
            "log_sha256": self.episode_log.digest(),
            "recent_success": [bool(s) for s in self.recent_success],
            "evaluation_due": self.evaluation_due,
            "rng": {"python": [version, list(internal), gauss],
                    "numpy": self.rng.bit_generator.state},
        }

    def _restore(self, path: Path, tensors: dict[str, torch.Tensor], state: dict[str, Any]) -> None:
        if state["network"] != self.agent.shape.to_dict():
            raise ckpt.CheckpointCorrupt(f"{path}: network {state['network']} does not match the run's "
                                         f"{self.agent.shape.to_dict()}")
        check_fits(path, tensors, state, self.agent, self.rng,
                   self.config.replay_capacity if self.replay.priorities is not None else None)
        recorded = state.get("log_sha256")
        if recorded is not None and self.episode_log.prefix_digest(state["log_bytes"]) != recorded:
            raise ckpt.CheckpointNotRestorable(
                f"the part of {rd.EPISODES_FILE} it covers ({state['log_bytes']} bytes) was changed since")
        replay_state = ReplayStoreState.from_json(state["replay"])
        try:
            rows = self.store.restore(replay_state, self.config.replay_capacity)
        except ReplayCorrupt as exc:
            # The network, optimizer and counters are intact: keep them, refill the replay.
            self.warn(f"{exc}: resuming from {path.name} with an empty replay buffer (network, optimizer "
                      "and counters are intact; the replay refills as training goes on)")
            rows = self.store.discard(replay_state)
        self.agent.online.load_state_dict(_prefixed(tensors, "online."))
        self.agent.target.load_state_dict(_prefixed(tensors, "target."))
        optimizer_state = torch.load(io.BytesIO(tensors["optimizer"].numpy().tobytes()), weights_only=True)
        self.agent.optimizer.load_state_dict(optimizer_state)
        torch.set_rng_state(tensors["rng.torch"])
        self.replay.restore(rows, state["replay"]["total_rows"])
        if self.replay.priorities is not None and "replay.priorities" in tensors:
            self.replay.priorities.restore(tensors["replay.priorities"].numpy(),
                                           float(tensors["replay.max_priority"]))
        self.episode_log.truncate(state["log_bytes"])
        self.episode = state["episode"]
        self.global_step = state["global_step"]
        self.updates = state["updates"]
        self.epsilon_max = state["epsilon_max"]
        self.recent_success.extend(state["recent_success"])
        self.evaluation_due = bool(state.get("evaluation_due", False))
        drop_evaluations_after(self.run_dir / rd.EVALS_FILE, self.episode)  # flown again from here
        version, internal, gauss = state["rng"]["python"]
        random.setstate((version, tuple(internal), gauss))
        self.rng.bit_generator.state = state["rng"]["numpy"]
        self._kept = []
        for older in sorted(ckpt.list_checkpoints(self.checkpoint_dir)):
            try:
                self._kept.append((older, ckpt.read_state(older)["replay"]["total_rows"]))
            except ckpt.CheckpointCorrupt:
                continue
        log.info("resumed %s from %s (episode %d)", self.run_dir, path.name, self.episode)

    def save_checkpoint(self) -> Path:
        """Checkpoint the state after `self.episode` episodes; prune old checkpoints and shards."""
        path = ckpt.checkpoint_path(self.checkpoint_dir, self.episode)
        ckpt.save_checkpoint(path, self._state_tensors(), self._state_json(self.episode_log.size()))
        self._kept.append((path, self.store.state.total_rows))
        while len(self._kept) > self.config.checkpoints_kept:
            old, _ = self._kept.pop(0)
            old.unlink(missing_ok=True)
        # Keep every replay row that any kept checkpoint could restore.
        self.store.prune(self._kept[0][1] - self.config.replay_capacity)
        return path

    # -- the loop ---------------------------------------------------------------------------
    def epsilon(self) -> float:
        return self.learner.epsilon()

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
                self._log_tensorboard(records)
                exploring = {"epsilon": f"{records[0].epsilon:.3f}"} if self.config.algorithm == "dqn" else {}
                bar.update(self.episode - before, explore_success=f"{self.success_rate():.2f}", **exploring)
                if self.evaluation_due and self._periodic_evaluation(bar):
                    self.stopped_early = True
                    break
                if on_episode is not None and on_episode(records) is False:
                    break
        finally:
            bar.close()
            if self._writer is not None:
                self._writer.flush()
        return TrainResult(self.run_dir, self.episode, self.global_step, self.episode - first_episode,
                           self.global_step - first_step, time.perf_counter() - start, self.success_rate())

    def _periodic_evaluation(self, bar: Progress) -> bool:
        """The greedy evaluation of the state just checkpointed (read back when an earlier
        session finished it) and the constant-action baseline; True when it solves the scenario."""
        result = self.recorded_evaluation() or self.evaluate()
        self.last_eval = result
        baseline = self.constant_baseline()  # measured once per run, then read back
        bar.update(0, greedy=f"{result.success_rate:.0%}", constant_best=f"{baseline.success_rate:.0%}")
        return self.solved(result)

    def recorded_evaluation(self) -> EvalResult | None:
        """The evaluation of the current state that `evals.jsonl` already holds, if any (a
        resumed session does not fly it again)."""
        return recorded_evaluation(self.run_dir / rd.EVALS_FILE, self.episode, self.global_step)

    def solved(self, result: EvalResult) -> bool:
        """A greedy evaluation solves the scenario when it reaches `stop_on_success` and beats
        the best constant-action policy on the same episodes (else nothing was learned)."""
        if not self.config.stop_on_success or result.success_rate < self.config.stop_on_success:
            return False
        return result.success_rate > self.constant_baseline().success_rate

    def constant_baseline(self) -> ConstantBaseline:
        """The best constant-action policy's greedy success on the evaluation episodes, measured
        once per run and kept in the run directory (`baseline.json`)."""
        path = self.run_dir / rd.BASELINE_FILE
        if path.exists():
            with contextlib.suppress(ValueError, KeyError, TypeError):
                return ConstantBaseline(**json.loads(path.read_text()))
        print(baseline_notice(len(constant_actions(self.env)), self.config.eval_episodes), file=sys.stderr)
        baseline = constant_action_baseline(self.env, world=self.spec.world, episodes=self.config.eval_episodes,
                                            seed=self.spec.seed, progress=self.progress, beat=self.beat)
        atomic_write_json(path, baseline.to_dict())
        if self.config.stop_on_success and baseline.success_rate >= self.config.stop_on_success:
            self.warn(f"always choosing action {baseline.action} already succeeds in "
                      f"{baseline.success_rate:.0%} of the evaluation episodes: this scenario needs no "
                      "learning, so training runs its whole budget")
        return baseline

    def evaluate(self, episodes: int | None = None) -> EvalResult:
        """Greedy evaluation of the current network in the training scenario: appended to
        evals.jsonl, written to eval.json (the latest), logged to TensorBoard."""
        episodes = self.config.eval_episodes if episodes is None else episodes
        start, cpu_start = time.perf_counter(), time.process_time()
        result, traces = self._greedy(episodes)
        confirm = self.config.stop_confirm_episodes
        if confirm and self.config.stop_on_success and result.success_rate >= self.config.stop_on_success:
            # 20 episodes at 95 % is one failure from 90 %: a stop (and the best checkpoint)
            # rests on the longer evaluation, which goes on from the episodes just flown.
            result, _ = self._greedy(episodes + confirm, flown=traces)
        record = {**result.to_dict(), "after_episodes": self.episode, "global_step": self.global_step,
                  "wall_time_s": time.perf_counter() - start, "cpu_time_s": time.process_time() - cpu_start}
        atomic_write_json(self.run_dir / rd.EVAL_FILE, record)
        self._keep_if_best(result)
        # Last: the journal's line marks the evaluation done (rl/training/eval_journal.py).
        append_durably(self.run_dir / rd.EVALS_FILE, (json.dumps(record) + "\n").encode())
        if self._writer is not None:
            self._writer.evaluation(self.episode - 1, result)
        self.last_eval = result
        return result

    def greedy_action(self, obs: np.ndarray) -> Any:
        """The current network's deterministic action for one observation."""
        return self.agent.greedy(obs)

    def learning_rate(self) -> float:
        return float(self.agent.optimizer.param_groups[0]["lr"])

    def _greedy(self, episodes: int, flown: Sequence[Trace] = ()) -> tuple[EvalResult, list[Trace]]:
        return evaluate_on(self.env, self.greedy_action,
                           world=self.spec.world, episodes=episodes, seed=self.spec.seed,
                           progress=self.progress, desc="greedy evaluation", flown=flown, beat=self.beat)

    def beat(self, phase: str = TRAINING) -> None:
        """With `heartbeat` on, tell a watchdog the run is alive and what it is doing."""
        if self.heartbeat:
            write_heartbeat(self.run_dir, self.episode, self.global_step, phase)

    def _keep_if_best(self, result: EvalResult) -> None:
        """Copy the checkpoint just evaluated to `best.safetensors` when its greedy success beats
        every earlier evaluation's (ties: the higher mean reward). Later training may forget
        what was learned (the thesis's OR collapsed after solving it); the best stays the
        run's result. Resumes compare against `best.json`."""
        source = ckpt.checkpoint_path(self.checkpoint_dir, self.episode)
        if not source.is_file():  # evaluated before the state was checkpointed: nothing to keep
            return
        best_file = self.run_dir / rd.BEST_FILE
        score = selection_score(result.success_rate, result.drone_episodes, result.mean_reward)
        with contextlib.suppress(OSError, ValueError, KeyError, TypeError):
            best = json.loads(best_file.read_text())
            # best.json of an older version may lack drone_episodes: its episodes then
            trials = best.get("drone_episodes", best.get("episodes", 1))
            if score <= selection_score(best["success_rate"], trials, best["mean_reward"]):
                return
        atomic_write_bytes(self.run_dir / ckpt.BEST_CHECKPOINT, source.read_bytes())
        atomic_write_json(best_file, {**result.to_dict(), "after_episodes": self.episode,
                                      "global_step": self.global_step, "checkpoint": source.name})

    def success_rate(self) -> float:
        return float(np.mean(self.recent_success)) if self.recent_success else 0.0

    def run_episodes(self) -> list[EpisodeRecord]:
        """Fly the next episode (with `num_envs` > 1, the next wave of that many episodes at
        once: rl/training/vector_collect.py), learn from it and persist it; the caller checkpoints."""
        if self.collector is None:
            return self.run_episode()
        return self.collector.run_wave(self.learner, self.spec.seed, self.persist)

    def run_episode(self) -> list[EpisodeRecord]:
        """Fly one training episode with every drone, learn from it, persist it."""
        learner = self.learner
        learner.start_episodes()
        wall_start, cpu_start = time.perf_counter(), time.process_time()
        episode = learner.episode
        env_seed = episode_seed(self.spec.seed, episode)
        epsilon_start = learner.epsilon()
        obs, reset_infos = self.env.reset(env_seed)
        learner.observe(np.stack(list(obs.values())))
        folder = learner.n_step_folder()
        tally = EpisodeTally(self.env.num_drones, reset_infos)
        losses: list[float] = []
        new_rows: list[np.ndarray] = []
        while self.env.live:
            epsilon = learner.epsilon()
            chosen = {i: learner.act(i, obs[i], epsilon) for i in self.env.live}
            if episode < self.config.guided_explore_episodes:
                self._guide(chosen, epsilon)
            result = self.env.step(chosen)
            for i, action in chosen.items():
                tally.add(i, action, result.rewards[i], result.terminated[i], result.truncated[i],
                          result.infos.get(i, {}))
            rows = learner.transition_rows(folder, chosen, obs, result)
            if len(rows):
                learner.remember(rows)
                new_rows.append(rows)
            learner.observe(np.stack([result.obs[i] for i in chosen]))
            obs.update(result.obs)
            learner.after_steps(1, losses)
        learner.end_episodes(1)

        records = tally.records(episode=episode, wall_time_s=time.perf_counter() - wall_start,
                                epsilon=epsilon_start, mean_loss=float(np.mean(losses)) if losses else None,
                                global_step=learner.global_step, env_seed=env_seed,
                                cpu_time_s=time.process_time() - cpu_start)
        self.persist(records, new_rows)
        return records

    def _guide(self, chosen: dict[int, int], epsilon: float) -> None:
        """`guided_explore_episodes`: a share of the exploring steps (probability epsilon times
        `guided_explore_share`) takes the goal-seeking guide's action instead."""
        for i in chosen:
            if self.rng.random() < epsilon * self.config.guided_explore_share:
                chosen[i] = self.env.guided_action(i)

    def persist(self, records: list[EpisodeRecord], new_rows: list[np.ndarray]) -> None:
        """Count finished episodes' successes, then persist their replay rows and then their
        records (the checkpoint naming both lengths comes after)."""
        self.recent_success.extend(r.success for r in records)
        if self.early_end is not None and (warning := self.early_end.add(records)):
            self.warn(warning)
        if new_rows:
            self.store.append(np.concatenate(new_rows))
        self.episode_log.append(records)

    def _log_tensorboard(self, records: list[EpisodeRecord]) -> None:
        if self._writer is None:
            # purge_step drops events a killed session wrote after its last checkpoint.
            self._writer = TensorBoardLog(self.run_dir / rd.TENSORBOARD, purge_step=records[0].episode)
        rate, lr = self.success_rate(), self.learning_rate()
        for episode in sorted({r.episode for r in records}):  # a wave's episodes share its end's rates
            self._writer.episode(episode, [r for r in records if r.episode == episode], rate, lr)

    def close(self) -> None:
        """Close the env(s) and the TensorBoard writer."""
        if self._writer is not None:
            self._writer.close()
            self._writer = None
        (self.collector or self.env).close()

    def __enter__(self) -> Trainer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _refuse_edited_config(run_dir: Path, config: TrainConfig) -> None:
    """A config.yaml edited after the run's checkpoints were written is a ConfigError naming
    each differing key, before anything is restored: the checkpoints are sound, only the file
    changed, so nothing is condemned and putting the values back resumes the run."""
    for path in ckpt.list_checkpoints(run_dir / rd.CHECKPOINTS):
        try:
            recorded = ckpt.read_state(path).get("config")
        except (ckpt.CheckpointCorrupt, OSError, ValueError, AttributeError):
            continue  # the newest readable one speaks for the run; damaged ones fall back later
        differing = rd.config_differences(recorded, config)
        if differing:
            raise ConfigError(f"{run_dir / rd.CONFIG_FILE} differs from the run's checkpoints in: "
                              f"{', '.join(differing)}; put the values back to resume (or start a new run)")
        return


def check_same_algorithm(path: Path, state: dict[str, Any], algorithm: str) -> None:
    """ShapeMismatch when the network a run starts from (`--init-from`) was trained by another
    algorithm than the run's."""
    source = network_algorithm(state["network"])
    if source != algorithm:
        raise ShapeMismatch(f"--init-from {path}: holds a {source} network, but this run trains {algorithm} "
                            "(start from a run of the same algorithm)")


def _prefixed(tensors: dict[str, torch.Tensor], prefix: str) -> dict[str, torch.Tensor]:
    return {k[len(prefix):]: v for k, v in tensors.items() if k.startswith(prefix)}


def _adopt_architecture(config: TrainConfig, network: dict[str, int]) -> TrainConfig:
    """A transferred network keeps its depth and width, whatever this scenario's config says."""
    if (config.layers, config.hidden_units) != (network["layers"], network["hidden_units"]):
        log.warning("init-from network has %d layers x %d units; using that instead of %d x %d",
                    network["layers"], network["hidden_units"], config.layers, config.hidden_units)
        config = config.replace(layers=network["layers"], hidden_units=network["hidden_units"])
    return config


def read_run_records(run_dir: str | Path) -> list[dict]:
    """The episode records of a run directory."""
    return read_records(Path(run_dir) / rd.EPISODES_FILE)
