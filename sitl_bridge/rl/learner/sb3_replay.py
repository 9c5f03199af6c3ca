"""The replay of an SB3 off-policy run (SAC, TD3) on disk: one `.npz` shard of plain arrays per
training episode, so a resume refills SB3's ReplayBuffer exactly.

A shard `replay/r{first:012d}_{end:012d}.npz` holds the rows the episode added (global row
indices first..end-1) of each array of SB3's ReplayBuffer (observations, next_observations,
actions, rewards, dones, timeouts); it is written atomically before the checkpoint that counts
its rows, and read with `allow_pickle=False`. Restoring a checkpoint that counts `total` rows
puts the last `buffer_size` of them back in the ring slots SB3's own `add` gave them.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import numpy as np

from sitl_bridge.rl.common.atomic import atomic_write_bytes

FIELDS = ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")


class ReplayShardError(RuntimeError):
    """The shards do not hold the rows a checkpoint counts (missing or damaged)."""


def _shard_name(first: int, end: int) -> str:
    return f"r{first:012d}_{end:012d}.npz"


def _shards(directory: Path) -> list[tuple[int, int, Path]]:
    found = []
    for path in directory.glob("r*_*.npz"):
        first, _, end = path.stem[1:].partition("_")
        if first.isdigit() and end.isdigit():
            found.append((int(first), int(end), path))
    return sorted(found)


class ReplayShards:
    """The shard folder of one run."""

    def __init__(self, directory: str | Path) -> None:
        self.directory = Path(directory)

    def append(self, buffer: Any, first: int, end: int) -> None:
        """Write rows first..end-1 (global indices; slots `index % buffer_size`) of `buffer`."""
        if end <= first:
            return
        slots = np.arange(first, end) % buffer.buffer_size
        arrays = {name: getattr(buffer, name)[slots] for name in FIELDS}
        data = io.BytesIO()
        np.savez(data, **arrays)
        self.directory.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(self.directory / _shard_name(first, end), data.getvalue())

    def restore(self, buffer: Any, total: int) -> None:
        """Refill `buffer` (emptied) with the last `buffer_size` of the first `total` rows."""
        size = buffer.buffer_size
        keep_from = max(total - size, 0)
        covered = keep_from
        for first, end, path in _shards(self.directory):
            if end <= keep_from or first >= total:
                continue
            if first > covered or end > total:
                raise ReplayShardError(f"{self.directory}: rows {covered}..{first} are missing")
            try:
                with np.load(path, allow_pickle=False) as arrays:
                    rows = {name: arrays[name] for name in FIELDS}
            except (OSError, ValueError, KeyError) as exc:
                raise ReplayShardError(f"{path}: unreadable ({exc})") from None
            if any(len(rows[name]) != end - first for name in FIELDS):
                raise ReplayShardError(f"{path}: holds another number of rows than its name says")
            start = max(first, keep_from)
            index = np.arange(start, end)
            for name in FIELDS:
                getattr(buffer, name)[index % size] = rows[name][start - first:]
            covered = end
        if covered < total:
            raise ReplayShardError(f"{self.directory}: rows {covered}..{total} are missing")
        buffer.pos = total % size
        buffer.full = total >= size

    def prune(self, needed_from: int, written_up_to: int | None = None) -> None:
        """Delete shards wholly before row `needed_from` (no kept checkpoint needs them) and,
        with `written_up_to`, shards past it (an episode written but never checkpointed)."""
        for first, end, path in _shards(self.directory):
            if end <= needed_from or (written_up_to is not None and first >= written_up_to):
                path.unlink(missing_ok=True)
