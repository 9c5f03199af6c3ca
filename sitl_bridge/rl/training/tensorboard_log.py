"""TensorBoard scalars of a run: the episode log's numbers, per episode, plus evaluations.

Scalar names are stable (dashboards and scripts rely on them); the step is the episode index:

| name | value |
|---|---|
| `reward/total`, `reward/<term>` | episode reward, in total and per reward term (drones averaged) |
| `outcome/goal`, `outcome/crash`, `outcome/out`, `outcome/timeout` | share of drones ending that way |
| `episode/steps`, `episode/sim_time_s`, `episode/wall_time_s` | episode length |
| `train/epsilon`, `train/loss`, `train/learning_rate`, `train/success_rate` | learner state (success: rolling, exploring) |
| `eval/success`, `eval/crash`, `eval/mean_reward` | periodic greedy evaluation |
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sitl_bridge.rl.common.episode_log import EpisodeRecord
from sitl_bridge.rl.evaluation.evaluate import EvalResult

OUTCOMES = ("goal", "crash", "out", "timeout")


class TensorBoardLog:
    """One SummaryWriter; the step of every scalar is the episode index."""

    def __init__(self, directory: str | Path, purge_step: int | None = None) -> None:
        from torch.utils.tensorboard import SummaryWriter  # imports tensorboard: only when used

        self.writer = SummaryWriter(str(directory), purge_step=purge_step)

    def episode(self, step: int, records: list[EpisodeRecord], success_rate: float, learning_rate: float) -> None:
        """Scalars of one finished episode (drones averaged)."""
        w = self.writer
        w.add_scalar("reward/total", float(np.mean([r.reward for r in records])), step)
        for name in sorted({name for r in records for name in r.reward_terms}):
            w.add_scalar(f"reward/{name}", float(np.mean([r.reward_terms.get(name, 0.0) for r in records])), step)
        for outcome in OUTCOMES:
            w.add_scalar(f"outcome/{outcome}", float(np.mean([r.outcome == outcome for r in records])), step)
        w.add_scalar("episode/steps", float(np.mean([r.steps for r in records])), step)
        w.add_scalar("episode/sim_time_s", records[0].sim_time_s, step)
        w.add_scalar("episode/wall_time_s", records[0].wall_time_s, step)
        w.add_scalar("train/epsilon", records[0].epsilon, step)
        w.add_scalar("train/success_rate", success_rate, step)
        w.add_scalar("train/learning_rate", learning_rate, step)
        if records[0].mean_loss is not None:
            w.add_scalar("train/loss", records[0].mean_loss, step)

    def evaluation(self, step: int, result: EvalResult) -> None:
        """Scalars of a greedy evaluation after episode `step`."""
        self.writer.add_scalar("eval/success", result.success_rate, step)
        self.writer.add_scalar("eval/crash", result.crash_rate, step)
        self.writer.add_scalar("eval/mean_reward", result.mean_reward, step)

    def flush(self) -> None:
        self.writer.flush()

    def close(self) -> None:
        self.writer.close()
