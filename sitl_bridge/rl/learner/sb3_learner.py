"""An SB3 algorithm driven one env step at a time, so a run checkpoints between episodes.

SB3's `learn()` owns the env loop and can only be interrupted at its rollout boundaries; a run
directory checkpoints after every episode (the only moment the simulator's state need not be
saved). So the trainer flies each episode itself and this class does, step by step, what SB3's
`collect_rollouts` does with the model's own parts:

- PPO: `policy(obs)` -> action, value, log-prob into SB3's RolloutBuffer (a time-limit end
  bootstraps with the value of the last observation, as SB3 does); when the buffer is full,
  `compute_returns_and_advantage` and the model's own `train()`.
- SAC/TD3: the model's `_sample_action` (uniform before learning_starts, action noise for
  TD3), the transition into SB3's ReplayBuffer, `train(gradient_steps, batch_size)` every
  train_freq steps (or episodes) once learning_starts transitions are collected.

Several drones share one policy (parameter sharing, as the DQN side does): every live drone's
observation goes through it and each drone's transitions feed the one buffer. SAC/TD3 add one
replay row per drone-step. PPO keeps each drone's trajectory as its own stream, column i of a
RolloutBuffer with n_envs = drones (SB3's layout for parallel envs), each column filled at its
own pace because a drone that finished its episode stops contributing until the next one. When
a column is full (n_steps rows), the columns' rows are laid end to end in a one-env
RolloutBuffer for SB3's GAE and `train()`: each column's first row is marked an episode start
so no advantage runs across streams, and a column whose drone is still flying bootstraps its
last reward with the value of the drone's next observation, which is exactly what SB3 does with
`last_values` at the end of a rollout. With one drone this is SB3's rollout, step for step.

Its state between episodes is tensors (`state_tensors`) and JSON (`state_json`): the model's
networks and optimizers, the partial rollout (PPO), counters and RNG states; the replay
(SAC/TD3) is saved per episode by `rl/learner/sb3_replay.py`.
"""

from __future__ import annotations

import random
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from sitl_bridge.rl.learner.sb3_models import (
    OFF_POLICY,
    SB3Network,
    SB3Shape,
    build_model,
    load_model_tensors,
    model_tensors,
)

ROLLOUT_FIELDS = ("observations", "actions", "rewards", "episode_starts", "values", "log_probs")


class SB3Learner:
    """One SB3 model fed by the trainer's episode loop, shared by `num_drones` drones."""

    def __init__(self, algorithm: str, obs_dim: int, action_space: gym.Space, arguments: dict[str, Any],
                 *, seed: int, device: torch.device | str = "cpu", num_drones: int = 1) -> None:
        self.shape = SB3Shape.of(algorithm, obs_dim, action_space, arguments)
        self.model = build_model(self.shape, arguments, seed=seed, device=device)
        self.network = SB3Network(self.shape, self.model.policy)
        self.off_policy = algorithm in OFF_POLICY
        self.num_drones = num_drones
        self.episode = 0
        self.global_step = 0
        """Env steps (all drones acting at once count one), as the DQN learner counts them."""
        self.replay_rows = 0
        """SAC/TD3: transitions added to the replay (one per drone-step); SB3's `num_timesteps`."""
        self.updates = 0
        """Calls of the model's `train()`."""
        self.steps_since_train = 0
        self.episodes_since_train = 0
        self.rows_since_train = 0
        """SAC/TD3: replay rows added since the last `train()` (what gradient_steps -1 trains on)."""
        self._obs: dict[int, np.ndarray] = {}
        self._episode_start: dict[int, bool] = {}
        self._pending: dict[int, tuple[Any, ...]] = {}
        self.losses: list[float] = []
        """Losses of this episode's `train()` calls."""
        if not self.off_policy:
            model = self.model
            model.rollout_buffer = model.rollout_buffer_class(
                model.n_steps, model.observation_space, model.action_space, device=model.device,
                gamma=model.gamma, gae_lambda=model.gae_lambda, n_envs=num_drones)
            self.rollout_pos = [0] * num_drones
            """PPO: rows filled in each drone's column of the rollout buffer."""

    # -- acting and learning -------------------------------------------------------------------
    def start_episode(self, obs: dict[int, np.ndarray]) -> None:
        """A new episode starts with these drones' observations (drone index -> observation)."""
        self._obs = {i: np.asarray(o, dtype=np.float32).reshape(1, -1) for i, o in obs.items()}
        self._episode_start = dict.fromkeys(obs, True)
        self.losses = []

    def act(self, drones: list[int]) -> dict[int, Any]:
        """The exploring action of each of `drones` for the observation `start_episode` or `step`
        left it, as the env takes it (int for Discrete, array for Box)."""
        model = self.model
        if self.off_policy:
            chosen = {}
            for i in drones:  # one at a time: each drone its own warm-up sample and action noise
                model._last_obs = self._obs[i]
                model.num_timesteps = self.replay_rows
                action, buffer_action = model._sample_action(model.learning_starts, model.action_noise, 1)
                self._pending[i] = (buffer_action,)
                chosen[i] = np.asarray(action[0], dtype=np.float32)
            return chosen
        batch = np.concatenate([self._obs[i] for i in drones])
        with torch.no_grad():
            actions, values, log_probs = model.policy(model.policy.obs_to_tensor(batch)[0])
        actions = actions.cpu().numpy()
        chosen = {}
        for k, i in enumerate(drones):
            self._pending[i] = (actions[k], values[k], log_probs[k])
            chosen[i] = (np.clip(actions[k], model.action_space.low, model.action_space.high).astype(np.float32)
                         if self.shape.continuous else int(actions[k]))
        return chosen

    def step(self, drones: list[int], rewards: dict[int, float], next_obs: dict[int, np.ndarray],
             terminated: dict[int, bool], truncated: dict[int, bool]) -> None:
        """The outcome of the actions `act` gave `drones` (one env step): store it, train when
        SB3 would."""
        self.global_step += 1
        self.steps_since_train += 1
        for i in drones:
            following = np.asarray(next_obs[i], dtype=np.float32).reshape(1, -1)
            if self.off_policy:
                self._store_transition(i, rewards[i], following, terminated[i], truncated[i])
            else:
                self._add_rollout_row(i, rewards[i], following, terminated[i], truncated[i])
            self._obs[i] = following
            self._episode_start[i] = False
            if terminated[i] or truncated[i]:
                del self._obs[i]  # this drone's episode is over: it stops contributing
        if self.off_policy:
            self._train_off_policy(episode_ended=False)
        elif max(self.rollout_pos) >= self.model.n_steps:
            self._train_on_policy()

    def end_episode(self) -> None:
        self.episode += 1
        self.episodes_since_train += 1
        if self.off_policy:
            self._train_off_policy(episode_ended=True)

    def _add_rollout_row(self, drone: int, reward: float, next_obs: np.ndarray, terminated: bool,
                         truncated: bool) -> None:
        """One row of `drone`'s column (what SB3's `RolloutBuffer.add` writes for one env)."""
        model = self.model
        action, value, log_prob = self._pending.pop(drone)
        if truncated and not terminated:
            # A time limit, not a real end: bootstrap with the last observation's value (SB3 does the same).
            reward += model.gamma * self._value(next_obs)
        buffer, row = model.rollout_buffer, self.rollout_pos[drone]
        buffer.observations[row, drone] = self._obs[drone][0]
        buffer.actions[row, drone] = np.asarray(action).reshape(buffer.action_dim)
        buffer.rewards[row, drone] = reward
        buffer.episode_starts[row, drone] = self._episode_start[drone]
        buffer.values[row, drone] = float(value.reshape(-1)[0])
        buffer.log_probs[row, drone] = float(log_prob.reshape(-1)[0])
        self.rollout_pos[drone] = row + 1

    def _value(self, obs: np.ndarray) -> float:
        with torch.no_grad():
            return float(self.model.policy.predict_values(self.model.policy.obs_to_tensor(obs)[0])[0])

    def _train_on_policy(self) -> None:
        """SB3's GAE and `train()` on the drones' streams laid end to end, then an empty rollout."""
        from stable_baselines3.common.buffers import RolloutBuffer

        model, columns = self.model, self.model.rollout_buffer
        drones = [i for i in range(self.num_drones) if self.rollout_pos[i]]
        rows = sum(self.rollout_pos)
        streams = RolloutBuffer(rows, model.observation_space, model.action_space, device=model.device,
                                gamma=model.gamma, gae_lambda=model.gae_lambda, n_envs=1)
        for name in ROLLOUT_FIELDS:
            laid = np.concatenate([getattr(columns, name)[:self.rollout_pos[i], i] for i in drones])
            getattr(streams, name)[:] = laid.reshape(getattr(streams, name).shape)
        first = 0
        for i in drones:
            last = first + self.rollout_pos[i] - 1
            streams.episode_starts[first] = 1.0  # no advantage runs from one drone's stream into another's
            if i in self._obs:  # still flying: the rollout ends mid-episode, as SB3's last_values does
                streams.rewards[last] += model.gamma * self._value(self._obs[i])
            first = last + 1
        streams.pos, streams.full = rows, True
        streams.compute_returns_and_advantage(last_values=torch.zeros(1), dones=np.ones(1, dtype=bool))
        model.rollout_buffer = streams
        try:
            self._train(lambda: model.train())
        finally:
            model.rollout_buffer = columns
        columns.reset()
        self.rollout_pos = [0] * self.num_drones

    def _store_transition(self, drone: int, reward: float, next_obs: np.ndarray, terminated: bool,
                          truncated: bool) -> None:
        (buffer_action,) = self._pending.pop(drone)
        self.model.replay_buffer.add(self._obs[drone], next_obs, buffer_action, np.array([reward], dtype=np.float32),
                                     np.array([terminated or truncated]),
                                     [{"TimeLimit.truncated": truncated and not terminated}])
        self.replay_rows += 1
        self.rows_since_train += 1

    def _train_off_policy(self, *, episode_ended: bool) -> None:
        from stable_baselines3.common.type_aliases import TrainFrequencyUnit

        model = self.model
        frequency = model.train_freq
        if frequency.unit == TrainFrequencyUnit.STEP:
            due = not episode_ended and self.steps_since_train >= frequency.frequency
        else:
            due = episode_ended and self.episodes_since_train >= frequency.frequency
        if not due:
            return
        collected = self.rows_since_train
        self.steps_since_train = self.episodes_since_train = self.rows_since_train = 0
        if self.replay_rows > model.learning_starts:
            # gradient_steps -1: as many as transitions collected, as SB3 counts them with n_envs
            gradient_steps = model.gradient_steps if model.gradient_steps >= 0 else collected
            if gradient_steps > 0:
                model.num_timesteps = self.replay_rows
                self._train(lambda: model.train(gradient_steps=gradient_steps, batch_size=model.batch_size))

    def _train(self, train: Any) -> None:
        train()
        self.model.policy.set_training_mode(False)
        self.updates += 1
        values = self.model.logger.name_to_value
        loss = values.get("train/loss", values.get("train/critic_loss"))
        if loss is not None:
            self.losses.append(float(loss))

    # -- greedy policy --------------------------------------------------------------------------
    def greedy(self, obs: np.ndarray) -> Any:
        """The deterministic action for one observation (int or array, as `act`)."""
        with torch.no_grad():
            scores = self.network(torch.as_tensor(np.asarray(obs, dtype=np.float32).reshape(1, -1)))[0].numpy()
        return scores.astype(np.float32) if self.shape.continuous else int(np.argmax(scores))

    def learning_rate(self) -> float:
        optimizer = self.model.policy.optimizer if not self.off_policy else self.model.actor.optimizer
        return float(optimizer.param_groups[0]["lr"])

    # -- state ----------------------------------------------------------------------------------
    def state_tensors(self) -> dict[str, torch.Tensor]:
        """Networks, optimizers, the partial rollout (PPO: rows x drones) and torch's RNG state."""
        tensors = model_tensors(self.model)
        if not self.off_policy:
            buffer, filled = self.model.rollout_buffer, max(self.rollout_pos)
            for name in ROLLOUT_FIELDS:
                tensors[f"rollout.{name}"] = torch.from_numpy(np.ascontiguousarray(getattr(buffer, name)[:filled]))
        tensors["rng.torch"] = torch.get_rng_state()
        return tensors

    def state_json(self) -> dict[str, Any]:
        """Counters and RNG states (Python, NumPy's global one SB3 samples minibatches and noise
        with, the action space's own for SAC/TD3's warm-up)."""
        version, internal, gauss = random.getstate()
        kind, keys, pos, has_gauss, cached = np.random.get_state()
        state: dict[str, Any] = {
            "episode": self.episode, "global_step": self.global_step, "updates": self.updates,
            "steps_since_train": self.steps_since_train, "episodes_since_train": self.episodes_since_train,
            "sb3_n_updates": int(self.model._n_updates),  # TD3 delays its actor updates by this count
            "network": self.shape.to_dict(),
            "rng": {"python": [version, list(internal), gauss],
                    "numpy_global": [kind, [int(k) for k in keys], int(pos), int(has_gauss), float(cached)],
                    "action_space": self.model.action_space.np_random.bit_generator.state},
        }
        if self.off_policy:
            state.update(replay_rows=self.replay_rows, rows_since_train=self.rows_since_train)
        else:
            state["rollout_pos"] = list(self.rollout_pos)
        return state

    def restore(self, tensors: dict[str, torch.Tensor], state: dict[str, Any]) -> None:
        """Put a checkpoint's state back (the replay: `restore_replay`)."""
        load_model_tensors(self.model, tensors)
        if not self.off_policy:
            positions = state["rollout_pos"]
            positions = [int(p) for p in (positions if isinstance(positions, list) else [positions])]
            if len(positions) != self.num_drones:
                raise ValueError(f"its rollout has {len(positions)} drone columns, the scenario {self.num_drones} drones")
            buffer = self.model.rollout_buffer
            buffer.reset()
            filled = max(positions)
            for name in ROLLOUT_FIELDS:
                getattr(buffer, name)[:filled] = tensors[f"rollout.{name}"].numpy()
            self.rollout_pos = positions
        torch.set_rng_state(tensors["rng.torch"])
        for name in ("episode", "global_step", "updates", "steps_since_train", "episodes_since_train"):
            setattr(self, name, int(state[name]))
        # single-drone checkpoints of earlier versions: one replay row per env step
        self.replay_rows = int(state.get("replay_rows", self.global_step))
        self.rows_since_train = int(state.get("rows_since_train", self.steps_since_train))
        self.model.num_timesteps = self.replay_rows if self.off_policy else self.global_step
        self.model._n_updates = int(state["sb3_n_updates"])
        version, internal, gauss = state["rng"]["python"]
        random.setstate((version, tuple(internal), gauss))
        kind, keys, pos, has_gauss, cached = state["rng"]["numpy_global"]
        np.random.set_state((kind, np.array(keys, dtype=np.uint32), pos, has_gauss, cached))
        self.model.action_space.np_random.bit_generator.state = state["rng"]["action_space"]
