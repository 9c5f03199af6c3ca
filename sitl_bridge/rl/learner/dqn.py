"""Deep Q-learning as in the thesis (chapter 3), in one module you can check against its equations.

- Q network: an MLP of `layers` linear layers with PReLU activations between them; optionally
  (`train:` options, all off by default) with observation normalisation in front
  (`rl/learner/normalizer.py`) and a dueling head: Q(s, a) = V(s) + A(s, a) - mean_a' A(s, a').
- Exploration: epsilon-greedy with eps = eps_min + (eps_max - eps_min) * exp(-lambda * steps)
  (thesis equation 16); with `explore_repeat_max` > 1 a random step starts a run of repeats
  (ez-greedy, `rl/learner/exploration.py`).
- Target: y = r + gamma * (1 - terminated) * Q_target(s', a*), with
  a* = argmax_a Q_online(s', a) for double DQN (or argmax_a Q_target(s', a) for plain DQN).
  Truncated episodes (step limit) still bootstrap: only a real end (goal, crash, out) stops it.
  With n-step returns (`rl/learner/nstep.py`) the replay rows already hold the n-step return and
  encode gamma^m in `terminated`, so this target is unchanged.
- Loss: MSE (thesis), Huber or MAE between Q_online(s, a) and y, each transition weighted by its
  importance weight under prioritized replay (`rl/learner/prioritized.py`); the gradient norm is clipped
  to `max_grad_norm` when set; the target network is a copy of the online network, re-aligned
  every `target_update_period` steps or episodes.
- Learning rate: constant, or geometric from `learning_rate` to `learning_rate_end` over the run.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from sitl_bridge.rl.learner.config import TrainConfig
from sitl_bridge.rl.learner.normalizer import RunningNorm


# --- network ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class NetworkShape:
    """What a Q network looks like; saved with every checkpoint so it can be rebuilt alone."""

    obs_dim: int
    n_actions: int
    layers: int
    hidden_units: int
    dueling: bool = False
    normalize: bool = False

    def to_dict(self) -> dict[str, int | bool]:
        shape: dict[str, int | bool] = {"obs_dim": self.obs_dim, "n_actions": self.n_actions,
                                        "layers": self.layers, "hidden_units": self.hidden_units}
        # Only when on, so checkpoints of plain networks keep their original description.
        if self.dueling:
            shape["dueling"] = True
        if self.normalize:
            shape["normalize"] = True
        return shape


def _mlp(sizes: list[int]) -> nn.Sequential:
    """Linear layers through `sizes`, PReLU between them (none after the last)."""
    modules: list[nn.Module] = []
    for i, (n_in, n_out) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
        modules.append(nn.Linear(n_in, n_out))
        if i < len(sizes) - 2:
            modules.append(nn.PReLU(n_out))
    return nn.Sequential(*modules)


def dueling_q(value: torch.Tensor, advantage: torch.Tensor) -> torch.Tensor:
    """Q(s, a) = V(s) + A(s, a) - mean_a' A(s, a') (value [B, 1], advantage [B, actions])."""
    return value + advantage - advantage.mean(dim=1, keepdim=True)


class QNetwork(nn.Module):
    """MLP observation -> one Q value per action; `layers` Linear layers, PReLU in between.

    Dueling: the last layer is split into a value head (1 output) and an advantage head."""

    def __init__(self, shape: NetworkShape) -> None:
        super().__init__()
        self.shape = shape
        self.norm = RunningNorm(shape.obs_dim) if shape.normalize else None
        sizes = [shape.obs_dim] + [shape.hidden_units] * (shape.layers - 1) + [shape.n_actions]
        if not shape.dueling or shape.layers < 2:
            self.net = _mlp(sizes)
            self.value = None
        else:
            self.net = nn.Sequential(_mlp(sizes[:-1]), nn.PReLU(sizes[-2]))
            self.advantage = nn.Linear(sizes[-2], shape.n_actions)
            self.value = nn.Linear(sizes[-2], 1)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        if obs.dim() == 1:  # one observation: per-unit PReLU needs a batch dimension
            return self.forward(obs.unsqueeze(0)).squeeze(0)
        if self.norm is not None:
            obs = self.norm(obs)
        features = self.net(obs)
        if self.value is None:
            return features
        return dueling_q(self.value(features), self.advantage(features))


# --- schedules --------------------------------------------------------------------------------
def epsilon_at(step: int, eps_max: float, eps_min: float, decay: float) -> float:
    """Thesis eq. 16: eps = eps_min + (eps_max - eps_min) * exp(-lambda * steps)."""
    return eps_min + (eps_max - eps_min) * math.exp(-decay * step)


def learning_rate_at(episode: int, total_episodes: int, start: float, end: float) -> float:
    """Constant `start` when `end` is 0, else geometric from `start` (episode 0) to `end` (last)."""
    if end <= 0.0 or total_episodes <= 1:
        return start
    fraction = min(max(episode / (total_episodes - 1), 0.0), 1.0)
    return start * (end / start) ** fraction


# --- the update -------------------------------------------------------------------------------
def td_targets(
    online: nn.Module, target: nn.Module, rewards: torch.Tensor, next_obs: torch.Tensor,
    terminated: torch.Tensor, gamma: float, double: bool = True,
) -> torch.Tensor:
    """y = r + gamma * (1 - terminated) * Q_target(s', a*) (a* from the online net when double)."""
    # no_grad, not inference_mode: the loss saves y for its backward, which an inference tensor refuses.
    with torch.no_grad():
        next_q_target = target(next_obs)
        if double:
            best_next = online(next_obs).argmax(dim=1, keepdim=True)
        else:
            best_next = next_q_target.argmax(dim=1, keepdim=True)
        next_value = next_q_target.gather(1, best_next).squeeze(1)
        return rewards + gamma * (1.0 - terminated) * next_value


LOSS_FUNCTIONS: dict[str, Callable[..., torch.Tensor]] = {
    "mse": nn.functional.mse_loss,
    "huber": nn.functional.smooth_l1_loss,
    "mae": nn.functional.l1_loss,
}
"""Element-wise losses (called with reduction="none", then averaged with the weights)."""

OPTIMIZER_CLASSES: dict[str, type[torch.optim.Optimizer]] = {
    "adam": torch.optim.Adam,
    "adamax": torch.optim.Adamax,
    "sgd": torch.optim.SGD,
    "rmsprop": torch.optim.RMSprop,
}


@dataclass
class Batch:
    """A mini-batch of transitions as tensors (shapes: [B, obs], [B], [B], [B, obs], [B])."""

    obs: torch.Tensor
    actions: torch.Tensor
    rewards: torch.Tensor
    next_obs: torch.Tensor
    terminated: torch.Tensor
    weights: torch.Tensor | None = None
    """Importance-sampling weights per transition (prioritized replay), else None (all 1)."""
    slots: np.ndarray | None = None
    """Replay slots the transitions came from (prioritized replay updates their priorities)."""


def dqn_loss(online: nn.Module, target: nn.Module, batch: Batch, gamma: float,
             loss: str = "mse", double: bool = True) -> torch.Tensor:
    """Loss between Q_online(s, a) and the TD target of `batch` (gradients flow to `online` only)."""
    return dqn_loss_and_errors(online, target, batch, gamma, loss, double)[0]


def dqn_loss_and_errors(online: nn.Module, target: nn.Module, batch: Batch, gamma: float,
                        loss: str = "mse", double: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """The (importance-weighted) loss and the TD errors y - Q_online(s, a) of each transition."""
    y = td_targets(online, target, batch.rewards, batch.next_obs, batch.terminated, gamma, double)
    q_taken = online(batch.obs).gather(1, batch.actions.long().unsqueeze(1)).squeeze(1)
    per_transition = LOSS_FUNCTIONS[loss](q_taken, y, reduction="none")
    if batch.weights is not None:
        per_transition = per_transition * batch.weights
    return per_transition.mean(), (y - q_taken).detach()


# --- the agent --------------------------------------------------------------------------------
class DQNAgent:
    """Online + target network, optimizer and the epsilon-greedy policy. One per run; several
    drones share it (every drone's experience trains the same network)."""

    def __init__(self, shape: NetworkShape, config: TrainConfig, device: torch.device | str = "cpu") -> None:
        self.config = config
        self.device = torch.device(device)
        self.shape = shape
        self.online = QNetwork(shape).to(self.device)
        self.target = copy.deepcopy(self.online)
        self.target.requires_grad_(False)
        self.optimizer = OPTIMIZER_CLASSES[config.optimizer](self.online.parameters(), lr=config.learning_rate)
        self.last_td_errors = np.zeros(0, dtype=np.float32)
        """TD errors of the last update's batch (prioritized replay's new priorities)."""

    def q_values(self, obs: np.ndarray) -> np.ndarray:
        """Q values of one observation (or a batch of them)."""
        with torch.inference_mode():  # no autograd bookkeeping at all (acting never backpropagates)
            tensor = torch.as_tensor(np.asarray(obs, dtype=np.float32), device=self.device)
            return self.online(tensor).cpu().numpy()

    def act(self, obs: np.ndarray, epsilon: float, rng: np.random.Generator) -> int:
        """Epsilon-greedy action: random with probability epsilon, else argmax Q."""
        # Draw both numbers every time so the RNG stream does not depend on the network.
        explore = rng.random() < epsilon
        random_action = int(rng.integers(self.shape.n_actions))
        if explore:
            return random_action
        return self.greedy(obs)

    def greedy(self, obs: np.ndarray) -> int:
        """The online network's best action for one observation (argmax Q)."""
        return int(np.argmax(self.q_values(obs)))

    def act_batch(self, obs: np.ndarray, epsilon: float, rng: np.random.Generator) -> np.ndarray:
        """`act` for each row of `obs` (the same random draws, row by row), with one network
        call for all the rows that exploit."""
        draws = [(rng.random() < epsilon, int(rng.integers(self.shape.n_actions))) for _ in range(len(obs))]
        actions = np.array([action for _, action in draws], dtype=np.int64)
        greedy = np.array([not explore for explore, _ in draws], dtype=bool)
        if greedy.any():
            actions[greedy] = np.argmax(self.q_values(np.asarray(obs)[greedy]), axis=1)
        return actions

    def set_learning_rate(self, rate: float) -> None:
        for group in self.optimizer.param_groups:
            group["lr"] = rate

    def observe(self, obs: np.ndarray) -> None:
        """Feed new observations to the online network's normaliser (no-op without one)."""
        if self.online.norm is not None:
            self.online.norm.update(torch.as_tensor(np.asarray(obs, dtype=np.float32), device=self.device))

    def update(self, batch: Batch) -> float:
        """One gradient step on `batch`; returns the loss value (TD errors in `last_td_errors`)."""
        loss, errors = dqn_loss_and_errors(self.online, self.target, batch, self.config.gamma,
                                           self.config.loss, self.config.double_dqn)
        self.last_td_errors = errors.cpu().numpy()
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if self.config.max_grad_norm > 0:
            nn.utils.clip_grad_norm_(self.online.parameters(), self.config.max_grad_norm)
        self.optimizer.step()
        return float(loss.detach())

    def align_target(self) -> None:
        """Copy the online weights into the target network."""
        self.target.load_state_dict(self.online.state_dict())
