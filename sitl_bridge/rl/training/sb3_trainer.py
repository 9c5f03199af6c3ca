"""A crash-safe training run of a Stable-Baselines3 algorithm (PPO, SAC, TD3) in a run directory.

The same run directory, loop and guarantees as the DQN `Trainer` (this class is one): every
episode reset with its own seed, its records appended to `episodes.jsonl`, then a checkpoint;
periodic greedy evaluations on the held-out seeds into `evals.jsonl`, the best kept as
`best.safetensors`; TensorBoard under the same scalar names; the heartbeat for `--watchdog`.
What differs is the learner (`rl/learner/sb3_learner.py`, SB3's own networks and updates; the
drones of a multi-drone scenario share its one policy, as DQN's drones share one network) and
what a checkpoint holds:

    checkpoints/ckpt_*.safetensors   policy and optimizer state dicts, PPO's partial rollout,
                                     torch's RNG state; counters and the other RNG states in
                                     its JSON state (no pickle: SB3's `model.save` is not used)
    replay/r*_*.npz                  SAC/TD3: the transitions, one array shard per episode
                                     (`rl/learner/sb3_replay.py`)

so `--resume` after `kill -9` continues exactly where the last checkpoint left off.
"""

from __future__ import annotations

import random
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sitl_bridge.errors import ConfigError
from sitl_bridge.rl.common.action_names import logged_action
from sitl_bridge.rl.common.drones_env import DronesEnv, EnvFactory
from sitl_bridge.rl.common.episode_log import EpisodeRecord
from sitl_bridge.rl.evaluation.rollout import episode_seed
from sitl_bridge.rl.learner import checkpoint as ckpt
from sitl_bridge.rl.learner.checkpoint_fit import RESTORE_ERRORS, unfit
from sitl_bridge.rl.learner.config import TrainConfig
from sitl_bridge.rl.learner.sb3_learner import SB3Learner
from sitl_bridge.rl.learner.sb3_models import policy_tensors
from sitl_bridge.rl.learner.sb3_replay import ReplayShardError, ReplayShards
from sitl_bridge.rl.training import run_dir as rd
from sitl_bridge.rl.training.episode_tally import EpisodeTally
from sitl_bridge.rl.training.eval_journal import drop_evaluations_after
from sitl_bridge.rl.training.trainer import ShapeMismatch, Trainer, check_same_algorithm, log


class SB3Trainer(Trainer):
    """Trains one SB3 run; build with `SB3Trainer.start(...)` or `SB3Trainer.resume(...)` (or
    `rl/training/runs.py`, which picks the trainer of the config's algorithm)."""

    def __init__(self, run_dir: Path, spec: rd.RunSpec, config: TrainConfig, env_factory: EnvFactory,
                 *, progress: bool = True, warn: Callable[[str], None] | None = None,
                 heartbeat: bool = False) -> None:
        if config.num_envs != 1:
            raise ConfigError(f"train.num_envs: {config.algorithm} runs fly one copy at a time (set num_envs 1)")
        self.run_dir = Path(run_dir)
        self.heartbeat = heartbeat
        self.spec = spec
        self.config = config
        self.progress = progress
        self.warn = warn or (lambda msg: print(f"warning: {msg}", file=sys.stderr))
        torch.set_num_threads(config.torch_threads)
        self.collector = None
        self.env = DronesEnv(env_factory(spec.seed))
        try:
            random.seed(spec.seed)
            np.random.seed(spec.seed % 2**32)
            torch.manual_seed(spec.seed)
            self.learner = SB3Learner(config.algorithm, self.env.obs_dim, self.env.action_space,
                                      config.sb3_arguments, seed=spec.seed, device=config.device,
                                      num_drones=self.env.num_drones)
        except BaseException:
            self.env.close()
            raise
        self.shards = ReplayShards(self.run_dir / rd.REPLAY) if self.learner.off_policy else None
        self._init_run_state()

    # -- checkpoint contents ---------------------------------------------------------------------
    def _state_tensors(self) -> dict[str, torch.Tensor]:
        return self.learner.state_tensors()

    def _state_json(self, log_bytes: int) -> dict[str, Any]:
        return {**self.learner.state_json(), "algorithm": self.config.algorithm,
                "learning_rate": self.learning_rate(), "world": self.spec.world, "seed": self.spec.seed,
                "config": self.config.to_dict(), "log_bytes": log_bytes,
                "log_sha256": self.episode_log.digest(),
                "recent_success": [bool(s) for s in self.recent_success],
                "evaluation_due": self.evaluation_due}

    def _restore(self, path: Path, tensors: dict[str, torch.Tensor], state: dict[str, Any]) -> None:
        if state.get("network") != self.learner.shape.to_dict():
            raise ckpt.CheckpointCorrupt(f"{path}: network {state.get('network')} does not match the run's "
                                         f"{self.learner.shape.to_dict()}")
        recorded = state.get("log_sha256")
        if recorded is not None and self.episode_log.prefix_digest(state["log_bytes"]) != recorded:
            raise ckpt.CheckpointNotRestorable(
                f"the part of {rd.EPISODES_FILE} it covers ({state['log_bytes']} bytes) was changed since")
        try:
            self.learner.restore(tensors, state)
        except RESTORE_ERRORS as exc:
            raise unfit(path, exc) from None
        if self.shards is not None:
            buffer = self.learner.model.replay_buffer
            try:
                self.shards.restore(buffer, self.learner.replay_rows)
            except ReplayShardError as exc:
                buffer.pos, buffer.full = 0, False
                self.warn(f"{exc}: resuming from {path.name} with an empty replay buffer (networks, optimizers "
                          "and counters are intact; the replay refills as training goes on)")
            self.shards.prune(0, written_up_to=self.learner.replay_rows)  # episodes never checkpointed
        self.episode_log.truncate(state["log_bytes"])
        self.recent_success.extend(state["recent_success"])
        self.evaluation_due = bool(state.get("evaluation_due", False))
        drop_evaluations_after(self.run_dir / rd.EVALS_FILE, self.episode)
        self._kept = []
        for older in sorted(ckpt.list_checkpoints(self.checkpoint_dir)):
            try:
                older_state = ckpt.read_state(older)
                self._kept.append((older, int(older_state.get("replay_rows", older_state["global_step"]))))
            except (ckpt.CheckpointCorrupt, KeyError, TypeError, ValueError):
                continue
        log.info("resumed %s from %s (episode %d)", self.run_dir, path.name, self.episode)

    def save_checkpoint(self) -> Path:
        """Checkpoint the state after `self.episode` episodes; prune old checkpoints and shards."""
        path = ckpt.checkpoint_path(self.checkpoint_dir, self.episode)
        ckpt.save_checkpoint(path, self._state_tensors(), self._state_json(self.episode_log.size()))
        self._kept.append((path, self.learner.replay_rows))
        while len(self._kept) > self.config.checkpoints_kept:
            old, _ = self._kept.pop(0)
            old.unlink(missing_ok=True)
        if self.shards is not None:  # keep every row the oldest kept checkpoint could restore
            self.shards.prune(self._kept[0][1] - self.learner.model.replay_buffer.buffer_size)
        return path

    def _load_init(self, path: Path, tensors: dict[str, torch.Tensor], state: dict[str, Any]) -> None:
        """Start from another run's policy (`--init-from`): same algorithm, same spaces."""
        check_same_algorithm(path, state, self.config.algorithm)
        mine = self.learner.shape.to_dict()
        theirs = state["network"]
        differing = [k for k in ("obs_dim", "n_actions", "action_dim", "policy_kwargs", "use_sde")
                     if theirs.get(k) != mine.get(k)]
        if differing:
            raise ShapeMismatch(f"--init-from {path}: its network differs from what {self.spec.world} needs in "
                                + ", ".join(f"{k} ({theirs.get(k)!r}, here {mine.get(k)!r})" for k in differing))
        self.learner.model.policy.load_state_dict(policy_tensors(tensors))

    # -- the loop ----------------------------------------------------------------------------------
    def greedy_action(self, obs: np.ndarray) -> Any:
        return self.learner.greedy(obs)

    def learning_rate(self) -> float:
        return self.learner.learning_rate()

    def epsilon(self) -> float:
        return 0.0  # SB3 explores through its own policy (PPO, SAC) or action noise (TD3)

    def run_episodes(self) -> list[EpisodeRecord]:
        return self.run_episode()

    def run_episode(self) -> list[EpisodeRecord]:
        """Fly one training episode with every drone (one shared policy), learn from it as SB3
        does, persist it."""
        learner = self.learner
        wall_start, cpu_start = time.perf_counter(), time.process_time()
        episode, first_row = learner.episode, learner.replay_rows
        env_seed = episode_seed(self.spec.seed, episode)
        obs, reset_infos = self.env.reset(env_seed)
        learner.start_episode(obs)
        tally = EpisodeTally(self.env.num_drones, reset_infos)
        while self.env.live:
            drones = list(self.env.live)
            chosen = learner.act(drones)
            result = self.env.step(chosen)
            for i, action in chosen.items():
                tally.add(i, logged_action(action), result.rewards[i], result.terminated[i], result.truncated[i],
                          result.infos.get(i, {}))
            learner.step(drones, result.rewards, result.obs, result.terminated, result.truncated)
            obs.update(result.obs)
        learner.end_episode()
        records = tally.records(episode=episode, wall_time_s=time.perf_counter() - wall_start, epsilon=0.0,
                                mean_loss=float(np.mean(learner.losses)) if learner.losses else None,
                                global_step=learner.global_step, env_seed=env_seed,
                                cpu_time_s=time.process_time() - cpu_start)
        if self.shards is not None:
            self.shards.append(learner.model.replay_buffer, first_row, learner.replay_rows)
        self.persist(records, [])
        return records
