"""The experience replay on disk: append-only array shards, never rewritten.

Rows (see `replay.transition_dtype`) are appended to `seg_000000.bin`, `seg_000001.bin`, ... of
`segment_rows` rows each, fsync'd after every episode. A checkpoint records how many rows existed
and a CRC32 of each live shard's prefix, so a resume truncates what a killed run appended after its
last checkpoint and detects a damaged shard. Shards whose rows can no longer be in any kept
checkpoint's replay are deleted. The layout is described in `format.json` (no pickle anywhere).
"""

from __future__ import annotations

import json
import os
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sitl_bridge.rl.common.atomic import atomic_write_json, fsync_dir
from sitl_bridge.rl.learner.replay_buffer import transition_dtype

FORMAT_VERSION = 1


class ReplayCorrupt(RuntimeError):
    """The replay shards on disk do not match what a checkpoint recorded."""


@dataclass
class ReplayStoreState:
    """What a checkpoint records about the replay shards."""

    total_rows: int = 0
    crc: dict[int, int] = field(default_factory=dict)
    """CRC32 of each live shard's first rows (as many as existed at the checkpoint)."""
    base_row: int = 0
    """Rows before this one are not on disk (discarded after damage); shard 0 starts here."""

    def to_json(self) -> dict:
        return {"total_rows": self.total_rows, "crc": {str(k): v for k, v in self.crc.items()},
                "base_row": self.base_row}

    @classmethod
    def from_json(cls, value: dict) -> ReplayStoreState:
        return cls(int(value["total_rows"]), {int(k): int(v) for k, v in value["crc"].items()},
                   int(value.get("base_row", 0)))


class ReplayStore:
    """Append-only shard files of one run's replay, in `directory`."""

    def __init__(self, directory: str | Path, obs_dim: int, segment_rows: int) -> None:
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.dtype = transition_dtype(obs_dim)
        self.segment_rows = segment_rows
        self.state = ReplayStoreState()
        layout = {"version": FORMAT_VERSION, "obs_dim": obs_dim, "segment_rows": segment_rows,
                  "row_bytes": self.dtype.itemsize, "dtype": [list(map(str, f)) for f in self.dtype.descr]}
        format_path = self.directory / "format.json"
        if format_path.exists():
            existing = json.loads(format_path.read_text())
            if existing != json.loads(json.dumps(layout)):
                raise ReplayCorrupt(f"{format_path}: replay layout {existing} does not match {layout}")
        else:
            atomic_write_json(format_path, layout)

    @classmethod
    def open_existing(cls, directory: str | Path) -> ReplayStore:
        """Another run's replay, to read (its layout from its `format.json`)."""
        path = Path(directory) / "format.json"
        if not path.is_file():
            raise ReplayCorrupt(f"{directory}: no replay there ({path.name} is missing)")
        layout = json.loads(path.read_text())
        return cls(directory, int(layout["obs_dim"]), int(layout["segment_rows"]))

    def _path(self, segment: int) -> Path:
        return self.directory / f"seg_{segment:06d}.bin"

    def append(self, rows: np.ndarray) -> None:
        """Append rows durably (fsync) to the shards."""
        offset = 0
        while offset < len(rows):
            segment, row_in_segment = divmod(self.state.total_rows - self.state.base_row, self.segment_rows)
            take = min(len(rows) - offset, self.segment_rows - row_in_segment)
            data = rows[offset:offset + take].tobytes()
            path = self._path(segment)
            created = not path.exists()
            with open(path, "ab") as handle:
                # A killed run may have left bytes past the checkpointed rows: write where they end.
                handle.truncate(row_in_segment * self.dtype.itemsize)
                handle.write(data)
                handle.flush()
                os.fsync(handle.fileno())
            if created:
                fsync_dir(self.directory)
            self.state.crc[segment] = zlib.crc32(data, self.state.crc.get(segment, 0))
            self.state.total_rows += take
            offset += take

    def read(self, state: ReplayStoreState, capacity: int) -> np.ndarray:
        """The last min(total_rows, capacity) rows a checkpoint's `state` names, checked against
        its checksums; changes nothing on disk. Raises ReplayCorrupt on damage."""
        base = state.base_row
        first_needed_row = max(base, state.total_rows - capacity)
        first_segment = (first_needed_row - base) // self.segment_rows
        stored = state.total_rows - base
        last_segment = (stored - 1) // self.segment_rows if stored else -1
        chunks: list[np.ndarray] = []
        for segment in range(first_segment, last_segment + 1):
            rows_in_segment = min(self.segment_rows, stored - segment * self.segment_rows)
            data = self._read_prefix(segment, rows_in_segment)
            expected = state.crc.get(segment)
            if expected is None or zlib.crc32(data) != expected:
                raise ReplayCorrupt(f"replay shard {self._path(segment)} does not match its checksum")
            chunks.append(np.frombuffer(data, dtype=self.dtype))
        rows = np.concatenate(chunks) if chunks else np.zeros(0, dtype=self.dtype)
        skip = first_needed_row - base - first_segment * self.segment_rows
        return rows[skip:].copy()

    def restore(self, state: ReplayStoreState, capacity: int) -> np.ndarray:
        """Check the shards against a checkpoint's `state`, cut off rows written after it, and
        return its last min(total_rows, capacity) rows. Raises ReplayCorrupt on damage."""
        rows = self.read(state, capacity)
        stored = state.total_rows - state.base_row
        last_segment = (stored - 1) // self.segment_rows if stored else -1
        # Verified: now drop what came after the checkpoint.
        for segment in range(last_segment + 1, last_segment + 1_000_000):
            path = self._path(segment)
            if not path.exists():
                break
            path.unlink()
        if last_segment >= 0:
            size = (stored - last_segment * self.segment_rows) * self.dtype.itemsize
            with open(self._path(last_segment), "r+b") as handle:
                handle.truncate(size)
                os.fsync(handle.fileno())
        fsync_dir(self.directory)
        self.state = ReplayStoreState(state.total_rows, dict(state.crc), state.base_row)
        return rows

    def discard(self, state: ReplayStoreState) -> np.ndarray:
        """Give up the shards on disk (after damage): delete them and continue at the row count
        of `state` with an empty replay; returns the (no) rows to restore."""
        for path in self.directory.glob("seg_*.bin"):
            path.unlink()
        fsync_dir(self.directory)
        self.state = ReplayStoreState(state.total_rows, {}, state.total_rows)
        return np.zeros(0, dtype=self.dtype)

    def _read_prefix(self, segment: int, rows: int) -> bytes:
        path = self._path(segment)
        want = rows * self.dtype.itemsize
        try:
            with open(path, "rb") as handle:
                data = handle.read(want)
        except FileNotFoundError:
            raise ReplayCorrupt(f"replay shard {path} is missing") from None
        if len(data) != want:
            raise ReplayCorrupt(f"replay shard {path} is truncated ({len(data)} of {want} bytes)")
        return data

    def prune(self, keep_from_row: int) -> None:
        """Delete shards holding only rows before `keep_from_row` (no kept checkpoint needs them)."""
        last_dead = (keep_from_row - self.state.base_row) // self.segment_rows - 1
        for segment in sorted(self.state.crc):
            if segment > last_dead:
                break
            self._path(segment).unlink(missing_ok=True)
            del self.state.crc[segment]
