"""Where a run's finished episodes go: the rolling exploring success rate, the early-end
warning, the replay rows (to the shards) and then the records (to `episodes.jsonl`), the
TensorBoard scalars and, with `heartbeat` on, `heartbeat.json` for a watchdog."""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from pathlib import Path

import numpy as np

from sitl_bridge.rl.common.episode_log import EpisodeLog, EpisodeRecord
from sitl_bridge.rl.evaluation.evaluate import EvalResult
from sitl_bridge.rl.training import run_dir as rd
from sitl_bridge.rl.training.early_end import EarlyEndWatch
from sitl_bridge.rl.training.heartbeat import TRAINING, write_heartbeat
from sitl_bridge.rl.training.tensorboard_log import TensorBoardLog


class EpisodeSink:
    """Persists a run's finished episodes and reports its progress."""

    def __init__(self, run_dir: Path, success_window: int, early_end: EarlyEndWatch | None,
                 store_rows: Callable[[np.ndarray], None] | None, *, heartbeat: bool,
                 warn: Callable[[str], None]) -> None:
        self.run_dir = run_dir
        self.episode_log = EpisodeLog(run_dir / rd.EPISODES_FILE)
        self.recent_success: deque[bool] = deque(maxlen=success_window)
        self.early_end = early_end
        self.store_rows = store_rows
        """Appends transitions to the replay shards (None: the learner writes its own)."""
        self.heartbeat = heartbeat
        self.warn = warn
        self._writer: TensorBoardLog | None = None

    def persist(self, records: list[EpisodeRecord], new_rows: list[np.ndarray]) -> None:
        """Count finished episodes' successes, then persist their replay rows and then their
        records (the checkpoint naming both lengths comes after)."""
        self.recent_success.extend(r.success for r in records)
        if self.early_end is not None and (warning := self.early_end.add(records)):
            self.warn(warning)
        if new_rows:
            assert self.store_rows is not None, "this learner writes its replay rows itself"
            self.store_rows(np.concatenate(new_rows))
        self.episode_log.append(records)

    def success_rate(self) -> float:
        """The exploring success rate over the last `success_window` drone-episodes."""
        return float(np.mean(self.recent_success)) if self.recent_success else 0.0

    def tensorboard(self, records: list[EpisodeRecord], learning_rate: float) -> None:
        """The episodes' scalars (a wave's episodes share its end's rates)."""
        if self._writer is None:
            # purge_step drops events a killed session wrote after its last checkpoint.
            self._writer = TensorBoardLog(self.run_dir / rd.TENSORBOARD, purge_step=records[0].episode)
        rate = self.success_rate()
        for episode in sorted({r.episode for r in records}):
            self._writer.episode(episode, [r for r in records if r.episode == episode], rate, learning_rate)

    def evaluation(self, episode: int, result: EvalResult) -> None:
        """An evaluation's scalars (once this session has logged an episode)."""
        if self._writer is not None:
            self._writer.evaluation(episode, result)

    def beat(self, episode: int, global_step: int, phase: str = TRAINING) -> None:
        """With `heartbeat` on, tell a watchdog the run is alive and what it is doing."""
        if self.heartbeat:
            write_heartbeat(self.run_dir, episode, global_step, phase)

    def flush(self) -> None:
        if self._writer is not None:
            self._writer.flush()

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None
