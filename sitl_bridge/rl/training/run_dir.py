"""Run directories: `{world}__{experiment}__{seed}__{timestamp}` holding everything of one run.

    run.json            what the run is: world file, autopilot, seed, init-from, and its provenance
                        (creation time, package version, git commit, command line, platform)
    scenario.yaml       a copy of the scenario file the run trains in: the run's own world, used by
                        resume, eval, rules, plot and `run --policy` from any working directory
    config.yaml         the resolved hyperparameters (TrainConfig)
    episodes.jsonl      the episode log (one record per drone per episode)
    checkpoints/        ckpt_0000042.safetensors ... (newest few kept); best.safetensors: a copy
                        of the one whose greedy evaluation was the best (best.json says which)
    replay/             append-only replay shards + format.json
    tb/                 TensorBoard events
    eval.json           the latest greedy evaluation (evals.jsonl: all of them, during training too)
    baseline.json       the best constant-action policy's greedy success (what "solved" must beat)
"""

from __future__ import annotations

import json
import platform
import shlex
import shutil
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import yaml

from sitl_bridge.errors import ConfigError, Node
from sitl_bridge.rl.common.atomic import atomic_write_json, atomic_write_text
from sitl_bridge.rl.learner.config import TrainConfig, parse_train_node

RUN_FILE = "run.json"
SCENARIO_FILE = "scenario.yaml"
CONFIG_FILE = "config.yaml"
EPISODES_FILE = "episodes.jsonl"
CHECKPOINTS = "checkpoints"
REPLAY = "replay"
TENSORBOARD = "tb"
EVAL_FILE = "eval.json"
EVALS_FILE = "evals.jsonl"
BASELINE_FILE = "baseline.json"
BEST_FILE = "best.json"
"""The best greedy evaluation so far and the checkpoint it scored (`checkpoint.BEST_CHECKPOINT`)."""


@dataclass(frozen=True)
class RunSpec:
    """What a run trains on; fixed for the run's whole life (resumes included)."""

    world: str
    """Scenario file the run trains in."""
    autopilot: str = "direct"
    seed: int = 0
    init_from: str | None = None
    standby: bool = False
    """Envs with a standby autopilot (`EnvOptions.standby`, px4): speed only, same episodes."""
    """Checkpoint the network started from (curriculum), if any."""
    created: str = ""
    """Creation time, ISO 8601 UTC."""
    version: str = ""
    """sitl-bridge version that created the run."""
    git_commit: str | None = None
    """Commit of the sitl-bridge source tree, when it is a git checkout (`+dirty` if modified)."""
    command: str = ""
    """The full command line that created the run."""
    platform: str = ""
    """Python, torch and operating system."""

    def with_provenance(self) -> RunSpec:
        """This spec with creation time, version, commit, command line and platform filled in."""
        import torch

        from sitl_bridge import __version__

        return RunSpec(**{**asdict(self),
                          "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                          "version": __version__, "git_commit": source_commit(),
                          "command": shlex.join(sys.argv),
                          "platform": f"python {platform.python_version()}, torch {torch.__version__}, "
                                      f"{platform.platform()}"})


def source_commit() -> str | None:
    """Git commit of the package's source tree, or None (installed copy, no git)."""
    import sitl_bridge  # the package's own folder, wherever this module sits inside it

    root = Path(sitl_bridge.__file__).resolve().parents[1]
    if not (root / ".git").exists():
        return None
    try:
        head = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True,
                              text=True, timeout=10, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=10, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return head + ("+dirty" if dirty else "")


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
    try:
        if Path(spec.world).is_file():  # (a run of an env built in code names no file)
            atomic_write_text(path / SCENARIO_FILE, Path(spec.world).read_text(encoding="utf-8"))
        write_run_files(path, spec.with_provenance(), config)
    except BaseException:
        shutil.rmtree(path, ignore_errors=True)  # a failed start leaves no run directory
        raise
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
    known = {f.name for f in fields(RunSpec)}
    spec = RunSpec(**{k: v for k, v in json.loads((path / RUN_FILE).read_text()).items() if k in known})
    source = str(path / CONFIG_FILE)
    config = parse_train_node(Node(yaml.safe_load((path / CONFIG_FILE).read_text()), source, "train"))
    return spec, config


RESUME_MAY_CHANGE = frozenset({"episodes"})
"""Config keys a resume may change (`train --resume --episodes N` extends the budget)."""


def config_differences(checkpoint_config: Any, config: TrainConfig) -> list[str]:
    """`key (checkpoint's value -> config.yaml's)` for each hyperparameter of a checkpoint's
    recorded config that the run's config.yaml now gives another value (keys a resume may
    change, and keys the checkpoint's version did not have, aside)."""
    if not isinstance(checkpoint_config, dict):
        return []
    current = json.loads(json.dumps(config.to_dict()))  # as the checkpoint's JSON holds it
    return [f"{key} ({checkpoint_config[key]!r} -> {current[key]!r})" for key in current
            if key in checkpoint_config and key not in RESUME_MAY_CHANGE and checkpoint_config[key] != current[key]]


def run_dir_of(path: str | Path) -> Path | None:
    """The run directory holding `path` (a run directory, its checkpoints folder or a checkpoint
    file in it), or None when `path` is not inside one."""
    path = Path(path)
    for candidate in (path, path.parent, path.parent.parent):
        if (candidate / RUN_FILE).is_file():
            return candidate
    return None


def run_scenario(path: str | Path) -> Path:
    """The scenario file of the run holding `path`: its own copy (`scenario.yaml`), or, for runs
    made before copies were kept, the world file it names (which must still exist)."""
    run_dir = run_dir_of(path)
    if run_dir is None:
        raise ConfigError(f"{path}: not inside a run directory (no {RUN_FILE}); pass --world")
    if (run_dir / SCENARIO_FILE).is_file():
        return run_dir / SCENARIO_FILE
    spec, _ = read_run_files(run_dir)
    world = Path(spec.world)
    if not world.is_file():
        raise ConfigError(f"{run_dir}: has no {SCENARIO_FILE} and its world {spec.world} is not "
                          "readable from here; pass --world")
    return world
