"""The DQN side of a run (`Trainer` with `algorithm: dqn`): the env (or N copies), the
`DQNLearner` and its replay shards; the single-env episode loop (the N-copy waves are
rl/training/vector_collect.py's); what a checkpoint holds of them and how it is restored;
starting from another run's network (`--init-from`)."""

from __future__ import annotations

import io
import random
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sitl_bridge.errors import ConfigError
from sitl_bridge.rl.common.drones_env import DronesEnv, EnvFactory
from sitl_bridge.rl.common.episode_log import EpisodeRecord
from sitl_bridge.rl.evaluation.rollout import episode_seed
from sitl_bridge.rl.learner import checkpoint as ckpt
from sitl_bridge.rl.learner.checkpoint_fit import check_fits
from sitl_bridge.rl.learner.config import TrainConfig
from sitl_bridge.rl.learner.dqn import NetworkShape
from sitl_bridge.rl.learner.dqn_learner import DQNLearner
from sitl_bridge.rl.learner.replay_store import ReplayCorrupt, ReplayStore, ReplayStoreState
from sitl_bridge.rl.learner.torch_threads import use_torch_threads
from sitl_bridge.rl.training import run_dir as rd
from sitl_bridge.rl.training.episode_tally import EpisodeTally
from sitl_bridge.rl.training.init_from import ShapeMismatch, adopt_replay, check_same_algorithm
from sitl_bridge.rl.training.vector_collect import VectorCollector

Persist = Callable[[list[EpisodeRecord], list[np.ndarray]], None]


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


class DQNTraining:
    """The env(s), learner and replay shards of a DQN run, and the episode loop that joins them."""

    def __init__(self, run_dir: Path, spec: rd.RunSpec, config: TrainConfig, env_factory: EnvFactory,
                 warn: Callable[[str], None]) -> None:
        self.spec, self.config, self.warn = spec, config, warn
        use_torch_threads(config.torch_threads)
        self.device = resolve_device(config.device)
        self.collector: VectorCollector | None = None
        if config.num_envs > 1:
            self.collector = VectorCollector(env_factory, spec.seed, config.num_envs)
            self.env = self.collector.copies[0]  # evaluations fly copy 0 between waves
        else:
            self.env = DronesEnv(env_factory(spec.seed))
        if self.env.continuous:
            self.close()
            raise ConfigError(f"{spec.world}: dqn needs discrete actions and this scenario's are continuous "
                              f"({self.env.action_space}); train it with --algorithm ppo, sac or td3")
        # Seed everything before the network exists, so its initial weights are reproducible.
        random.seed(spec.seed)
        torch.manual_seed(spec.seed)
        self.rng = np.random.default_rng(spec.seed)
        shape = NetworkShape(self.env.obs_dim, self.env.n_actions, config.layers, config.hidden_units,
                             dueling=config.dueling, normalize=config.normalize_observations)
        self.learner = DQNLearner(shape, config, self.device, self.rng)
        self.agent = self.learner.agent
        self.store = ReplayStore(Path(run_dir) / rd.REPLAY, shape.obs_dim, config.replay_segment_rows)

    def close(self) -> None:
        (self.collector or self.env).close()

    # -- flying --------------------------------------------------------------------------------
    def greedy_action(self, obs: np.ndarray) -> Any:
        """The current network's deterministic action for one observation."""
        return self.agent.greedy(obs)

    def learning_rate(self) -> float:
        return float(self.agent.optimizer.param_groups[0]["lr"])

    def epsilon(self) -> float:
        return self.learner.epsilon()

    def run_episodes(self, persist: Persist) -> list[EpisodeRecord]:
        """Fly the next episode (with `num_envs` > 1, the next wave of that many episodes at
        once: rl/training/vector_collect.py), learn from it and `persist` it."""
        if self.collector is None:
            return self.run_episode(persist)
        return self.collector.run_wave(self.learner, self.spec.seed, persist)

    def run_episode(self, persist: Persist) -> list[EpisodeRecord]:
        """Fly one training episode with every drone, learn from it, `persist` it."""
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
        persist(records, new_rows)
        return records

    def _guide(self, chosen: dict[int, int], epsilon: float) -> None:
        """`guided_explore_episodes`: a share of the exploring steps (probability epsilon times
        `guided_explore_share`) takes the goal-seeking guide's action instead."""
        for i in chosen:
            if self.rng.random() < epsilon * self.config.guided_explore_share:
                chosen[i] = self.env.guided_action(i)

    def store_rows(self, rows: np.ndarray) -> None:
        """Append a finished episode's transitions to the replay shards."""
        self.store.append(rows)

    # -- checkpoint contents (the explicit save list) ------------------------------------------
    def state_tensors(self) -> dict[str, torch.Tensor]:
        buffer = io.BytesIO()
        torch.save(self.agent.optimizer.state_dict(), buffer)
        tensors = {f"online.{k}": v for k, v in self.agent.online.state_dict().items()}
        tensors.update({f"target.{k}": v for k, v in self.agent.target.state_dict().items()})
        tensors["optimizer"] = torch.frombuffer(bytearray(buffer.getvalue()), dtype=torch.uint8)
        tensors["rng.torch"] = torch.get_rng_state()
        replay = self.learner.replay
        if replay.priorities is not None:
            tensors["replay.priorities"] = torch.from_numpy(replay.priorities.values.copy())
            tensors["replay.max_priority"] = torch.tensor(replay.priorities.max_priority, dtype=torch.float64)
        return tensors

    def state_json(self) -> dict[str, Any]:
        learner = self.learner
        version, internal, gauss = random.getstate()
        return {
            "episode": learner.episode,
            "global_step": learner.global_step,
            "updates": learner.updates,
            "epsilon_max": learner.epsilon_max,
            "epsilon": learner.epsilon(),
            "learning_rate": self.agent.optimizer.param_groups[0]["lr"],
            "network": self.agent.shape.to_dict(),
            "replay": self.store.state.to_json(),
            "rng": {"python": [version, list(internal), gauss],
                    "numpy": self.rng.bit_generator.state},
        }

    def check_restorable(self, path: Path, tensors: dict[str, torch.Tensor], state: dict[str, Any]) -> None:
        """CheckpointCorrupt when the checkpoint's network or tensors do not fit this run."""
        if state["network"] != self.agent.shape.to_dict():
            raise ckpt.CheckpointCorrupt(f"{path}: network {state['network']} does not match the run's "
                                         f"{self.agent.shape.to_dict()}")
        check_fits(path, tensors, state, self.agent, self.rng,
                   self.config.replay_capacity if self.learner.replay.priorities is not None else None)

    def restore(self, path: Path, tensors: dict[str, torch.Tensor], state: dict[str, Any]) -> None:
        """Replay, network, optimizer, counters and RNG states from a checkpoint that fits."""
        learner, replay = self.learner, self.learner.replay
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
        replay.restore(rows, state["replay"]["total_rows"])
        if replay.priorities is not None and "replay.priorities" in tensors:
            replay.priorities.restore(tensors["replay.priorities"].numpy(), float(tensors["replay.max_priority"]))
        learner.episode = state["episode"]
        learner.global_step = state["global_step"]
        learner.updates = state["updates"]
        learner.epsilon_max = state["epsilon_max"]
        version, internal, gauss = state["rng"]["python"]
        random.setstate((version, tuple(internal), gauss))
        self.rng.bit_generator.state = state["rng"]["numpy"]

    def replay_rows(self) -> int:
        """Replay rows written so far (what a checkpoint taken now needs of the shards)."""
        return self.store.state.total_rows

    @staticmethod
    def rows_needed(checkpoint: Path) -> int | None:
        """The replay rows an older checkpoint needs (None: unreadable, so not kept)."""
        try:
            return ckpt.read_state(checkpoint)["replay"]["total_rows"]
        except ckpt.CheckpointCorrupt:
            return None

    def prune_replay(self, oldest_rows: int) -> None:
        """Keep every replay row that a checkpoint needing `oldest_rows` rows could restore."""
        self.store.prune(oldest_rows - self.config.replay_capacity)

    # -- --init-from ---------------------------------------------------------------------------
    def load_init(self, path: Path, tensors: dict[str, torch.Tensor], state: dict[str, Any]) -> None:
        """Start from another run's network (and with `transfer_replay`, its transitions)."""
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
        self.learner.epsilon_max = self.config.transfer_epsilon_max
        if self.config.transfer_replay:
            adopt_replay(path, self.learner.replay, self.store, self.config.replay_capacity)


def _prefixed(tensors: dict[str, torch.Tensor], prefix: str) -> dict[str, torch.Tensor]:
    return {k[len(prefix):]: v for k, v in tensors.items() if k.startswith(prefix)}
