"""Run directories: `{world}__{experiment}__{seed}__{timestamp}` holding everything of one run.

    run.json            what the run is: world file, autopilot, seed, init-from (written once)
    config.yaml         the resolved hyperparameters (TrainConfig)
    episodes.jsonl      the episode log (one record per drone per episode)
    checkpoints/        ckpt_0000042.safetensors ... (newest few kept)
    replay/             append-only replay shards + format.json
    tb/                 TensorBoard events
    eval.json           the latest greedy evaluation (evals.jsonl: all of them, during training too)
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import yaml

from sitl_bridge.errors import ConfigError, Node
from sitl_bridge.rl.atomic import atomic_write_json, atomic_write_text
from sitl_bridge.rl.config import TrainConfig, parse_train_node

RUN_FILE = "run.json"
CONFIG_FILE = "config.yaml"
EPISODES_FILE = "episodes.jsonl"
CHECKPOINTS = "checkpoints"
REPLAY = "replay"
TENSORBOARD = "tb"
EVAL_FILE = "eval.json"
EVALS_FILE = "evals.jsonl"


@dataclass(frozen=True)
class RunSpec:
    """What a run trains on; fixed for the run's whole life (resumes included)."""

    world: str
    """Scenario file the run trains in."""
    autopilot: str = "direct"
    seed: int = 0
    init_from: str | None = None
    """Checkpoint the network started from (curriculum), if any."""
    created: str = ""


def run_dir_name(world: str | Path, experiment: str, seed: int, timestamp: float | None = None) -> str:
    """`{world}__{experiment}__{seed}__{timestamp}` (UTC, sortable)."""
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime(timestamp if timestamp is not None else time.time()))
    return f"{Path(world).stem}__{experiment}__{seed}__{stamp}"


def create_run_dir(out: str | Path, spec: RunSpec, config: TrainConfig) -> Path:
    """A new, empty run directory with run.json and config.yaml written."""
    base = Path(out) / run_dir_name(spec.world, config.experiment, spec.seed)
    path, suffix = base, 1
    while path.exists():  # two runs started in the same second
        path = base.with_name(f"{base.name}-{suffix}")
        suffix += 1
    path.mkdir(parents=True)
    write_run_files(path, spec, config)
    return path


def write_run_files(path: Path, spec: RunSpec, config: TrainConfig) -> None:
    """(Re)write run.json and config.yaml atomically."""
    atomic_write_json(path / RUN_FILE, asdict(spec))
    atomic_write_text(path / CONFIG_FILE, yaml.safe_dump(config.to_dict(), sort_keys=False))


def read_run_files(path: str | Path) -> tuple[RunSpec, TrainConfig]:
    """The spec and resolved config of an existing run directory."""
    path = Path(path)
    if not (path / RUN_FILE).is_file():
        raise ConfigError(f"{path}: not a run directory (no {RUN_FILE})")
    spec = RunSpec(**json.loads((path / RUN_FILE).read_text()))
    source = str(path / CONFIG_FILE)
    config = parse_train_node(Node(yaml.safe_load((path / CONFIG_FILE).read_text()), source, "train"))
    return spec, config
