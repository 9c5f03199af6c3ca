"""Reinforcement learning on the scenarios: DQN, persisted replay, crash-safe checkpoints,
trainer, curriculum (incremental complexity), learning-rate probe, evaluation, plots, rules.

Public entry points:

- `TrainConfig`, `load_train_config` (`sitl_bridge.rl.config`): hyperparameters from `train:`.
- `Trainer` (`sitl_bridge.rl.trainer`): one crash-safe training run in a run directory.
- `policy_from_checkpoint` (`sitl_bridge.rl.policy`): a greedy `obs -> action` callable.
- `evaluate` (`sitl_bridge.rl.evaluate`): greedy success/crash rates of a policy.
"""

from __future__ import annotations

__all__ = ["policy_from_checkpoint"]


def policy_from_checkpoint(path):  # noqa: ANN001, ANN201 - thin lazy re-export (avoids importing torch early)
    """Greedy policy of a run directory or checkpoint file: `callable(obs) -> int action`."""
    from sitl_bridge.rl.policy import policy_from_checkpoint as _load

    return _load(path)
