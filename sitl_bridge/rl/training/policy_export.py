"""Exporting a run's best network as a policy file, and slimming a run down to what its report needs.

`export_policy` writes the policy-only file (`rl/learner/policy_file.py`) and verifies it twice before it
counts: the bytes read back from disk must pass the file's own checks, and the network rebuilt
from them must give exactly the checkpoint's Q values on the probe observations. Only then does
`slim_run` remove the training checkpoints, `best.safetensors` and the replay (what a resume
needs, not what evaluation, rules, pictures or the report need).
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from sitl_bridge.rl.common.atomic import fsync_dir
from sitl_bridge.rl.learner.checkpoint import (
    BEST_CHECKPOINT,
    CHECKPOINT_DIR,
    CheckpointError,
    resolve_checkpoint,
)
from sitl_bridge.rl.learner.policy_file import (
    POLICY_FILE,
    PolicyFileError,
    build_network,
    online_tensors,
    policy_bytes,
    probe_q_values,
    read_policy,
)
from sitl_bridge.rl.training.run_dir import REPLAY


@dataclass(frozen=True)
class Export:
    """What `export_policy` wrote."""

    path: Path
    source: Path
    """The checkpoint (or policy file) the network came from."""
    episode: int
    bytes: int


def export_policy(source: str | Path, out: str | Path | None = None) -> Export:
    """Write the network of `source` (a run directory: its best network; a checkpoint or policy
    file) as a policy file at `out` (default: `policy.safetensors` in the run directory, or beside
    the file). `out` may be the checkpoint itself: it is replaced only after its replacement,
    written under a temporary name, is verified."""
    file, state, network, reference, data = policy_export_bytes(source)
    source = Path(source)
    target = Path(out) if out is not None else (source if source.is_dir() else file.parent) / POLICY_FILE
    temporary = target.with_name(f".{target.name}.export{os.getpid()}")
    try:
        with open(temporary, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        check_export(temporary, network, reference)
        os.replace(temporary, target)
    finally:
        temporary.unlink(missing_ok=True)
    fsync_dir(target.parent)
    check_export(target, network, reference)
    return Export(target, file, int(state.get("episode", 0)), len(data))


def policy_export_bytes(source: str | Path) -> tuple[Path, dict[str, Any], dict[str, torch.Tensor], torch.Tensor, bytes]:
    """The policy file's bytes for the network of `source` (nothing written), with the file it
    came from, its state, its tensors and its Q values on the probe observations."""
    file, tensors, state = resolve_checkpoint(source)
    network = online_tensors(tensors)
    reference = probe_q_values(build_network(state["network"], network))
    data = policy_bytes(network, state["network"], episode=int(state.get("episode", 0)),
                        exported_from=file.name, probe_q=reference)
    return file, state, network, reference, data


def check_export(path: Path, network: dict[str, torch.Tensor], reference: torch.Tensor) -> None:
    """Raise PolicyFileError unless the policy file at `path` reads back (its own checks) as
    exactly `network`, and its rebuilt network gives exactly `reference` on the probes."""
    tensors, state = read_policy(path)
    read = online_tensors(tensors)
    if read.keys() != network.keys() or any(not torch.equal(read[k], network[k]) for k in network):
        raise PolicyFileError(f"{path}: the written network differs from the checkpoint's")
    if not torch.equal(probe_q_values(build_network(state["network"], read)), reference):
        raise PolicyFileError(f"{path}: the written network's Q values differ from the checkpoint's")


def slim_run(run_dir: str | Path) -> tuple[Export, int]:
    """Export the run's best network (verified), then remove its training checkpoints,
    `best.safetensors` and replay. Returns the export and the bytes removed."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise CheckpointError(f"{run_dir}: not a run directory")
    export = export_policy(run_dir)  # raises before anything is removed
    removed = 0
    for name in (CHECKPOINT_DIR, REPLAY, BEST_CHECKPOINT):
        path = run_dir / name
        if path.is_dir():
            removed += sum(f.stat().st_size for f in path.rglob("*") if f.is_file())
            shutil.rmtree(path)
        elif path.is_file():
            removed += path.stat().st_size
            path.unlink()
    fsync_dir(run_dir)
    return export, removed
