"""A run's saved state: after each episode (or wave) one checkpoint (atomic, self-checking:
rl/learner/checkpoint.py) holding the learner's state and how much of the replay shards and of
`episodes.jsonl` it covers; the newest `checkpoints_kept` kept. Resuming restores the newest one
that verifies and fits (older ones are fallbacks), cuts the episode log and the evaluation
journal back to it, and refuses a config.yaml edited since or a run that would train over its
own logged history."""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import torch

from sitl_bridge.errors import ConfigError
from sitl_bridge.rl.common.episode_log import read_records
from sitl_bridge.rl.learner import checkpoint as ckpt
from sitl_bridge.rl.learner.config import TrainConfig
from sitl_bridge.rl.training import run_dir as rd
from sitl_bridge.rl.training.episode_sink import EpisodeSink
from sitl_bridge.rl.training.eval_journal import drop_evaluations_after

log = logging.getLogger(__name__)
Tensors = dict[str, torch.Tensor]


class Saveable(Protocol):
    """What an algorithm's side of a run (`DQNTraining`, `SB3Training`) saves and restores."""

    learner: Any

    def state_tensors(self) -> Tensors: ...
    def state_json(self) -> dict[str, Any]: ...
    def check_restorable(self, path: Path, tensors: Tensors, state: dict[str, Any]) -> None: ...
    def restore(self, path: Path, tensors: Tensors, state: dict[str, Any]) -> None: ...
    def replay_rows(self) -> int: ...
    def rows_needed(self, checkpoint: Path) -> int | None: ...
    def prune_replay(self, oldest_rows: int) -> None: ...


class RunState:
    """Checkpoints of one run: written after each episode or wave, restored on resume."""

    def __init__(self, run_dir: Path, spec: rd.RunSpec, config: TrainConfig, training: Saveable,
                 sink: EpisodeSink) -> None:
        self.run_dir, self.spec, self.config = run_dir, spec, config
        self.training, self.sink = training, sink
        self.directory = run_dir / rd.CHECKPOINTS
        self._kept: list[tuple[Path, int]] = []  # (checkpoint, replay rows it needs)

    def save(self, evaluation_due: bool) -> Path:
        """Checkpoint the state after the finished episodes; prune old checkpoints and shards."""
        learner, sink = self.training.learner, self.sink
        path = ckpt.checkpoint_path(self.directory, learner.episode)
        state = {**self.training.state_json(), "world": self.spec.world, "seed": self.spec.seed,
                 "config": self.config.to_dict(), "log_bytes": sink.episode_log.size(),
                 "log_sha256": sink.episode_log.digest(),
                 "recent_success": [bool(s) for s in sink.recent_success], "evaluation_due": evaluation_due}
        ckpt.save_checkpoint(path, self.training.state_tensors(), state)
        self._kept.append((path, self.training.replay_rows()))
        while len(self._kept) > self.config.checkpoints_kept:
            old, _ = self._kept.pop(0)
            old.unlink(missing_ok=True)
        self.training.prune_replay(self._kept[0][1])  # every row a kept checkpoint could restore
        return path

    def restore(self, path: Path, tensors: Tensors, state: dict[str, Any]) -> bool:
        """Restore one checkpoint (`checkpoint.restore_newest` falls back to older ones when it
        raises); returns its `evaluation_due`."""
        self.training.check_restorable(path, tensors, state)
        episode_log = self.sink.episode_log
        recorded = state.get("log_sha256")
        if recorded is not None and episode_log.prefix_digest(state["log_bytes"]) != recorded:
            raise ckpt.CheckpointNotRestorable(
                f"the part of {rd.EPISODES_FILE} it covers ({state['log_bytes']} bytes) was changed since")
        self.training.restore(path, tensors, state)
        episode_log.truncate(state["log_bytes"])
        self.sink.recent_success.extend(state["recent_success"])
        episode = self.training.learner.episode
        drop_evaluations_after(self.run_dir / rd.EVALS_FILE, episode)  # flown again from here
        self._kept = []
        for older in sorted(ckpt.list_checkpoints(self.directory)):
            rows = self.training.rows_needed(older)
            if rows is not None:
                self._kept.append((older, rows))
        log.info("resumed %s from %s (episode %d)", self.run_dir, path.name, episode)
        return bool(state.get("evaluation_due", False))

    def restore_newest(self, warn: Callable[[str], None]) -> bool | None:
        """Restore the newest checkpoint that verifies and fits (its `evaluation_due`); None
        when the run has none (`start_over_without_history`)."""
        if not ckpt.list_checkpoints(self.directory):
            return None
        return ckpt.restore_newest(self.directory, self.restore, warn=warn)

    def start_over_without_history(self) -> None:
        """A run with no checkpoint starts over, unless it already logged finished episodes:
        it must never train over its own history (duplicate episodes in the log)."""
        episode_log = self.sink.episode_log
        logged = {r["episode"] for r in read_records(episode_log.path, warn=lambda _msg: None)}
        if logged - {0}:
            raise ckpt.CheckpointError(
                f"{self.run_dir}: {len(logged)} episodes are logged but no checkpoint is usable; refusing "
                "to start the run over its own history (start a new run, or put the checkpoints back)")
        episode_log.truncate(0)  # killed before its first checkpoint: nothing to keep


def refuse_edited_config(run_dir: Path, config: TrainConfig) -> None:
    """A config.yaml edited after the run's checkpoints were written is a ConfigError naming
    each differing key, before anything is restored: the checkpoints are sound, only the file
    changed, so nothing is condemned and putting the values back resumes the run."""
    for path in ckpt.list_checkpoints(run_dir / rd.CHECKPOINTS):
        try:
            recorded = ckpt.read_state(path).get("config")
        except (ckpt.CheckpointCorrupt, OSError, ValueError, AttributeError):
            continue  # the newest readable one speaks for the run; damaged ones fall back later
        differing = rd.config_differences(recorded, config)
        if differing:
            raise ConfigError(f"{run_dir / rd.CONFIG_FILE} differs from the run's checkpoints in: "
                              f"{', '.join(differing)}; put the values back to resume (or start a new run)")
        return
