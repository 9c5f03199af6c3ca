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
  train_freq steps (or episodes) once learning_starts steps are collected.

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
    """One SB3 model fed by the trainer's episode loop (single drone)."""

    def __init__(self, algorithm: str, obs_dim: int, action_space: gym.Space, arguments: dict[str, Any],
                 *, seed: int, device: torch.device | str = "cpu") -> None:
        self.shape = SB3Shape.of(algorithm, obs_dim, action_space, arguments)
        self.model = build_model(self.shape, arguments, seed=seed, device=device)
        self.network = SB3Network(self.shape, self.model.policy)
        self.off_policy = algorithm in OFF_POLICY
        self.episode = 0
        self.global_step = 0
        self.updates = 0
        """Calls of the model's `train()`."""
        self.steps_since_train = 0
        self.episodes_since_train = 0
        self._obs: np.ndarray | None = None
        self._episode_start = True
        self._pending: tuple[Any, ...] = ()
        self.losses: list[float] = []
        """Losses of this episode's `train()` calls."""

    # -- acting and learning -------------------------------------------------------------------
    def start_episode(self, obs: np.ndarray) -> None:
        self._obs = np.asarray(obs, dtype=np.float32).reshape(1, -1)
        self._episode_start = True
        self.losses = []

    def act(self, obs: np.ndarray) -> Any:
        """The exploring action for `obs` (the observation `start_episode` or `step` left),
        as the env takes it (int for Discrete, array for Box)."""
        model = self.model
        if self.off_policy:
            model._last_obs = self._obs
            model.num_timesteps = self.global_step
            action, buffer_action = model._sample_action(model.learning_starts, model.action_noise, 1)
            self._pending = (buffer_action,)
            return np.asarray(action[0], dtype=np.float32)
        with torch.no_grad():
            actions, values, log_probs = model.policy(model.policy.obs_to_tensor(self._obs)[0])
        actions = actions.cpu().numpy()
        self._pending = (actions, values, log_probs)
        if self.shape.continuous:
            return np.clip(actions[0], model.action_space.low, model.action_space.high).astype(np.float32)
        return int(actions[0])

    def step(self, reward: float, next_obs: np.ndarray, terminated: bool, truncated: bool) -> None:
        """The outcome of the action `act` gave: store it, train when SB3 would."""
        next_obs = np.asarray(next_obs, dtype=np.float32).reshape(1, -1)
        self.global_step += 1
        self.steps_since_train += 1
        if self.off_policy:
            self._store_transition(reward, next_obs, terminated, truncated)
        else:
            self._add_rollout_step(reward, next_obs, terminated, truncated)
        self._obs = next_obs
        self._episode_start = False

    def end_episode(self) -> None:
        self.episode += 1
        self.episodes_since_train += 1
        if self.off_policy:
            self._train_off_policy(episode_ended=True)

    def _add_rollout_step(self, reward: float, next_obs: np.ndarray, terminated: bool, truncated: bool) -> None:
        model = self.model
        actions, values, log_probs = self._pending
        if truncated and not terminated:
            # A time limit, not a real end: bootstrap with the last observation's value (SB3 does the same).
            with torch.no_grad():
                reward += model.gamma * float(model.policy.predict_values(model.policy.obs_to_tensor(next_obs)[0])[0])
        if not self.shape.continuous:
            actions = actions.reshape(-1, 1)
        buffer = model.rollout_buffer
        buffer.add(self._obs, actions, np.array([reward], dtype=np.float32), np.array([self._episode_start]),
                   values, log_probs)
        if buffer.full:
            done = terminated or truncated
            with torch.no_grad():
                last_values = model.policy.predict_values(model.policy.obs_to_tensor(next_obs)[0])
            buffer.compute_returns_and_advantage(last_values=last_values, dones=np.array([done]))
            self._train(lambda: model.train())
            buffer.reset()

    def _store_transition(self, reward: float, next_obs: np.ndarray, terminated: bool, truncated: bool) -> None:
        (buffer_action,) = self._pending
        self.model.replay_buffer.add(self._obs, next_obs, buffer_action, np.array([reward], dtype=np.float32),
                                     np.array([terminated or truncated]),
                                     [{"TimeLimit.truncated": truncated and not terminated}])
        self._train_off_policy(episode_ended=False)

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
        collected = self.steps_since_train
        self.steps_since_train = self.episodes_since_train = 0
        if self.global_step > model.learning_starts:
            gradient_steps = model.gradient_steps if model.gradient_steps >= 0 else collected
            if gradient_steps > 0:
                model.num_timesteps = self.global_step
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
        """Networks, optimizers, the partial rollout (PPO) and torch's RNG state."""
        tensors = model_tensors(self.model)
        if not self.off_policy:
            buffer = self.model.rollout_buffer
            for name in ROLLOUT_FIELDS:
                tensors[f"rollout.{name}"] = torch.from_numpy(np.ascontiguousarray(getattr(buffer, name)[:buffer.pos]))
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
        if not self.off_policy:
            state["rollout_pos"] = int(self.model.rollout_buffer.pos)
        return state

    def restore(self, tensors: dict[str, torch.Tensor], state: dict[str, Any]) -> None:
        """Put a checkpoint's state back (the replay: `restore_replay`)."""
        load_model_tensors(self.model, tensors)
        if not self.off_policy:
            buffer = self.model.rollout_buffer
            buffer.reset()
            pos = int(state["rollout_pos"])
            for name in ROLLOUT_FIELDS:
                getattr(buffer, name)[:pos] = tensors[f"rollout.{name}"].numpy()
            buffer.pos = pos
        torch.set_rng_state(tensors["rng.torch"])
        for name in ("episode", "global_step", "updates", "steps_since_train", "episodes_since_train"):
            setattr(self, name, int(state[name]))
        self.model.num_timesteps = self.global_step
        self.model._n_updates = int(state["sb3_n_updates"])
        version, internal, gauss = state["rng"]["python"]
        random.setstate((version, tuple(internal), gauss))
        kind, keys, pos, has_gauss, cached = state["rng"]["numpy_global"]
        np.random.set_state((kind, np.array(keys, dtype=np.uint32), pos, has_gauss, cached))
        self.model.action_space.np_random.bit_generator.state = state["rng"]["action_space"]
