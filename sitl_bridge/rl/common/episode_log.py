"""The episode log: `episodes.jsonl`, one JSON record per drone per finished episode.

Appended (and fsync'd) before each checkpoint; the checkpoint records the file's length, so a
resume cuts off records of episodes that were logged but never checkpointed: numbering continues
with no gap and no duplicate.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

from sitl_bridge.rl.common.atomic import append_durably
from sitl_bridge.rl.common.episode_files import open_log

OUTCOMES = ("goal", "crash", "out", "timeout")


@dataclass
class EpisodeRecord:
    """What one drone did in one episode."""

    episode: int
    """Episode index, 0-based, continuous across resumes."""
    drone: int
    actions: list
    """Action codes in order (the thesis's behaviour strings); a continuous command as its
    components (`action_names.logged_action`)."""
    reward: float
    """Cumulative reward."""
    reward_terms: dict[str, float]
    """Cumulative reward per named term (closer_to_goal, crash, ...)."""
    outcome: str
    """goal, crash, out or timeout."""
    steps: int
    sim_time_s: float
    """Simulated seconds the episode took."""
    wall_time_s: float
    """Real seconds the episode took (simulation + learning)."""
    epsilon: float
    """Exploration rate at the episode's start."""
    mean_loss: float | None
    """Mean training loss over the episode's updates (None before learning starts)."""
    global_step: int = 0
    """Environment steps taken by the run when the episode ended."""
    env_seed: int = 0
    """Seed the episode's reset used (re-runs the same start and goal)."""
    cpu_time_s: float | None = None
    """CPU seconds the training process spent on the episode (all its threads; what one core
    would need, however busy the machine was; in a wave of several episodes at once, an even
    share of the wave's). None in logs written before it was recorded."""
    extra: dict = field(default_factory=dict)
    """Anything else the environment reported at the end (positions, ...)."""

    @property
    def success(self) -> bool:
        return self.outcome == "goal"


class EpisodeLog:
    """Append-only JSON Lines file of EpisodeRecords."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.touch(exist_ok=True)
        self._sha: hashlib._Hash | None = None  # running SHA-256 of the file, built when first asked

    def append(self, records: list[EpisodeRecord]) -> int:
        """Append records durably; returns the file's size in bytes afterwards."""
        data = "".join(json.dumps(asdict(r), separators=(",", ":")) + "\n" for r in records).encode()
        if self._sha is not None:
            self._sha.update(data)
        return append_durably(self.path, data)

    def digest(self) -> str:
        """SHA-256 of the whole log (kept up to date as records are appended)."""
        if self._sha is None:
            self._sha = hashlib.sha256(self.path.read_bytes())
        return self._sha.hexdigest()

    def prefix_digest(self, size: int) -> str:
        """SHA-256 of the log's first `size` bytes (what a checkpoint recorded)."""
        with open(self.path, "rb") as handle:
            return hashlib.sha256(handle.read(size)).hexdigest()

    def size(self) -> int:
        return self.path.stat().st_size

    def truncate(self, size: int) -> None:
        """Cut the log back to `size` bytes (records after the restored checkpoint)."""
        with open(self.path, "r+b") as handle:
            handle.truncate(size)
            os.fsync(handle.fileno())
        self._sha = None


def read_records(path: str | Path, warn=None) -> list[dict]:  # noqa: ANN001 - callable(str)
    """Every complete record of an episode log (plain, or its `.xz`: `rl/common/episode_files.py`). A
    torn last line is ignored; a line that is not a JSON record (damage) is skipped and reported
    through `warn` (default: logging)."""
    import logging

    records: list[dict] = []
    with open_log(path) as handle:
        for number, raw in enumerate(handle, start=1):
            if not raw.endswith(b"\n"):
                break
            try:
                record = json.loads(raw)
                if not isinstance(record, dict) or "episode" not in record:
                    raise ValueError("not an episode record")
            except ValueError:
                (warn or logging.getLogger(__name__).warning)(
                    f"{path}: line {number} is not an episode record; skipped")
                continue
            records.append(record)
    return records
