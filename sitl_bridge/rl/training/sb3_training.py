"""The Stable-Baselines3 side of a run (`Trainer` with `algorithm` ppo, sac or td3): the env, the
`SB3Learner` (rl/learner/sb3_learner.py: SB3's own networks and updates; the drones of a
multi-drone scenario share its one policy, as DQN's drones share one network) and, for SAC and
TD3, its replay shards. The run directory, loop, evaluations, best checkpoint, TensorBoard names
and heartbeat are the same as DQN's; what differs is the learner and what a checkpoint holds:

    checkpoints/ckpt_*.safetensors   policy and optimizer state dicts, PPO's partial rollout,
                                     torch's RNG state; counters and the other RNG states in
                                     its JSON state (no pickle: SB3's `model.save` is not used)
    replay/r*_*.npz                  SAC/TD3: the transitions, one array shard per episode
                                     (`rl/learner/sb3_replay.py`)

so `--resume` after `kill -9` continues exactly where the last checkpoint left off.
"""

from __future__ import annotations

import random
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
from sitl_bridge.rl.training.init_from import ShapeMismatch, check_same_algorithm

Persist = Callable[[list[EpisodeRecord], list[np.ndarray]], None]


class SB3Training:
    """The env, learner and replay shards of an SB3 run, and the episode loop that joins them."""

    store_rows = None
    """SB3 writes its replay shards itself (`run_episode`), not through the run's persist."""

    def __init__(self, run_dir: Path, spec: rd.RunSpec, config: TrainConfig, env_factory: EnvFactory,
                 warn: Callable[[str], None]) -> None:
        if config.num_envs != 1:
            raise ConfigError(f"train.num_envs: {config.algorithm} runs fly one copy at a time (set num_envs 1)")
        self.spec, self.config, self.warn = spec, config, warn
        torch.set_num_threads(config.torch_threads)
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
        self.shards = ReplayShards(Path(run_dir) / rd.REPLAY) if self.learner.off_policy else None

    def close(self) -> None:
        self.env.close()

    # -- flying --------------------------------------------------------------------------------
    def greedy_action(self, obs: np.ndarray) -> Any:
        return self.learner.greedy(obs)

    def learning_rate(self) -> float:
        return self.learner.learning_rate()

    def epsilon(self) -> float:
        return 0.0  # SB3 explores through its own policy (PPO, SAC) or action noise (TD3)

    def run_episodes(self, persist: Persist) -> list[EpisodeRecord]:
        return self.run_episode(persist)

    def run_episode(self, persist: Persist) -> list[EpisodeRecord]:
        """Fly one training episode with every drone (one shared policy), learn from it as SB3
        does, `persist` it."""
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
        persist(records, [])
        return records

    # -- checkpoint contents -------------------------------------------------------------------
    def state_tensors(self) -> dict[str, torch.Tensor]:
        return self.learner.state_tensors()

    def state_json(self) -> dict[str, Any]:
        return {**self.learner.state_json(), "algorithm": self.config.algorithm,
                "learning_rate": self.learning_rate()}

    def check_restorable(self, path: Path, tensors: dict[str, torch.Tensor], state: dict[str, Any]) -> None:
        """CheckpointCorrupt when the checkpoint's network is not this run's."""
        if state.get("network") != self.learner.shape.to_dict():
            raise ckpt.CheckpointCorrupt(f"{path}: network {state.get('network')} does not match the run's "
                                         f"{self.learner.shape.to_dict()}")

    def restore(self, path: Path, tensors: dict[str, torch.Tensor], state: dict[str, Any]) -> None:
        """Policy, optimizer, counters and RNG states, then the replay buffer from its shards."""
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

    def replay_rows(self) -> int:
        """Replay rows written so far (what a checkpoint taken now needs of the shards)."""
        return self.learner.replay_rows

    @staticmethod
    def rows_needed(checkpoint: Path) -> int | None:
        """The replay rows an older checkpoint needs (None: unreadable, so not kept)."""
        try:
            state = ckpt.read_state(checkpoint)
            return int(state.get("replay_rows", state["global_step"]))
        except (ckpt.CheckpointCorrupt, KeyError, TypeError, ValueError):
            return None

    def prune_replay(self, oldest_rows: int) -> None:
        """Keep every replay row that a checkpoint needing `oldest_rows` rows could restore."""
        if self.shards is not None:
            self.shards.prune(oldest_rows - self.learner.model.replay_buffer.buffer_size)

    # -- --init-from ---------------------------------------------------------------------------
    def load_init(self, path: Path, tensors: dict[str, torch.Tensor], state: dict[str, Any]) -> None:
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
