"""Reinforcement learning on the scenarios: DQN, persisted replay, crash-safe checkpoints,
trainer, curriculum (incremental complexity), learning-rate probe, evaluation, plots, rules.

Entry points:

- `TrainConfig`, `load_train_config` (`sitl_bridge.rl.learner.config`): hyperparameters from `train:`.
- `Trainer` (`sitl_bridge.rl.training.trainer`): one crash-safe training run in a run directory.
- `policy_from_checkpoint` (`sitl_bridge.rl.learner.policy`): a greedy `obs -> action` callable.
- `evaluate_checkpoint` (`sitl_bridge.rl.evaluation.evaluate`): greedy success/crash rates of a policy.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from sitl_bridge.rl.learner.policy import GreedyPolicy

__all__ = ["policy_from_checkpoint"]


def policy_from_checkpoint(path: str | Path) -> GreedyPolicy:
    """Greedy policy of a run directory or checkpoint file: `policy(obs) -> int action`.
    (Re-exported lazily so `import sitl_bridge.rl` does not load torch.)"""
    from sitl_bridge.rl.learner.policy import policy_from_checkpoint as load

    return load(path)
