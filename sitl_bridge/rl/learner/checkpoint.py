"""Checkpoint files: one safetensors file per saved episode, written atomically, self-checking.

A checkpoint is a standard safetensors file (`checkpoints/ckpt_0000042.safetensors` = state after
42 finished episodes). Tensors hold the weights (and other binary state such as the optimizer's
`torch.save` bytes, read back with `weights_only=True`); the safetensors metadata holds a JSON
`state` (counters, RNG states, ...) and a SHA-256 over the state and every tensor, so a damaged or
truncated file is detected instead of silently loaded. No pickle anywhere.
"""

from __future__ import annotations

import hashlib
import json
import logging
import struct
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import safetensors.torch
import torch

from sitl_bridge.rl.common.atomic import atomic_write_bytes, fsync_dir
from sitl_bridge.rl.learner.policy_file import (
    POLICY_FILE,
    PolicyFileError,
    is_policy_file,
    read_policy,
)

FORMAT = "sitl_bridge.checkpoint/1"
CHECKPOINT_DIR = "checkpoints"
BEST_CHECKPOINT = "best.safetensors"
"""In a run directory: a copy of the checkpoint whose greedy evaluation scored best (the run's
result; `best.json` beside it says when and how well)."""
log = logging.getLogger(__name__)
T = TypeVar("T")


class CheckpointError(RuntimeError):
    """No usable checkpoint (the message says where and why)."""


class CheckpointCorrupt(CheckpointError):
    """A checkpoint file is damaged, truncated or not a checkpoint."""


class CheckpointNotRestorable(CheckpointError):
    """A sound checkpoint that cannot be resumed from as it is (e.g. the episode log it covers
    was damaged since): the previous one is tried, and this one is left in place."""


def checkpoint_path(directory: str | Path, episode: int) -> Path:
    """Where the checkpoint taken after `episode` finished episodes lives."""
    return Path(directory) / f"ckpt_{episode:07d}.safetensors"


def _digest(tensors: dict[str, torch.Tensor], state_json: str) -> str:
    sha = hashlib.sha256(state_json.encode())
    for name in sorted(tensors):
        tensor = tensors[name].detach().cpu().contiguous()
        sha.update(f"{name}|{tensor.dtype}|{tuple(tensor.shape)}|".encode())
        sha.update(tensor.view(-1).view(torch.uint8).numpy().tobytes() if tensor.numel() else b"")
    return sha.hexdigest()


def save_checkpoint(path: str | Path, tensors: dict[str, torch.Tensor], state: dict[str, Any]) -> None:
    """Write tensors + JSON state to `path` atomically (temp file, fsync, rename)."""
    tensors = {k: v.detach().cpu().contiguous().clone() for k, v in tensors.items()}
    state_json = json.dumps(state, sort_keys=True)
    metadata = {"format": FORMAT, "state": state_json, "sha256": _digest(tensors, state_json)}
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, safetensors.torch.save(tensors, metadata=metadata))


def _read_metadata(data: bytes) -> dict[str, str]:
    if len(data) < 8:
        raise CheckpointCorrupt("file is shorter than a safetensors header")
    (header_len,) = struct.unpack("<Q", data[:8])
    if header_len > len(data) - 8:
        raise CheckpointCorrupt("file is truncated (header runs past the end)")
    try:
        header = json.loads(data[8:8 + header_len])
    except ValueError:
        raise CheckpointCorrupt("header is not valid JSON") from None
    metadata = header.get("__metadata__") or {}
    if metadata.get("format") != FORMAT:
        raise CheckpointCorrupt(f"not a sitl-bridge checkpoint (format {metadata.get('format')!r})")
    return metadata


def _check_length(data: bytes) -> None:
    """Truncation shows as tensor data ending past the end of the file."""
    (header_len,) = struct.unpack("<Q", data[:8])
    header = json.loads(data[8:8 + header_len])
    end = max((v["data_offsets"][1] for k, v in header.items() if k != "__metadata__"), default=0)
    if 8 + header_len + end != len(data):
        raise CheckpointCorrupt(f"file is truncated ({len(data)} of {8 + header_len + end} bytes)")


def load_checkpoint(path: str | Path) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Read and verify a checkpoint; raises CheckpointCorrupt naming the problem."""
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise CheckpointCorrupt(f"{path}: cannot read ({exc.strerror})") from None
    try:
        metadata = _read_metadata(data)
        _check_length(data)
        tensors = safetensors.torch.load(data)
    except CheckpointCorrupt as exc:
        raise CheckpointCorrupt(f"{path}: {exc}") from None
    except Exception as exc:  # safetensors raises its own error types for damaged files
        raise CheckpointCorrupt(f"{path}: unreadable safetensors data ({exc})") from None
    if _digest(tensors, metadata["state"]) != metadata.get("sha256"):
        raise CheckpointCorrupt(f"{path}: checksum mismatch (file damaged)")
    return tensors, json.loads(metadata["state"])


def read_state(path: str | Path) -> dict[str, Any]:
    """The JSON state of a checkpoint from its header alone (no tensors read, no checksum)."""
    with open(path, "rb") as handle:
        head = handle.read(8)
        if len(head) < 8:
            raise CheckpointCorrupt(f"{path}: file is shorter than a safetensors header")
        (header_len,) = struct.unpack("<Q", head)
        data = head + handle.read(min(header_len, 1 << 26))
    try:
        return json.loads(_read_metadata(data)["state"])
    except CheckpointCorrupt as exc:
        raise CheckpointCorrupt(f"{path}: {exc}") from None


def list_checkpoints(directory: str | Path) -> list[Path]:
    """Checkpoint files in `directory`, newest (most episodes) first."""
    return sorted(Path(directory).glob("ckpt_*.safetensors"), reverse=True)


def quarantine(path: Path) -> Path:
    """Rename a bad checkpoint to `*.corrupt` so it is never picked again (kept for inspection)."""
    target = path.with_name(path.name + ".corrupt")
    path.replace(target)
    fsync_dir(path.parent)
    return target


def restore_newest(directory: str | Path,
                   restore: Callable[[Path, dict[str, torch.Tensor], dict[str, Any]], T],
                   warn: Callable[[str], None] = log.warning) -> T:
    """Call `restore` with the newest checkpoint that loads and restores without error; damaged
    ones (CheckpointCorrupt, or any error type `restore` raises as CheckpointCorrupt) are
    reported through `warn`, quarantined, and the previous one is tried."""
    candidates = list_checkpoints(directory)
    if not candidates:
        raise CheckpointError(f"{directory}: no checkpoint found")
    problems: list[str] = []
    for path in candidates:
        try:
            tensors, state = load_checkpoint(path)
            return restore(path, tensors, state)
        except CheckpointNotRestorable as exc:
            problems.append(str(exc))
            warn(f"checkpoint {path.name} cannot be resumed from: {exc}; trying the previous checkpoint")
        except CheckpointCorrupt as exc:
            problems.append(str(exc))
            moved = quarantine(path)
            warn(f"checkpoint {path.name} is unusable: {exc}; moved to {moved.name}, "
                 "falling back to the previous checkpoint")
    raise CheckpointError(f"{directory}: no usable checkpoint ({'; '.join(problems)})")


def best_checkpoint(run_dir: str | Path) -> Path:
    """The run's best checkpoint (`best.safetensors`) when the trainer kept one, else the run
    directory itself (its policy export or newest valid checkpoint, as `resolve_checkpoint` reads it)."""
    best = Path(run_dir) / BEST_CHECKPOINT
    return best if best.is_file() else Path(run_dir)


def load_network_file(path: str | Path) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """A training checkpoint or a policy file (`rl/learner/policy_file.py`), verified; a policy file's
    tensors carry the `online.` prefix and its state says `policy_only`."""
    if is_policy_file(path):
        try:
            return read_policy(path)
        except PolicyFileError as exc:
            raise CheckpointCorrupt(str(exc)) from None
    return load_checkpoint(path)


def resolve_checkpoint(path: str | Path, *, latest: bool = False) -> tuple[Path, dict[str, torch.Tensor], dict[str, Any]]:
    """The network behind a checkpoint file, a policy file, or a run directory. A run directory
    gives its best greedy network (`best.safetensors`, a checkpoint or its policy-only
    replacement, else the policy export `policy.safetensors`) when `latest` is False, else (or
    when it has neither) the newest valid checkpoint of the run (or of a `checkpoints/` folder);
    a slimmed run with no checkpoint left gives its policy export even with `latest`. Loaded and
    verified; read-only: nothing is quarantined."""
    return open_checkpoint(path, lambda file, tensors, state: (file, tensors, state), latest=latest)


def open_checkpoint(path: str | Path, use: Callable[[Path, dict[str, torch.Tensor], dict[str, Any]], T], *,
                    latest: bool = False) -> T:
    """`use(file, tensors, state)` of the network `resolve_checkpoint` picks; when that one is
    unusable (damaged, or `use` raises CheckpointCorrupt: its content does not fit), of the next
    one in the same order (best, policy export, then newest to oldest checkpoint). A file given
    by name has no fallback: its problem is the CheckpointError. Read-only: nothing is
    quarantined."""
    path = Path(path)
    if path.is_file():
        return use(path, *load_network_file(path))
    candidates = [] if latest else [path / BEST_CHECKPOINT, path / POLICY_FILE]
    candidates = [c for c in candidates if c.is_file()]
    folder = path / CHECKPOINT_DIR if (path / CHECKPOINT_DIR).is_dir() else path
    if not folder.is_dir():
        raise CheckpointError(f"{path}: neither a checkpoint or policy file nor a run directory")
    problems: list[str] = []
    for candidate in [*candidates, *list_checkpoints(folder)]:
        try:
            return use(candidate, *load_network_file(candidate))
        except CheckpointCorrupt as exc:
            problems.append(str(exc))
            log.warning("skipping unusable checkpoint: %s", exc)
    if latest and (path / POLICY_FILE).is_file():
        try:
            return use(path / POLICY_FILE, *load_network_file(path / POLICY_FILE))
        except CheckpointCorrupt as exc:
            problems.append(str(exc))
    raise CheckpointError(f"{path}: no usable checkpoint" + (f" ({'; '.join(problems)})" if problems else ""))
