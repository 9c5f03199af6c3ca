"""Starting a run from another run's network (`train --init-from`, curricula): the checks that
the network fits, and `--transfer-replay`'s adoption of the source run's transitions."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from sitl_bridge.rl.learner import checkpoint as ckpt
from sitl_bridge.rl.learner.config import TrainConfig
from sitl_bridge.rl.learner.policy_file import network_algorithm
from sitl_bridge.rl.learner.replay_buffer import ReplayBuffer
from sitl_bridge.rl.learner.replay_store import ReplayCorrupt, ReplayStore, ReplayStoreState
from sitl_bridge.rl.training import run_dir as rd

log = logging.getLogger(__name__)


class ShapeMismatch(ValueError):
    """A network cannot be transferred: its input/output sizes differ from the scenario's."""


def check_same_algorithm(path: Path, state: dict[str, Any], algorithm: str) -> None:
    """ShapeMismatch when the network a run starts from (`--init-from`) was trained by another
    algorithm than the run's."""
    source = network_algorithm(state["network"])
    if source != algorithm:
        raise ShapeMismatch(f"--init-from {path}: holds a {source} network, but this run trains {algorithm} "
                            "(start from a run of the same algorithm)")


def adopt_architecture(config: TrainConfig, network: dict[str, int]) -> TrainConfig:
    """A transferred network keeps its depth and width, whatever this scenario's config says."""
    if (config.layers, config.hidden_units) != (network["layers"], network["hidden_units"]):
        log.warning("init-from network has %d layers x %d units; using that instead of %d x %d",
                    network["layers"], network["hidden_units"], config.layers, config.hidden_units)
        config = config.replace(layers=network["layers"], hidden_units=network["hidden_units"])
    return config


def adopt_replay(init_path: Path, replay: ReplayBuffer, store: ReplayStore, capacity: int) -> None:
    """Start the replay with the transitions of the run `init_path` belongs to (written to
    this run's own shards, so checkpoints and resumes cover them like any other rows)."""
    source = next((d for d in (init_path, *init_path.parents) if (d / rd.RUN_FILE).is_file()), None)
    if source is None:
        raise ckpt.CheckpointError(f"--transfer-replay: {init_path} is not inside a run directory")
    try:
        source_store = ReplayStore.open_existing(source / rd.REPLAY)
        if source_store.dtype != store.dtype:
            raise ShapeMismatch(f"--transfer-replay: {source}'s replay rows do not fit this run's")
        _, _, state = ckpt.resolve_checkpoint(source, latest=True)
        rows = source_store.read(ReplayStoreState.from_json(state["replay"]), capacity)
    except ReplayCorrupt as exc:
        raise ckpt.CheckpointError(f"--transfer-replay: {exc} (committed results keep no replay: "
                                   "train the source run here, or leave --transfer-replay off)") from None
    replay.add_rows(rows)
    store.append(rows)
    log.info("started the replay with %d transitions of %s", len(rows), source)
