"""Training heartbeat: a small JSON file in the run directory that a watchdog reads.

Written atomically after every training episode and after every episode of an evaluation or of
the constant-action baseline (cheap: one small file), naming the phase, so a watchdog that sees
no new heartbeat for T seconds knows the learner/simulator is frozen, not busy evaluating.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any

from sitl_bridge.rl.common.atomic import atomic_write_json

HEARTBEAT_FILE = "heartbeat.json"
TRAINING = "training"
"""The phase of a heartbeat written between training episodes."""


def write_heartbeat(run_dir: str | Path, episode: int, global_step: int, phase: str = TRAINING) -> None:
    """Record that training is alive at `episode`, doing `phase` (`training`, or e.g.
    `evaluation 3/100`); `global_step` (environment steps) is the simulated-time counter,
    `wall_time` and `pid` tell a watchdog who beat and when."""
    atomic_write_json(Path(run_dir) / HEARTBEAT_FILE, {
        "episode": episode, "global_step": global_step, "phase": phase, "wall_time": time.time(),
        "pid": os.getpid()})


def read_heartbeat(run_dir: str | Path) -> dict[str, Any] | None:
    """The last heartbeat, or None when there is none (yet) or it cannot be read."""
    try:
        value = json.loads((Path(run_dir) / HEARTBEAT_FILE).read_text())
    except (OSError, ValueError):
        return None
    return value if isinstance(value, dict) else None
