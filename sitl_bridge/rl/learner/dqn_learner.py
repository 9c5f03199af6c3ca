"""The DQN learner that both training loops drive: the single-env episode loop
(`Trainer.run_episode`) and the wave loop of N copies (`VectorCollector.run_wave`).

It owns what learning needs and nothing of the run around it (run directory, checkpoints files,
episode log, evaluations): the network pair (`DQNAgent`), ez-greedy exploration, the replay
buffer (uniform or prioritized, n-step folding), the run's random generator and the counters the
schedules follow (episodes, env steps, gradient updates). A loop calls, per episode or wave:
`start_episodes`, then per env step `act`/`act_batch`, `transition_rows` + `remember`,
`observe`, `after_steps`; and at the end `end_episodes`. Another learning algorithm is another
class with these methods.
"""

from __future__ import annotations

import numpy as np
import torch

from sitl_bridge.rl.common.drones_env import StepResult
from sitl_bridge.rl.learner.config import TrainConfig
from sitl_bridge.rl.learner.dqn import DQNAgent, NetworkShape, epsilon_at, learning_rate_at
from sitl_bridge.rl.learner.exploration import RepeatedExploration
from sitl_bridge.rl.learner.nstep import NStepFolder, Step
from sitl_bridge.rl.learner.prioritized import Priorities
from sitl_bridge.rl.learner.replay_buffer import ReplayBuffer


class DQNLearner:
    """DQN with its replay and schedules; the loops that fly episodes drive it (module docstring)."""

    def __init__(self, shape: NetworkShape, config: TrainConfig, device: torch.device,
                 rng: np.random.Generator) -> None:
        self.config = config
        self.device = device
        self.rng = rng
        self.agent = DQNAgent(shape, config, device)
        self.explorer = (RepeatedExploration(self.agent.greedy, shape.n_actions, config.explore_repeat_max,
                                             config.explore_repeat_exponent)
                         if config.explore_repeat_max > 1 else None)
        priorities = (Priorities(config.replay_capacity, config.per_alpha, config.per_epsilon)
                      if config.prioritized_replay else None)
        self.replay = ReplayBuffer(config.replay_capacity, shape.obs_dim, priorities)
        self.episode = 0
        """Episodes learned from (the learning-rate and priority-correction schedules follow it)."""
        self.global_step = 0
        """Env transitions (drone steps) so far; epsilon follows it."""
        self.updates = 0
        self.epsilon_max = config.epsilon_max

    # -- a loop's calls ----------------------------------------------------------------------
    def epsilon(self) -> float:
        return epsilon_at(self.global_step, self.epsilon_max, self.config.epsilon_min, self.config.epsilon_decay)

    def start_episodes(self) -> None:
        """Before the next episode (or wave, whose first episode sets it): its learning rate and
        a new exploration run."""
        config = self.config
        self.agent.set_learning_rate(learning_rate_at(self.episode, config.episodes, config.learning_rate,
                                                      config.learning_rate_end))
        if self.explorer is not None:
            self.explorer.start_episode()

    def act(self, drone: int, obs: np.ndarray, epsilon: float) -> int:
        """One drone's exploring action (ez-greedy when configured)."""
        if self.explorer is None:
            return self.agent.act(obs, epsilon, self.rng)
        return self.explorer.act(drone, obs, epsilon, self.rng)

    def act_batch(self, batch: np.ndarray, epsilon: float) -> np.ndarray:
        """Epsilon-greedy actions of a batch of observations with one network call."""
        return self.agent.act_batch(batch, epsilon, self.rng)

    def observe(self, batch: np.ndarray) -> None:
        """Observations seen (the input normalizer's statistics)."""
        self.agent.observe(batch)

    def n_step_folder(self) -> NStepFolder | None:
        """A fresh n-step folder for an episode (None for 1-step returns)."""
        return NStepFolder(self.config.n_step, self.config.gamma) if self.config.n_step > 1 else None

    def transition_rows(self, folder: NStepFolder | None, chosen: dict[int, int], obs: dict[int, np.ndarray],
                        result: StepResult) -> np.ndarray:
        """Replay rows of one env step of the drones in `chosen` (n-step: those complete now)."""
        if folder is None:
            return self.replay.make_rows(
                np.stack([obs[i] for i in chosen]), np.array(list(chosen.values())),
                np.array([result.rewards[i] for i in chosen]), np.stack([result.obs[i] for i in chosen]),
                np.array([float(result.terminated[i]) for i in chosen]))
        return self._fold_n_step(folder, chosen, obs, result)

    def remember(self, rows: np.ndarray) -> None:
        """Add replay rows (`transition_rows`)."""
        self.replay.add_rows(rows)

    def after_steps(self, steps: int, losses: list[float]) -> None:
        """Count `steps` env transitions and make the DQN updates due for them: `gradient_steps`
        every `train_every` steps once the replay holds enough rows (losses appended to `losses`)."""
        config = self.config
        before = self.global_step
        self.global_step += steps
        if len(self.replay) < max(config.batch_size, config.learning_starts):
            return
        due = self.global_step // config.train_every - before // config.train_every
        for _ in range(due * config.gradient_steps):
            losses.append(self._learn_step())
            self.updates += 1
            if config.target_update_unit == "steps" and self.updates % config.target_update_period == 0:
                self.agent.align_target()

    def end_episodes(self, count: int) -> None:
        """`count` episodes ended (one, or a wave's); the target network follows per episode when
        `target_update_unit` is `episodes`."""
        first = self.episode
        self.episode += count
        period = self.config.target_update_period
        if self.config.target_update_unit == "episodes" and first // period != self.episode // period:
            self.agent.align_target()

    # -- inside ------------------------------------------------------------------------------
    def _fold_n_step(self, folder: NStepFolder, chosen: dict[int, int], obs: dict[int, np.ndarray],
                     result: StepResult) -> np.ndarray:
        """This step's transitions folded into the n-step rows that are complete now."""
        ready = []
        for i, action in chosen.items():
            step = Step(obs[i], action, float(result.rewards[i]), result.obs[i], bool(result.terminated[i]))
            ready += folder.push(i, step, bool(result.terminated[i] or result.truncated[i]))
        if not ready:
            return self.replay.make_rows(np.zeros((0, self.agent.shape.obs_dim)), np.zeros(0),
                                         np.zeros(0), np.zeros((0, self.agent.shape.obs_dim)), np.zeros(0))
        return self.replay.make_rows(np.stack([r.obs for r in ready]), np.array([r.action for r in ready]),
                                     np.array([r.reward for r in ready]),
                                     np.stack([r.next_obs for r in ready]),
                                     np.array([r.terminated for r in ready]))

    def _learn_step(self) -> float:
        """One gradient update from the replay (by priority when prioritized replay is on)."""
        config = self.config
        if self.replay.priorities is None:
            return self.agent.update(self.replay.sample(config.batch_size, self.rng, self.device))
        # beta anneals from per_beta to 1 over the run (full bias correction at the end).
        fraction = min(self.episode / max(config.episodes - 1, 1), 1.0)
        beta = config.per_beta + (1.0 - config.per_beta) * fraction
        batch = self.replay.sample_prioritized(config.batch_size, beta, self.rng, self.device)
        loss = self.agent.update(batch)
        assert batch.slots is not None
        self.replay.priorities.update(batch.slots, self.agent.last_td_errors)
        return loss
