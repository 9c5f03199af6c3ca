"""Reinforcement learning on the scenarios: DQN, persisted replay, crash-safe checkpoints,
trainer, curriculum (incremental complexity), learning-rate probe, evaluation, plots, rules.

Entry points:

- `TrainConfig`, `load_train_config` (`sitl_bridge.rl.config`): hyperparameters from `train:`.
- `Trainer` (`sitl_bridge.rl.trainer`): one crash-safe training run in a run directory.
- `policy_from_checkpoint` (`sitl_bridge.rl.policy`): a greedy `obs -> action` callable.
- `evaluate_checkpoint` (`sitl_bridge.rl.evaluate`): greedy success/crash rates of a policy.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from sitl_bridge.rl.policy import GreedyPolicy

__all__ = ["policy_from_checkpoint"]


def policy_from_checkpoint(path: str | Path) -> GreedyPolicy:
    """Greedy policy of a run directory or checkpoint file: `policy(obs) -> int action`.
    (Re-exported lazily so `import sitl_bridge.rl` does not load torch.)"""
    from sitl_bridge.rl.policy import policy_from_checkpoint as load

    return load(path)
