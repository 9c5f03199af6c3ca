"""Caches of the report step's own flights (behaviour, rules, trees, pictures): a result is kept
in a JSON file beside what it was made from and reused while its key (the best networks' digests,
the settings, the code's version) is the same, so rebuilding RESULTS.md after training one more
part of an experiment only flies the scenarios whose runs changed."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

from sitl_bridge.rl.common.atomic import atomic_write_text

CACHE_FORMAT = 1
"""Bumped when what the cached sections hold changes."""


def checkpoint_digest(run_dir: str | Path) -> str:
    """sha256 of the network a run's greedy policy flies (its best, else its newest): of its
    tensors and shape, not of the file, so a run whose checkpoint was replaced by its policy-only
    export (`rl/training/policy_export.py`) keeps its cached results."""
    from sitl_bridge.rl.learner.checkpoint import resolve_checkpoint
    from sitl_bridge.rl.learner.policy_file import network_digest, online_tensors

    _, tensors, state = resolve_checkpoint(run_dir)
    return network_digest(online_tensors(tensors), state["network"])


def world_digest(path: str | Path) -> str:
    """sha256 of a scenario file's parsed content (its YAML data as canonical JSON): a comment or
    layout edit keeps the report's cached flights, a changed value flies them again."""
    from sitl_bridge.errors import load_yaml

    data = load_yaml(path).value
    return hashlib.sha256(json.dumps(data, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def cache_key(**parts: Any) -> dict[str, Any]:
    """`parts` plus the package version and the cache format (a new version recomputes)."""
    from sitl_bridge import __version__

    return {"format": CACHE_FORMAT, "version": __version__, **parts}


def load(path: str | Path, key: dict[str, Any]) -> Any | None:
    """The cached value at `path` when it was stored under `key`, else None."""
    path = Path(path)
    if not path.is_file():
        return None
    try:
        cached = json.loads(path.read_text())
    except ValueError:
        return None
    # compare through JSON: tuples in `key` come back as lists
    if not isinstance(cached, dict) or cached.get("key") != json.loads(json.dumps(key)):
        return None
    return cached.get("value")


def store(path: str | Path, key: dict[str, Any], value: Any) -> None:
    """Keep `value` (JSON) at `path` under `key`, its mappings in their order (a report lists
    scenarios and shares in the order they were made)."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps({"key": key, "value": value}, indent=1, allow_nan=False) + "\n")
