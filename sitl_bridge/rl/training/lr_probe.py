"""The thesis's learning-rate probe: find a rate a run can safely start with.

1. Collect the first few batches of experience with a random policy (what a run sees first).
2. For each candidate rate, from high to low: train a fresh network for many epochs on that data
   (targets from a frozen copy of the initial network, so the regression problem is fixed and
   only the rate decides whether it converges).
3. A rate diverges when the loss becomes non-finite, ends above where it started, or climbs back
   well above its best value. The highest rate that does not diverge is the safe starting rate.
"""

from __future__ import annotations

import copy
import math
from dataclasses import asdict, dataclass, field

import numpy as np
import torch

from sitl_bridge.rl.common.drones_env import DronesEnv, EnvFactory
from sitl_bridge.rl.learner.config import TrainConfig
from sitl_bridge.rl.learner.dqn import DQNAgent, NetworkShape, dqn_loss
from sitl_bridge.rl.learner.replay_buffer import ReplayBuffer, rows_to_batch
from sitl_bridge.rl.learner.torch_threads import use_torch_threads

DEFAULT_RATES = tuple(float(f"{10 ** (-k / 2):.3g}") for k in range(2, 15))
"""0.1, 0.0316, 0.01, ... 1e-7 (half decades)."""

REBOUND_FACTOR = 3.0
"""A final loss this many times above the best epoch's loss counts as diverging."""


@dataclass
class RateTrial:
    """The loss curve of one candidate rate."""

    learning_rate: float
    epoch_losses: list[float]
    diverged: bool
    reason: str


@dataclass
class ProbeResult:
    """All trials (epoch_losses[0]: before training) and the recommended starting rate (None when every rate diverged)."""

    transitions: int
    epochs: int
    safe_learning_rate: float | None
    trials: list[RateTrial] = field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)

    def report(self) -> str:
        lines = [f"learning-rate probe: {self.transitions} transitions, {self.epochs} epochs per rate"]
        for t in self.trials:
            first, last = t.epoch_losses[0], t.epoch_losses[-1]
            verdict = f"DIVERGES ({t.reason})" if t.diverged else "ok"
            lines.append(f"  lr {t.learning_rate:<9.3g} loss {first:10.4g} -> {last:10.4g}  {verdict}")
        rate = "none found" if self.safe_learning_rate is None else f"{self.safe_learning_rate:.3g}"
        lines.append(f"safe starting learning rate: {rate}")
        return "\n".join(lines)


def collect_random(env: DronesEnv, transitions: int, seed: int) -> np.ndarray:
    """At least `transitions` transitions from random actions (whole episodes)."""
    rng = np.random.default_rng(seed)
    buffer = ReplayBuffer(transitions + 1000 * env.num_drones, env.obs_dim)
    episode = 0
    while buffer.total_added < transitions:
        obs, _ = env.reset(int(np.random.SeedSequence([seed, episode]).generate_state(1)[0]))
        episode += 1
        while env.live and buffer.total_added < buffer.capacity:
            chosen = {i: int(rng.integers(env.n_actions)) for i in env.live}
            result = env.step(chosen)
            buffer.add_rows(buffer.make_rows(
                np.stack([obs[i] for i in chosen]), np.array(list(chosen.values())),
                np.array([result.rewards[i] for i in chosen]), np.stack([result.obs[i] for i in chosen]),
                np.array([float(result.terminated[i]) for i in chosen])))
            obs.update(result.obs)
    return buffer.rows[:len(buffer)]


def judge(losses: list[float]) -> tuple[bool, str]:
    """(diverged, why) for one loss curve; `losses[0]` is the untrained network's loss."""
    if not all(math.isfinite(x) for x in losses):
        return True, "loss became inf/nan"
    if max(losses) > REBOUND_FACTOR * losses[0]:
        return True, f"loss blew up to {max(losses) / losses[0]:.3g}x its start"
    if losses[-1] > losses[0]:
        return True, "loss ended above its start"
    if losses[-1] > REBOUND_FACTOR * min(losses) and losses[-1] > 1e-6:
        return True, f"loss rebounded to {losses[-1] / min(losses):.1f}x its best"
    return False, ""


def train_epochs(rows: np.ndarray, shape: NetworkShape, config: TrainConfig, rate: float,
                 epochs: int, seed: int) -> list[float]:
    """Loss of the untrained network, then mean loss per epoch at `rate` (frozen targets)."""
    torch.manual_seed(seed)
    agent = DQNAgent(shape, config.replace(learning_rate=rate))
    agent.target = copy.deepcopy(agent.online).requires_grad_(False)
    rng = np.random.default_rng(seed)
    with torch.no_grad():
        losses = [float(dqn_loss(agent.online, agent.target, rows_to_batch(rows), config.gamma,
                                 config.loss, config.double_dqn))]
    for _ in range(epochs):
        order = rng.permutation(len(rows))
        batch_losses = []
        for start in range(0, len(rows), config.batch_size):
            batch_losses.append(agent.update(rows_to_batch(rows[order[start:start + config.batch_size]])))
            if not math.isfinite(batch_losses[-1]):
                return losses + [math.inf]
        losses.append(float(np.mean(batch_losses)))
    return losses


def probe(env_factory: EnvFactory, config: TrainConfig, *, batches: int = 5, epochs: int = 100,
          rates: tuple[float, ...] = DEFAULT_RATES, seed: int = 0, stop_after_safe: int = 2) -> ProbeResult:
    """Run the probe: collect `batches` batches of random experience, then try `rates` from the
    highest; stop once `stop_after_safe` rates in a row converged."""
    use_torch_threads(config.torch_threads)
    env = DronesEnv(env_factory(seed))
    try:
        rows = collect_random(env, batches * config.batch_size, seed)
        shape = NetworkShape(env.obs_dim, env.n_actions, config.layers, config.hidden_units)
    finally:
        env.close()
    result = ProbeResult(transitions=len(rows), epochs=epochs, safe_learning_rate=None)
    converged_in_a_row = 0
    for rate in sorted(rates, reverse=True):
        losses = train_epochs(rows, shape, config, rate, epochs, seed)
        diverged, reason = judge(losses)
        result.trials.append(RateTrial(rate, losses, diverged, reason))
        if diverged:
            converged_in_a_row = 0
            result.safe_learning_rate = None
            continue
        if result.safe_learning_rate is None:
            result.safe_learning_rate = rate
        converged_in_a_row += 1
        if converged_in_a_row >= stop_after_safe:
            break
    return result
